//! Rendering with frozen density: stylization never changes the density, so
//! which samples a ray has and how much each contributes (its weight
//! T_i (1 - exp(-sigma_i delta_i)) and the ray's final transmittance) are
//! fixed. They are computed once in plain Rust from the density mirror and
//! kept; what is left for the Burn graph is the view-independent colour:
//! gather the 8 corner SH rows, interpolate, `max(C0 c + 0.5, 0)`, weight
//! and sum per ray. This is the whole differentiable renderer of the
//! stylization phase, and it is linear in the samples, which makes the
//! cached lists cheap to reuse every epoch.

use burn::tensor::{Device, IndexingUpdateOp, Int, Tensor, activation::relu};

use crate::field::composite::{interpolate_corners, max_samples_per_call};
use crate::field::grid::{CellLattice, RadianceGrid, weights_of_fractions};
use crate::field::march::{ColourCorners, MarchParams, Marcher, colour_weights};
#[cfg(feature = "wgpu")]
use crate::kernels::frozen_op;
use crate::kernels::gather_op::{RowIndex, gather_rows, runs_of, sum_runs};
use crate::scene::camera::Ray;
use crate::scene::sh;
use crate::util::budget_ranges;
use crate::util::tensor::{assign_rows, cumsum_rows, floats, indices, is_host_memory, select_rows, to_vec};
use rayon::prelude::*;

/// Rays marched between two checks of a cache's budget (`march_within`):
/// a refused march holds at most the budget plus one chunk's lists.
pub const MARCH_CHUNK: usize = 16384;

/// Rays marched per rayon task.
const RAYS_PER_TASK: usize = 256;

/// Samples of a set of rays with their fixed weights (plain buffers),
/// compact: consecutive samples of a ray that fall in one lattice cell
/// (half a voxel apart, many do) share one cell entry, the flat lattice
/// index of the cell's base, whose 8 rows and active corners are read
/// back from the grid's links when used (`CellLattice::cell`, what the
/// march itself computes); a sample keeps where it lies in its cell, not
/// its 8 colour weights, which are recomputed from that when read
/// (`colour_weights`, the march's own formula: the same numbers to the
/// bit). A sample costs 17 bytes and a cell 4, against 68 bytes a sample
/// with every sample's rows and weights written out (and 33 a cell with
/// its rows and active corners written out).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrozenSamples {
    pub num_rays: usize,
    /// Samples of ray r are `ray_offsets[r]..ray_offsets[r + 1]`.
    pub ray_offsets: Vec<u32>,
    /// Cells of ray r are `ray_cells[r]..ray_cells[r + 1]`.
    pub ray_cells: Vec<u32>,
    /// The flat lattice index of each cell's base: its rows and active
    /// corners are `lattice.cell(key)`.
    pub cell_keys: Vec<u32>,
    /// The links the cell keys are read through (shared with the grid).
    pub lattice: CellLattice,
    /// Whether a sample is the first of its cell (the ray's next cell); a
    /// ray's first sample always is.
    pub starts_cell: Vec<bool>,
    /// Where each sample lies inside its cell (`GridGeometry::trilinear_fractions`).
    pub fractions: Vec<[f32; 3]>,
    /// Compositing weight of each sample.
    pub weight: Vec<f32>,
    /// Transmittance left at the end of each ray (multiplies the background).
    pub final_transmittance: Vec<f32>,
    /// The far background's colour behind each ray (`RadianceGrid::far`);
    /// empty when the grid has none and the constant background applies.
    pub far: Vec<[f32; 3]>,
    /// How the colour weights treat inactive corners (the march's setting).
    pub colour_corners: ColourCorners,
}

/// One sample as read from the lists: its index, its cell's 8 rows and its
/// colour interpolation weights.
pub struct ListedSample {
    pub index: usize,
    pub rows: [i32; 8],
    pub colour_weights: [f32; 8],
}

impl FrozenSamples {
    /// No rays yet, cells read through `lattice`, colour weights as `colour_corners` says.
    pub fn empty(lattice: CellLattice, colour_corners: ColourCorners) -> Self {
        Self { ray_offsets: vec![0], ray_cells: vec![0], lattice, colour_corners, ..Default::default() }
    }

    /// Marches `rays` through the grid and computes every sample's weight from
    /// the density mirror, exactly as `render::composite` does. Samples whose
    /// weight is below `min_weight` are dropped (their colour cannot matter
    /// to the image; 0 keeps all).
    pub fn march(marcher: &Marcher, rays: &[Ray], params: &MarchParams, min_weight: f32) -> Self {
        Self::march_within(marcher, rays, params, min_weight, MARCH_CHUNK, usize::MAX)
            .expect("an unbounded march always fits")
    }

