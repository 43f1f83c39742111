//! `refnpr stylize` settings: TOML with a default for every field (the
//! defaults are `configs/stylize.toml`); unknown keys and out-of-range values
//! are errors naming the file.

use anyhow::{Context, Result, ensure};
use serde::{Deserialize, Serialize};
use std::path::Path;

use crate::field::march::ColourCorners;
use crate::field::optim::RmsStart;
use crate::reference::r3::RegisterParams;
use crate::util::config;
use crate::vgg::VggWeights;

/// How the SH learning rate moves over a stylization.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LrSchedule {
    /// The refit at `lr_refit`; the image epochs decay from `lr` to `lr_final` over their own steps.
    PerPhase,
    /// One exponential decay from `lr` to `lr_final` over `lr_decay_steps`
    /// optimiser steps, counted from the refit's first step through the
    /// image epochs (the released code: 0.1 -> 0.01 over 250,000 steps).
    Shared,
}

impl LrSchedule {
    /// The name the config file gives it.
    pub fn name(self) -> &'static str {
        match self {
            LrSchedule::PerPhase => "per_phase",
            LrSchedule::Shared => "shared",
        }
    }
}

/// Where the cached sample lists (L_ref's pseudo-rays, the training views)
/// are kept for the image epochs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Placement {
    /// Also on the device when its memory is not the host's (wgpu); else on the host only.
    Auto,
    /// Also on the device, uploaded once; each step's rays are gathered there.
    Device,
    /// On the host only; each step's rays are cut out and uploaded.
    Host,
}

pub use crate::field::RayKernel;

/// What the colour map shrinks a colour towards where the reference shows
/// it in few pixels (`[colour_map] prior_pixels`' worth).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MapPrior {
    /// No change: the photo colour stays.
    Unchanged,
    /// The painting's least-squares affine colour transform (photo colour
    /// and 1 to painted colour, over the reference's scene pixels): a
    /// grade's global part, which holds for colours the reference never
    /// shows too.
    Affine,
}

/// What L_color's squared error is averaged over.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ColourNorm {
    /// Summed over channels, averaged over the supervised positions.
    Matched,
    /// Averaged over channels and over all relu5 positions, the unsupervised
    /// ones counting zero (the released code).
    AllPositions,
}

/// Which patches L_color treats as background (no colour loss).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WhiteOn {
    /// The content render's patch, brighter than `colour_white` in every channel (fixed per view).
    Content,
    /// The current render's patch, its channel mean above `colour_white` (the released code, every step).
    Render,
}

/// Phases and optimiser.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ScheduleConfig {
    /// View-independent colour refit to the photos before stylizing (epochs over all training rays).
    pub ray_epochs: f32,
    /// Rays per refit step.
    pub ray_batch: usize,
    /// RMSprop learning rate of the refit.
    pub lr_refit: f32,
    /// Stylization epochs; one step = one whole training view.
    pub image_epochs: usize,
    /// Fraction of the image epochs (the last ones) run as the smooth content update.
    pub smooth_fraction: f32,
    /// SH learning rate of the image epochs, decaying exponentially to `lr_final`.
    pub lr: f32,
    pub lr_final: f32,
    /// `per_phase` or `shared` (see `LrSchedule`).
    pub lr_schedule: LrSchedule,
    /// Steps of the shared schedule's decay from `lr` to `lr_final`.
    pub lr_decay_steps: usize,
    pub rmsprop_beta: f32,
    pub eps: f32,
    /// Image steps between two writes of `OUT/resume.bin` (0: only after the refit).
    pub checkpoint_every: usize,
    /// Ref-NPR: everything before the smooth update (R³, the refit, the
    /// guides, the image epochs) runs on the training views this many times
    /// smaller, the smooth update on the views at full size (1: all at full
    /// size). Cost follows pixels; the grid does not change with it.
    pub coarse_scale: u32,
    /// With `coarse_scale` > 1: the smooth update's TCM matches are found
    /// on the coarse views (content renders, VGG16 and the nearest-neighbour
    /// search at 1/n² of the pixels) and carried to full size, each
    /// full-size position taking its coarse position's match offset within
    /// its n x n block; false: found again at full size, where the search's
    /// pairs grow with the square of the pixels. On by default: lego 400
    /// and fern 1008x756 kept their Ref-LPIPS within 0.001, their renders
    /// 41.5 and 51.3 dB from matching at full size, in 3/4 of the time
    /// (docs/performance.md).
    pub coarse_matches: bool,
}

