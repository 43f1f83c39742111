//! Photorealistic fitting of the radiance grid (Plenoxels-style): the
//! `Trainer` and its one optimisation step.
//!
//! Each step: plain Rust draws a batch of training rays and marches them
//! (`march::Marcher`); the rows of the grid those samples touch
//! (plus their +x/+y/+z neighbours, for total variation) are gathered into a
//! small leaf tensor that requires grad; the Burn graph renders the batch,
//! adds the TV terms and back-propagates (on the CPU backends
//! `field::host_fit` renders and differentiates the batch in plain Rust
//! instead, and only the TV terms go through a graph); RMSprop then updates just those
//! rows of the grid and of its running averages ("lazy" RMSprop, as
//! Plenoxels' sparse updates). Cost per step is proportional to the batch,
//! not to the grid (RMSprop and TV: `field::optim`).

use anyhow::{Result, bail};
use burn::tensor::{Device, Int, Tensor};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use std::path::Path;

use crate::field::RayKernel;
use crate::field::checkpoint::{self, CheckpointMeta};
use crate::field::composite::{self, BatchTensors};
use crate::field::environment::{Environment, FarOptimiser};
use crate::field::grid::{GridGeometry, RadianceGrid, kept_on_host};
use crate::field::host_fit::{self, FitBuffers};
use crate::field::march::{BlockOccupancy, Marcher, SampleBatch};
use crate::field::optim::{
    RmsStart, Rmsprop, RowSubset, TvLinks, TvNorm, add_tv_gradient, add_tv_gradient_per_channel, log_lerp,
    total_variation,
};
use crate::kernels::rows_op::{PREFETCH_AHEAD, read_rows, read_rows_into};
use crate::photo::config::{FarBackground, GridConfig, TrainConfig};
use crate::scene::camera::Ray;
use crate::scene::data::{Dataset, DatasetKind};
use crate::util::backend::max_buffer_bytes;
use crate::util::device_stats::PeakProbe;
use crate::util::profile::StepProfile;
use crate::util::rng::{Stream, step_rng};
use crate::util::tensor::{floats, indices, is_host_memory, scalar, select_rows, to_vec};
use crate::util::transfer::human_bytes;

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
    /// The far background's optimiser (when the grid has one).
    far_optimiser: FarOptimiser,
    /// Empty-space skipping structure of the current grid (None: rebuild).
    occupancy: Option<BlockOccupancy>,
    /// The rows of the current step (reused between steps).
    subset: RowSubset,
    /// The plain-Rust gradient pass's buffers (reused between steps).
    fit_buffers: FitBuffers,
    /// The host step's copies of its rows and corner indices (reused between steps).
    step_buffers: StepBuffers,
    /// The step's batch of samples (reused between steps).
    batch: SampleBatch,
    /// Wall time per part of a step (march, rows, gradient, update),
    /// summed over the steps since it was last cleared.
    pub profile: StepProfile,
    /// Whether the steps run on the fused plain-Rust pass (`field::host_fit`)
    /// or the Burn graph: `ray_kernel`, resolved once for the run's device.
    host_kernel: bool,
    /// The run's device, where the steps render and differentiate. The grid
    /// is kept on it, or in host memory when it outgrows the device's
    /// buffers (`field::grid::placement`); the step's rows then travel.
    compute: Device,
    /// The most samples the graph step renders in one graph: None takes
    /// the device's (`composite::max_samples_per_call`).
    max_samples_per_call: Option<usize>,
    /// The graph step's peak device memory, when a measurement enables it.
    pub memory_probe: PeakProbe,
}

/// The host step's working copies, kept from one step to the next: on
/// fern's fine grid the SH rows alone are tens of MB, and fresh buffers
/// every step cost more in page faults than the copies themselves.
#[derive(Debug, Default)]
struct StepBuffers {
    /// The step rows' densities, `[rows]`.
    density: Vec<f32>,
    /// The step rows' SH coefficients, `[rows, 3 nb]`.
    sh: Vec<f32>,
    /// The step row of each corner of the batch.
    corners: Vec<i32>,
}

/// Numbers of one optimisation step.
#[derive(Debug, Clone, Copy)]
pub struct StepStats {
    pub mse: f32,
    pub samples: usize,
    /// The longest ray's samples (the renderer pads every ray to it).
    pub max_samples_per_ray: usize,
    pub rows: usize,
}

