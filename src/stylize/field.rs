//! The grid being stylized: SH degree 0, density frozen, its RMSprop state
//! and SH total variation; the rows a step updates (`StepRows`: all, or
//! only those the step touched); and the chunked gradient of a loss over
//! rendered rays (the second half of deferred back-propagation).

use std::cell::Cell;

use burn::tensor::{IndexingUpdateOp, Int, Tensor};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use crate::field::checkpoint::CheckpointMeta;
use crate::field::frozen::{self, DeviceSamples, FrozenSamples};
use crate::field::grid::{CellLattice, RadianceGrid};
use crate::field::optim::{Rmsprop, RowSubset, TvNorm, total_variation};
use crate::scene::sh;
use crate::stylize::colour_map::ColourMap;
use crate::stylize::colour_transfer::ColourTransfer;
use crate::util::tensor::{assign_rows, floats, indices, is_host_memory, select_rows, tensor_bytes, to_vec};

/// The rows one optimiser step updates, and where each one's gradient sits
/// in the step's gradient buffer: every row of the grid (dense; the buffer
/// is grid-sized) or only the rows the step touches (sparse, as svox2: its
/// rays' samples and the TV rows; the buffer has one row per touched row).
pub struct StepRows {
    num_rows: usize,
    touched: Option<RowSubset>,
    /// The touched rows on the device, uploaded at most once per step (every
    /// sparse gradient and the optimiser step use them).
    on_device: std::cell::OnceCell<Tensor<1, Int>>,
}

impl StepRows {
    pub fn dense(num_rows: usize) -> Self {
        Self { num_rows, touched: None, on_device: Default::default() }
    }

    pub fn sparse(num_rows: usize) -> Self {
        Self::sparse_reusing(RowSubset::default(), num_rows)
    }

    /// Sparse, in a subset kept from an earlier step: clearing it resets
    /// only the rows that step set, not a grid-sized map.
    fn sparse_reusing(mut subset: RowSubset, num_rows: usize) -> Self {
        subset.clear(num_rows);
        Self { num_rows, touched: Some(subset), on_device: Default::default() }
    }

    /// Marks `rows` as touched (nothing to do when dense).
    pub fn add(&mut self, rows: &[i32]) {
        self.on_device.take();
        if let Some(s) = &mut self.touched {
            for &r in rows {
                s.insert(r);
            }
        }
    }

    /// Rows in the gradient buffer.
    pub fn len(&self) -> usize {
        self.touched.as_ref().map_or(self.num_rows, |s| s.rows().len())
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The buffer row of grid row `row` (it must have been added).
    pub fn slot(&self, row: i32) -> i32 {
        self.slot_fn()(row)
    }

    /// Grid row -> buffer row as a plain function (shareable across threads).
    pub fn slot_fn(&self) -> impl Fn(i32) -> i32 + Sync + '_ {
        let touched = self.touched.as_ref();
        move |row| touched.map_or(row, |s| s.local(row))
    }

    /// The buffer rows of `grid_rows`, as an index tensor.
    pub fn slots(&self, grid_rows: &[i32], device: &burn::tensor::Device) -> Tensor<1, Int> {
        indices(grid_rows.iter().map(|&r| self.slot(r)).collect(), device)
    }

    /// The touched rows on the device (sparse only).
    fn touched_on_device(&self, device: &burn::tensor::Device) -> Option<Tensor<1, Int>> {
        let s = self.touched.as_ref()?;
        Some(self.on_device.get_or_init(|| indices(s.rows().to_vec(), device)).clone())
    }

    /// The step's buffer taken from a grid-sized gradient (dense: itself).
    pub fn take_from(&self, grid_sized: Tensor<2>) -> Tensor<2> {
        match self.touched_on_device(&grid_sized.device()) {
            None => grid_sized,
            Some(ids) => select_rows(grid_sized, ids),
        }
    }

    /// The grid row of each buffer row, in buffer order.
    pub fn grid_rows(&self) -> Box<dyn Iterator<Item = usize> + '_> {
        match &self.touched {
            None => Box::new(0..self.num_rows),
            Some(s) => Box::new(s.rows().iter().map(|&r| r as usize)),
        }
    }

    /// An empty gradient buffer.
    pub fn zeros(&self, device: &burn::tensor::Device) -> Tensor<2> {
        Tensor::zeros([self.len(), 3], device)
    }
}

