//! Checkpoints: everything needed to render (grid, SH degree, bounds, NDC,
//! dataset kind, config) plus the optimiser state for resuming, in one file
//! written atomically (temporary file, then rename).

use crate::field::composite::{ViewRender, ViewRenderer};
use crate::field::grid::{GridGeometry, RadianceGrid};
use crate::photo::config::TrainConfig;
use crate::scene::camera::{Camera, NdcParams};
use crate::scene::data::DatasetKind;
use crate::util::tensor::{floats, to_vec};
use crate::util::{diverged, files};
use anyhow::{Context, Result, bail};
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

pub const CHECKPOINT_FILE: &str = "checkpoint.bin";
const MAGIC: &[u8; 8] = b"REFNPRG1";

/// What a checkpoint says about its scene and run.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CheckpointMeta {
    /// Steps done when it was written.
    pub step: usize,
    pub geometry: GridGeometry,
    pub sh_degree: u32,
    pub ndc: Option<NdcParams>,
    pub kind: DatasetKind,
    pub background: [f32; 3],
    pub near_far: Option<(f32, f32)>,
    /// The dataset folder it was trained on.
    pub data_dir: PathBuf,
    pub config: TrainConfig,
    /// Seconds of training so far (summed over resumed runs).
    pub train_seconds: f64,
}

#[derive(Serialize, Deserialize)]
struct Payload {
    meta_json: String,
    coords: Vec<u32>,
    density: Vec<f32>,
    sh: Vec<f32>,
    opt_density: Vec<f32>,
    opt_sh: Vec<f32>,
}

/// A loaded checkpoint.
pub struct Checkpoint {
    /// The file it was loaded from.
    pub source: PathBuf,
    pub meta: CheckpointMeta,
    pub grid: RadianceGrid,
    /// RMSprop running averages [rows, 1] and [rows, 3B] (zeros if absent;
    /// empty, 0 rows, when loaded without optimiser state).
    pub opt_density: Tensor<2>,
    pub opt_sh: Tensor<2>,
}

impl Checkpoint {
    /// A fingerprint of the field (FNV-1a over its geometry, step and
    /// density): two runs, or one run at two steps, differ in it.
    pub fn fingerprint(&self) -> u64 {
        let g = &self.meta.geometry;
        let words = g.res.iter().map(|&r| r as u32).chain([self.meta.step as u32, self.grid.num_rows() as u32]);
        let bits = self.grid.density_cpu.iter().map(|d| d.to_bits());
        words.chain(bits).fold(0xcbf2_9ce4_8422_2325u64, |h, w| {
            w.to_le_bytes().iter().fold(h, |h, &b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3))
        })
    }

    /// A renderer of the checkpoint's field with its own march settings,
    /// NDC warp and background (many views: build it once).
    pub fn renderer(&self) -> ViewRenderer<'_> {
        let cfg = &self.meta.config;
        ViewRenderer::new(&self.grid, self.meta.ndc.as_ref(), &cfg.march, self.meta.background, cfg.render_chunk)
    }

    /// Renders `camera`'s view (one view; many: [`renderer`](Self::renderer)).
    pub fn render_view(&self, camera: &Camera) -> ViewRender {
        self.renderer().view(camera)
    }
}

/// The checkpoint path for a run folder or a checkpoint file path.
pub fn resolve(path: &Path) -> PathBuf {
    if path.is_dir() { path.join(CHECKPOINT_FILE) } else { path.to_path_buf() }
}

pub fn save(
    path: &Path,
    meta: &CheckpointMeta,
    grid: &RadianceGrid,
    opt_density: &Tensor<2>,
    opt_sh: &Tensor<2>,
) -> Result<()> {
    let payload = Payload {
        meta_json: serde_json::to_string(meta)?,
        coords: grid.coords.clone(),
        density: to_vec(grid.density.clone()),
        sh: to_vec(grid.sh.clone()),
        opt_density: to_vec(opt_density.clone()),
        opt_sh: to_vec(opt_sh.clone()),
    };
    let arrays = [("density", &payload.density[..]), ("SH colour", &payload.sh), ("optimiser state", &payload.opt_sh)];
    if let Some(what) = diverged::first_non_finite(&arrays) {
        let kept = match path.exists() {
            true => "the file keeps its previous content",
            false => "nothing was written",
        };
        bail!(
            "refusing to write {} at step {}: the field's {what} holds NaN or infinite values (the run diverged); {kept}",
            path.display(),
            meta.step
        );
    }
    files::save(path, MAGIC, &payload)
}

pub fn load(path: &Path, device: &Device) -> Result<Checkpoint> {
    load_with(path, device, true)
}

/// Loads a checkpoint; without `optimiser_state` the RMSprop averages are
/// dropped (empty tensors), which is all rendering and R³ need and saves
/// a grid-sized block of memory.
pub fn load_with(path: &Path, device: &Device, optimiser_state: bool) -> Result<Checkpoint> {
    let path = resolve(path);
    if !path.exists() {
        bail!("no checkpoint at {} (train one with `refnpr train`)", path.display());
    }
    let mut p: Payload = files::load(&path, MAGIC, "a refnpr checkpoint")?;
    if !optimiser_state {
        p.opt_density = Vec::new();
        p.opt_sh = Vec::new();
    }
    let meta: CheckpointMeta =
        serde_json::from_str(&p.meta_json).with_context(|| format!("{}: corrupt metadata", path.display()))?;
    let n = p.coords.len();
    let cols = 3 * crate::scene::sh::num_basis(meta.sh_degree);
    let npts = meta.geometry.num_points();
    if p.density.len() != n || p.sh.len() != n * cols || p.coords.iter().any(|&c| c as usize >= npts) {
        bail!("{}: grid arrays have inconsistent sizes", path.display());
    }
    let grid = RadianceGrid::from_rows(meta.geometry, meta.sh_degree, p.coords, p.density, p.sh, device);
    let (opt_density, opt_sh) = if !optimiser_state {
        (Tensor::zeros([0, 1], device), Tensor::zeros([0, cols], device))
    } else {
        (
            if p.opt_density.len() == n {
                floats(p.opt_density, [n, 1], device)
            } else {
                Tensor::zeros([n, 1], device)
            },
            if p.opt_sh.len() == n * cols {
                floats(p.opt_sh, [n, cols], device)
            } else {
                Tensor::zeros([n, cols], device)
            },
        )
    };
    Ok(Checkpoint { source: path, meta, grid, opt_density, opt_sh })
}

/// A checkpoint (without optimiser state: for rendering and R³) and the
/// dataset it was trained on (or `data`, when given).
pub fn load_run(
    path: &Path,
    data: Option<&Path>,
    device: &Device,
) -> Result<(Checkpoint, crate::scene::data::Dataset)> {
    let ck = load_with(path, device, false)?;
    let dir = data.map(Path::to_path_buf).unwrap_or_else(|| ck.meta.data_dir.clone());
    let dataset = crate::scene::data::load(&dir, &ck.meta.config.data)
        .with_context(|| format!("loading the run's dataset {} (pass --data to use another)", dir.display()))?;
    Ok((ck, dataset))
}
