//! Photorealistic fitting of the radiance grid (Plenoxels-style).
//!
//! Each step: plain Rust draws a batch of training rays and marches them
//! (`render::generate_samples`); the rows of the grid those samples touch
//! (plus their +x/+y/+z neighbours, for total variation) are gathered into a
//! small leaf tensor that requires grad; the Burn graph renders the batch,
//! adds the TV terms and back-propagates; RMSprop then updates just those
//! rows of the grid and of its running averages ("lazy" RMSprop, as
//! Plenoxels' sparse updates). Cost per step is proportional to the batch,
//! not to the grid.
//!
//! RMSprop rather than Adam: it is what Plenoxels uses with published,
//! well-tested learning rates for density (30) and SH (1e-2), and its
//! per-coordinate normalisation copes with the very different gradient
//! scales of density and colour.

use crate::camera::Ray;
use crate::checkpoint::{self, CheckpointMeta};
use crate::config::TrainConfig;
use crate::data::{Dataset, View};
use crate::grid::{GridGeometry, RadianceGrid};
use crate::metrics;
use crate::render::{self, BatchTensors};
use crate::tensor_util::{floats, indices, scalar, to_vec};
use anyhow::{Context, Result};
use burn::tensor::{Device, IndexingUpdateOp, Tensor};
use indicatif::{ProgressBar, ProgressStyle};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// RMSprop running averages of squared gradients, one per grid row.
pub struct RmsState {
    pub density: Tensor<2>,
    pub sh: Tensor<2>,
}

impl RmsState {
    pub fn zeros(grid: &RadianceGrid) -> Self {
        let d = grid.device();
        let n = grid.num_rows();
        Self { density: Tensor::zeros([n, 1], &d), sh: Tensor::zeros([n, 3 * grid.num_basis()], &d) }
    }
}

/// A training run's state.
pub struct Trainer {
    pub grid: RadianceGrid,
    pub state: RmsState,
    pub config: TrainConfig,
    pub step: usize,
    pub train_seconds: f64,
    /// All training rays and their colours.
    rays: Vec<Ray>,
    colours: Vec<[f32; 3]>,
    background: [f32; 3],
    /// Empty-space skipping structure of the current grid (None: rebuild).
    occupancy: Option<render::BlockOccupancy>,
    /// The rows of the current step (reused between steps).
    subset: RowSubset,
}

/// Numbers of one optimisation step.
#[derive(Debug, Clone, Copy)]
pub struct StepStats {
    pub mse: f32,
    pub samples: usize,
    pub rows: usize,
}

/// A subset of grid rows (those a step touches) and the map grid row ->
/// local index. Kept between steps: starting a new subset resets only the
/// entries the last one set, so its cost follows the subset (a few hundred
/// thousand rows), not the grid (millions).
#[derive(Debug, Default)]
pub struct RowSubset {
    local_of: Vec<i32>,
    rows: Vec<i32>,
}

impl RowSubset {
    /// Empties the subset for a grid of `num_rows` rows.
    pub fn clear(&mut self, num_rows: usize) {
        if self.local_of.len() == num_rows {
            for &r in &self.rows {
                self.local_of[r as usize] = -1;
            }
        } else {
            self.local_of = vec![-1; num_rows];
        }
        self.rows.clear();
    }

    /// The subset of the distinct rows in `rows`, in first-seen order.
    pub fn of(num_rows: usize, rows: &[i32]) -> Self {
        let mut s = Self::default();
        s.reset_to(num_rows, rows);
        s
    }

    /// Clears, then adds the distinct rows of `rows` in first-seen order.
    pub fn reset_to(&mut self, num_rows: usize, rows: &[i32]) {
        self.clear(num_rows);
        for &r in rows {
            self.insert(r);
        }
    }

    /// Local index of `row`, adding it at the end if new.
    pub fn insert(&mut self, row: i32) -> i32 {
        let slot = &mut self.local_of[row as usize];
        if *slot < 0 {
            *slot = self.rows.len() as i32;
            self.rows.push(row);
        }
        *slot
    }

    /// Local index of `row` (-1 when not in the subset).
    pub fn local(&self, row: i32) -> i32 {
        self.local_of[row as usize]
    }

    /// The grid rows, in local order.
    pub fn rows(&self) -> &[i32] {
        &self.rows
    }

    /// Exchanges the local indices `i` and `j`.
    fn swap(&mut self, i: usize, j: usize) {
        self.rows.swap(i, j);
        self.local_of[self.rows[i] as usize] = i as i32;
        self.local_of[self.rows[j] as usize] = j as i32;
    }
}

