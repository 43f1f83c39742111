//! One stylization step and what it needs: the style field, VGG16, the
//! sample cache, and the ray kernel chosen once (the fused plain-Rust
//! passes of `field::host_colour` on the CPU backends, the Burn graph on a
//! GPU). An image step (`image_step`) and a refit step (`refit_step`)
//! each take one RMSprop step and return their losses; the loops that
//! drive them, their resume points and phases are `run`'s.
//!
//! Deferred back-propagation: an image step renders the whole view
//! without autodiff, takes the image losses' gradient with respect to the
//! image through VGG16, then re-renders in chunks with autodiff and
//! injects that gradient (`field::chunked_gradient`), so memory is bounded
//! by the chunk.

use anyhow::{Result, bail};
use burn::tensor::{Device, Int, Tensor};
use rand::Rng;

use crate::field::checkpoint::CheckpointMeta;
use crate::field::frozen::{self, DeviceSamples, FrozenSamples};
use crate::field::grid::RadianceGrid;
use crate::field::host_colour;
use crate::field::march::MarchParams;
use crate::field::optim::{Rmsprop, log_lerp};
use crate::kernels::rows_op;
use crate::reference::registration::RegistrationFile;
use crate::scene::data::Dataset;
use crate::stylize::budget;
use crate::stylize::colour_transfer::{ColourStats, ColourTransfer};
use crate::stylize::config::{LrSchedule, StylizeConfig, TransferPixels, WhiteOn};
use crate::stylize::far::stylized_far;
use crate::stylize::field::{
    DeviceChunk, ShTv, StepRows, StyleField, chunked_gradient, chunks_gradient, gathered_gradient, picked_gradient,
    render_chunks, render_gathered,
};
use crate::stylize::losses;
use crate::stylize::region::{EditRegion, PixelRegion, edit_region, mark_painted_elsewhere};
use crate::stylize::samples::{PseudoRays, SampleCache};
use crate::stylize::styles::colour_stats;
use crate::stylize::tcm::{self, ColourTargets, FEATURE_BLOCKS, RELU3, StoredFeatures, Template};
use crate::stylize::{CurvePoint, HeldMemory, Method, StepKind, StylizeJob};
use crate::util::image::Image;
use crate::util::profile::{PartTime, StepProfile};
use crate::util::progress::{Event, Progress};
use crate::util::rng::{Stream, step_rng};
use crate::util::tensor::{floats, is_host_memory, scalar, tensor_bytes, to_vec};
use crate::vgg::{Vgg16, VggLayer};

/// The interleaved `[pixels, 3]` gradient of an image loss (planar `[1, 3, H, W]` gradient in).
fn interleaved(grad: Tensor<4>) -> Tensor<2> {
    let [_, c, h, w] = grad.dims();
    grad.reshape([c, h * w]).transpose()
}

/// Rendered colours `[h * w, 3]` (row-major pixels) as a `[1, 3, h, w]` image: the inverse of `interleaved`.
fn planar_image(rgb: Tensor<2>, w: usize, h: usize) -> Tensor<4> {
    rgb.transpose().reshape([1, 3, h, w])
}

/// The rays of a squared-error loss: sample lists on the host (uploaded
/// chunk by chunk), or picks into lists kept on the device.
enum RaySet<'s> {
    Host(&'s FrozenSamples),
    Gathered(&'s DeviceSamples, &'s [usize]),
}

impl RaySet<'_> {
    fn len(&self) -> usize {
        match self {
            RaySet::Host(s) => s.num_rays,
            RaySet::Gathered(_, picks) => picks.len(),
        }
    }
}

/// The content term's fixed features of a view (λ').
pub(crate) enum ContentFeatures {
    /// No content term.
    Unused,
    /// Raw features per block, kept.
    Kept(Vec<StoredFeatures>),
    /// Taken again at each step of the view from the image VGG16 saw (the
    /// memory budget had no room to keep them: `stylize::budget`).
    Recomputed(Image),
}

impl ContentFeatures {
    fn bytes(&self) -> usize {
        match self {
            Self::Unused => 0,
            Self::Kept(blocks) => blocks.iter().map(StoredFeatures::bytes).sum(),
            Self::Recomputed(image) => image.rgb.len() * 4,
        }
    }
}

/// Per-view data kept for the image epochs.
pub struct ViewGuide {
    pub(crate) content: ContentFeatures,
    /// TCM matches per block (Ref-NPR).
    pub(crate) matches: Vec<Tensor<1, Int>>,
    /// A local edit: per relu3 position, whether it looks like an edited
    /// reference position (`Template::edit_votes`; empty otherwise).
    pub(crate) edit_votes: Vec<bool>,
    pub(crate) colour: Option<ColourTargets>,
}