/// The TV terms of a step: for each of the first `num_core` local rows, the
/// local index of its +x, +y, +z neighbour (itself if none).
struct TvNeighbours {
    neighbours: [Vec<i32>; 3],
    num_core: usize,
}

impl TvNeighbours {
    /// Plenoxels' per-channel TV, averaged over the core rows, of `values`
    /// (the step's local rows; the core rows come first).
    fn total_variation(&self, values: Tensor<2>, device: &Device) -> Tensor<1> {
        let centre = values.clone().narrow(0, 0, self.num_core);
        let neighbours = self.neighbours.iter().map(|nb| select_rows(values.clone(), indices(nb.clone(), device)));
        total_variation(centre, neighbours, TvNorm::PerChannel) / self.num_core as f32
    }
}

/// Fills `subset` with the rows `corner_rows` touch, then moves a random
/// `tv_fraction` of them to the front (a deterministic random subset, as
/// Plenoxels regularises a random subset of voxels each step): those get TV
/// terms, and their neighbours join the subset.
fn step_rows(
    grid: &RadianceGrid,
    corner_rows: &[i32],
    subset: &mut RowSubset,
    tv_fraction: f32,
    rng: &mut ChaCha8Rng,
) -> TvNeighbours {
    // The random subset is drawn on the rows alone, before the subset
    // writes its map (one write per row instead of two per move).
    let mut num_core = 0;
    subset.reset_to_arranged(grid.num_rows(), corner_rows, |rows| {
        let touched = rows.len();
        num_core = ((touched as f32 * tv_fraction).ceil() as usize).min(touched);
        for i in 0..num_core {
            let j = rng.random_range(i..touched);
            rows.swap(i, j);
        }
    });
    // The grid lookups (random reads of the links) in parallel; the
    // insertions, which number the new rows, in order, each row's entry of
    // the map asked for a few centres ahead.
    let grid_neighbours: Vec<[Option<i32>; 3]> = subset.rows()[..num_core]
        .par_iter()
        .with_min_len(1 << 12)
        .map(|&row| grid.neighbour_rows(row as usize))
        .collect();
    let mut neighbours: [Vec<i32>; 3] = std::array::from_fn(|_| Vec::with_capacity(num_core));
    for (li, found) in grid_neighbours.iter().enumerate() {
        for nb in grid_neighbours.get(li + PREFETCH_AHEAD).into_iter().flatten().flatten() {
            subset.prefetch(*nb);
        }
        for (list, nb) in neighbours.iter_mut().zip(found) {
            list.push(match nb {
                Some(nb) => subset.insert(*nb),
                None => li as i32,
            });
        }
    }
    TvNeighbours { neighbours, num_core }
}

/// Refuses a batch with a ray whose samples alone would not fit in one of
/// the device's buffers (the graph step cuts larger batches into runs of
/// rays, but a ray is rendered whole): wgpu would otherwise read garbage or
/// fail inside the step, far from the cause.
fn check_buffer_limit(batch: &SampleBatch, columns: usize, device: &Device) -> Result<()> {
    let (most, longest) = (composite::max_samples_per_call(device, columns), batch.max_samples_per_ray());
    if longest > most {
        bail!(
            "a ray of this step has {longest} samples, more than the {most} whose gathered corners (8 x {columns} \
             coefficients each) fit in one of the wgpu adapter's buffers ({}): raise [march] step, use a lower \
             grid.sh_degree, or use --backend flex",
            max_buffer_bytes(device).map(human_bytes).unwrap_or_default(),
        );
    }
    Ok(())
}

impl Trainer {
    /// A fresh run on a dataset.
    pub fn new(dataset: &Dataset, config: TrainConfig, backend_device: &Device) -> Result<Self> {
        config.validate()?;
        let geo = GridGeometry::new(config.grid.initial_res, dataset.bbox_min, dataset.bbox_max);
        let mut grid = RadianceGrid::new_dense(geo, config.grid.sh_degree, config.grid.init_density, backend_device)?;
        if far_decision(dataset, &config.grid)?.0 {
            grid.far = Some(initial_far(dataset, config.grid.far_resolution_at(0)));
        }
        let state = RmsState::zeros(&grid);
        Ok(Self::assemble(dataset, config, grid, state, 0, 0.0, backend_device))
    }

