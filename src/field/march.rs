//! Ray marching, the plain-Rust half of volume rendering (paper eqs. 1-2, 4):
//! which samples exist (ray/box intersection, empty-space skipping through
//! the voxel links and the density mirror, early termination), packed into a
//! `SampleBatch`, and the equation-4 depth. The differentiable half -
//! trilinear gathers, colours, transmittance, weights, per-ray sums - is the
//! Burn graph in `composite` (and `frozen` for the stylization).

use crate::field::grid::{CellLattice, RadianceGrid, weights_of_fractions};
use crate::scene::camera::Ray;
use crate::scene::sh;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// How a sample's colour treats the empty (inactive) corners of its voxel.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ColourCorners {
    /// The trilinear weights renormalised over the active corners: empty
    /// space has no colour, so it must not pull surfaces towards grey.
    #[default]
    Renormalised,
    /// Empty corners count as zero coefficients (svox2): at a silhouette
    /// the colour is pulled towards SH 0 (grey 0.5).
    Zero,
}

/// How rays are marched.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MarchParams {
    /// Step between samples in voxels, measured in lattice coordinates along the ray (0.5 as in Plenoxels).
    pub step: f32,
    /// Samples whose interpolated density is at or below this are skipped.
    pub sigma_threshold: f32,
    /// A ray stops once its transmittance falls below this.
    pub stop_threshold: f32,
    /// Equation 4: depth is where the accumulated optical depth
    /// sum(sigma * delta) reaches this (ln 2: transmittance 0.5), located
    /// inside the sample's segment assuming constant density there.
    pub depth_threshold: f32,
    /// Colour interpolation at voxels with empty corners.
    pub colour_corners: ColourCorners,
}

impl Default for MarchParams {
    fn default() -> Self {
        Self {
            step: 0.5,
            sigma_threshold: 1e-8,
            stop_threshold: 1e-4,
            depth_threshold: std::f32::consts::LN_2,
            colour_corners: ColourCorners::Renormalised,
        }
    }
}

/// Packed samples of a set of rays (plain Rust). Samples of ray r are
/// `ray_offsets[r]..ray_offsets[r+1]`.
#[derive(Debug, Default, Clone)]
pub struct SampleBatch {
    pub num_rays: usize,
    pub ray_offsets: Vec<u32>,
    /// 8 grid rows per sample (an inactive corner points at an active row with weight 0).
    pub corner_rows: Vec<i32>,
    /// 8 trilinear weights per sample (density: empty corners count as zero density).
    pub corner_weights: Vec<f32>,
    /// The weights colour is interpolated with: by default renormalised over
    /// the active corners (see `ColourCorners`).
    pub colour_weights: Vec<f32>,
    /// Distance along the ray of each sample.
    pub t: Vec<f32>,
    /// Interval length of each sample.
    pub delta: Vec<f32>,
    /// SH basis of the sample's view direction, `num_basis` per sample.
    pub basis: Vec<f32>,
    /// Equation-4 depth per ray (None = miss), from the density mirror.
    pub threshold_depth: Vec<Option<f32>>,
    /// The far background's colour per ray (`RadianceGrid::far`); empty
    /// when the grid has none and the constant background applies.
    pub far: Vec<[f32; 3]>,
}

impl SampleBatch {
    /// No rays, the allocations kept.
    fn clear(&mut self) {
        self.num_rays = 0;
        self.ray_offsets.clear();
        self.ray_offsets.push(0);
        self.corner_rows.clear();
        self.corner_weights.clear();
        self.colour_weights.clear();
        self.t.clear();
        self.delta.clear();
        self.basis.clear();
        self.threshold_depth.clear();
        self.far.clear();
    }

    /// The background behind ray `r`: the far map's colour there, else `constant`.
    #[inline]
    pub fn background_of(&self, r: usize, constant: [f32; 3]) -> [f32; 3] {
        self.far.get(r).copied().unwrap_or(constant)
    }

    pub fn num_samples(&self) -> usize {
        self.t.len()
    }

    pub fn max_samples_per_ray(&self) -> usize {
        self.ray_offsets.windows(2).map(|w| (w[1] - w[0]) as usize).max().unwrap_or(0)
    }

    /// The rays cut, in order, into consecutive runs of at most
    /// `max_samples` samples each (a ray with more samples alone in its
    /// run): `(first ray, rays)` per run; one empty run for no rays. Sized so that every tensor a
    /// run uploads or gathers fits in a device's largest buffer.
    pub fn ray_runs(&self, max_samples: usize) -> Vec<(usize, usize)> {
        let sizes = self.ray_offsets.windows(2).map(|w| (w[1] - w[0]) as usize);
        let mut runs = crate::util::budget_ranges(sizes, usize::MAX, max_samples);
        if runs.is_empty() {
            runs.push((0, 0));
        }
        runs
    }

