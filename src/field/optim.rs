//! What the optimisers of both stages share: RMSprop (dense, and lazy on a
//! subset of rows), the total-variation regulariser, the subset of grid rows
//! a step touches, and the exponential rate schedule.
//!
//! RMSprop rather than Adam: it is what Plenoxels uses with published,
//! well-tested learning rates for density (30) and SH (1e-2), and its
//! per-coordinate normalisation copes with the very different gradient
//! scales of density and colour.

use burn::tensor::{Device, Int, Tensor};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use std::sync::atomic::{AtomicI32, AtomicU64, Ordering::Relaxed};

use crate::field::grid::CellLattice;
use crate::kernels::rows_op;
use crate::util::tensor::{floats, indices, is_host_memory, to_vec};

/// Exponential decay from `a` to `b` over `t` in [0, 1].
pub fn log_lerp(a: f32, b: f32, t: f32) -> f32 {
    (a.ln() * (1.0 - t) + b.ln() * t).exp()
}

/// Where RMSprop's running average of squared gradients starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RmsStart {
    /// At zero (PyTorch): the first steps are up to 1/sqrt(1 - beta) times lr.
    Zero,
    /// At the first squared gradient (svox2's kernel: `rms == 0 ? g*g : lerp`):
    /// the first step of every coordinate is lr * sign(g).
    FirstGrad,
}

/// RMSprop: v = beta v + (1 - beta) g^2; x -= lr g / (sqrt(v) + eps).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rmsprop {
    pub beta: f32,
    pub eps: f32,
    pub start: RmsStart,
}

impl Rmsprop {
    /// The running average after gradient `grad`.
    fn average(&self, avg: Tensor<2>, grad: Tensor<2>) -> Tensor<2> {
        let sq = grad.clone() * grad;
        match self.start {
            RmsStart::Zero => avg * self.beta + sq * (1.0 - self.beta),
            RmsStart::FirstGrad => {
                let fresh = avg.clone().equal_elem(0.0);
                (avg * self.beta + sq.clone() * (1.0 - self.beta)).mask_where(fresh, sq)
            }
        }
    }

    /// The normalised gradient g / (sqrt(v) + eps), before the learning rate.
    fn normalised(&self, grad: Tensor<2>, avg: Tensor<2>) -> Tensor<2> {
        grad / (avg.sqrt() + self.eps)
    }

    /// A step on every row of `param` (its running average `avg` has the same shape).
    pub fn step_dense(&self, param: &mut Tensor<2>, avg: &mut Tensor<2>, grad: Tensor<2>, lr: f32) {
        // Taking the tensors out of their slots leaves them uniquely owned,
        // so the backend updates them in place instead of copying the grid.
        let a = take(avg);
        *avg = self.average(a, grad.clone());
        let p = take(param);
        *param = p - self.normalised(grad, avg.clone()) * lr;
    }

    /// A lazy step on the given rows only ("sparse" updates as Plenoxels:
    /// cost follows the rows, not the grid); `rows_t` holds `rows` as a
    /// tensor and `grad` those rows' gradients in the same order (distinct
    /// rows). On a GPU one kernel per tensor (`kernels::optim_op`).
    pub fn step_rows(
        &self,
        param: &mut Tensor<2>,
        avg: &mut Tensor<2>,
        rows: &[i32],
        rows_t: &Tensor<1, Int>,
        grad: Tensor<2>,
        lr: f32,
    ) {
        #[cfg(feature = "wgpu")]
        if !is_host_memory(&param.device()) {
            use crate::kernels::optim_op::OptimBackend;
            let (p, a) = <burn::backend::Dispatch as OptimBackend>::rmsprop_rows(
                take(param).into_dispatch(),
                take(avg).into_dispatch(),
                rows_t.clone().into_dispatch(),
                grad.into_dispatch(),
                self.beta,
                self.eps,
                lr,
                self.start == RmsStart::FirstGrad,
            );
            (*param, *avg) = (Tensor::from_dispatch(p), Tensor::from_dispatch(a));
            return;
        }
        let v_old = rows_op::gather_rows(avg, rows, rows_t);
        let v_new = self.average(v_old.clone(), grad.clone());
        let update = self.normalised(grad, v_new.clone()) * (-lr);
        add_rows(avg, rows, rows_t, v_new - v_old);
        add_rows(param, rows, rows_t, update);
    }

