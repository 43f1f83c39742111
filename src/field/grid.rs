//! The radiance grid: density + spherical-harmonic colour on a voxel lattice
//! over the scene box, stored occupancy-compacted.
//!
//! Layout (as in Plenoxels): a dense `links` array maps each lattice point
//! to a row of the compact data tensors, or -1 where the point is empty.
//! Only active points own rows, so a 512^3 grid costs 512 MB of links plus
//! data for the occupied fraction. The data rows are Burn tensors (they are
//! what autodiff and the optimiser see); a plain-Rust mirror of the density
//! column lets the sample generator skip empty space and stop rays early
//! without touching the tensors.

use crate::field::environment::Environment;
use crate::scene::sh;
use crate::util::tensor::{floats, indices, to_vec};
use crate::util::transfer::human_bytes;
use anyhow::{Result, bail};
use burn::tensor::{Device, Tensor};
use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Resolution and placement of the lattice.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GridGeometry {
    pub res: [usize; 3],
    pub bbox_min: Vec3,
    pub bbox_max: Vec3,
}

/// The trilinear weights of the 8 corners of a cell (corner `c` is offset
/// by bits 2, 1, 0 of `c` along x, y, z) at `frac` inside it.
#[inline]
pub fn weights_of_fractions(frac: [f32; 3]) -> [f32; 8] {
    std::array::from_fn(|c| {
        let (dx, dy, dz) = ((c >> 2) & 1, (c >> 1) & 1, c & 1);
        let wx = if dx == 1 { frac[0] } else { 1.0 - frac[0] };
        let wy = if dy == 1 { frac[1] } else { 1.0 - frac[1] };
        let wz = if dz == 1 { frac[2] } else { 1.0 - frac[2] };
        wx * wy * wz
    })
}

impl GridGeometry {
    pub fn new(res: [usize; 3], bbox_min: Vec3, bbox_max: Vec3) -> Self {
        Self { res, bbox_min, bbox_max }
    }

    pub fn num_points(&self) -> usize {
        self.res[0] * self.res[1] * self.res[2]
    }

    /// Edge lengths of one voxel in world units.
    pub fn voxel_size(&self) -> Vec3 {
        (self.bbox_max - self.bbox_min) / Vec3::new(self.res[0] as f32, self.res[1] as f32, self.res[2] as f32)
    }

    /// Continuous lattice coordinates: lattice point i sits at the centre of
    /// voxel i, so coordinate 0 is half a voxel inside the box.
    #[inline]
    pub fn world_to_grid(&self, p: Vec3) -> Vec3 {
        self.world_to_grid_in(p, self.voxel_size())
    }

    /// `world_to_grid` with `voxel_size()` computed once by the caller (a
    /// march of millions of samples): the same arithmetic, the same bits.
    #[inline(always)]
    pub fn world_to_grid_in(&self, p: Vec3, voxel_size: Vec3) -> Vec3 {
        (p - self.bbox_min) / voxel_size - Vec3::splat(0.5)
    }

    pub fn grid_to_world(&self, g: Vec3) -> Vec3 {
        self.bbox_min + (g + Vec3::splat(0.5)) * self.voxel_size()
    }

    #[inline]
    pub fn flat(&self, i: usize, j: usize, k: usize) -> usize {
        (i * self.res[1] + j) * self.res[2] + k
    }

    #[inline]
    pub fn unflat(&self, f: usize) -> [usize; 3] {
        let k = f % self.res[2];
        let j = (f / self.res[2]) % self.res[1];
        let i = f / (self.res[1] * self.res[2]);
        [i, j, k]
    }

    /// The lowest of the 8 lattice points `trilinear` uses for `g` (per axis:
    /// `g` clamped into the lattice, floored, at most `res - 2`).
    #[inline]
    pub fn trilinear_base(&self, g: Vec3) -> [usize; 3] {
        std::array::from_fn(|a| {
            let c = g[a].clamp(0.0, (self.res[a] - 1) as f32);
            // `as` truncates, which is the floor of a clamped (non-negative,
            // or NaN -> 0) value; `f32::floor` is a libm call on the
            // baseline x86-64 target (5 % of a fern march in `perf`).
            (c as usize).min(self.res[a].saturating_sub(2))
        })
    }

