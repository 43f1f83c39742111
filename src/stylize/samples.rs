//! The rays a stylization's losses draw from and their frozen sample lists:
//! the training views (cached up to a memory budget, marched when not
//! held), the reference views, the registered pixels of R³, and the device
//! copies of those lists when they are kept there (`samples_on_device`).
//! Density never changes during a stylization, so a list marched once
//! stays right for the whole run.

use std::borrow::Cow;

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::field::frozen::{self, DeviceSamples, FrozenSamples};
use crate::field::grid::{CellLattice, RadianceGrid};
use crate::field::march::{BlockOccupancy, MarchParams, Marcher};
use crate::reference::registration::RegistrationFile;
use crate::scene::camera::{Camera, NdcParams, Ray, to_ndc};
use crate::scene::data::Dataset;
use crate::stylize::config::{Placement, StylizeConfig};
use crate::stylize::{Method, SampleCacheReport};
use crate::util::tensor::is_host_memory;

/// One group of L_ref's pseudo-rays: rays of `lists` (repeats allowed)
/// and their target colours; `on_device`, a device copy of `lists` to
/// gather them from.
pub(crate) struct PseudoRays<'s> {
    pub lists: Cow<'s, FrozenSamples>,
    pub on_device: Option<&'s DeviceSamples>,
    pub rays: Vec<usize>,
    pub target: Vec<f32>,
}

impl PseudoRays<'_> {
    /// Each ray's cells (whose corners are the step's rows).
    pub fn cells(&self) -> impl Iterator<Item = &[u32]> {
        self.rays.iter().map(move |&r| self.lists.ray_cells(r))
    }
}

/// The sample lists of a stylization's rays, and the pseudo-rays of
/// L_ref (the references' pixels and R³'s registered pixels).
pub(crate) struct SampleCache<'a> {
    dataset: &'a Dataset,
    ndc: Option<NdcParams>,
    march: MarchParams,
    min_sample_weight: f32,
    /// Empty-space skipping for every march (the density and rows are frozen).
    occupancy: BlockOccupancy,
    /// Cached sample lists of the training views (None = re-marched when needed).
    views: Vec<Option<FrozenSamples>>,
    /// Whether `cache` has run (it runs once, before the refit or, in a
    /// resumed run, before the guidance).
    cached: bool,
    /// Where each training view's pixels start among all training pixels
    /// (views one after another), and their total last.
    view_first_pixel: Vec<usize>,
    /// Device copies of the cached views' lists (`samples_on_device`).
    views_on_device: Vec<Option<DeviceSamples>>,
    /// Sample lists of the reference views, one after another; reference
    /// `r`'s rays start at `reference_first_ray[r]`.
    reference_lists: FrozenSamples,
    reference_first_ray: Vec<usize>,
    /// (reference, pixel) of every reference pixel L_ref uses: those that
    /// see the scene, or all of them (`loss.reference_misses`).
    reference_pixels: Vec<(usize, usize)>,
    pub registration: RegistrationFile,
    /// All registered pixels: (view, pixel, colour).
    pub registered: Vec<(u32, u32, [f32; 3])>,
    /// Sample lists of the registered pixels, in that order (None = re-marched when picked).
    registered_samples: Option<FrozenSamples>,
    /// Device copies of `reference_lists` and `registered_samples`, when
    /// the pseudo-rays are gathered there (`samples_on_device`).
    reference_on_device: Option<DeviceSamples>,
    registered_on_device: Option<DeviceSamples>,
}