    /// Resumes from a checkpoint.
    pub fn resume(dataset: &Dataset, ckpt_path: &Path, backend_device: &Device) -> Result<Self> {
        let ck = checkpoint::load(ckpt_path, backend_device)?;
        let config: TrainConfig = serde_json::from_value(ck.meta.run_config.clone()).map_err(|e| {
            anyhow::anyhow!(
                "{} was not written by `refnpr train` (its config: {e}): it cannot resume a fit",
                ck.source.display()
            )
        })?;
        let state = RmsState { density: ck.opt_density, sh: ck.opt_sh };
        let mut t =
            Self::assemble(dataset, config, ck.grid, state, ck.meta.step, ck.meta.train_seconds, backend_device);
        t.far_optimiser.mean_square = ck.opt_far;
        Ok(t)
    }

    fn assemble(
        dataset: &Dataset,
        config: TrainConfig,
        grid: RadianceGrid,
        state: RmsState,
        step: usize,
        secs: f64,
        compute: &Device,
    ) -> Self {
        let (rays, colours) = dataset.pixel_rays(&dataset.train);
        let host_kernel = config.ray_kernel.is_host(compute);
        Self {
            host_kernel,
            compute: compute.clone(),
            grid,
            state,
            config,
            step,
            train_seconds: secs,
            rays,
            colours,
            background: dataset.background,
            far_optimiser: FarOptimiser::default(),
            occupancy: None,
            subset: RowSubset::default(),
            fit_buffers: FitBuffers::default(),
            step_buffers: StepBuffers::default(),
            batch: SampleBatch::default(),
            profile: StepProfile::default(),
            max_samples_per_call: None,
            memory_probe: PeakProbe::default(),
        }
    }

    /// Whether the grid is kept in host memory, having outgrown the run
    /// device's buffers (`field::grid::placement`).
    pub fn grid_kept_on_host(&self) -> bool {
        kept_on_host(&self.grid, &self.compute)
    }

    /// The run's device (where the steps render and differentiate).
    pub fn compute_device(&self) -> Device {
        self.compute.clone()
    }

    /// The same run with its steps on another ray kernel (`ray_kernel`):
    /// how a resumed run's step is measured on each (examples/step_costs.rs).
    pub fn with_ray_kernel(mut self, kernel: RayKernel) -> Self {
        self.host_kernel = kernel.is_host(&self.compute);
        self.config.ray_kernel = kernel;
        self
    }

    /// The graph step renders at most `samples` samples in one graph, as on
    /// an adapter with small buffers (tests cut a step into runs with it).
    pub fn with_max_samples_per_call(mut self, samples: usize) -> Self {
        self.max_samples_per_call = Some(samples.max(1));
        self
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
            self.grid.upsample(res, &self.compute)?;
            self.state = RmsState::zeros(&self.grid);
            if let Some(far) = &mut self.grid.far {
                let [width, height] = g.far_resolution_at(i + 1);
                *far = far.resampled(width, height);
                self.far_optimiser = FarOptimiser::default();
            }
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
        let mut rng = step_rng(cfg.seed, Stream::Fit, self.step);
        let n = cfg.optim.batch_rays;
        let picks: Vec<usize> = (0..n).map(|_| rng.random_range(0..self.rays.len())).collect();
        let rays: Vec<Ray> = picks.iter().map(|&i| self.rays[i]).collect();
        let target: Vec<f32> = picks.iter().flat_map(|&i| self.colours[i]).collect();

        let profile = std::mem::take(&mut self.profile);
        let mut batch = std::mem::take(&mut self.batch);
        profile.time("march", || {
            let occupancy = self.occupancy.get_or_insert_with(|| BlockOccupancy::of(&self.grid));
            Marcher::with_occupancy(&self.grid, occupancy).samples_into(&rays, &cfg.march, &mut batch);
        });
        check_buffer_limit(&batch, 3 * self.grid.num_basis(), &self.compute)?;
        let (local, rows_t) = profile.time("rows", || {
            let local = step_rows(&self.grid, &batch.corner_rows, &mut self.subset, cfg.optim.tv_fraction, &mut rng);
            (local, indices(self.subset.rows().to_vec(), &plain))
        });
        let (mse_value, far_grad) = match self.host_kernel {
            true => self.host_step(&batch, &local, &rows_t, &target, &profile),
            false => self.graph_step(&batch, &local, &rows_t, &target, &profile),
        };
        profile.time("far", || self.far_step(&rays, &far_grad));
        self.profile = profile;
        self.step += 1;
        let stats = StepStats {
            mse: mse_value,
            samples: batch.num_samples(),
            max_samples_per_ray: batch.max_samples_per_ray(),
            rows: self.subset.rows().len(),
        };
        self.batch = batch;
        Ok(stats)
    }

