//! Renderer throughput benchmark (`refnpr bench`): rays per second of the
//! forward pass and of forward + backward, on a synthetic scene at a given
//! resolution. A benchmark, not a test: it reports medians, asserts nothing.

use crate::backend::BackendKind;
use crate::camera::{Camera, Intrinsics, look_at};
use crate::grid::{GridGeometry, RadianceGrid};
use crate::render::{self, BatchTensors, MarchParams};
use crate::sh;
use crate::tensor_util::{floats, indices, to_vec};
use anyhow::Result;
use glam::Vec3;
use serde::Serialize;
use std::time::Instant;

/// One benchmark measurement.
#[derive(Debug, Clone, Serialize)]
pub struct BenchResult {
    pub backend: String,
    pub res: usize,
    pub rays: usize,
    pub active_voxels: usize,
    pub samples_per_ray: f64,
    pub forward_rays_per_s: f64,
    pub forward_backward_rays_per_s: f64,
    pub repeats: usize,
}

/// A grid holding a textured solid sphere of radius 0.6 (density 40) in
/// [-1,1]^3 at resolution `res`, SH degree 2; only the sphere and a
/// one-voxel shell own rows, as after pruning.
pub fn sphere_grid(res: usize, device: &burn::tensor::Device) -> RadianceGrid {
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

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// Measures forward and forward+backward throughput for `rays` rays of a
/// 2.2-unit-away camera (each ray chunk is one batch).
pub fn renderer_throughput(backend: BackendKind, res: usize, rays: usize, repeats: usize) -> Result<BenchResult> {
    let device = backend.device();
    let grid = sphere_grid(res, &device);
    let side = (rays as f32).sqrt().ceil() as u32;
    let cam = Camera::new(Intrinsics::from_fov_x(side, side, 0.9), look_at(Vec3::new(2.2, 1.0, 0.8), Vec3::ZERO, Vec3::Z));
    let all = cam.rays(None);
    let batch_rays = &all[..rays.min(all.len())];
    let params = MarchParams::default();
    let (dens, shv) = (grid.density.clone(), grid.sh.clone());
    let mut fwd = Vec::new();
    let mut fb = Vec::new();
    let mut samples = 0;
    for rep in 0..repeats + 1 {
        // Forward: sample generation + compositing, read back.
        let t = Instant::now();
        let b = render::generate_samples(&grid, batch_rays, &params);
        let bt = BatchTensors::new(&b, None, &device);
        let out = render::composite(dens.clone(), shv.clone(), &bt, [1.0; 3]);
        let _ = to_vec(out.rgb);
        let f_s = t.elapsed().as_secs_f64();
        samples = b.num_samples();
        // Forward + backward as a training step does it (touched rows as leaves).
        let t = Instant::now();
        let b = render::generate_samples(&grid, batch_rays, &params);
        let mut mark = Vec::new();
        let rows = crate::train::touched_rows(grid.num_rows(), &b.corner_rows, &mut mark);
        let bt = BatchTensors::new(&b, Some(&|r: i32| mark[r as usize]), &device);
        let idx = indices(rows, &device);
        let ld = dens.clone().select(0, idx.clone()).autodiff().require_grad();
        let ls = shv.clone().select(0, idx).autodiff().require_grad();
        let out = render::composite(ld.clone(), ls.clone(), &bt, [1.0; 3]);
        let n = batch_rays.len();
        let target = floats(vec![0.5; n * 3], [n, 3], &device);
        let d = out.rgb - target;
        let grads = (d.clone() * d).mean().backward();
        let _ = to_vec(ld.grad(&grads).expect("density grad"));
        let _ = to_vec(ls.grad(&grads).expect("sh grad"));
        let fb_s = t.elapsed().as_secs_f64();
        if rep > 0 {
            // The first repetition warms up kernels and allocators.
            fwd.push(n as f64 / f_s);
            fb.push(n as f64 / fb_s);
        }
    }
    Ok(BenchResult {
        backend: backend.to_string(),
        res,
        rays: batch_rays.len(),
        active_voxels: grid.num_rows(),
        samples_per_ray: samples as f64 / batch_rays.len() as f64,
        forward_rays_per_s: median(fwd),
        forward_backward_rays_per_s: median(fb),
        repeats,
    })
}
