//! What one photoreal training step costs on one backend and ray kernel,
//! from a fitted run (lego at 256³ for the figures in docs/performance.md):
//! `REFNPR_BACKEND=wgpu cargo run --example step_costs -- DATA CHECKPOINT
//! STEPS KERNEL` with KERNEL one of auto, graph, unfused, host. It resumes
//! the checkpoint, runs 2 steps to warm up (shader compilation, the pools'
//! first pages), then STEPS steps, and prints per step: the median wall
//! time, the part profile, host-device traffic and kernel launches, and the
//! device memory after them; then, over 2 more steps, the graph step's
//! peak. One kernel per process, so that its memory figures are its own.
use std::path::PathBuf;

use refnpr::field::RayKernel;
use refnpr::photo::trainer::Trainer;
use refnpr::scene::data;
use refnpr::util::{device_stats, profile, transfer};
use refnpr::{BackendKind, TrainConfig};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [data_dir, checkpoint, steps, kernel] = args.as_slice() else {
        anyhow::bail!("usage: step_costs DATA CHECKPOINT STEPS auto|graph|unfused|host (backend from REFNPR_BACKEND)");
    };
    let kernel: RayKernel = serde_json::from_value(serde_json::Value::String(kernel.clone()))
        .map_err(|_| anyhow::anyhow!("KERNEL is one of auto, graph, unfused, host, not {kernel:?}"))?;
    let steps: usize = steps.parse::<usize>()?.max(1);
    let backend = BackendKind::from_env()?;
    let dir = PathBuf::from(data_dir);
    let dataset = data::load(&dir, &TrainConfig::for_dir(&dir)?.data)?;
    let device = backend.open(&refnpr::Console::default())?;
    let mut trainer = Trainer::resume(&dataset, &PathBuf::from(checkpoint), &device)?.with_ray_kernel(kernel);
    for _ in 0..2 {
        trainer.step_once()?;
    }
    trainer.profile.clear();
    let (before, mut seconds, mut samples) = (transfer::counted(), Vec::new(), 0);
    for _ in 0..steps {
        let started = std::time::Instant::now();
        // A step reads its loss back: the device's queue is drained when it returns.
        let st = trainer.step_once()?;
        seconds.push(started.elapsed().as_secs_f64());
        samples += st.samples;
    }
    let moved = transfer::counted().since(before).per_step(steps);
    let parts: Vec<profile::PartTime> = trainer.profile.parts().iter().map(|p| p.per_step(steps)).collect();
    // The peak over two more steps, untimed (each probe waits for the device).
    trainer.memory_probe = device_stats::PeakProbe::enabled();
    for _ in 0..2 {
        trainer.step_once()?;
    }
    seconds.sort_by(f64::total_cmp);
    println!("{backend}, ray_kernel {kernel:?}: {} rows, {} samples a step", trainer.grid.num_rows(), samples / steps);
    println!("  median step {:.3} s (of {steps}); a step's parts: {}", seconds[steps / 2], profile::describe(&parts));
    println!("  per step: {moved}");
    match device_stats::device_memory() {
        Some(m) => println!(
            "  device memory: {} in use, {} reserved",
            transfer::human_bytes(m.in_use),
            transfer::human_bytes(m.reserved)
        ),
        None => println!("  device memory: host memory (a CPU backend)"),
    }
    if let Some(peak) = trainer.memory_probe.peak() {
        println!(
            "  a step's peak device memory in use (after its forward or its backward): {}",
            transfer::human_bytes(peak)
        );
    }
    Ok(())
}
