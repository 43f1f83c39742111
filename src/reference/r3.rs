//! R³, reference ray registration (paper section 3.2, equations 5-8), in
//! plain Rust: lift every reference pixel to the 3D point its depth gives,
//! store those points in a sparse voxel dictionary, and give every training
//! pixel whose own 3D point lands next to a stored reference point, seen from
//! a compatible direction, that reference pixel's stylized colour.
//!
//! Choices (see `RegisterParams` for the values):
//! - cubic dictionary voxels over the bounding box of the reference points
//!   (the longest side divided by `dict_res`), stored sparsely as sorted keys;
//!   up to `per_voxel` reference points per voxel (the first ones in
//!   reference, then pixel order);
//! - a training point is matched among the stored points of its own voxel
//!   and, with `neighbours`, the 26 around it, that pass the angle test
//!   (cosine between the two world viewing directions above `cos_threshold`)
//!   and lie within `max_dist_voxels` voxels of it: the one whose reference
//!   *ray* passes nearest to the point wins (that is the reference pixel the
//!   point projects into; the nearest stored *point* is often the
//!   neighbouring pixel at grazing angles);
//! - points are in the grid's space (NDC for forward-facing scenes, where a
//!   voxel is anisotropic in world units but still the field's own lattice);
//!   directions are the world viewing directions.

use std::collections::HashMap;

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::scene::camera::Ray;

/// Registration settings: `[register]` in a stylize config, and the flags
/// of `refnpr register` and `refnpr stylize` (one type for both).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, clap::Args)]
#[serde(deny_unknown_fields, default)]
pub struct RegisterParams {
    /// Dictionary voxels along the longest side of the reference points' box
    /// (released code: 512; paper: 256).
    #[arg(long, default_value_t = RegisterParams::default().dict_res)]
    pub dict_res: usize,
    /// Reference points kept per voxel (paper: 8; released code: 1).
    #[arg(long, default_value_t = RegisterParams::default().per_voxel)]
    pub per_voxel: usize,
    /// Minimum cosine between the reference and training viewing directions
    /// (paper: 0.6; released code: 0.3).
    #[arg(long, default_value_t = RegisterParams::default().cos_threshold)]
    pub cos_threshold: f32,
    /// Largest accepted distance to the matched reference point, in voxels.
    #[arg(long, default_value_t = RegisterParams::default().max_dist_voxels)]
    pub max_dist_voxels: f32,
    /// Also search the 26 neighbouring voxels (`--no-neighbours`: only the point's own).
    #[arg(long = "no-neighbours", action = clap::ArgAction::SetFalse)]
    pub neighbours: bool,
    /// Never make voxels smaller than the reference's pixel footprint (the
    /// median distance between the 3D points of neighbouring reference
    /// pixels): finer voxels only lose matches, since most of them hold no
    /// reference point (the released code's low registration rate on small
    /// images). `dict_res` is then an upper bound (`--no-cap-to-footprint`:
    /// exactly `dict_res`).
    #[arg(long = "no-cap-to-footprint", alias = "no-footprint-cap", action = clap::ArgAction::SetFalse)]
    pub cap_to_footprint: bool,
    /// Erode the reference's hit mask this many times (3x3) before storing:
    /// drops silhouette pixels whose depth mixes foreground and background.
    #[arg(long = "erode-reference", alias = "erode", default_value_t = RegisterParams::default().erode_reference)]
    pub erode_reference: usize,
}

impl Default for RegisterParams {
    fn default() -> Self {
        Self {
            dict_res: 512,
            per_voxel: 8,
            cos_threshold: 0.6,
            max_dist_voxels: 1.0,
            neighbours: true,
            cap_to_footprint: true,
            erode_reference: 0,
        }
    }
}

impl RegisterParams {
    pub fn validate(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            (2..=1 << 20).contains(&self.dict_res),
            "register.dict_res must be in 2..=1048576, got {}",
            self.dict_res
        );
        anyhow::ensure!(self.per_voxel >= 1, "register.per_voxel must be at least 1");
        anyhow::ensure!((-1.0..=1.0).contains(&self.cos_threshold), "register.cos_threshold must be in [-1, 1]");
        anyhow::ensure!(
            self.max_dist_voxels > 0.0 && self.max_dist_voxels.is_finite(),
            "register.max_dist_voxels must be > 0"
        );
        Ok(())
    }
}

/// The surface seen by one camera: a 3D point per pixel (None = no hit),
/// the world viewing direction per pixel, and each pixel's ray (origin and
/// unit direction in the points' space, NDC for forward-facing scenes).
#[derive(Debug, Clone)]
pub struct Surface {
    pub width: usize,
    pub height: usize,
    pub points: Vec<Option<Vec3>>,
    pub dirs: Vec<Vec3>,
    pub rays: Vec<(Vec3, Vec3)>,
}