/// The SH total variation's settings (see `LossConfig::tv_sh*`).
#[derive(Debug, Clone, Copy)]
pub struct ShTv {
    pub weight: f32,
    /// Fraction of the rows picked per step.
    pub fraction: f32,
    /// `weight` per picked voxel (svox2) instead of over their mean.
    pub per_voxel: bool,
    pub per_channel: bool,
}

/// The photoreal grid as the stylized field starts from it, and `meta`
/// with its march: cut to SH degree 0 and, with `scale` > 1
/// (`colour_grid_scale`), resampled onto a lattice `scale` times finer along
/// each axis, so that the colour has more voxels to hold a painting's
/// strokes. The density, resampled with it, stays frozen and describes the
/// same surfaces; the march keeps its step in world units (`scale` fine
/// voxels a step), so rays take as many samples.
pub fn colour_grid(
    mut grid: RadianceGrid,
    meta: &CheckpointMeta,
    scale: u32,
    compute: &burn::tensor::Device,
) -> anyhow::Result<(RadianceGrid, CheckpointMeta)> {
    // The degree-0 cut first: the resampling then moves 3 colour numbers a voxel, not 3 x 9.
    grid.truncate_sh(0);
    let mut meta = meta.clone();
    if scale > 1 {
        let res = grid.geometry.res.map(|r| r * scale as usize);
        anyhow::Context::context(grid.upsample(res, compute), "the finer colour grid (colour_grid_scale)")?;
        meta.render.march.step *= scale as f32;
        meta.geometry = grid.geometry;
    }
    Ok((grid, meta))
}

/// The grid being stylized: SH degree 0, density frozen, RMSprop state.
pub struct StyleField {
    pub grid: RadianceGrid,
    rms: Tensor<2>,
    /// Per row, its +x / +y / +z neighbour row (itself when empty): SH TV.
    neighbours: [Vec<i32>; 3],
    /// The sparse steps' row subset, kept between steps (see `RowSubset`);
    /// a `Cell` so a step can take it while the step's samples borrow the stylizer.
    touched: Cell<RowSubset>,
}

impl StyleField {
    /// Cuts a photoreal grid to view-independent colour (the DC band).
    pub fn new(mut grid: RadianceGrid) -> Self {
        grid.truncate_sh(0);
        let rows = grid.num_rows();
        let neighbours = std::array::from_fn(|axis| {
            (0..rows).map(|row| grid.neighbour_row(row, axis).unwrap_or(row as i32)).collect()
        });
        let rms = Tensor::zeros([rows, 3], &grid.device());
        Self { grid, rms, neighbours, touched: Cell::default() }
    }

    /// Bytes held: the grid (density, colour, its plain density copy,
    /// occupancy links and coordinates, the far background) and the
    /// optimiser's state and TV neighbours.
    pub fn bytes(&self) -> usize {
        let g = &self.grid;
        let grid = tensor_bytes(&g.density) + tensor_bytes(&g.sh) + g.density_cpu.len() * 4;
        let lattice = (g.links.len() + g.coords.len()) * 4 + g.far.as_ref().map_or(0, |f| f.rgb.len() * 4);
        grid + lattice + tensor_bytes(&self.rms) + self.neighbours.iter().map(|n| n.len() * 4).sum::<usize>()
    }

    /// Recolours the field with an affine colour map: a colour
    /// `c = C0 s + 0.5` becomes `M c + b` (before the renderer's clamp), so
    /// `s -> M s + (M 0.5 + b - 0.5) / C0` (the released code's
    /// `grid.apply_ct`, for DC-only colour).
    pub fn apply_colour_transfer(&mut self, tf: &ColourTransfer) {
        let device = self.grid.device();
        let transposed: Vec<f32> = (0..3).flat_map(|j| (0..3).map(move |i| tf.matrix[i][j])).collect();
        let shift: Vec<f32> =
            (0..3).map(|i| (0.5 * tf.matrix[i].iter().sum::<f32>() + tf.offset[i] - 0.5) / sh::C0).collect();
        self.grid.sh =
            self.grid.sh.clone().matmul(floats(transposed, [3, 3], &device)) + floats(shift, [1, 3], &device);
    }

