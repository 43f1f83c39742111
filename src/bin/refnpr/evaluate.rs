//! Evaluation: `refnpr eval` (the stylization metrics, or a photoreal run's
//! test PSNR) and `refnpr lpips` (LPIPS between two images).

use std::path::{Path, PathBuf};

use anyhow::{Result, ensure};
use refnpr::eval::lpips::LpipsNet;
use refnpr::eval::stylization::{EvalJob, RobustnessViews};
use refnpr::field::checkpoint;
use refnpr::photo::evaluate::evaluate;
use refnpr::util::files;
use refnpr::{BackendKind, Console};

use crate::common::backend_or_env;

// `refnpr eval`'s arguments.
#[derive(clap::Args)]
pub struct EvalArgs {
    /// Run folder (or its checkpoint file): a photoreal or a stylized run.
    #[arg(long, alias = "ckpt")]
    pub run: PathBuf,
    /// The stylized run's reference case: stylization metrics (ref_lpips,
    /// stability, and with --gt the ground-truth PSNRs). Without it: PSNR
    /// and SSIM of the run's test views.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Dataset whose test views are the ground truth (a procedural scene's `stylized/`).
    #[arg(long)]
    pub gt: Option<PathBuf>,
    /// Restylize from N of the run's own renders and report their PSNR (slow: N stylizations).
    #[arg(long, default_value_t = 0)]
    pub robustness: usize,
    /// Image epochs of each robustness stylization (default: the run's).
    #[arg(long)]
    pub robustness_epochs: Option<usize>,
    /// Which path frames --robustness restylizes from: the nearest to the reference camera, or spread along the path.
    #[arg(long, value_enum, default_value_t = RobustnessViews::Near)]
    pub robustness_views: RobustnessViews,
    /// Keep the restylizations a killed `eval --robustness` finished, and continue the one
    /// it was running from its resume.bin.
    #[arg(long)]
    pub resume: bool,
    /// Also write the JSON here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// The run's dataset folder, when it moved.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
    #[arg(long, value_enum, env = "REFNPR_BACKEND")]
    pub backend: Option<BackendKind>,
}

/// `refnpr eval`: the stylization metrics (with `--reference`), or a photoreal run's test PSNR.
pub fn eval(args: EvalArgs, progress: &Console) -> Result<()> {
    let EvalArgs { run, reference, gt, robustness, robustness_epochs, robustness_views, resume, out, data, backend } =
        args;
    let backend = backend_or_env(backend, progress)?;
    let json = match reference {
        Some(case) => {
            let job = EvalJob { run, case, gt, robustness, robustness_views, backend, data, robustness_epochs, resume };
            serde_json::to_value(refnpr::tools::robustness::evaluate(&job, progress)?)?
        }
        None => {
            ensure!(robustness == 0, "--robustness needs --reference (the stylized run's case)");
            photoreal_eval(&run, gt.or(data), backend)?
        }
    };
    if let Some(path) = out {
        files::write_json(&path, &json)?;
    }
    println!("{}", serde_json::to_string_pretty(&json)?);
    Ok(())
}

/// `refnpr eval` without `--reference`: PSNR / SSIM of the run's test views
/// against its dataset's (or `truth`'s).
fn photoreal_eval(run: &Path, truth: Option<PathBuf>, backend: BackendKind) -> Result<serde_json::Value> {
    let (ck, dataset) = checkpoint::load_run(run, truth.as_deref(), &backend.device())?;
    let r = evaluate(&ck.grid, &dataset, &dataset.test, &ck.meta.render, None)?;
    Ok(serde_json::json!({"psnr": r.psnr, "ssim": r.ssim, "views": r.per_view_psnr.len(), "data": dataset.root}))
}

// `refnpr lpips`'s arguments.
#[derive(clap::Args)]
pub struct LpipsArgs {
    /// The first image (PNG or JPEG; alpha composited over --background).
    pub a: PathBuf,
    /// The second image.
    pub b: PathBuf,
    /// The feature network: vgg (the paper's Ref-LPIPS) or alex (the `lpips` package's default).
    #[arg(long, value_enum, default_value_t = LpipsNet::Vgg)]
    pub net: LpipsNet,
    /// The colour transparent pixels are composited over, as R,G,B in [0, 1].
    #[arg(long, value_delimiter = ',', num_args = 3, default_values_t = [1.0, 1.0, 1.0])]
    pub background: Vec<f32>,
    /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
    #[arg(long, value_enum, env = "REFNPR_BACKEND")]
    pub backend: Option<BackendKind>,
}

/// `refnpr lpips A B`: the distance on stdout alone (for scripts), a resize on stderr.
pub fn lpips(args: LpipsArgs, progress: &Console) -> Result<()> {
    let LpipsArgs { a, b, net, background, backend } = args;
    let device = backend_or_env(backend, progress)?.open(progress)?;
    let background = [background[0], background[1], background[2]];
    let (distance, note) = refnpr::eval::lpips::file_distance(&a, &b, net, background, &device)?;
    if let Some(note) = note {
        eprintln!("{note}");
    }
    println!("{distance:.6}");
    Ok(())
}
