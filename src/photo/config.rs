//! Training configuration: TOML files with a default for every field.
//! Unknown keys and out-of-range values are errors that name the file.

use crate::field::RayKernel;
use crate::field::march::MarchParams;
use crate::field::view::RenderSettings;
use crate::scene::data::{DatasetKind, LoadOptions};
use anyhow::{Context, Result, bail};

use crate::util::config;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The voxel grid and its coarse-to-fine schedule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GridConfig {
    /// Lattice resolution at the start.
    pub initial_res: [usize; 3],
    /// Steps at which the grid is pruned and upsampled ...
    pub upsample_steps: Vec<usize>,
    /// ... to these resolutions (same length as `upsample_steps`).
    pub upsample_res: Vec<[usize; 3]>,
    /// Spherical-harmonic degree of the colour (0, 1 or 2).
    pub sh_degree: u32,
    /// Initial density of every voxel.
    pub init_density: f32,
    /// Voxels whose density (and their neighbours') is below this are pruned before upsampling.
    pub prune_threshold: f32,
    /// Whether the field learns a far background behind the box
    /// (`field::environment`): `auto` does for captures around the scene
    /// read from COLMAP or `transforms.json` whose photos' borders are not
    /// one plain colour (a room or landscape lies beyond the box;
    /// `photo::trainer::far_decision`); the research layouts have a
    /// constant one.
    pub far_background: FarBackground,
    /// The far map's size, `[width, height]` texels (azimuth, polar angle),
    /// after the last upsampling; it starts halved once per upsampling step
    /// and doubles with the grid (`far_resolution_at`).
    pub far_resolution: [usize; 2],
    /// The grid follows the images: the fewest voxels the last resolution
    /// puts across each pixel of a training view (`follow_images`). Where
    /// the views are large enough that it falls short, every upsampling
    /// resolution grows in proportion, up to about [`MAX_FOLLOWED_POINTS`]; the
    /// schedule as written is the floor. 0: the resolutions as written.
    pub voxels_per_pixel: f32,
}

/// The most lattice points a grid that follows the images grows to: 512³,
/// the authors' synthetic grid at 800 px (its links alone take 512 MB).
pub const MAX_FOLLOWED_POINTS: usize = 512 * 512 * 512;

/// When a fit learns a far background (`GridConfig::far_background`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FarBackground {
    #[default]
    Auto,
    On,
    Off,
}

impl GridConfig {
    /// The far map's size after `upsamplings` of the grid's upsampling
    /// steps: halved once per step still to come, so that the texels no
    /// ray has reached at the finer size keep the coarse map's colours.
    pub fn far_resolution_at(&self, upsamplings: usize) -> [usize; 2] {
        let to_come = self.upsample_steps.len().saturating_sub(upsamplings).min(16);
        self.far_resolution.map(|r| (r >> to_come).max(1))
    }

    /// The resolution the schedule ends at.
    pub fn final_res(&self) -> [usize; 3] {
        *self.upsample_res.last().unwrap_or(&self.initial_res)
    }

    /// Grows the schedule's resolutions for views spanning `pixels_across`
    /// pixels of the box along x, y and z (0: an axis not measured in
    /// pixels, NDC's depth) until the last one holds `voxels_per_pixel`
    /// voxels across each pixel, in proportion on every axis (the
    /// upsampling resolutions, or the initial one where there are none),
    /// rounded up to multiples of 16, up to about [`MAX_FOLLOWED_POINTS`]. Returns the
    /// factor applied (1: unchanged, the images are no larger than the
    /// schedule was written for).
    pub fn follow_images(&mut self, pixels_across: [f32; 3]) -> f32 {
        let last = self.final_res();
        let wanted = (0..3)
            .map(|axis| self.voxels_per_pixel * pixels_across[axis] / last[axis] as f32)
            .filter(|ratio| ratio.is_finite())
            .fold(1.0f32, f32::max);
        let points = last.iter().product::<usize>() as f32;
        let scale = wanted.min((MAX_FOLLOWED_POINTS as f32 / points).cbrt().max(1.0));
        if scale <= 1.0 {
            return 1.0;
        }
        let grow = |res: &mut [usize; 3]| {
            *res = res.map(|r| ((r as f32 * scale / 16.0).ceil() as usize * 16).clamp(r, 2048));
        };
        match self.upsample_res.is_empty() {
            true => grow(&mut self.initial_res),
            false => self.upsample_res.iter_mut().for_each(grow),
        }
        scale
    }
}