    /// The far background's update from its colours' gradients per ray
    /// (`[rays, 3]`; empty when the grid has none), at the SH's learning rate.
    fn far_step(&mut self, rays: &[Ray], per_ray: &[f32]) {
        let (_, lr) = self.learning_rates();
        let o = &self.config.optim;
        let Some(far) = self.grid.far.as_mut() else { return };
        let mut grad = vec![0.0f32; far.rgb.len()];
        for (ray, g) in rays.iter().zip(per_ray.chunks_exact(3)) {
            far.add_gradient(ray.view_dir, [g[0], g[1], g[2]], &mut grad);
        }
        self.far_optimiser.step(far, &grad, lr, o.rmsprop_beta, o.eps);
    }

    /// The RMSprop optimiser of this run.
    fn rmsprop(&self) -> Rmsprop {
        let o = &self.config.optim;
        Rmsprop { beta: o.rmsprop_beta, eps: o.eps, start: RmsStart::Zero }
    }

    /// The step through the Burn graph (the GPU path): the gradients by
    /// autodiff, then RMSprop on the step's rows as tensor operations.
    /// Returns the batch's MSE.
    fn graph_step(
        &mut self,
        batch: &SampleBatch,
        local: &TvNeighbours,
        rows_t: &Tensor<1, Int>,
        target: &[f32],
        profile: &StepProfile,
    ) -> (f32, Vec<f32>) {
        let (gd, gs, mse, far) = profile.time("gradient", || self.graph_gradients(batch, local, rows_t, target));
        profile.time("update", || {
            let (lr_d, lr_s) = self.learning_rates();
            let rmsprop = self.rmsprop();
            let rows = self.subset.rows();
            rmsprop.step_rows(&mut self.grid.density, &mut self.state.density, rows, rows_t, gd, lr_d);
            rmsprop.step_rows(&mut self.grid.sh, &mut self.state.sh, rows, rows_t, gs, lr_s);
            // The host copy of the densities takes the rows' new values.
            for (r, v) in rows.iter().zip(read_rows(&self.grid.density, rows, rows_t)) {
                self.grid.density_cpu[*r as usize] = v;
            }
        });
        (mse, far)
    }

