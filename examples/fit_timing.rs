//! Times a photoreal fit on one backend without the stylization's VGG16, so
//! the binary stays small enough to carry to a machine without Rust (a lent
//! GPU): `REFNPR_BACKEND=wgpu cargo run --example fit_timing -- DATA OUT STEPS
//! [CONFIG]`. Prints the fit's test PSNR, its wall time and the per-part step
//! profile after the last upsampling (`metrics.json` has the rest), then the
//! renderer's throughput at 256³ as `refnpr bench` measures it.
use std::path::PathBuf;

use refnpr::photo::run::run_training;
use refnpr::scene::data;
use refnpr::{BackendKind, Console, TrainConfig};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [data_dir, out, steps, rest @ ..] = args.as_slice() else {
        anyhow::bail!("usage: fit_timing DATA OUT STEPS [CONFIG] (backend from REFNPR_BACKEND)");
    };
    let backend = BackendKind::from_env()?;
    let dir = PathBuf::from(data_dir);
    let base = TrainConfig::for_dir(&dir)?;
    let mut cfg = match rest.first() {
        Some(p) => TrainConfig::from_file(std::path::Path::new(p), &base)?,
        None => base,
    };
    cfg.optim.steps = steps.parse()?;
    cfg.validate()?;
    let dataset = data::load(&dir, &cfg.data)?;
    let m = run_training(&dataset, cfg, &PathBuf::from(out), backend, false, &Console::default())?;
    println!("{backend}: test PSNR {:.2} dB, {} steps in {:.1} s", m.test_psnr, m.steps, m.train_seconds);
    for p in &m.step_profile {
        println!("  {p:?}");
    }
    let b = refnpr::tools::bench::renderer_throughput(backend, 256, 4096, 5)?;
    println!("renderer at 256³: {b:?}");
    Ok(())
}