    /// The rays `first..first + count` as a batch of their own (a copy).
    pub fn sub_batch(&self, first: usize, count: usize) -> SampleBatch {
        let (lo, hi) = (self.ray_offsets[first] as usize, self.ray_offsets[first + count] as usize);
        let nb = self.basis.len().checked_div(self.num_samples()).unwrap_or(0);
        SampleBatch {
            num_rays: count,
            ray_offsets: self.ray_offsets[first..=first + count].iter().map(|o| o - lo as u32).collect(),
            corner_rows: self.corner_rows[lo * 8..hi * 8].to_vec(),
            corner_weights: self.corner_weights[lo * 8..hi * 8].to_vec(),
            colour_weights: self.colour_weights[lo * 8..hi * 8].to_vec(),
            t: self.t[lo..hi].to_vec(),
            delta: self.delta[lo..hi].to_vec(),
            basis: self.basis[lo * nb..hi * nb].to_vec(),
            threshold_depth: self.threshold_depth[first..first + count].to_vec(),
            far: self.far.get(first..first + count).map(<[_]>::to_vec).unwrap_or_default(),
        }
    }
}

/// One sample of a march: a position whose voxel has an active corner and
/// whose interpolated density is above `sigma_threshold`.
#[derive(Debug, Clone, Copy)]
pub struct MarchSample {
    /// 8 grid rows (an inactive corner points at an active row with weight 0).
    pub rows: [i32; 8],
    /// Trilinear density weights (inactive corners: 0).
    pub weights: [f32; 8],
    /// Colour interpolation weights (see `ColourCorners`; inactive corners:
    /// 0), `colour_weights(weights_of_fractions(fractions), active, ..)`.
    pub colour_weights: [f32; 8],
    /// Where the sample lies inside its cell (`GridGeometry::trilinear_fractions`).
    pub fractions: [f32; 3],
    /// Which corners are active: bit `c` for corner `c`.
    pub active: u8,
    /// The flat lattice index of the cell's base (`CellLattice::cell` gives
    /// back `rows` and `active` from it).
    pub key: usize,
    /// Distance along the ray and the interval length.
    pub t: f32,
    pub delta: f32,
    /// The interpolated density (empty corners count as zero).
    pub sigma: f32,
}

/// The weights a sample's colour is interpolated with, from its trilinear
/// weights `w` and which corners are `active` (bit `c`): inactive corners
/// get 0; the active ones are renormalised to sum to 1 or kept as they are
/// (`ColourCorners`). One definition for the march and for sample lists
/// that keep only the fractions and the bits (`FrozenSamples`). Written
/// with selects, not branches: which corners are active changes from cell
/// to cell without a pattern a branch predictor could learn.
#[inline]
pub fn colour_weights(w: &[f32; 8], active: u8, corners: ColourCorners) -> [f32; 8] {
    let masked: [f32; 8] = std::array::from_fn(|c| if active & (1 << c) != 0 { w[c] } else { 0.0 });
    let sum = match corners {
        // Adding an inactive corner's +0.0 leaves the sum's bits as they are.
        ColourCorners::Renormalised => masked.iter().fold(0.0f32, |sum, &wc| sum + wc),
        ColourCorners::Zero => 1.0,
    };
    std::array::from_fn(|c| if active & (1 << c) != 0 { masked[c] / sum } else { 0.0 })
}

/// The lattice rows and densities of the cell a ray sampled last:
/// consecutive samples, half a voxel apart, mostly fall in one cell, and
/// its 8 lattice and density reads (random reads) and what follows from
/// them (which corners are active, the rows an empty corner points at)
/// are then done once for the cell, not per sample.
struct LastCell {
    /// The flat lattice index of the cell's base (compared as one number:
    /// comparing the three indices as an array went through memory).
    key: usize,
    /// The corners' rows, an empty corner pointing at the first active row
    /// (as a sample's rows do; all -1 when none is active).
    rows: [i32; 8],
    /// The density of each corner, 0 for an empty one.
    density: [f32; 8],
    /// Which corners are active: bit `c` for corner `c`.
    active: u8,
    /// Whether a corner has positive density. When none has, every sample
    /// in the cell has density <= 0 (non-negative trilinear weights times
    /// non-positive densities), below any non-negative `sigma_threshold`.
    alive: bool,
}

impl LastCell {
    fn new() -> Self {
        Self { key: usize::MAX, rows: [-1; 8], density: [0.0; 8], active: 0, alive: false }
    }

    /// Whether a sample in the held cell may have a density above the
    /// threshold: no when the cell has no active corner, nor, with
    /// `skip_dead`, a corner of positive density.
    #[inline(always)]
    fn may_emit(&self, skip_dead: bool) -> bool {
        self.active != 0 && (self.alive || !skip_dead)
    }