    /// One coordinate's step: from its running average `v` and gradient `g`,
    /// what to add to the average and what to add to the coordinate.
    #[inline]
    fn coordinate_step(&self, v: f32, g: f32, lr: f32) -> (f32, f32) {
        let sq = g * g;
        let v_new = match self.start {
            RmsStart::FirstGrad if v == 0.0 => sq,
            _ => v * self.beta + sq * (1.0 - self.beta),
        };
        (v_new - v, g / (v_new.sqrt() + self.eps) * (-lr))
    }

    /// [`step_rows`](Self::step_rows) with the gradient on the host (`grad`,
    /// `[rows.len(), cols]`), in one pass over each row of `param` and `avg`
    /// (`kernels::rows_op::update_row_pairs`: in place on flex) and the same
    /// numbers: the average gets `v_new - v` added, the row its step.
    pub fn host_step_rows(
        &self,
        param: &mut Tensor<2>,
        avg: &mut Tensor<2>,
        rows: &[i32],
        rows_t: &Tensor<1, Int>,
        grad: &[f32],
        lr: f32,
    ) {
        let cols = param.dims()[1];
        assert_eq!(grad.len(), rows.len() * cols, "one gradient row per step row");
        rows_op::update_row_pairs(avg, param, rows, rows_t, &|k, v, p| {
            for ((v, p), &g) in v.iter_mut().zip(p.iter_mut()).zip(&grad[k * cols..(k + 1) * cols]) {
                let (dv, step) = self.coordinate_step(*v, g, lr);
                *v += dv;
                *p += step;
            }
        });
    }
}

/// Adds `values` to the rows `rows` of `slot` (a grid-sized tensor;
/// `rows_t` holds the same indices as a tensor), in place: the tensor is
/// moved out of its slot first, so the backend sees it uniquely owned
/// instead of copying the grid. In parallel on flex (`kernels::rows_op`).
pub fn add_rows(slot: &mut Tensor<2>, rows: &[i32], rows_t: &Tensor<1, Int>, values: Tensor<2>) {
    let t = take(slot);
    *slot = rows_op::add_to_rows(t, rows, rows_t, values);
}

/// Moves a tensor out of its slot (leaving a 1x1 placeholder).
fn take(slot: &mut Tensor<2>) -> Tensor<2> {
    let device = slot.device();
    std::mem::replace(slot, Tensor::zeros([1, 1], &device))
}

/// Appends to `out`, in order, the rows of `rows` not yet marked in the
/// bitmap `seen` (one bit per row of a grid of `num_rows`), marking them.
/// Without branches (whether a row is new is a coin toss to the
/// processor): every row is written, and the count moves past the new ones.
fn append_new(rows: &[i32], num_rows: usize, seen: &mut [u64], out: &mut Vec<i32>) {
    let start = out.len();
    out.resize(start + rows.len(), 0);
    let mut count = start;
    for &r in rows {
        assert!(r >= 0 && (r as usize) < num_rows, "row {r} out of range for {num_rows} rows");
        let (word, bit) = (r as usize / 64, 1u64 << (r % 64));
        let marks = seen[word];
        out[count] = r;
        count += usize::from(marks & bit == 0);
        seen[word] = marks | bit;
    }
    out.truncate(count);
}

/// How total variation combines the channels of a voxel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TvNorm {
    /// sum over channels of sqrt(dx^2 + dy^2 + dz^2 + eps) (Plenoxels' fit).
    PerChannel,
    /// sqrt(sum over channels of dx^2 + dy^2 + dz^2, + eps) (the stylization).
    PerVoxel,
}