impl Surface {
    /// Points at `origin + depth * dir` of each ray (depth along the ray's unit
    /// direction, in the ray's space, as the renderer and the procedural scene
    /// report it); non-finite or non-positive depths count as misses.
    pub fn from_depth(rays: &[Ray], depth: &[Option<f32>], width: usize, height: usize) -> Self {
        assert_eq!(rays.len(), width * height, "one ray per pixel");
        assert_eq!(depth.len(), rays.len(), "one depth per ray");
        let points = rays
            .iter()
            .zip(depth)
            .map(|(r, d)| d.filter(|t| t.is_finite() && *t > 0.0).map(|t| r.origin + t * r.dir))
            .collect();
        let dirs = rays.iter().map(|r| r.view_dir.normalize()).collect();
        let rays = rays.iter().map(|r| (r.origin, r.dir)).collect();
        Self { width, height, points, dirs, rays }
    }

    pub fn num_hits(&self) -> usize {
        self.points.iter().filter(|p| p.is_some()).count()
    }

    /// Drops the points of the pixels `keep` (row-major) does not mark.
    pub fn keep_points(&mut self, keep: &[bool]) {
        assert_eq!(keep.len(), self.points.len(), "one flag per pixel");
        for (p, k) in self.points.iter_mut().zip(keep) {
            if !k {
                *p = None;
            }
        }
    }
}

/// A reference view: its surface and the stylized colour of every pixel.
#[derive(Debug, Clone)]
pub struct Reference {
    pub surface: Surface,
    pub colours: Vec<[f32; 3]>,
}

#[derive(Debug, Clone, Copy)]
struct Entry {
    point: Vec3,
    /// The reference ray: origin and unit direction in the points' space.
    origin: Vec3,
    ray_dir: Vec3,
    /// World viewing direction (for the angle test).
    dir: Vec3,
    colour: [f32; 3],
    reference: u32,
}

/// The sparse voxel dictionary of reference points.
pub struct Dictionary {
    min: Vec3,
    voxel: f32,
    dims: [u64; 3],
    /// Entries sorted by voxel key; `cells` maps a key to its range.
    entries: Vec<Entry>,
    cells: HashMap<u64, (u32, u32)>,
}

impl Dictionary {
    /// Builds the dictionary; None when no reference pixel hits the scene.
    pub fn build(references: &[Reference], params: &RegisterParams) -> Option<Self> {
        let mut entries = Vec::new();
        for (ri, r) in references.iter().enumerate() {
            let mut mask: Vec<bool> = r.surface.points.iter().map(|p| p.is_some()).collect();
            if params.erode_reference > 0 {
                mask = erode(&mask, r.surface.width, r.surface.height, params.erode_reference);
            }
            for (pi, p) in r.surface.points.iter().enumerate() {
                if let (Some(point), true) = (p, mask[pi]) {
                    let (origin, ray_dir) = r.surface.rays[pi];
                    entries.push(Entry {
                        point: *point,
                        origin,
                        ray_dir,
                        dir: r.surface.dirs[pi],
                        colour: r.colours[pi],
                        reference: ri as u32,
                    });
                }
            }
        }
        if entries.is_empty() {
            return None;
        }
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for e in &entries {
            lo = lo.min(e.point);
            hi = hi.max(e.point);
        }
        let extent = (hi - lo).max_element().max(1e-6);
        let mut voxel = extent / params.dict_res as f32;
        if params.cap_to_footprint
            && let Some(f) = median_footprint(references)
        {
            voxel = voxel.max(f);
        }
        let dims = ((hi - lo) / voxel).floor().as_uvec3().to_array().map(|d| d as u64 + 1);
        let mut dict = Self { min: lo, voxel, dims, entries: Vec::new(), cells: HashMap::new() };
        let mut keyed: Vec<(u64, Entry)> = entries.into_iter().map(|e| (dict.key(dict.cell(e.point)), e)).collect();
        // Stable sort: within a voxel, reference then pixel order is kept.
        keyed.sort_by_key(|(k, _)| *k);
        let mut start = 0;
        while start < keyed.len() {
            let key = keyed[start].0;
            let end = start + keyed[start..].iter().take_while(|(k, _)| *k == key).count();
            let keep = (end - start).min(params.per_voxel);
            let at = dict.entries.len() as u32;
            dict.entries.extend(keyed[start..start + keep].iter().map(|(_, e)| *e));
            dict.cells.insert(key, (at, keep as u32));
            start = end;
        }
        Some(dict)
    }

    /// Voxel size (world or NDC units).
    pub fn voxel_size(&self) -> f32 {
        self.voxel
    }

    pub fn num_points(&self) -> usize {
        self.entries.len()
    }

    pub fn num_cells(&self) -> usize {
        self.cells.len()
    }

    fn cell(&self, p: Vec3) -> [i64; 3] {
        let c = ((p - self.min) / self.voxel).floor();
        [c.x as i64, c.y as i64, c.z as i64]
    }

    fn key(&self, c: [i64; 3]) -> u64 {
        (c[0] as u64 * self.dims[1] + c[1] as u64) * self.dims[2] + c[2] as u64
    }