impl Default for ScheduleConfig {
    fn default() -> Self {
        Self {
            ray_epochs: 2.0,
            ray_batch: 8192,
            lr_refit: 1e-2,
            image_epochs: 10,
            smooth_fraction: 0.25,
            lr: 0.1,
            lr_final: 0.01,
            lr_schedule: LrSchedule::Shared,
            lr_decay_steps: 250_000,
            rmsprop_beta: 0.95,
            eps: 1e-8,
            checkpoint_every: 50,
            coarse_scale: 1,
            coarse_matches: true,
        }
    }
}

/// Loss weights (λ) and their settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LossConfig {
    /// λ_r: reference loss on R³ pseudo-rays.
    pub reference: f32,
    /// Pseudo-rays per step drawn from the reference view(s) (all of them when fewer).
    pub reference_rays: usize,
    /// Reference pixels whose ray misses the scene are pseudo-rays too (the released code).
    pub reference_misses: bool,
    /// Pseudo-rays per step drawn from the registered pixels of the training views.
    pub registered_rays: usize,
    /// λ_f: TCM feature loss.
    pub feature: f32,
    /// λ': content term of the feature loss (MSE to the content render's features).
    pub content: f32,
    /// λ_c: coarse colour matching (relu5, patch means).
    pub colour: f32,
    /// Colour matches whose cosine distance exceeds this are ignored (released code 0.6, paper 0.4).
    pub colour_max_distance: f32,
    /// Patches brighter than this (see `colour_white_on`) get no colour loss (background).
    pub colour_white: f32,
    /// `content` or `render` (see `WhiteOn`).
    pub colour_white_on: WhiteOn,
    /// `matched` or `all_positions` (see `ColourNorm`).
    pub colour_norm: ColourNorm,
    /// Feature loss weight during the smooth content update (λ' is 0 there).
    pub smooth_feature: f32,
    /// Image total variation on the rendered view.
    pub image_tv: f32,
    /// Total variation on the SH grid, on a random `tv_fraction` of the
    /// voxels per step. Under RMSprop a picked voxel moves at full rate
    /// along whichever gradient dominates it, so this weight says where the
    /// TV wins: at the code's 1e-3 it wins over L_ref on most voxels and
    /// smooths a painting's strokes away (fern at its own camera: LPIPS
    /// 0.455 to the painting, 0.354 at 1e-4, 0.214 at 0); at 1e-4 it still
    /// smooths the voxels no loss speaks for (without it the twin keeps
    /// noise: speckle 13.4 % against its truth's 5.5 %).
    pub tv_sh: f32,
    /// The same during the refit to the photos (code: `tv_sh`). With
    /// RMSprop each picked voxel's TV gradient becomes a full-rate step
    /// however small it is, and on lego it pulls the refit from 24.7 down to
    /// 21.1 dB (without it: up to 29.8 dB).
    pub refit_tv_sh: f32,
    pub tv_fraction: f32,
    /// `tv_sh` weighs each picked voxel's TV (svox2: its gradient is
    /// `tv_sh` x the unit difference direction however many are picked)
    /// instead of the mean over the picked voxels.
    pub tv_sh_per_voxel: bool,
    /// TV per colour channel (svox2) instead of over the three channels together.
    pub tv_sh_per_channel: bool,
}

impl Default for LossConfig {
    fn default() -> Self {
        Self {
            reference: 10.0,
            reference_rays: 50_000,
            reference_misses: false,
            registered_rays: 50_000,
            feature: 1.0,
            content: 5e-3,
            colour: 5.0,
            colour_max_distance: 0.6,
            colour_white: 0.99,
            colour_white_on: WhiteOn::Content,
            colour_norm: ColourNorm::Matched,
            smooth_feature: 0.2,
            image_tv: 1.0,
            tv_sh: 1e-4,
            refit_tv_sh: 0.0,
            tv_fraction: 0.01,
            tv_sh_per_voxel: true,
            tv_sh_per_channel: true,
        }
    }
}