    /// The 8 lattice points around `g` and their trilinear weights (bit 0 =
    /// +z, bit 1 = +y, bit 2 = +x). `g` is clamped into the lattice.
    #[inline]
    pub fn trilinear(&self, g: Vec3) -> ([usize; 8], [f32; 8]) {
        let base = self.trilinear_base(g);
        (std::array::from_fn(|c| self.corner_index(base, c)), self.trilinear_weights(g, base))
    }

    /// The flat lattice index of corner `c` (bit 0 = +z, bit 1 = +y, bit 2
    /// = +x) of the cell at `base` (`trilinear_base`).
    #[inline]
    pub fn corner_index(&self, base: [usize; 3], c: usize) -> usize {
        let (dx, dy, dz) = ((c >> 2) & 1, (c >> 1) & 1, c & 1);
        self.flat(
            (base[0] + dx).min(self.res[0] - 1),
            (base[1] + dy).min(self.res[1] - 1),
            (base[2] + dz).min(self.res[2] - 1),
        )
    }

    /// How far apart in flat indices (`flat`) the lattice's neighbours are
    /// along x, y and z.
    pub fn strides(&self) -> [usize; 3] {
        [self.res[1] * self.res[2], self.res[2], 1]
    }

    /// What `corner_index(base, c)` adds to the base's own flat index, for
    /// every `base` that `trilinear_base` gives (its indices stay below
    /// `res - 1` on axes longer than one point; on a one-point axis the
    /// `+1` corner is clamped back onto the base).
    pub fn corner_offsets(&self) -> [usize; 8] {
        let stride = self.strides();
        let step = |axis: usize, bit: usize| if bit == 1 && self.res[axis] > 1 { stride[axis] } else { 0 };
        std::array::from_fn(|c| step(0, (c >> 2) & 1) + step(1, (c >> 1) & 1) + step(2, c & 1))
    }

    /// The trilinear weights of the 8 corners of the cell at `base`
    /// (`trilinear_base(g)`) for `g`, clamped into the lattice.
    #[inline]
    pub fn trilinear_weights(&self, g: Vec3, base: [usize; 3]) -> [f32; 8] {
        weights_of_fractions(self.trilinear_fractions(g, base))
    }

    /// Where `g` lies inside the cell at `base`, per axis in [0, 1],
    /// clamped into the lattice: what the 8 trilinear weights are made of.
    #[inline]
    pub fn trilinear_fractions(&self, g: Vec3, base: [usize; 3]) -> [f32; 3] {
        let mut frac = [0f32; 3];
        for a in 0..3 {
            let c = g[a].clamp(0.0, (self.res[a] - 1) as f32);
            frac[a] = if self.res[a] > 1 { c - base[a] as f32 } else { 0.0 };
        }
        frac
    }

    /// Ray-box intersection in world units: (t_near, t_far) clipped to t >= 0.
    pub fn intersect(&self, o: Vec3, d: Vec3) -> Option<(f32, f32)> {
        let inv = Vec3::ONE / d;
        let t0 = (self.bbox_min - o) * inv;
        let t1 = (self.bbox_max - o) * inv;
        let tmin = t0.min(t1).max_element().max(0.0);
        let tmax = t0.max(t1).min_element();
        (tmax > tmin).then_some((tmin, tmax))
    }
}

/// Bytes a grid needs: the links array plus `rows` data rows, each with
/// parameters, optimiser state and gradients (4 copies).
pub fn estimate_bytes(res: [usize; 3], rows: usize, sh_degree: u32) -> u64 {
    let cols = 1 + 3 * sh::num_basis(sh_degree);
    (res[0] * res[1] * res[2]) as u64 * 4 + rows as u64 * cols as u64 * 4 * 4
}

