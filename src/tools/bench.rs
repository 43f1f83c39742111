//! Benchmarks, not tests: they report medians and assert nothing.
//! - `refnpr bench`: renderer rays per second (forward, forward + backward) on
//!   a synthetic scene at a given grid resolution;
//! - `refnpr bench-vgg`: VGG16 forward and forward + backward milliseconds per
//!   image size, the memory of forward + backward, and onnxruntime's CPU
//!   forward on the same input in the same run as a yardstick.

use crate::field::composite::{BatchTensors, composite};
use crate::field::grid::sphere_grid;
use crate::field::march::{MarchParams, generate_samples};
use crate::field::optim::RowSubset;
use crate::scene::camera::{Camera, Intrinsics, look_at};
use crate::util::backend::BackendKind;
use crate::util::memory::{peak_rss_mb, proc_status_mb, reset_peak_rss};
use crate::util::tensor::{floats, indices, to_vec};
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
    let cam =
        Camera::new(Intrinsics::from_fov_x(side, side, 0.9), look_at(Vec3::new(2.2, 1.0, 0.8), Vec3::ZERO, Vec3::Z));
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
        let b = generate_samples(&grid, batch_rays, &params);
        let bt = BatchTensors::new(&b, None, &device);
        let out = composite(dens.clone(), shv.clone(), &bt, [1.0; 3]);
        let _ = to_vec(out.rgb);
        let f_s = t.elapsed().as_secs_f64();
        samples = b.num_samples();
        // Forward + backward as a training step does it (touched rows as leaves).
        let t = Instant::now();
        let b = generate_samples(&grid, batch_rays, &params);
        let subset = RowSubset::of(grid.num_rows(), &b.corner_rows);
        let bt = BatchTensors::for_gradients(&b, Some(&|r: i32| subset.local(r)), &device);
        let idx = indices(subset.rows().to_vec(), &device);
        let ld = dens.clone().select(0, idx.clone()).autodiff().require_grad();
        let ls = shv.clone().select(0, idx).autodiff().require_grad();
        let out = composite(ld.clone(), ls.clone(), &bt, [1.0; 3]);
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

/// One VGG16 measurement (milliseconds are medians over the repeats).
#[derive(Debug, Clone, Serialize)]
pub struct VggBenchResult {
    pub backend: String,
    pub width: usize,
    pub height: usize,
    pub forward_ms: f64,
    pub forward_backward_ms: f64,
    /// Peak resident memory during one forward + backward, above the resident
    /// memory before it (Linux; None elsewhere).
    pub forward_backward_peak_mb: Option<f64>,
    /// How the forward pass ran.
    pub forward: crate::vgg::VggForward,
    pub warmup: usize,
    pub repeats: usize,
}

/// VGG16 on a fixed-seed `[1, 3, height, width]` uniform image: forward (all
/// 13 maps read back) and forward + backward of the sum of every relu3_x,
/// relu4_x and relu5_x map (TCM and colour layers) to the input image.
pub fn vgg_timing(
    backend: BackendKind,
    width: usize,
    height: usize,
    warmup: usize,
    repeats: usize,
    forward: Option<crate::vgg::VggForward>,
) -> Result<VggBenchResult> {
    anyhow::ensure!(repeats >= 1, "repeats must be at least 1");
    use crate::vgg::{Vgg16, VggLayer};
    use burn::tensor::{Distribution, Tensor};
    // Forward on the plain backend, forward + backward on its autodiff twin.
    let plain = backend.device();
    let device = backend.autodiff_device();
    let forward = forward.unwrap_or_default();
    let vgg_plain = Vgg16::load(&plain).with_forward(forward);
    let vgg = Vgg16::load(&device).with_forward(forward);
    plain.seed(0);
    let image_plain: Tensor<4> = Tensor::random([1, 3, height, width], Distribution::Uniform(0.0, 1.0), &plain);
    let image = Tensor::<4>::from_data(image_plain.to_data(), &device);
    let loss_layers: Vec<VggLayer> = VggLayer::TCM.iter().chain(VggLayer::COLOUR.iter()).copied().collect();
    let mut fwd = Vec::new();
    let mut fb = Vec::new();
    let mut peak = None;
    for rep in 0..warmup + repeats {
        let t = Instant::now();
        let maps = vgg_plain.features(image_plain.clone(), &VggLayer::ALL)?;
        for (_, m) in maps.iter() {
            let _ = to_vec(m.clone().sum());
        }
        let f_s = t.elapsed().as_secs_f64();
        drop(maps);
        let before = proc_status_mb("VmRSS:");
        let measured = rep + 1 == warmup + repeats && reset_peak_rss();
        let t = Instant::now();
        let x = image.clone().require_grad();
        let maps = vgg.features(x.clone(), &loss_layers)?;
        let loss = loss_layers.iter().map(|&l| maps.get(l).clone().mean()).reduce(|a, b| a + b).expect("layers");
        let grads = loss.backward();
        let _ = to_vec(x.grad(&grads).expect("image gradient"));
        let fb_s = t.elapsed().as_secs_f64();
        if measured {
            peak = peak_rss_mb().zip(before).map(|(p, b)| p - b);
        }
        if rep >= warmup {
            // Warm-up repetitions compile kernels and fill allocators.
            fwd.push(f_s * 1e3);
            fb.push(fb_s * 1e3);
        }
    }
    Ok(VggBenchResult {
        backend: backend.to_string(),
        width,
        height,
        forward_ms: median(fwd),
        forward_backward_ms: median(fb),
        forward_backward_peak_mb: peak,
        forward,
        warmup,
        repeats,
    })
}