    /// Reads the cell at `base` unless it is the one held. Selects, not
    /// branches, on whether a corner is empty (about a third of fern's
    /// lattice points are, in no pattern).
    #[inline(always)]
    fn load(&mut self, grid: &RadianceGrid, links: &[i32], corner_offsets: &[usize; 8], base: [usize; 3]) {
        let key = grid.geometry.flat(base[0], base[1], base[2]);
        if self.key == key {
            return;
        }
        self.key = key;
        // `CellLattice::cell`, with each corner's density read in the same
        // pass (kept apart: this is the march's hottest loop).
        let raw: [i32; 8] = std::array::from_fn(|c| links[key + corner_offsets[c]]);
        self.active = raw.iter().enumerate().fold(0u8, |bits, (c, &r)| bits | (u8::from(r >= 0) << c));
        if self.active == 0 {
            self.rows = [-1; 8];
            self.alive = false;
            return;
        }
        let first = raw[self.active.trailing_zeros() as usize];
        for ((&r, density), row) in raw.iter().zip(&mut self.density).zip(&mut self.rows) {
            let value = grid.density_cpu[r.max(first) as usize];
            *density = if r >= 0 { value } else { 0.0 };
            *row = if r >= 0 { r } else { first };
        }
        self.alive = self.density.iter().fold(false, |alive, &d| alive | (d > 0.0));
    }
}

/// A position's lattice point (`world_to_grid_in` with the voxel size the
/// marcher computed once: no two divisions per sample for it) and the base
/// of its cell (`trilinear_base`).
#[inline(always)]
fn lattice_point(grid: &RadianceGrid, voxel: glam::Vec3, pos: glam::Vec3) -> (glam::Vec3, [usize; 3]) {
    let g = grid.geometry.world_to_grid_in(pos, voxel);
    (g, grid.geometry.trilinear_base(g))
}

/// The sample of the held cell at lattice point `g`: where it lies in the
/// cell, its trilinear weights (empty corners: 0) and its interpolated
/// density (empty corners count as zero; adding their +0.0 products in
/// corner order gives the bits of a sum over the active corners only).
#[inline(always)]
fn cell_sample(grid: &RadianceGrid, g: glam::Vec3, base: [usize; 3], cell: &LastCell) -> ([f32; 3], [f32; 8], f32) {
    let fractions = grid.geometry.trilinear_fractions(g, base);
    let w = weights_of_fractions(fractions);
    let sigma = w.iter().zip(&cell.density).fold(0.0f32, |sigma, (&w, &density)| sigma + w * density);
    (fractions, w, sigma)
}

/// Equation 4 at sub-sample precision: the sample at `t` stands for the
/// segment [t - step/2, t + step/2] at constant density `sigma`; the optical
/// depth, `before` at its start, reaches `threshold` inside it here (a
/// whole-sample answer is off by up to one step, which shifts R³'s points by
/// a pixel at grazing angles).
fn threshold_crossing(t: f32, step: f32, before: f32, sigma: f32, threshold: f32) -> f32 {
    t - 0.5 * step + (threshold - before) / sigma
}

/// The per-ray step: `p.step` voxels measured in lattice coordinates along
/// the ray (as svox2 does), so anisotropic voxels (NDC grids are 4x deeper
/// than wide) are not oversampled along their long axis.
fn ray_step(grid: &RadianceGrid, ray: &Ray, p: &MarchParams) -> f32 {
    p.step / (ray.dir / grid.geometry.voxel_size()).length()
}

/// Which 8³ blocks of the lattice are empty: a block is empty when no
/// lattice point of its 9³ closure is active, so every sample whose
/// trilinear base lies in it has 8 empty corners and would be dropped
/// anyway. That depends only on which rows exist, so it stays valid until
/// the grid is pruned or upsampled: a training run builds it once per grid
/// (building costs O(active points), millions on real scenes).
///
/// Built `with_density`, it also knows which blocks are dead: no point of
/// the closure has positive density, so every sample there has density <= 0
/// and is dropped by any non-negative `sigma_threshold`. That holds only
/// while the densities stay as they are: rendering a checkpoint, R³, a
/// stylization (density frozen), not a photoreal fit. Most of fern's
/// lattice is active (its points are pruned by a threshold, not removed),
/// so only 0.3 % of its path render's positions lie in empty blocks but
/// 16 % in dead ones; the march passes over dead cells inside live blocks
/// at the cost of one cell read (`LastCell::alive`).
#[derive(Debug, Clone)]
pub struct BlockOccupancy {
    res: [usize; 3],
    num_rows: usize,
    blocks: [usize; 3],
    occupied: Vec<bool>,
    /// Blocks with a point of positive density (`with_density`).
    alive: Option<Vec<bool>>,
}

/// Block edge in lattice cells. 4 skips twice as many of fern's positions
/// as 8 but rendered fern no faster (dead cells are cheap to pass) and
/// lego 10 % slower (twice the block exits across its empty space).
const BLOCK: usize = 8;

