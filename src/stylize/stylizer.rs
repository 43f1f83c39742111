//! The `Stylizer`: one stylization's state and its phases - the colour
//! refit, the content guides (renders, VGG16 features, TCM matches, colour
//! targets), and the image epochs, each a loop over one `image_step`.
//!
//! Deferred back-propagation: a step renders the whole view without
//! autodiff, takes the image losses' gradient with respect to the image
//! through VGG16, then re-renders in chunks with autodiff and injects that
//! gradient (`field::chunked_gradient`), so memory is bounded by the chunk.

use std::borrow::Cow;

use anyhow::{Result, bail};
use burn::tensor::{Device, Int, Tensor};
use rand::Rng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::eval::metrics::psnr_from_mse;
use crate::field::checkpoint::{self, CheckpointMeta};
use crate::field::frozen::{self, DeviceSamples, FrozenSamples};
use crate::field::grid::{CellLattice, RadianceGrid};
use crate::field::host_colour;
use crate::field::march::{BlockOccupancy, MarchParams, Marcher};
use crate::field::optim::{Rmsprop, log_lerp};
use crate::reference::registration::RegistrationFile;
use crate::scene::camera::{Camera, NdcParams, Ray, to_ndc};
use crate::scene::data::Dataset;
use crate::stylize::colour_transfer::{ColourStats, ColourTransfer};
use crate::stylize::config::{LrSchedule, Placement, StylizeConfig, TransferPixels, WhiteOn};
use crate::stylize::field::{
    DeviceChunk, ShTv, StepRows, StyleField, chunked_gradient, chunks_gradient, gathered_gradient, render_chunks,
    render_gathered,
};
use crate::stylize::losses;
use crate::stylize::resume::{self, JobKey, ResumeState};
use crate::stylize::styles::{colour_stats, is_background};
use crate::stylize::tcm::{self, ColourTargets, FEATURE_BLOCKS, RELU3, ReferencePair, StoredFeatures, Template};
use crate::stylize::{CurvePoint, Method, SampleCacheReport, StepKind, StylizeJob};
use crate::util::diverged;
use crate::util::image::Image;
use crate::util::profile::{PartTime, StepProfile};
use crate::util::progress::{Event, Phase, Progress};
use crate::util::rng::{Stream, epoch_rng, step_rng};
use crate::util::tensor::{floats, is_host_memory, scalar, to_vec};
use crate::util::transfer::{self, PhaseTransfers, Transfers};
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

/// One group of L_ref's pseudo-rays: rays of `lists` (repeats allowed)
/// and their target colours; `on_device`, a device copy of `lists` to
/// gather them from.
struct PseudoRays<'s> {
    lists: Cow<'s, FrozenSamples>,
    on_device: Option<&'s DeviceSamples>,
    rays: Vec<usize>,
    target: Vec<f32>,
}

impl PseudoRays<'_> {
    /// Each ray's cells (whose corners are the step's rows).
    fn cells(&self) -> impl Iterator<Item = &[u32]> {
        self.rays.iter().map(move |&r| self.lists.ray_cells(r))
    }
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

/// Per-view data kept for the image epochs.
pub struct ViewGuide {
    /// Raw content features per block (for λ'; empty when unused).
    content: Vec<StoredFeatures>,
    /// TCM matches per block (Ref-NPR).
    matches: Vec<Tensor<1, Int>>,
    colour: Option<ColourTargets>,
}