impl Default for GridConfig {
    fn default() -> Self {
        Self {
            initial_res: [128; 3],
            upsample_steps: vec![],
            upsample_res: vec![],
            sh_degree: 2,
            init_density: 0.1,
            prune_threshold: 1.0,
            far_background: FarBackground::Auto,
            far_resolution: [512, 256],
            voxels_per_pixel: 0.9,
        }
    }
}

/// Optimiser (RMSprop, as Plenoxels) and regularisers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OptimConfig {
    /// Total optimisation steps.
    pub steps: usize,
    /// Rays per step.
    pub batch_rays: usize,
    /// Density learning rate at the start and at the end (exponential decay).
    pub lr_density: f32,
    pub lr_density_final: f32,
    /// SH learning rate at the start and at the end (exponential decay).
    pub lr_sh: f32,
    pub lr_sh_final: f32,
    /// The density learning rate ramps up from `lr_delay_mult` x over these steps.
    pub lr_delay_steps: usize,
    pub lr_delay_mult: f32,
    /// RMSprop decay of the squared-gradient average.
    pub rmsprop_beta: f32,
    pub eps: f32,
    /// Total-variation weights on density and SH (on the voxels a step touches).
    pub tv_density: f32,
    pub tv_sh: f32,
    /// Fraction of the voxels a step touches that get the TV terms (a random subset).
    pub tv_fraction: f32,
}

impl Default for OptimConfig {
    fn default() -> Self {
        Self {
            steps: 3600,
            batch_rays: 4096,
            // Plenoxels' rates are density 30 -> ~1, SH 1e-2 -> ~1e-4 over
            // ~50x more rays than a run here: each voxel is updated a few
            // hundred times, and a higher, slower-decaying rate fits more
            // (measured on lego and fern, docs/performance.md "Photorealistic fitting").
            lr_density: 30.0,
            lr_density_final: 5.0,
            lr_sh: 0.03,
            lr_sh_final: 6e-3,
            lr_delay_steps: 100,
            lr_delay_mult: 0.01,
            rmsprop_beta: 0.95,
            eps: 1e-8,
            tv_density: 1e-5,
            tv_sh: 1e-3,
            tv_fraction: 0.1,
        }
    }
}

/// Everything `refnpr train` needs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainConfig {
    /// Seed of every random choice (ray batches).
    pub seed: u64,
    pub data: LoadOptions,
    pub grid: GridConfig,
    pub march: MarchParams,
    pub optim: OptimConfig,
    /// Write a checkpoint every this many steps (and at the end).
    pub checkpoint_every: usize,
    /// Rays per chunk when rendering whole images.
    pub render_chunk: usize,
    /// What renders and differentiates a step's batch: `auto` (plain Rust,
    /// `field::host_fit`, on the CPU backends; the Burn graph with the fused
    /// compositing kernel on a GPU), `host`, `graph` or `unfused` (the graph
    /// without the fused kernel: its fallback on a GPU).
    pub ray_kernel: RayKernel,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            seed: 20200823,
            data: LoadOptions::default(),
            grid: GridConfig::default(),
            march: MarchParams::default(),
            optim: OptimConfig::default(),
            checkpoint_every: 1000,
            render_chunk: 8192,
            ray_kernel: RayKernel::Auto,
        }
    }
}

impl TrainConfig {
    /// How the fitted field is rendered (stored in its checkpoints).
    pub fn render_settings(&self) -> RenderSettings {
        RenderSettings { march: self.march, chunk: self.render_chunk }
    }

    /// The built-in defaults for a dataset kind (the same values as
    /// `configs/<kind>.toml`); COLMAP and `transforms.json` captures take
    /// Blender's (see [`TrainConfig::for_setup`] for forward-facing ones).
    pub fn for_kind(kind: DatasetKind) -> Self {
        Self::for_setup(kind, kind == DatasetKind::Llff)
    }

    /// The defaults for a dataset folder: its kind, and for COLMAP and
    /// `transforms.json` captures whether their cameras face forward
    /// (`data::probe`, the poses alone read).
    pub fn for_dir(dir: &Path) -> Result<Self> {
        let (kind, forward) = crate::scene::data::probe(dir, Default::default())?;
        Ok(Self::for_setup(kind, forward))
    }