/// Total variation summed over the rows of `centre`: `neighbours` yields,
/// for the +x, +y and +z axes, the values at each row's neighbour (the row
/// itself where there is none, which adds nothing). Callers scale the sum.
/// The iterator is consumed lazily, one axis at a time, so each gather sits
/// next to its use in the graph.
pub fn total_variation(centre: Tensor<2>, neighbours: impl Iterator<Item = Tensor<2>>, norm: TvNorm) -> Tensor<1> {
    let sq = neighbours
        .map(|nb| {
            let d = nb - centre.clone();
            d.clone() * d
        })
        .reduce(|a, b| a + b)
        .expect("three axes");
    match norm {
        TvNorm::PerChannel => (sq + 1e-9).sqrt().sum(),
        TvNorm::PerVoxel => (sq.sum_dim(1) + 1e-9).sqrt().sum(),
    }
}

/// Adds the gradient of `scale * total_variation(..., TvNorm::PerChannel)`
/// to `grad`, on host values: `values` and `grad` are `[rows, channels]`;
/// the first `neighbours[axis].len()` rows are the centres and
/// `neighbours[axis][i]` the row of centre i's neighbour along each axis
/// (the centre itself where there is none, which adds nothing). Serial:
/// a neighbour may be any row, and the TV rows are a tenth of a step's.
pub fn add_tv_gradient_per_channel(
    values: &[f32],
    channels: usize,
    neighbours: &[Vec<i32>; 3],
    scale: f32,
    grad: &mut [f32],
) {
    assert_eq!(values.len(), grad.len(), "one gradient per value");
    let num_core = neighbours[0].len();
    // A centre's three differences and scaled inverse norms, channel by
    // channel. Whole rows at a time (loops the compiler vectorises); each
    // gradient value still gets its terms in the order of the scalar
    // definition (centre by centre, axis by axis, the neighbour's before
    // the centre's), so the sums are the same bits.
    let mut diffs = vec![0.0f32; 3 * channels];
    let mut inv = vec![0.0f32; channels];
    for i in 0..num_core {
        // The neighbours are rows anywhere in the step: ask for the rows of
        // a later centre now.
        for nb in neighbours.iter().filter_map(|nb| nb.get(i + rows_op::PREFETCH_AHEAD)) {
            rows_op::prefetch_row(values, *nb as usize, channels);
            rows_op::prefetch_row(grad, *nb as usize, channels);
        }
        let row = |r: usize| r * channels..(r + 1) * channels;
        let nbs: [usize; 3] = std::array::from_fn(|axis| neighbours[axis][i] as usize);
        let centre = &values[row(i)];
        for (d, &nb) in diffs.chunks_exact_mut(channels).zip(&nbs) {
            for ((d, &v), &c) in d.iter_mut().zip(&values[row(nb)]).zip(centre) {
                *d = v - c;
            }
        }
        let (d0, d12) = diffs.split_at(channels);
        let (d1, d2) = d12.split_at(channels);
        for (ch, inv) in inv.iter_mut().enumerate() {
            let sq = d0[ch] * d0[ch] + d1[ch] * d1[ch] + d2[ch] * d2[ch];
            // d sqrt(sq + eps) / d d_axis = d_axis / sqrt(sq + eps).
            *inv = scale / (sq + 1e-9).sqrt();
        }
        for (d, &nb) in diffs.chunks_exact(channels).zip(&nbs) {
            for ((g, &d), &inv) in grad[row(nb)].iter_mut().zip(d).zip(&inv) {
                *g += d * inv;
            }
            for ((g, &d), &inv) in grad[row(i)].iter_mut().zip(d).zip(&inv) {
                *g -= d * inv;
            }
        }
    }
}

/// A step's TV terms as the TV kernel reads them: for each of the first
/// `num_core` rows (the centres) its +x, +y, +z neighbour (itself where
/// there is none), on the device (and on the host, for the CPU backends).
pub struct TvLinks {
    neighbours: [Vec<i32>; 3],
    /// `[3 num_core]`: the neighbours, axis by axis.
    links: Tensor<1, Int>,
    num_core: usize,
}