/// The stylization's optimiser: RMSprop on the SH rows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OptimConfig {
    /// Where the squared-gradient average starts: `zero` or `first_grad` (svox2).
    pub rms_init: RmsStart,
    /// Update only the rows the step touched (its rays' samples and the
    /// TV rows), leaving the others and their state alone (svox2); false
    /// updates every row every step.
    pub sparse: bool,
    /// Keep the optimiser state from the refit into the image epochs (svox2)
    /// instead of starting each phase afresh.
    pub keep_state: bool,
}

impl Default for OptimConfig {
    fn default() -> Self {
        Self { rms_init: RmsStart::FirstGrad, sparse: true, keep_state: true }
    }
}

/// Switches for the paper's ablations.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AblationConfig {
    /// L_ref on the R³ pseudo-rays.
    pub use_reference_loss: bool,
    /// Only the reference view's own pixels as pseudo-rays (no registered rays).
    pub reference_rays_only: bool,
    /// L_feat (TCM).
    pub use_feature_loss: bool,
    /// L_color.
    pub use_colour_loss: bool,
    /// The smooth content update of the last epochs.
    pub smooth_update: bool,
}

impl Default for AblationConfig {
    fn default() -> Self {
        Self {
            use_reference_loss: true,
            reference_rays_only: false,
            use_feature_loss: true,
            use_colour_loss: true,
            smooth_update: true,
        }
    }
}

/// Which pixels ARF's colour statistics are taken over.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TransferPixels {
    /// The pixels that show the scene: photo and render pixels not of the
    /// background colour, the reference's hit pixels.
    Scene,
    /// Every pixel, background included (the released code).
    All,
}

/// The ARF baseline's losses and colour transfers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ArfConfig {
    /// Nearest-neighbour feature matching (relu3_x block) weight.
    pub nnfm: f32,
    /// Content MSE (relu3_x block) weight.
    pub content: f32,
    /// Recolour the training photos to the style image's colour mean and
    /// covariance before the refit (ARF's preprocessing).
    pub colour_transfer: bool,
    /// Which pixels the colour statistics of both transfers are taken over.
    pub transfer_pixels: TransferPixels,
    /// Also apply the photos' recolouring to the field's colour before the
    /// refit (the released code's `grid.apply_ct`), so the refit starts there.
    pub transfer_grid: bool,
    /// After the image epochs, recolour the field so that its training-view
    /// renders get the style's colour statistics (the released code).
    pub post_transfer: bool,
    /// VGG sees renders and contents at half resolution (2x2 means, which is
    /// what a 0.5x bilinear resize computes) and the style image resized to
    /// the views' long side, then halved (the released code).
    pub half_resolution: bool,
    /// The image epochs' SH TV of an ARF run, in place of `[loss] tv_sh`
    /// (which is set for holding a painting: ARF at 1e-4 lost 0.43 dB on
    /// the 96 px twin), so the baseline keeps the code's weight.
    pub tv_sh: f32,
}

impl Default for ArfConfig {
    fn default() -> Self {
        Self {
            nnfm: 1.0,
            content: 5e-3,
            colour_transfer: true,
            transfer_pixels: TransferPixels::Scene,
            transfer_grid: false,
            post_transfer: false,
            half_resolution: false,
            tv_sh: 1e-3,
        }
    }
}