    /// Recolours the degree-0 colour `c = C0 s + 0.5` of every voxel (of
    /// those `only` marks, when given) through `map` (before the
    /// renderer's clamp, as `apply_colour_transfer`).
    pub fn apply_colour_map(&mut self, map: &ColourMap, only: Option<&[bool]>) {
        let device = self.grid.device();
        let sh = to_vec(self.grid.sh.clone());
        let mapped: Vec<f32> = sh
            .chunks_exact(3)
            .enumerate()
            .flat_map(|(row, s)| match only.is_none_or(|o| o[row]) {
                true => map.apply([0, 1, 2].map(|k| sh::C0 * s[k] + 0.5)).map(|c| (c - 0.5) / sh::C0),
                false => [s[0], s[1], s[2]],
            })
            .collect();
        self.grid.sh = floats(mapped, [sh.len() / 3, 3], &device);
    }

    /// Keeps the colours of `photo` (a degree-0 SH grid of the same rows)
    /// under this field's light and dark (`keep_chroma`).
    pub fn keep_chroma_of(&mut self, photo: &[f32]) {
        let device = self.grid.device();
        let kept = keep_chroma(&to_vec(self.grid.sh.clone()), photo);
        let rows = kept.len() / 3;
        self.grid.sh = floats(kept, [rows, 3], &device);
    }

    /// Keeps `strength` of the stylization: each colour the blend of this
    /// field's and `photo`'s (a degree-0 SH grid of the same rows; `blend`).
    pub fn blend_with(&mut self, photo: &[f32], strength: f32) {
        let device = self.grid.device();
        let blended = blend(&to_vec(self.grid.sh.clone()), photo, strength);
        let rows = blended.len() / 3;
        self.grid.sh = floats(blended, [rows, 3], &device);
    }

    /// The RMSprop running averages `[rows, 3]`.
    pub fn rms(&self) -> Tensor<2> {
        self.rms.clone()
    }

    /// Restores the running averages (a resumed run).
    pub fn set_rms(&mut self, rms: Tensor<2>) {
        self.rms = rms;
    }

    pub fn reset_optimiser(&mut self) {
        self.rms = Tensor::zeros([self.grid.num_rows(), 3], &self.grid.device());
    }

    /// The rows a step will update: all (dense), or those of its samples'
    /// cells (`FrozenSamples::cell_keys` of lists marched on this field's
    /// grid) and its TV rows (sparse), in increasing row order.
    pub fn step_rows(&self, sparse: bool, cells: &[&[u32]], tv: &[Vec<i32>]) -> StepRows {
        let n = self.grid.num_rows();
        if !sparse {
            return StepRows::dense(n);
        }
        let mut touched = self.touched.take();
        let tv: Vec<&[i32]> = tv.iter().map(Vec::as_slice).collect();
        touched.reset_to_union_with_cells(n, &tv, &CellLattice::of(&self.grid), cells);
        StepRows { num_rows: n, touched: Some(touched), on_device: Default::default() }
    }

    /// One RMSprop step on the SH rows of `rows` (density untouched); `grad`
    /// is the step's gradient buffer. With `host` (the run's ray kernel is
    /// the host pass: CPU backends) a sparse step runs the fused host step
    /// (one pass over each row and its average), the same numbers as the
    /// tensor step, which stays the graph path's (a GPU's: no read-back).
    pub fn rmsprop(&mut self, grad: Tensor<2>, rows: StepRows, lr: f32, opt: Rmsprop, host: bool) {
        let ids = rows.touched_on_device(&self.grid.device());
        match (rows.touched, ids) {
            (Some(s), Some(ids)) => {
                let (sh, rms) = (&mut self.grid.sh, &mut self.rms);
                match (s.rows().is_empty(), host && is_host_memory(&sh.device())) {
                    (true, _) => {}
                    (false, true) => opt.host_step_rows(sh, rms, s.rows(), &ids, &to_vec(grad), lr),
                    (false, false) => {
                        opt.step_rows(sh, rms, s.rows(), &ids, grad, lr);
                    }
                }
                self.touched.set(s);
            }
            _ => opt.step_dense(&mut self.grid.sh, &mut self.rms, grad, lr),
        }
    }

    /// The rows of one SH TV term: a random `tv.fraction` of the rows and,
    /// per axis, their +x/+y/+z neighbours (empty when `tv.weight` is 0).
    pub fn tv_rows(&self, tv: &ShTv, rng: &mut ChaCha8Rng) -> Vec<Vec<i32>> {
        let n = self.grid.num_rows();
        if tv.weight <= 0.0 || n == 0 {
            return Vec::new();
        }
        let count = ((n as f32 * tv.fraction).ceil() as usize).clamp(1, n);
        let core: Vec<i32> = (0..count).map(|_| rng.random_range(0..n) as i32).collect();
        std::iter::once(core.clone())
            .chain(self.neighbours.iter().map(|nb| core.iter().map(|&r| nb[r as usize]).collect()))
            .collect()
    }

