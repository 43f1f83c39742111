//! A field as 3D Gaussian splats in the standard 3DGS PLY layout (`x y z`,
//! `nx ny nz`, `f_dc_0..2`, `f_rest_*`, `opacity` as a logit, `scale_0..2`
//! as logs, `rot_0..3` as a w-first quaternion), which SuperSplat, Brush,
//! PlayCanvas, spark and the three.js viewers open.
//!
//! Why one splat per lattice point reproduces the render: the renderer
//! interpolates density trilinearly, so along any line the field is a sum
//! of tent functions one voxel wide per side, one per lattice point. A
//! splat replaces each tent by the Gaussian of the same second moment
//! (standard deviation `voxel / sqrt(6)` per axis) and the point's
//! absorption by the opacity a ray through its centre gets from the tent,
//! `1 - exp(-sigma * voxel)`: along a row of equal points the splats'
//! alpha compositing gives the renderer's `exp(-sum sigma delta)`. The
//! colour is the point's own SH row: refnpr's basis and its `+ 0.5` offset
//! are 3DGS's, coefficient for coefficient. Forward-facing (NDC) fields are
//! carried to world space: the centre through the inverse warp, the
//! Gaussian through its Jacobian (an anisotropic, rotated splat).
//!
//! What it drops: points whose opacity is below 1/255 (3DGS rasterisers
//! skip those contributions too), and points buried inside opaque matter
//! (every axis direction blocked by neighbours whose optical depth exceeds
//! `ln 1000`: no ray reaches them with more than 0.1 % of its light).

use glam::{Mat3, Quat, Vec3};

use crate::export::ply::{Ply, Scalar};
use crate::field::grid::RadianceGrid;
use crate::scene::camera::{Camera, NdcParams, from_ndc};
use crate::scene::sh;
use anyhow::{Result, bail};

/// Choices of a splat export.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SplatOptions {
    /// SH degree written (at most the field's; lower degrees drop the
    /// higher coefficients, the L2-nearest lower-degree colour). None: the field's.
    pub sh_degree: Option<u32>,
    /// Keep at most this many splats, the most opaque first. None: all.
    pub max_splats: Option<usize>,
    /// Drop splats below this opacity.
    pub min_opacity: f32,
    /// Drop splats buried inside opaque matter.
    pub drop_buried: bool,
    /// The splats' size relative to the tent-matched Gaussian.
    pub scale: f32,
    /// The screen-space blur, in pixels squared, that the target viewer
    /// adds to every splat without compensating its opacity (0.3 in 3DGS's
    /// rasteriser and the viewers that copy it; 0: none). The blur spreads
    /// each splat's opacity over a larger footprint, so sub-pixel splats
    /// pile up too dark; given it, each opacity is scaled by
    /// `s^2 / (s^2 + blur)` (`s`: the splat's size in pixels at the median
    /// distance from the cameras passed to [`splats_of`]), what an
    /// antialiased viewer does by itself. Exact at those cameras'
    /// resolution; nearer or larger views see the splats thinner.
    pub viewer_blur: f32,
}

impl Default for SplatOptions {
    fn default() -> Self {
        Self {
            sh_degree: None,
            max_splats: None,
            min_opacity: 1.0 / 255.0,
            drop_buried: true,
            scale: 1.0,
            viewer_blur: 0.0,
        }
    }
}

/// Splats as plain arrays (world space).
#[derive(Debug, Clone, Default)]
pub struct Splats {
    pub sh_degree: u32,
    pub position: Vec<Vec3>,
    /// Standard deviations along the rotated axes.
    pub scale: Vec<Vec3>,
    pub rotation: Vec<Quat>,
    /// In (0, 1).
    pub opacity: Vec<f32>,
    /// `3 * num_basis` coefficients per splat, channel-major (refnpr's row layout).
    pub sh: Vec<f32>,
}

impl Splats {
    pub fn len(&self) -> usize {
        self.position.len()
    }

    pub fn is_empty(&self) -> bool {
        self.position.is_empty()
    }
}

/// A standard deviation of the Gaussian with a tent's second moment: a
/// tent of half-width `v` has variance `v^2 / 6`.
const TENT_TO_SIGMA: f32 = 0.408_248_3; // 1 / sqrt(6)

/// Optical depth past which a neighbour blocks a point (`ln 1000`).
const BURIED_DEPTH: f32 = 6.907_755;