/// `[colour_map]` of the stylize config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ColourMapConfig {
    /// Recolour the refit field's colours through the map before the image
    /// epochs (Ref-NPR; ARF has its own colour transfer).
    pub init_field: bool,
    /// L_color's targets from the map over each view's content render
    /// (relu5-patch means) instead of the TCM-matched reference patches.
    pub colour_targets: bool,
    /// Keep L_color (with the first guides' targets) in the smooth content
    /// update, which otherwise has no colour term (paper, code).
    pub in_smooth_update: bool,
    /// The content term's fixed features are of each view's content render
    /// through the map (the content's structure in the reference's colours)
    /// instead of the render itself, which pulls colours back to the photo's.
    pub mapped_content: bool,
    /// Pixels per side of the patches whose mean colour L_color compares
    /// with the map's targets (16: one per relu5 position, as the paper's
    /// matched targets). Smaller patches hold colours closer to the map on
    /// every surface; larger ones leave more room for painted texture.
    pub target_patch: usize,
    /// A reference whose map explains at least this share of its
    /// painting's change (`ColourMap::explained`) is a recolouring: its
    /// colours are the map's on every surface, so the map is fitted again
    /// sharper (`recolour_sigma`, `recolour_prior`) and L_color
    /// weighs `recolour_weight` over `recolour_patch`-pixel patches instead
    /// of `[loss] colour` over `target_patch`. Painted strokes, which the
    /// map explains only in part, keep the room L_feat needs for texture.
    /// Above 1: never.
    pub recolour_explained: f32,
    /// λ_c of a recolouring's colour-map targets.
    pub recolour_weight: f32,
    /// Pixels per side of a recolouring's target patches.
    pub recolour_patch: usize,
    /// `sigma` of a recolouring's map: a grade is a function of colour, so
    /// nearby colours need not be mixed as much.
    pub recolour_sigma: f32,
    /// `prior` of a recolouring's map: lego's far side shows colours its
    /// reference view barely does, and a grade's affine part carries to them.
    pub recolour_prior: MapPrior,
    /// `[schedule] lr_schedule` of a recolouring recognised before the
    /// refit (measured on the content.png it was painted over; a case
    /// without one keeps `[schedule] lr_schedule`): `per_phase` gained
    /// 0.4-1.1 dB on recolourings of the twin and of lego, and cost painted
    /// references on the twin (docs/results.md).
    pub recolour_lr_schedule: LrSchedule,
    /// Bins per colour axis of the fitted offsets.
    pub bins: usize,
    /// Width (colour units, [0, 1] per channel) of the Gaussian that mixes nearby bins.
    pub sigma: f32,
    /// Pixels' worth of the `prior` mixed into every colour's mean offset:
    /// colours with fewer nearby reference pixels than this move more as
    /// the prior says.
    pub prior_pixels: f32,
    /// What those pixels say: no change, or the painting's affine transform.
    pub prior: MapPrior,
}

impl Default for ColourMapConfig {
    fn default() -> Self {
        Self {
            init_field: true,
            colour_targets: true,
            in_smooth_update: false,
            mapped_content: false,
            target_patch: 16,
            recolour_explained: 0.85,
            recolour_weight: 20.0,
            recolour_patch: 4,
            recolour_sigma: 0.03,
            recolour_prior: MapPrior::Affine,
            recolour_lr_schedule: LrSchedule::PerPhase,
            bins: 16,
            sigma: 0.08,
            prior_pixels: 4.0,
            prior: MapPrior::Unchanged,
        }
    }
}

impl ColourMapConfig {
    /// Whether Ref-NPR fits the map at all (any of its uses on).
    pub fn is_on(&self) -> bool {
        self.init_field || self.colour_targets || self.mapped_content
    }

    /// The map's settings for a recolouring (`recolour_sigma`, `recolour_prior`).
    pub fn recolouring(&self) -> ColourMapConfig {
        ColourMapConfig { sigma: self.recolour_sigma, prior: self.recolour_prior, ..self.clone() }
    }

    pub fn validate(&self) -> Result<()> {
        ensure!(
            (1..=64).contains(&self.target_patch),
            "colour_map.target_patch must be in 1..=64 pixels, got {}",
            self.target_patch
        );
        ensure!(
            (1..=64).contains(&self.recolour_patch),
            "colour_map.recolour_patch must be in 1..=64 pixels, got {}",
            self.recolour_patch
        );
        ensure!(
            self.recolour_explained.is_finite() && self.recolour_weight.is_finite() && self.recolour_weight >= 0.0,
            "colour_map.recolour_explained must be finite and colour_map.recolour_weight >= 0, got {} and {}",
            self.recolour_explained,
            self.recolour_weight
        );
        for (key, sigma) in [("sigma", self.sigma), ("recolour_sigma", self.recolour_sigma)] {
            ensure!(sigma.is_finite() && sigma > 0.0, "colour_map.{key} must be positive, got {sigma}");
        }
        ensure!(
            self.prior_pixels.is_finite() && self.prior_pixels >= 0.0,
            "colour_map.prior_pixels must be >= 0, got {}",
            self.prior_pixels
        );
        ensure!((2..=64).contains(&self.bins), "colour_map.bins must be in 2..=64, got {}", self.bins);
        Ok(())
    }
}