/// Where a grid of `rows` rows at `sh_degree` is kept when its steps run
/// on `device`: on it when its SH colour tensor (`rows` x 3 x the SH basis,
/// one tensor) fits in one of its buffers, else in host memory (a CPU
/// backend's device). On wgpu a larger tensor cannot be bound whole, and
/// lavapipe (128 MiB) then reads garbage instead of failing: the 32-pixel
/// scene's loss jumped to 48 at an upsampling to 1.3 M rows at SH degree 2.
/// A training step on a grid kept on the host still renders and
/// differentiates on `device`, from the rows it touches (`Trainer`); views
/// of it render on the CPU. The CPU backends have no such limit.
pub fn placement(rows: usize, sh_degree: u32, device: &Device) -> Result<Device> {
    let Some(limit) = crate::util::backend::max_buffer_bytes(device) else { return Ok(device.clone()) };
    let need = sh_bytes(rows, sh::num_basis(sh_degree));
    if need <= limit {
        return Ok(device.clone());
    }
    crate::util::backend::host_device().ok_or_else(|| {
        anyhow::anyhow!(
            "the field's SH colour ({rows} voxels, {}) is larger than the wgpu adapter's largest buffer ({}), \
             and this build has no CPU backend to keep it in host memory: build with the feature `flex`, or fit a \
             coarser grid ([grid] upsample_res) or a lower grid.sh_degree",
            human_bytes(need),
            human_bytes(limit)
        )
    })
}

/// Bytes of the SH colour tensor of `rows` voxels with `num_basis` SH
/// functions (f32, 3 channels).
pub fn sh_bytes(rows: usize, num_basis: usize) -> u64 {
    rows as u64 * 3 * num_basis as u64 * 4
}

/// Whether `grid` is kept in host memory while its steps run on `compute` (see [`placement`]).
pub fn kept_on_host(grid: &RadianceGrid, compute: &Device) -> bool {
    grid.device() != *compute
}

/// Refuses, before anything is allocated, a grid that would not fit in memory.
pub fn check_fits(res: [usize; 3], rows: usize, sh_degree: u32) -> Result<()> {
    let need = estimate_bytes(res, rows, sh_degree);
    if let Some(avail) = crate::util::memory::available_memory_bytes() {
        // Leave a quarter of the available memory for images, samples and the renderer.
        let budget = avail / 4 * 3;
        if need > budget {
            let cols = 1 + 3 * sh::num_basis(sh_degree);
            let per_row = cols as u64 * 16;
            let links = (res[0] * res[1] * res[2]) as u64 * 4;
            let rows_fit = budget.saturating_sub(links) / per_row;
            bail!(
                "a {}x{}x{} grid with {} active voxels and SH degree {} needs about {:.1} GB, \
                 but only {:.1} GB is available: at this resolution about {} active voxels fit \
                 (lower the resolution, raise the pruning threshold or use SH degree {})",
                res[0],
                res[1],
                res[2],
                rows,
                sh_degree,
                need as f64 / 1e9,
                budget as f64 / 1e9,
                rows_fit,
                sh_degree.saturating_sub(1)
            );
        }
    }
    Ok(())
}

/// A grid's lattice -> row map and its cells' corner offsets: what turns
/// a cell's base point into the rows of its 8 corners. Shared (the links
/// are not copied), so sample lists can keep one 4-byte base per cell
/// instead of its 8 rows (`frozen::FrozenSamples`).
#[derive(Debug, Clone, Default)]
pub struct CellLattice {
    links: Arc<Vec<i32>>,
    corner_offsets: [usize; 8],
}

impl CellLattice {
    pub fn of(grid: &RadianceGrid) -> Self {
        Self::new(grid.links.clone(), grid.geometry.corner_offsets())
    }

    /// A lattice from its links and corner offsets (tests build small ones by hand).
    pub fn new(links: Arc<Vec<i32>>, corner_offsets: [usize; 8]) -> Self {
        Self { links, corner_offsets }
    }

    /// The rows of the 8 corners of the cell whose base is lattice point
    /// `key` and which corners are active (bit `c` for corner `c`): an empty
    /// corner points at the first active corner's row (all -1 when none is
    /// active). Selects, not branches, on emptiness (about a third of fern's
    /// lattice points are empty, in no pattern a predictor learns).
    #[inline(always)]
    pub fn cell(&self, key: usize) -> ([i32; 8], u8) {
        let raw = self.raw_rows(key);
        let active = raw.iter().enumerate().fold(0u8, |bits, (c, &r)| bits | (u8::from(r >= 0) << c));
        if active == 0 {
            return ([-1; 8], 0);
        }
        let first = raw[active.trailing_zeros() as usize];
        (raw.map(|r| if r >= 0 { r } else { first }), active)
    }