    /// `into` plus the gradient of the SH total variation over the rows
    /// `lists` of `tv_rows`: `tv.weight` x the mean (or, `per_voxel`, the
    /// sum) over the picked rows of sqrt(sum of squared differences to the
    /// +x/+y/+z neighbours), over all channels together or per channel.
    /// Adding into the caller's gradient saves a buffer and a sum per step.
    pub fn add_tv_gradient(&self, into: Tensor<2>, tv: &ShTv, lists: &[Vec<i32>], rows: &StepRows) -> Tensor<2> {
        let weight = tv.weight;
        let Some(count) = lists.first().map(Vec::len).filter(|&c| c > 0 && weight > 0.0) else { return into };
        // Leaf = the rows involved (the picked rows and their neighbours), local indices.
        let subset = RowSubset::of(self.grid.num_rows(), &lists.concat());
        let device = self.grid.device();
        let leaf_rows = indices(subset.rows().to_vec(), &device);
        let leaf = select_rows(self.grid.sh.clone(), leaf_rows).autodiff().require_grad();
        let mut gathered = lists
            .iter()
            .map(|l| select_rows(leaf.clone(), indices(l.iter().map(|&r| subset.local(r)).collect(), &device)));
        let centre = gathered.next().expect("the picked rows");
        let norm = if tv.per_channel { TvNorm::PerChannel } else { TvNorm::PerVoxel };
        let scale = if tv.per_voxel { weight } else { weight / count as f32 };
        let tv = total_variation(centre, gathered, norm) * scale;
        let slots = rows.slots(subset.rows(), &device);
        match leaf.grad(&tv.backward()) {
            Some(g) => assign_rows(into, slots, g, IndexingUpdateOp::Add),
            None => into,
        }
    }
}

/// Degree-0 SH colours (`[rows, 3]`, flat) with `style`'s luminance
/// (Rec. 601) and `photo`'s chroma: each row is the photo's plus the
/// difference of their luminances on every channel, which keeps the
/// photo's Cb and Cr and takes the style's Y. Luminance is linear, so the
/// SH coefficients' difference is the colours' over C0.
pub fn keep_chroma(style: &[f32], photo: &[f32]) -> Vec<f32> {
    let luma = |s: &[f32]| 0.299 * s[0] + 0.587 * s[1] + 0.114 * s[2];
    style
        .chunks_exact(3)
        .zip(photo.chunks_exact(3))
        .flat_map(|(s, p)| {
            let shift = luma(s) - luma(p);
            [p[0] + shift, p[1] + shift, p[2] + shift]
        })
        .collect()
}

/// Degree-0 SH colours `(1 - strength) * photo + strength * style`: a render is
/// linear in the coefficients along each ray, so every view shows the same
/// blend of the stylized and the photo renders (up to the display clamp).
pub fn blend(style: &[f32], photo: &[f32], strength: f32) -> Vec<f32> {
    style.iter().zip(photo).map(|(s, p)| (1.0 - strength) * p + strength * s).collect()
}

/// A chunk of rays on the device, ready for both passes of deferred
/// back-propagation: its sample lists with corner rows renumbered to the
/// rows the chunk touches, and those rows. Uploaded once per step, it
/// serves the plain render and the re-render with autodiff.
pub struct DeviceChunk {
    /// The chunk's first ray and its number of rays.
    start: usize,
    len: usize,
    /// The grid rows the chunk's samples touch, in local order.
    rows: Vec<i32>,
    rows_t: Tensor<1, Int>,
    samples: frozen::FrozenTensors,
}

impl DeviceChunk {
    /// Rays `start..start + len` of `samples`, renumbered through `subset`
    /// (reused between chunks: resetting it clears only what it set).
    fn upload(
        samples: &FrozenSamples,
        start: usize,
        len: usize,
        num_grid_rows: usize,
        subset: &mut RowSubset,
        device: &burn::tensor::Device,
    ) -> Self {
        let part = samples.range(start, len);
        let (rows, weights) = part.expanded();
        subset.reset_to(num_grid_rows, &rows);
        let local = rows.iter().map(|&r| subset.local(r)).collect();
        let rows = subset.rows().to_vec();
        let samples = part.upload_expanded(local, weights, Some(rows.len()), device);
        Self { start, len, rows_t: indices(rows.clone(), device), rows, samples }
    }

