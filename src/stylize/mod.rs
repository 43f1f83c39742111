//! Ref-NPR stylization (paper sections 3.3-3.4) and the ARF baseline.
//!
//! From a photoreal run and a reference case to a stylized grid:
//! 1. R³ registers the reference(s) on the training views (`registration`);
//! 2. the colour is cut to SH degree 0 and refit to the photos for a few
//!    "ray epochs", density frozen;
//! 3. content views I are rendered once from that field; VGG16 features of
//!    every view and of the references are computed once; TCM matches and the
//!    colour-loss targets are kept per view;
//! 4. "image epochs": one whole training view per step with deferred
//!    back-propagation (full render without autodiff, image-space gradient
//!    of L_feat + L_color + image TV through VGG, then chunked re-render with
//!    autodiff injecting that gradient), plus L_ref on a batch of R³
//!    pseudo-rays and SH total variation, one RMSprop step per view;
//! 5. the last quarter of the epochs is the smooth content update: the
//!    stylized field becomes the content generator, L_feat at 0.2, λ' = 0,
//!    no colour loss.
//!
//! Density never changes, so every sample list and weight is computed once
//! in plain Rust (`frozen`); the differentiable part is only colour.

pub mod config;
pub mod frozen;
pub mod losses;
pub mod tcm;

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::tensor::{Device, IndexingUpdateOp, Tensor};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::backend::BackendKind;
use crate::camera::{Camera, Ray, to_ndc};
use crate::checkpoint;
use crate::colour_transfer::{ColourStats, ColourTransfer};
use crate::data::Dataset;
use crate::grid::{RadianceGrid, available_memory_bytes};
use crate::reference::{self, ReferenceCase};
use crate::registration::{RegistrationFile, register_case};
use crate::render::{BlockOccupancy, Marcher};
use crate::tensor_util::{assign_rows, floats, indices, scalar, select_rows};
use crate::train::{RowSubset, peak_rss_mb, progress_bar};
use crate::vgg::{Vgg16, VggLayer};
use config::StylizeConfig;
use frozen::FrozenSamples;
use tcm::{ColourTargets, FEATURE_BLOCKS, Image, RELU3, ReferencePair, Template};

/// A pixel within this of the background colour in every channel is background
/// (for the colour-transfer statistics).
const BACKGROUND_TOLERANCE: f32 = 0.01;

/// Whether a photo pixel has the background colour (within `BACKGROUND_TOLERANCE`).
fn is_background(c: &[f32; 3], background: [f32; 3]) -> bool {
    c.iter().zip(background).all(|(a, b)| (a - b).abs() <= BACKGROUND_TOLERANCE)
}

/// Which stylization.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Ref-NPR: R³ + TCM + colour matching.
    RefNpr,
    /// ARF: nearest-neighbour feature matching to a style image.
    Arf,
}

impl FromStr for Method {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "refnpr" | "ref-npr" => Ok(Method::RefNpr),
            "arf" => Ok(Method::Arf),
            o => bail!("unknown method '{o}': expected refnpr or arf"),
        }
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Method::RefNpr => "refnpr",
            Method::Arf => "arf",
        })
    }
}

/// What `refnpr stylize` is asked to do.
pub struct StylizeJob {
    pub photo: PathBuf,
    pub case: PathBuf,
    pub out: PathBuf,
    pub config: StylizeConfig,
    pub method: Method,
    pub backend: BackendKind,
    /// ARF: a style image other than the case's first reference.
    pub style: Option<PathBuf>,
    /// The photo run's dataset folder, when it moved.
    pub data: Option<PathBuf>,
    /// Render the test views of the result into `out/test`.
    pub render_test: bool,
}

/// One logged optimisation step.
#[derive(Debug, Clone, Serialize)]
pub struct CurvePoint {
    pub phase: &'static str,
    pub step: usize,
    pub total: f32,
    /// L_ref (refit: the photo MSE).
    pub reference: f32,
    /// L_feat (ARF: NNFM).
    pub feature: f32,
    pub colour: f32,
    pub content: f32,
    pub image_tv: f32,
}

/// `STYLE_RUN/stylize.json`.
#[derive(Debug, Clone, Serialize)]
pub struct StylizeReport {
    pub method: Method,
    pub backend: String,
    pub photo: PathBuf,
    pub case: PathBuf,
    pub config: StylizeConfig,
    pub views: usize,
    pub image_size: [usize; 2],
    pub registered_pixels: usize,
    pub registered_fraction: f32,
    pub colour_matched_fraction: f32,
    /// ARF: the affine recolouring applied to the photos before the refit.
    pub colour_transfer: Option<ColourTransfer>,
    /// Seconds per phase: registration, refit, content (renders, features, TCM), image_epochs, smooth_update.
    pub seconds: std::collections::BTreeMap<String, f64>,
    pub total_seconds: f64,
    pub peak_rss_mb: Option<f64>,
    pub final_losses: Option<CurvePoint>,
    pub curve: Vec<CurvePoint>,
    pub warnings: Vec<String>,
}

/// The grid being stylized: SH degree 0, density frozen, RMSprop state.
pub struct StyleField {
    pub grid: RadianceGrid,
    rms: Tensor<2>,
    /// Per row, its +x / +y / +z neighbour row (itself when empty): SH TV.
    neighbours: [Vec<i32>; 3],
}