impl ViewGuide {
    /// Bytes of its content features, matches, votes and colour targets.
    pub fn bytes(&self) -> usize {
        let matches: usize = self.matches.iter().map(tensor_bytes).sum();
        self.content.bytes() + matches + self.edit_votes.len() + self.colour.as_ref().map_or(0, ColourTargets::bytes)
    }

    /// L_color's targets of this view (Ref-NPR with the colour loss).
    pub fn colour(&self) -> Option<&ColourTargets> {
        self.colour.as_ref()
    }
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

/// The loss parts of an image step, kept on the device until the step
/// ends and then read back in one transfer: on a GPU every read waits for
/// the queue, and these values only feed the progress line and the curve.
#[derive(Default)]
struct LossParts {
    image_tv: Option<Tensor<1>>,
    feature: Option<Tensor<1>>,
    colour: Option<Tensor<1>>,
    content: Option<Tensor<1>>,
}

/// Adds `value`'s detached value to a running sum kept on the device
/// (read once, when the sum is complete: a read per term would wait for
/// the device's queue each time).
fn accumulate(sum: &mut Option<Tensor<1>>, value: &Tensor<1>) {
    let value = value.clone().inner();
    *sum = Some(match sum.take() {
        None => value,
        Some(s) => s + value,
    });
}

impl LossParts {
    /// All parts and the total, read in one transfer (absent parts are 0).
    fn read(self, total: &Tensor<1>) -> ImageLosses {
        let parts = [self.image_tv, self.feature, self.colour, self.content, Some(total.clone().inner())];
        let present: Vec<Tensor<1>> = parts.iter().flatten().cloned().collect();
        let mut values = to_vec(Tensor::cat(present, 0)).into_iter();
        let [image_tv, feature, colour, content, total] =
            parts.map(|p| p.map_or(0.0, |_| values.next().expect("one value per present part")));
        ImageLosses { total, feature, colour, content, image_tv }
    }
}

/// What the image epochs are guided by: the TCM template (Ref-NPR), the
/// style features (ARF) and the per-view guides.
pub struct Guidance {
    pub template: Option<Template>,
    pub style_bank: Option<Tensor<2>>,
    pub guides: Vec<ViewGuide>,
}

impl Guidance {
    /// Bytes of the template or style features and every view's guide.
    pub fn bytes(&self) -> usize {
        let guides: usize = self.guides.iter().map(ViewGuide::bytes).sum();
        guides + self.template.as_ref().map_or(0, Template::bytes) + self.style_bank.as_ref().map_or(0, tensor_bytes)
    }
}

/// Which kernel renders and differentiates the rays, chosen once (`ray_kernel`).
#[derive(Clone, Copy, PartialEq, Eq)]
enum RayPass {
    /// `field::host_colour` over the grid as host numbers (CPU backends).
    Host,
    /// The Burn graph (`stylize::field`'s chunked gradients).
    Graph,
}

/// What one image step and one refit step need.
pub struct StyleStep<'a> {
    job: &'a StylizeJob,
    cfg: &'a StylizeConfig,
    dataset: &'a Dataset,
    background: [f32; 3],
    pub field: StyleField,
    pub(crate) samples: SampleCache<'a>,
    pub(crate) vgg: Vgg16,
    /// The autodiff device (VGG16, the image losses) and the plain one.
    pub(crate) ad: Device,
    pub(crate) device: Device,
    kernel: RayPass,
    /// Optimiser steps taken so far, over all phases (the shared rate schedule).
    pub optimiser_steps: usize,
    /// Where the current phase's steps spend their time.
    profile: StepProfile,
    /// A local edit's voxels: the only rows the optimiser changes (all when None).
    pub(crate) edit: Option<EditRegion>,
    /// A local edit's regions, one per reference (the template keeps only their positions).
    pub(crate) regions: Option<Vec<PixelRegion>>,
    /// The sample cache's size, MB: `sample_cache_mb`, or what the memory
    /// budget leaves of it (`stylize::budget`).
    pub(crate) sample_cache_mb: usize,
    /// Views whose content features are kept (in the dataset's order; the
    /// others' are taken again at each of their steps): all unless the
    /// memory budget has no room for them.
    pub(crate) content_views_kept: usize,
    /// The SH grid as host numbers for the host ray passes, refilled each
    /// step into this one buffer (`take_host_sh`; a mutex, so that a step
    /// can take it while its other parts still borrow the rest).
    sh_host: std::sync::Mutex<Vec<f32>>,
}