    /// The same step in plain Rust (the CPU backends): the step's rows and
    /// their RMSprop averages are read once, `field::host_fit` renders and
    /// differentiates the batch, the TV gradients and RMSprop's arithmetic
    /// run on the host values, and the grid and its averages get one
    /// row-add each. The same numbers as `graph_step` up to the order of
    /// floating-point sums (test `host_training_step_matches_the_graph_step`).
    /// Its profile parts: "gradient" is the render and the MSE's gradient,
    /// "update" the TV terms and RMSprop (the SH's TV loop runs beside the
    /// density's update).
    fn host_step(
        &mut self,
        batch: &SampleBatch,
        local: &TvNeighbours,
        rows_t: &Tensor<1, Int>,
        target: &[f32],
        profile: &StepProfile,
    ) -> (f32, Vec<f32>) {
        let stride = 3 * self.grid.num_basis();
        let (mse, mut grads) = profile.time("gradient", || {
            let buf = &mut self.step_buffers;
            // Random reads of the grid-sized density mirror and row map: in
            // parallel (order kept, so the same values).
            let (density_cpu, subset) = (&self.grid.density_cpu, &self.subset);
            buf.density.clear();
            buf.density.par_extend(subset.rows().par_iter().with_min_len(1 << 14).map(|&r| density_cpu[r as usize]));
            read_rows_into(&self.grid.sh, subset.rows(), rows_t, &mut buf.sh);
            buf.corners.clear();
            buf.corners.par_extend(batch.corner_rows.par_iter().with_min_len(1 << 14).map(|&r| subset.local(r)));
            let fit = host_fit::mse_gradient(
                &buf.density,
                &buf.sh,
                self.grid.num_basis(),
                batch,
                &buf.corners,
                target,
                self.background,
                &mut self.fit_buffers,
            );
            (fit.mse as f32, fit)
        });
        profile.time("update", || {
            let (lr_d, lr_s) = self.learning_rates();
            let (rmsprop, o) = (self.rmsprop(), &self.config.optim);
            let (rows, buf, nbs) = (self.subset.rows(), &self.step_buffers, &local.neighbours);
            let (grid, state) = (&mut self.grid, &mut self.state);
            let per_row = 1.0 / local.num_core.max(1) as f32;
            let with_tv = |weight: f32| weight > 0.0 && local.num_core > 0;
            let (grad_density, grad_sh) = (&mut grads.density, &mut grads.sh);
            // The density's TV terms, update and host copy, and the SH's TV
            // terms (a serial loop that waits on memory) touch separate
            // buffers: side by side.
            rayon::join(
                || {
                    if with_tv(o.tv_density) {
                        let scale = o.tv_density * per_row;
                        add_tv_gradient_per_channel(&buf.density, 1, nbs, scale, grad_density);
                    }
                    rmsprop.host_step_rows(&mut grid.density, &mut state.density, rows, rows_t, grad_density, lr_d);
                    // The host copy of the densities takes the rows' new values.
                    read_rows_into(&grid.density, rows, rows_t, grad_density);
                    for (&r, &v) in rows.iter().zip(grad_density.iter()) {
                        grid.density_cpu[r as usize] = v;
                    }
                },
                || {
                    if with_tv(o.tv_sh) {
                        add_tv_gradient_per_channel(&buf.sh, stride, nbs, o.tv_sh * per_row, grad_sh);
                    }
                },
            );
            rmsprop.host_step_rows(&mut grid.sh, &mut state.sh, rows, rows_t, grad_sh, lr_s);
        });
        let far = std::mem::take(&mut grads.far);
        self.fit_buffers.keep(grads);
        (mse, far)
    }

    /// The step's gradients (density `[rows, 1]`, SH `[rows, 3 nb]`) and its
    /// MSE through the Burn graph and autodiff: the renderer, the MSE and
    /// the TV terms. A batch too large for one of the device's buffers
    /// (`composite::max_samples_per_call`) goes through in runs of rays,
    /// each its own graph, their gradients summed: the same gradients as
    /// one graph up to the order of the sums (test
    /// `a_step_cut_into_runs_has_the_gradients_of_one_graph`).
    fn graph_gradients(
        &self,
        batch: &SampleBatch,
        local: &TvNeighbours,
        rows_t: &Tensor<1, Int>,
        target: &[f32],
    ) -> (Tensor<2>, Tensor<2>, f32, Vec<f32>) {
        // The step's rows, moved to where the steps run when the grid is kept in host memory.
        let (storage, plain, subset) = (self.grid.device(), &self.compute, &self.subset);
        let density = self.grid.density.clone().select(0, rows_t.clone()).to_device(plain);
        let sh = self.grid.sh.clone().select(0, rows_t.clone()).to_device(plain);
        let most = self.max_samples_per_call.unwrap_or(composite::max_samples_per_call(plain, sh.dims()[1]));
        let runs = batch.ray_runs(most);
        // The batch's MSE is its squared errors' sum over 3 x rays.
        let per_value = 1.0 / (3 * batch.num_rays.max(1)) as f32;
        // On a GPU the TV terms' gradient is a kernel of its own (`tv_gradients`), not a graph.
        let tv_in_graph = is_host_memory(plain);
        let (mut gd, mut gs, mut squared) = (None::<Tensor<2>>, None::<Tensor<2>>, 0.0f32);
        let mut far = Vec::new();
        for (i, &(first, count)) in runs.iter().enumerate() {
            let cut;
            let run = match runs.len() {
                1 => batch,
                _ => {
                    cut = batch.sub_batch(first, count);
                    &cut
                }
            };
            let remap = |r: i32| subset.local(r);
            let mut bt = match self.config.ray_kernel {
                RayKernel::Unfused => BatchTensors::for_unfused_gradients(run, Some(&remap), plain),
                _ => BatchTensors::for_gradients(run, Some(&remap), plain),
            };
            // The far colours are a leaf too: their gradients train the far map.
            let far_leaf = bt.far.take().map(|f| f.autodiff().require_grad());
            bt.far = far_leaf.clone();
            let ld = density.clone().autodiff().require_grad();
            let ls = sh.clone().autodiff().require_grad();
            let out = composite::composite(ld.clone(), ls.clone(), &bt, self.background);
            let target_t = floats(target[3 * first..3 * (first + count)].to_vec(), [count, 3], plain);
            let diff = out.rgb - target_t;
            let run_squared = (diff.clone() * diff).sum();
            let mut loss = run_squared.clone() * per_value;
            if i == 0 && tv_in_graph {
                loss = loss + self.tv_loss(local, &ld, &ls);
            }
            self.memory_probe.note();
            let grads = loss.backward();
            self.memory_probe.note();
            // No gradient at all when no ray of the run met a sample.
            let add = |sum: Option<Tensor<2>>, grad: Option<Tensor<2>>| match (sum, grad) {
                (Some(s), Some(g)) => Some(s + g),
                (s, g) => s.or(g),
            };
            gd = add(gd, ld.grad(&grads));
            gs = add(gs, ls.grad(&grads));
            if let Some(leaf) = &far_leaf {
                far.extend(leaf.grad(&grads).map_or_else(|| vec![0.0; 3 * count], to_vec));
            }
            squared += scalar(run_squared.inner());
        }
        let or_zeros =
            |sum: Option<Tensor<2>>, like: &Tensor<2>| sum.unwrap_or_else(|| Tensor::zeros(like.dims(), plain));
        let (mut gd, mut gs) = (or_zeros(gd, &density), or_zeros(gs, &sh));
        if !tv_in_graph {
            (gd, gs) = self.tv_gradients(local, &density, &sh, gd, gs);
        }
        (gd.to_device(&storage), gs.to_device(&storage), squared * per_value, far)
    }