impl TvLinks {
    /// The neighbours of centres `0..neighbours[0].len()`, uploaded to
    /// `device`. Along each axis, no two centres may share a neighbour
    /// other than themselves (a lattice's neighbours; checked).
    pub fn new(neighbours: &[Vec<i32>; 3], device: &Device) -> Self {
        let num_core = neighbours[0].len();
        let mut seen = std::collections::HashSet::new();
        for (axis, nb) in neighbours.iter().enumerate() {
            seen.clear();
            for (centre, &r) in nb.iter().enumerate() {
                let shared = r as usize != centre && !seen.insert(r);
                assert!(!shared, "row {r} is the neighbour of two centres along axis {axis}");
            }
        }
        let links = indices(neighbours.iter().flatten().copied().collect(), device);
        Self { neighbours: neighbours.clone(), links, num_core }
    }
}

/// `grad` plus the gradient of `scale` x Plenoxels' per-channel TV of
/// `values` (`[rows, cols]`) over the centres of `links`:
/// `optim::add_tv_gradient_per_channel`'s numbers, on the GPU by one
/// thread per value (`kernels::optim_op`), on the CPU backends by that function.
pub fn add_tv_gradient(grad: Tensor<2>, values: &Tensor<2>, links: &TvLinks, scale: f32) -> Tensor<2> {
    if links.num_core == 0 {
        return grad;
    }
    #[cfg(feature = "wgpu")]
    if !is_host_memory(&grad.device()) {
        use crate::kernels::optim_op::OptimBackend;
        let out = <burn::backend::Dispatch as OptimBackend>::add_tv_gradient(
            grad.into_dispatch(),
            values.clone().into_dispatch(),
            links.links.clone().into_dispatch(),
            links.num_core,
            scale,
        );
        return Tensor::from_dispatch(out);
    }
    let (dims, device) = (grad.dims(), grad.device());
    let mut host = to_vec(grad);
    add_tv_gradient_per_channel(&to_vec(values.clone()), dims[1], &links.neighbours, scale, &mut host);
    floats(host, dims, &device)
}

/// A subset of grid rows (those a step touches) and the map grid row ->
/// local index. Kept between steps: starting a new subset resets only the
/// entries the last one set, so its cost follows the subset (a few hundred
/// thousand rows), not the grid (millions).
#[derive(Debug, Default)]
pub struct RowSubset {
    /// Local index per grid row, -1 outside the subset. Atomic so that
    /// the passes over distinct rows can write it from several threads
    /// (relaxed loads and stores are plain moves).
    local_of: Vec<AtomicI32>,
    rows: Vec<i32>,
    /// `reset_to`'s scratch, kept: a bitmap of the rows seen and the
    /// distinct rows of each piece of the list.
    piece_seen: Vec<Vec<u64>>,
    piece_rows: Vec<Vec<i32>>,
}

/// Entries of a list below which `reset_to` numbers it on one thread.
const MIN_PIECE: usize = 1 << 16;