    /// The links of the 8 corners of the cell at `key` (-1 for an empty corner).
    #[inline(always)]
    pub fn raw_rows(&self, key: usize) -> [i32; 8] {
        std::array::from_fn(|c| self.links[key + self.corner_offsets[c]])
    }

    /// Asks the CPU to start loading the links of the cell at `key`, so a
    /// `cell` read soon after finds them cached: a hint, with no effect on
    /// any result (and none off x86-64). Corners 2c and 2c + 1 are
    /// neighbours along z, adjacent in the links: one line each pair.
    #[inline(always)]
    pub fn prefetch(&self, key: usize) {
        #[cfg(not(target_arch = "x86_64"))]
        let _ = key;
        #[cfg(target_arch = "x86_64")]
        for c in [0, 2, 4, 6] {
            let point = self.links.as_ptr().wrapping_add(key + self.corner_offsets[c]);
            // SAFETY: a prefetch reads nothing and never faults, whatever the
            // address; its one requirement, SSE, every x86-64 CPU has.
            unsafe { std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(point.cast()) };
        }
    }
}

/// Lattices are equal when they are the same shared links (the common
/// case, compared without reading them) or hold the same numbers.
impl PartialEq for CellLattice {
    fn eq(&self, other: &Self) -> bool {
        self.corner_offsets == other.corner_offsets
            && (Arc::ptr_eq(&self.links, &other.links) || self.links == other.links)
    }
}

/// The radiance grid.
pub struct RadianceGrid {
    pub geometry: GridGeometry,
    pub sh_degree: u32,
    /// Dense lattice -> data row, -1 where empty (shared, not copied, with
    /// the sample lists that name cells by their base point: `CellLattice`).
    pub links: Arc<Vec<i32>>,
    /// Data row -> flat lattice index.
    pub coords: Vec<u32>,
    /// Density per row, [rows, 1] (raw; the renderer applies ReLU).
    pub density: Tensor<2>,
    /// SH coefficients per row, [rows, 3 * basis], colour-major.
    pub sh: Tensor<2>,
    /// Plain copy of `density`, kept in sync by whoever updates the tensor.
    pub density_cpu: Vec<f32>,
    /// The far background seen through what the grid leaves of a ray (a
    /// capture around the scene); `None`: the dataset's constant background.
    pub far: Option<Environment>,
}

impl RadianceGrid {
    /// Number of SH coefficients per colour channel.
    pub fn num_basis(&self) -> usize {
        sh::num_basis(self.sh_degree)
    }

    pub fn num_rows(&self) -> usize {
        self.coords.len()
    }

    /// The row of the lattice point next to row `row`'s point along +`axis`
    /// (0, 1, 2 = x, y, z); None past the lattice or where that point is empty.
    pub fn neighbour_row(&self, row: usize, axis: usize) -> Option<i32> {
        self.neighbour_rows(row)[axis]
    }

    /// `neighbour_row` along the +x, +y and +z axes, from one read of the
    /// row's lattice point and one split of it into coordinates.
    pub fn neighbour_rows(&self, row: usize) -> [Option<i32>; 3] {
        let geo = &self.geometry;
        let point = self.coords[row] as usize;
        let ijk = geo.unflat(point);
        let strides = geo.strides();
        std::array::from_fn(|axis| {
            if ijk[axis] + 1 >= geo.res[axis] {
                return None;
            }
            let nb = self.links[point + strides[axis]];
            (nb >= 0).then_some(nb)
        })
    }

    pub fn device(&self) -> Device {
        self.density.device()
    }

    /// A grid with every lattice point active, density `init_density`, SH zero.
    pub fn new_dense(geometry: GridGeometry, sh_degree: u32, init_density: f32, device: &Device) -> Result<Self> {
        let n = geometry.num_points();
        check_fits(geometry.res, n, sh_degree)?;
        let device = &placement(n, sh_degree, device)?;
        let coords: Vec<u32> = (0..n as u32).collect();
        let density = vec![init_density; n];
        let sh = vec![0.0; n * 3 * sh::num_basis(sh_degree)];
        Ok(Self::from_rows(geometry, sh_degree, coords, density, sh, device))
    }