    /// `gd` and `gs` plus the gradients of the TV terms (`tv_loss`'s), by
    /// the TV kernel (`kernels::optim_op`).
    fn tv_gradients(
        &self,
        local: &TvNeighbours,
        density: &Tensor<2>,
        sh: &Tensor<2>,
        mut gd: Tensor<2>,
        mut gs: Tensor<2>,
    ) -> (Tensor<2>, Tensor<2>) {
        let o = &self.config.optim;
        if local.num_core == 0 || (o.tv_density <= 0.0 && o.tv_sh <= 0.0) {
            return (gd, gs);
        }
        let links = TvLinks::new(&local.neighbours, &density.device());
        let per_row = 1.0 / local.num_core as f32;
        if o.tv_density > 0.0 {
            gd = add_tv_gradient(gd, density, &links, o.tv_density * per_row);
        }
        if o.tv_sh > 0.0 {
            gs = add_tv_gradient(gs, sh, &links, o.tv_sh * per_row);
        }
        (gd, gs)
    }

    /// The TV terms on the step's TV rows (zero when there are none).
    fn tv_loss(&self, local: &TvNeighbours, ld: &Tensor<2>, ls: &Tensor<2>) -> Tensor<1> {
        let (o, device) = (&self.config.optim, ld.device());
        let mut loss = Tensor::zeros([1], &device);
        if o.tv_density > 0.0 && local.num_core > 0 {
            loss = loss + local.total_variation(ld.clone(), &device) * o.tv_density;
        }
        if o.tv_sh > 0.0 && local.num_core > 0 {
            loss = loss + local.total_variation(ls.clone(), &device) * o.tv_sh;
        }
        loss
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
            render: self.config.render_settings(),
            data: self.config.data,
            run_config: serde_json::to_value(&self.config).expect("a config is plain data"),
            train_seconds: self.train_seconds,
        }
    }

    /// Writes this run's checkpoint into `out`.
    pub fn save(&self, dataset: &Dataset, out: &Path) -> Result<()> {
        self.checkpoint_writer(dataset)(out)
    }

    /// [`save`](Self::save) as a closure that borrows only the field and
    /// its optimiser state (the trainer's step buffers cannot be shared
    /// between threads), so the write can run on another thread beside
    /// renders of the field.
    pub fn checkpoint_writer(&self, dataset: &Dataset) -> impl FnOnce(&Path) -> Result<()> + Send + '_ {
        let (meta, grid, state, far) = (self.meta(dataset), &self.grid, &self.state, &self.far_optimiser);
        move |out| {
            let file = out.join(checkpoint::CHECKPOINT_FILE);
            checkpoint::save(&file, &meta, grid, &state.density, &state.sh, &far.mean_square)
        }
    }
}

