//! `refnpr demo`: the whole method on the built-in scene, and its figures.

use std::path::{Path, PathBuf};

use anyhow::Result;
use refnpr::tools::demo;
use refnpr::{BackendKind, Console, Progress};

use crate::common::backend_or_env;

// `refnpr demo`'s arguments.
#[derive(clap::Args)]
pub struct DemoArgs {
    /// The folder to write: scene/, photo/, case/, stylized/, orbit/, eval.json.
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
    #[arg(long, value_enum, env = "REFNPR_BACKEND")]
    pub backend: Option<BackendKind>,
    /// Override the number of photoreal training steps.
    #[arg(long)]
    pub steps: Option<usize>,
    /// Override the number of stylization image epochs.
    #[arg(long = "image-epochs", alias = "epochs")]
    pub epochs: Option<usize>,
}

/// `refnpr demo`.
pub fn demo(args: DemoArgs, progress: &Console) -> Result<()> {
    let DemoArgs { out, backend, steps, epochs } = args;
    run_demo(&out, backend_or_env(backend, progress)?, steps, epochs, progress)
}

fn run_demo(
    out: &Path,
    backend: BackendKind,
    steps: Option<usize>,
    epochs: Option<usize>,
    progress: &dyn Progress,
) -> Result<()> {
    let r = demo::run_demo(out, backend, &demo::DemoOptions { steps, epochs, ..Default::default() }, progress)?;
    let e = &r.eval;
    let fmt = |v: Option<f32>| v.map(|v| format!("{v:.2} dB")).unwrap_or_else(|| "-".into());
    println!("demo done in {:.0} s (backend {backend})", r.seconds);
    println!(
        "  photoreal fit:   {:.2} dB test PSNR ({:.0} s)  orbit: {}",
        r.photo.test_psnr,
        r.photo.train_seconds,
        out.join("orbit/path.gif").display()
    );
    println!("  reference:       {}", out.join("case/style.png").display());
    println!(
        "  stylized:        {:.0} s  orbit: {}",
        r.stylize.total_seconds,
        out.join("stylized/orbit/path.gif").display()
    );
    println!(
        "  vs ground truth: {} (photoreal field: {:.2} dB), on surfaces the reference does not see: {} ({:.0}% of the surface)",
        fmt(e.gt_psnr),
        r.photo_gt_psnr,
        fmt(e.gt_psnr_occluded),
        100.0 * e.occluded_fraction.unwrap_or(0.0)
    );
    let st: Vec<String> = e.stability.iter().map(|s| format!("{} frame(s) apart {:.4}", s.gap, s.rmse)).collect();
    println!(
        "  Ref-LPIPS {:.4} (LPIPS vgg, the paper's metric; alex {:.4}); stability (warp RMSE) {}",
        e.ref_lpips,
        e.ref_lpips_alex,
        st.join(", ")
    );
    println!(
        "  speckle {:.2}% of the surface pixels (test views {}, ground truth {})",
        100.0 * e.speckle,
        e.speckle_test.map_or("-".into(), |v| format!("{:.2}%", 100.0 * v)),
        e.gt_speckle.map_or("-".into(), |v| format!("{:.2}%", 100.0 * v))
    );
    println!("  all figures: {}", out.join("eval.json").display());
    Ok(())
}
