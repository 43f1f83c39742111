//! Ref-NPR stylization (paper sections 3.3-3.4) and the ARF baseline.
//!
//! From a photoreal run and a reference case to a stylized grid:
//! 1. R³ registers the reference(s) on the training views (or `--registration`
//!    reads what `refnpr register` wrote);
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
//! in plain Rust (`field::frozen`); the differentiable part is only colour.
//!
//! Modules: `config` (the TOML settings), `losses`, `tcm` (template
//! correspondence and colour targets), `colour_transfer` (ARF's
//! preprocessing), `styles` (reading style images), `far` (the far
//! background painted and recoloured from the references), `field` (the style
//! field, its optimiser and chunked gradients), `samples` (the rays the
//! losses draw from and their frozen sample lists), `step` (one image step,
//! one refit step), `guides` (content renders, TCM matches, colour targets),
//! `outputs` (the checkpoint and renders a run ends with), `region` (local edits: the painted pixels, the voxels they make, the
//! photoreal field kept elsewhere), `strokes` (the paintings' strokes at another scale), `run` (`refnpr stylize` from files to
//! files: the loops, resume points and phase costs).

pub mod budget;
pub(crate) mod coarse;
pub mod colour_map;
pub mod colour_transfer;
pub mod config;
pub mod far;
pub mod field;
pub(crate) mod guides;
pub(crate) mod inputs;
pub mod losses;
pub(crate) mod outputs;
pub(crate) mod recolouring;
pub mod region;
pub mod resume;
pub mod run;
pub(crate) mod samples;
pub(crate) mod step;
pub(crate) mod strokes;
pub mod styles;
pub mod tcm;

use std::collections::BTreeMap;
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::stylize::colour_transfer::ColourTransfer;
use crate::stylize::config::StylizeConfig;
use crate::stylize::tcm::{FEATURE_BLOCKS, RELU3};
use crate::util::backend::BackendKind;
use crate::vgg::VggLayer;

/// Which stylization.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Ref-NPR: R³ + TCM + colour matching.
    #[value(name = "refnpr", alias = "ref-npr")]
    RefNpr,
    /// ARF: nearest-neighbour feature matching to a style image.
    Arf,
}

impl Method {
    /// The VGG16 layers whose features the method compares, by block: Ref-NPR's
    /// feature blocks (relu3, relu4), ARF's relu3.
    pub fn feature_blocks(self) -> Vec<&'static [VggLayer]> {
        match self {
            Method::RefNpr => FEATURE_BLOCKS.to_vec(),
            Method::Arf => vec![&RELU3],
        }
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        use clap::ValueEnum;
        f.write_str(self.to_possible_value().expect("no skipped variants").get_name())
    }
}

/// What `refnpr stylize` is asked to do.
#[derive(Debug, Clone)]
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
    /// A `refnpr register` output (folder or `registration.bin`) to use
    /// instead of registering again.
    pub registration: Option<PathBuf>,
    /// Render the test views of the result into `out/test`.
    pub render_test: bool,
    /// Continue a killed run from `out/resume.bin` when it is there.
    pub resume: bool,
}

impl StylizeJob {
    /// Epochs of the smooth content update (Ref-NPR with it on; ARF none).
    pub fn smooth_epochs(&self) -> usize {
        let s = &self.config.schedule;
        match self.method == Method::RefNpr && self.config.ablation.smooth_update {
            true => (s.image_epochs as f32 * s.smooth_fraction).round() as usize,
            false => 0,
        }
    }

    /// What the run's time scales with, for its estimate: the training
    /// pixels times the epochs (refit and image), the epochs before the
    /// smooth update counted at the coarse views' pixels under
    /// `schedule.coarse_scale` (1/n² of the views' own).
    pub fn work_units(&self, train_pixels: f64) -> f64 {
        let s = &self.config.schedule;
        let smooth = self.smooth_epochs().min(s.image_epochs);
        let coarse = s.ray_epochs as f64 + (s.image_epochs - smooth) as f64;
        let n = s.coarse_scale.max(1) as f64;
        train_pixels * (coarse / (n * n) + smooth as f64)
    }
}

/// Which phase a logged step belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StepKind {
    Refit,
    Image,
    Smooth,
}

/// One logged optimisation step.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CurvePoint {
    pub phase: StepKind,
    pub step: usize,
    pub total: f32,
    /// L_ref (refit: the photo MSE).
    pub reference: f32,
    /// L_feat (ARF: NNFM).
    pub feature: f32,
    pub colour: f32,
    pub content: f32,
    pub image_tv: f32,
    /// Wall seconds the step took.
    #[serde(default)]
    pub seconds: f32,
}

impl CurvePoint {
    /// A step of the colour refit, with its photo MSE.
    pub fn refit(step: usize, mse: f32) -> Self {
        Self {
            phase: StepKind::Refit,
            step,
            total: mse,
            reference: mse,
            feature: 0.0,
            colour: 0.0,
            content: 0.0,
            image_tv: 0.0,
            seconds: 0.0,
        }
    }
}