    /// Every chunk of `samples`, uploaded.
    pub fn upload_all(samples: &FrozenSamples, chunk: usize, sh: &Tensor<2>) -> Vec<DeviceChunk> {
        let device = sh.device();
        let mut subset = RowSubset::default();
        samples
            .chunks(chunk, sh)
            .into_iter()
            .map(|(start, len)| Self::upload(samples, start, len, sh.dims()[0], &mut subset, &device))
            .collect()
    }

    /// Colours `[len, 3]` of the chunk's rays from `sh` (grid rows; no autodiff).
    fn render(&self, sh: &Tensor<2>, background: [f32; 3]) -> Tensor<2> {
        frozen::render_colour(select_rows(sh.clone(), self.rows_t.clone()), &self.samples, background)
    }

    /// Adds d/d(sh) of `loss_of(rendered chunk, first ray, rays)` into
    /// `total` (the step's buffer, laid out by `rows`): the autodiff leaf is
    /// only the rows the chunk touches.
    fn add_gradient(
        &self,
        sh: &Tensor<2>,
        background: [f32; 3],
        rows: &StepRows,
        loss_of: &dyn Fn(Tensor<2>, usize, usize) -> Tensor<1>,
        total: Tensor<2>,
    ) -> Tensor<2> {
        let leaf = select_rows(sh.clone(), self.rows_t.clone()).autodiff().require_grad();
        let rgb = frozen::render_colour(leaf.clone(), &self.samples, background);
        let loss = loss_of(rgb, self.start, self.len);
        // A chunk whose rays all miss the scene renders the background: no graph, no gradient.
        if loss.is_tracked()
            && let Some(g) = leaf.grad(&loss.backward())
        {
            return assign_rows(total, rows.slots(&self.rows, &sh.device()), g, IndexingUpdateOp::Add);
        }
        total
    }
}

/// All rays of `chunks` rendered from `sh` without autodiff: `[rays, 3]`
/// on the device (the first half of deferred back-propagation).
pub fn render_chunks(sh: &Tensor<2>, chunks: &[DeviceChunk], background: [f32; 3]) -> Tensor<2> {
    if chunks.is_empty() {
        return Tensor::zeros([0, 3], &sh.device());
    }
    Tensor::cat(chunks.iter().map(|c| c.render(sh, background)).collect(), 0)
}

/// All rays of `chunks` (`(first ray, rays, samples)` with the grid's own
/// corner rows, gathered on the device) rendered from `sh` without autodiff.
pub fn render_gathered(
    sh: &Tensor<2>,
    chunks: &[(usize, usize, frozen::FrozenTensors)],
    background: [f32; 3],
) -> Tensor<2> {
    if chunks.is_empty() {
        return Tensor::zeros([0, 3], &sh.device());
    }
    Tensor::cat(chunks.iter().map(|(_, _, c)| frozen::render_colour(sh.clone(), c, background)).collect(), 0)
}

/// d/d(sh) of the sum over `chunks` of `loss_of(rendered chunk, first ray,
/// rays)`, each chunk rendered with autodiff and back-propagated on its own
/// (the second half of deferred back-propagation): gradients are added into
/// the step's buffer (`rows`: grid-sized, or one row per touched row, the
/// samples' rows among them).
pub fn chunks_gradient(
    sh: &Tensor<2>,
    chunks: &[DeviceChunk],
    background: [f32; 3],
    rows: &StepRows,
    loss_of: &dyn Fn(Tensor<2>, usize, usize) -> Tensor<1>,
) -> Tensor<2> {
    chunks.iter().fold(rows.zeros(&sh.device()), |total, c| c.add_gradient(sh, background, rows, loss_of, total))
}