impl StyleField {
    /// Cuts a photoreal grid to view-independent colour (the DC band).
    pub fn new(mut grid: RadianceGrid) -> Self {
        grid.truncate_sh(0);
        let rows = grid.num_rows();
        let geo = grid.geometry;
        let neighbours = std::array::from_fn(|axis| {
            grid.coords
                .iter()
                .enumerate()
                .map(|(row, &c)| {
                    let mut ijk = geo.unflat(c as usize);
                    ijk[axis] += 1;
                    let nb = if ijk[axis] < geo.res[axis] { grid.links[geo.flat(ijk[0], ijk[1], ijk[2])] } else { -1 };
                    if nb < 0 { row as i32 } else { nb }
                })
                .collect()
        });
        let rms = Tensor::zeros([rows, 3], &grid.device());
        Self { grid, rms, neighbours }
    }

    pub fn reset_optimiser(&mut self) {
        self.rms = Tensor::zeros([self.grid.num_rows(), 3], &self.grid.device());
    }

    /// Dense RMSprop step on the SH rows (density untouched).
    pub fn rmsprop(&mut self, grad: Tensor<2>, lr: f32, beta: f32, eps: f32) {
        let device = self.grid.device();
        let rms = std::mem::replace(&mut self.rms, Tensor::zeros([1, 1], &device));
        self.rms = rms * beta + grad.clone() * grad.clone() * (1.0 - beta);
        let sh = std::mem::replace(&mut self.grid.sh, Tensor::zeros([1, 1], &device));
        self.grid.sh = sh - grad / (self.rms.clone().sqrt() + eps) * lr;
    }

    /// `into` plus the gradient of `weight` x the SH total variation over a
    /// random `fraction` of the rows (mean over those rows of sqrt(sum of
    /// squared differences to the +x/+y/+z neighbours)). Adding into the
    /// caller's gradient saves a grid-sized buffer and a grid-sized sum per step.
    pub fn add_tv_gradient(&self, into: Tensor<2>, weight: f32, fraction: f32, rng: &mut ChaCha8Rng) -> Tensor<2> {
        let n = self.grid.num_rows();
        if weight <= 0.0 || n == 0 {
            return into;
        }
        let count = ((n as f32 * fraction).ceil() as usize).clamp(1, n);
        let core: Vec<i32> = (0..count).map(|_| rng.random_range(0..n) as i32).collect();
        // Leaf = the rows involved (the picked rows and their neighbours), local indices.
        let lists: Vec<Vec<i32>> = std::iter::once(core.clone()).chain(self.neighbours.iter().map(|nb| core.iter().map(|&r| nb[r as usize]).collect())).collect();
        let subset = RowSubset::of(n, &lists.concat());
        let device = self.grid.device();
        let rows = indices(subset.rows().to_vec(), &device);
        let leaf = select_rows(self.grid.sh.clone(), rows.clone()).autodiff().require_grad();
        let mut lists = lists.into_iter().map(|l| select_rows(leaf.clone(), indices(l.iter().map(|&r| subset.local(r)).collect(), &device)));
        let centre = lists.next().expect("the picked rows");
        let sq = lists.map(|nb| (nb - centre.clone()).powi_scalar(2)).reduce(|a, b| a + b).expect("three axes");
        let tv = (sq.sum_dim(1) + 1e-9).sqrt().sum() * (weight / count as f32);
        match leaf.grad(&tv.backward()) {
            Some(g) => assign_rows(into, rows, g, IndexingUpdateOp::Add),
            None => into,
        }
    }
}

/// d/d(sh) of the sum over ray chunks of `loss_of(rendered chunk, first ray, rays)`:
/// each chunk is rendered with autodiff and back-propagated on its own, so
/// memory is bounded by the chunk (the second half of deferred back-propagation).
/// The autodiff leaf of a chunk is only the rows its samples touch (a grid
/// has millions of rows, a chunk touches a few percent of them); their
/// gradients are added into one full-size buffer.
pub fn chunked_gradient(sh: &Tensor<2>, samples: &FrozenSamples, background: [f32; 3], chunk: usize, loss_of: &dyn Fn(Tensor<2>, usize, usize) -> Tensor<1>) -> Tensor<2> {
    let device = sh.device();
    let mut total = Tensor::zeros(sh.dims(), &device);
    let mut subset = RowSubset::default();
    let mut start = 0;
    while start < samples.num_rays {
        let len = chunk.max(1).min(samples.num_rays - start);
        let mut part = samples.range(start, len);
        subset.reset_to(sh.dims()[0], &part.corner_rows);
        for r in part.corner_rows.iter_mut() {
            *r = subset.local(*r);
        }
        let ft = part.upload(&device);
        let rows = indices(subset.rows().to_vec(), &device);
        let leaf = select_rows(sh.clone(), rows.clone()).autodiff().require_grad();
        let rgb = frozen::render_colour(leaf.clone(), &ft, background);
        let loss = loss_of(rgb, start, len);
        // A chunk whose rays all miss the scene renders the background: no graph, no gradient.
        if loss.is_tracked()
            && let Some(g) = leaf.grad(&loss.backward())
        {
            total = assign_rows(total, rows, g, IndexingUpdateOp::Add);
        }
        start += len;
    }
    total
}