impl<'a> SampleCache<'a> {
    /// The reference views' lists, marched now; the training views' and
    /// the registered pixels' wait for [`cache`](Self::cache).
    pub fn new(
        grid: &RadianceGrid,
        dataset: &'a Dataset,
        ndc: Option<NdcParams>,
        march: MarchParams,
        cfg: &StylizeConfig,
        registration: RegistrationFile,
    ) -> Self {
        let misses = cfg.loss.reference_misses;
        let reference_pixels = registration
            .references
            .iter()
            .enumerate()
            .flat_map(|(r, p)| p.hits.iter().enumerate().filter(move |(_, h)| **h || misses).map(move |(i, _)| (r, i)))
            .collect();
        let mut cache = SampleCache {
            dataset,
            ndc,
            march,
            min_sample_weight: cfg.min_sample_weight,
            occupancy: BlockOccupancy::with_density(grid),
            views: vec![None; dataset.train.len()],
            cached: false,
            view_first_pixel: std::iter::once(0)
                .chain(dataset.train.iter().scan(0, |end, v| {
                    *end += v.camera.intrinsics.width as usize * v.camera.intrinsics.height as usize;
                    Some(*end)
                }))
                .collect(),
            views_on_device: vec![None; dataset.train.len()],
            reference_lists: FrozenSamples::default(),
            reference_first_ray: vec![0],
            reference_pixels,
            registered: registration.registered_pixels(),
            registration,
            registered_samples: None,
            reference_on_device: None,
            registered_on_device: None,
        };
        for r in 0..cache.registration.references.len() {
            let samples = cache.march_camera(grid, &cache.registration.references[r].camera);
            cache.reference_lists.append(&samples);
            cache.reference_first_ray.push(cache.reference_lists.num_rays);
        }
        cache
    }

    /// How the stylized field is marched.
    pub fn march(&self) -> MarchParams {
        self.march
    }

    /// The forward-facing warp of the rays (None around a scene).
    pub fn ndc(&self) -> Option<NdcParams> {
        self.ndc
    }

    /// Frees every cached list (the cache is being replaced).
    pub fn release(&mut self) {
        self.views.iter_mut().for_each(|v| *v = None);
        self.views_on_device.iter_mut().for_each(|v| *v = None);
        (self.registered_samples, self.registered_on_device, self.reference_on_device) = (None, None, None);
        self.reference_lists = FrozenSamples::default();
    }

    pub fn num_references(&self) -> usize {
        self.reference_first_ray.len() - 1
    }

    /// The transmittance each reference pixel's ray leaves, every
    /// reference's pixels one after another (the lists' own march).
    pub fn reference_transmittance(&self) -> &[f32] {
        &self.reference_lists.final_transmittance
    }

    /// The sample lists of reference `r`.
    pub fn reference_samples(&self, r: usize) -> FrozenSamples {
        let first = self.reference_first_ray[r];
        self.reference_lists.range(first, self.reference_first_ray[r + 1] - first)
    }