/// The feature network of the losses (TCM's and L_color's matches, L_feat,
/// the content term, ARF's NNFM).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VggConfig {
    /// Which ImageNet weights VGG16 carries: Oxford's original release or
    /// torchvision's (the authors'), each with its own input normalisation.
    pub weights: VggWeights,
}

/// The controls an artist turns beside the painting (docs/local_edits.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ControlsConfig {
    /// Keep the photo's colours and take only the painting's light and dark:
    /// after the image epochs each voxel keeps the stylized luminance and
    /// takes the refit photo colour's chroma (`--preserve-colour`).
    pub preserve_colour: bool,
    /// How much of the stylization the field keeps: 1 all of it, 0 the refit
    /// photo; between, each voxel's colour is the blend (`--style-strength`).
    pub style_strength: f32,
    /// The painting's strokes this many times larger (1 to 4) on every
    /// surface: the paintings are rescaled before any work, their
    /// colours kept (`--stroke-scale`, `stylize::strokes`).
    pub stroke_scale: f32,
}

impl Default for ControlsConfig {
    fn default() -> Self {
        Self { preserve_colour: false, style_strength: 1.0, stroke_scale: 1.0 }
    }
}

impl ControlsConfig {
    pub fn validate(&self) -> Result<()> {
        ensure!(
            (0.0..=1.0).contains(&self.style_strength),
            "controls.style_strength must be in [0, 1], got {}",
            self.style_strength
        );
        ensure!(
            (1.0..=4.0).contains(&self.stroke_scale),
            "controls.stroke_scale must be in [1, 4] (strokes are made larger only), got {}",
            self.stroke_scale
        );
        Ok(())
    }
}

/// Everything `refnpr stylize` needs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StylizeConfig {
    pub seed: u64,
    pub schedule: ScheduleConfig,
    pub optim: OptimConfig,
    pub loss: LossConfig,
    pub ablation: AblationConfig,
    pub arf: ArfConfig,
    pub register: RegisterParams,
    /// The reference's colour mapping carried to every surface (`colour_map`).
    pub colour_map: ColourMapConfig,
    /// The losses' feature network.
    pub vgg: VggConfig,
    /// What an artist turns beside the painting.
    pub controls: ControlsConfig,
    /// Colour at voxels with empty corners, for the stylized field (its
    /// checkpoint records it, so every render of it uses the same).
    pub colour_corners: ColourCorners,
    /// The stylized field's colour on a lattice this many times finer
    /// along each axis than the photoreal grid's (1: the same lattice):
    /// more voxels to hold a painting's strokes, the frozen density
    /// resampled with it (`stylize::field::colour_grid`).
    pub colour_grid_scale: u32,
    /// Samples whose compositing weight is below this are dropped from the cached sample lists.
    pub min_sample_weight: f32,
    /// Memory for cached per-view sample lists (MB); views beyond it are re-marched each step.
    pub sample_cache_mb: usize,
    /// The run's memory budget, GB (`stylize::budget`): the sample cache
    /// and the kept content features shrink to fit it, and a run that
    /// cannot fit is refused before the refit. 0: 90 % of the machine's
    /// free memory.
    pub memory_gb: f32,
    /// Where the cached sample lists are kept (a device copy is in addition
    /// to the host's, which gives each step its rows, so it takes up to
    /// `sample_cache_mb` of device memory).
    pub samples_on_device: Placement,
    /// What computes the ray losses (`RayKernel`).
    pub ray_kernel: RayKernel,
    /// On the CPU backends, keep the content term's fixed features as f16
    /// numbers (half their memory; `tcm::StoredFeatures`). No effect on a GPU.
    pub half_content_features: bool,
    /// Keep the content term's fixed features of every view from the
    /// guides on; false: take them again at each step from the view's
    /// content render (one more VGG16 forward per step, no memory for
    /// them). The memory budget may leave fewer views kept.
    pub keep_content_features: bool,
    /// Wait for the device at the end of each timed part of a step, so
    /// that on a GPU each part's time in the step profile is its own work
    /// (its queue runs asynchronously otherwise, and a part's time lands
    /// where the host next waits); compare whole steps without it (the
    /// queue is drained between parts). `bench-stylize --sync-parts`.
    pub sync_parts: bool,
    /// Rays per chunk in rendering and the deferred re-render.
    pub render_chunk: usize,
    /// Query rows per chunk in the nearest-neighbour searches.
    pub search_chunk: usize,
}