/// The splats of `grid` (`ndc`: the warp its lattice lives in, for
/// forward-facing scenes); `cameras` are the views `viewer_blur` is
/// compensated for (unused without it).
pub fn splats_of(
    grid: &RadianceGrid,
    ndc: Option<&NdcParams>,
    options: &SplatOptions,
    cameras: &[Camera],
) -> Result<Splats> {
    if options.viewer_blur > 0.0 && cameras.is_empty() {
        bail!("compensating a viewer's blur needs the cameras it is measured at");
    }
    let degree = options.sh_degree.unwrap_or(grid.sh_degree);
    if degree > grid.sh_degree {
        bail!("the field has SH degree {}; a splat file of degree {degree} would only pad zeros", grid.sh_degree);
    }
    let geo = grid.geometry;
    let voxel = geo.voxel_size();
    // Along a ray through the centre the tent integrates to one voxel; an
    // NDC lattice is marched along its depth axis (rays run near +-z).
    let crossing = if ndc.is_some() { voxel.z } else { voxel.min_element() };
    let optical: Vec<f32> = grid.density_cpu.iter().map(|&d| d.max(0.0) * crossing).collect();
    let mut kept: Vec<usize> = (0..grid.num_rows())
        .filter(|&r| 1.0 - (-optical[r]).exp() >= options.min_opacity)
        .filter(|&r| !options.drop_buried || !is_buried(grid, &optical, r))
        .collect();
    if let Some(max) = options.max_splats {
        // Most opaque first; ties by row, so the choice is deterministic.
        kept.sort_by(|&a, &b| optical[b].total_cmp(&optical[a]).then(a.cmp(&b)));
        kept.truncate(max);
        kept.sort_unstable();
    }
    let (rows_basis, out_basis) = (grid.num_basis(), sh::num_basis(degree));
    let sh_rows = grid.sh_cpu();
    let mut s = Splats { sh_degree: degree, ..Default::default() };
    for &r in &kept {
        let ijk = geo.unflat(grid.coords[r] as usize);
        let centre = geo.grid_to_world(Vec3::new(ijk[0] as f32, ijk[1] as f32, ijk[2] as f32));
        let sigma = voxel * TENT_TO_SIGMA * options.scale;
        let (position, scale, rotation) = match ndc {
            None => (centre, sigma, Quat::IDENTITY),
            Some(p) => match warped_gaussian(centre, sigma, p) {
                Some(g) => g,
                None => continue, // at the NDC far plane: infinitely far
            },
        };
        s.position.push(position);
        s.scale.push(scale);
        s.rotation.push(rotation);
        let alpha = 1.0 - (-optical[r]).exp();
        s.opacity.push(if options.viewer_blur > 0.0 {
            let pixels = scale.element_sum() / 3.0 * median_pixels_per_unit(position, cameras);
            alpha * pixels * pixels / (pixels * pixels + options.viewer_blur)
        } else {
            alpha
        });
        for ch in 0..3 {
            let row = &sh_rows[r * 3 * rows_basis + ch * rows_basis..][..out_basis];
            s.sh.extend_from_slice(row);
        }
    }
    Ok(s)
}

/// Pixels per world unit at `p`, the median over `cameras` (focal length
/// over distance).
fn median_pixels_per_unit(p: Vec3, cameras: &[Camera]) -> f32 {
    let mut v: Vec<f32> = cameras.iter().map(|c| c.intrinsics.fx / (p - c.position()).length().max(1e-6)).collect();
    v.sort_by(f32::total_cmp);
    v[v.len() / 2]
}

/// Whether every axis direction from row `r`'s point is blocked: the
/// optical depth of the next three points along it reaches `BURIED_DEPTH`.
fn is_buried(grid: &RadianceGrid, optical: &[f32], r: usize) -> bool {
    let geo = &grid.geometry;
    let ijk = geo.unflat(grid.coords[r] as usize);
    (0..3).all(|axis| {
        [-1i64, 1].iter().all(|&dir| {
            let mut depth = 0.0;
            for k in 1..=3i64 {
                let mut p = [ijk[0] as i64, ijk[1] as i64, ijk[2] as i64];
                p[axis] += dir * k;
                if p[axis] < 0 || p[axis] >= geo.res[axis] as i64 {
                    return false; // the box edge: open to the outside
                }
                let row = grid.links[geo.flat(p[0] as usize, p[1] as usize, p[2] as usize)];
                if row >= 0 {
                    depth += optical[row as usize];
                }
            }
            depth >= BURIED_DEPTH
        })
    })
}