/// The TV terms of a step: for each of the first `num_core` local rows, the
/// local index of its +x, +y, +z neighbour (itself if none).
struct TvNeighbours {
    neighbours: [Vec<i32>; 3],
    num_core: usize,
}

/// Fills `subset` with the rows `corner_rows` touch, then moves a random
/// `tv_fraction` of them to the front (a deterministic random subset, as
/// Plenoxels regularises a random subset of voxels each step): those get TV
/// terms, and their neighbours join the subset.
fn step_rows(grid: &RadianceGrid, corner_rows: &[i32], subset: &mut RowSubset, tv_fraction: f32, rng: &mut ChaCha8Rng) -> TvNeighbours {
    subset.reset_to(grid.num_rows(), corner_rows);
    let touched = subset.rows().len();
    let num_core = ((touched as f32 * tv_fraction).ceil() as usize).min(touched);
    for i in 0..num_core {
        let j = rng.random_range(i..touched);
        subset.swap(i, j);
    }
    let geo = grid.geometry;
    let mut neighbours: [Vec<i32>; 3] = [Vec::with_capacity(num_core), Vec::with_capacity(num_core), Vec::with_capacity(num_core)];
    for li in 0..num_core {
        let [i, j, k] = geo.unflat(grid.coords[subset.rows()[li] as usize] as usize);
        let ijk = [i, j, k];
        for (axis, list) in neighbours.iter_mut().enumerate() {
            let mut n = ijk;
            n[axis] += 1;
            let nb = if n[axis] < geo.res[axis] { grid.links[geo.flat(n[0], n[1], n[2])] } else { -1 };
            list.push(if nb < 0 { li as i32 } else { subset.insert(nb) });
        }
    }
    TvNeighbours { neighbours, num_core }
}

/// Total variation sum_voxels sum_channels sqrt(dx^2 + dy^2 + dz^2 + eps) / voxels.
fn total_variation(values: Tensor<2>, lr: &TvNeighbours, device: &Device) -> Tensor<1> {
    let n = lr.num_core;
    let core = values.clone().narrow(0, 0, n);
    let mut sq = None;
    for nb in &lr.neighbours {
        let d = crate::tensor_util::select_rows(values.clone(), indices(nb.clone(), device)) - core.clone();
        let d2 = d.clone() * d;
        sq = Some(match sq {
            None => d2,
            Some(s) => s + d2,
        });
    }
    (sq.unwrap() + 1e-9).sqrt().sum() / n as f32
}

/// Exponential decay from `a` to `b` over `t` in [0, 1].
pub(crate) fn log_lerp(a: f32, b: f32, t: f32) -> f32 {
    (a.ln() * (1.0 - t) + b.ln() * t).exp()
}

impl Trainer {
    /// A fresh run on a dataset.
    pub fn new(dataset: &Dataset, config: TrainConfig, backend_device: &Device) -> Result<Self> {
        config.validate()?;
        let geo = GridGeometry::new(config.grid.initial_res, dataset.bbox_min, dataset.bbox_max);
        let grid = RadianceGrid::new_dense(geo, config.grid.sh_degree, config.grid.init_density, backend_device)?;
        let state = RmsState::zeros(&grid);
        Ok(Self::assemble(dataset, config, grid, state, 0, 0.0))
    }

    /// Resumes from a checkpoint.
    pub fn resume(dataset: &Dataset, ckpt_path: &Path, backend_device: &Device) -> Result<Self> {
        let ck = checkpoint::load(ckpt_path, backend_device)?;
        let state = RmsState { density: ck.opt_density, sh: ck.opt_sh };
        Ok(Self::assemble(dataset, ck.meta.config.clone(), ck.grid, state, ck.meta.step, ck.meta.train_seconds))
    }

    fn assemble(dataset: &Dataset, config: TrainConfig, grid: RadianceGrid, state: RmsState, step: usize, secs: f64) -> Self {
        let (rays, colours) = training_rays(&dataset.train, dataset);
        Self {
            grid,
            state,
            config,
            step,
            train_seconds: secs,
            rays,
            colours,
            background: dataset.background,
            occupancy: None,
            subset: RowSubset::default(),
        }
    }

