//! Ray marching, the plain-Rust half of volume rendering (paper eqs. 1-2, 4):
//! which samples exist (ray/box intersection, empty-space skipping through
//! the voxel links and the density mirror, early termination), packed into a
//! `SampleBatch`, and the equation-4 depth. The differentiable half -
//! trilinear gathers, colours, transmittance, weights, per-ray sums - is the
//! Burn graph in `composite` (and `frozen` for the stylization).

use crate::field::grid::{RadianceGrid, weights_of_fractions};
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
}

impl SampleBatch {
    pub fn num_samples(&self) -> usize {
        self.t.len()
    }

    pub fn max_samples_per_ray(&self) -> usize {
        self.ray_offsets.windows(2).map(|w| (w[1] - w[0]) as usize).max().unwrap_or(0)
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
    /// Distance along the ray and the interval length.
    pub t: f32,
    pub delta: f32,
    /// The interpolated density (empty corners count as zero).
    pub sigma: f32,
}

/// The 8 lattice corners around a point: their rows (-1 = empty), where
/// the point lies in the cell, its trilinear weights, the first active
/// row, the interpolated density (empty = 0) and which corners are active.
struct Corners {
    rows: [i32; 8],
    fractions: [f32; 3],
    w: [f32; 8],
    first_active: i32,
    sigma: f32,
    active: u8,
}

/// The weights a sample's colour is interpolated with, from its trilinear
/// weights `w` and which corners are `active` (bit `c`): inactive corners
/// get 0; the active ones are renormalised to sum to 1 or kept as they are
/// (`ColourCorners`). One definition for the march and for sample lists
/// that keep only the fractions and the bits (`FrozenSamples`).
#[inline]
pub fn colour_weights(w: &[f32; 8], active: u8, corners: ColourCorners) -> [f32; 8] {
    let sum = match corners {
        ColourCorners::Renormalised => {
            let mut sum = 0.0f32;
            for (c, &wc) in w.iter().enumerate() {
                if active & (1 << c) != 0 {
                    sum += wc;
                }
            }
            sum
        }
        ColourCorners::Zero => 1.0,
    };
    std::array::from_fn(|c| if active & (1 << c) != 0 { w[c] / sum } else { 0.0 })
}

/// The lattice rows and densities of the cell a ray sampled last:
/// consecutive samples, half a voxel apart, mostly fall in one cell, and
/// its 8 lattice and density reads (random reads, the march's main cost)
/// are then done once for the cell, not per sample.
struct LastCell {
    base: [usize; 3],
    rows: [i32; 8],
    /// The density of each active corner (0 for empty ones, never read).
    density: [f32; 8],
}

impl LastCell {
    fn new() -> Self {
        Self { base: [usize::MAX; 3], rows: [-1; 8], density: [0.0; 8] }
    }
}

fn corners(grid: &RadianceGrid, pos: glam::Vec3, cell: &mut LastCell) -> Corners {
    let geo = &grid.geometry;
    let g = geo.world_to_grid(pos);
    let base = geo.trilinear_base(g);
    if cell.base != base {
        cell.base = base;
        for c in 0..8 {
            let r = grid.links[geo.corner_index(base, c)];
            cell.rows[c] = r;
            cell.density[c] = if r >= 0 { grid.density_cpu[r as usize] } else { 0.0 };
        }
    }
    let fractions = geo.trilinear_fractions(g, base);
    let w = weights_of_fractions(fractions);
    let mut out = Corners { rows: cell.rows, fractions, w, first_active: -1, sigma: 0.0, active: 0 };
    for (c, ((&r, &w), &density)) in cell.rows.iter().zip(&w).zip(&cell.density).enumerate() {
        if r >= 0 {
            if out.first_active < 0 {
                out.first_active = r;
            }
            out.sigma += w * density;
            out.active |= 1 << c;
        }
    }
    out
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
/// anyway. It depends only on which rows exist, so it stays valid until the
/// grid is pruned or upsampled: a training run builds it once per grid
/// (building costs O(active points), millions on real scenes).
#[derive(Debug, Clone)]
pub struct BlockOccupancy {
    res: [usize; 3],
    num_rows: usize,
    blocks: [usize; 3],
    occupied: Vec<bool>,
}

const BLOCK: usize = 8;

/// Rays marched per rayon task by `Marcher::samples`.
const RAYS_PER_TASK: usize = 256;

impl BlockOccupancy {
    pub fn of(grid: &RadianceGrid) -> Self {
        let geo = &grid.geometry;
        let blocks = geo.res.map(|r| r.div_ceil(BLOCK).max(1));
        let mut occupied = vec![false; blocks[0] * blocks[1] * blocks[2]];
        // The blocks whose closed range [b*B, b*B+B] holds lattice index i.
        let owners = |i: usize, n: usize| {
            let b = (i / BLOCK).min(n - 1);
            let below = (i.is_multiple_of(BLOCK) && i > 0).then(|| i / BLOCK - 1);
            [Some(b), below]
        };
        for &flat in &grid.coords {
            let [i, j, k] = geo.unflat(flat as usize);
            for bi in owners(i, blocks[0]).into_iter().flatten() {
                for bj in owners(j, blocks[1]).into_iter().flatten() {
                    for bk in owners(k, blocks[2]).into_iter().flatten() {
                        occupied[(bi * blocks[1] + bj) * blocks[2] + bk] = true;
                    }
                }
            }
        }
        Self { res: geo.res, num_rows: grid.num_rows(), blocks, occupied }
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
}

impl<'a> Marcher<'a> {
    pub fn new(grid: &'a RadianceGrid) -> Self {
        Self { grid, occupancy: std::borrow::Cow::Owned(BlockOccupancy::of(grid)) }
    }

    /// A marcher on an occupancy built earlier for this very grid state.
    pub fn with_occupancy(grid: &'a RadianceGrid, occupancy: &'a BlockOccupancy) -> Self {
        assert!(occupancy.matches(grid), "block occupancy built for another grid state");
        Self { grid, occupancy: std::borrow::Cow::Borrowed(occupancy) }
    }

    /// The grid this marches through.
    pub fn grid(&self) -> &'a RadianceGrid {
        self.grid
    }

    /// When sample `k` (at `t`) lies in an empty block: the index of the
    /// first sample at or after the ray's exit from that block.
    fn skip_empty(&self, a: glam::Vec3, d: glam::Vec3, t0: f32, step: f32, t: f32, k: usize) -> Option<usize> {
        let b = self.grid.geometry.trilinear_base(a + t * d).map(|v| v / BLOCK);
        let occ = &*self.occupancy;
        if occ.occupied[(b[0] * occ.blocks[1] + b[1]) * occ.blocks[2] + b[2]] {
            return None;
        }
        let mut exit = f32::INFINITY;
        for ax in 0..3 {
            let bound = if d[ax] > 0.0 {
                ((b[ax] + 1) * BLOCK) as f32
            } else if d[ax] < 0.0 {
                (b[ax] * BLOCK) as f32
            } else {
                continue;
            };
            exit = exit.min((bound - a[ax]) / d[ax]);
        }
        let next = ((exit - t0) / step - 0.5 - 1e-3).ceil();
        Some(if next.is_finite() && next > k as f32 { next as usize } else { k + 1 })
    }

    /// Equation-4 depth of every ray (None = miss), in parallel, without
    /// tensors (R³).
    pub fn depths(&self, rays: &[Ray], params: &MarchParams) -> Vec<Option<f32>> {
        rays.par_iter().map(|r| self.depth(r, params)).collect()
    }

    /// The same march and sub-sample crossing as `walk`, stopping at the crossing.
    fn depth(&self, ray: &Ray, p: &MarchParams) -> Option<f32> {
        let grid = self.grid;
        let geo = &grid.geometry;
        let (t0, t1) = geo.intersect(ray.origin, ray.dir)?;
        let step = ray_step(grid, ray, p);
        // The ray in lattice coordinates: g(t) = a + t * d.
        let a = geo.world_to_grid(ray.origin);
        let d = ray.dir / geo.voxel_size();
        let mut optical = 0.0f32;
        let mut cell = LastCell::new();
        let mut k = 0usize;
        loop {
            let t = t0 + (k as f32 + 0.5) * step;
            if t >= t1 {
                return None;
            }
            if let Some(next) = self.skip_empty(a, d, t0, step, t, k) {
                k = next;
                continue;
            }
            let c = corners(grid, ray.origin + t * ray.dir, &mut cell);
            if c.first_active >= 0 && c.sigma > p.sigma_threshold {
                let before = optical;
                optical += c.sigma * step;
                if optical >= p.depth_threshold {
                    return Some(threshold_crossing(t, step, before, c.sigma, p.depth_threshold));
                }
            }
            k += 1;
        }
    }

    /// Marches every ray (in parallel) and packs the samples. Each rayon
    /// task packs its rays into a batch of its own (no vectors per ray);
    /// the pieces are appended in ray order, so the batch does not depend
    /// on the thread count.
    pub fn samples(&self, rays: &[Ray], params: &MarchParams) -> SampleBatch {
        let pieces: Vec<SampleBatch> = rays.par_chunks(RAYS_PER_TASK).map(|part| self.pack(part, params)).collect();
        let mut b = SampleBatch { num_rays: 0, ray_offsets: vec![0], ..Default::default() };
        let total: usize = pieces.iter().map(SampleBatch::num_samples).sum();
        b.ray_offsets.reserve(rays.len());
        b.threshold_depth.reserve(rays.len());
        b.corner_rows.reserve(total * 8);
        b.corner_weights.reserve(total * 8);
        b.colour_weights.reserve(total * 8);
        b.t.reserve(total);
        b.delta.reserve(total);
        b.basis.reserve(total * self.grid.num_basis());
        for piece in pieces {
            let base = b.t.len() as u32;
            b.ray_offsets.extend(piece.ray_offsets[1..].iter().map(|o| o + base));
            b.corner_rows.extend_from_slice(&piece.corner_rows);
            b.corner_weights.extend_from_slice(&piece.corner_weights);
            b.colour_weights.extend_from_slice(&piece.colour_weights);
            b.t.extend_from_slice(&piece.t);
            b.delta.extend_from_slice(&piece.delta);
            b.basis.extend_from_slice(&piece.basis);
            b.threshold_depth.extend_from_slice(&piece.threshold_depth);
            b.num_rays += piece.num_rays;
        }
        b
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
        let geo = &grid.geometry;
        let (t0, t1) = geo.intersect(ray.origin, ray.dir)?;
        let step = ray_step(grid, ray, p);
        let a = geo.world_to_grid(ray.origin);
        let d = ray.dir / geo.voxel_size();
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
            if let Some(next) = self.skip_empty(a, d, t0, step, t, k) {
                k = next;
                continue;
            }
            k += 1;
            let Corners { rows, fractions, w, first_active, sigma, active } =
                corners(grid, ray.origin + t * ray.dir, &mut cell);
            if first_active >= 0 && sigma > p.sigma_threshold {
                let mut sample = MarchSample {
                    rows,
                    weights: w,
                    colour_weights: colour_weights(&w, active, p.colour_corners),
                    fractions,
                    active,
                    t,
                    delta: step,
                    sigma,
                };
                for (c, &row) in rows.iter().enumerate() {
                    if row < 0 {
                        sample.rows[c] = first_active;
                        sample.weights[c] = 0.0;
                    }
                }
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

    /// Skipping empty blocks must give exactly the samples of a march that
    /// visits every position (the same marcher with every block marked occupied).
    #[test]
    fn empty_space_skipping_is_exact() {
        let device = crate::util::backend::BackendKind::Flex.device();
        let grid = crate::field::grid::sphere_grid(48, &device);
        let skipping = Marcher::new(&grid);
        let mut everything = BlockOccupancy::of(&grid);
        assert!(everything.occupied.iter().any(|o| !o), "the sphere grid has empty blocks");
        everything.occupied.fill(true);
        let full = Marcher::with_occupancy(&grid, &everything);
        let cam =
            Camera::new(Intrinsics::from_fov_x(40, 40, 0.9), look_at(Vec3::new(2.2, 1.0, 0.8), Vec3::ZERO, Vec3::Z));
        let rays = cam.rays(None);
        let params = MarchParams::default();
        let (a, b) = (skipping.samples(&rays, &params), full.samples(&rays, &params));
        assert!(a.num_samples() > 1000);
        assert_eq!(a.ray_offsets, b.ray_offsets);
        assert_eq!(a.corner_rows, b.corner_rows);
        assert_eq!(a.t, b.t);
        assert_eq!(a.threshold_depth, b.threshold_depth);
        assert_eq!(skipping.depths(&rays, &params), a.threshold_depth);
    }
}