impl Default for StylizeConfig {
    fn default() -> Self {
        Self {
            seed: 20200823,
            schedule: ScheduleConfig::default(),
            optim: OptimConfig::default(),
            loss: LossConfig::default(),
            ablation: AblationConfig::default(),
            arf: ArfConfig::default(),
            register: RegisterParams::default(),
            colour_map: ColourMapConfig::default(),
            vgg: VggConfig::default(),
            controls: ControlsConfig::default(),
            colour_corners: ColourCorners::Renormalised,
            colour_grid_scale: 1,
            min_sample_weight: 1e-5,
            sample_cache_mb: 2048,
            memory_gb: 0.0,
            samples_on_device: Placement::Auto,
            ray_kernel: RayKernel::Auto,
            half_content_features: true,
            keep_content_features: true,
            sync_parts: false,
            render_chunk: 16384,
            search_chunk: 1024,
        }
    }
}

/// Named stylize configurations (`refnpr stylize --preset`), compiled in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Preset {
    /// The defaults (`configs/stylize.toml`): the paper's full schedule, 10 image epochs.
    Paper,
    /// A shorter schedule, 6 image epochs (`configs/demo_stylize.toml`, the demo's).
    Fast,
    /// The authors' released code as closely as this design allows (`configs/stylize_authors.toml`).
    Authors,
}

impl Preset {
    /// The preset's config (`Fast` is also the demo's stylization).
    pub fn config(self) -> Result<StylizeConfig> {
        match self {
            Preset::Paper => Ok(StylizeConfig::default()),
            Preset::Fast => StylizeConfig::from_toml_str(
                include_str!("../../configs/demo_stylize.toml"),
                "configs/demo_stylize.toml",
            ),
            Preset::Authors => StylizeConfig::from_toml_str(
                include_str!("../../configs/stylize_authors.toml"),
                "configs/stylize_authors.toml",
            ),
        }
    }
}

impl StylizeConfig {
    /// Parses TOML over the defaults and validates.
    pub fn from_toml_str(text: &str, source: &str) -> Result<Self> {
        let cfg: Self = config::parse_over(&Self::default(), text, source, "stylize config")?;
        cfg.validate().with_context(|| format!("{source}: invalid stylize config"))?;
        Ok(cfg)
    }

    pub fn from_file(path: &Path) -> Result<Self> {
        Self::from_toml_str(&config::read(path)?, &path.display().to_string())
    }