impl<'a> StyleStep<'a> {
    /// A stylization of `grid` (the photoreal field, cut to SH degree 0
    /// here) with the pseudo-rays of `registration`.
    pub fn new(
        job: &'a StylizeJob,
        dataset: &'a Dataset,
        grid: RadianceGrid,
        meta: &CheckpointMeta,
        registration: RegistrationFile,
    ) -> Self {
        let field = StyleField::new(grid);
        let march = MarchParams { colour_corners: job.config.colour_corners, ..meta.render.march };
        let samples = SampleCache::new(&field.grid, dataset, meta.ndc, march, &job.config, registration);
        let (ad, device) = (job.backend.autodiff_device(), job.backend.device());
        let kernel = if job.config.ray_kernel.is_host(&device) { RayPass::Host } else { RayPass::Graph };
        let profile = StepProfile::syncing(job.config.sync_parts.then(|| device.clone()));
        StyleStep {
            job,
            cfg: &job.config,
            dataset,
            background: meta.background,
            field,
            samples,
            vgg: Vgg16::load_weights(&ad, job.config.vgg.weights),
            ad,
            device,
            kernel,
            optimiser_steps: 0,
            profile,
            edit: None,
            regions: None,
            sample_cache_mb: job.config.sample_cache_mb,
            content_views_kept: if job.config.keep_content_features { usize::MAX } else { 0 },
            sh_host: std::sync::Mutex::new(Vec::new()),
        }
    }

    /// Whether the content term's fixed features are kept as f16
    /// (`half_content_features`, on the CPU backends only).
    pub(crate) fn half_content_features(&self) -> bool {
        self.cfg.half_content_features && is_host_memory(&self.device)
    }

    /// What this stylization holds now, by part (`guidance`: the guides
    /// when they are built).
    pub fn held(&self, guidance: Option<&Guidance>) -> HeldMemory {
        let mb = |bytes: usize| budget::mb(bytes as u64);
        let d = self.dataset;
        let photos: usize = d.train.iter().chain(&d.val).chain(&d.test).map(|v| v.rgb.len() * 4).sum();
        HeldMemory {
            photos_mb: mb(photos),
            registration_mb: mb(self.samples.registration_bytes()),
            sample_lists_mb: mb(self.samples.lists_bytes()),
            field_mb: mb(self.field.bytes()),
            guides_mb: mb(guidance.map_or(0, Guidance::bytes)),
        }
    }