    /// Learning rates at the current step.
    fn learning_rates(&self) -> (f32, f32) {
        let o = &self.config.optim;
        let t = (self.step as f32 / o.steps.max(1) as f32).min(1.0);
        let mut lr_d = log_lerp(o.lr_density, o.lr_density_final, t);
        if o.lr_delay_steps > 0 {
            let ramp = (self.step as f32 / o.lr_delay_steps as f32).min(1.0);
            lr_d *= o.lr_delay_mult + (1.0 - o.lr_delay_mult) * (0.5 * std::f32::consts::PI * ramp).sin();
        }
        (lr_d, log_lerp(o.lr_sh, o.lr_sh_final, t))
    }

    /// Applies the coarse-to-fine schedule if this step is an upsampling step.
    fn maybe_upsample(&mut self) -> Result<bool> {
        let g = &self.config.grid;
        if let Some(i) = g.upsample_steps.iter().position(|&s| s == self.step) {
            let res = g.upsample_res[i];
            self.grid.prune(g.prune_threshold);
            self.grid.upsample(res)?;
            self.state = RmsState::zeros(&self.grid);
            self.occupancy = None;
            return Ok(true);
        }
        Ok(false)
    }

    /// One optimisation step.
    pub fn step_once(&mut self) -> Result<StepStats> {
        self.maybe_upsample()?;
        let cfg = self.config.clone();
        let plain = self.grid.device();
        // Deterministic per step, so a resumed run draws the same batches.
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed ^ (self.step as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let n = cfg.optim.batch_rays;
        let picks: Vec<usize> = (0..n).map(|_| rng.random_range(0..self.rays.len())).collect();
        let rays: Vec<Ray> = picks.iter().map(|&i| self.rays[i]).collect();
        let target: Vec<f32> = picks.iter().flat_map(|&i| self.colours[i]).collect();

        let occupancy = self.occupancy.get_or_insert_with(|| render::BlockOccupancy::of(&self.grid));
        let batch = render::Marcher::with_occupancy(&self.grid, occupancy).samples(&rays, &cfg.march);
        let local = step_rows(&self.grid, &batch.corner_rows, &mut self.subset, cfg.optim.tv_fraction, &mut rng);
        let rows_t = indices(self.subset.rows().to_vec(), &plain);
        let subset = &self.subset;
        let bt = BatchTensors::new(&batch, Some(&|r: i32| subset.local(r)), &plain);

        let ld = self.grid.density.clone().select(0, rows_t.clone()).autodiff().require_grad();
        let ls = self.grid.sh.clone().select(0, rows_t.clone()).autodiff().require_grad();
        let out = render::composite(ld.clone(), ls.clone(), &bt, self.background);
        let target_t = floats(target, [n, 3], &plain);
        let diff = out.rgb - target_t;
        let mse = (diff.clone() * diff).mean();
        let mut loss = mse.clone();
        if cfg.optim.tv_density > 0.0 && local.num_core > 0 {
            loss = loss + total_variation(ld.clone(), &local, &plain) * cfg.optim.tv_density;
        }
        if cfg.optim.tv_sh > 0.0 && local.num_core > 0 {
            loss = loss + total_variation(ls.clone(), &local, &plain) * cfg.optim.tv_sh;
        }
        let grads = loss.backward();
        let mse_value = scalar(mse.inner());
        let (lr_d, lr_s) = self.learning_rates();
        if let (Some(gd), Some(gs)) = (ld.grad(&grads), ls.grad(&grads)) {
            let beta = cfg.optim.rmsprop_beta;
            let eps = cfg.optim.eps;
            let new_d = ld.inner() + rmsprop_rows(&mut self.grid.density, &mut self.state.density, &rows_t, gd, lr_d, beta, eps);
            rmsprop_rows(&mut self.grid.sh, &mut self.state.sh, &rows_t, gs, lr_s, beta, eps);
            for (r, v) in self.subset.rows().iter().zip(to_vec(new_d)) {
                self.grid.density_cpu[*r as usize] = v;
            }
        }
        self.step += 1;
        Ok(StepStats { mse: mse_value, samples: batch.num_samples(), rows: self.subset.rows().len() })
    }

    /// The metadata a checkpoint of this run carries.
    pub fn meta(&self, dataset: &Dataset) -> CheckpointMeta {
        CheckpointMeta {
            step: self.step,
            geometry: self.grid.geometry,
            sh_degree: self.grid.sh_degree,
            ndc: dataset.ndc,
            kind: dataset.kind,
            background: dataset.background,
            near_far: dataset.near_far,
            data_dir: dataset.root.clone(),
            config: self.config.clone(),
            train_seconds: self.train_seconds,
        }
    }

    pub fn save(&self, dataset: &Dataset, out: &Path) -> Result<()> {
        checkpoint::save(&out.join(checkpoint::CHECKPOINT_FILE), &self.meta(dataset), &self.grid, &self.state.density, &self.state.sh)
    }
}

/// Lazy RMSprop on the given rows: v = b v + (1-b) g^2; x -= lr g / (sqrt(v) + eps).
/// Returns the rows' update (what was added to them).
#[allow(clippy::too_many_arguments)]
fn rmsprop_rows(
    param: &mut Tensor<2>,
    avg: &mut Tensor<2>,
    rows: &burn::tensor::Tensor<1, burn::tensor::Int>,
    grad: Tensor<2>,
    lr: f32,
    beta: f32,
    eps: f32,
) -> Tensor<2> {
    let v_old = avg.clone().select(0, rows.clone());
    let v_new = v_old.clone() * beta + grad.clone() * grad.clone() * (1.0 - beta);
    let update = grad / (v_new.clone().sqrt() + eps) * (-lr);
    // Take the tensors out of their slots so they are uniquely owned and the
    // backend can update them in place instead of copying the whole grid.
    let device = param.device();
    let a = std::mem::replace(avg, Tensor::zeros([1, 1], &device));
    *avg = crate::tensor_util::assign_rows(a, rows.clone(), v_new - v_old, IndexingUpdateOp::Add);
    let p = std::mem::replace(param, Tensor::zeros([1, 1], &device));
    *param = crate::tensor_util::assign_rows(p, rows.clone(), update.clone(), IndexingUpdateOp::Add);
    update
}

/// Rays and colours of every pixel of the given views.
pub fn training_rays(views: &[View], dataset: &Dataset) -> (Vec<Ray>, Vec<[f32; 3]>) {
    let mut rays = Vec::new();
    let mut colours = Vec::new();
    for v in views {
        rays.extend(v.camera.rays(dataset.ndc.as_ref()));
        colours.extend(crate::imageio::pixels(&v.rgb));
    }
    (rays, colours)
}

/// Quality of a grid on a set of views.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct EvalReport {
    pub psnr: f32,
    pub ssim: f32,
    pub per_view_psnr: Vec<f32>,
}