    pub fn validate(&self) -> Result<()> {
        let s = &self.schedule;
        let l = &self.loss;
        ensure!(s.ray_epochs >= 0.0 && s.ray_epochs.is_finite(), "schedule.ray_epochs must be >= 0");
        ensure!(
            s.ray_batch > 0 && self.render_chunk > 0 && self.search_chunk > 0,
            "schedule.ray_batch, render_chunk and search_chunk must be positive"
        );
        ensure!((0.0..=1.0).contains(&s.smooth_fraction), "schedule.smooth_fraction must be in [0, 1]");
        for (name, v) in [
            ("schedule.lr", s.lr),
            ("schedule.lr_final", s.lr_final),
            ("schedule.lr_refit", s.lr_refit),
            ("schedule.eps", s.eps),
        ] {
            ensure!(v.is_finite() && v > 0.0, "{name} must be a positive number, got {v}");
        }
        ensure!(s.lr_decay_steps > 0, "schedule.lr_decay_steps must be positive");
        ensure!((1..=8).contains(&s.coarse_scale), "schedule.coarse_scale must be in 1..=8, got {}", s.coarse_scale);
        ensure!(
            s.coarse_scale == 1
                || (self.ablation.smooth_update && (s.image_epochs as f32 * s.smooth_fraction).round() >= 1.0),
            "schedule.coarse_scale > 1 runs the smooth update at full size: it needs ablation.smooth_update and \
             at least one smooth epoch (schedule.smooth_fraction of schedule.image_epochs)"
        );
        ensure!(
            s.coarse_scale == 1 || !self.colour_map.in_smooth_update,
            "schedule.coarse_scale > 1 cannot keep L_color in the smooth update (colour_map.in_smooth_update): \
             its targets are the coarse views'"
        );
        ensure!((0.0..1.0).contains(&s.rmsprop_beta), "schedule.rmsprop_beta must be in [0, 1)");
        ensure!(
            (1..=3).contains(&self.colour_grid_scale),
            "colour_grid_scale must be 1, 2 or 3 (the colour grid's memory grows with its cube), got {}",
            self.colour_grid_scale
        );
        ensure!(
            self.memory_gb.is_finite() && self.memory_gb >= 0.0,
            "memory_gb must be a number of GB >= 0 (0: 90 % of the free memory), got {}",
            self.memory_gb
        );
        for (name, v) in [
            ("loss.reference", l.reference),
            ("loss.feature", l.feature),
            ("loss.content", l.content),
            ("loss.colour", l.colour),
            ("loss.smooth_feature", l.smooth_feature),
            ("loss.image_tv", l.image_tv),
            ("loss.tv_sh", l.tv_sh),
            ("loss.refit_tv_sh", l.refit_tv_sh),
            ("arf.nnfm", self.arf.nnfm),
            ("arf.content", self.arf.content),
            ("arf.tv_sh", self.arf.tv_sh),
        ] {
            ensure!(v.is_finite() && v >= 0.0, "{name} must be >= 0, got {v}");
        }
        ensure!(
            (0.0..=2.0).contains(&l.colour_max_distance),
            "loss.colour_max_distance is a cosine distance, in [0, 2]"
        );
        ensure!(l.tv_fraction > 0.0 && l.tv_fraction <= 1.0, "loss.tv_fraction must be in (0, 1]");
        ensure!((0.0..1.0).contains(&self.min_sample_weight), "min_sample_weight must be in [0, 1)");
        self.colour_map.validate()?;
        self.controls.validate()?;
        self.register.validate()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The controls' ranges are checked, naming the key.
    #[test]
    fn controls_out_of_range_are_refused_naming_the_key() {
        let mut config = StylizeConfig::default();
        assert_eq!(config.controls.style_strength, 1.0);
        config.controls = ControlsConfig { style_strength: 1.5, ..ControlsConfig::default() };
        assert!(config.validate().unwrap_err().to_string().contains("controls.style_strength"));
        for scale in [0.5, 5.0] {
            config.controls = ControlsConfig { stroke_scale: scale, ..ControlsConfig::default() };
            assert!(config.validate().unwrap_err().to_string().contains("controls.stroke_scale"), "{scale}");
        }
    }

    /// The compiled-in presets parse, and each is what its help says.
    #[test]
    fn presets_parse_and_are_what_they_say() {
        let paper = Preset::Paper.config().unwrap();
        assert_eq!(paper.schedule.image_epochs, 10);
        assert_eq!(Preset::Fast.config().unwrap().schedule.image_epochs, 6);
        let authors = Preset::Authors.config().unwrap();
        assert_eq!(authors.colour_corners, ColourCorners::Zero, "the authors' svox2 corners");
        assert!(
            !authors.colour_map.init_field && !authors.colour_map.colour_targets,
            "the authors' method has no colour map"
        );
        assert_eq!(authors.vgg.weights, VggWeights::Torchvision, "the authors' VGG16");
        assert_eq!(paper.vgg.weights, VggWeights::Oxford);
        // The SH TV: the authors' weight in their preset and for the ARF
        // baseline, a tenth of it for refnpr's own Ref-NPR runs.
        assert_eq!((authors.loss.tv_sh, authors.arf.tv_sh), (1e-3, 1e-3));
        assert_eq!((paper.loss.tv_sh, paper.arf.tv_sh), (1e-4, 1e-3));
        let file = StylizeConfig::from_toml_str(include_str!("../../configs/stylize.toml"), "configs/stylize.toml");
        assert_eq!(file.unwrap(), paper, "configs/stylize.toml is the defaults");
        let mut bad = paper.clone();
        bad.arf.tv_sh = -1.0;
        assert!(bad.validate().unwrap_err().to_string().contains("arf.tv_sh"));
    }
}