    pub fn cfg(&self) -> &'a StylizeConfig {
        self.cfg
    }

    pub fn method(&self) -> Method {
        self.job.method
    }

    pub fn dataset(&self) -> &'a Dataset {
        self.dataset
    }

    /// The colour of rays that miss the scene (the photoreal run's).
    pub fn background(&self) -> [f32; 3] {
        self.background
    }

    /// Ref-NPR, after the refit (which fits the photos, far background
    /// included): the far map stylized by the references
    /// (`stylize::far`), and the sample lists made to see it.
    pub fn stylize_far(&mut self, progress: &dyn Progress) {
        let (references, left) = (&self.samples.registration.references, self.samples.reference_transmittance());
        if let Some(far) =
            self.field.grid.far.as_ref().map(|photo| stylized_far(photo, references, left, &self.cfg.colour_map))
        {
            self.field.grid.far = Some(far);
            self.samples.refresh_far(&self.field.grid, &self.device);
            progress.event(Event::Detail("far background painted and recoloured from the references".into()));
        }
    }

    /// From now on the steps are on `dataset`'s training views, with the
    /// pseudo-rays of `registration` (coarse epochs: the views at full size
    /// for the smooth update). The old lists are freed first, and the new
    /// ones cached.
    pub fn use_views(&mut self, dataset: &'a Dataset, registration: RegistrationFile) {
        let (ndc, march) = (self.samples.ndc(), self.samples.march());
        self.samples.release();
        self.dataset = dataset;
        self.samples = SampleCache::new(&self.field.grid, dataset, ndc, march, self.cfg, registration);
        self.cache_samples();
    }

    /// Caches the sample lists (once; `samples::SampleCache::cache`).
    pub fn cache_samples(&mut self) {
        self.samples.cache(&self.field.grid, self.cfg, self.job.method, &self.device, self.sample_cache_mb);
    }

    /// The step profile of the phase that just ended (and a fresh one for the next).
    pub fn take_profile(&mut self) -> Vec<PartTime> {
        let parts = self.profile.parts();
        self.profile.clear();
        parts
    }

    /// How the stylized field is marched (the photoreal run's, with this
    /// stylization's `colour_corners`).
    pub fn march(&self) -> MarchParams {
        self.samples.march()
    }

    pub fn num_references(&self) -> usize {
        self.samples.num_references()
    }

    /// The SH grid as a tensor on the field's device.
    pub fn sh_tensor(&self, values: &[f32]) -> Tensor<2> {
        floats(values.to_vec(), [values.len() / 3, 3], &self.field.grid.device())
    }

    /// One image step on training view `v`: the image losses by deferred
    /// back-propagation, L_ref on a batch of pseudo-rays (Ref-NPR), SH TV,
    /// one RMSprop step on the rows the step touches (or on all rows).
    pub fn image_step(
        &mut self,
        v: usize,
        step: usize,
        total_steps: usize,
        guidance: &Guidance,
        smooth: bool,
    ) -> Result<CurvePoint> {
        let s = &self.cfg.schedule;
        let mut rng = step_rng(self.cfg.seed, Stream::ImageStep, step);
        let samples = self.profile.time("view_samples", || self.samples.view(&self.field.grid, v));
        let (pseudo, tv, rows) = self.profile.time("step_rows", || {
            let pseudo = if self.job.method == Method::RefNpr {
                self.samples.pseudo_ray_batch(&self.field.grid, self.cfg, &mut rng)
            } else {
                Vec::new()
            };
            let tv = self.field.tv_rows(&self.sh_tv(false), &mut rng);
            let cells: Vec<&[u32]> =
                std::iter::once(&samples.cell_keys[..]).chain(pseudo.iter().flat_map(PseudoRays::cells)).collect();
            let rows = self.field.step_rows(self.cfg.optim.sparse, &cells, &tv);
            (pseudo, tv, rows)
        });
        // The grid as host numbers, read once for the step's fused ray passes (`ray_kernel`).
        let host_sh =
            (self.kernel == RayPass::Host).then(|| take_host_sh(&self.sh_host, &self.field.grid.sh, &self.profile));
        let (grad, parts) = self.image_gradient(
            v,
            &samples,
            &rows,
            host_sh.as_deref(),
            &guidance.guides[v],
            guidance.template.as_ref(),
            guidance.style_bank.as_ref(),
            smooth,
        )?;
        drop(samples);
        let (ref_grad, ref_loss) =
            self.profile.time("reference_loss", || self.reference_gradient(pseudo, &rows, host_sh.as_deref()));
        let grad = match ref_grad {
            Some(g) => grad + g,
            None => grad,
        };
        let grad = self.profile.time("sh_tv", || self.field.add_tv_gradient(grad, &self.sh_tv(false), &tv, &rows));
        let lr = self.learning_rate(log_lerp(s.lr, s.lr_final, step as f32 / total_steps.max(1) as f32));
        let started = std::time::Instant::now();
        self.optimiser_step(grad, rows, lr);
        self.profile.add_since("optimiser", started);
        if let Some(sh) = host_sh {
            *self.sh_host.lock().expect("the SH buffer") = sh;
        }
        Ok(CurvePoint {
            phase: if smooth { StepKind::Smooth } else { StepKind::Image },
            step,
            total: parts.total + ref_loss,
            reference: ref_loss,
            feature: parts.feature,
            colour: parts.colour,
            content: parts.content,
            image_tv: parts.image_tv,
            seconds: 0.0,
        })
    }

    /// The rate of the next optimiser step: `per_phase` is the phase's own
    /// (the refit's, or the image epochs' decay); the shared schedule
    /// decays over all steps taken so far.
    fn learning_rate(&self, per_phase: f32) -> f32 {
        let s = &self.cfg.schedule;
        match s.lr_schedule {
            LrSchedule::PerPhase => per_phase,
            LrSchedule::Shared => {
                log_lerp(s.lr, s.lr_final, (self.optimiser_steps as f32 / s.lr_decay_steps as f32).min(1.0))
            }
        }
    }

    /// The SH TV of an image step, or of a refit step (`refit`); an ARF
    /// run's image steps take `[arf] tv_sh`.
    fn sh_tv(&self, refit: bool) -> ShTv {
        let l = &self.cfg.loss;
        let image = if self.job.method == Method::Arf { self.cfg.arf.tv_sh } else { l.tv_sh };
        ShTv {
            weight: if refit { l.refit_tv_sh } else { image },
            fraction: l.tv_fraction,
            per_voxel: l.tv_sh_per_voxel,
            per_channel: l.tv_sh_per_channel,
        }
    }

    fn optimiser_step(&mut self, grad: Tensor<2>, rows: StepRows, lr: f32) {
        // A local edit: the gradient of every row outside it is zero, and
        // RMSprop moves a row only by its gradient.
        let grad = match &self.edit {
            Some(edit) => grad * edit.gradient_mask(&mut rows.grid_rows(), &self.field.grid.device()),
            None => grad,
        };
        let s = &self.cfg.schedule;
        let opt = Rmsprop { beta: s.rmsprop_beta, eps: s.eps, start: self.cfg.optim.rms_init };
        self.field.rmsprop(grad, rows, lr, opt, self.kernel == RayPass::Host);
        self.optimiser_steps += 1;
    }

    /// One refit step: a seeded batch of training pixels (`colours`, their
    /// targets, views one after another), their MSE gradient plus SH TV,
    /// one RMSprop step. Returns the batch's MSE as a curve point.
    pub fn refit_step(&mut self, step: usize, colours: &[[f32; 3]]) -> CurvePoint {
        let s = &self.cfg.schedule;
        let mut rng = step_rng(self.cfg.seed, Stream::Refit, step);
        let picks: Vec<usize> = (0..s.ray_batch).map(|_| rng.random_range(0..colours.len())).collect();
        let target: Vec<f32> = picks.iter().flat_map(|&i| colours[i]).collect();
        let samples = self.profile.time("sample_lists", || self.samples.training_pixel_lists(&self.field.grid, &picks));
        let (tv, rows) = self.profile.time("step_rows", || {
            let tv = self.field.tv_rows(&self.sh_tv(true), &mut rng);
            let rows = self.field.step_rows(self.cfg.optim.sparse, &[&samples.cell_keys], &tv);
            (tv, rows)
        });
        let host_sh =
            (self.kernel == RayPass::Host).then(|| take_host_sh(&self.sh_host, &self.field.grid.sh, &self.profile));
        let (grad, mse) = self.profile.time("photo_loss", || match &host_sh {
            Some(sh) => self.host_mse_gradient(sh, &samples, None, &target, &rows, 1.0),
            None => {
                let target = floats(target, [picks.len(), 3], &self.device);
                self.mse_gradient(RaySet::Host(&samples), &rows, target, 1.0)
            }
        });
        let grad = self.profile.time("sh_tv", || self.field.add_tv_gradient(grad, &self.sh_tv(true), &tv, &rows));
        let lr = self.learning_rate(s.lr_refit);
        let started = std::time::Instant::now();
        self.optimiser_step(grad, rows, lr);
        self.profile.add_since("optimiser", started);
        if let Some(sh) = host_sh {
            *self.sh_host.lock().expect("the SH buffer") = sh;
        }
        CurvePoint::refit(step, mse)
    }

    /// [`mse_gradient`](Self::mse_gradient) by `field::host_colour`: `rays`
    /// of `samples` (all when None), `target` interleaved RGB per ray.
    fn host_mse_gradient(
        &self,
        sh: &[f32],
        samples: &FrozenSamples,
        rays: Option<&[usize]>,
        target: &[f32],
        rows: &StepRows,
        weight: f32,
    ) -> (Tensor<2>, f32) {
        let n = rays.map_or(samples.num_rays, <[usize]>::len);
        let scale = weight / (3.0 * n.max(1) as f32);
        let (grad, loss) =
            host_colour::colour_gradient(sh, samples, rays, self.background, rows.len(), &rows.slot_fn(), |k, rgb| {
                let d = [0, 1, 2].map(|c| rgb[c] - target[k * 3 + c]);
                (d.map(|x| 2.0 * scale * x), scale * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]))
            });
        (floats(grad, [rows.len(), 3], &self.device), loss as f32)
    }

    /// `weight` x the mean squared error of the rays' colours to `target`
    /// (`[rays, 3]`): its SH gradient and its value.
    fn mse_gradient(&self, rays: RaySet, rows: &StepRows, target: Tensor<2>, weight: f32) -> (Tensor<2>, f32) {
        let scale = weight / (3.0 * rays.len().max(1) as f32);
        // Summed on the device and read once (a read per chunk would wait for the queue each time).
        let value: std::cell::RefCell<Option<Tensor<1>>> = std::cell::RefCell::new(None);
        let loss_of = |rgb: Tensor<2>, start: usize, len: usize| {
            let d = rgb - target.clone().narrow(0, start, len);
            let loss = (d.clone() * d).sum() * scale;
            accumulate(&mut value.borrow_mut(), &loss);
            loss
        };
        let (sh, chunk) = (&self.field.grid.sh, self.cfg.render_chunk);
        let grad = match rays {
            RaySet::Host(samples) => chunked_gradient(sh, samples, self.background, chunk, rows, &loss_of),
            RaySet::Gathered(lists, picks) => picked_gradient(sh, lists, picks, chunk, self.background, rows, &loss_of),
        };
        (grad, value.into_inner().map_or(0.0, scalar))
    }

    /// Training view `v` rendered from the field as it is now.
    pub fn render_view(&self, v: usize) -> Image {
        let rgb = frozen::render_plain(
            &self.field.grid.sh,
            &self.samples.view(&self.field.grid, v),
            self.background,
            self.cfg.render_chunk,
        );
        self.dataset.train[v].camera.image_of(rgb)
    }

    /// Reference `r` rendered from the field as it is now.
    pub fn render_reference(&self, r: usize) -> Image {
        let samples = self.samples.reference_samples(r);
        let rgb = frozen::render_plain(&self.field.grid.sh, &samples, self.background, self.cfg.render_chunk);
        self.samples.registration.references[r].camera.image_of(rgb)
    }

    /// ARF's second colour transfer: the field's training-view renders
    /// (clamped, as they are shown) get `style`'s colour statistics.
    pub fn post_colour_transfer(&mut self, style: &ColourStats, which: TransferPixels) -> Result<ColourTransfer> {
        let renders: Vec<Vec<f32>> = (0..self.dataset.train.len())
            .map(|v| self.render_view(v).rgb.into_iter().map(|x| x.clamp(0.0, 1.0)).collect())
            .collect();
        let renders: Vec<&[f32]> = renders.iter().map(|r| &r[..]).collect();
        let tf = ColourTransfer::between(&colour_stats(&renders, self.background, which)?, style);
        self.field.apply_colour_transfer(&tf);
        Ok(tf)
    }

    /// A local edit's regions, one per reference, with the pixels each
    /// leaves unpainted but another paints marked (`mark_painted_elsewhere`).
    pub fn set_regions(&mut self, regions: Option<Vec<PixelRegion>>) {
        self.regions = regions.map(|mut regions| {
            let references: Vec<_> = (0..regions.len()).map(|r| self.samples.reference_samples(r)).collect();
            mark_painted_elsewhere(self.field.grid.num_rows(), &references, &mut regions);
            regions
        });
    }

    /// A local edit's voxels (`stylize::region`): the references' rays by
    /// their regions, and the training views' rays by their relu3 TCM
    /// matches in `guides` (Ref-NPR; ARF has none, and decides only what
    /// a reference sees).
    pub fn edit_region(&self, regions: &[PixelRegion], guides: &[ViewGuide]) -> Result<EditRegion> {
        let references: Vec<_> =
            regions.iter().enumerate().map(|(r, region)| (self.samples.reference_samples(r), region)).collect();
        let mut views = guides.iter().enumerate().filter(|(_, g)| !g.edit_votes.is_empty()).map(|(v, g)| {
            let k = self.dataset.train[v].camera.intrinsics;
            let lists = self.samples.view(&self.field.grid, v);
            (lists, &g.edit_votes[..], [k.width as usize, k.height as usize])
        });
        edit_region(self.field.grid.num_rows(), &references, &mut views)
    }

    /// The pseudo-ray loss's gradient on the step's rows (λ_r times the mean
    /// squared error of each group of `pseudo_ray_batch`) and its value.
    /// `host_sh` (the grid as host numbers) selects the fused ray pass.
    fn reference_gradient(
        &self,
        groups: Vec<PseudoRays>,
        rows: &StepRows,
        host_sh: Option<&[f32]>,
    ) -> (Option<Tensor<2>>, f32) {
        let mut total: Option<Tensor<2>> = None;
        let mut value = 0.0;
        for group in groups {
            let (g, v) = match (host_sh, group.on_device) {
                (Some(sh), _) => self.host_mse_gradient(
                    sh,
                    &group.lists,
                    Some(&group.rays),
                    &group.target,
                    rows,
                    self.cfg.loss.reference,
                ),
                (None, Some(lists)) => {
                    let target = floats(group.target, [group.rays.len(), 3], &self.device);
                    self.mse_gradient(RaySet::Gathered(lists, &group.rays), rows, target, self.cfg.loss.reference)
                }
                (None, None) => {
                    let target = floats(group.target, [group.rays.len(), 3], &self.device);
                    let samples = group.lists.subset(&group.rays);
                    self.mse_gradient(RaySet::Host(&samples), rows, target, self.cfg.loss.reference)
                }
            };
            value += v;
            total = Some(match total {
                None => g,
                Some(t) => t + g,
            });
        }
        (total, value)
    }

    /// Deferred back-propagation of the image losses of view `v`: the
    /// gradient with respect to the SH rows, and the loss values. `host_sh`
    /// (the grid as host numbers) selects the fused ray pass.
    #[allow(clippy::too_many_arguments)]
    fn image_gradient(
        &self,
        v: usize,
        samples: &FrozenSamples,
        rows: &StepRows,
        host_sh: Option<&[f32]>,
        guide: &ViewGuide,
        template: Option<&Template>,
        style_bank: Option<&Tensor<2>>,
        smooth: bool,
    ) -> Result<(Tensor<2>, ImageLosses)> {
        let cam = &self.dataset.train[v].camera;
        let (w, h) = (cam.intrinsics.width as usize, cam.intrinsics.height as usize);
        if let Some(sh) = host_sh {
            return self.host_image_gradient(sh, samples, rows, (w, h), guide, template, style_bank, smooth);
        }
        // 1. Full image, no autodiff; it stays on the device, and so do the
        // chunks' sample lists, gathered there (the view's lists are kept on
        // the device) or uploaded, once for both passes.
        let sh = &self.field.grid.sh;
        let started = std::time::Instant::now();
        let gathered: Option<Vec<_>> = self.samples.view_on_device(v).map(|lists| {
            let all: Vec<usize> = (0..samples.num_rays).collect();
            lists.gather_chunks(&all, self.cfg.render_chunk, sh).collect()
        });
        let uploaded = match gathered {
            Some(_) => Vec::new(),
            None => DeviceChunk::upload_all(samples, self.cfg.render_chunk, sh),
        };
        let rgb = match &gathered {
            Some(chunks) => render_gathered(sh, chunks, self.background),
            None => render_chunks(sh, &uploaded, self.background),
        };
        self.profile.add_since("image_render", started);
        // 2. Image losses on a leaf image, gradient with respect to the image.
        let started = std::time::Instant::now();
        let image = planar_image(rgb, w, h).autodiff().require_grad();
        let (loss, parts) = self.image_loss(image.clone(), guide, template, style_bank, smooth)?;
        let grads = loss.backward();
        let Some(g) = image.grad(&grads) else { bail!("the image losses do not depend on the image") };
        let g = interleaved(g);
        self.profile.add_since("image_losses_vgg", started);
        // 3. Chunked re-render with autodiff, injecting the image gradient.
        let inject = |rgb: Tensor<2>, start: usize, len: usize| (rgb * g.clone().narrow(0, start, len)).sum();
        let grad = self.profile.time("image_rerender_grad", || match gathered {
            Some(chunks) => gathered_gradient(sh, chunks, self.background, rows, &inject),
            None => chunks_gradient(sh, &uploaded, self.background, rows, &inject),
        });
        Ok((grad, parts))
    }

    /// [`image_gradient`](Self::image_gradient) with the render and the
    /// re-render by `field::host_colour` (the same sums, no upload).
    #[allow(clippy::too_many_arguments)]
    fn host_image_gradient(
        &self,
        sh: &[f32],
        samples: &FrozenSamples,
        rows: &StepRows,
        (w, h): (usize, usize),
        guide: &ViewGuide,
        template: Option<&Template>,
        style_bank: Option<&Tensor<2>>,
        smooth: bool,
    ) -> Result<(Tensor<2>, ImageLosses)> {
        let rgb = self.profile.time("image_render", || host_colour::render(sh, samples, None, self.background));
        let started = std::time::Instant::now();
        let image = planar_image(floats(rgb, [w * h, 3], &self.device), w, h).autodiff().require_grad();
        let (loss, parts) = self.image_loss(image.clone(), guide, template, style_bank, smooth)?;
        let grads = loss.backward();
        let Some(g) = image.grad(&grads) else { bail!("the image losses do not depend on the image") };
        let g = to_vec(interleaved(g));
        self.profile.add_since("image_losses_vgg", started);
        let (grad, _) = self.profile.time("image_rerender_grad", || {
            host_colour::colour_gradient(sh, samples, None, self.background, rows.len(), &rows.slot_fn(), |k, _| {
                ([g[k * 3], g[k * 3 + 1], g[k * 3 + 2]], 0.0)
            })
        });
        Ok((floats(grad, [rows.len(), 3], &self.device), parts))
    }

    /// The content term's fixed features per block (none in the smooth
    /// update, which has no content term).
    fn content_features(&self, content: &ContentFeatures, smooth: bool) -> Result<Vec<Tensor<2>>> {
        Ok(match content {
            _ if smooth => Vec::new(),
            ContentFeatures::Unused => Vec::new(),
            ContentFeatures::Kept(blocks) => blocks.iter().map(StoredFeatures::tensor).collect(),
            ContentFeatures::Recomputed(image) => {
                let blocks = self.job.method.feature_blocks();
                // Rounded as kept features are, so a view's loss is the same either way.
                let half = self.half_content_features();
                let raw = tcm::image_features(&self.vgg, image, &self.ad, &blocks, false)?.0;
                raw.into_iter().map(|f| StoredFeatures::store(f, half).tensor()).collect()
            }
        })
    }

    fn image_loss(
        &self,
        image: Tensor<4>,
        guide: &ViewGuide,
        template: Option<&Template>,
        style_bank: Option<&Tensor<2>>,
        smooth: bool,
    ) -> Result<(Tensor<1>, ImageLosses)> {
        let [_, _, h, w] = image.dims();
        let l = &self.cfg.loss;
        let content = self.profile.time("content_features", || self.content_features(&guide.content, smooth))?;
        let mut parts = LossParts::default();
        let tv = losses::image_tv(image.clone());
        accumulate(&mut parts.image_tv, &tv);
        let mut total = tv * l.image_tv;
        match self.job.method {
            Method::RefNpr => {
                let template = template.expect("Ref-NPR has a template");
                if self.cfg.ablation.use_feature_loss {
                    let maps = self.vgg.features(image.clone(), &VggLayer::TCM)?;
                    let render = tcm::render_blocks(&maps, &FEATURE_BLOCKS, h, w);
                    let (weight, content_weight) =
                        if smooth { (l.smooth_feature, 0.0) } else { (l.feature, l.content) };
                    for (b, r) in render.into_iter().enumerate() {
                        let style = losses::cosine_distance(r.clone(), template.guidance(b, &guide.matches[b]));
                        accumulate(&mut parts.feature, &style);
                        total = total + style * weight;
                        if let (true, Some(fixed)) = (content_weight > 0.0, content.get(b)) {
                            let c = losses::content_loss(r, fixed.clone(), self.cfg.vgg.weights);
                            accumulate(&mut parts.content, &c);
                            total = total + c * (weight * content_weight);
                        }
                    }
                }
                if let Some(c) = guide.colour.as_ref().filter(|_| !smooth || self.cfg.colour_map.in_smooth_update) {
                    let patches = losses::patch_means(image, c.patch);
                    let mask = match l.colour_white_on {
                        WhiteOn::Content => c.mask.clone(),
                        WhiteOn::Render => c.mask.clone() * losses::not_white(patches.clone().detach(), l.colour_white),
                    };
                    let loss = losses::colour_loss(patches, c.target.clone(), mask, l.colour_norm);
                    accumulate(&mut parts.colour, &loss);
                    total = total + loss * c.weight;
                }
            }
            Method::Arf => {
                let a = &self.cfg.arf;
                let (image, h, w) = if a.half_resolution { (losses::half(image), h / 2, w / 2) } else { (image, h, w) };
                let maps = self.vgg.features(image, &RELU3)?;
                let render = tcm::render_blocks(&maps, &[&RELU3], h, w).remove(0);
                let nnfm = losses::nnfm_loss(
                    render.clone(),
                    style_bank.expect("ARF has a style bank").clone(),
                    self.cfg.search_chunk,
                );
                accumulate(&mut parts.feature, &nnfm);
                total = total + nnfm * a.nnfm;
                if let (true, Some(fixed)) = (a.content > 0.0, content.first()) {
                    let c = losses::content_loss(render, fixed.clone(), self.cfg.vgg.weights);
                    accumulate(&mut parts.content, &c);
                    total = total + c * a.content;
                }
            }
        }
        let parts = parts.read(&total);
        Ok((total, parts))
    }
}

/// The SH grid `sh` as host numbers (for `field::host_colour`), in the
/// buffer `kept` from step to step (taken out of it: the caller puts it
/// back when the step is done with it), timed as `host_sh`.
fn take_host_sh(kept: &std::sync::Mutex<Vec<f32>>, sh: &Tensor<2>, profile: &StepProfile) -> Vec<f32> {
    let started = std::time::Instant::now();
    let mut values = std::mem::take(&mut *kept.lock().expect("the SH buffer"));
    rows_op::read_all_into(sh, &mut values);
    profile.add_since("host_sh", started);
    values
}