/// [`chunks_gradient`] over `samples` in chunks of `chunk` rays, each
/// uploaded just before its pass, so memory is bounded by the chunk (a
/// single pass: the pseudo-ray losses).
pub fn chunked_gradient(
    sh: &Tensor<2>,
    samples: &FrozenSamples,
    background: [f32; 3],
    chunk: usize,
    rows: &StepRows,
    loss_of: &dyn Fn(Tensor<2>, usize, usize) -> Tensor<1>,
) -> Tensor<2> {
    let device = sh.device();
    let mut subset = RowSubset::default();
    samples.chunks(chunk, sh).into_iter().fold(rows.zeros(&device), |total, (start, len)| {
        DeviceChunk::upload(samples, start, len, sh.dims()[0], &mut subset, &device)
            .add_gradient(sh, background, rows, loss_of, total)
    })
}

/// [`chunks_gradient`] for chunks whose corner rows are the grid's own
/// (`(first ray, rays, samples)`, gathered on the device by
/// `DeviceSamples::gather`): each chunk's autodiff leaf is the whole SH
/// grid, so no renumbering has to come from the host, and the gradients
/// are summed grid-sized on the device until the step's rows are taken.
/// The sums are those of `chunked_gradient`, in the same order.
pub fn gathered_gradient(
    sh: &Tensor<2>,
    chunks: impl IntoIterator<Item = (usize, usize, frozen::FrozenTensors)>,
    background: [f32; 3],
    rows: &StepRows,
    loss_of: &dyn Fn(Tensor<2>, usize, usize) -> Tensor<1>,
) -> Tensor<2> {
    let mut total = Tensor::zeros(sh.dims(), &sh.device());
    for (start, len, samples) in chunks {
        let leaf = sh.clone().autodiff().require_grad();
        let loss = loss_of(frozen::render_colour(leaf.clone(), &samples, background), start, len);
        if loss.is_tracked()
            && let Some(g) = leaf.grad(&loss.backward())
        {
            total = total + g;
        }
    }
    rows.take_from(total)
}

/// [`gathered_gradient`] of the picks `picks` (repeats allowed) of lists
/// kept on the device, in chunks of `chunk` rays; on a GPU, when the picks
/// are a large enough share of the lists (`DeviceSamples::renders_whole`),
/// by one render of the whole lists instead, whose backward is parallel.
/// `loss_of` sees the picks' colours whole (`start` 0) then.
pub fn picked_gradient(
    sh: &Tensor<2>,
    lists: &DeviceSamples,
    picks: &[usize],
    chunk: usize,
    background: [f32; 3],
    rows: &StepRows,
    loss_of: &dyn Fn(Tensor<2>, usize, usize) -> Tensor<1>,
) -> Tensor<2> {
    if !lists.renders_whole(picks) {
        return gathered_gradient(sh, lists.gather_chunks(picks, chunk, sh), background, rows, loss_of);
    }
    let leaf = sh.clone().autodiff().require_grad();
    let loss = loss_of(lists.render_picks(leaf.clone(), picks, background), 0, picks.len());
    let total = match loss.is_tracked() {
        true => leaf.grad(&loss.backward()),
        false => None,
    };
    rows.take_from(total.unwrap_or_else(|| Tensor::zeros(sh.dims(), &sh.device())))
}

/// Checked against the Burn graph and autodiff, on every backend the test
/// command runs (`cargo test --lib graph_oracle`).
#[cfg(test)]
#[allow(clippy::print_stdout, clippy::print_stderr)] // the measured errors, shown with --nocapture
mod graph_oracle {
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::{StepRows, chunked_gradient};
    use crate::field::frozen::{FrozenSamples, render_plain};
    use crate::field::grid::blob_grid;
    use crate::field::host_colour;
    use crate::field::march::{MarchParams, Marcher};
    use crate::test_support::{backend, device, test_camera, tol};
    use crate::util::tensor::{floats, to_vec};