    /// `march`, `chunk` rays at a time, giving up (None) as soon as the kept
    /// samples hold more than `budget` bytes (checked after each chunk, so
    /// a refused march holds at most the budget plus one chunk). The result
    /// does not depend on `chunk`. Each sample is weighted and cut as the
    /// march finds it: the unfiltered samples are never stored (packed
    /// first, fern's 1.9 M registered pixels needed more than 20 GB, and
    /// re-marching a fern view cost 1.9 s of a 6.6 s image step).
    pub fn march_within(
        marcher: &Marcher,
        rays: &[Ray],
        params: &MarchParams,
        min_weight: f32,
        chunk: usize,
        budget: usize,
    ) -> Option<Self> {
        let lattice = marcher.lattice();
        let mut out = Self::empty(lattice.clone(), params.colour_corners);
        out.ray_offsets.reserve(rays.len());
        out.ray_cells.reserve(rays.len());
        for part in rays.chunks(chunk.max(1)) {
            // Each task keeps its rays' samples in a buffer of its own; the
            // buffers are appended in ray order, so the lists do not depend
            // on the thread count.
            let pieces: Vec<FrozenSamples> = part
                .par_chunks(RAYS_PER_TASK)
                .map(|rays| {
                    let mut piece = Self::empty(lattice.clone(), params.colour_corners);
                    for ray in rays {
                        piece.push_ray(marcher, ray, params, min_weight);
                    }
                    piece
                })
                .collect();
            for piece in &pieces {
                out.append(piece);
            }
            if out.bytes() > budget {
                return None;
            }
        }
        Some(out)
    }

    /// Marches one ray and appends the samples whose compositing weight
    /// exceeds `min_weight` (0 keeps all), as they are found: no packed
    /// batch of every sample is built first. A kept sample opens a new
    /// cell entry unless it lies in the cell of the ray's previous kept
    /// sample.
    fn push_ray(&mut self, marcher: &Marcher, ray: &Ray, params: &MarchParams, min_weight: f32) {
        let mut optical = 0.0f32;
        let first_cell = self.cell_keys.len();
        marcher.walk(ray, params, |s| {
            let tau = s.sigma.max(0.0) * s.delta;
            let w = (-optical).exp() * (1.0 - (-tau).exp());
            optical += tau;
            if w > min_weight || (min_weight == 0.0 && w >= 0.0) {
                // Lattice indices fit u32: the grid's `coords` are u32 too.
                let key = s.key as u32;
                let last = self.cell_keys.len();
                let same_cell = last > first_cell && self.cell_keys[last - 1] == key;
                if !same_cell {
                    self.cell_keys.push(key);
                }
                self.starts_cell.push(!same_cell);
                self.fractions.push(s.fractions);
                self.weight.push(w);
            }
        });
        self.final_transmittance.push((-optical).exp());
        if let Some(far) = &marcher.grid().far {
            self.far.push(far.colour(ray.view_dir));
        }
        self.ray_offsets.push(self.weight.len() as u32);
        self.ray_cells.push(self.cell_keys.len() as u32);
        self.num_rays += 1;
    }

    pub fn num_samples(&self) -> usize {
        self.weight.len()
    }

    pub fn num_cells(&self) -> usize {
        self.cell_keys.len()
    }

    /// Bytes held by the buffers (the shared links not counted: the grid holds them).
    pub fn bytes(&self) -> usize {
        (self.ray_offsets.len() + self.ray_cells.len() + self.final_transmittance.len() + self.cell_keys.len()) * 4
            + self.far.len() * 12
            + self.num_samples() * (1 + 12 + 4)
    }

    /// The cells of ray `r` (their base's lattice index; what its samples touch).
    pub fn ray_cells(&self, r: usize) -> &[u32] {
        &self.cell_keys[self.ray_cells[r] as usize..self.ray_cells[r + 1] as usize]
    }

    /// Starts loading the links of ray `r`'s cells (`CellLattice::prefetch`):
    /// a pass over rays calls it a few rays ahead, so that reading a cell's
    /// rows does not wait on memory first (a step's pseudo-rays lie anywhere
    /// in the lattice, and a cell's link reads and then its SH rows' reads
    /// would each wait in turn).
    #[inline]
    pub fn prefetch_ray(&self, r: usize) {
        for &key in self.ray_cells(r) {
            self.lattice.prefetch(key as usize);
        }
    }

    /// The grid rows of every cell, 8 per cell, in cell order.
    pub fn cell_rows(&self) -> Vec<i32> {
        self.cell_keys.iter().flat_map(|&k| self.lattice.cell(k as usize).0).collect()
    }