/// Renders each view, compares with its photo, optionally writes PNGs to `out`.
pub fn evaluate(grid: &RadianceGrid, dataset: &Dataset, views: &[View], config: &TrainConfig, out: Option<&Path>) -> Result<EvalReport> {
    let mut psnrs = Vec::new();
    let mut ssims = Vec::new();
    for (i, v) in views.iter().enumerate() {
        let r = render::render_view(grid, &v.camera, dataset.ndc.as_ref(), &config.march, dataset.background, config.render_chunk);
        psnrs.push(metrics::psnr(&r.rgb, &v.rgb));
        ssims.push(metrics::ssim(&r.rgb, &v.rgb, r.width as usize, r.height as usize));
        if let Some(dir) = out {
            crate::imageio::save_png(&dir.join(format!("{i:04}.png")), r.width, r.height, &r.rgb)?;
        }
    }
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len().max(1) as f32;
    Ok(EvalReport { psnr: mean(&psnrs), ssim: mean(&ssims), per_view_psnr: psnrs })
}

/// What `refnpr train` writes to `RUN/metrics.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrainMetrics {
    pub test_psnr: f32,
    pub test_ssim: f32,
    pub train_seconds: f64,
    pub steps: usize,
    pub backend: String,
    pub dataset: PathBuf,
    pub kind: String,
    pub grid_res: [usize; 3],
    pub active_voxels: usize,
    pub per_view_psnr: Vec<f32>,
    pub peak_rss_mb: Option<f64>,
}

/// Peak resident memory of this process (Linux), in MB.
pub fn peak_rss_mb() -> Option<f64> {
    proc_status_mb("VmHWM:")
}

/// A memory line of /proc/self/status (`VmRSS:`, `VmHWM:`, ...) in MB (Linux).
pub fn proc_status_mb(key: &str) -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let l = s.lines().find(|l| l.starts_with(key))?;
    Some(l.split_whitespace().nth(1)?.parse::<f64>().ok()? / 1024.0)
}