/// The interleaved `[pixels, 3]` gradient of an image loss (planar `[1, 3, H, W]` gradient in).
fn interleaved(grad: Tensor<4>) -> Tensor<2> {
    let [_, c, h, w] = grad.dims();
    grad.reshape([c, h * w]).transpose()
}

/// Per-view data kept for the image epochs.
struct ViewGuide {
    /// Raw content features per block (for λ'; empty when unused).
    content: Vec<Tensor<2>>,
    /// TCM matches per block (Ref-NPR).
    matches: Vec<Tensor<1, burn::tensor::Int>>,
    colour: Option<ColourTargets>,
}

/// Loss values of one image step.
#[derive(Default, Clone, Copy)]
struct ImageLosses {
    total: f32,
    feature: f32,
    colour: f32,
    content: f32,
    image_tv: f32,
}

/// The stylization run.
struct Stylizer<'a> {
    job: &'a StylizeJob,
    cfg: &'a StylizeConfig,
    dataset: &'a Dataset,
    ndc: Option<crate::camera::NdcParams>,
    background: [f32; 3],
    march: crate::render::MarchParams,
    field: StyleField,
    /// Empty-space skipping for every march (the density and rows are frozen).
    occupancy: BlockOccupancy,
    vgg: Vgg16,
    ad: Device,
    device: Device,
    /// Cached sample lists of the training views (None = re-marched when needed).
    view_samples: Vec<Option<FrozenSamples>>,
    /// Sample lists of the reference views.
    reference_samples: Vec<FrozenSamples>,
    /// (reference, pixel) of every reference pixel that sees the scene.
    reference_hits: Vec<(usize, usize)>,
    registration: RegistrationFile,
    /// All registered pixels: (view, pixel, colour).
    registered: Vec<(u32, u32, [f32; 3])>,
    /// Sample lists of the registered pixels, in that order (None = re-marched when picked).
    registered_samples: Option<FrozenSamples>,
    /// ARF: the photos are recoloured with this before the refit.
    colour_transfer: Option<ColourTransfer>,
    curve: Vec<CurvePoint>,
    warnings: Vec<String>,
}