    /// The samples of ray `r`, front to back, with their cells' rows and
    /// their colour weights.
    pub fn ray_samples(&self, r: usize) -> impl Iterator<Item = ListedSample> + '_ {
        let (lo, hi) = (self.ray_offsets[r] as usize, self.ray_offsets[r + 1] as usize);
        // Each cell is read when its first sample is (a ray's first sample
        // always starts one; a ray without samples has no cell).
        let mut cell = self.ray_cells[r] as usize;
        let mut corners = ([-1; 8], 0u8);
        (lo..hi).map(move |s| {
            if self.starts_cell[s] {
                if s > lo {
                    cell += 1;
                }
                corners = self.lattice.cell(self.cell_keys[cell] as usize);
            }
            let w = weights_of_fractions(self.fractions[s]);
            ListedSample {
                index: s,
                rows: corners.0,
                colour_weights: colour_weights(&w, corners.1, self.colour_corners),
            }
        })
    }

    /// Every sample's 8 rows and 8 colour weights written out (the layout
    /// of the Burn graph's gathers).
    pub fn expanded(&self) -> (Vec<i32>, Vec<f32>) {
        let mut rows = Vec::with_capacity(self.num_samples() * 8);
        let mut weights = Vec::with_capacity(self.num_samples() * 8);
        for r in 0..self.num_rays {
            for s in self.ray_samples(r) {
                rows.extend_from_slice(&s.rows);
                weights.extend_from_slice(&s.colour_weights);
            }
        }
        (rows, weights)
    }

    /// The samples of the given rays (in that order; repeats allowed).
    pub fn subset(&self, rays: &[usize]) -> FrozenSamples {
        let mut out = Self::empty(self.lattice.clone(), self.colour_corners);
        out.ray_offsets.reserve(rays.len());
        out.ray_cells.reserve(rays.len());
        for &r in rays {
            out.push_ray_of(self, r);
        }
        out
    }

    /// Appends ray `r` of `from` (lists of the same march settings and lattice).
    pub fn push_ray_of(&mut self, from: &FrozenSamples, r: usize) {
        debug_assert_eq!(self.colour_corners, from.colour_corners);
        self.adopt_lattice(from);
        let (lo, hi) = (from.ray_offsets[r] as usize, from.ray_offsets[r + 1] as usize);
        self.cell_keys.extend_from_slice(from.ray_cells(r));
        self.starts_cell.extend_from_slice(&from.starts_cell[lo..hi]);
        self.fractions.extend_from_slice(&from.fractions[lo..hi]);
        self.weight.extend_from_slice(&from.weight[lo..hi]);
        self.final_transmittance.push(from.final_transmittance[r]);
        self.far.extend(from.far.get(r));
        self.ray_offsets.push(self.weight.len() as u32);
        self.ray_cells.push(self.cell_keys.len() as u32);
        self.num_rays += 1;
    }

    /// Lists without cells take the lattice of `from` (whose cells they are
    /// about to copy); lists with cells must already read through it.
    fn adopt_lattice(&mut self, from: &FrozenSamples) {
        if self.cell_keys.is_empty() {
            self.lattice = from.lattice.clone();
        } else {
            debug_assert!(from.cell_keys.is_empty() || self.lattice == from.lattice, "lists of two lattices");
        }
    }

    /// `(first ray, rays)` pieces of at most `chunk` rays, each with no more
    /// samples than one render of them may hold on `sh`'s device
    /// (`composite::max_samples_per_call`; unbounded on the CPU backends).
    pub fn chunks(&self, chunk: usize, sh: &Tensor<2>) -> Vec<(usize, usize)> {
        let most = max_samples_per_call(&sh.device(), sh.dims()[1]);
        budget_ranges(self.ray_offsets.windows(2).map(|w| (w[1] - w[0]) as usize), chunk, most)
    }

    /// The far colours read again from `grid`'s far map (after it changed),
    /// `rays` being the rays the lists were marched for.
    pub fn refresh_far(&mut self, grid: &RadianceGrid, rays: &[Ray]) {
        assert_eq!(rays.len(), self.num_rays, "the lists' own rays");
        self.far = match &grid.far {
            Some(far) => rays.iter().map(|r| far.colour(r.view_dir)).collect(),
            None => Vec::new(),
        };
    }

    /// Rays `start..start + len` (for chunked rendering).
    pub fn range(&self, start: usize, len: usize) -> FrozenSamples {
        let ids: Vec<usize> = (start..start + len).collect();
        self.subset(&ids)
    }

    /// Concatenates sample sets (rays of `b` follow those of `self`).
    pub fn append(&mut self, b: &FrozenSamples) {
        if self.ray_offsets.is_empty() {
            self.ray_offsets.push(0);
            self.ray_cells.push(0);
        }
        self.adopt_lattice(b);
        let (samples, cells) = (self.num_samples() as u32, self.num_cells() as u32);
        self.ray_offsets.extend(b.ray_offsets[1..].iter().map(|o| o + samples));
        self.ray_cells.extend(b.ray_cells[1..].iter().map(|o| o + cells));
        self.cell_keys.extend_from_slice(&b.cell_keys);
        self.starts_cell.extend_from_slice(&b.starts_cell);
        self.fractions.extend_from_slice(&b.fractions);
        self.weight.extend_from_slice(&b.weight);
        self.final_transmittance.extend_from_slice(&b.final_transmittance);
        self.far.extend_from_slice(&b.far);
        self.num_rays += b.num_rays;
    }

    /// The buffers on a device (rows and colour weights written out per
    /// sample), for a render: differentiable, but on a GPU with Burn's
    /// serial `select` backward (no transpose is built).
    pub fn upload(&self, device: &Device) -> FrozenTensors {
        let (rows, weights) = self.expanded();
        self.upload_expanded(rows, weights, None, device)
    }

    /// `upload` with the rows and colour weights of `expanded` given (the
    /// rows possibly renumbered). With `table_rows` (the rows of the SH
    /// table the corners index), on a GPU the corner gather carries its
    /// transpose, for a parallel backward (`gather_op`).
    pub fn upload_expanded(
        &self,
        rows: Vec<i32>,
        weights: Vec<f32>,
        table_rows: Option<usize>,
        device: &Device,
    ) -> FrozenTensors {
        let s = self.num_samples();
        let mut ray_of_sample = Vec::with_capacity(s);
        for r in 0..self.num_rays {
            for _ in self.ray_offsets[r]..self.ray_offsets[r + 1] {
                ray_of_sample.push(r as i32);
            }
        }
        FrozenTensors {
            num_rays: self.num_rays,
            num_samples: s,
            corners: match table_rows {
                Some(table) => RowIndex::new(rows, table, device),
                None => RowIndex::plain(indices(rows, device)),
            },
            colour_weights: floats(weights, [s * 8, 1], device),
            weight: floats(self.weight.clone(), [s, 1], device),
            ray_of_sample: indices(ray_of_sample, device),
            ray_starts: self.ray_offsets.iter().map(|&o| o as i32).collect(),
            final_transmittance: floats(self.final_transmittance.clone(), [self.num_rays, 1], device),
            far: far_tensor(&self.far, device),
        }
    }
}

