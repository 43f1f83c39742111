//! What the stylization's colour pass costs on one backend, the fused
//! kernel (`kernels::frozen_op`, what `frozen::render_colour` runs on a GPU)
//! against the Burn graph (`frozen::render_colour_graph`), on one training
//! view of a photoreal run: `REFNPR_BACKEND=wgpu cargo run --example
//! colour_costs -- RUN/checkpoint.bin DATA VIEW REPEATS`. It marches the
//! view as a stylization caches it (degree-0 colour, `min_sample_weight`'s
//! default), keeps its lists on the device (`DeviceSamples`, as an image
//! step reads them), warms each path up once, then times REPEATS renders
//! and REPEATS re-renders with a gradient (an image step's two colour
//! passes), each waiting for the device before the clock stops. It prints
//! the medians, kernel launches and host-device traffic of each.
use std::path::PathBuf;

use burn::tensor::Tensor;
use refnpr::field::checkpoint::load_run_view_independent;
use refnpr::field::frozen::{DeviceSamples, FrozenSamples, FrozenTensors, render_colour, render_colour_graph};
use refnpr::field::march::{MarchParams, Marcher};
use refnpr::util::tensor::{floats, to_vec};
use refnpr::util::{device_stats, transfer};
use refnpr::{BackendKind, StylizeConfig};

/// The colour pass as one path draws it.
type Pass = fn(Tensor<2>, &FrozenTensors, [f32; 3]) -> Tensor<2>;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [checkpoint, data, view, repeats] = args.as_slice() else {
        anyhow::bail!("usage: colour_costs CHECKPOINT DATA VIEW REPEATS (backend from REFNPR_BACKEND)");
    };
    let (view, repeats): (usize, usize) = (view.parse()?, repeats.parse::<usize>()?.max(1));
    let backend = BackendKind::from_env()?;
    let device = backend.open(&refnpr::Console::default())?;
    let (ck, dataset) = load_run_view_independent(&PathBuf::from(checkpoint), Some(&PathBuf::from(data)), &device)?;
    let camera = &dataset.train.get(view).ok_or_else(|| anyhow::anyhow!("no training view {view}"))?.camera;
    let cfg = StylizeConfig::default();
    let march = MarchParams { colour_corners: cfg.colour_corners, ..ck.meta.render.march };
    let rays = camera.rays(ck.meta.ndc.as_ref());
    let samples = FrozenSamples::march(&Marcher::new(&ck.grid), &rays, &march, cfg.min_sample_weight);
    let lists = DeviceSamples::upload(&samples, &device);
    let sh = ck.grid.sh.clone();
    let all: Vec<usize> = (0..samples.num_rays).collect();
    let chunks: Vec<FrozenTensors> = lists.gather_chunks(&all, cfg.render_chunk, &sh).map(|(_, _, ft)| ft).collect();
    // A fixed image gradient to inject, as the image losses' would be.
    let grad: Vec<f32> = (0..samples.num_rays * 3).map(|i| ((i * 37) % 17) as f32 / 17.0 - 0.5).collect();
    let grad = floats(grad, [samples.num_rays, 3], &device);
    let bg = ck.meta.background;
    println!(
        "{backend}: view {view}, {} rays, {} samples in {} chunk(s), {} grid rows",
        samples.num_rays,
        samples.num_samples(),
        chunks.len(),
        ck.grid.num_rows()
    );
    let render = |pass: Pass| {
        let parts: Vec<Tensor<2>> = chunks.iter().map(|ft| pass(sh.clone(), ft, bg)).collect();
        let _ = to_vec(Tensor::cat(parts, 0).sum());
    };
    let rerender = |pass: Pass| {
        let mut start = 0;
        let mut total = Tensor::<2>::zeros(sh.dims(), &device);
        for ft in &chunks {
            let leaf = sh.clone().autodiff().require_grad();
            let loss = (pass(leaf.clone(), ft, bg) * grad.clone().narrow(0, start, ft.num_rays)).sum();
            total = total + leaf.grad(&loss.backward()).expect("the colours depend on the SH");
            start += ft.num_rays;
        }
        let _ = to_vec(total.sum());
    };
    for (name, pass) in [("fused kernel", render_colour as Pass), ("graph", render_colour_graph as Pass)] {
        for (what, run) in [("render", &render as &dyn Fn(Pass)), ("re-render with gradient", &rerender)] {
            run(pass);
            let before = transfer::counted();
            let mut seconds: Vec<f64> = (0..repeats)
                .map(|_| {
                    let started = std::time::Instant::now();
                    run(pass);
                    started.elapsed().as_secs_f64()
                })
                .collect();
            let moved = transfer::counted().since(before).per_step(repeats);
            seconds.sort_by(f64::total_cmp);
            println!("  {name}, {what}: median {:.3} s (of {repeats}); per call {moved}", seconds[repeats / 2]);
        }
    }
    if let Some(m) = device_stats::device_memory() {
        println!(
            "  device memory: {} in use, {} reserved",
            transfer::human_bytes(m.in_use),
            transfer::human_bytes(m.reserved)
        );
    }
    Ok(())
}