impl ViewGuide {
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

/// What the image epochs cost: seconds, and host-device traffic per step
/// (image epochs, smooth update) and of the smooth update's new guides.
pub struct EpochCosts {
    pub image_seconds: f64,
    pub smooth_seconds: f64,
    pub image_steps: PhaseTransfers,
    pub smooth_steps: PhaseTransfers,
    pub smooth_guides: PhaseTransfers,
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

/// A stylization in progress: the field, its frozen sample lists, VGG16,
/// the pseudo-rays, and the loss curve so far.
pub struct Stylizer<'a> {
    job: &'a StylizeJob,
    cfg: &'a StylizeConfig,
    dataset: &'a Dataset,
    ndc: Option<NdcParams>,
    background: [f32; 3],
    march: MarchParams,
    pub field: StyleField,
    /// Empty-space skipping for every march (the density and rows are frozen).
    occupancy: BlockOccupancy,
    vgg: Vgg16,
    ad: Device,
    device: Device,
    /// Cached sample lists of the training views (None = re-marched when needed).
    view_samples: Vec<Option<FrozenSamples>>,
    /// Whether `cache_samples` has run (it runs once, before the refit or,
    /// in a resumed run, before the guidance).
    samples_cached: bool,
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
    registration: RegistrationFile,
    /// All registered pixels: (view, pixel, colour).
    pub registered: Vec<(u32, u32, [f32; 3])>,
    /// Sample lists of the registered pixels, in that order (None = re-marched when picked).
    registered_samples: Option<FrozenSamples>,
    /// Device copies of `reference_lists` and `registered_samples`, when
    /// the pseudo-rays are gathered there (`samples_on_device`).
    reference_on_device: Option<DeviceSamples>,
    registered_on_device: Option<DeviceSamples>,
    /// ARF: the photos are recoloured with this before the refit.
    pub colour_transfer: Option<ColourTransfer>,
    pub curve: Vec<CurvePoint>,
    /// Optimiser steps taken so far, over all phases (the shared rate schedule).
    optimiser_steps: usize,
    /// The field after the refit and when the smooth update began: the
    /// guides were built from them, so a resumed run rebuilds them from these.
    refit_sh: Vec<f32>,
    smooth_sh: Option<Vec<f32>>,
    /// The image step of the last `resume.bin` written by this run.
    saved_at: Option<usize>,
    /// Where the current phase's steps spend their time.
    profile: StepProfile,
    /// Each finished phase's step profile (`refit`, `image_epochs`, `smooth_update`).
    pub step_profiles: std::collections::BTreeMap<String, Vec<PartTime>>,
}

/// What the image epochs are guided by: the TCM template (Ref-NPR), the
/// style features (ARF) and the per-view guides.
pub struct Guidance {
    pub template: Option<Template>,
    pub style_bank: Option<Tensor<2>>,
    pub guides: Vec<ViewGuide>,
}

impl<'a> Stylizer<'a> {
    /// Sets up a stylization of `grid` (the photoreal field, cut to SH
    /// degree 0 here) with the pseudo-rays of `registration`.
    pub fn new(
        job: &'a StylizeJob,
        dataset: &'a Dataset,
        grid: RadianceGrid,
        meta: &CheckpointMeta,
        registration: RegistrationFile,
        colour_transfer: Option<ColourTransfer>,
    ) -> Self {
        let field = StyleField::new(grid);
        let misses = job.config.loss.reference_misses;
        let reference_pixels = registration
            .references
            .iter()
            .enumerate()
            .flat_map(|(r, p)| p.hits.iter().enumerate().filter(move |(_, h)| **h || misses).map(move |(i, _)| (r, i)))
            .collect();
        let ad = job.backend.autodiff_device();
        let mut st = Stylizer {
            job,
            cfg: &job.config,
            dataset,
            ndc: meta.ndc,
            background: meta.background,
            march: MarchParams { colour_corners: job.config.colour_corners, ..meta.config.march },
            occupancy: BlockOccupancy::with_density(&field.grid),
            field,
            vgg: Vgg16::load(&ad),
            ad,
            device: job.backend.device(),
            view_samples: vec![None; dataset.train.len()],
            samples_cached: false,
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
            colour_transfer,
            curve: Vec::new(),
            optimiser_steps: 0,
            refit_sh: Vec::new(),
            smooth_sh: None,
            saved_at: None,
            profile: StepProfile::default(),
            step_profiles: Default::default(),
        };
        for r in 0..st.registration.references.len() {
            let samples = st.march_camera(&st.registration.references[r].camera);
            st.reference_lists.append(&samples);
            st.reference_first_ray.push(st.reference_lists.num_rays);
        }
        st
    }

    /// Caches the sample lists, then builds the template (Ref-NPR) or the
    /// style features (ARF) and every view's guide; also the fraction of
    /// relu5 positions the colour loss supervises.
    pub fn guidance(
        &mut self,
        styles: &[Image],
        keep_content: bool,
        colour: bool,
        progress: &dyn Progress,
    ) -> Result<(Guidance, f32)> {
        self.cache_samples();
        let (template, style_bank) = match self.job.method {
            Method::RefNpr => (Some(self.template(styles)?), None),
            Method::Arf => {
                let style = match self.cfg.arf.half_resolution {
                    true => arf_style_at_half_resolution(&styles[0], &self.dataset.train[0].camera),
                    false => styles[0].clone(),
                };
                let (raw, _) = tcm::image_features(&self.vgg, &style, &self.ad, &[&RELU3], false)?;
                (None, Some(raw.into_iter().next().expect("one block")))
            }
        };
        let (guides, matched) = self.guides(template.as_ref(), keep_content, colour, progress)?;
        Ok((Guidance { template, style_bank, guides }, matched))
    }

