//! Checkpoints: everything needed to render (grid, SH degree, bounds, NDC,
//! dataset kind, render settings) plus the optimiser state and the writing
//! run's config for resuming, in one file written atomically (temporary
//! file, then rename).

use crate::field::grid::{GridGeometry, RadianceGrid};
use crate::field::view::{RenderSettings, ViewRender, ViewRenderer};
use crate::scene::camera::{Camera, NdcParams};
use crate::scene::data::{DatasetKind, LoadOptions};
use crate::util::input::InputError;
use crate::util::tensor::floats;
use crate::util::{bin_fields, files, rows_op};
use anyhow::{Context, Result, bail};

use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};
use std::io::{self, BufRead, Seek, Write};
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
    /// How the field is rendered (march settings, render chunk).
    pub render: RenderSettings,
    /// How `data_dir` was read.
    pub data: LoadOptions,
    /// The config of the run that wrote the file, as its stage stores it
    /// (stage 1's `TrainConfig`, which resuming a fit reads back); nothing
    /// that renders the field reads it.
    pub run_config: serde_json::Value,
    /// Seconds of training so far (summed over resumed runs).
    pub train_seconds: f64,
}

/// The file's content after its magic tag: bincode's layout of these
/// fields, in this order ([`save`] writes them, [`read_payload`] reads
/// them, `util::bin_fields`).
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
        ViewRenderer::new(&self.grid, self.meta.ndc.as_ref(), &self.meta.render, self.meta.background)
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

/// Values per block when a grid-sized array is streamed into the file
/// (4 MB: stays in cache between the read, the check and the encoding).
const SAVE_BLOCK_VALUES: usize = 1 << 20;

/// Writes a checkpoint (atomically: `files::write_atomic`). The grid and
/// optimiser arrays go from their tensors to the file in blocks
/// (`util::bin_fields`, the bytes bincode writes for `Payload`), each block
/// checked for NaN and infinities on the way: a diverged field is refused
/// and the file keeps its previous content.
pub fn save(
    path: &Path,
    meta: &CheckpointMeta,
    grid: &RadianceGrid,
    opt_density: &Tensor<2>,
    opt_sh: &Tensor<2>,
) -> Result<()> {
    let meta_json = serde_json::to_string(meta)?;
    let arrays = [
        ("density", &grid.density),
        ("SH colour", &grid.sh),
        ("optimiser state", opt_density),
        ("optimiser state", opt_sh),
    ];
    let nothing_kept = if path.exists() { "" } else { "; nothing was written" };
    files::write_atomic(path, |w| {
        let io = |e| files::io_error(e, path);
        let mut scratch = Vec::new();
        w.write_all(MAGIC).map_err(io)?;
        bin_fields::write_str(w, &meta_json).map_err(io)?;
        bin_fields::write_len(w, grid.coords.len()).map_err(io)?;
        bin_fields::write_values(w, &grid.coords, u32::to_le_bytes, &mut scratch).map_err(io)?;
        for (what, values) in arrays {
            bin_fields::write_len(w, values.shape().num_elements()).map_err(io)?;
            rows_op::for_each_row_block(values, SAVE_BLOCK_VALUES, |block| {
                if !block.iter().fold(true, |finite, v| finite & v.is_finite()) {
                    bail!(
                        "refusing to write {} at step {}: the field's {what} holds NaN or infinite values \
                         (the run diverged){nothing_kept}",
                        path.display(),
                        meta.step
                    );
                }
                bin_fields::write_values(w, block, f32::to_le_bytes, &mut scratch).map_err(io)
            })?;
        }
        Ok(())
    })
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
        let message = format!("no checkpoint at {} (train one with `refnpr train`)", path.display());
        return Err(InputError::Missing { path, message }.into());
    }
    let (file, len) = files::open_tagged(&path, MAGIC, "a refnpr checkpoint")?;
    let fields = bin_fields::FieldReader::new(file, len);
    let malformed = |message: String| InputError::Malformed { path: path.clone(), message };
    let p =
        read_payload(fields, optimiser_state).with_context(|| malformed(format!("{} is corrupt", path.display())))?;
    let meta = parse_meta(&p.meta_json).with_context(|| malformed(format!("{}: corrupt metadata", path.display())))?;
    let n = p.coords.len();
    let cols = 3 * crate::scene::sh::num_basis(meta.sh_degree);
    let npts = meta.geometry.num_points();
    if p.density.len() != n || p.sh.len() != n * cols || p.coords.iter().any(|&c| c as usize >= npts) {
        return Err(malformed(format!("{}: grid arrays have inconsistent sizes", path.display())).into());
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

/// The metadata JSON. Files written before the field stored its own
/// settings hold the whole training config under `config` instead of
/// `render`, `data` and `run_config`: they are read by taking the march
/// settings, the render chunk and the load options out of it, and keeping
/// it whole as `run_config` (the same values the older code read).
fn parse_meta(json: &str) -> Result<CheckpointMeta> {
    let mut value: serde_json::Value = serde_json::from_str(json)?;
    if let Some(meta) = value.as_object_mut()
        && !meta.contains_key("render")
        && let Some(config) = meta.remove("config")
    {
        let render = serde_json::json!({ "march": config["march"], "chunk": config["render_chunk"] });
        meta.insert("render".into(), render);
        meta.insert("data".into(), config["data"].clone());
        meta.insert("run_config".into(), config);
    }
    Ok(serde_json::from_value(value)?)
}

/// The file's fields, read straight into their vectors (`bin_fields`);
/// without `optimiser_state` its two arrays are passed over, not read.
fn read_payload(mut r: bin_fields::FieldReader<impl BufRead + Seek>, optimiser_state: bool) -> io::Result<Payload> {
    let mut p = Payload {
        meta_json: r.read_str()?,
        coords: r.read_vec(u32::from_le_bytes)?,
        density: r.read_vec(f32::from_le_bytes)?,
        sh: r.read_vec(f32::from_le_bytes)?,
        opt_density: Vec::new(),
        opt_sh: Vec::new(),
    };
    if optimiser_state {
        p.opt_density = r.read_vec(f32::from_le_bytes)?;
        p.opt_sh = r.read_vec(f32::from_le_bytes)?;
    } else {
        r.skip_vec::<4>()?;
        r.skip_vec::<4>()?;
    }
    Ok(p)
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
    let dataset = crate::scene::data::load(&dir, &ck.meta.data)
        .with_context(|| format!("loading the run's dataset {} (pass --data to use another)", dir.display()))?;
    Ok((ck, dataset))
}
