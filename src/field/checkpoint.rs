//! Checkpoints: everything needed to render (grid, SH degree, bounds, NDC,
//! dataset kind, render settings) plus the optimiser state and the writing
//! run's config for resuming, in one file written atomically (temporary
//! file, then rename): a safetensors file, which Python (`safetensors`,
//! numpy), PyTorch and `burn-store` read without refnpr.

use crate::field::environment::Environment;
use crate::field::grid::{GridGeometry, RadianceGrid};
use crate::field::view::{RenderSettings, ViewRender, ViewRenderer};
use crate::kernels::rows_op;
use crate::scene::camera::{Camera, NdcParams};
use crate::scene::data::{DatasetKind, LoadOptions};
use crate::util::input::InputError;
use crate::util::safetensors::{self, DType};
use crate::util::tensor::floats;
use crate::util::{bin_fields, files};
use anyhow::{Context, Result, bail};

use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::{self, BufRead, Read, Seek, Write};
use std::path::{Path, PathBuf};

pub const CHECKPOINT_FILE: &str = "checkpoint.bin";
/// The tag of the files written before checkpoints were safetensors (still read).
const MAGIC: &[u8; 8] = b"REFNPRG1";
/// What a checkpoint's safetensors metadata says it is (`format`, `version`).
pub const FORMAT: &str = "refnpr-checkpoint";
const VERSION: &str = "2";

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