    /// The image epochs, one `image_step` per training view in a seeded
    /// order; the last `smooth_fraction` of them (Ref-NPR) are the smooth
    /// content update, where the stylized field becomes the content
    /// generator. Returns the seconds of the image epochs and of the smooth update.
    /// A resumed run passes the image steps already done as `start`.
    pub fn image_epochs(
        &mut self,
        styles: &[Image],
        mut guidance: Guidance,
        start: usize,
        progress: &dyn Progress,
    ) -> Result<EpochCosts> {
        let s = &self.cfg.schedule;
        let views = self.dataset.train.len();
        let total_steps = s.image_epochs * views;
        let smooth_epochs = if self.job.method == Method::RefNpr && self.cfg.ablation.smooth_update {
            (s.image_epochs as f32 * s.smooth_fraction).round() as usize
        } else {
            0
        };
        let smooth_start = s.image_epochs - smooth_epochs.min(s.image_epochs);
        if !self.cfg.optim.keep_state && start == 0 {
            self.field.reset_optimiser();
        }
        let started = std::time::Instant::now();
        let mut smooth_started = None;
        // Per-step traffic, the smooth update's guides (content renders) apart.
        let (mut image_moved, mut smooth_moved, mut guides_moved) =
            (Transfers::default(), Transfers::default(), Transfers::default());
        progress.event(Event::Start { phase: Phase::ImageEpochs, done: start, total: total_steps });
        let mut step = 0;
        for epoch in 0..s.image_epochs {
            let smooth = epoch >= smooth_start;
            if smooth && smooth_started.is_none() {
                smooth_started = Some(std::time::Instant::now());
                self.finish_profile("image_epochs");
                // Resumed past this point: the guides come from the field as it was here.
                let now = match (&self.smooth_sh, step < start) {
                    (Some(then), true) => {
                        let then = self.sh_tensor(then);
                        Some(std::mem::replace(&mut self.field.grid.sh, then))
                    }
                    _ => None,
                };
                let m = transfer::measure(|| -> Result<_> {
                    let t = self.template(styles)?;
                    Ok((self.guides(Some(&t), false, false, progress)?.0, t))
                });
                let (guides, t) = m.value?;
                (guidance.guides, guidance.template, guides_moved) = (guides, Some(t), m.moved);
                match now {
                    Some(now) => self.field.grid.sh = now,
                    None => self.smooth_sh = Some(to_vec(self.field.grid.sh.clone())),
                }
            }
            let mut order: Vec<usize> = (0..views).collect();
            order.shuffle(&mut epoch_rng(self.cfg.seed, epoch));
            for v in order {
                if step < start {
                    step += 1;
                    continue;
                }
                let m = transfer::measure(|| self.image_step(v, step, total_steps, &guidance, smooth));
                let (mut point, moved) = (m.value?, m.moved);
                point.seconds = m.seconds as f32;
                diverged::check_loss(point.total, Phase::ImageEpochs, step + 1, || self.what_is_kept())?;
                if smooth {
                    smooth_moved = smooth_moved.plus(moved);
                } else {
                    image_moved = image_moved.plus(moved);
                }
                let message = format!(
                    "epoch {}/{} {:?} | total {:.4} ref {:.4} feat {:.4} colour {:.4}",
                    epoch + 1,
                    s.image_epochs,
                    point.phase,
                    point.total,
                    point.reference,
                    point.feature,
                    point.colour
                );
                progress.event(Event::Step { phase: Phase::ImageEpochs, done: step + 1, total: total_steps, message });
                self.curve.push(point);
                step += 1;
                let every = self.cfg.schedule.checkpoint_every;
                if every > 0 && step.is_multiple_of(every) && step < total_steps {
                    self.save_resume_point(step)?;
                }
            }
        }
        let smooth_secs = smooth_started.map(|t| t.elapsed().as_secs_f64()).unwrap_or(0.0);
        self.finish_profile(if smooth_started.is_some() { "smooth_update" } else { "image_epochs" });
        Ok(EpochCosts {
            image_seconds: started.elapsed().as_secs_f64() - smooth_secs,
            smooth_seconds: smooth_secs,
            image_steps: PhaseTransfers::new(image_moved, smooth_start * views),
            smooth_steps: PhaseTransfers::new(smooth_moved, (s.image_epochs - smooth_start) * views),
            smooth_guides: PhaseTransfers::new(guides_moved, 0),
        })
    }

    /// Files the step profile of the phase that just ended under `phase`.
    fn finish_profile(&mut self, phase: &str) {
        let parts = self.profile.parts();
        self.profile.clear();
        if !parts.is_empty() {
            self.step_profiles.insert(phase.to_string(), parts);
        }
    }