    /// Builds a grid from compact rows (coords must be distinct and in range).
    pub fn from_rows(
        geometry: GridGeometry,
        sh_degree: u32,
        coords: Vec<u32>,
        density: Vec<f32>,
        sh_data: Vec<f32>,
        device: &Device,
    ) -> Self {
        let n = coords.len();
        let cols = 3 * sh::num_basis(sh_degree);
        assert_eq!(density.len(), n);
        assert_eq!(sh_data.len(), n * cols);
        let mut links = vec![-1i32; geometry.num_points()];
        for (row, &c) in coords.iter().enumerate() {
            links[c as usize] = row as i32;
        }
        Self {
            geometry,
            sh_degree,
            links: Arc::new(links),
            coords,
            density: floats(density.clone(), [n, 1], device),
            sh: floats(sh_data, [n, cols], device),
            density_cpu: density,
            far: None,
        }
    }

    /// Trilinear density (before ReLU) from the plain mirror; inactive corners count as 0.
    pub fn density_at(&self, g: Vec3) -> f32 {
        let (idx, w) = self.geometry.trilinear(g);
        let mut s = 0.0;
        for c in 0..8 {
            let row = self.links[idx[c]];
            if row >= 0 {
                s += w[c] * self.density_cpu[row as usize];
            }
        }
        s
    }

    /// The SH rows as a plain buffer.
    pub fn sh_cpu(&self) -> Vec<f32> {
        to_vec(self.sh.clone())
    }

    /// Re-reads the density mirror from the tensor (after bulk changes).
    pub fn sync_density_mirror(&mut self) {
        self.density_cpu = to_vec(self.density.clone());
    }

    /// Drops rows whose density (and that of all 26 neighbours) is below
    /// `threshold`: empty space stops costing memory and samples. Returns the
    /// number of rows kept.
    pub fn prune(&mut self, threshold: f32) -> usize {
        let geo = self.geometry;
        let dens = &self.density_cpu;
        let links = &self.links;
        let solid = |f: usize| {
            let r = links[f];
            r >= 0 && dens[r as usize] >= threshold
        };
        let keep: Vec<bool> = self
            .coords
            .par_iter()
            .map(|&c| {
                let [i, j, k] = geo.unflat(c as usize);
                for di in -1i64..=1 {
                    for dj in -1i64..=1 {
                        for dk in -1i64..=1 {
                            let (a, b, cc) = (i as i64 + di, j as i64 + dj, k as i64 + dk);
                            if a < 0 || b < 0 || cc < 0 {
                                continue;
                            }
                            let (a, b, cc) = (a as usize, b as usize, cc as usize);
                            if a >= geo.res[0] || b >= geo.res[1] || cc >= geo.res[2] {
                                continue;
                            }
                            if solid(geo.flat(a, b, cc)) {
                                return true;
                            }
                        }
                    }
                }
                false
            })
            .collect();
        let kept_rows: Vec<i32> = (0..keep.len()).filter(|&r| keep[r]).map(|r| r as i32).collect();
        self.keep_rows(kept_rows)
    }

    /// Keeps only the given rows (in that order).
    fn keep_rows(&mut self, rows: Vec<i32>) -> usize {
        let device = self.device();
        let n = rows.len();
        let coords: Vec<u32> = rows.iter().map(|&r| self.coords[r as usize]).collect();
        let density: Vec<f32> = rows.iter().map(|&r| self.density_cpu[r as usize]).collect();
        let idx = indices(rows, &device);
        let sh = self.sh.clone().select(0, idx);
        let mut links = vec![-1i32; self.geometry.num_points()];
        for (row, &c) in coords.iter().enumerate() {
            links[c as usize] = row as i32;
        }
        self.links = Arc::new(links);
        self.coords = coords;
        self.density = floats(density.clone(), [n, 1], &device);
        self.density_cpu = density;
        self.sh = sh;
        n
    }