    /// Training view `v`'s lists: the cached ones, or marched now.
    pub fn view(&self, grid: &RadianceGrid, v: usize) -> Cow<'_, FrozenSamples> {
        match &self.views[v] {
            Some(s) => Cow::Borrowed(s),
            None => Cow::Owned(self.march_camera(grid, &self.dataset.train[v].camera)),
        }
    }

    /// The device copy of training view `v`'s lists, when kept there.
    pub fn view_on_device(&self, v: usize) -> Option<&DeviceSamples> {
        self.views_on_device[v].as_ref()
    }

    /// Which training view and pixel the `i`-th of `Dataset::pixel_rays`
    /// of the training views is (views one after another).
    fn view_pixel(&self, i: usize) -> (usize, usize) {
        let v = self.view_first_pixel.partition_point(|&first| first <= i) - 1;
        (v, i - self.view_first_pixel[v])
    }

    /// The ray through pixel `p` of training view `v` (NDC-warped for forward-facing scenes).
    fn pixel_ray(&self, v: usize, p: usize) -> Ray {
        let camera = &self.dataset.train[v].camera;
        let w = camera.intrinsics.width as usize;
        let r = camera.ray((p % w) as f32, (p / w) as f32);
        match &self.ndc {
            Some(n) => to_ndc(r, n),
            None => r,
        }
    }

    /// The samples of `rays` (on the frozen density's block occupancy, built
    /// once per run), or None as soon as they would hold more than `budget` bytes.
    fn march_rays_within(&self, grid: &RadianceGrid, rays: &[Ray], budget: usize) -> Option<FrozenSamples> {
        let marcher = Marcher::with_occupancy(grid, &self.occupancy);
        FrozenSamples::march_within(&marcher, rays, &self.march, self.min_sample_weight, frozen::MARCH_CHUNK, budget)
    }

    fn march_rays(&self, grid: &RadianceGrid, rays: &[Ray]) -> FrozenSamples {
        self.march_rays_within(grid, rays, usize::MAX).expect("an unbounded march always fits")
    }

    pub fn march_camera(&self, grid: &RadianceGrid, camera: &Camera) -> FrozenSamples {
        self.march_rays(grid, &camera.rays(self.ndc.as_ref()))
    }

    /// Caches the views' sample lists up to the configured memory (a view
    /// the cache does not hold is marched in its step). On the host that is
    /// all: a registered pixel's ray is its view's, so L_ref's pseudo-rays
    /// copy their lists from the cached views (`registered_lists`) and
    /// march only those of views not held.
    ///
    /// Lists kept on the device (`samples_on_device`) also keep the
    /// registered pixels' lists as a set of their own (the device gathers
    /// a step's pseudo-rays from one set), cached before or after the
    /// views, whichever saves the more marching per byte: first when a
    /// step draws a larger share of them (`registered_rays` of all) than
    /// of the views (one of all). Lego: 50,000 of about a million
    /// registered pixels against one view of 100, first; fern: 50,000 of
    /// 1.9 million against one of 17, after.
    pub fn cache(
        &mut self,
        grid: &RadianceGrid,
        cfg: &StylizeConfig,
        method: Method,
        device: &burn::tensor::Device,
        budget_mb: usize,
    ) {
        if std::mem::replace(&mut self.cached, true) {
            return;
        }
        // Each march gives up as soon as it would overrun what is left of the
        // budget, so memory never holds more than the budget plus one chunk.
        let budget = budget_mb * 1024 * 1024;
        let mut used = 0usize;
        let on_device = match cfg.samples_on_device {
            Placement::Auto => !is_host_memory(device),
            Placement::Device => true,
            Placement::Host => false,
        };
        let wants_registered = on_device && method == Method::RefNpr && !self.registered.is_empty();
        let views = self.dataset.train.len();
        let registered_share = cfg.loss.registered_rays as f64 / self.registered.len().max(1) as f64;
        let registered_first = registered_share >= 1.0 / views.max(1) as f64;
        if wants_registered && registered_first {
            self.cache_registered(grid, budget, &mut used);
        }
        for v in 0..views {
            let rays = self.dataset.train[v].camera.rays(self.ndc.as_ref());
            let samples = self.march_rays_within(grid, &rays, budget - used);
            used += samples.as_ref().map_or(0, FrozenSamples::bytes);
            self.views[v] = samples;
        }
        if wants_registered && !registered_first {
            self.cache_registered(grid, budget, &mut used);
        }
        if on_device {
            let upload = |s: &FrozenSamples| DeviceSamples::upload(s, device);
            self.views_on_device = self.views.iter().map(|s| s.as_ref().map(upload)).collect();
            if method == Method::RefNpr {
                self.reference_on_device = Some(upload(&self.reference_lists));
                self.registered_on_device = self.registered_samples.as_ref().map(upload);
            }
        }
    }

    /// Every list's far colours read again from `grid`'s far map (after
    /// the stylization changed it), the device copies uploaded again.
    pub fn refresh_far(&mut self, grid: &RadianceGrid, device: &burn::tensor::Device) {
        let ndc = self.ndc;
        let reference_rays: Vec<Ray> =
            self.registration.references.iter().flat_map(|r| r.camera.rays(ndc.as_ref())).collect();
        self.reference_lists.refresh_far(grid, &reference_rays);
        for (v, lists) in self.views.iter_mut().enumerate() {
            if let Some(lists) = lists {
                lists.refresh_far(grid, &self.dataset.train[v].camera.rays(ndc.as_ref()));
            }
        }
        if let Some(mut lists) = self.registered_samples.take() {
            let rays: Vec<Ray> = self.registered.iter().map(|p| self.pixel_ray(p.0 as usize, p.1 as usize)).collect();
            lists.refresh_far(grid, &rays);
            self.registered_samples = Some(lists);
        }
        let upload = |s: &FrozenSamples| DeviceSamples::upload(s, device);
        for (copy, lists) in self.views_on_device.iter_mut().zip(&self.views) {
            if copy.is_some() {
                *copy = lists.as_ref().map(upload);
            }
        }
        if self.reference_on_device.is_some() {
            self.reference_on_device = Some(upload(&self.reference_lists));
        }
        if self.registered_on_device.is_some() {
            self.registered_on_device = self.registered_samples.as_ref().map(upload);
        }
    }

    /// Caches the registered pixels' sample lists when they fit in what is
    /// left of `budget` (`used` bytes taken).
    fn cache_registered(&mut self, grid: &RadianceGrid, budget: usize, used: &mut usize) {
        let rays: Vec<Ray> = self.registered.iter().map(|p| self.pixel_ray(p.0 as usize, p.1 as usize)).collect();
        self.registered_samples = self.march_rays_within(grid, &rays, budget - *used);
        *used += self.registered_samples.as_ref().map_or(0, FrozenSamples::bytes);
    }

    /// What the cache holds (after `cache`).
    pub fn report(&self, budget_mb: usize) -> SampleCacheReport {
        let cached: Vec<&FrozenSamples> = self.views.iter().flatten().chain(self.registered_samples.as_ref()).collect();
        SampleCacheReport {
            budget_mb,
            views_cached: self.views.iter().flatten().count(),
            views: self.views.len(),
            registered_cached: self.registered_samples.is_some(),
            mb: cached.iter().map(|s| s.bytes()).sum::<usize>() as f64 / (1024.0 * 1024.0),
            samples: cached.iter().map(|s| s.num_samples()).sum(),
            cells: cached.iter().map(|s| s.num_cells()).sum(),
        }
    }

    /// The references' sample lists' bytes a ray (marched when the cache
    /// is made: the memory budget sizes the views' lists from them).
    pub fn reference_list_bytes_per_ray(&self) -> f64 {
        self.reference_lists.bytes() as f64 / self.reference_lists.num_rays.max(1) as f64
    }

    /// Bytes of the host sample lists held: the cached training views, the
    /// registered pixels' and the references' (device copies not counted).
    pub fn lists_bytes(&self) -> usize {
        let views: usize = self.views.iter().flatten().map(FrozenSamples::bytes).sum();
        views + self.registered_samples.as_ref().map_or(0, FrozenSamples::bytes) + self.reference_lists.bytes()
    }

    /// Bytes of what R³ carried: the registration (reference pixels, each
    /// view's registered pixels), the flat list of registered pixels and
    /// the reference pixels L_ref uses.
    pub fn registration_bytes(&self) -> usize {
        let file = &self.registration;
        let references: usize = file.references.iter().map(|r| r.colours.len() * 12 + r.hits.len()).sum();
        let views: usize = file.views.iter().map(|v| v.registration.pixels.len() * (4 + 12 + 2)).sum();
        references + views + self.registered.len() * 20 + self.reference_pixels.len() * 16
    }

    /// Keeps only the reference pixels `keep(reference, pixel)` accepts for
    /// L_ref (a local edit's regions).
    pub fn keep_reference_pixels(&mut self, keep: impl Fn(usize, usize) -> bool) {
        self.reference_pixels.retain(|&(r, i)| keep(r, i));
    }

    /// A step's pseudo-rays for L_ref: a batch of reference pixels and a
    /// batch of registered pixels, each with its target colours (none when
    /// L_ref is off).
    pub fn pseudo_ray_batch(
        &self,
        grid: &RadianceGrid,
        cfg: &StylizeConfig,
        rng: &mut ChaCha8Rng,
    ) -> Vec<PseudoRays<'_>> {
        let l = &cfg.loss;
        if !cfg.ablation.use_reference_loss || l.reference <= 0.0 {
            return Vec::new();
        }
        let mut groups = Vec::new();
        // Reference pixels (those that see the scene, or all: `reference_misses`),
        // ordered by reference.
        let pixels = &self.reference_pixels;
        if !pixels.is_empty() {
            let picks: Vec<(usize, usize)> = if l.reference_rays >= pixels.len() {
                pixels.clone()
            } else {
                (0..l.reference_rays).map(|_| pixels[rng.random_range(0..pixels.len())]).collect()
            };
            let mut rays = Vec::with_capacity(picks.len());
            let mut target = Vec::with_capacity(picks.len() * 3);
            for r in 0..self.num_references() {
                for &(_, i) in picks.iter().filter(|p| p.0 == r) {
                    rays.push(self.reference_first_ray[r] + i);
                    target.extend(self.registration.references[r].colours[i]);
                }
            }
            groups.push(PseudoRays {
                lists: Cow::Borrowed(&self.reference_lists),
                on_device: self.reference_on_device.as_ref(),
                rays,
                target,
            });
        }
        if !cfg.ablation.reference_rays_only && !self.registered.is_empty() && l.registered_rays > 0 {
            let picks: Vec<usize> =
                (0..l.registered_rays).map(|_| rng.random_range(0..self.registered.len())).collect();
            let target = picks.iter().flat_map(|&i| self.registered[i].2).collect();
            groups.push(match &self.registered_samples {
                Some(cached) => PseudoRays {
                    lists: Cow::Borrowed(cached),
                    on_device: self.registered_on_device.as_ref(),
                    rays: picks,
                    target,
                },
                None => {
                    let lists = self.registered_lists(grid, &picks);
                    let rays = (0..lists.num_rays).collect();
                    PseudoRays { lists: Cow::Owned(lists), on_device: None, rays, target }
                }
            });
        }
        groups
    }

    /// The sample lists of the registered pixels `picks`, in that order.
    fn registered_lists(&self, grid: &RadianceGrid, picks: &[usize]) -> FrozenSamples {
        let pixels: Vec<(usize, usize)> =
            picks.iter().map(|&i| (self.registered[i].0 as usize, self.registered[i].1 as usize)).collect();
        self.pixel_lists(grid, &pixels)
    }

    /// The sample lists of the `i`-th training pixels (views one after
    /// another), in that order.
    pub fn training_pixel_lists(&self, grid: &RadianceGrid, picks: &[usize]) -> FrozenSamples {
        let pixels: Vec<(usize, usize)> = picks.iter().map(|&i| self.view_pixel(i)).collect();
        self.pixel_lists(grid, &pixels)
    }

    /// The sample lists of training pixels `(view, pixel)`, in that order:
    /// copied from the view's cached lists (the very samples a march of the
    /// pixel's ray gives: the view's lists are of the same rays), marched
    /// only for views the cache does not hold.
    fn pixel_lists(&self, grid: &RadianceGrid, pixels: &[(usize, usize)]) -> FrozenSamples {
        let uncached: Vec<Ray> =
            pixels.iter().filter(|&&(v, _)| self.views[v].is_none()).map(|&(v, p)| self.pixel_ray(v, p)).collect();
        let marched = self.march_rays(grid, &uncached);
        // Where each pixel's lists are: its view's ray, or the next marched one.
        let mut next_marched = 0;
        let sources: Vec<(&FrozenSamples, usize)> = pixels
            .iter()
            .map(|&(v, p)| match &self.views[v] {
                Some(view) => (view, p),
                None => {
                    next_marched += 1;
                    (&marched, next_marched - 1)
                }
            })
            .collect();
        // Copied in parallel pieces (random reads across the views' lists),
        // appended in order: the same lists as one serial copy.
        let (lattice, corners) = (CellLattice::of(grid), self.march.colour_corners);
        let pieces: Vec<FrozenSamples> = sources
            .par_chunks(2048)
            .map(|part| {
                let mut piece = FrozenSamples::empty(lattice.clone(), corners);
                for &(from, r) in part {
                    piece.push_ray_of(from, r);
                }
                piece
            })
            .collect();
        let mut lists = FrozenSamples::empty(lattice, corners);
        for piece in &pieces {
            lists.append(piece);
        }
        lists
    }
}