    /// What a diverged run leaves: its checkpoint is written only at its
    /// end; its last resume point, if any, is good.
    fn what_is_kept(&self) -> String {
        let out = &self.job.out;
        match self.saved_at {
            Some(k) => format!(
                "the last resume point, {} (image step {k}), is kept: `--resume` continues from it",
                resume::path(out).display()
            ),
            None => format!("nothing was written to {}", out.join(checkpoint::CHECKPOINT_FILE).display()),
        }
    }

    /// The refit is over: its field is kept (the guides are built from it)
    /// and the first resume point written.
    pub fn finish_refit(&mut self) -> Result<()> {
        self.refit_sh = to_vec(self.field.grid.sh.clone());
        self.save_resume_point(0)
    }

    /// Writes `OUT/resume.bin` after `image_steps` image steps; refuses a
    /// field that is not finite (a resume point must be good).
    fn save_resume_point(&mut self, image_steps: usize) -> Result<()> {
        let state = ResumeState {
            job: JobKey::of(self.job),
            refit_sh: self.refit_sh.clone(),
            smooth_sh: self.smooth_sh.clone(),
            sh: to_vec(self.field.grid.sh.clone()),
            rms: to_vec(self.field.rms()),
            image_steps,
            optimiser_steps: self.optimiser_steps,
            curve: self.curve.clone(),
        };
        if let Some(what) = diverged::first_non_finite(&[("SH colour", &state.sh), ("RMSprop state", &state.rms)]) {
            bail!(
                "the field's {what} holds NaN or infinite values after image step {image_steps}; {}",
                self.what_is_kept()
            );
        }
        state.save(&self.job.out)?;
        self.saved_at = Some(image_steps);
        Ok(())
    }

    /// A resumed run: the field as the refit left it (to rebuild the first
    /// guides from).
    pub fn start_from_refit(&mut self, state: &ResumeState) -> Result<()> {
        let rows = self.field.grid.num_rows();
        if state.refit_sh.len() != rows * 3 || state.sh.len() != rows * 3 || state.rms.len() != rows * 3 {
            bail!("{} does not fit this photoreal run's grid", resume::path(&self.job.out).display());
        }
        self.refit_sh = state.refit_sh.clone();
        self.field.grid.sh = self.sh_tensor(&state.refit_sh);
        Ok(())
    }

    /// A resumed run, once its first guides are built: the field, optimiser
    /// state, step count and curve as the killed run left them.
    pub fn restore(&mut self, state: ResumeState) {
        self.field.grid.sh = self.sh_tensor(&state.sh);
        self.field.set_rms(self.sh_tensor(&state.rms));
        self.smooth_sh = state.smooth_sh;
        self.optimiser_steps = state.optimiser_steps;
        self.curve = state.curve;
        self.saved_at = Some(state.image_steps);
    }

    fn sh_tensor(&self, values: &[f32]) -> Tensor<2> {
        floats(values.to_vec(), [values.len() / 3, 3], &self.field.grid.device())
    }