/// A ray in lattice coordinates, `a + t d`, and its samples, the first at
/// `t0 + step / 2`.
struct LatticeRay {
    a: glam::Vec3,
    d: glam::Vec3,
    t0: f32,
    step: f32,
}

impl LatticeRay {
    /// `voxel`: the grid's voxel size, computed once by the marcher.
    fn new(grid: &RadianceGrid, voxel: glam::Vec3, ray: &Ray, t0: f32, step: f32) -> Self {
        Self { a: grid.geometry.world_to_grid_in(ray.origin, voxel), d: ray.dir / voxel, t0, step }
    }

    /// The index of the first sample at or after the ray's exit from block
    /// `b`, sample `k` being inside it (a little before the exit when
    /// rounding is close: the march then looks at that sample again).
    fn block_exit(&self, b: [usize; 3], k: usize) -> usize {
        let mut exit = f32::INFINITY;
        for (ax, &block) in b.iter().enumerate() {
            let bound = if self.d[ax] > 0.0 {
                ((block + 1) * BLOCK) as f32
            } else if self.d[ax] < 0.0 {
                (block * BLOCK) as f32
            } else {
                continue;
            };
            exit = exit.min((bound - self.a[ax]) / self.d[ax]);
        }
        let next = ((exit - self.t0) / self.step - 0.5 - 1e-3).ceil();
        if next.is_finite() && next > k as f32 { next as usize } else { k + 1 }
    }
}

/// Rays marched per rayon task by `Marcher::samples`.
const RAYS_PER_TASK: usize = 256;

/// Appends each piece's `field` to `out`, in piece order.
fn concat_into<T: Copy>(out: &mut Vec<T>, pieces: &[SampleBatch], field: impl Fn(&SampleBatch) -> &Vec<T>) {
    out.reserve(pieces.iter().map(|p| field(p).len()).sum());
    for piece in pieces {
        out.extend_from_slice(field(piece));
    }
}

impl BlockOccupancy {
    /// The empty blocks of `grid`'s rows (valid across density updates).
    pub fn of(grid: &RadianceGrid) -> Self {
        Self::build(grid, false)
    }

    /// The empty and the dead blocks of `grid` as its densities are now.
    pub fn with_density(grid: &RadianceGrid) -> Self {
        Self::build(grid, true)
    }

    fn build(grid: &RadianceGrid, density: bool) -> Self {
        let geo = &grid.geometry;
        let blocks = geo.res.map(|r| r.div_ceil(BLOCK).max(1));
        let mut occupied = vec![false; blocks[0] * blocks[1] * blocks[2]];
        let mut alive = vec![false; if density { occupied.len() } else { 0 }];
        // The blocks whose closed range [b*B, b*B+B] holds lattice index i.
        let owners = |i: usize, n: usize| {
            let b = (i / BLOCK).min(n - 1);
            let below = (i.is_multiple_of(BLOCK) && i > 0).then(|| i / BLOCK - 1);
            [Some(b), below]
        };
        for (row, &flat) in grid.coords.iter().enumerate() {
            let [i, j, k] = geo.unflat(flat as usize);
            let positive = density && grid.density_cpu[row] > 0.0;
            for bi in owners(i, blocks[0]).into_iter().flatten() {
                for bj in owners(j, blocks[1]).into_iter().flatten() {
                    for bk in owners(k, blocks[2]).into_iter().flatten() {
                        let b = (bi * blocks[1] + bj) * blocks[2] + bk;
                        occupied[b] = true;
                        if positive {
                            alive[b] = true;
                        }
                    }
                }
            }
        }
        Self { res: geo.res, num_rows: grid.num_rows(), blocks, occupied, alive: density.then_some(alive) }
    }

    /// The blocks a march with `params` must visit: the live ones when
    /// known and the threshold drops non-positive densities, else the
    /// occupied ones. Also says whether dead cells may be skipped.
    fn to_visit(&self, params: &MarchParams) -> (&[bool], bool) {
        match &self.alive {
            Some(alive) if params.sigma_threshold >= 0.0 => (alive, true),
            _ => (&self.occupied, false),
        }
    }

    /// Whether this was plausibly built for `grid` (same lattice, same number of rows).
    pub fn matches(&self, grid: &RadianceGrid) -> bool {
        self.res == grid.geometry.res && self.num_rows == grid.num_rows()
    }
}

/// Ray marching with empty-space skipping over the blocks of a
/// `BlockOccupancy`: skipping is exact (the same samples at the same
/// positions as a march that visits every position). Build one per grid
/// state and reuse it for many rays.
pub struct Marcher<'a> {
    grid: &'a RadianceGrid,
    occupancy: std::borrow::Cow<'a, BlockOccupancy>,
    /// `GridGeometry::corner_offsets` of the grid.
    corner_offsets: [usize; 8],
    /// `GridGeometry::voxel_size` of the grid.
    voxel: glam::Vec3,
}