    fn inside(&self, c: [i64; 3]) -> bool {
        (0..3).all(|a| c[a] >= 0 && (c[a] as u64) < self.dims[a])
    }

    /// The acceptable reference point whose ray passes nearest to `p` (seen along `dir`).
    fn lookup(&self, p: Vec3, dir: Vec3, params: &RegisterParams) -> Option<&Entry> {
        let c = self.cell(p);
        let r = if params.neighbours { 1 } else { 0 };
        let max_d2 = (params.max_dist_voxels * self.voxel).powi(2);
        let mut best: Option<(f32, &Entry)> = None;
        for dx in -r..=r {
            for dy in -r..=r {
                for dz in -r..=r {
                    let n = [c[0] + dx, c[1] + dy, c[2] + dz];
                    if !self.inside(n) {
                        continue;
                    }
                    let Some(&(at, len)) = self.cells.get(&self.key(n)) else { continue };
                    for e in &self.entries[at as usize..(at + len) as usize] {
                        if e.dir.dot(dir) <= params.cos_threshold {
                            continue;
                        }
                        if e.point.distance_squared(p) > max_d2 {
                            continue;
                        }
                        let v = p - e.origin;
                        let off_ray = (v - v.dot(e.ray_dir) * e.ray_dir).length_squared();
                        if best.is_none_or(|(b, _)| off_ray < b) {
                            best = Some((off_ray, e));
                        }
                    }
                }
            }
        }
        best.map(|(_, e)| e)
    }
}

/// The registered pixels of one training view.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ViewRegistration {
    pub width: u32,
    pub height: u32,
    /// Row-major pixel indices, ascending.
    pub pixels: Vec<u32>,
    /// Stylized colour per registered pixel.
    pub colours: Vec<[f32; 3]>,
    /// Which reference each colour came from.
    pub reference: Vec<u16>,
    /// Pixels of the view with a surface point (the denominator of coverage).
    pub hits: u32,
}

impl ViewRegistration {
    /// The registration of a view when nothing could be registered.
    pub fn nothing_registered(view: &Surface) -> Self {
        Self {
            width: view.width as u32,
            height: view.height as u32,
            hits: view.num_hits() as u32,
            ..Default::default()
        }
    }

    /// Registered pixels over pixels with a surface point.
    pub fn fraction_of_hits(&self) -> f32 {
        if self.hits == 0 { 0.0 } else { self.pixels.len() as f32 / self.hits as f32 }
    }
}

/// Registers one training view against the dictionary (parallel over rows).
pub fn register_view(dict: &Dictionary, view: &Surface, params: &RegisterParams) -> ViewRegistration {
    let rows: Vec<Vec<(u32, [f32; 3], u16)>> = (0..view.height)
        .into_par_iter()
        .map(|y| {
            let mut out = Vec::new();
            for x in 0..view.width {
                let i = y * view.width + x;
                if let Some(p) = view.points[i]
                    && let Some(e) = dict.lookup(p, view.dirs[i], params)
                {
                    out.push((i as u32, e.colour, e.reference as u16));
                }
            }
            out
        })
        .collect();
    let mut reg = ViewRegistration {
        width: view.width as u32,
        height: view.height as u32,
        hits: view.num_hits() as u32,
        ..Default::default()
    };
    for (p, c, r) in rows.into_iter().flatten() {
        reg.pixels.push(p);
        reg.colours.push(c);
        reg.reference.push(r);
    }
    reg
}

/// The median distance between the 3D points of horizontally and vertically
/// adjacent reference pixels (both hits): the spacing of stored points.
pub fn median_footprint(references: &[Reference]) -> Option<f32> {
    let mut d = Vec::new();
    for r in references {
        let (w, h) = (r.surface.width, r.surface.height);
        let pts = &r.surface.points;
        for y in 0..h {
            for x in 0..w {
                let Some(p) = pts[y * w + x] else { continue };
                if x + 1 < w
                    && let Some(q) = pts[y * w + x + 1]
                {
                    d.push(p.distance(q));
                }
                if y + 1 < h
                    && let Some(q) = pts[(y + 1) * w + x]
                {
                    d.push(p.distance(q));
                }
            }
        }
    }
    if d.is_empty() {
        return None;
    }
    let mid = d.len() / 2;
    Some(*d.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1)
}

/// 3x3 binary erosion, `iterations` times (pixels outside the image count as empty).
pub fn erode(mask: &[bool], width: usize, height: usize, iterations: usize) -> Vec<bool> {
    let mut cur = mask.to_vec();
    for _ in 0..iterations {
        let prev = cur.clone();
        for y in 0..height {
            for x in 0..width {
                let mut all = true;
                'n: for dy in -1i64..=1 {
                    for dx in -1i64..=1 {
                        let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                        if nx < 0
                            || ny < 0
                            || nx >= width as i64
                            || ny >= height as i64
                            || !prev[ny as usize * width + nx as usize]
                        {
                            all = false;
                            break 'n;
                        }
                    }
                }
                cur[y * width + x] = all;
            }
        }
    }
    cur
}