/// Sample lists kept on the device, uploaded once: a step picks rays by
/// index and their samples are gathered there. What crosses per pick is
/// three indices per ray (its id, where its samples start in the batch, a
/// boundary mark), not its samples (72 bytes each, written out per sample
/// on the device): lego's 100,000 pseudo-rays a step are about 3.5 M
/// samples. On a GPU the lists also keep the transpose of their corner
/// rows (about 32 bytes a sample more), for a parallel backward.
#[derive(Clone)]
pub struct DeviceSamples {
    /// Host copy of `FrozenSamples::ray_offsets`: sizes each gather.
    ray_offsets: Vec<u32>,
    /// Per ray, the index of its first sample.
    first_sample: Tensor<1, Int>,
    /// `[samples, 8]` grid rows of the corners.
    corner_rows: Tensor<2, Int>,
    /// `[samples, 8]` colour interpolation weights.
    colour_weights: Tensor<2>,
    /// `[samples, 1]` compositing weights.
    weight: Tensor<2>,
    /// `[rays, 1]`.
    final_transmittance: Tensor<2>,
    /// `[rays, 3]`, when the lists carry a far background.
    far: Option<Tensor<2>>,
    /// On a GPU: the lists themselves in chunks of rays, `(first ray, rays,
    /// tensors)`, each within one render call's buffers, their corner
    /// gathers carrying compact transposes (built here, once): a render of
    /// the whole lists whose backward is parallel (`render_picks`, and
    /// `gather_chunks` when every ray is picked in order). Empty on the CPU
    /// backends, whose `select` backward is a loop over host memory.
    whole: Vec<(usize, usize, FrozenTensors)>,
}

impl DeviceSamples {
    pub fn upload(samples: &FrozenSamples, device: &Device) -> Self {
        let (r, s) = (samples.num_rays, samples.num_samples());
        let firsts = samples.ray_offsets[..r].iter().map(|&o| o as i32).collect();
        let (rows, weights) = samples.expanded();
        let mut lists = Self {
            ray_offsets: samples.ray_offsets.clone(),
            first_sample: indices(firsts, device),
            corner_rows: indices(rows.clone(), device).reshape([s, 8]),
            colour_weights: floats(weights, [s, 8], device),
            weight: floats(samples.weight.clone(), [s, 1], device),
            final_transmittance: floats(samples.final_transmittance.clone(), [r, 1], device),
            far: far_tensor(&samples.far, device),
            whole: Vec::new(),
        };
        if !is_host_memory(device) {
            // The colour pass is of degree 0: 3 columns a row.
            let most = max_samples_per_call(device, 3);
            let sizes = samples.ray_offsets.windows(2).map(|w| (w[1] - w[0]) as usize);
            let ranges = budget_ranges(sizes, usize::MAX, most);
            lists.whole = ranges.into_iter().map(|(first, n)| (first, n, lists.part(first, n, &rows))).collect();
        }
        lists
    }

    /// Rays `first..first + n` as they lie in the lists (no gather), their
    /// corner gather with a compact transpose of `rows` (the lists' corner
    /// rows on the host).
    fn part(&self, first: usize, n: usize, rows: &[i32]) -> FrozenTensors {
        let device = self.weight.device();
        let (lo, hi) = (self.ray_offsets[first] as usize, self.ray_offsets[first + n] as usize);
        let total = hi - lo;
        let ray_starts: Vec<i32> = self.ray_offsets[first..=first + n].iter().map(|&o| o as i32 - lo as i32).collect();
        let final_transmittance = self.final_transmittance.clone().narrow(0, first, n);
        let far = self.far.as_ref().map(|far| far.clone().narrow(0, first, n));
        let Some(ray_of_sample) = runs_of(&ray_starts, total, &device).filter(|_| total > 0) else {
            return FrozenTensors::background_only(n, final_transmittance, far, &device);
        };
        let idx = self.corner_rows.clone().narrow(0, lo, total).reshape([total * 8]);
        FrozenTensors {
            num_rays: n,
            num_samples: total,
            corners: RowIndex::compact(idx, &rows[lo * 8..hi * 8]),
            colour_weights: self.colour_weights.clone().narrow(0, lo, total).reshape([total * 8, 1]),
            weight: self.weight.clone().narrow(0, lo, total),
            ray_of_sample,
            ray_starts,
            final_transmittance,
            far,
        }
    }

    /// The number of rays in the lists.
    pub fn num_rays(&self) -> usize {
        self.ray_offsets.len() - 1
    }

    /// Whether a step picking `rays` had better render the whole lists
    /// ([`render_picks`](Self::render_picks)) than gather the picks'
    /// samples: on a GPU, when the picks hold at least a sixteenth of the
    /// lists' samples. Why: a gather's backward is burn-cubecl's serial
    /// `select_assign` (one thread per column, looping over every gathered
    /// corner), the whole lists' is parallel over the rows they read, its
    /// cost the lists' size; only picks much smaller than the lists make
    /// the serial loop the cheaper one.
    pub fn renders_whole(&self, rays: &[usize]) -> bool {
        let picked: usize = rays.iter().map(|&r| (self.ray_offsets[r + 1] - self.ray_offsets[r]) as usize).sum();
        let all = *self.ray_offsets.last().unwrap_or(&0) as usize;
        !self.whole.is_empty() && picked.saturating_mul(16) >= all
    }

