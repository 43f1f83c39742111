//! A field's density iso-surface as a coloured triangle mesh.
//!
//! Marching tetrahedra over the lattice (each cell cut into six tetrahedra
//! around its main diagonal, the same cut in every cell, so neighbouring
//! cells' faces agree): no case tables to get wrong, and with vertices keyed
//! by the lattice edge they sit on, the surface is closed wherever the
//! level set is (the lattice is padded with empty points, so the box's
//! faces close it too; not for forward-facing fields, whose box is the
//! view frustum: their surface is open at its edges). Colours are the field's view-independent colour
//! (the SH degree-0 term) of the cell's corners weighted by their density;
//! normals are the
//! area-weighted mean of the faces around each vertex.

use std::collections::HashMap;

use glam::Vec3;

use crate::export::ply::{Ply, Scalar};
use crate::field::grid::RadianceGrid;
use crate::scene::camera::{NdcParams, from_ndc};
use crate::scene::sh;
use anyhow::{Result, bail};

/// A triangle mesh with per-vertex normals and colours (world space).
#[derive(Debug, Clone, Default)]
pub struct Mesh {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    /// sRGB in [0, 1], as refnpr renders it.
    pub colours: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

/// Voxels a fitted surface's density ramps up over: the default level is
/// the density at which this many voxels' crossing absorbs half the light.
/// On lego the three.js renders of the mesh against refnpr's (4 test views)
/// were 20.7 dB at 4 voxels, 19.6 dB at 2 and 14.1 dB at 1 (the level of
/// one voxel leaves holes where a surface is spread over several).
const SURFACE_RAMP_VOXELS: f32 = 4.0;

/// The surface's default level: `ln 2 / (SURFACE_RAMP_VOXELS * voxel)`.
pub fn default_level(grid: &RadianceGrid, ndc: Option<&NdcParams>) -> f32 {
    let v = grid.geometry.voxel_size();
    std::f32::consts::LN_2 / (SURFACE_RAMP_VOXELS * if ndc.is_some() { v.z } else { v.min_element() })
}

/// The six tetrahedra of a cell, as corner numbers (bit 2 = +x, bit 1 = +y,
/// bit 0 = +z, as `GridGeometry::trilinear`), all around the 0-7 diagonal.
const TETRAHEDRA: [[usize; 4]; 6] =
    [[0, 7, 1, 3], [0, 7, 3, 2], [0, 7, 2, 6], [0, 7, 6, 4], [0, 7, 4, 5], [0, 7, 5, 1]];

/// The iso-surface of `grid`'s density (after the ReLU) at `level`.
pub fn mesh_of(grid: &RadianceGrid, ndc: Option<&NdcParams>, level: f32) -> Result<Mesh> {
    let max = grid.density_cpu.iter().fold(0.0f32, |m, &d| m.max(d));
    if grid.num_rows() == 0 || max <= 0.0 {
        bail!("the field is empty (no point has positive density): there is no surface to export");
    }
    if !(level > 0.0 && level < max) {
        bail!("level {level} is outside the field's density range (0, {max}): pick a level inside it");
    }
    let geo = grid.geometry;
    let res = geo.res.map(|r| r as i64);
    // The density at a lattice point, 0 outside the lattice (the padding).
    let value = |p: [i64; 3]| -> f32 {
        if (0..3).any(|a| p[a] < 0 || p[a] >= res[a]) {
            return 0.0;
        }
        let row = grid.links[geo.flat(p[0] as usize, p[1] as usize, p[2] as usize)];
        if row < 0 { 0.0 } else { grid.density_cpu[row as usize].max(0.0) }
    };
    let key = |p: [i64; 3]| ((p[0] + 1) * (res[1] + 2) + p[1] + 1) * (res[2] + 2) + p[2] + 1;
    let mut mesh = Mesh::default();
    let mut on_edge: HashMap<(i64, i64), u32> = HashMap::new();
    let mut lattice_positions = Vec::new();
    // Cells from the padding on (closing the surface at the box's faces),
    // except for a forward-facing field: its box is the view frustum, whose
    // near and side faces cut through the scene and would cap it with walls.
    let first = if ndc.is_some() { 0 } else { -1 };
    let last = |a: usize| if ndc.is_some() { res[a] - 1 } else { res[a] };
    for i in first..last(0) {
        for j in first..last(1) {
            for k in first..last(2) {
                let corner = |c: usize| [i + ((c >> 2) & 1) as i64, j + ((c >> 1) & 1) as i64, k + (c & 1) as i64];
                let values: [f32; 8] = std::array::from_fn(|c| value(corner(c)));
                if values.iter().all(|&v| v > level) || values.iter().all(|&v| v <= level) {
                    continue;
                }
                for tet in TETRAHEDRA {
                    let pts = tet.map(corner);
                    let vals = tet.map(|c| values[c]);
                    let mut vertex = |a: usize, b: usize| -> u32 {
                        let (ka, kb) = (key(pts[a]), key(pts[b]));
                        *on_edge.entry((ka.min(kb), ka.max(kb))).or_insert_with(|| {
                            let t = (level - vals[a]) / (vals[b] - vals[a]);
                            let pa = Vec3::new(pts[a][0] as f32, pts[a][1] as f32, pts[a][2] as f32);
                            let pb = Vec3::new(pts[b][0] as f32, pts[b][1] as f32, pts[b][2] as f32);
                            lattice_positions.push(pa + t * (pb - pa));
                            (lattice_positions.len() - 1) as u32
                        })
                    };
                    let inside: Vec<usize> = (0..4).filter(|&v| vals[v] > level).collect();
                    let outside: Vec<usize> = (0..4).filter(|&v| vals[v] <= level).collect();
                    let mut faces = Vec::new();
                    match inside.len() {
                        1 | 3 => {
                            let (lone, rest) =
                                if inside.len() == 1 { (inside[0], &outside) } else { (outside[0], &inside) };
                            faces.push([vertex(lone, rest[0]), vertex(lone, rest[1]), vertex(lone, rest[2])]);
                        }
                        2 => {
                            let (a, b, c, d) = (inside[0], inside[1], outside[0], outside[1]);
                            let (ac, ad, bc, bd) = (vertex(a, c), vertex(a, d), vertex(b, c), vertex(b, d));
                            faces.push([ac, ad, bd]);
                            faces.push([ac, bd, bc]);
                        }
                        _ => {}
                    }
                    // Outward (towards lower density): away from the inside corners.
                    let centre = |set: &[usize]| {
                        set.iter()
                            .map(|&v| Vec3::new(pts[v][0] as f32, pts[v][1] as f32, pts[v][2] as f32))
                            .sum::<Vec3>()
                            / set.len() as f32
                    };
                    let outward = centre(&outside) - centre(&inside);
                    for f in faces {
                        let [a, b, c] = f.map(|v| lattice_positions[v as usize]);
                        let flip = (b - a).cross(c - a).dot(outward) < 0.0;
                        mesh.triangles.push(if flip { [f[0], f[2], f[1]] } else { f });
                    }
                }
            }
        }
    }
    to_world(grid, ndc, &lattice_positions, &mut mesh);
    Ok(mesh)
}

/// Places the lattice-coordinate vertices in the world (through the NDC
/// warp when there is one: triangles at the far plane are dropped), colours
/// them, and sets the normals.
fn to_world(grid: &RadianceGrid, ndc: Option<&NdcParams>, lattice: &[Vec3], mesh: &mut Mesh) {
    let geo = grid.geometry;
    let nb = grid.num_basis();
    let sh_rows = grid.sh_cpu();
    let mut world = Vec::with_capacity(lattice.len());
    for &g in lattice {
        let p = geo.grid_to_world(g);
        world.push(match ndc {
            None => Some(p),
            Some(params) => from_ndc(p, params),
        });
        mesh.colours.push(colour_at(grid, &sh_rows, nb, g));
    }
    mesh.triangles.retain(|t| t.iter().all(|&v| world[v as usize].is_some()));
    mesh.positions = world.into_iter().map(|p| p.unwrap_or(Vec3::ZERO)).collect();
    set_normals(mesh);
}

/// Each vertex's normal: the area-weighted mean of its triangles' normals.
pub fn set_normals(mesh: &mut Mesh) {
    mesh.normals = vec![Vec3::ZERO; mesh.positions.len()];
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|v| mesh.positions[v as usize]);
        let area_normal = (b - a).cross(c - a); // length = twice the area
        for &v in t {
            mesh.normals[v as usize] += area_normal;
        }
    }
    for n in &mut mesh.normals {
        *n = n.normalize_or_zero();
    }
}