    /// One image step on training view `v`: the image losses by deferred
    /// back-propagation, L_ref on a batch of pseudo-rays (Ref-NPR), SH TV,
    /// one RMSprop step on the rows the step touches (or on all rows).
    fn image_step(
        &mut self,
        v: usize,
        step: usize,
        total_steps: usize,
        guidance: &Guidance,
        smooth: bool,
    ) -> Result<CurvePoint> {
        let s = &self.cfg.schedule;
        let mut rng = step_rng(self.cfg.seed, Stream::ImageStep, step);
        let samples = self.profile.time("view_samples", || self.view_samples(v));
        let (pseudo, tv, rows) = self.profile.time("step_rows", || {
            let pseudo = if self.job.method == Method::RefNpr { self.pseudo_ray_batch(&mut rng) } else { Vec::new() };
            let tv = self.field.tv_rows(&self.sh_tv(), &mut rng);
            let cells: Vec<&[u32]> =
                std::iter::once(&samples.cell_keys[..]).chain(pseudo.iter().flat_map(PseudoRays::cells)).collect();
            let rows = self.field.step_rows(self.cfg.optim.sparse, &cells, &tv);
            (pseudo, tv, rows)
        });
        // The grid as host numbers, read once for the step's fused ray passes (`ray_kernel`).
        let host_sh = self.host_kernel().then(|| self.profile.time("image_render", || self.host_sh()));
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
        let grad = self.profile.time("sh_tv", || self.field.add_tv_gradient(grad, &self.sh_tv(), &tv, &rows));
        let lr = self.learning_rate(log_lerp(s.lr, s.lr_final, step as f32 / total_steps.max(1) as f32));
        let started = std::time::Instant::now();
        self.optimiser_step(grad, rows, lr);
        self.profile.add("optimiser", started.elapsed().as_secs_f64());
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

    fn sh_tv(&self) -> ShTv {
        let l = &self.cfg.loss;
        ShTv {
            weight: l.tv_sh,
            fraction: l.tv_fraction,
            per_voxel: l.tv_sh_per_voxel,
            per_channel: l.tv_sh_per_channel,
        }
    }

    fn optimiser_step(&mut self, grad: Tensor<2>, rows: StepRows, lr: f32) {
        let s = &self.cfg.schedule;
        let opt = Rmsprop { beta: s.rmsprop_beta, eps: s.eps, start: self.cfg.optim.rms_init };
        let host = self.host_kernel();
        self.field.rmsprop(grad, rows, lr, opt, host);
        self.optimiser_steps += 1;
    }

    fn view_samples(&self, v: usize) -> Cow<'_, FrozenSamples> {
        match &self.view_samples[v] {
            Some(s) => Cow::Borrowed(s),
            None => Cow::Owned(self.march_camera(&self.dataset.train[v].camera)),
        }
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
    fn march_rays_within(&self, rays: &[Ray], budget: usize) -> Option<FrozenSamples> {
        let marcher = Marcher::with_occupancy(&self.field.grid, &self.occupancy);
        FrozenSamples::march_within(
            &marcher,
            rays,
            &self.march,
            self.cfg.min_sample_weight,
            frozen::MARCH_CHUNK,
            budget,
        )
    }

    fn march_rays(&self, rays: &[Ray]) -> FrozenSamples {
        self.march_rays_within(rays, usize::MAX).expect("an unbounded march always fits")
    }

    pub fn march_camera(&self, camera: &Camera) -> FrozenSamples {
        self.march_rays(&camera.rays(self.ndc.as_ref()))
    }

    fn render_view(&self, v: usize) -> Image {
        let rgb =
            frozen::render_plain(&self.field.grid.sh, &self.view_samples(v), self.background, self.cfg.render_chunk);
        Image::of_camera(&self.dataset.train[v].camera, rgb)
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

    /// How the stylized field is marched (the photoreal run's, with this
    /// stylization's `colour_corners`).
    pub fn march(&self) -> MarchParams {
        self.march
    }

    pub fn num_references(&self) -> usize {
        self.reference_first_ray.len() - 1
    }

    /// The sample lists of reference `r`.
    fn reference_samples(&self, r: usize) -> FrozenSamples {
        let first = self.reference_first_ray[r];
        self.reference_lists.range(first, self.reference_first_ray[r + 1] - first)
    }

    pub fn render_reference(&self, r: usize) -> Image {
        let samples = self.reference_samples(r);
        let rgb = frozen::render_plain(&self.field.grid.sh, &samples, self.background, self.cfg.render_chunk);
        Image::of_camera(&self.registration.references[r].camera, rgb)
    }

    /// Ray epochs: refit the degree-0 colour to the photos (MSE, SH TV);
    /// ARF: to the recoloured photos.
    pub fn refit(&mut self, progress: &dyn Progress) -> Result<()> {
        let mut colours: Vec<[f32; 3]> =
            self.dataset.train.iter().flat_map(|v| crate::util::image::pixels(&v.rgb)).collect();
        if let Some(tf) = &self.colour_transfer {
            // Background pixels stay: rays that miss the scene render the
            // fixed background colour, and a recoloured target there could
            // never be fitted (lego: 70 % of the pixels).
            colours.iter_mut().filter(|c| !is_background(c, self.background)).for_each(|c| *c = tf.apply(*c));
        }
        // The refit's rays are training pixels: with the views' lists cached
        // first, a step copies its rays' lists instead of marching them.
        self.cache_samples();
        let s = &self.cfg.schedule;
        let steps = (s.ray_epochs as f64 * colours.len() as f64 / s.ray_batch as f64).ceil() as usize;
        progress.event(Event::Start { phase: Phase::Refit, done: 0, total: steps });
        if !self.cfg.optim.keep_state {
            self.field.reset_optimiser();
        }
        for step in 0..steps {
            let started = std::time::Instant::now();
            let mse = self.refit_step(step, &colours);
            diverged::check_loss(mse, Phase::Refit, step + 1, || self.what_is_kept())?;
            let message = format!("mse {mse:.5} psnr {:.2}", psnr_from_mse(mse));
            progress.event(Event::Step { phase: Phase::Refit, done: step + 1, total: steps, message });
            self.curve.push(CurvePoint { seconds: started.elapsed().as_secs_f32(), ..CurvePoint::refit(step, mse) });
        }
        self.finish_profile("refit");
        Ok(())
    }

    /// One refit step: a seeded batch of training pixels (`colours`, their
    /// targets, views one after another), their MSE gradient plus SH TV,
    /// one RMSprop step. Returns the batch's MSE.
    fn refit_step(&mut self, step: usize, colours: &[[f32; 3]]) -> f32 {
        let s = &self.cfg.schedule;
        let mut rng = step_rng(self.cfg.seed, Stream::Refit, step);
        let picks: Vec<usize> = (0..s.ray_batch).map(|_| rng.random_range(0..colours.len())).collect();
        let target: Vec<f32> = picks.iter().flat_map(|&i| colours[i]).collect();
        let samples = self.profile.time("sample_lists", || {
            let pixels: Vec<(usize, usize)> = picks.iter().map(|&i| self.view_pixel(i)).collect();
            self.pixel_lists(&pixels)
        });
        let (tv, rows) = self.profile.time("step_rows", || {
            let tv = self.field.tv_rows(&self.sh_tv(), &mut rng);
            let rows = self.field.step_rows(self.cfg.optim.sparse, &[&samples.cell_keys], &tv);
            (tv, rows)
        });
        let (grad, mse) = self.profile.time("photo_loss", || match self.host_kernel() {
            true => self.host_mse_gradient(&self.host_sh(), &samples, None, &target, &rows, 1.0),
            false => {
                let target = floats(target, [picks.len(), 3], &self.device);
                self.mse_gradient(RaySet::Host(&samples), &rows, target, 1.0)
            }
        });
        let grad = self.profile.time("sh_tv", || self.field.add_tv_gradient(grad, &self.sh_tv(), &tv, &rows));
        let lr = self.learning_rate(s.lr_refit);
        let started = std::time::Instant::now();
        self.optimiser_step(grad, rows, lr);
        self.profile.add("optimiser", started.elapsed().as_secs_f64());
        mse
    }

    /// Whether the ray losses run on `field::host_colour` (`ray_kernel`).
    fn host_kernel(&self) -> bool {
        self.cfg.ray_kernel.is_host(&self.device)
    }

    /// The SH grid as host numbers (for `field::host_colour`).
    fn host_sh(&self) -> Vec<f32> {
        to_vec(self.field.grid.sh.clone())
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
            RaySet::Gathered(lists, picks) => {
                gathered_gradient(sh, lists.gather_chunks(picks, chunk), self.background, rows, &loss_of)
            }
        };
        (grad, value.into_inner().map_or(0.0, scalar))
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
    fn cache_samples(&mut self) {
        if std::mem::replace(&mut self.samples_cached, true) {
            return;
        }
        // Each march gives up as soon as it would overrun what is left of the
        // budget, so memory never holds more than the budget plus one chunk.
        let budget = self.cfg.sample_cache_mb * 1024 * 1024;
        let mut used = 0usize;
        let on_device = match self.cfg.samples_on_device {
            Placement::Auto => !is_host_memory(&self.device),
            Placement::Device => true,
            Placement::Host => false,
        };
        let wants_registered = on_device && self.job.method == Method::RefNpr && !self.registered.is_empty();
        let views = self.dataset.train.len();
        let registered_share = self.cfg.loss.registered_rays as f64 / self.registered.len().max(1) as f64;
        let registered_first = registered_share >= 1.0 / views.max(1) as f64;
        if wants_registered && registered_first {
            self.cache_registered(budget, &mut used);
        }
        for v in 0..views {
            let samples = self.march_rays_within(&self.dataset.train[v].camera.rays(self.ndc.as_ref()), budget - used);
            used += samples.as_ref().map_or(0, FrozenSamples::bytes);
            self.view_samples[v] = samples;
        }
        if wants_registered && !registered_first {
            self.cache_registered(budget, &mut used);
        }
        if on_device {
            let upload = |s: &FrozenSamples| DeviceSamples::upload(s, &self.device);
            self.views_on_device = self.view_samples.iter().map(|s| s.as_ref().map(upload)).collect();
            if self.job.method == Method::RefNpr {
                self.reference_on_device = Some(upload(&self.reference_lists));
                self.registered_on_device = self.registered_samples.as_ref().map(upload);
            }
        }
    }

    /// What the sample cache holds (after `guidance`).
    pub fn sample_cache_report(&self) -> SampleCacheReport {
        let cached: Vec<&FrozenSamples> =
            self.view_samples.iter().flatten().chain(self.registered_samples.as_ref()).collect();
        SampleCacheReport {
            budget_mb: self.cfg.sample_cache_mb,
            views_cached: self.view_samples.iter().flatten().count(),
            views: self.view_samples.len(),
            registered_cached: self.registered_samples.is_some(),
            mb: cached.iter().map(|s| s.bytes()).sum::<usize>() as f64 / (1024.0 * 1024.0),
            samples: cached.iter().map(|s| s.num_samples()).sum(),
            cells: cached.iter().map(|s| s.num_cells()).sum(),
        }
    }

    /// Caches the registered pixels' sample lists when they fit in what is
    /// left of `budget` (`used` bytes taken).
    fn cache_registered(&mut self, budget: usize, used: &mut usize) {
        let rays: Vec<Ray> = self.registered.iter().map(|p| self.pixel_ray(p.0 as usize, p.1 as usize)).collect();
        self.registered_samples = self.march_rays_within(&rays, budget - *used);
        *used += self.registered_samples.as_ref().map_or(0, FrozenSamples::bytes);
    }

    /// A step's pseudo-rays for L_ref: a batch of reference pixels and a
    /// batch of registered pixels, each with its target colours (none when
    /// L_ref is off).
    fn pseudo_ray_batch(&self, rng: &mut ChaCha8Rng) -> Vec<PseudoRays<'_>> {
        let l = &self.cfg.loss;
        if !self.cfg.ablation.use_reference_loss || l.reference <= 0.0 {
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
        if !self.cfg.ablation.reference_rays_only && !self.registered.is_empty() && l.registered_rays > 0 {
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
                    let lists = self.registered_lists(&picks);
                    let rays = (0..lists.num_rays).collect();
                    PseudoRays { lists: Cow::Owned(lists), on_device: None, rays, target }
                }
            });
        }
        groups
    }