    /// Resamples the grid onto a finer lattice over the same box
    /// (trilinear). A new point is active when the old cell around it has an
    /// active corner. Refuses, before allocating, a grid that would not fit;
    /// the new grid is kept where steps on `compute` keep it ([`placement`]).
    pub fn upsample(&mut self, new_res: [usize; 3], compute: &Device) -> Result<()> {
        let old = self.geometry;
        let new = GridGeometry::new(new_res, old.bbox_min, old.bbox_max);
        let links_bytes = new.num_points() as u64 * 4;
        if let Some(avail) = crate::util::memory::available_memory_bytes()
            && links_bytes > avail / 2
        {
            bail!(
                "upsampling to {}x{}x{} needs {:.1} GB for the voxel index alone, more than the {:.1} GB available",
                new_res[0],
                new_res[1],
                new_res[2],
                links_bytes as f64 / 1e9,
                avail as f64 / 1e9
            );
        }
        // Which new points lie in an old cell with an active corner (parallel over x slabs).
        let active: Vec<u32> = (0..new_res[0])
            .into_par_iter()
            .flat_map_iter(|i| {
                let mut v = Vec::new();
                for j in 0..new_res[1] {
                    for k in 0..new_res[2] {
                        let w = new.grid_to_world(Vec3::new(i as f32, j as f32, k as f32));
                        let (idx, _) = old.trilinear(old.world_to_grid(w));
                        if idx.iter().any(|&f| self.links[f] >= 0) {
                            v.push(new.flat(i, j, k) as u32);
                        }
                    }
                }
                v.into_iter()
            })
            .collect();
        check_fits(new_res, active.len(), self.sh_degree)?;
        let cols = 3 * self.num_basis();
        let old_sh = self.sh_cpu();
        let rows: Vec<(f32, Vec<f32>)> = active
            .par_iter()
            .map(|&f| {
                let [i, j, k] = new.unflat(f as usize);
                let w = new.grid_to_world(Vec3::new(i as f32, j as f32, k as f32));
                let (idx, wt) = old.trilinear(old.world_to_grid(w));
                // Density: empty corners are zero density; colour: averaged over
                // the active corners only (as the renderer does).
                let mut d = 0.0;
                let mut wsum = 0.0;
                let mut s = vec![0.0; cols];
                for c in 0..8 {
                    let r = self.links[idx[c]];
                    if r >= 0 {
                        let r = r as usize;
                        d += wt[c] * self.density_cpu[r];
                        wsum += wt[c];
                        for (q, v) in s.iter_mut().zip(&old_sh[r * cols..(r + 1) * cols]) {
                            *q += wt[c] * v;
                        }
                    }
                }
                if wsum > 0.0 {
                    s.iter_mut().for_each(|q| *q /= wsum);
                }
                (d, s)
            })
            .collect();
        let density: Vec<f32> = rows.iter().map(|r| r.0).collect();
        let sh_data: Vec<f32> = rows.into_iter().flat_map(|r| r.1).collect();
        let device = placement(active.len(), self.sh_degree, compute)?;
        let far = self.far.take();
        *self = Self::from_rows(new, self.sh_degree, active, density, sh_data, &device);
        self.far = far;
        Ok(())
    }

    /// Keeps only the first `degree` SH bands (e.g. 0 for view-independent colour).
    pub fn truncate_sh(&mut self, degree: u32) {
        if degree >= self.sh_degree {
            return;
        }
        let (old_b, new_b) = (self.num_basis(), sh::num_basis(degree));
        let n = self.num_rows();
        let sh3 = self.sh.clone().reshape([n, 3, old_b]).narrow(2, 0, new_b);
        self.sh = sh3.reshape([n, 3 * new_b]);
        self.sh_degree = degree;
    }
}

/// A dense 12³ grid over [-1, 1]³ of SH degree 0: a blob of random
/// density (2 to 8) inside radius 0.7, random colour coefficients
/// everywhere, from `seed` (the tests' field for the colour passes).
pub fn blob_grid(seed: u64, device: &Device) -> RadianceGrid {
    use rand::{Rng, SeedableRng};
    let geo = GridGeometry::new([12; 3], Vec3::splat(-1.0), Vec3::splat(1.0));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let n = geo.num_points();
    let coords: Vec<u32> = (0..n as u32).collect();
    let density: Vec<f32> = (0..n)
        .map(|f| {
            let [i, j, k] = geo.unflat(f);
            let p = geo.grid_to_world(Vec3::new(i as f32, j as f32, k as f32));
            if p.length() < 0.7 { 2.0 + 6.0 * rng.random::<f32>() } else { 0.0 }
        })
        .collect();
    let sh: Vec<f32> = (0..n * 3).map(|_| rng.random::<f32>() * 2.0 - 1.0).collect();
    RadianceGrid::from_rows(geo, 0, coords, density, sh, device)
}