    /// The colours `[rays.len(), 3]` of `rays` (repeats allowed) from `sh`:
    /// every ray of the lists rendered, then the picks gathered (with a
    /// transpose, built on the host from `rays`). Differentiable in `sh`,
    /// both backwards parallel. Only where `renders_whole` holds.
    pub fn render_picks(&self, sh: Tensor<2>, rays: &[usize], background: [f32; 3]) -> Tensor<2> {
        assert!(!self.whole.is_empty(), "render_picks needs the whole lists on a GPU (renders_whole)");
        let parts: Vec<Tensor<2>> =
            self.whole.iter().map(|(_, _, ft)| render_colour(sh.clone(), ft, background)).collect();
        let all = Tensor::cat(parts, 0);
        let device = all.device();
        gather_rows(all, &RowIndex::new(rays.iter().map(|&r| r as i32).collect(), self.num_rays(), &device))
    }

    /// [`gather`](Self::gather) of `rays` in chunks of `chunk` rays, each
    /// with no more samples than a render from `sh` may hold on its device
    /// ([`FrozenSamples::chunks`]): `(first ray, rays, samples)` per chunk,
    /// gathered as it is reached.
    /// When every ray is picked in order and the lists are kept whole (a
    /// GPU), the chunks are those lists' own, no gather needed.
    pub fn gather_chunks<'a>(
        &'a self,
        rays: &'a [usize],
        chunk: usize,
        sh: &Tensor<2>,
    ) -> Box<dyn Iterator<Item = (usize, usize, FrozenTensors)> + 'a> {
        let in_order = rays.len() == self.num_rays() && rays.iter().enumerate().all(|(i, &r)| i == r);
        if in_order && !self.whole.is_empty() {
            return Box::new(self.whole.iter().cloned());
        }
        let most = max_samples_per_call(&sh.device(), sh.dims()[1]);
        let sizes = rays.iter().map(|&r| (self.ray_offsets[r + 1] - self.ray_offsets[r]) as usize);
        Box::new(budget_ranges(sizes, chunk, most).into_iter().map(move |(s, n)| (s, n, self.gather(&rays[s..s + n]))))
    }

    /// The samples of `rays` (in that order; repeats allowed): the same
    /// tensors as `samples.subset(rays).upload(device)`, gathered on the
    /// device. Sample `j` of the batch belongs to the last pick whose start
    /// is at or before `j` (picks without samples share the next start):
    /// `gather_op::runs_of` on a GPU, a cumulative sum of marks elsewhere.
    pub fn gather(&self, rays: &[usize]) -> FrozenTensors {
        let device = self.weight.device();
        let mut starts = Vec::with_capacity(rays.len());
        let mut total = 0usize;
        for &r in rays {
            starts.push(total as i32);
            total += (self.ray_offsets[r + 1] - self.ray_offsets[r]) as usize;
        }
        let ray_ids = indices(rays.iter().map(|&r| r as i32).collect(), &device);
        let final_transmittance = select_rows(self.final_transmittance.clone(), ray_ids.clone());
        let far = self.far.as_ref().map(|far| select_rows(far.clone(), ray_ids.clone()));
        if total == 0 {
            return FrozenTensors::background_only(rays.len(), final_transmittance, far, &device);
        }
        let ray_starts: Vec<i32> = starts.iter().copied().chain([total as i32]).collect();
        let ray_of_sample = match runs_of(&ray_starts, total, &device) {
            Some(runs) => runs,
            None => ray_of_sample_by_marks(&starts, total, &device),
        };
        let first = select_rows(select_rows(self.first_sample.clone(), ray_ids), ray_of_sample.clone());
        let start = select_rows(indices(starts, &device), ray_of_sample.clone());
        let sample_ids = first + Tensor::arange(0..total as i64, &device) - start;
        FrozenTensors {
            num_rays: rays.len(),
            num_samples: total,
            corners: RowIndex::plain(select_rows(self.corner_rows.clone(), sample_ids.clone()).reshape([total * 8])),
            colour_weights: select_rows(self.colour_weights.clone(), sample_ids.clone()).reshape([total * 8, 1]),
            weight: select_rows(self.weight.clone(), sample_ids),
            ray_of_sample,
            ray_starts,
            final_transmittance,
            far,
        }
    }
}

/// Each of `total` samples' pick, from the picks' `starts` (the CPU
/// backends' way; a GPU has `gather_op::runs_of`): a cumulative sum of
/// marks at the picks' starts, summed in f32, exact below 2^24 samples a
/// batch (a chunk holds far fewer).
fn ray_of_sample_by_marks(starts: &[i32], total: usize, device: &Device) -> Tensor<1, Int> {
    let marks: Vec<i32> = starts.iter().skip(1).copied().filter(|&s| (s as usize) < total).collect();
    if marks.is_empty() {
        return Tensor::zeros([total], device);
    }
    let ones: Tensor<2> = Tensor::ones([marks.len(), 1], device);
    let marked = assign_rows(Tensor::zeros([total, 1], device), indices(marks, device), ones, IndexingUpdateOp::Add);
    cumsum_rows(marked).reshape([total]).int()
}