    /// The defaults for a kind of dataset of either shape: a forward-facing
    /// capture takes LLFF's grid and schedule (at the images' own size), one
    /// around the scene Blender's.
    pub fn for_setup(kind: DatasetKind, forward_facing: bool) -> Self {
        let mut c = Self::default();
        match kind {
            DatasetKind::Colmap | DatasetKind::Transforms => {
                c = Self::for_kind(if forward_facing { DatasetKind::Llff } else { DatasetKind::Blender });
                c.data.downscale = 1;
            }
            DatasetKind::Blender => {
                c.grid.initial_res = [64; 3];
                c.grid.upsample_steps = vec![250, 900];
                c.grid.upsample_res = vec![[128; 3], [256; 3]];
            }
            DatasetKind::Llff => {
                c.data.downscale = 8;
                // The NDC box is wider than [-1, 1] in x and y (about 3 x 2.7
                // on fern, see `data::llff`): ~128 voxels per NDC unit across.
                c.grid.initial_res = [192, 176, 32];
                c.grid.upsample_steps = vec![250];
                c.grid.upsample_res = vec![[384, 352, 64]];
                // As written at every size: fern's grid is 66 % active (a
                // forward-facing box is seen everywhere), so following
                // 1008x756 views (8x the lattice) would take ~26 GB, and
                // no real capture at that size is here to measure its gain.
                c.grid.voxels_per_pixel = 0.0;
                c.optim.steps = 3000;
                c.optim.tv_density = 5e-4;
                c.optim.tv_sh = 5e-3;
            }
            DatasetKind::Nsvf => {
                c.grid.initial_res = [64; 3];
                c.grid.upsample_steps = vec![250, 900];
                c.grid.upsample_res = vec![[128; 3], [256; 3]];
                c.data.background = [0.0; 3];
            }
        }
        c
    }

    /// Parses a TOML config (missing fields take `base`'s values) and validates it.
    pub fn from_toml_str(text: &str, base: &TrainConfig, source: &str) -> Result<Self> {
        let cfg: TrainConfig = config::parse_over(base, text, source, "config")?;
        cfg.validate().with_context(|| format!("{source}: invalid config"))?;
        Ok(cfg)
    }

    pub fn from_file(path: &Path, base: &TrainConfig) -> Result<Self> {
        Self::from_toml_str(&config::read(path)?, base, &path.display().to_string())
    }

    /// The fit of views larger than the schedule was written for
    /// (`GridConfig::follow_images`): the grid grows by a factor s per axis
    /// and the steps by s², so that each voxel's face, s² times smaller,
    /// is crossed by as many rays as at the written size. Returns s (1:
    /// unchanged).
    pub fn follow_images(&mut self, pixels_across: [f32; 3]) -> f32 {
        let scale = self.grid.follow_images(pixels_across);
        if scale > 1.0 {
            self.optim.steps = (self.optim.steps as f32 * scale * scale).round() as usize;
        }
        scale
    }

    /// This config for `dataset`'s views: [`TrainConfig::follow_images`] on
    /// the pixels its training views span of the box.
    pub fn for_views(&self, dataset: &crate::scene::data::Dataset) -> TrainConfig {
        let mut config = self.clone();
        config.follow_images(dataset.box_pixels_across());
        config
    }