/// What the stylization's sample cache holds: which lists fit in
/// `sample_cache_mb` (the others are marched in each step that needs them).
#[derive(Debug, Clone, Default, Serialize)]
pub struct SampleCacheReport {
    pub budget_mb: usize,
    pub views_cached: usize,
    pub views: usize,
    /// Whether the registered pixels' lists are cached (Ref-NPR with L_ref).
    pub registered_cached: bool,
    /// Bytes of the cached lists, their samples and their cells (samples
    /// of one ray in one lattice cell share a cell entry).
    pub mb: f64,
    pub samples: usize,
    pub cells: usize,
}

/// What a stylization holds from step to step when a phase ends, by part
/// (MB): where its memory goes besides each step's own working set and
/// what the allocator keeps (`memory` beside it has the process's figures).
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct HeldMemory {
    /// The dataset's photos (training, validation and test views, f32 RGB).
    pub photos_mb: f64,
    /// R³'s registered pixels and the reference pixels.
    pub registration_mb: f64,
    /// Sample lists on the host (`sample_cache_mb` bounds the training views').
    pub sample_lists_mb: f64,
    /// The grid being stylized, its optimiser state and TV neighbours.
    pub field_mb: f64,
    /// The guides: content features, TCM matches and colour targets of
    /// every view, the template.
    pub guides_mb: f64,
}

impl HeldMemory {
    /// One line: each part in MB.
    pub fn describe(&self) -> String {
        format!(
            "held: photos {:.0} MB, registration {:.0} MB, sample lists {:.0} MB, field {:.0} MB, guides {:.0} MB",
            self.photos_mb, self.registration_mb, self.sample_lists_mb, self.field_mb, self.guides_mb
        )
    }
}

/// The references' colour map in `stylize.json`.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct ColourMapReport {
    /// Reference pixels it was fitted on.
    pub pixels: usize,
    /// `ColourMap::explained`: over the image the reference was painted
    /// over where the case keeps it (content.png), else over the refit
    /// render's reference pixels.
    pub explained: f32,
    /// What `explained` was measured on: `content.png` or `the refit render`.
    pub explained_on: &'static str,
    /// At least `[colour_map] recolour_explained`: the map was fitted again
    /// with the recolouring's settings and L_color took its weight and patches.
    pub recolouring: bool,
}

/// A local edit's extent: painted pixels per reference, edited voxels.
#[derive(Debug, Clone, Serialize)]
pub struct LocalEditReport {
    pub painted_pixels: Vec<usize>,
    /// Edited voxels a reference sees, and those TCM gave the edit.
    pub seen_voxels: usize,
    pub matched_voxels: usize,
    pub voxels: usize,
}

/// `STYLE_RUN/stylize.json`.
#[derive(Debug, Clone, Serialize)]
pub struct StylizeReport {
    pub method: Method,
    pub backend: String,
    pub photo: PathBuf,
    pub case: PathBuf,
    pub config: StylizeConfig,
    /// The `refnpr register` output used instead of registering again.
    pub registration: Option<PathBuf>,
    pub views: usize,
    pub image_size: [usize; 2],
    pub registered_pixels: usize,
    pub registered_fraction: f32,
    pub colour_matched_fraction: f32,
    /// Ref-NPR with `[colour_map]` on: the references' colour map, how much
    /// of the painting it explains, and whether that made it a recolouring.
    pub colour_map: Option<ColourMapReport>,
    /// ARF: the affine recolouring applied to the photos before the refit.
    pub colour_transfer: Option<ColourTransfer>,
    /// ARF with `arf.post_transfer`: the recolouring applied to the field after the image epochs.
    pub post_colour_transfer: Option<ColourTransfer>,
    /// Seconds per phase: registration, refit, content (renders, features, TCM), image_epochs, smooth_update.
    pub seconds: BTreeMap<String, f64>,
    /// Host-device traffic per phase (`util::transfer`): the same phases,
    /// per step where a phase has steps, and the smooth update's new guides apart.
    pub transfers: BTreeMap<String, crate::util::transfer::PhaseTransfers>,
    /// Where each phase's steps spent their time (`util::profile`): wall
    /// seconds per part, summed over the phase's steps.
    pub step_profiles: BTreeMap<String, Vec<crate::util::profile::PartTime>>,
    pub total_seconds: f64,
    pub peak_rss_mb: Option<f64>,
    /// Resident and peak memory when each phase ended (registration,
    /// refit, content, image_epochs: the image epochs and the smooth update).
    pub memory: BTreeMap<String, crate::util::memory::MemoryNow>,
    /// The memory budget's plan (None where the OS gives no memory figures).
    pub memory_plan: Option<budget::MemoryPlan>,
    /// What the run held when each phase ended, by part.
    pub held: BTreeMap<String, HeldMemory>,
    /// What the sample cache (`sample_cache_mb`) holds.
    pub sample_cache: SampleCacheReport,
    /// A local edit (`stylize::region`): the voxels it changed.
    pub local_edit: Option<LocalEditReport>,
    pub final_losses: Option<CurvePoint>,
    pub curve: Vec<CurvePoint>,
    pub warnings: Vec<String>,
}