/// Far colours `[rays, 3]` on `device`, or `None` for none.
fn far_tensor(far: &[[f32; 3]], device: &Device) -> Option<Tensor<2>> {
    (!far.is_empty()).then(|| floats(far.concat(), [far.len(), 3], device))
}

/// `FrozenSamples` uploaded to a device.
#[derive(Clone)]
pub struct FrozenTensors {
    pub num_rays: usize,
    pub num_samples: usize,
    /// The grid rows of each sample's 8 corners, `[samples * 8]`.
    pub corners: RowIndex,
    pub colour_weights: Tensor<2>,
    pub weight: Tensor<2>,
    pub ray_of_sample: Tensor<1, Int>,
    /// Where each ray's samples start, and the number of samples last
    /// (`rays + 1` host values): the rays' sums by runs (`sum_runs`).
    pub ray_starts: Vec<i32>,
    pub final_transmittance: Tensor<2>,
    /// `[rays, 3]` far background colours, else the constant background.
    pub far: Option<Tensor<2>>,
}

impl FrozenTensors {
    /// `rays` rays without samples: only their background shows.
    fn background_only(rays: usize, final_transmittance: Tensor<2>, far: Option<Tensor<2>>, device: &Device) -> Self {
        Self {
            num_rays: rays,
            num_samples: 0,
            corners: RowIndex::plain(Tensor::zeros([0], device)),
            colour_weights: Tensor::zeros([0, 1], device),
            weight: Tensor::zeros([0, 1], device),
            ray_of_sample: Tensor::zeros([0], device),
            ray_starts: vec![0; rays + 1],
            final_transmittance,
            far,
        }
    }
}

/// Colours `[rays, 3]` of the rays from degree-0 SH rows `sh` (`[rows, 3]`):
/// differentiable in `sh` when it is on an autodiff device. On a GPU the
/// fused kernel (`frozen_op`) wherever its backward can run: the corners
/// carry their transpose, or nothing is differentiated; else the graph.
pub fn render_colour(sh: Tensor<2>, ft: &FrozenTensors, background: [f32; 3]) -> Tensor<2> {
    #[cfg(feature = "wgpu")]
    if ft.num_samples > 0
        && !is_host_memory(&sh.device())
        && (ft.corners.transpose_parts().is_some() || !sh.is_tracked())
    {
        let device = sh.device();
        let starts = indices(ft.ray_starts.clone(), &device);
        let colour =
            frozen_op::colour_fused(sh, &ft.corners, &ft.colour_weights, &ft.weight, &ft.ray_of_sample, starts);
        return colour + background_part(ft, background, &device);
    }
    render_colour_graph(sh, ft, background)
}

/// [`render_colour`] as the Burn graph: the CPU backends' path, and the
/// oracle of the GPU's fused kernel.
pub fn render_colour_graph(sh: Tensor<2>, ft: &FrozenTensors, background: [f32; 3]) -> Tensor<2> {
    let behind = background_part(ft, background, &sh.device());
    if ft.num_samples == 0 {
        return behind;
    }
    let coeff = interpolate_corners(sh, &ft.corners, ft.colour_weights.clone());
    let colour = relu(coeff * sh::C0 + 0.5);
    let contribution = colour * ft.weight.clone();
    sum_runs(contribution, &ft.ray_of_sample, &ft.ray_starts) + behind
}

/// Each ray's background (its far colour, else `background`) times its
/// final transmittance, `[rays, 3]`.
fn background_part(ft: &FrozenTensors, background: [f32; 3], device: &Device) -> Tensor<2> {
    let bg = match &ft.far {
        Some(far) => far.clone(),
        None => floats(background.to_vec(), [1, 3], device),
    };
    ft.final_transmittance.clone() * bg
}

/// Renders all rays of `samples` in chunks of `chunk` rays without autodiff:
/// `[rays, 3]` RGB on `sh`'s device (not clamped: the image losses see what
/// the gradient will be injected into).
pub fn render_rays(sh: &Tensor<2>, samples: &FrozenSamples, background: [f32; 3], chunk: usize) -> Tensor<2> {
    let device = sh.device();
    let chunks: Vec<Tensor<2>> = samples
        .chunks(chunk, sh)
        .into_iter()
        .map(|(start, len)| render_colour(sh.clone(), &samples.range(start, len).upload(&device), background))
        .collect();
    if chunks.is_empty() {
        return Tensor::zeros([0, 3], &device);
    }
    Tensor::cat(chunks, 0)
}