/// Photos whose border pixels are this close (in every channel) to their
/// median colour are "plain" there ...
const PLAIN_TOLERANCE: f32 = 0.04;
/// ... when most of the border pixels are: an object on a white backdrop
/// leaves 97-100 % of them white (the procedural scene at 96 px, lego's
/// renders through COLMAP) even where it reaches the frame; a room or
/// landscape leaves almost none near any one colour (the twin's
/// environment: 0.03 %).
const PLAIN_SHARE: f32 = 0.5;

/// Whether a fit of `dataset` learns a far background, and why (what
/// `train` prints). `auto` learns one for a COLMAP or `transforms.json`
/// capture around the scene unless the training photos' borders are one
/// plain colour: a capture on a plain backdrop (lego's renders on white
/// through COLMAP) is fitted better by the constant background (29.9 dB
/// against 29.2 with a far map, whose texels few rays reach stay off-white).
pub fn far_decision(dataset: &Dataset, grid: &GridConfig) -> Result<(bool, String)> {
    let ndc = dataset.ndc.is_some();
    let around = matches!(dataset.kind, DatasetKind::Colmap | DatasetKind::Transforms) && !ndc;
    let learn = "learned behind the box";
    Ok(match grid.far_background {
        FarBackground::Off => (false, "none (grid.far_background = \"off\")".into()),
        FarBackground::On if ndc => bail!(
            "grid.far_background = \"on\" needs a capture around the scene: a forward-facing (NDC) one reaches to infinity already"
        ),
        FarBackground::On => (true, format!("{learn} (grid.far_background = \"on\")")),
        FarBackground::Auto if !around => {
            (false, "none (a constant background: not a COLMAP or transforms.json capture around the scene)".into())
        }
        FarBackground::Auto => match plain_border(dataset) {
            Some((colour, share)) => (
                false,
                format!(
                    "none: the photos' borders are one plain colour ({:.0} % within {PLAIN_TOLERANCE} of ({:.2}, {:.2}, {:.2})), \
                     the constant background; grid.far_background = \"on\" learns one",
                    share * 100.0,
                    colour[0],
                    colour[1],
                    colour[2]
                ),
            ),
            None => (true, format!("{learn} (the photos' borders show more than one plain colour)")),
        },
    })
}

/// The training photos' border colour (the median of the pixels of each
/// photo's outer frame, 2 pixels wide) and the share of them near it, when
/// that share makes the border plain.
fn plain_border(dataset: &Dataset) -> Option<([f32; 3], f32)> {
    let mut border: Vec<[f32; 3]> = Vec::new();
    for view in &dataset.train {
        let (w, h) = (view.camera.intrinsics.width as usize, view.camera.intrinsics.height as usize);
        for y in 0..h {
            for x in 0..w {
                if x < 2 || y < 2 || x + 2 >= w || y + 2 >= h {
                    let at = (y * w + x) * 3;
                    border.push([view.rgb[at], view.rgb[at + 1], view.rgb[at + 2]]);
                }
            }
        }
    }
    if border.is_empty() {
        return None;
    }
    let median: [f32; 3] = std::array::from_fn(|c| {
        let mut channel: Vec<f32> = border.iter().map(|p| p[c]).collect();
        channel.sort_by(f32::total_cmp);
        channel[channel.len() / 2]
    });
    let near = border.iter().filter(|p| p.iter().zip(median).all(|(a, b)| (a - b).abs() <= PLAIN_TOLERANCE)).count();
    let share = near as f32 / border.len() as f32;
    (share >= PLAIN_SHARE).then_some((median, share))
}

/// A far map to start from: the training photos' mean colour everywhere.
fn initial_far(dataset: &Dataset, [width, height]: [usize; 2]) -> Environment {
    let (mut sum, mut count) = ([0.0f64; 3], 0usize);
    for view in &dataset.train {
        for px in view.rgb.chunks_exact(3) {
            for (s, &v) in sum.iter_mut().zip(px) {
                *s += v as f64;
            }
            count += 1;
        }
    }
    Environment::uniform(width, height, sum.map(|s| (s / count.max(1) as f64) as f32))
}