/// A grid holding a textured solid sphere of radius 0.6 (density 40) in
/// [-1,1]^3 at resolution `res`, SH degree 2; only the sphere and a
/// one-voxel shell own rows, as after pruning.
pub fn sphere_grid(res: usize, device: &Device) -> RadianceGrid {
    let geo = GridGeometry::new([res; 3], Vec3::splat(-1.0), Vec3::splat(1.0));
    let nb = sh::num_basis(2);
    let shell = 1.5 * geo.voxel_size().x;
    let mut coords = Vec::new();
    let mut dens = Vec::new();
    let mut shd = Vec::new();
    for f in 0..geo.num_points() {
        let [i, j, k] = geo.unflat(f);
        let p = geo.grid_to_world(Vec3::new(i as f32, j as f32, k as f32));
        let r = p.length();
        if r < 0.6 + shell {
            coords.push(f as u32);
            dens.push(if r < 0.6 { 40.0 } else { 0.0 });
            for c in 0..3 {
                for b in 0..nb {
                    shd.push(if b == 0 { sh::dc_for_colour(0.5 + 0.4 * (p[c] * 7.0).sin()) } else { 0.05 });
                }
            }
        }
    }
    RadianceGrid::from_rows(geo, 2, coords, dens, shd, device)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The flat base index plus `corner_offsets` is `corner_index` for
    /// every cell base `trilinear_base` gives, one-point axes included.
    #[test]
    fn corner_offsets_match_corner_index() {
        for res in [[4, 5, 6], [1, 3, 2], [3, 1, 1], [2, 2, 2]] {
            let geo = GridGeometry::new(res, Vec3::splat(-1.0), Vec3::splat(1.0));
            let offsets = geo.corner_offsets();
            let mut bases = std::collections::BTreeSet::new();
            for step in 0..=40 {
                let x = step as f32 / 40.0;
                let g = Vec3::new(x * res[0] as f32, (1.0 - x) * res[1] as f32, x * x * res[2] as f32) - 0.5;
                bases.insert(geo.trilinear_base(g));
            }
            assert!(bases.len() > 1 || res.iter().all(|&r| r <= 2), "{res:?}: {bases:?}");
            for base in bases {
                let flat = geo.flat(base[0], base[1], base[2]);
                for (c, offset) in offsets.iter().enumerate() {
                    assert_eq!(flat + offset, geo.corner_index(base, c), "res {res:?} base {base:?} corner {c}");
                }
            }
        }
    }

    #[test]
    fn trilinear_weights_sum_to_one_and_hit_lattice_points() {
        let g = GridGeometry::new([4, 5, 6], Vec3::splat(-1.0), Vec3::splat(1.0));
        let (idx, w) = g.trilinear(Vec3::new(1.0, 2.0, 3.0));
        assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        let best = (0..8).max_by(|&a, &b| w[a].total_cmp(&w[b])).unwrap();
        assert_eq!(idx[best], g.flat(1, 2, 3));
        assert!((w[best] - 1.0).abs() < 1e-6);
    }

    #[test]
    fn world_grid_round_trip() {
        let g = GridGeometry::new([8, 8, 4], Vec3::new(-1.0, -2.0, 0.0), Vec3::new(1.0, 2.0, 1.0));
        let p = Vec3::new(0.3, -1.1, 0.7);
        assert!((g.grid_to_world(g.world_to_grid(p)) - p).length() < 1e-5);
    }

    #[test]
    fn refuses_an_absurd_grid_before_allocating() {
        let err = check_fits([4096, 4096, 4096], 4096 * 4096 * 4096, 2).unwrap_err();
        assert!(err.to_string().contains("available"), "{err}");
    }
}