impl<'a> Marcher<'a> {
    /// A marcher on `grid` as it is now (borrowed, so its densities cannot
    /// change under the marcher: dead blocks are skipped too).
    pub fn new(grid: &'a RadianceGrid) -> Self {
        Self::on(grid, std::borrow::Cow::Owned(BlockOccupancy::with_density(grid)))
    }

    /// A marcher on an occupancy built earlier for this very grid state.
    pub fn with_occupancy(grid: &'a RadianceGrid, occupancy: &'a BlockOccupancy) -> Self {
        assert!(occupancy.matches(grid), "block occupancy built for another grid state");
        Self::on(grid, std::borrow::Cow::Borrowed(occupancy))
    }

    fn on(grid: &'a RadianceGrid, occupancy: std::borrow::Cow<'a, BlockOccupancy>) -> Self {
        let (corner_offsets, voxel) = (grid.geometry.corner_offsets(), grid.geometry.voxel_size());
        Self { grid, occupancy, corner_offsets, voxel }
    }

    /// The grid this marches through.
    pub fn grid(&self) -> &'a RadianceGrid {
        self.grid
    }

    /// The grid's links and cell corners (what a sample's `key` names).
    pub fn lattice(&self) -> CellLattice {
        CellLattice::of(self.grid)
    }

    /// When sample `k`, whose cell's base is `base`, lies in a block that
    /// `blocks` (`BlockOccupancy::to_visit`) marks false: the index of the
    /// first sample at or after the ray's exit from that block.
    #[inline(always)]
    fn skip_block(&self, blocks: &[bool], base: [usize; 3], ray: &LatticeRay, k: usize) -> Option<usize> {
        let b = base.map(|v| v / BLOCK);
        let occ = &*self.occupancy;
        if blocks[(b[0] * occ.blocks[1] + b[1]) * occ.blocks[2] + b[2]] {
            return None;
        }
        Some(ray.block_exit(b, k))
    }

    /// Equation-4 depth of every ray (None = miss), in parallel, without
    /// tensors (R³).
    pub fn depths(&self, rays: &[Ray], params: &MarchParams) -> Vec<Option<f32>> {
        rays.par_iter().map(|r| self.depth(r, params)).collect()
    }

    /// The same march and sub-sample crossing as `walk`, stopping at the crossing.
    fn depth(&self, ray: &Ray, p: &MarchParams) -> Option<f32> {
        let grid = self.grid;
        let links: &[i32] = &grid.links;
        let geo = &grid.geometry;
        let (t0, t1) = geo.intersect(ray.origin, ray.dir)?;
        let step = ray_step(grid, ray, p);
        let lattice_ray = LatticeRay::new(grid, self.voxel, ray, t0, step);
        let (blocks, skip_dead) = self.occupancy.to_visit(p);
        let mut optical = 0.0f32;
        let mut cell = LastCell::new();
        let mut k = 0usize;
        loop {
            let t = t0 + (k as f32 + 0.5) * step;
            if t >= t1 {
                return None;
            }
            let (g, base) = lattice_point(grid, self.voxel, ray.origin + t * ray.dir);
            if let Some(next) = self.skip_block(blocks, base, &lattice_ray, k) {
                k = next;
                continue;
            }
            k += 1;
            cell.load(grid, links, &self.corner_offsets, base);
            if !cell.may_emit(skip_dead) {
                continue;
            }
            let (_, _, sigma) = cell_sample(grid, g, base, &cell);
            if sigma > p.sigma_threshold {
                let before = optical;
                optical += sigma * step;
                if optical >= p.depth_threshold {
                    return Some(threshold_crossing(t, step, before, sigma, p.depth_threshold));
                }
            }
        }
    }

    /// Marches every ray (in parallel) and packs the samples. Each rayon
    /// task packs its rays into a batch of its own (no vectors per ray);
    /// the pieces are appended in ray order, so the batch does not depend
    /// on the thread count.
    pub fn samples(&self, rays: &[Ray], params: &MarchParams) -> SampleBatch {
        let mut batch = SampleBatch::default();
        self.samples_into(rays, params, &mut batch);
        batch
    }

    /// [`samples`](Self::samples) into `batch`, a buffer kept by a caller
    /// that marches every step (the training step), whose batches of tens
    /// of MB would otherwise be fresh pages, zeroed by the kernel, every
    /// step. The tasks' pieces stay fresh: kept too, they cost about
    /// 0.5 GB more at the peak of a short fern fit (measured; why, not
    /// traced: perhaps the allocator's per-thread arenas) for 5 ms less a
    /// step.
    pub fn samples_into(&self, rays: &[Ray], params: &MarchParams, batch: &mut SampleBatch) {
        let pieces: Vec<SampleBatch> = rays.par_chunks(RAYS_PER_TASK).map(|part| self.pack(part, params)).collect();
        let b = batch;
        b.clear();
        b.num_rays = rays.len();
        for piece in &pieces {
            let base = *b.ray_offsets.last().expect("the leading 0");
            b.ray_offsets.extend(piece.ray_offsets[1..].iter().map(|o| o + base));
            b.threshold_depth.extend_from_slice(&piece.threshold_depth);
            b.far.extend_from_slice(&piece.far);
        }
        // The per-sample arrays (tens of MB on fern) side by side, each
        // piece in order.
        let SampleBatch { corner_rows, corner_weights, colour_weights, t, delta, basis, .. } = b;
        rayon::scope(|scope| {
            scope.spawn(|_| concat_into(corner_rows, &pieces, |p| &p.corner_rows));
            scope.spawn(|_| concat_into(corner_weights, &pieces, |p| &p.corner_weights));
            scope.spawn(|_| concat_into(colour_weights, &pieces, |p| &p.colour_weights));
            scope.spawn(|_| concat_into(basis, &pieces, |p| &p.basis));
            concat_into(t, &pieces, |p| &p.t);
            concat_into(delta, &pieces, |p| &p.delta);
        });
    }

    /// Marches `rays` one after another into one batch.
    fn pack(&self, rays: &[Ray], params: &MarchParams) -> SampleBatch {
        let grid = self.grid;
        let mut basis = vec![0.0f32; grid.num_basis()];
        let mut b = SampleBatch { num_rays: rays.len(), ray_offsets: vec![0], ..Default::default() };
        for ray in rays {
            sh::eval_basis(grid.sh_degree, ray.view_dir, &mut basis);
            let depth = self.walk(ray, params, |s| {
                b.corner_rows.extend_from_slice(&s.rows);
                b.corner_weights.extend_from_slice(&s.weights);
                b.colour_weights.extend_from_slice(&s.colour_weights);
                b.t.push(s.t);
                b.delta.push(s.delta);
                b.basis.extend_from_slice(&basis);
            });
            b.threshold_depth.push(depth);
            if let Some(far) = &grid.far {
                b.far.push(far.colour(ray.view_dir));
            }
            b.ray_offsets.push(b.t.len() as u32);
        }
        b
    }

    /// Marches one ray and hands each of its samples, front to back, to
    /// `visit`; returns the ray's equation-4 depth (None = miss). The one
    /// march loop behind `samples` (packed batches) and the fused passes
    /// that consume samples as they are found (`FrozenSamples::march`,
    /// `host_render::render_rays`), so all see the very same samples.
    pub fn walk(&self, ray: &Ray, p: &MarchParams, mut visit: impl FnMut(&MarchSample)) -> Option<f32> {
        let grid = self.grid;
        let links: &[i32] = &grid.links;
        let geo = &grid.geometry;
        let (t0, t1) = geo.intersect(ray.origin, ray.dir)?;
        let step = ray_step(grid, ray, p);
        let lattice_ray = LatticeRay::new(grid, self.voxel, ray, t0, step);
        let (blocks, skip_dead) = self.occupancy.to_visit(p);
        let log_stop = p.stop_threshold.ln();
        let mut depth = None;
        let mut optical = 0.0f32; // sum of sigma * delta so far
        let mut cell = LastCell::new();
        // Sample k sits at t0 + (k + 0.5) step (computed, not accumulated,
        // so skipping lands on the very same positions).
        let mut k = 0usize;
        loop {
            let t = t0 + (k as f32 + 0.5) * step;
            if t >= t1 {
                break;
            }
            let (g, base) = lattice_point(grid, self.voxel, ray.origin + t * ray.dir);
            if let Some(next) = self.skip_block(blocks, base, &lattice_ray, k) {
                k = next;
                continue;
            }
            k += 1;
            cell.load(grid, links, &self.corner_offsets, base);
            if !cell.may_emit(skip_dead) {
                continue;
            }
            let (fractions, w, sigma) = cell_sample(grid, g, base, &cell);
            if sigma > p.sigma_threshold {
                let active = cell.active;
                let sample = MarchSample {
                    rows: cell.rows,
                    weights: std::array::from_fn(|c| if active & (1 << c) != 0 { w[c] } else { 0.0 }),
                    colour_weights: colour_weights(&w, active, p.colour_corners),
                    fractions,
                    active,
                    key: cell.key,
                    t,
                    delta: step,
                    sigma,
                };
                visit(&sample);
                let before = optical;
                optical += sigma * step;
                if depth.is_none() && optical >= p.depth_threshold {
                    depth = Some(threshold_crossing(t, step, before, sigma, p.depth_threshold));
                }
                if -optical < log_stop {
                    break;
                }
            }
        }
        depth
    }
}