impl RowSubset {
    /// Empties the subset for a grid of `num_rows` rows.
    pub fn clear(&mut self, num_rows: usize) {
        if self.local_of.len() == num_rows {
            let local_of = &self.local_of;
            self.rows.par_iter().with_min_len(1 << 14).for_each(|&r| local_of[r as usize].store(-1, Relaxed));
        } else {
            self.local_of = (0..num_rows).map(|_| AtomicI32::new(-1)).collect();
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
    ///
    /// In parallel, and the same order on any thread count: the list is
    /// cut into pieces, each piece finds its distinct rows in first-seen
    /// order (a bitmap of the grid's rows, a few hundred kB, stays in the
    /// core's cache where the grid-sized map would not), and a serial merge
    /// takes each piece's rows in piece order, skipping those an earlier
    /// piece had: the first-seen order of the whole list. A training step
    /// on fern numbers 2 M corner entries so, about 400,000 distinct rows.
    pub fn reset_to(&mut self, num_rows: usize, rows: &[i32]) {
        self.reset_to_arranged(num_rows, rows, |_| {});
    }

    /// `reset_to`, with the distinct rows put in the order `arrange` gives
    /// them before the map grid row -> local index is written: a caller
    /// that moves many rows saves the map's random writes of each move.
    pub fn reset_to_arranged(&mut self, num_rows: usize, rows: &[i32], arrange: impl FnOnce(&mut [i32])) {
        self.clear(num_rows);
        let piece_len = rows.len().div_ceil(rayon::current_num_threads()).max(MIN_PIECE);
        let pieces = rows.len().div_ceil(piece_len);
        if pieces == 0 {
            arrange(&mut self.rows);
            return;
        }
        let words = num_rows.div_ceil(64);
        self.piece_seen.resize_with(pieces, Vec::new);
        self.piece_rows.resize_with(pieces, Vec::new);
        let scratch = self.piece_seen.par_iter_mut().zip(self.piece_rows.par_iter_mut());
        scratch.zip(rows.par_chunks(piece_len)).for_each(|((seen, distinct), piece)| {
            seen.clear();
            seen.resize(words, 0);
            distinct.clear();
            append_new(piece, num_rows, seen, distinct);
        });
        // The first piece's rows are all new; its bitmap becomes the union.
        let union = &mut self.piece_seen[0];
        self.rows.extend_from_slice(&self.piece_rows[0]);
        for later in &self.piece_rows[1..pieces] {
            append_new(later, num_rows, union, &mut self.rows);
        }
        arrange(&mut self.rows);
        // Distinct rows: each entry of the map is written once.
        let local_of = &self.local_of;
        self.rows
            .par_iter()
            .enumerate()
            .with_min_len(1 << 14)
            .for_each(|(i, &r)| local_of[r as usize].store(i as i32, Relaxed));
    }

    /// Clears, then holds the distinct rows of all `lists` in increasing
    /// order, marked in a bitmap in parallel (a fern view's samples have
    /// tens of millions of corner entries; measured, this is not where a
    /// fern step's `step_rows` time goes: see docs/performance.md).
    pub fn reset_to_union(&mut self, num_rows: usize, lists: &[&[i32]]) {
        self.reset_to_union_with_cells(num_rows, lists, &CellLattice::default(), &[]);
    }

    /// `reset_to_union` of `lists` and the rows of the cells `cells` (lattice
    /// indices of their bases, read through `lattice`).
    pub fn reset_to_union_with_cells(
        &mut self,
        num_rows: usize,
        lists: &[&[i32]],
        lattice: &CellLattice,
        cells: &[&[u32]],
    ) {
        const CHUNK: usize = 1 << 16;
        self.clear(num_rows);
        let words: Vec<AtomicU64> = (0..num_rows.div_ceil(64)).map(|_| AtomicU64::new(0)).collect();
        let mark = |r: i32| {
            assert!(r >= 0 && (r as usize) < num_rows, "row {r} out of range for {num_rows} rows");
            let (word, bit) = (&words[r as usize / 64], 1u64 << (r % 64));
            // Most entries repeat a row (neighbouring samples share corners): read first.
            if word.load(Relaxed) & bit == 0 {
                word.fetch_or(bit, Relaxed);
            }
        };
        lists.par_iter().flat_map(|list| list.par_chunks(CHUNK)).for_each(|chunk| chunk.iter().for_each(|&r| mark(r)));
        // A cell's empty corners point at one of its active rows: its
        // active corners' rows are all it touches.
        cells.par_iter().flat_map(|list| list.par_chunks(CHUNK / 8)).for_each(|chunk| {
            for &key in chunk {
                lattice.raw_rows(key as usize).into_iter().filter(|&r| r >= 0).for_each(mark);
            }
        });
        for (w, word) in words.into_iter().enumerate() {
            let mut bits = word.into_inner();
            while bits != 0 {
                let row = w * 64 + bits.trailing_zeros() as usize;
                *self.local_of[row].get_mut() = self.rows.len() as i32;
                self.rows.push(row as i32);
                bits &= bits - 1;
            }
        }
    }

    /// Local index of `row`, adding it at the end if new.
    pub fn insert(&mut self, row: i32) -> i32 {
        let slot = self.local_of[row as usize].get_mut();
        if *slot < 0 {
            *slot = self.rows.len() as i32;
            self.rows.push(row);
        }
        *slot
    }

    /// A hint to start loading `row`'s entry of the map (`insert` and
    /// `local` of rows anywhere in the grid wait on memory for it).
    pub fn prefetch(&self, row: i32) {
        rows_op::prefetch_row(&self.local_of, row as usize, 1);
    }

    /// Local index of `row` (-1 when not in the subset).
    pub fn local(&self, row: i32) -> i32 {
        self.local_of[row as usize].load(Relaxed)
    }

    /// The grid rows, in local order.
    pub fn rows(&self) -> &[i32] {
        &self.rows
    }
}

#[cfg(test)]
mod tests {
    use super::{MIN_PIECE, RowSubset, add_tv_gradient_per_channel};
    use crate::field::grid::CellLattice;

    /// A deterministic stream of pseudo-random numbers for the tests.
    fn lcg(seed: u64) -> impl FnMut() -> usize {
        let mut state = seed;
        move || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (state >> 33) as usize
        }
    }

    /// The distinct rows of `list` in first-seen order, one at a time.
    fn first_seen(num_rows: usize, list: &[i32]) -> Vec<i32> {
        let mut seen = vec![false; num_rows];
        list.iter().copied().filter(|&r| !std::mem::replace(&mut seen[r as usize], true)).collect()
    }

    /// The numbering in pieces gives the one-at-a-time first-seen order on
    /// any thread count: a list of several pieces, with rows repeated
    /// within a piece, across pieces and in whole runs of 8 (the corners of
    /// samples in one cell), numbered into a reused subset.
    #[test]
    fn numbering_in_pieces_gives_the_first_seen_order() {
        let num_rows = 50_000;
        let mut next = lcg(7);
        let mut list = Vec::new();
        while list.len() < 5 * MIN_PIECE {
            let corners: Vec<i32> = (0..8)
                .map(|_| if next().is_multiple_of(2) { next() % 3000 } else { next() % num_rows } as i32)
                .collect();
            for _ in 0..1 + next() % 3 {
                list.extend_from_slice(&corners);
            }
        }
        let want = first_seen(num_rows, &list);
        let short = first_seen(num_rows, &list[..100]);
        let in_want: std::collections::HashSet<i32> = want.iter().copied().collect();
        let absent = (0..num_rows as i32).find(|r| !in_want.contains(r)).expect("a row the list misses");
        let only_long = *want.iter().find(|r| !short.contains(r)).expect("a row past the first 100 entries");
        let mut s = RowSubset::of(num_rows, &list[..1000]);
        for threads in [1, 2, 3, 8] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| s.reset_to(num_rows, &list));
            assert_eq!(s.rows(), &want[..], "{threads} threads");
            assert!(want.iter().enumerate().all(|(i, &r)| s.local(r) == i as i32), "{threads} threads: the map");
            assert_eq!(s.local(absent), -1);
            // A shorter list on the same subset forgets the rows only the longer one had.
            pool.install(|| s.reset_to(num_rows, &list[..100]));
            assert_eq!((s.rows(), s.local(only_long)), (&short[..], -1), "{threads} threads");
        }
        s.reset_to(num_rows, &[]);
        assert!(s.rows().is_empty() && s.local(short[0]) == -1);
    }

    #[test]
    #[should_panic(expected = "row 12 out of range for 10 rows")]
    fn numbering_refuses_a_row_past_the_grid() {
        RowSubset::of(10, &[3, 12]);
    }

    /// The row-at-a-time TV gradient gives the scalar definition's sums to
    /// the bit: every value gets its terms centre by centre, axis by axis,
    /// the neighbour's term before the centre's, whether its neighbour is
    /// another row, itself, or shared with other centres.
    #[test]
    fn tv_gradient_by_rows_is_the_scalar_definition_to_the_bit() {
        let (rows, core, scale) = (40, 15, 0.37f32);
        let mut next = lcg(11);
        let neighbours: [Vec<i32>; 3] = [
            (0..core).map(|i| ((i * 13 + 5) % rows) as i32).collect(),
            (0..core).map(|i| if i % 4 == 0 { i as i32 } else { (rows - 1 - i) as i32 }).collect(),
            (0..core).map(|i| (30 + i % 3) as i32).collect(),
        ];
        for channels in [1, 4, 27] {
            let values: Vec<f32> = (0..rows * channels).map(|_| (next() % 2001) as f32 / 1000.0 - 1.0).collect();
            let start: Vec<f32> = (0..rows * channels).map(|_| (next() % 201) as f32 / 1e4 - 0.01).collect();
            let mut scalar = start.clone();
            for i in 0..core {
                for ch in 0..channels {
                    let centre = values[i * channels + ch];
                    let d: [f32; 3] =
                        std::array::from_fn(|axis| values[neighbours[axis][i] as usize * channels + ch] - centre);
                    let inv = scale / (d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + 1e-9).sqrt();
                    for (axis, d) in d.iter().enumerate() {
                        scalar[neighbours[axis][i] as usize * channels + ch] += d * inv;
                        scalar[i * channels + ch] -= d * inv;
                    }
                }
            }
            let mut by_rows = start.clone();
            add_tv_gradient_per_channel(&values, channels, &neighbours, scale, &mut by_rows);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&by_rows), bits(&scalar), "{channels} channels");
            assert_ne!(by_rows, start, "{channels} channels: the terms moved the gradient");
        }
    }

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
        // The union of lists, in increasing row order, across 64-row words.
        let mut u = RowSubset::of(200, &[7, 3]);
        u.reset_to_union(200, &[&[130, 5, 64, 5], &[], &[63, 130, 199, 0]]);
        assert_eq!(u.rows(), &[0, 5, 63, 64, 130, 199]);
        assert_eq!((u.local(64), u.local(199), u.local(7), u.local(3)), (3, 5, -1, -1));
        // With cells: a 1x2x3 lattice whose corner offsets reach +1 and +3
        // (the other corners repeat the base); point 4 is empty.
        let lattice = CellLattice::new(std::sync::Arc::new(vec![9, 8, 7, 6, -1, 5]), [0, 1, 3, 4, 0, 1, 3, 4]);
        u.reset_to_union_with_cells(12, &[&[11]], &lattice, &[&[1], &[0, 0]]);
        // Cell 1: points 1, 2, 4 (empty), 5; cell 0: points 0, 1, 3, 4 (empty).
        assert_eq!(u.rows(), &[5, 6, 7, 8, 9, 11]);
    }
}