/// An axis-aligned Gaussian in NDC space (centre, standard deviations)
/// carried to world space: the centre through `from_ndc`, the covariance
/// through the warp's Jacobian there, `J S^2 J^T`, as scales and a rotation.
fn warped_gaussian(centre: Vec3, sigma: Vec3, p: &NdcParams) -> Option<(Vec3, Vec3, Quat)> {
    let world = from_ndc(centre, p)?;
    // from_ndc: (x z / ax, y z / ay, z) with z = 2 near / (q.z - 1).
    let ax = -2.0 * p.focal / p.width;
    let ay = -2.0 * p.focal / p.height;
    let z = world.z;
    let dz = -2.0 * p.near / ((centre.z - 1.0) * (centre.z - 1.0));
    let jacobian = Mat3::from_cols(
        Vec3::new(z / ax, 0.0, 0.0),
        Vec3::new(0.0, z / ay, 0.0),
        Vec3::new(centre.x * dz / ax, centre.y * dz / ay, dz),
    );
    let m = jacobian * Mat3::from_diagonal(sigma);
    let (axes, variances) = symmetric_eigen(m * m.transpose());
    let scale = Vec3::new(variances.x.max(0.0).sqrt(), variances.y.max(0.0).sqrt(), variances.z.max(0.0).sqrt());
    Some((world, scale, Quat::from_mat3(&axes)))
}

/// Eigenvectors (the columns of a rotation) and eigenvalues of a symmetric
/// 3x3 matrix, by cyclic Jacobi rotations (converges in a few sweeps at f32).
fn symmetric_eigen(a: Mat3) -> (Mat3, Vec3) {
    let (mut m, mut v) = (a, Mat3::IDENTITY);
    let at = |m: &Mat3, row: usize, col: usize| m.col(col)[row];
    for _sweep in 0..12 {
        let off = at(&m, 0, 1).powi(2) + at(&m, 0, 2).powi(2) + at(&m, 1, 2).powi(2);
        let diag = at(&m, 0, 0).powi(2) + at(&m, 1, 1).powi(2) + at(&m, 2, 2).powi(2);
        if off <= 1e-14 * diag.max(f32::MIN_POSITIVE) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            let apq = at(&m, p, q);
            if apq.abs() < f32::MIN_POSITIVE {
                continue;
            }
            // The plane rotation J that zeroes entry (p, q) of J^T m J.
            let theta = 0.5 * (2.0 * apq).atan2(at(&m, q, q) - at(&m, p, p));
            let (s, c) = theta.sin_cos();
            let mut j = Mat3::IDENTITY.to_cols_array_2d(); // j[col][row]
            j[p][p] = c;
            j[q][q] = c;
            j[q][p] = s;
            j[p][q] = -s;
            let j = Mat3::from_cols_array_2d(&j);
            m = j.transpose() * m * j;
            v *= j;
        }
    }
    if v.determinant() < 0.0 {
        v.z_axis = -v.z_axis; // a rotation, not a reflection
    }
    (v, Vec3::new(at(&m, 0, 0), at(&m, 1, 1), at(&m, 2, 2)))
}

/// The splats as a 3DGS PLY.
pub fn to_ply(s: &Splats, source: &str) -> Ply {
    let n = s.len();
    let nb = sh::num_basis(s.sh_degree);
    let mut ply = Ply { comments: vec![format!("refnpr splats of {source}")], ..Default::default() };
    let column = |f: &dyn Fn(usize) -> f32| (0..n).map(f).collect::<Vec<f32>>();
    for (a, name) in ["x", "y", "z"].iter().enumerate() {
        ply.add(name, Scalar::Float, column(&|i| s.position[i][a]));
    }
    for name in ["nx", "ny", "nz"] {
        ply.add(name, Scalar::Float, vec![0.0; n]);
    }
    for ch in 0..3 {
        ply.add(&format!("f_dc_{ch}"), Scalar::Float, column(&|i| s.sh[i * 3 * nb + ch * nb]));
    }
    // 3DGS orders the rest coefficients channel by channel, like refnpr's rows.
    for ch in 0..3 {
        for b in 1..nb {
            let name = format!("f_rest_{}", ch * (nb - 1) + b - 1);
            ply.add(&name, Scalar::Float, column(&|i| s.sh[i * 3 * nb + ch * nb + b]));
        }
    }
    ply.add("opacity", Scalar::Float, column(&|i| logit(s.opacity[i])));
    for a in 0..3 {
        ply.add(&format!("scale_{a}"), Scalar::Float, column(&|i| s.scale[i][a].max(1e-12).ln()));
    }
    let wxyz = |q: Quat| [q.w, q.x, q.y, q.z];
    for a in 0..4 {
        ply.add(&format!("rot_{a}"), Scalar::Float, column(&|i| wxyz(s.rotation[i])[a]));
    }
    ply
}