/// The view-independent colour at lattice coordinates `g`: the degree-0
/// coefficients of the cell's corners weighted by trilinear weight times
/// density, `C0 k + 0.5`, clamped to [0, 1]. A vertex sits on the surface's
/// thin outer fringe, whose own colours light never reaches; weighting by
/// density takes the colour of the matter behind it, which a ray sees.
fn colour_at(grid: &RadianceGrid, sh_rows: &[f32], nb: usize, g: Vec3) -> [f32; 3] {
    let (idx, w) = grid.geometry.trilinear(g);
    let (mut sum, mut total) = ([0.0f32; 3], 0.0f32);
    for c in 0..8 {
        let row = grid.links[idx[c]];
        if row >= 0 {
            let weight = w[c] * grid.density_cpu[row as usize].max(0.0);
            for (ch, s) in sum.iter_mut().enumerate() {
                *s += weight * sh_rows[row as usize * 3 * nb + ch * nb];
            }
            total += weight;
        }
    }
    if total <= 0.0 {
        return [0.5; 3]; // no active corner: SH zero, grey
    }
    sum.map(|s| (sh::C0 * s / total + 0.5).clamp(0.0, 1.0))
}

/// The mesh as a PLY (positions, normals, 8-bit sRGB colours, triangles).
pub fn to_ply(mesh: &Mesh, source: &str) -> Ply {
    let mut ply = Ply { comments: vec![format!("refnpr mesh of {source}")], ..Default::default() };
    for (a, name) in ["x", "y", "z"].iter().enumerate() {
        ply.add(name, Scalar::Float, mesh.positions.iter().map(|p| p[a]).collect());
    }
    for (a, name) in ["nx", "ny", "nz"].iter().enumerate() {
        ply.add(name, Scalar::Float, mesh.normals.iter().map(|p| p[a]).collect());
    }
    for (ch, name) in ["red", "green", "blue"].iter().enumerate() {
        ply.add(name, Scalar::UChar, mesh.colours.iter().map(|c| c[ch] * 255.0).collect());
    }
    ply.triangles = mesh.triangles.clone();
    ply
}