    /// Checks every value is in range.
    pub fn validate(&self) -> Result<()> {
        let g = &self.grid;
        let o = &self.optim;
        let m = &self.march;
        if g.initial_res.iter().any(|&r| !(2..=2048).contains(&r)) {
            bail!("grid.initial_res must be between 2 and 2048 per axis, got {:?}", g.initial_res);
        }
        if g.upsample_steps.len() != g.upsample_res.len() {
            bail!("grid.upsample_steps and grid.upsample_res must have the same length");
        }
        if g.upsample_steps.windows(2).any(|w| w[0] >= w[1]) {
            bail!("grid.upsample_steps must be increasing");
        }
        if g.upsample_res.iter().flatten().any(|&r| !(2..=2048).contains(&r)) {
            bail!("grid.upsample_res entries must be between 2 and 2048 per axis");
        }
        if g.sh_degree > 2 {
            bail!("grid.sh_degree must be 0, 1 or 2, got {}", g.sh_degree);
        }
        if !(g.init_density.is_finite() && g.prune_threshold.is_finite() && g.prune_threshold >= 0.0) {
            bail!("grid.init_density must be finite and grid.prune_threshold >= 0");
        }
        if !(g.voxels_per_pixel.is_finite() && (0.0..=8.0).contains(&g.voxels_per_pixel)) {
            bail!("grid.voxels_per_pixel must be between 0 and 8, got {}", g.voxels_per_pixel);
        }
        if g.far_resolution.iter().any(|&r| !(1..=4096).contains(&r)) {
            bail!("grid.far_resolution must be between 1 and 4096 texels per axis, got {:?}", g.far_resolution);
        }
        if o.steps == 0 || o.batch_rays == 0 {
            bail!("optim.steps and optim.batch_rays must be positive");
        }
        for (name, v) in [
            ("optim.lr_density", o.lr_density),
            ("optim.lr_density_final", o.lr_density_final),
            ("optim.lr_sh", o.lr_sh),
            ("optim.lr_sh_final", o.lr_sh_final),
            ("optim.eps", o.eps),
        ] {
            if !(v.is_finite() && v > 0.0) {
                bail!("{name} must be a positive number, got {v}");
            }
        }
        if !(0.0..1.0).contains(&o.rmsprop_beta) {
            bail!("optim.rmsprop_beta must be in [0, 1), got {}", o.rmsprop_beta);
        }
        if !(0.0..=1.0).contains(&o.lr_delay_mult) {
            bail!("optim.lr_delay_mult must be in [0, 1], got {}", o.lr_delay_mult);
        }
        if !(o.tv_density >= 0.0 && o.tv_sh >= 0.0) {
            bail!("optim.tv_density and optim.tv_sh must be >= 0");
        }
        if !(o.tv_fraction > 0.0 && o.tv_fraction <= 1.0) {
            bail!("optim.tv_fraction must be in (0, 1], got {}", o.tv_fraction);
        }
        if !(m.step > 0.0 && m.step <= 4.0) {
            bail!("march.step must be in (0, 4] voxels, got {}", m.step);
        }
        if !(m.stop_threshold > 0.0 && m.stop_threshold < 1.0) {
            bail!("march.stop_threshold must be in (0, 1), got {}", m.stop_threshold);
        }
        if !(m.sigma_threshold >= 0.0 && m.depth_threshold > 0.0) {
            bail!("march.sigma_threshold must be >= 0 and march.depth_threshold > 0");
        }
        if self.data.downscale == 0 || self.data.background.iter().any(|c| !(0.0..=1.0).contains(c)) {
            bail!("data.downscale must be >= 1 and data.background in [0, 1]");
        }
        if self.checkpoint_every == 0 || self.render_chunk == 0 {
            bail!("checkpoint_every and render_chunk must be positive");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Lego's box at 200, 400 and 800 px spans about 207, 414 and 827
    /// pixels; fern's NDC box at 504x378 about 751 x 510 (x, y).
    #[test]
    fn the_grid_follows_larger_images_and_keeps_the_written_schedule_for_smaller() {
        let blender = || TrainConfig::for_kind(DatasetKind::Blender).grid;
        let mut at_200 = blender();
        assert_eq!(at_200.follow_images([207.0; 3]), 1.0);
        assert_eq!(at_200, blender());
        let mut at_400 = TrainConfig::for_kind(DatasetKind::Blender);
        let scale = at_400.follow_images([414.0; 3]);
        assert!((1.4..1.5).contains(&scale), "{scale}");
        assert_eq!(at_400.grid.upsample_res, vec![[192; 3], [384; 3]]);
        assert_eq!(at_400.grid.initial_res, [64; 3]);
        assert_eq!(at_400.optim.steps, (3600.0 * scale * scale).round() as usize);
        let mut at_800 = blender();
        at_800.follow_images([827.0; 3]);
        assert_eq!(at_800.final_res(), [512; 3], "capped at the authors' 512³");
        let mut written = blender();
        written.voxels_per_pixel = 0.0;
        assert_eq!(written.follow_images([827.0; 3]), 1.0);

        // NDC's depth is not across pixels: it grows with x and y.
        let mut llff = TrainConfig::for_kind(DatasetKind::Llff).grid;
        assert_eq!(llff.follow_images([1502.0, 1020.0, 0.0]), 1.0, "LLFF's grid is as written");
        llff.voxels_per_pixel = 0.5;
        assert_eq!(llff.follow_images([751.0, 510.0, 0.0]), 1.0);
        llff.follow_images([1502.0, 1020.0, 0.0]);
        assert_eq!(llff.final_res(), [752, 704, 128]);
    }
}