/// onnxruntime's forward milliseconds (median) on the same input size, via
/// `models/bench_onnxruntime.py`; an error says how to install it.
pub fn onnxruntime_forward_ms(width: usize, height: usize, repeats: usize) -> Result<f64> {
    let python = std::env::var("REFNPR_PYTHON").unwrap_or_else(|_| "python3".to_string());
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models/bench_onnxruntime.py");
    let out = std::process::Command::new(&python)
        .arg(&script)
        .args(["--width", &width.to_string(), "--height", &height.to_string(), "--repeats", &repeats.to_string()])
        .output()
        .map_err(|e| anyhow::anyhow!("cannot run {python}: {e}"))?;
    if !out.status.success() {
        anyhow::bail!(
            "{} failed (pip install onnxruntime onnx numpy?): {}",
            script.display(),
            String::from_utf8_lossy(&out.stderr).lines().last().unwrap_or("")
        );
    }
    let v: serde_json::Value = serde_json::from_slice(&out.stdout)?;
    v["forward_ms_median"].as_f64().ok_or_else(|| anyhow::anyhow!("unexpected output from {}", script.display()))
}

/// One phase of a short stylization: its steps and what one costs.
#[derive(Debug, Clone, Serialize)]
pub struct PhaseCost {
    /// `refit`, `image_epochs` or `smooth_update`.
    pub phase: String,
    pub steps: usize,
    /// Median and mean wall seconds of one step.
    pub median_step_seconds: f64,
    pub mean_step_seconds: f64,
    /// Mean seconds per step of each part of a step (`util::profile`).
    pub parts: Vec<crate::util::profile::PartTime>,
}

/// `refnpr bench-stylize`: a short stylization's cost per step and phase.
#[derive(Debug, Clone, Serialize)]
pub struct StylizeBenchResult {
    pub method: String,
    pub backend: String,
    pub views: usize,
    pub image_size: [usize; 2],
    pub phases: Vec<PhaseCost>,
    /// Seconds of the whole phases (registration, refit, content, image_epochs, smooth_update).
    pub seconds: std::collections::BTreeMap<String, f64>,
    pub total_seconds: f64,
    pub peak_rss_mb: Option<f64>,
}

/// Runs `job` shortened to `refit_epochs` ray epochs and `image_epochs`
/// image epochs (Ref-NPR: the last of them the smooth update), no resume
/// points and no test renders, and reports the cost of one step of each
/// phase. Costs per step do not depend on the schedule's length, so the
/// full schedule's time is about steps x these figures.
pub fn stylize_timing(
    mut job: crate::stylize::StylizeJob,
    refit_epochs: f32,
    image_epochs: usize,
    progress: &dyn crate::util::progress::Progress,
) -> Result<StylizeBenchResult> {
    use crate::stylize::StepKind;
    anyhow::ensure!(image_epochs >= 1, "bench-stylize needs at least one image epoch");
    anyhow::ensure!(refit_epochs > 0.0, "bench-stylize needs a refit (--refit-epochs > 0)");
    let s = &mut job.config.schedule;
    s.ray_epochs = refit_epochs;
    s.image_epochs = image_epochs;
    s.smooth_fraction = if image_epochs >= 2 { 1.0 / image_epochs as f32 } else { 0.0 };
    s.checkpoint_every = 0;
    job.render_test = false;
    job.config.validate()?;
    let report = crate::stylize::run::run_stylize(&job, progress)?;
    let kinds = [("refit", StepKind::Refit), ("image_epochs", StepKind::Image), ("smooth_update", StepKind::Smooth)];
    let phases = kinds
        .iter()
        .filter_map(|(name, kind)| {
            let times: Vec<f64> = report.curve.iter().filter(|p| p.phase == *kind).map(|p| p.seconds as f64).collect();
            let parts = report.step_profiles.get(*name).filter(|_| !times.is_empty())?;
            let steps = times.len();
            Some(PhaseCost {
                phase: name.to_string(),
                steps: times.len(),
                median_step_seconds: median(times.clone()),
                mean_step_seconds: times.iter().sum::<f64>() / steps as f64,
                parts: parts.iter().map(|p| p.per_step(steps)).collect(),
            })
        })
        .collect();
    Ok(StylizeBenchResult {
        method: report.method.to_string(),
        backend: report.backend,
        views: report.views,
        image_size: report.image_size,
        phases,
        seconds: report.seconds,
        total_seconds: report.total_seconds,
        peak_rss_mb: report.peak_rss_mb,
    })
}