/// Marches every ray (in parallel) and packs the samples (builds the
/// skipping structure; many batches on one grid: `Marcher::samples`).
pub fn generate_samples(grid: &RadianceGrid, rays: &[Ray], params: &MarchParams) -> SampleBatch {
    Marcher::new(grid).samples(rays, params)
}

/// Only the equation-4 depth of every ray (None = miss): plain Rust, no
/// tensors. Many views: build one `Marcher` and reuse it.
pub fn threshold_depths(grid: &RadianceGrid, rays: &[Ray], params: &MarchParams) -> Vec<Option<f32>> {
    Marcher::new(grid).depths(rays, params)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::camera::{Camera, Intrinsics, look_at};
    use glam::Vec3;

    /// Every sample of a march (which reuses the last cell's lattice and
    /// density reads) has the rows, weights and density that reading the
    /// lattice afresh at its position gives, to the bit.
    #[test]
    fn samples_reusing_the_last_cell_equal_fresh_lookups() {
        let device = crate::util::backend::BackendKind::Flex.device();
        let grid = crate::field::grid::sphere_grid(40, &device);
        let marcher = Marcher::new(&grid);
        let cam =
            Camera::new(Intrinsics::from_fov_x(31, 27, 0.9), look_at(Vec3::new(2.2, 1.0, 0.8), Vec3::ZERO, Vec3::Z));
        let (mut checked, mut shared) = (0usize, 0usize);
        for ray in cam.rays(None) {
            let mut last_base = None;
            marcher.walk(&ray, &MarchParams::default(), |s| {
                let g = grid.geometry.world_to_grid(ray.origin + s.t * ray.dir);
                let base = grid.geometry.trilinear_base(g);
                shared += usize::from(last_base == Some(base));
                last_base = Some(base);
                let (idx, w) = grid.geometry.trilinear(g);
                let (mut sigma, mut first) = (0.0f32, -1);
                for c in 0..8 {
                    let r = grid.links[idx[c]];
                    if r >= 0 {
                        first = if first < 0 { r } else { first };
                        sigma += w[c] * grid.density_cpu[r as usize];
                        assert_eq!((s.rows[c], s.weights[c].to_bits()), (r, w[c].to_bits()));
                    }
                }
                for c in (0..8).filter(|&c| grid.links[idx[c]] < 0) {
                    assert_eq!((s.rows[c], s.weights[c]), (first, 0.0));
                }
                assert_eq!(s.sigma.to_bits(), sigma.to_bits());
                checked += 1;
            });
        }
        assert!(checked > 500 && shared > checked / 4, "{checked} samples, {shared} in the previous one's cell");
    }

    /// Rays of a 40x40 view of the origin from `eye`.
    fn view_rays(eye: Vec3) -> Vec<Ray> {
        Camera::new(Intrinsics::from_fov_x(40, 40, 0.9), look_at(eye, Vec3::ZERO, Vec3::Z)).rays(None)
    }

    /// Asserts that `skipping` gives exactly the samples and depths of a
    /// march that visits every position (a marcher on `grid` with every
    /// block marked occupied); returns how many samples.
    fn assert_equals_full_visit(grid: &RadianceGrid, skipping: &Marcher, rays: &[Ray], params: &MarchParams) -> usize {
        let mut everything = BlockOccupancy::of(grid);
        everything.occupied.fill(true);
        let full = Marcher::with_occupancy(grid, &everything);
        let (a, b) = (skipping.samples(rays, params), full.samples(rays, params));
        assert_eq!(a.ray_offsets, b.ray_offsets);
        assert_eq!(a.corner_rows, b.corner_rows);
        assert_eq!(a.corner_weights, b.corner_weights);
        assert_eq!(a.t, b.t);
        assert_eq!(a.threshold_depth, b.threshold_depth);
        assert_eq!(skipping.depths(rays, params), a.threshold_depth);
        a.num_samples()
    }

    /// A batch cut into runs within a sample budget: each run within it
    /// (unless a single ray exceeds it), and the runs' sub-batches are the
    /// batch again, in order, field by field.
    #[test]
    fn runs_of_rays_cut_a_batch_within_a_sample_budget() {
        let device = crate::util::backend::BackendKind::Flex.device();
        let grid = crate::field::grid::sphere_grid(40, &device);
        let batch = Marcher::new(&grid).samples(&view_rays(Vec3::new(2.2, 1.0, 0.8)), &MarchParams::default());
        let budget = batch.num_samples() / 7;
        assert!(budget > batch.max_samples_per_ray(), "{budget}");
        let runs = batch.ray_runs(budget);
        assert!(runs.len() >= 7, "{} runs", runs.len());
        let mut again = SampleBatch { ray_offsets: vec![0], ..Default::default() };
        for &(first, count) in &runs {
            let run = batch.sub_batch(first, count);
            assert!(run.num_samples() <= budget && run.num_rays == count && count > 0);
            assert_eq!(first, again.num_rays, "runs follow each other");
            let base = again.num_samples() as u32;
            again.ray_offsets.extend(run.ray_offsets[1..].iter().map(|o| o + base));
            again.num_rays += run.num_rays;
            again.corner_rows.extend(run.corner_rows);
            again.corner_weights.extend(run.corner_weights);
            again.colour_weights.extend(run.colour_weights);
            again.t.extend(run.t);
            again.delta.extend(run.delta);
            again.basis.extend(run.basis);
            again.threshold_depth.extend(run.threshold_depth);
        }
        assert_eq!(format!("{again:?}"), format!("{batch:?}"));
        assert_eq!(batch.ray_runs(usize::MAX), vec![(0, batch.num_rays)]);
        let hitting = |first: usize, count: usize| {
            (first..first + count).filter(|&r| batch.ray_offsets[r + 1] > batch.ray_offsets[r]).count()
        };
        assert!(
            batch.ray_runs(1).iter().all(|&(f, c)| hitting(f, c) <= 1),
            "a ray over the budget is a run of its own"
        );
        assert_eq!(SampleBatch::default().ray_runs(5), vec![(0, 0)]);
    }

    /// A batch marched into a kept buffer (after a larger batch, whose
    /// values it still holds) is the fresh batch.
    #[test]
    fn a_batch_in_kept_buffers_is_a_fresh_one() {
        let device = crate::util::backend::BackendKind::Flex.device();
        let grid = crate::field::grid::sphere_grid(40, &device);
        let marcher = Marcher::new(&grid);
        let params = MarchParams::default();
        let (first, second) = (view_rays(Vec3::new(2.2, 1.0, 0.8)), view_rays(Vec3::new(-1.5, 2.0, 0.6)));
        let mut kept = SampleBatch::default();
        marcher.samples_into(&first, &params, &mut kept);
        marcher.samples_into(&second[..700], &params, &mut kept);
        let fresh = marcher.samples(&second[..700], &params);
        assert!(fresh.num_samples() > 1000);
        assert_eq!((kept.num_rays, &kept.ray_offsets), (fresh.num_rays, &fresh.ray_offsets));
        assert_eq!((&kept.corner_rows, &kept.corner_weights), (&fresh.corner_rows, &fresh.corner_weights));
        assert_eq!((&kept.colour_weights, &kept.basis), (&fresh.colour_weights, &fresh.basis));
        assert_eq!((&kept.t, &kept.delta, &kept.threshold_depth), (&fresh.t, &fresh.delta, &fresh.threshold_depth));
    }

    /// Skipping empty blocks must give exactly the samples of a march that
    /// visits every position.
    #[test]
    fn empty_space_skipping_is_exact() {
        let device = crate::util::backend::BackendKind::Flex.device();
        let grid = crate::field::grid::sphere_grid(48, &device);
        assert!(BlockOccupancy::of(&grid).occupied.iter().any(|o| !o), "the sphere grid has empty blocks");
        let rays = view_rays(Vec3::new(2.2, 1.0, 0.8));
        let samples = assert_equals_full_visit(&grid, &Marcher::new(&grid), &rays, &MarchParams::default());
        assert!(samples > 1000);
    }

    /// Skipping dead blocks and cells (no positive density) gives exactly
    /// the samples and depths of a march that visits every position, on a
    /// sphere whose -x half has negative density.
    #[test]
    fn dead_space_skipping_is_exact() {
        let device = crate::util::backend::BackendKind::Flex.device();
        let sphere = crate::field::grid::sphere_grid(48, &device);
        let geo = sphere.geometry;
        let density: Vec<f32> = sphere
            .coords
            .iter()
            .zip(&sphere.density_cpu)
            .map(|(&flat, &d)| {
                let [i, _, _] = geo.unflat(flat as usize);
                if i < 20 { -3.0 } else { d }
            })
            .collect();
        let sh = crate::util::tensor::to_vec(sphere.sh.clone());
        let grid = RadianceGrid::from_rows(geo, sphere.sh_degree, sphere.coords.clone(), density, sh, &device);
        let skipping = Marcher::new(&grid);
        let alive = skipping.occupancy.alive.as_ref().expect("Marcher::new knows the densities");
        let dead = skipping.occupancy.occupied.iter().zip(alive).filter(|&(&o, &a)| o && !a).count();
        assert!(dead > 10, "only {dead} occupied blocks are dead");
        let rays = view_rays(Vec3::new(-2.2, 1.0, 0.8));
        let params = MarchParams::default();
        let kept = assert_equals_full_visit(&grid, &skipping, &rays, &params);
        assert!(kept > 1000);
        // A negative threshold keeps samples of density in (threshold, 0]:
        // then nothing dead may be skipped, and there are more samples.
        let keep_negative = MarchParams { sigma_threshold: -5.0, ..params };
        assert!(assert_equals_full_visit(&grid, &skipping, &rays, &keep_negative) > kept);
    }
}