/// [`render_rays`] read back as interleaved RGB (one read for all chunks).
pub fn render_plain(sh: &Tensor<2>, samples: &FrozenSamples, background: [f32; 3], chunk: usize) -> Vec<f32> {
    if samples.num_rays == 0 {
        return Vec::new();
    }
    to_vec(render_rays(sh, samples, background, chunk))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::camera::{Camera, Intrinsics, look_at};
    use glam::Vec3;

    /// Sample lists written out per sample: what `FrozenSamples` held
    /// before it shared cells and kept fractions.
    #[derive(Default)]
    struct WrittenOut {
        ray_offsets: Vec<u32>,
        corner_rows: Vec<i32>,
        colour_weights: Vec<f32>,
        weight: Vec<f32>,
        final_transmittance: Vec<f32>,
    }

    /// The packed march (`Marcher::samples`) weighted afterwards from the
    /// density mirror: what `march_within` did before it weighted samples
    /// as the march found them.
    fn weighted_from_batch(marcher: &Marcher, rays: &[Ray], params: &MarchParams, min_weight: f32) -> WrittenOut {
        let grid = marcher.grid();
        let batch = marcher.samples(rays, params);
        let mut out = WrittenOut { ray_offsets: vec![0], ..Default::default() };
        for r in 0..rays.len() {
            let mut optical = 0.0f32;
            for s in batch.ray_offsets[r] as usize..batch.ray_offsets[r + 1] as usize {
                let mut sigma = 0.0f32;
                for c in 0..8 {
                    sigma += batch.corner_weights[s * 8 + c] * grid.density_cpu[batch.corner_rows[s * 8 + c] as usize];
                }
                let tau = sigma.max(0.0) * batch.delta[s];
                let w = (-optical).exp() * (1.0 - (-tau).exp());
                optical += tau;
                if w > min_weight || (min_weight == 0.0 && w >= 0.0) {
                    out.corner_rows.extend_from_slice(&batch.corner_rows[s * 8..s * 8 + 8]);
                    out.colour_weights.extend_from_slice(&batch.colour_weights[s * 8..s * 8 + 8]);
                    out.weight.push(w);
                }
            }
            out.final_transmittance.push((-optical).exp());
            out.ray_offsets.push(out.weight.len() as u32);
        }
        out
    }

    /// The fused march keeps exactly the samples, weights and
    /// transmittances of weighting the packed batch, whatever the chunk,
    /// and its compact lists (shared cells, fractions) read back as the very
    /// rows and colour weights the march wrote out.
    #[test]
    fn fused_march_equals_weighting_the_packed_batch() {
        let device = crate::util::backend::BackendKind::Flex.device();
        let grid = crate::field::grid::sphere_grid(40, &device);
        let marcher = Marcher::new(&grid);
        let cam =
            Camera::new(Intrinsics::from_fov_x(37, 29, 0.9), look_at(Vec3::new(2.2, 1.0, 0.8), Vec3::ZERO, Vec3::Z));
        let rays = cam.rays(None);
        let params = MarchParams::default();
        for min_weight in [0.0, 1e-3] {
            let want = weighted_from_batch(&marcher, &rays, &params, min_weight);
            assert!(want.weight.len() > 500, "the camera sees the sphere");
            for chunk in [1, 300, MARCH_CHUNK] {
                let got = FrozenSamples::march_within(&marcher, &rays, &params, min_weight, chunk, usize::MAX)
                    .expect("unbounded");
                assert_eq!(got.num_rays, rays.len());
                assert_eq!(got.ray_offsets, want.ray_offsets, "min weight {min_weight}, chunk {chunk}");
                let (rows, colour_weights) = got.expanded();
                assert_eq!(rows, want.corner_rows);
                assert_eq!(colour_weights, want.colour_weights);
                assert_eq!(got.weight, want.weight);
                assert_eq!(got.final_transmittance, want.final_transmittance);
                // The lists share cells: fewer cells than samples, and the
                // subset of every ray reads back the same.
                assert!(
                    got.num_cells() < got.num_samples(),
                    "{} cells, {} samples",
                    got.num_cells(),
                    got.num_samples()
                );
                let all: Vec<usize> = (0..rays.len()).collect();
                assert_eq!(got.subset(&all).expanded(), (rows, colour_weights));
            }
        }
        // Subsets and appends keep each ray's samples with their cells.
        let lists = FrozenSamples::march(&marcher, &rays, &params, 0.0);
        let picks = [700, 3, 3, 512, 1000];
        let picked = lists.subset(&picks);
        // A ray's lists do not depend on the rays marched with it: the
        // picks' lists equal a march of the picked rays alone (what lets a
        // stylization copy a pixel's lists from its view's).
        let picked_rays: Vec<Ray> = picks.iter().map(|&r| rays[r]).collect();
        let marched = FrozenSamples::march(&marcher, &picked_rays, &params, 0.0);
        assert!(marched == picked, "the picks' lists differ from a march of the picked rays");
        let mut appended = lists.subset(&picks[..2]);
        appended.append(&lists.subset(&picks[2..]));
        for (k, &r) in picks.iter().enumerate() {
            let want: Vec<([i32; 8], [f32; 8])> = lists.ray_samples(r).map(|s| (s.rows, s.colour_weights)).collect();
            for set in [&picked, &appended] {
                let got: Vec<([i32; 8], [f32; 8])> = set.ray_samples(k).map(|s| (s.rows, s.colour_weights)).collect();
                assert_eq!(got, want, "ray {r}");
                assert_eq!(set.ray_cells(k), lists.ray_cells(r));
            }
        }
        let some = FrozenSamples::march(&marcher, &rays, &params, 0.0).bytes();
        assert!(FrozenSamples::march_within(&marcher, &rays, &params, 0.0, 100, some / 2).is_none());
    }
}

/// The fused kernel (`frozen_op`) against the Burn graph ([`render_colour_graph`]),
/// on every backend the test command runs (`cargo test --lib
/// graph_oracle`): the kernel runs on wgpu; on the CPU backends both sides
/// are the graph.
#[cfg(test)]
#[allow(clippy::print_stdout)] // the measured errors, shown with --nocapture
mod graph_oracle {
    use super::{DeviceSamples, FrozenSamples, FrozenTensors, render_colour, render_colour_graph};
    use crate::field::grid::blob_grid;
    use crate::field::march::{MarchParams, Marcher};
    use crate::scene::sh::C0;
    use crate::test_support::{device, test_camera};
    use crate::util::device_stats::kernel_launches;
    use crate::util::tensor::{floats, is_host_memory, to_vec};
    use burn::tensor::Tensor;