    /// The fused plain-Rust ray pass (`field::host_colour`, the CPU backends'
    /// path for L_ref and the refit) against the Burn graph and autodiff: the
    /// same colours and the same mean-squared-error gradient to 1e-5 relative
    /// (1e-4 on wgpu),
    /// dense and sparse, on repeated and empty picks, with a target low enough
    /// that some samples' colours clamp at zero.
    #[test]
    fn host_ray_kernel_matches_the_graph() {
        let d = backend().device();
        let grid = blob_grid(6, &device());
        let rays = test_camera(40).rays(None);
        let bg = [1.0, 0.5, 0.0];
        let samples = FrozenSamples::march(&Marcher::new(&grid), &rays, &MarchParams::default(), 0.0);
        let sh = to_vec(grid.sh.clone());
        let graph_rgb = render_plain(&grid.sh, &samples, bg, 4096);
        let host_rgb = host_colour::render(&sh, &samples, None, bg);
        let worst = graph_rgb.iter().zip(&host_rgb).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(worst < tol(1e-5), "colours differ by {worst}");
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let mut picks = vec![0, 0, samples.num_rays - 1];
        picks.extend((0..3000).map(|_| rng.random_range(0..samples.num_rays)));
        let target: Vec<f32> = (0..picks.len() * 3).map(|_| rng.random::<f32>() * 0.3).collect();
        let cut = samples.subset(&picks);
        let scale = 10.0 / (3.0 * picks.len() as f32);
        let target_t = floats(target.clone(), [picks.len(), 3], &d);
        for sparse in [false, true] {
            let mut rows = if sparse { StepRows::sparse(grid.num_rows()) } else { StepRows::dense(grid.num_rows()) };
            rows.add(&cut.cell_rows());
            let graph = to_vec(chunked_gradient(&grid.sh, &cut, bg, 700, &rows, &|rgb, start, len| {
                let diff = rgb - target_t.clone().narrow(0, start, len);
                (diff.clone() * diff).sum() * scale
            }));
            let (host, loss) =
                host_colour::colour_gradient(&sh, &samples, Some(&picks), bg, rows.len(), &rows.slot_fn(), |k, rgb| {
                    let e = [0, 1, 2].map(|c| rgb[c] - target[k * 3 + c]);
                    (e.map(|x| 2.0 * scale * x), scale * e.iter().map(|x| x * x).sum::<f32>())
                });
            let expected: f32 = (0..picks.len() * 3)
                .map(|i| {
                    let e = host_rgb[picks[i / 3] * 3 + i % 3] - target[i];
                    scale * e * e
                })
                .sum();
            assert!((loss as f32 - expected).abs() <= 1e-5 * expected, "loss {loss} vs {expected}");
            assert_eq!(host.len(), graph.len());
            let norm = graph.iter().map(|x| x * x).sum::<f32>().sqrt();
            let err = graph.iter().zip(&host).map(|(a, b)| (a - b) * (a - b)).sum::<f32>().sqrt();
            eprintln!("sparse {sparse}: host vs graph gradient, relative L2 error {:.2e}", err / norm);
            assert!(norm > 0.0 && err / norm < tol(1e-5), "sparse {sparse}: relative error {}", err / norm);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{blend, keep_chroma};

    /// Strength 1 keeps the stylization, 0 gives the photo, and between the
    /// distance to the photo scales with it.
    #[test]
    fn blend_moves_from_the_photo_to_the_style_with_the_strength() {
        let (style, photo) = ([0.9, -0.1, 0.4], [0.1, 0.3, -0.2]);
        assert_eq!(blend(&style, &photo, 1.0), style);
        assert_eq!(blend(&style, &photo, 0.0), photo);
        let half = blend(&style, &photo, 0.5);
        for c in 0..3 {
            assert!((half[c] - photo[c] - 0.5 * (style[c] - photo[c])).abs() < 1e-7, "{half:?}");
        }
    }

    /// The kept colour has the style's luminance and the photo's chroma;
    /// a grey style over a coloured photo keeps the photo's hue.
    #[test]
    fn keep_chroma_takes_luminance_from_the_style_and_chroma_from_the_photo() {
        let (style, photo) = ([0.9, 0.1, -0.4, 0.2, 0.2, 0.2], [-0.3, 0.5, 0.1, 0.6, -0.2, 0.0]);
        let kept = keep_chroma(&style, &photo);
        let luma = |s: &[f32]| 0.299 * s[0] + 0.587 * s[1] + 0.114 * s[2];
        // Chroma as Rec. 601 defines it: Cb ~ B - Y, Cr ~ R - Y.
        let chroma = |s: &[f32]| [s[2] - luma(s), s[0] - luma(s)];
        for (k, (s, p)) in kept.chunks(3).zip(style.chunks(3).zip(photo.chunks(3))) {
            assert!((luma(k) - luma(s)).abs() < 1e-6, "luminance {k:?} vs the style's {s:?}");
            let (a, b) = (chroma(k), chroma(p));
            assert!((a[0] - b[0]).abs() < 1e-6 && (a[1] - b[1]).abs() < 1e-6, "chroma {k:?} vs the photo's {p:?}");
        }
        assert_ne!(kept[..3], style[..3]);
    }
}