/// Each undirected edge's number of triangles: a closed surface has 2 everywhere.
pub fn edge_uses(triangles: &[[u32; 3]]) -> HashMap<(u32, u32), u32> {
    let mut uses = HashMap::new();
    for t in triangles {
        for e in 0..3 {
            let (a, b) = (t[e], t[(e + 1) % 3]);
            *uses.entry((a.min(b), a.max(b))).or_insert(0) += 1;
        }
    }
    uses
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::grid::sphere_grid;

    #[test]
    fn a_ball_gives_a_closed_outward_sphere_of_its_radius() {
        let grid = sphere_grid(24, &Default::default());
        let mesh = mesh_of(&grid, None, 20.0).unwrap();
        assert!(mesh.triangles.len() > 500);
        assert!(edge_uses(&mesh.triangles).values().all(|&n| n == 2), "every edge between two triangles");
        let radii: Vec<f32> = mesh.positions.iter().map(|p| p.length()).collect();
        let mean = radii.iter().sum::<f32>() / radii.len() as f32;
        // Density 40 inside r < 0.6, 0 outside: level 20 sits half a lattice step out.
        assert!((mean - 0.6).abs() < 0.06, "mean radius {mean}");
        let outward = mesh.positions.iter().zip(&mesh.normals).filter(|(p, n)| p.dot(**n) > 0.0).count();
        assert_eq!(outward, mesh.positions.len(), "normals point out");
        // Signed volume of a closed outward mesh is positive, near (4/3) pi r^3.
        let volume: f32 = mesh
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|v| mesh.positions[v as usize]);
                a.dot(b.cross(c)) / 6.0
            })
            .sum();
        assert!((volume / (4.0 / 3.0 * std::f32::consts::PI * mean.powi(3)) - 1.0).abs() < 0.1, "volume {volume}");
        assert!(mesh.colours.iter().flatten().all(|c| (0.0..=1.0).contains(c)));
    }

    #[test]
    fn a_level_outside_the_density_range_is_refused() {
        let grid = sphere_grid(12, &Default::default());
        assert!(mesh_of(&grid, None, 50.0).unwrap_err().to_string().contains("outside the field's density range"));
        assert!(mesh_of(&grid, None, 0.0).is_err());
        assert!(mesh_of(&grid, None, f32::NAN).is_err());
    }
}