/// A checkpoint's content: in a safetensors file the tensors `coords`
/// (U32 `[rows]`), `density` (F32 `[rows, 1]`), `sh` (F32 `[rows, 3 x
/// basis]`), `opt_density`, `opt_sh` (RMSprop's averages, the same shapes,
/// or 0 rows), and the metadata strings `format` = [`FORMAT`], `version`,
/// `meta` (the [`CheckpointMeta`] as JSON). Files written before hold
/// bincode's layout of these fields after the tag `REFNPRG1`
/// (`util::bin_fields`, read by [`read_legacy`]).
struct Payload {
    meta_json: String,
    coords: Vec<u32>,
    density: Vec<f32>,
    sh: Vec<f32>,
    opt_density: Vec<f32>,
    opt_sh: Vec<f32>,
    /// The far background, when the field has one (tensor `far`, F32
    /// `[height, width, 3]`), and its RMSprop averages (`opt_far`, the same
    /// shape, or empty).
    far: Option<Environment>,
    opt_far: Vec<f32>,
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
    /// The far background's RMSprop averages (empty when absent or not loaded).
    pub opt_far: Vec<f32>,
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

/// Writes a checkpoint (atomically: `files::write_atomic`) as a
/// safetensors file (`Payload`). The grid and optimiser arrays go from
/// their tensors to the file in blocks, each block
/// checked for NaN and infinities on the way: a diverged field is refused
/// and the file keeps its previous content.
pub fn save(
    path: &Path,
    meta: &CheckpointMeta,
    grid: &RadianceGrid,
    opt_density: &Tensor<2>,
    opt_sh: &Tensor<2>,
    opt_far: &[f32],
) -> Result<()> {
    let meta_json = serde_json::to_string(meta)?;
    let arrays = [
        ("density", &grid.density),
        ("SH colour", &grid.sh),
        ("optimiser state", opt_density),
        ("optimiser state", opt_sh),
    ];
    let nothing_kept = if path.exists() { "" } else { "; nothing was written" };
    let shape = |t: &Tensor<2>| t.shape().dims::<2>().to_vec();
    let metadata = BTreeMap::from([
        ("format".to_string(), FORMAT.to_string()),
        ("version".to_string(), VERSION.to_string()),
        ("meta".to_string(), meta_json),
    ]);
    let mut tensors = vec![
        ("coords", DType::U32, vec![grid.coords.len()]),
        ("density", DType::F32, shape(&grid.density)),
        ("sh", DType::F32, shape(&grid.sh)),
        ("opt_density", DType::F32, shape(opt_density)),
        ("opt_sh", DType::F32, shape(opt_sh)),
    ];
    if let Some(far) = &grid.far {
        if !far.rgb.iter().all(|v| v.is_finite()) {
            bail!("refusing to write {}: the far background holds NaN values{nothing_kept}", path.display());
        }
        tensors.push(("far", DType::F32, vec![far.height, far.width, 3]));
        if opt_far.len() == far.rgb.len() {
            tensors.push(("opt_far", DType::F32, vec![far.height, far.width, 3]));
        }
    }
    let (header, _) = safetensors::header(&tensors, &metadata);
    files::write_atomic(path, |w| {
        let io = |e| files::io_error(e, path);
        let mut scratch = Vec::new();
        w.write_all(&header).map_err(io)?;
        safetensors::write_values(w, &grid.coords, u32::to_le_bytes, &mut scratch).map_err(io)?;
        for (what, values) in arrays {
            rows_op::for_each_row_block(values, SAVE_BLOCK_VALUES, |block| {
                if !block.iter().fold(true, |finite, v| finite & v.is_finite()) {
                    bail!(
                        "refusing to write {} at step {}: the field's {what} holds NaN or infinite values \
                         (the run diverged){nothing_kept}",
                        path.display(),
                        meta.step
                    );
                }
                safetensors::write_values(w, block, f32::to_le_bytes, &mut scratch).map_err(io)
            })?;
        }
        if let Some(far) = &grid.far {
            safetensors::write_values(w, &far.rgb, f32::to_le_bytes, &mut scratch).map_err(io)?;
            if opt_far.len() == far.rgb.len() {
                safetensors::write_values(w, opt_far, f32::to_le_bytes, &mut scratch).map_err(io)?;
            }
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
    load_parts(path, device, optimiser_state, false)
}

/// [`load_run`] with the colour cut to its view-independent band (SH
/// degree 0) on the host, before anything reaches the device: all a
/// stylization reads of the photoreal field. Lego's SH at degree 2 is nine
/// times the size, and on wgpu may not fit in one of the adapter's buffers
/// when the DC band does. The grid then says degree 0; the metadata keeps
/// the fit's degree.
pub fn load_run_view_independent(
    path: &Path,
    data: Option<&Path>,
    device: &Device,
) -> Result<(Checkpoint, crate::scene::data::Dataset)> {
    let ck = load_parts(path, device, false, true)?;
    let dataset = load_dataset(&ck, data)?;
    Ok((ck, dataset))
}

/// Only the first SH coefficient of each colour channel of `sh` (rows of
/// `3 x nb` coefficients, colour-major): `RadianceGrid::truncate_sh(0)` on the host.
fn dc_band(sh: &[f32], nb: usize) -> Vec<f32> {
    sh.iter().step_by(nb).copied().collect()
}

fn load_parts(path: &Path, device: &Device, optimiser_state: bool, view_independent: bool) -> Result<Checkpoint> {
    let path = resolve(path);
    if !path.exists() {
        let message = format!("no checkpoint at {} (train one with `refnpr train`)", path.display());
        return Err(InputError::Missing { path, message }.into());
    }
    let malformed = |message: String| InputError::Malformed { path: path.clone(), message };
    let p = read_file(&path, optimiser_state)?;
    let meta = parse_meta(&p.meta_json).with_context(|| malformed(format!("{}: corrupt metadata", path.display())))?;
    let n = p.coords.len();
    if meta.sh_degree > 3 {
        return Err(malformed(format!("{}: SH degree {} (at most 3)", path.display(), meta.sh_degree)).into());
    }
    let cols = 3 * crate::scene::sh::num_basis(meta.sh_degree);
    let npts = plausible_lattice(meta.geometry.res, n)
        .ok_or_else(|| malformed(format!("{}: a {:?} lattice for {n} rows", path.display(), meta.geometry.res)))?;
    crate::field::grid::check_fits(meta.geometry.res, n, meta.sh_degree)?;
    let grid_degree = if view_independent { 0 } else { meta.sh_degree };
    let device = &crate::field::grid::placement(n, grid_degree, device)
        .with_context(|| format!("loading {}", path.display()))?;
    if p.density.len() != n || p.sh.len() != n * cols || p.coords.iter().any(|&c| c as usize >= npts) {
        return Err(malformed(format!("{}: grid arrays have inconsistent sizes", path.display())).into());
    }
    let sh = if view_independent { dc_band(&p.sh, cols / 3) } else { p.sh };
    let mut grid = RadianceGrid::from_rows(meta.geometry, grid_degree, p.coords, p.density, sh, device);
    grid.far = p.far;
    let opt_far = if optimiser_state { p.opt_far } else { Vec::new() };
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
    Ok(Checkpoint { source: path, meta, grid, opt_density, opt_sh, opt_far })
}

/// The lattice's point count, when a fit could have written it for `rows`
/// stored rows: the links array (4 bytes a point) is allocated from the
/// metadata alone, so a corrupt resolution must not allocate gigabytes. A
/// fit prunes to far more than one point in 4096 (lego: 1 in 15), and any
/// lattice up to 2^24 points (64 MB of links) passes.
fn plausible_lattice(res: [usize; 3], rows: usize) -> Option<usize> {
    let points = res.iter().try_fold(1usize, |p, &r| p.checked_mul(r))?;
    let bound = (1usize << 24).saturating_add(rows.saturating_mul(4096)).min(i32::MAX as usize);
    (points <= bound && res.iter().all(|&r| r > 0)).then_some(points)
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

/// A checkpoint file's arrays and metadata: safetensors, or the bincode
/// layout of the files written before it (`REFNPRG1`, still read).
fn read_file(path: &Path, optimiser_state: bool) -> Result<Payload> {
    let corrupt = |e: io::Error| InputError::Malformed {
        path: path.to_path_buf(),
        message: format!("{} is corrupt: {e}", path.display()),
    };
    let cannot_read = || format!("cannot read {}", path.display());
    let mut file = std::fs::File::open(path).with_context(cannot_read)?;
    let len = file.metadata().map(|m| m.len()).unwrap_or(0);
    let mut start = [0u8; 9];
    let read = file.read(&mut start).with_context(cannot_read)?;
    if read >= 8 && &start[..8] == MAGIC {
        let (file, len) = files::open_tagged(path, MAGIC, "a refnpr checkpoint")?;
        return Ok(read_legacy(bin_fields::FieldReader::new(file, len), optimiser_state).map_err(corrupt)?);
    }
    if !safetensors::looks_like(&start[..read], len) {
        let message = format!("{} is not a refnpr checkpoint", path.display());
        return Err(InputError::WrongKind { path: path.to_path_buf(), message }.into());
    }
    file.seek(io::SeekFrom::Start(0)).with_context(cannot_read)?;
    let mut r = io::BufReader::new(file);
    read_safetensors(&mut r, len, optimiser_state).map_err(corrupt).map_err(Into::into)
}

/// A safetensors checkpoint: the metadata's `meta` and the five arrays
/// (the optimiser's two passed over, not read, without `optimiser_state`).
fn read_safetensors(r: &mut (impl Read + Seek), len: u64, optimiser_state: bool) -> io::Result<Payload> {
    let safetensors::Header { metadata, entries, data_start: data } = safetensors::read_header(r, len)?;
    let invalid = |m: String| io::Error::new(io::ErrorKind::InvalidData, m);
    if metadata.get("format").map(String::as_str) != Some(FORMAT) {
        return Err(invalid(format!("a safetensors file, but not a refnpr checkpoint (no format \"{FORMAT}\")")));
    }
    let meta_json = metadata.get("meta").cloned().ok_or_else(|| invalid("no meta in the metadata".into()))?;
    let entry = |name: &str, dtype: DType| match entries.get(name) {
        Some(e) if e.dtype == dtype => Ok(e.clone()),
        _ => Err(invalid(format!("no {dtype:?} tensor {name}"))),
    };
    let floats =
        |r: &mut _, name: &str| safetensors::read_values(r, data, &entry(name, DType::F32)?, f32::from_le_bytes);
    let coords = safetensors::read_values(r, data, &entry("coords", DType::U32)?, u32::from_le_bytes)?;
    let (density, sh) = (floats(r, "density")?, floats(r, "sh")?);
    let (opt_density, opt_sh) =
        if optimiser_state { (floats(r, "opt_density")?, floats(r, "opt_sh")?) } else { (Vec::new(), Vec::new()) };
    let far = match entries.get("far") {
        None => None,
        Some(e) if e.dtype == DType::F32 && e.shape.len() == 3 && e.shape[2] == 3 && e.shape[0] * e.shape[1] > 0 => {
            let rgb = safetensors::read_values(r, data, e, f32::from_le_bytes)?;
            Some(Environment { width: e.shape[1], height: e.shape[0], rgb })
        }
        Some(e) => return Err(invalid(format!("a far background of shape {:?} (want [height, width, 3])", e.shape))),
    };
    let opt_far = match (&far, entries.get("opt_far")) {
        (Some(f), Some(e)) if optimiser_state && e.dtype == DType::F32 && e.num_elements() == f.rgb.len() => {
            safetensors::read_values(r, data, e, f32::from_le_bytes)?
        }
        _ => Vec::new(),
    };
    Ok(Payload { meta_json, coords, density, sh, opt_density, opt_sh, far, opt_far })
}

/// The legacy file's fields, read straight into their vectors (`bin_fields`);
/// without `optimiser_state` its two arrays are passed over, not read.
fn read_legacy(mut r: bin_fields::FieldReader<impl BufRead + Seek>, optimiser_state: bool) -> io::Result<Payload> {
    let mut p = Payload {
        meta_json: r.read_str()?,
        coords: r.read_vec(u32::from_le_bytes)?,
        density: r.read_vec(f32::from_le_bytes)?,
        sh: r.read_vec(f32::from_le_bytes)?,
        opt_density: Vec::new(),
        opt_sh: Vec::new(),
        far: None,
        opt_far: Vec::new(),
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
    let dataset = load_dataset(&ck, data)?;
    Ok((ck, dataset))
}

/// The dataset `ck` was trained on (or `data`, when given), read the way the run read it.
pub fn load_dataset(ck: &Checkpoint, data: Option<&Path>) -> Result<crate::scene::data::Dataset> {
    let dir = data.map(Path::to_path_buf).unwrap_or_else(|| ck.meta.data_dir.clone());
    crate::scene::data::load(&dir, &ck.meta.data)
        .with_context(|| format!("loading the run's dataset {} (pass --data to use another)", dir.display()))
}
