//! Helpers shared by the integration tests.
#![allow(dead_code)]

use burn::tensor::Device;
use refnpr::BackendKind;
use refnpr::photo::config::TrainConfig;
use refnpr::scene::data::DatasetKind;
use std::path::PathBuf;

/// The backend under test: `REFNPR_BACKEND` (flex when unset).
pub fn backend() -> BackendKind {
    BackendKind::from_env().expect("REFNPR_BACKEND names a backend")
}

pub fn device() -> Device {
    backend().device()
}

/// A fresh temporary folder, removed when dropped.
pub struct TempDir(pub PathBuf);

impl TempDir {
    pub fn new(tag: &str) -> Self {
        use std::sync::atomic::{AtomicUsize, Ordering};
        static N: AtomicUsize = AtomicUsize::new(0);
        let p = std::env::temp_dir().join(format!(
            "refnpr-test-{tag}-{}-{}",
            std::process::id(),
            N.fetch_add(1, Ordering::SeqCst)
        ));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap();
        Self(p)
    }
    pub fn path(&self) -> &std::path::Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Tolerance for float comparisons: wgpu runs f32 kernels with other reduction orders.
pub fn tol(cpu: f32) -> f32 {
    if backend() == BackendKind::Wgpu { cpu * 10.0 } else { cpu }
}

/// Every pixel ray of every view of an NDC dataset stays inside the grid's
/// box from the near plane (z = -1) to infinity (z = 1).
pub fn assert_ndc_rays_inside_box(ds: &refnpr::scene::data::Dataset) {
    let ndc = ds.ndc.expect("an NDC dataset");
    let eps = 1e-4;
    for v in ds.train.iter().chain(&ds.test) {
        for r in v.camera.rays(Some(&ndc)) {
            let far = r.origin + r.dir * ((1.0 - r.origin.z) / r.dir.z);
            for p in [r.origin, far] {
                assert!(
                    p.cmpge(ds.bbox_min - eps).all() && p.cmple(ds.bbox_max + eps).all(),
                    "{}: NDC point {p:?} outside the box {:?}..{:?}",
                    v.name,
                    ds.bbox_min,
                    ds.bbox_max
                );
            }
        }
    }
}

/// `x` with coordinate `i` moved by `+h` and by `-h`.
pub fn perturbed(x: &[f32], i: usize, h: f32) -> (Vec<f32>, Vec<f32>) {
    let (mut plus, mut minus) = (x.to_vec(), x.to_vec());
    plus[i] += h;
    minus[i] -= h;
    (plus, minus)
}

/// The central finite difference (loss(x + h e_i) - loss(x - h e_i)) / 2h.
pub fn central_difference(x: &[f32], i: usize, h: f32, loss: impl Fn(&[f32]) -> f64) -> f64 {
    let (plus, minus) = perturbed(x, i, h);
    (loss(&plus) - loss(&minus)) / (2.0 * h as f64)
}

/// The Blender defaults cut down for a quick fit in the tests: `coarse`³
/// voxels upsampled to `fine`³ at step `upsample_at` (as written: the grid
/// does not follow the images), SH degree 1, `steps` steps of `batch_rays`
/// rays, a 20-step learning-rate ramp, one checkpoint.
pub fn quick_blender_config(
    coarse: usize,
    fine: usize,
    upsample_at: usize,
    steps: usize,
    batch_rays: usize,
) -> TrainConfig {
    let mut c = TrainConfig::for_kind(DatasetKind::Blender);
    c.grid.initial_res = [coarse; 3];
    c.grid.upsample_steps = vec![upsample_at];
    c.grid.upsample_res = vec![[fine; 3]];
    c.grid.voxels_per_pixel = 0.0;
    c.grid.sh_degree = 1;
    c.optim.steps = steps;
    c.optim.batch_rays = batch_rays;
    c.optim.lr_delay_steps = 20;
    c.checkpoint_every = steps;
    c
}