/// The logit 3DGS stores opacity as (capped where its rasterisers cap alpha).
fn logit(alpha: f32) -> f32 {
    let a = alpha.clamp(1e-6, 0.999);
    (a / (1.0 - a)).ln()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::grid::sphere_grid;
    use crate::scene::camera::Ray;
    use crate::scene::camera::to_ndc;

    #[test]
    fn jacobi_recovers_a_rotated_diagonal() {
        let r = Mat3::from_quat(Quat::from_euler(glam::EulerRot::XYZ, 0.3, -0.7, 1.1));
        let a = r * Mat3::from_diagonal(Vec3::new(4.0, 1.0, 0.25)) * r.transpose();
        let (axes, values) = symmetric_eigen(a);
        let back = axes * Mat3::from_diagonal(values) * axes.transpose();
        for (x, y) in back.to_cols_array().iter().zip(a.to_cols_array()) {
            assert!((x - y).abs() < 1e-4, "{back} vs {a}");
        }
        assert!((axes.determinant() - 1.0).abs() < 1e-4);
        let mut sorted = values.to_array();
        sorted.sort_by(f32::total_cmp);
        assert!((sorted[0] - 0.25).abs() < 1e-4 && (sorted[2] - 4.0).abs() < 1e-4);
    }

    #[test]
    fn the_ndc_gaussian_stretches_with_depth_as_the_warp_does() {
        let p = NdcParams { width: 100.0, height: 80.0, focal: 90.0, near: 1.0 };
        // Two NDC points a small step apart in depth map to world points
        // whose distance the warped Gaussian's covariance predicts.
        let centre = Vec3::new(0.1, -0.2, 0.5);
        let (world, scale, rot) = warped_gaussian(centre, Vec3::splat(0.01), &p).unwrap();
        let cov = Mat3::from_quat(rot) * Mat3::from_diagonal(scale * scale) * Mat3::from_quat(rot).transpose();
        let step = Vec3::new(0.0, 0.0, 0.01);
        let moved = from_ndc(centre + step, &p).unwrap() - from_ndc(centre - step, &p).unwrap();
        let predicted_var = cov.mul_vec3(moved.normalize()).dot(moved.normalize());
        let half = moved.length() / 2.0;
        assert!((predicted_var.sqrt() - half).abs() < 0.05 * half, "{} vs {half}", predicted_var.sqrt());
        // The round trip through the forward warp lands on the centre.
        let ray = Ray { origin: Vec3::ZERO, dir: world.normalize(), view_dir: world.normalize() };
        let back = to_ndc(ray, &p);
        assert!((back.origin.x - centre.x).abs() < 1e-3 && (back.origin.y - centre.y).abs() < 1e-3);
    }

    #[test]
    fn a_solid_ball_keeps_its_shell_and_drops_its_core() {
        let device = Default::default();
        let grid = sphere_grid(24, &device);
        let all = splats_of(&grid, None, &SplatOptions { drop_buried: false, ..Default::default() }, &[]).unwrap();
        let shell = splats_of(&grid, None, &SplatOptions::default(), &[]).unwrap();
        assert!(!shell.is_empty() && shell.len() < all.len(), "{} of {}", shell.len(), all.len());
        let budget = splats_of(&grid, None, &SplatOptions { max_splats: Some(10), ..Default::default() }, &[]).unwrap();
        assert_eq!(budget.len(), 10);
        assert!(budget.opacity.iter().all(|&o| o >= *shell.opacity.iter().min_by(|a, b| a.total_cmp(b)).unwrap()));
        let ply = to_ply(&shell, "test");
        let expected = 6 + 3 + 3 * (sh::num_basis(grid.sh_degree) - 1) + 1 + 3 + 4;
        assert_eq!(ply.columns.len(), expected);
        assert!(splats_of(&grid, None, &SplatOptions { sh_degree: Some(3), ..Default::default() }, &[]).is_err());
        // Blur compensation: thinner splats, by s^2 / (s^2 + blur), never thicker.
        let blur = SplatOptions { viewer_blur: 0.3, ..Default::default() };
        assert!(splats_of(&grid, None, &blur, &[]).is_err(), "needs cameras");
        let k = crate::scene::camera::Intrinsics::from_fov_x(64, 64, 0.7);
        let far = Camera::new(k, glam::Mat4::from_translation(Vec3::new(0.0, 0.0, 4.0)));
        let thin = splats_of(&grid, None, &blur, &[far]).unwrap();
        assert_eq!(thin.len(), shell.len());
        let px = shell.scale[0].x * k.fx / (shell.position[0] - far.position()).length();
        let expected = shell.opacity[0] * px * px / (px * px + 0.3);
        assert!((thin.opacity[0] - expected).abs() < 1e-5, "{} vs {expected}", thin.opacity[0]);
    }
}