impl Stylizer<'_> {
    fn view_samples(&self, v: usize) -> std::borrow::Cow<'_, FrozenSamples> {
        match &self.view_samples[v] {
            Some(s) => std::borrow::Cow::Borrowed(s),
            None => std::borrow::Cow::Owned(self.march_camera(&self.dataset.train[v].camera)),
        }
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
    fn march_rays_within(&self, rays: &[Ray], budget: usize) -> Option<FrozenSamples> {
        let marcher = Marcher::with_occupancy(&self.field.grid, &self.occupancy);
        FrozenSamples::march_within(&marcher, rays, &self.march, self.cfg.min_sample_weight, frozen::MARCH_CHUNK, budget)
    }

    fn march_rays(&self, rays: &[Ray]) -> FrozenSamples {
        self.march_rays_within(rays, usize::MAX).expect("an unbounded march always fits")
    }

    fn march_camera(&self, camera: &Camera) -> FrozenSamples {
        self.march_rays(&camera.rays(self.ndc.as_ref()))
    }

    fn render_view(&self, v: usize) -> Image {
        let cam = &self.dataset.train[v].camera;
        let rgb = frozen::render_plain(&self.field.grid.sh, &self.view_samples(v), self.background, self.cfg.render_chunk);
        Image { width: cam.intrinsics.width as usize, height: cam.intrinsics.height as usize, rgb }
    }

    fn render_reference(&self, r: usize) -> Image {
        let cam = &self.registration.references[r].camera;
        let rgb = frozen::render_plain(&self.field.grid.sh, &self.reference_samples[r], self.background, self.cfg.render_chunk);
        Image { width: cam.intrinsics.width as usize, height: cam.intrinsics.height as usize, rgb }
    }

    fn log(&mut self, p: CurvePoint) {
        self.curve.push(p);
    }

    /// Ray epochs: refit the degree-0 colour to the photos (MSE, SH TV);
    /// ARF: to the recoloured photos.
    fn refit(&mut self) -> Result<()> {
        let (rays, mut colours) = crate::train::training_rays(&self.dataset.train, self.dataset);
        if let Some(tf) = &self.colour_transfer {
            // Background pixels stay: rays that miss the scene render the
            // fixed background colour, and a recoloured target there could
            // never be fitted (lego: 70 % of the pixels).
            colours.iter_mut().filter(|c| !is_background(c, self.background)).for_each(|c| *c = tf.apply(*c));
        }
        let s = &self.cfg.schedule;
        let steps = (s.ray_epochs as f64 * rays.len() as f64 / s.ray_batch as f64).ceil() as usize;
        let bar = progress_bar(steps as u64, 0);
        self.field.reset_optimiser();
        for step in 0..steps {
            let mut rng = ChaCha8Rng::seed_from_u64(self.cfg.seed ^ 0x5EF1 ^ (step as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            let picks: Vec<usize> = (0..s.ray_batch).map(|_| rng.random_range(0..rays.len())).collect();
            let batch_rays: Vec<Ray> = picks.iter().map(|&i| rays[i]).collect();
            let target = floats(picks.iter().flat_map(|&i| colours[i]).collect(), [picks.len(), 3], &self.device);
            let samples = self.march_rays(&batch_rays);
            let (grad, mse) = self.mse_gradient(&samples, target, 1.0);
            let grad = self.with_tv(grad, &mut rng);
            self.field.rmsprop(grad, s.lr_refit, s.rmsprop_beta, s.eps);
            bar.set_position(step as u64 + 1);
            bar.set_message(format!("refit mse {mse:.5} psnr {:.2}", crate::metrics::psnr_from_mse(mse)));
            if bar.is_hidden() && (step + 1) % (steps / 10).max(1) == 0 {
                eprintln!("refit {}/{steps} mse {mse:.5}", step + 1);
            }
            self.log(CurvePoint { phase: "refit", step, total: mse, reference: mse, feature: 0.0, colour: 0.0, content: 0.0, image_tv: 0.0 });
        }
        bar.finish_and_clear();
        Ok(())
    }

    /// `weight` x the mean squared error of the rays' colours to `target`
    /// (`[rays, 3]`): its SH gradient and its value.
    fn mse_gradient(&self, samples: &FrozenSamples, target: Tensor<2>, weight: f32) -> (Tensor<2>, f32) {
        let scale = weight / (3.0 * samples.num_rays.max(1) as f32);
        let value = std::cell::Cell::new(0.0f32);
        let grad = chunked_gradient(&self.field.grid.sh, samples, self.background, self.cfg.render_chunk, &|rgb, start, len| {
            let d = rgb - target.clone().narrow(0, start, len);
            let loss = (d.clone() * d).sum() * scale;
            value.set(value.get() + scalar(loss.clone().inner()));
            loss
        });
        (grad, value.get())
    }

    fn with_tv(&self, grad: Tensor<2>, rng: &mut ChaCha8Rng) -> Tensor<2> {
        self.field.add_tv_gradient(grad, self.cfg.loss.tv_sh, self.cfg.loss.tv_fraction, rng)
    }

    /// Caches sample lists up to the configured memory: first the
    /// registered pixels (a batch of them is rendered every step), then the views.
    fn cache_samples(&mut self) {
        // Each march gives up as soon as it would overrun what is left of the
        // budget, so memory never holds more than the budget plus one chunk.
        let budget = self.cfg.sample_cache_mb * 1024 * 1024;
        let mut used = 0usize;
        if self.job.method == Method::RefNpr && !self.registered.is_empty() {
            let rays: Vec<Ray> = self.registered.iter().map(|p| self.pixel_ray(p.0 as usize, p.1 as usize)).collect();
            self.registered_samples = self.march_rays_within(&rays, budget);
            used += self.registered_samples.as_ref().map_or(0, FrozenSamples::bytes);
        }
        for v in 0..self.dataset.train.len() {
            let samples = self.march_rays_within(&self.dataset.train[v].camera.rays(self.ndc.as_ref()), budget - used);
            used += samples.as_ref().map_or(0, FrozenSamples::bytes);
            self.view_samples[v] = samples;
        }
    }

    /// The pseudo-ray loss's gradient (λ_r times the mean squared error of
    /// a batch of reference pixels plus that of a batch of registered pixels).
    fn reference_gradient(&self, rng: &mut ChaCha8Rng) -> (Option<Tensor<2>>, f32) {
        let l = &self.cfg.loss;
        if !self.cfg.ablation.use_reference_loss || l.reference <= 0.0 {
            return (None, 0.0);
        }
        let mut groups: Vec<(FrozenSamples, Vec<f32>)> = Vec::new();
        // Reference pixels that see the scene.
        let mut samples = FrozenSamples::default();
        let mut target = Vec::new();
        let hits = &self.reference_hits;
        if !hits.is_empty() {
            let picks: Vec<(usize, usize)> =
                if l.reference_rays >= hits.len() { hits.clone() } else { (0..l.reference_rays).map(|_| hits[rng.random_range(0..hits.len())]).collect() };
            for r in 0..self.reference_samples.len() {
                let ids: Vec<usize> = picks.iter().filter(|p| p.0 == r).map(|p| p.1).collect();
                samples.append(&self.reference_samples[r].subset(&ids));
                target.extend(ids.iter().flat_map(|&i| self.registration.references[r].colours[i]));
            }
            groups.push((samples, target));
        }
        if !self.cfg.ablation.reference_rays_only && !self.registered.is_empty() && l.registered_rays > 0 {
            let picks: Vec<usize> = (0..l.registered_rays).map(|_| rng.random_range(0..self.registered.len())).collect();
            let samples = match &self.registered_samples {
                Some(cached) => cached.subset(&picks),
                None => {
                    let rays: Vec<Ray> = picks.iter().map(|&i| self.pixel_ray(self.registered[i].0 as usize, self.registered[i].1 as usize)).collect();
                    self.march_rays(&rays)
                }
            };
            groups.push((samples, picks.iter().flat_map(|&i| self.registered[i].2).collect()));
        }
        let mut total: Option<Tensor<2>> = None;
        let mut value = 0.0;
        for (samples, target) in groups {
            let target = floats(target, [samples.num_rays, 3], &self.device);
            let (g, v) = self.mse_gradient(&samples, target, l.reference);
            value += v;
            total = Some(match total {
                None => g,
                Some(t) => t + g,
            });
        }
        (total, value)
    }

    /// Deferred back-propagation of the image losses of view `v`: the
    /// gradient with respect to the SH rows, and the loss values.
    fn image_gradient(&self, v: usize, guide: &ViewGuide, template: Option<&Template>, style_bank: Option<&Tensor<2>>, smooth: bool) -> Result<(Tensor<2>, ImageLosses)> {
        let samples = self.view_samples(v);
        let cam = &self.dataset.train[v].camera;
        let (w, h) = (cam.intrinsics.width as usize, cam.intrinsics.height as usize);
        // 1. Full image, no autodiff.
        let rgb = frozen::render_plain(&self.field.grid.sh, &samples, self.background, self.cfg.render_chunk);
        // 2. Image losses on a leaf image, gradient with respect to the image.
        let image = crate::vgg::image_tensor(&rgb, w, h, &self.ad).require_grad();
        let (loss, parts) = self.image_loss(image.clone(), guide, template, style_bank, smooth)?;
        let grads = loss.backward();
        let Some(g) = image.grad(&grads) else { bail!("the image losses do not depend on the image") };
        let g = interleaved(g);
        // 3. Chunked re-render with autodiff, injecting the image gradient.
        let grad = chunked_gradient(&self.field.grid.sh, &samples, self.background, self.cfg.render_chunk, &|rgb, start, len| {
            (rgb * g.clone().narrow(0, start, len)).sum()
        });
        Ok((grad, parts))
    }

    fn image_loss(&self, image: Tensor<4>, guide: &ViewGuide, template: Option<&Template>, style_bank: Option<&Tensor<2>>, smooth: bool) -> Result<(Tensor<1>, ImageLosses)> {
        let [_, _, h, w] = image.dims();
        let l = &self.cfg.loss;
        let mut parts = ImageLosses::default();
        let mut total = losses::image_tv(image.clone()) * l.image_tv;
        parts.image_tv = scalar(total.clone().inner()) / l.image_tv.max(1e-12);
        match self.job.method {
            Method::RefNpr => {
                let template = template.expect("Ref-NPR has a template");
                if self.cfg.ablation.use_feature_loss {
                    let maps = self.vgg.features(image.clone(), &VggLayer::TCM)?;
                    let render = tcm::render_blocks(&maps, &FEATURE_BLOCKS, h, w);
                    let (weight, content_weight) = if smooth { (l.smooth_feature, 0.0) } else { (l.feature, l.content) };
                    for (b, r) in render.into_iter().enumerate() {
                        let style = losses::cosine_distance(r.clone(), template.guidance(b, &guide.matches[b]));
                        parts.feature += scalar(style.clone().inner());
                        total = total + style * weight;
                        if content_weight > 0.0 && b < guide.content.len() {
                            let c = losses::content_loss(r, guide.content[b].clone());
                            parts.content += scalar(c.clone().inner());
                            total = total + c * (weight * content_weight);
                        }
                    }
                }
                if let (Some(c), false) = (&guide.colour, smooth) {
                    let loss = losses::colour_loss(losses::patch_means(image, tcm::COLOUR_PATCH), c.target.clone(), c.mask.clone());
                    parts.colour = scalar(loss.clone().inner());
                    total = total + loss * l.colour;
                }
            }
            Method::Arf => {
                let a = &self.cfg.arf;
                let maps = self.vgg.features(image, &RELU3)?;
                let render = tcm::render_blocks(&maps, &[&RELU3], h, w).remove(0);
                let nnfm = losses::nnfm_loss(render.clone(), style_bank.expect("ARF has a style bank").clone(), self.cfg.search_chunk);
                parts.feature = scalar(nnfm.clone().inner());
                total = total + nnfm * a.nnfm;
                if let (true, Some(content)) = (a.content > 0.0, guide.content.first()) {
                    let c = losses::content_loss(render, content.clone());
                    parts.content = scalar(c.clone().inner());
                    total = total + c * a.content;
                }
            }
        }
        parts.total = scalar(total.clone().inner());
        Ok((total, parts))
    }

    /// Content renders, features, TCM matches and colour targets of every view.
    fn guides(&self, template: Option<&Template>, keep_content: bool, colour: bool) -> Result<(Vec<ViewGuide>, f32)> {
        let blocks: Vec<&[VggLayer]> = match self.job.method {
            Method::RefNpr => FEATURE_BLOCKS.to_vec(),
            Method::Arf => vec![&RELU3],
        };
        let n = self.dataset.train.len();
        let bar = progress_bar(n as u64, 0);
        bar.set_message("content features and TCM matches");
        let mut out = Vec::with_capacity(n);
        let mut matched = 0.0;
        for v in 0..n {
            let content = self.render_view(v);
            let (raw, colour_desc) = tcm::image_features(&self.vgg, &content, &self.ad, &blocks, colour)?;
            let matches = template.map(|t| t.matches(&raw, self.cfg.search_chunk)).unwrap_or_default();
            let colour = match (template, colour_desc) {
                (Some(t), Some(d)) => {
                    let c = t.colour_targets(d, &content, self.cfg.loss.colour_max_distance, self.cfg.loss.colour_white, self.cfg.search_chunk);
                    matched += c.matched_fraction / n as f32;
                    Some(c)
                }
                _ => None,
            };
            out.push(ViewGuide { content: if keep_content { raw } else { Vec::new() }, matches, colour });
            bar.inc(1);
        }
        bar.finish_and_clear();
        Ok((out, matched))
    }

    fn template(&self, styles: &[Image]) -> Result<Template> {
        let pairs: Vec<ReferencePair> = styles.iter().enumerate().map(|(r, s)| ReferencePair { content: self.render_reference(r), style: s.clone() }).collect();
        Template::build(&self.vgg, &pairs, &self.ad)
    }
}

/// Bytes the per-view feature caches need (raw content features of the
/// feature blocks, when kept, plus match indices).
fn feature_cache_bytes(method: Method, views: usize, width: usize, height: usize, keep_content: bool) -> u64 {
    let blocks: Vec<&[VggLayer]> = match method {
        Method::RefNpr => FEATURE_BLOCKS.to_vec(),
        Method::Arf => vec![&RELU3],
    };
    let per_view: usize = blocks
        .iter()
        .map(|b| {
            let [h, w] = tcm::block_size(b, height, width);
            let c: usize = b.iter().map(|l| l.channels()).sum();
            h * w * (if keep_content { c * 4 } else { 0 } + 8)
        })
        .sum();
    (per_view * views) as u64
}

/// Warnings about a style image that will not stylize well.
fn style_warnings(path: &Path, rgb: &[f32]) -> Result<Vec<String>> {
    let mut out = Vec::new();
    let img = image::open(path).with_context(|| format!("cannot read style image {}", path.display()))?.to_rgba32f();
    let n = (img.width() * img.height()) as f32;
    let transparent = img.pixels().filter(|p| p.0[3] < 0.5).count() as f32 / n;
    if transparent > 0.5 {
        out.push(format!("style image {} is {:.0}% transparent: those pixels become the background colour", path.display(), transparent * 100.0));
    }
    let mean: [f32; 3] = std::array::from_fn(|c| rgb.iter().skip(c).step_by(3).sum::<f32>() / (rgb.len() / 3) as f32);
    let spread = rgb.chunks_exact(3).map(|p| (0..3).map(|c| (p[c] - mean[c]).abs()).fold(0.0f32, f32::max)).fold(0.0f32, f32::max);
    if spread < 1e-3 {
        out.push(format!("style image {} is a single colour: the stylized scene will be flat", path.display()));
    }
    Ok(out)
}

/// Reads a reference's style image; a different aspect ratio from the view
/// is an error (a case for another scene or resolution).
fn read_reference_style(path: &Path, camera: &Camera, background: [f32; 3]) -> Result<(Vec<f32>, Vec<String>)> {
    let (w, h) = (camera.intrinsics.width, camera.intrinsics.height);
    let (iw, ih) = image::image_dimensions(path).with_context(|| format!("cannot read style image {}", path.display()))?;
    let (a, b) = (iw as f32 / ih as f32, w as f32 / h as f32);
    if (a / b - 1.0).abs() > 0.02 {
        bail!(
            "style image {} is {iw}x{ih} but its reference view is {w}x{h} (another aspect ratio): is the case for another scene or resolution?",
            path.display()
        );
    }
    let (rgb, note) = reference::read_style(path, w, h, background)?;
    let mut warnings: Vec<String> = note.into_iter().collect();
    warnings.extend(style_warnings(path, &rgb)?);
    Ok((rgb, warnings))
}

/// `refnpr stylize`.
pub fn run_stylize(job: &StylizeJob) -> Result<StylizeReport> {
    let started = Instant::now();
    let cfg = &job.config;
    cfg.validate()?;
    let device = job.backend.device();
    let ad = job.backend.autodiff_device();
    let (ck, dataset) = checkpoint::load_run(&job.photo, job.data.as_deref(), &device)?;
    let case = ReferenceCase::load(&job.case)?;
    if let Some(m) = case.scene_mismatch(&dataset) {
        bail!("{m}: the reference case does not belong to the photoreal run {} (fix `scene_name` in the case if it does)", job.photo.display());
    }
    if dataset.train.is_empty() {
        bail!("the photoreal run's dataset {} has no training views", dataset.root.display());
    }
    let cam0 = dataset.train[0].camera.intrinsics;
    let (width, height) = (cam0.width as usize, cam0.height as usize);
    if width < crate::vgg::MIN_SIDE || height < crate::vgg::MIN_SIDE {
        bail!("training views are {width}x{height}: stylization needs at least {0}x{0} (VGG16)", crate::vgg::MIN_SIDE);
    }
    let keep_content = match job.method {
        Method::RefNpr => cfg.loss.content > 0.0 && cfg.ablation.use_feature_loss,
        Method::Arf => cfg.arf.content > 0.0,
    };
    let grid_bytes = ck.grid.num_rows() as u64 * 3 * 4 * 6; // SH, RMSprop state, gradients
    let per_view = feature_cache_bytes(job.method, 1, width, height, keep_content);
    let need = per_view * dataset.train.len() as u64 + grid_bytes;
    if let Some(avail) = available_memory_bytes()
        && need > avail / 4 * 3
    {
        let fit = (avail / 4 * 3).saturating_sub(grid_bytes) / per_view.max(1);
        bail!(
            "stylizing {} views of {width}x{height} needs about {:.1} GB for feature caches and the grid, but {:.1} GB is available \
             (about {fit} views fit): use a lower-resolution photoreal run, or set loss.content = 0 (drops the cached content features)",
            dataset.train.len(),
            need as f64 / 1e9,
            avail as f64 / 1e9
        );
    }
    std::fs::create_dir_all(&job.out).with_context(|| format!("cannot create {}", job.out.display()))?;
    let mut seconds = std::collections::BTreeMap::new();
    let mut warnings = Vec::new();

    // R³ on the photoreal field.
    let t = Instant::now();
    let (registration, reg_report) = register_case(&ck, &dataset, &case, &cfg.register)?;
    warnings.extend(reg_report.warnings.iter().cloned());
    let registered: Vec<(u32, u32, [f32; 3])> = registration
        .views
        .iter()
        .enumerate()
        .flat_map(|(v, r)| r.registration.pixels.iter().zip(&r.registration.colours).map(move |(&p, &c)| (v as u32, p, c)))
        .collect();
    if job.method == Method::RefNpr && registered.is_empty() {
        let msg = "R³ registered no training pixel: L_ref uses the reference view only, the rest comes from TCM".to_string();
        eprintln!("warning: {msg}");
        warnings.push(msg);
    }
    seconds.insert("registration".to_string(), t.elapsed().as_secs_f64());

    // Style images (per reference; ARF: one image).
    let mut styles = Vec::new();
    for (spec, p) in case.references.iter().zip(&registration.references) {
        let (rgb, w) = read_reference_style(&spec.style, &p.camera, ck.meta.background)?;
        for m in &w {
            eprintln!("note: {m}");
        }
        warnings.extend(w);
        styles.push(Image { width: p.camera.intrinsics.width as usize, height: p.camera.intrinsics.height as usize, rgb });
    }
    if let (Method::Arf, Some(path)) = (job.method, &job.style) {
        let img = image::open(path).with_context(|| format!("cannot read style image {}", path.display()))?;
        let (w, h) = (img.width(), img.height());
        let rgb = crate::data::composite_over(&img.to_rgba32f(), ck.meta.background);
        warnings.extend(style_warnings(path, &rgb)?);
        styles = vec![Image { width: w as usize, height: h as usize, rgb }];
    }

    // ARF's colour transfer: photo statistics over the pixels that are not
    // the background colour, style statistics over the reference pixels that
    // see the scene (a style image given with --style: its non-background pixels).
    let colour_transfer = if job.method == Method::Arf && cfg.arf.colour_transfer {
        let background = ck.meta.background;
        let photos = || dataset.train.iter().flat_map(|v| crate::imageio::pixels(&v.rgb));
        // Falls back to every pixel when the mask leaves none.
        let content = ColourStats::of(photos().filter(|c| !is_background(c, background))).or_else(|_| ColourStats::of(photos()))?;
        let style_pixels: Vec<[f32; 3]> = crate::imageio::pixels(&styles[0].rgb).collect();
        let style_mask: Vec<bool> = match (&job.style, registration.references.first()) {
            (None, Some(r)) if r.hits.len() == style_pixels.len() => r.hits.clone(),
            _ => style_pixels.iter().map(|c| !is_background(c, background)).collect(),
        };
        let style = ColourStats::of(style_pixels.iter().zip(&style_mask).filter(|(_, m)| **m).map(|(c, _)| *c)).or_else(|_| ColourStats::of(style_pixels.iter().copied()))?;
        Some(ColourTransfer::between(&content, &style))
    } else {
        None
    };
    if let Some(tf) = &colour_transfer {
        eprintln!("ARF colour transfer: photos recoloured with {:?} + {:?}", tf.matrix, tf.offset);
    }

    let photo_meta = ck.meta.clone();
    let field = StyleField::new(ck.grid);
    let mut st = Stylizer {
        job,
        cfg,
        dataset: &dataset,
        ndc: photo_meta.ndc,
        background: photo_meta.background,
        march: photo_meta.config.march,
        occupancy: BlockOccupancy::of(&field.grid),
        field,
        vgg: Vgg16::load(&ad),
        ad: ad.clone(),
        device: device.clone(),
        view_samples: vec![None; dataset.train.len()],
        reference_samples: Vec::new(),
        reference_hits: registration
            .references
            .iter()
            .enumerate()
            .flat_map(|(r, p)| p.hits.iter().enumerate().filter(|(_, h)| **h).map(move |(i, _)| (r, i)))
            .collect(),
        registration,
        registered,
        registered_samples: None,
        colour_transfer,
        curve: Vec::new(),
        warnings,
    };
    st.reference_samples = st.registration.references.iter().map(|p| st.march_camera(&p.camera)).collect();

    // Ray epochs.
    let t = Instant::now();
    st.refit()?;
    seconds.insert("refit".to_string(), t.elapsed().as_secs_f64());

    // Content views, features, TCM.
    let t = Instant::now();
    st.cache_samples();
    let (template, style_bank) = match job.method {
        Method::RefNpr => (Some(st.template(&styles)?), None),
        Method::Arf => {
            let (raw, _) = tcm::image_features(&st.vgg, &styles[0], &ad, &[&RELU3], false)?;
            (None, Some(raw.into_iter().next().expect("one block")))
        }
    };
    let colour = job.method == Method::RefNpr && cfg.ablation.use_colour_loss && case.color_pre;
    let (mut guides, colour_matched) = st.guides(template.as_ref(), keep_content, colour)?;
    seconds.insert("content".to_string(), t.elapsed().as_secs_f64());

    // Image epochs.
    let s = &cfg.schedule;
    let views = dataset.train.len();
    let total_steps = s.image_epochs * views;
    let smooth_epochs = if job.method == Method::RefNpr && cfg.ablation.smooth_update { (s.image_epochs as f32 * s.smooth_fraction).round() as usize } else { 0 };
    let smooth_start = s.image_epochs - smooth_epochs.min(s.image_epochs);
    st.field.reset_optimiser();
    let bar = progress_bar(total_steps as u64, 0);
    let mut template = template;
    let t_epochs = Instant::now();
    let mut t_smooth = None;
    let mut step = 0;
    for epoch in 0..s.image_epochs {
        let smooth = epoch >= smooth_start;
        if smooth && t_smooth.is_none() {
            // The stylized field becomes the content generator.
            t_smooth = Some(Instant::now());
            let t = st.template(&styles)?;
            guides = st.guides(Some(&t), false, false)?.0;
            template = Some(t);
        }
        let mut order: Vec<usize> = (0..views).collect();
        order.shuffle(&mut ChaCha8Rng::seed_from_u64(cfg.seed ^ (epoch as u64 + 1).wrapping_mul(0xA24B_AED4_963E_E407)));
        for v in order {
            let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed ^ 0x1A6E ^ (step as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            let (grad, parts) = st.image_gradient(v, &guides[v], template.as_ref(), style_bank.as_ref(), smooth)?;
            let (ref_grad, ref_loss) = if job.method == Method::RefNpr { st.reference_gradient(&mut rng) } else { (None, 0.0) };
            let grad = match ref_grad {
                Some(g) => grad + g,
                None => grad,
            };
            let grad = st.with_tv(grad, &mut rng);
            let frac = step as f32 / total_steps.max(1) as f32;
            let lr = crate::train::log_lerp(s.lr, s.lr_final, frac);
            st.field.rmsprop(grad, lr, s.rmsprop_beta, s.eps);
            let point = CurvePoint {
                phase: if smooth { "smooth" } else { "image" },
                step,
                total: parts.total + ref_loss,
                reference: ref_loss,
                feature: parts.feature,
                colour: parts.colour,
                content: parts.content,
                image_tv: parts.image_tv,
            };
            bar.set_position(step as u64 + 1);
            bar.set_message(format!(
                "epoch {}/{} {} | total {:.4} ref {:.4} feat {:.4} colour {:.4}",
                epoch + 1,
                s.image_epochs,
                point.phase,
                point.total,
                point.reference,
                point.feature,
                point.colour
            ));
            if bar.is_hidden() && (step + 1) % (views / 4).max(1) == 0 {
                eprintln!(
                    "epoch {}/{} step {}/{total_steps} ({}) total {:.4} ref {:.4} feat {:.4} colour {:.4} ({:.0} s)",
                    epoch + 1,
                    s.image_epochs,
                    step + 1,
                    point.phase,
                    point.total,
                    point.reference,
                    point.feature,
                    point.colour,
                    started.elapsed().as_secs_f64()
                );
            }
            st.log(point);
            step += 1;
        }
    }
    bar.finish_and_clear();
    let smooth_secs = t_smooth.map(|t| t.elapsed().as_secs_f64()).unwrap_or(0.0);
    seconds.insert("image_epochs".to_string(), t_epochs.elapsed().as_secs_f64() - smooth_secs);
    seconds.insert("smooth_update".to_string(), smooth_secs);

    // The stylized checkpoint: a normal grid with SH degree 0.
    let mut meta = photo_meta.clone();
    meta.sh_degree = 0;
    meta.config.grid.sh_degree = 0;
    meta.step = step;
    meta.train_seconds = started.elapsed().as_secs_f64();
    let rows = st.field.grid.num_rows();
    checkpoint::save(&job.out.join(checkpoint::CHECKPOINT_FILE), &meta, &st.field.grid, &Tensor::zeros([rows, 1], &device), &Tensor::zeros([rows, 3], &device))?;
    for r in 0..st.reference_samples.len() {
        let img = st.render_reference(r);
        crate::imageio::save_png(&job.out.join(format!("reference_{r}.png")), img.width as u32, img.height as u32, &img.rgb)?;
    }
    let report = StylizeReport {
        method: job.method,
        backend: job.backend.to_string(),
        photo: job.photo.clone(),
        case: job.case.clone(),
        config: cfg.clone(),
        views,
        image_size: [width, height],
        registered_pixels: st.registered.len(),
        registered_fraction: reg_report.fraction_overall,
        colour_matched_fraction: colour_matched,
        colour_transfer: st.colour_transfer,
        total_seconds: started.elapsed().as_secs_f64(),
        seconds,
        peak_rss_mb: peak_rss_mb(),
        final_losses: st.curve.iter().rev().find(|p| p.phase != "refit").cloned(),
        curve: std::mem::take(&mut st.curve),
        warnings: std::mem::take(&mut st.warnings),
    };
    let json = job.out.join("stylize.json");
    std::fs::write(&json, serde_json::to_string_pretty(&report)?).with_context(|| format!("cannot write {}", json.display()))?;
    if job.render_test && !dataset.test.is_empty() {
        let style_ck = checkpoint::load_with(&job.out, &device, false)?;
        let cams: Vec<Camera> = dataset.test.iter().map(|v| v.camera).collect();
        crate::render_path::render_frames(&style_ck, &cams, &job.out.join("test"), true)?;
    }
    Ok(report)
}

