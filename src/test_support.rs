//! What the library's own unit tests share (`#[cfg(test)]`): the backend
//! under test (`REFNPR_BACKEND`, flex when unset), float tolerances, and
//! the small grids the kernels are checked on against the Burn graph.

use burn::tensor::Device;
use glam::Vec3;

use crate::field::grid::{GridGeometry, RadianceGrid};
use crate::field::march::MarchParams;
use crate::scene::camera::{Camera, Intrinsics, Ray, look_at};
use crate::scene::sh;
use crate::util::backend::BackendKind;

pub fn backend() -> BackendKind {
    BackendKind::from_env().expect("REFNPR_BACKEND names a backend")
}

pub fn device() -> Device {
    backend().device()
}

/// Tolerance for float comparisons: wgpu runs f32 kernels with other reduction orders.
pub fn tol(cpu: f32) -> f32 {
    if backend() == BackendKind::Wgpu { cpu * 10.0 } else { cpu }
}

/// The largest difference relative to the reference's largest value.
pub fn max_rel_err(ours: &[f32], reference: &[f32]) -> f32 {
    assert_eq!(ours.len(), reference.len());
    let scale = reference.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let diff = ours.iter().zip(reference).fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    diff / scale.max(1e-12)
}

pub fn params(step: f32) -> MarchParams {
    MarchParams { step, sigma_threshold: 0.0, stop_threshold: 1e-7, ..MarchParams::default() }
}

fn axis_ray(o: Vec3, d: Vec3) -> Ray {
    Ray { origin: o, dir: d.normalize(), view_dir: d.normalize() }
}

/// A sparse 6^3 grid of SH degree 2 (every third lattice point left out),
/// densities from -1 to `max_density`, and 40 rays that hit, graze and miss it.
pub fn sparse_degree2_grid(max_density: f32) -> (RadianceGrid, Vec<f32>, Vec<f32>, Vec<Ray>) {
    let geo = GridGeometry::new([6; 3], Vec3::splat(-1.0), Vec3::splat(1.0));
    let nb = sh::num_basis(2);
    let coords: Vec<u32> = (0..geo.num_points() as u32).filter(|i| i % 3 != 1).collect();
    let n = coords.len();
    let dens: Vec<f32> = (0..n).map(|i| -1.0 + max_density * ((i * 7919) % 13) as f32 / 13.0).collect();
    let shd: Vec<f32> = (0..n * 3 * nb).map(|i| 0.6 * ((((i * 104_729) % 17) as f32 / 17.0) - 0.5)).collect();
    let grid = RadianceGrid::from_rows(geo, 2, coords, dens.clone(), shd.clone(), &device());
    let rays = (0..40)
        .map(|i| {
            let o = Vec3::new(-2.5, -1.8 + 0.09 * i as f32, 1.9 - 0.1 * i as f32);
            axis_ray(o, Vec3::new(1.0, 0.2 + 0.01 * i as f32, -0.6 + 0.04 * i as f32))
        })
        .collect();
    (grid, dens, shd, rays)
}

/// A square camera of `size` pixels looking at the origin.
pub fn test_camera(size: u32) -> Camera {
    Camera::new(Intrinsics::from_fov_x(size, size, 0.8), look_at(Vec3::new(0.3, 0.5, 2.6), Vec3::ZERO, Vec3::Y))
}

/// A fresh, empty folder under the system's temp dir, unique to this process and `name`.
pub fn temp_dir(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("refnpr-test-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir
}