    /// The sample lists of the registered pixels `picks`, in that order.
    fn registered_lists(&self, picks: &[usize]) -> FrozenSamples {
        let pixels: Vec<(usize, usize)> =
            picks.iter().map(|&i| (self.registered[i].0 as usize, self.registered[i].1 as usize)).collect();
        self.pixel_lists(&pixels)
    }

    /// The sample lists of training pixels `(view, pixel)`, in that order:
    /// copied from the view's cached lists (the very samples a march of the
    /// pixel's ray gives: the view's lists are of the same rays), marched
    /// only for views the cache does not hold.
    fn pixel_lists(&self, pixels: &[(usize, usize)]) -> FrozenSamples {
        let uncached: Vec<Ray> = pixels
            .iter()
            .filter(|&&(v, _)| self.view_samples[v].is_none())
            .map(|&(v, p)| self.pixel_ray(v, p))
            .collect();
        let marched = self.march_rays(&uncached);
        // Where each pixel's lists are: its view's ray, or the next marched one.
        let mut next_marched = 0;
        let sources: Vec<(&FrozenSamples, usize)> = pixels
            .iter()
            .map(|&(v, p)| match &self.view_samples[v] {
                Some(view) => (view, p),
                None => {
                    next_marched += 1;
                    (&marched, next_marched - 1)
                }
            })
            .collect();
        // Copied in parallel pieces (random reads across the views' lists),
        // appended in order: the same lists as one serial copy.
        let (lattice, corners) = (CellLattice::of(&self.field.grid), self.march.colour_corners);
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
        let gathered: Option<Vec<_>> = self.views_on_device[v].as_ref().map(|lists| {
            let all: Vec<usize> = (0..samples.num_rays).collect();
            lists.gather_chunks(&all, self.cfg.render_chunk).collect()
        });
        let uploaded = match gathered {
            Some(_) => Vec::new(),
            None => DeviceChunk::upload_all(samples, self.cfg.render_chunk, sh),
        };
        let rgb = match &gathered {
            Some(chunks) => render_gathered(sh, chunks, self.background),
            None => render_chunks(sh, &uploaded, self.background),
        };
        self.profile.add("image_render", started.elapsed().as_secs_f64());
        // 2. Image losses on a leaf image, gradient with respect to the image.
        let started = std::time::Instant::now();
        let image = planar_image(rgb, w, h).autodiff().require_grad();
        let (loss, parts) = self.image_loss(image.clone(), guide, template, style_bank, smooth)?;
        let grads = loss.backward();
        let Some(g) = image.grad(&grads) else { bail!("the image losses do not depend on the image") };
        let g = interleaved(g);
        self.profile.add("image_losses_vgg", started.elapsed().as_secs_f64());
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
        self.profile.add("image_losses_vgg", started.elapsed().as_secs_f64());
        let (grad, _) = self.profile.time("image_rerender_grad", || {
            host_colour::colour_gradient(sh, samples, None, self.background, rows.len(), &rows.slot_fn(), |k, _| {
                ([g[k * 3], g[k * 3 + 1], g[k * 3 + 2]], 0.0)
            })
        });
        Ok((floats(grad, [rows.len(), 3], &self.device), parts))
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
                        if content_weight > 0.0 && b < guide.content.len() {
                            let c = losses::content_loss(r, guide.content[b].tensor());
                            accumulate(&mut parts.content, &c);
                            total = total + c * (weight * content_weight);
                        }
                    }
                }
                if let (Some(c), false) = (&guide.colour, smooth) {
                    let patches = losses::patch_means(image, tcm::COLOUR_PATCH);
                    let mask = match l.colour_white_on {
                        WhiteOn::Content => c.mask.clone(),
                        WhiteOn::Render => c.mask.clone() * losses::not_white(patches.clone().detach(), l.colour_white),
                    };
                    let loss = losses::colour_loss(patches, c.target.clone(), mask, l.colour_norm);
                    accumulate(&mut parts.colour, &loss);
                    total = total + loss * l.colour;
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
                if let (true, Some(content)) = (a.content > 0.0, guide.content.first()) {
                    let c = losses::content_loss(render, content.tensor());
                    accumulate(&mut parts.content, &c);
                    total = total + c * a.content;
                }
            }
        }
        let parts = parts.read(&total);
        Ok((total, parts))
    }

    /// Content renders, features, TCM matches and colour targets of every view.
    pub fn guides(
        &self,
        template: Option<&Template>,
        keep_content: bool,
        colour: bool,
        progress: &dyn Progress,
    ) -> Result<(Vec<ViewGuide>, f32)> {
        let blocks: Vec<&[VggLayer]> = match self.job.method {
            Method::RefNpr => FEATURE_BLOCKS.to_vec(),
            Method::Arf => vec![&RELU3],
        };
        let n = self.dataset.train.len();
        progress.event(Event::Start { phase: Phase::Guides, done: 0, total: n });
        let mut out = Vec::with_capacity(n);
        let mut matched = 0.0;
        let half = self.job.method == Method::Arf && self.cfg.arf.half_resolution;
        let half_content = self.cfg.half_content_features && is_host_memory(&self.device);
        for v in 0..n {
            let content = self.render_view(v);
            let halved;
            let vgg_input = if half {
                halved = content.half();
                &halved
            } else {
                &content
            };
            let (raw, colour_desc) = tcm::image_features(&self.vgg, vgg_input, &self.ad, &blocks, colour)?;
            let matches = template.map(|t| t.matches(&raw, self.cfg.search_chunk)).unwrap_or_default();
            let colour = match (template, colour_desc) {
                (Some(t), Some(d)) => {
                    let l = &self.cfg.loss;
                    let white = (l.colour_white_on == WhiteOn::Content).then_some(l.colour_white);
                    let c = t.colour_targets(d, &content, l.colour_max_distance, white, self.cfg.search_chunk);
                    matched += c.matched_fraction / n as f32;
                    Some(c)
                }
                _ => None,
            };
            let content = if keep_content {
                raw.into_iter().map(|features| StoredFeatures::store(features, half_content)).collect()
            } else {
                Vec::new()
            };
            out.push(ViewGuide { content, matches, colour });
            progress.event(Event::Step { phase: Phase::Guides, done: v + 1, total: n, message: String::new() });
        }
        Ok((out, matched))
    }

    pub fn template(&self, styles: &[Image]) -> Result<Template> {
        let pairs: Vec<ReferencePair> = styles
            .iter()
            .enumerate()
            .map(|(r, s)| ReferencePair { content: self.render_reference(r), style: s.clone() })
            .collect();
        Template::build(&self.vgg, &pairs, &self.ad)
    }
}

/// ARF's style image at the released code's scale: resized so its long side
/// is the views' long side, then halved (the renders VGG sees are halved too).
fn arf_style_at_half_resolution(style: &Image, view: &Camera) -> Image {
    let long_side = view.intrinsics.width.max(view.intrinsics.height) as f32;
    let scale = long_side / style.width.max(style.height) as f32;
    let (w, h) = ((style.width as f32 * scale).round() as usize, (style.height as f32 * scale).round() as usize);
    let sized = if (w, h) == (style.width, style.height) { style.clone() } else { style.resized(w, h) };
    sized.half()
}