/// `Rmsprop::step_rows` (`kernels::optim_op`'s kernel on a GPU, Burn's operations on the CPU
/// backends) against `Rmsprop::host_step_rows` (the arithmetic in plain
/// Rust), on every backend the test command runs (`cargo test --lib
/// graph_oracle`).
#[cfg(test)]
#[allow(clippy::print_stdout)] // the measured errors, shown with --nocapture
mod graph_oracle {
    use burn::tensor::Tensor;

    use super::{RmsStart, Rmsprop, TvLinks, add_tv_gradient, add_tv_gradient_per_channel};
    use crate::test_support::device;
    use crate::util::tensor::{floats, indices, to_vec};

    /// The TV gradient (`kernels::optim_op`'s kernel on a GPU) against the host
    /// loop `add_tv_gradient_per_channel`, on a 6³ lattice whose first 100
    /// rows are the centres (those on the far faces are their own
    /// neighbours there): 1e-5 of the largest value (the kernel adds each
    /// row's terms in another order), rows no centre reaches unchanged.
    #[test]
    fn the_tv_gradient_matches_the_host_loop() {
        let dev = device();
        let (side, cols, num_core) = (6usize, 4usize, 100usize);
        let rows = side.pow(3);
        let step = |i: usize, stride: usize, coord: usize| if coord + 1 < side { i + stride } else { i } as i32;
        let neighbours: [Vec<i32>; 3] = [
            (0..num_core).map(|i| step(i, 1, i % side)).collect(),
            (0..num_core).map(|i| step(i, side, i / side % side)).collect(),
            (0..num_core).map(|i| step(i, side * side, i / (side * side))).collect(),
        ];
        let values: Vec<f32> = (0..rows * cols).map(|i| ((i * 37) % 29) as f32 / 29.0 - 0.3).collect();
        let before: Vec<f32> = (0..rows * cols).map(|i| ((i * 11) % 7) as f32 * 0.01).collect();
        let links = TvLinks::new(&neighbours, &dev);
        let values_t = floats(values.clone(), [rows, cols], &dev);
        let ours = to_vec(add_tv_gradient(floats(before.clone(), [rows, cols], &dev), &values_t, &links, 0.7));
        let mut host = before.clone();
        add_tv_gradient_per_channel(&values, cols, &neighbours, 0.7, &mut host);
        let scale = host.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let err = ours.iter().zip(&host).fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
        println!("TV gradient: max |kernel - host| = {err:.2e} of {scale:.2e}");
        assert!(err <= 1e-5 * scale, "{err:.2e} of {scale:.2e}");
        let reached = num_core + side * side;
        assert!(ours[..reached * cols] != before[..reached * cols], "the TV terms added nothing");
        assert!(ours[reached * cols..] == before[reached * cols..], "rows no centre reaches moved");
    }