    /// Colours and the SH gradient of a weighted sum of them, to 1e-5 of
    /// each one's largest value, for the three ways the stylization lays
    /// out its samples: uploaded with a full transpose (a chunk's rows
    /// renumbered), the device lists' chunks (compact transposes), and a
    /// render-only upload (no transpose: the fused forward, no backward).
    /// The SH values run from -3 to 3, so some colours clip at zero and
    /// their ReLUs pass no gradient; the rays have far colours of their own.
    /// Both sides sum the corners in one order and the samples front to
    /// back, but a GPU may fuse multiply-adds. A wrong term (the ReLU mask
    /// left out, a weight applied twice) is off by whole percents.
    #[test]
    fn the_fused_colour_pass_matches_the_graph() {
        let dev = device();
        let grid = blob_grid(6, &dev);
        let rays = test_camera(40).rays(None);
        let mut samples = FrozenSamples::march(&Marcher::new(&grid), &rays, &MarchParams::default(), 0.0);
        samples.far = (0..samples.num_rays).map(|i| [0.1 * (i % 7) as f32, 0.5, 1.0 - 0.0005 * i as f32]).collect();
        assert!(samples.num_samples() > 2000, "{} samples", samples.num_samples());
        let rows = grid.num_rows();
        let sh: Vec<f32> = (0..rows * 3).map(|i| ((i * 37) % 23) as f32 / 23.0 * 6.0 - 3.0).collect();
        let clipped = (0..samples.num_rays)
            .flat_map(|r| samples.ray_samples(r).collect::<Vec<_>>())
            .filter(|s| (0..8).map(|c| s.colour_weights[c] * sh[s.rows[c] as usize * 3]).sum::<f32>() * C0 + 0.5 < 0.0)
            .count();
        assert!(clipped > 100, "{clipped} samples' red clips at zero");
        let weights: Vec<f32> = (0..samples.num_rays * 3).map(|i| ((i * 13) % 11) as f32 / 11.0 - 0.4).collect();
        let bg = [0.2, 0.9, 0.4];
        let run = |ft: &FrozenTensors, graph: bool| {
            let leaf = floats(sh.clone(), [rows, 3], &dev).autodiff().require_grad();
            let rgb = match graph {
                true => render_colour_graph(leaf.clone(), ft, bg),
                false => render_colour(leaf.clone(), ft, bg),
            };
            let loss = (rgb.clone() * floats(weights.clone(), [ft.num_rays, 3], &dev)).sum();
            let grad = leaf.grad(&loss.backward()).expect("a gradient");
            (to_vec(rgb), to_vec(grad))
        };
        let (expanded_rows, colour_weights) = samples.expanded();
        let full = samples.upload_expanded(expanded_rows, colour_weights, Some(rows), &dev);
        let all: Vec<usize> = (0..samples.num_rays).collect();
        let lists = DeviceSamples::upload(&samples, &dev);
        let sh_t = floats(sh.clone(), [rows, 3], &dev);
        let chunks: Vec<FrozenTensors> = lists.gather_chunks(&all, 16384, &sh_t).map(|(_, _, ft)| ft).collect();
        assert_eq!(chunks.len(), 1, "the lists fit one chunk");
        let on_gpu = !is_host_memory(&dev);
        for (name, ft) in [("full transpose", &full), ("compact transpose", &chunks[0])] {
            assert_eq!(ft.corners.transpose_parts().is_some(), on_gpu, "{name}: the GPU's lists carry a transpose");
            let before = kernel_launches();
            let ours = run(ft, false);
            let fused_launches = kernel_launches() - before;
            let before = kernel_launches();
            let theirs = run(ft, true);
            let graph_launches = kernel_launches() - before;
            for (what, a, b) in [("colours", &ours.0, &theirs.0), ("SH gradient", &ours.1, &theirs.1)] {
                let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs()));
                let err = a.iter().zip(b).fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
                println!("{name}, {what}: max |fused - graph| = {err:.2e} of {scale:.2e}");
                assert!(scale > 0.0 && b.iter().filter(|v| **v != 0.0).count() > 10, "{name}, {what}: all zero");
                assert!(err <= 1e-5 * scale, "{name}, {what}: {err:.2e} of {scale:.2e}");
            }
            println!("{name}: {fused_launches} kernel launches fused, {graph_launches} by the graph");
            match on_gpu {
                true => assert!(fused_launches < graph_launches, "{fused_launches} vs {graph_launches}"),
                false => assert_eq!((fused_launches, graph_launches), (0, 0), "the CPU backends launch no kernels"),
            }
        }
        // A render-only upload (no transpose) renders the same colours.
        let plain = samples.upload(&dev);
        let forward: Tensor<2> = render_colour(floats(sh.clone(), [rows, 3], &dev), &plain, bg);
        let graph = render_colour_graph(floats(sh, [rows, 3], &dev), &plain, bg);
        let err = to_vec(forward).iter().zip(to_vec(graph)).fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
        assert!(err <= 1e-5, "render-only forward: {err:.2e}");
    }
}