/// Trains (or resumes) a run in `out`, writes checkpoints, test renders and metrics.
pub fn run_training(dataset: &Dataset, config: TrainConfig, out: &Path, backend: crate::backend::BackendKind, resume: bool) -> Result<TrainMetrics> {
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let device = backend.device();
    let ckpt = out.join(checkpoint::CHECKPOINT_FILE);
    let mut trainer = if resume && ckpt.exists() {
        let t = Trainer::resume(dataset, &ckpt, &device)?;
        eprintln!("resuming {} at step {}", ckpt.display(), t.step);
        t
    } else {
        Trainer::new(dataset, config, &device)?
    };
    std::fs::write(out.join("config.toml"), toml::to_string_pretty(&trainer.config)?)
        .with_context(|| format!("cannot write {}", out.join("config.toml").display()))?;
    let total = trainer.config.optim.steps;
    let bar = progress_bar(total as u64, trainer.step as u64);
    let started = Instant::now();
    let mut seg_start = Instant::now();
    let mut rays_done = 0usize;
    let log_every = (total / 20).max(1);
    while trainer.step < total {
        let st = trainer.step_once()?;
        rays_done += trainer.config.optim.batch_rays;
        let psnr = metrics::psnr_from_mse(st.mse);
        let rays_s = rays_done as f64 / seg_start.elapsed().as_secs_f64().max(1e-9);
        bar.set_position(trainer.step as u64);
        bar.set_message(format!("loss {:.5} psnr {:.2} | {:.0} rays/s | {} samples", st.mse, psnr, rays_s, st.samples));
        if bar.is_hidden() && (trainer.step % log_every == 0 || trainer.step == total) {
            eprintln!("step {}/{} loss {:.5} psnr {:.2} rays/s {:.0} voxels {}", trainer.step, total, st.mse, psnr, rays_s, trainer.grid.num_rows());
        }
        if trainer.step % trainer.config.checkpoint_every == 0 && trainer.step < total {
            trainer.train_seconds += seg_start.elapsed().as_secs_f64();
            seg_start = Instant::now();
            rays_done = 0;
            trainer.save(dataset, out)?;
        }
    }
    trainer.train_seconds += seg_start.elapsed().as_secs_f64();
    bar.finish_and_clear();
    trainer.save(dataset, out)?;
    eprintln!("trained {} steps in {:.1} s; evaluating {} test views", trainer.step, started.elapsed().as_secs_f64(), dataset.test.len());
    let report = evaluate(&trainer.grid, dataset, &dataset.test, &trainer.config, Some(&out.join("test")))?;
    let metrics = TrainMetrics {
        test_psnr: report.psnr,
        test_ssim: report.ssim,
        train_seconds: trainer.train_seconds,
        steps: trainer.step,
        backend: backend.to_string(),
        dataset: dataset.root.clone(),
        kind: dataset.kind.to_string(),
        grid_res: trainer.grid.geometry.res,
        active_voxels: trainer.grid.num_rows(),
        per_view_psnr: report.per_view_psnr,
        peak_rss_mb: peak_rss_mb(),
    };
    std::fs::write(out.join("metrics.json"), serde_json::to_string_pretty(&metrics)?)?;
    Ok(metrics)
}

/// A progress bar on a terminal; hidden (with periodic log lines) otherwise.
pub fn progress_bar(len: u64, pos: u64) -> ProgressBar {
    let bar = if std::io::stderr().is_terminal() { ProgressBar::new(len) } else { ProgressBar::hidden() };
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} {msg}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_position(pos);
    bar
}

#[cfg(test)]
mod tests {
    use super::RowSubset;

    /// A reused subset must behave as a fresh one: rows of the previous
    /// subset are forgotten, local indices follow first-seen order.
    #[test]
    fn a_reused_row_subset_forgets_the_previous_rows() {
        let mut s = RowSubset::default();
        s.reset_to(10, &[7, 3, 7, 9, 3]);
        assert_eq!(s.rows(), &[7, 3, 9]);
        assert_eq!((s.local(7), s.local(3), s.local(9), s.local(0)), (0, 1, 2, -1));
        s.reset_to(10, &[9, 1]);
        assert_eq!(s.rows(), &[9, 1]);
        assert_eq!((s.local(9), s.local(1), s.local(7), s.local(3)), (0, 1, -1, -1));
        assert_eq!(s.insert(4), 2);
        assert_eq!(s.insert(9), 0);
        // A grid of another size starts from scratch.
        s.reset_to(5, &[4]);
        assert_eq!((s.rows(), s.local(4), s.local(1)), (&[4][..], 0, -1));
        let fresh = RowSubset::of(10, &[2, 2, 5]);
        assert_eq!(fresh.rows(), &[2, 5]);
    }
}