    /// Both starts, over rows whose averages are zero (a first step) and
    /// rows already averaged, gradients of both signs and zero: the same
    /// parameters and averages to 1e-6 of their largest value (a GPU's
    /// division and square root need not round as the CPU's do); the rows
    /// outside the step and a copy of the tensors taken before it keep
    /// their values exactly.
    #[test]
    fn the_row_step_matches_the_host_step() {
        let dev = device();
        let (n, cols) = (300, 9);
        let rows: Vec<i32> = (0..120).map(|k| (k * 7 + 3) % n as i32).collect();
        let param: Vec<f32> = (0..n * cols).map(|i| ((i * 31) % 19) as f32 / 19.0 - 0.5).collect();
        let avg: Vec<f32> =
            (0..n * cols).map(|i| if i % 3 == 0 { 0.0 } else { ((i * 17) % 11) as f32 * 1e-3 }).collect();
        let grad: Vec<f32> = (0..rows.len() * cols).map(|i| ((i * 13) % 9) as f32 * 0.1 - 0.4).collect();
        let rows_t = indices(rows.clone(), &dev);
        for start in [RmsStart::Zero, RmsStart::FirstGrad] {
            let opt = Rmsprop { beta: 0.95, eps: 1e-8, start };
            let (mut p, mut a) = (floats(param.clone(), [n, cols], &dev), floats(avg.clone(), [n, cols], &dev));
            let (kept_p, kept_a): (Tensor<2>, Tensor<2>) = (p.clone(), a.clone());
            opt.step_rows(&mut p, &mut a, &rows, &rows_t, floats(grad.clone(), [rows.len(), cols], &dev), 0.3);
            let (mut hp, mut ha) = (floats(param.clone(), [n, cols], &dev), floats(avg.clone(), [n, cols], &dev));
            opt.host_step_rows(&mut hp, &mut ha, &rows, &rows_t, &grad, 0.3);
            assert!(to_vec(kept_p) == param && to_vec(kept_a) == avg, "{start:?}: a copy taken before changed");
            for (name, ours, host, before) in [("param", p, hp, &param), ("avg", a, ha, &avg)] {
                let (ours, host) = (to_vec(ours), to_vec(host));
                let scale = host.iter().fold(0.0f32, |m, v| m.max(v.abs()));
                let err = ours.iter().zip(&host).fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
                println!("{start:?} {name}: max |step_rows - host| = {err:.2e} of {scale:.2e}");
                assert!(err <= 1e-6 * scale, "{start:?} {name}: {err:.2e} of {scale:.2e}");
                assert!(ours != *before, "{start:?} {name}: the step changed nothing");
                for r in (0..n).filter(|r| !rows.contains(&(*r as i32))) {
                    assert!(
                        ours[r * cols..(r + 1) * cols] == before[r * cols..(r + 1) * cols],
                        "{name}: row {r} moved"
                    );
                }
            }
        }
    }
}
