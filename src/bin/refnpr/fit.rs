//! The photoreal field: `refnpr train`, `refine-poses`, `render` (a camera
//! path's frames) and `views` (the contact sheet to pick a reference from).

use std::path::{Path, PathBuf};

use anyhow::Result;
use refnpr::field::checkpoint;
use refnpr::field::render_path::{self, PathKind};
use refnpr::photo::config::TrainConfig;
use refnpr::photo::pose_refine;
use refnpr::photo::run::{run_training, run_training_with_refined_poses};
use refnpr::scene::data;
use refnpr::{BackendKind, Console, Progress};

use crate::common::{backend_or_env, run_folder};

// `refnpr train`'s arguments.
#[derive(clap::Args)]
pub struct TrainArgs {
    /// The dataset folder.
    #[arg(long)]
    pub data: PathBuf,
    /// The run folder to write: checkpoint.bin, metrics.json, test/ renders.
    #[arg(long)]
    pub out: PathBuf,
    /// TOML config; fields it leaves out take the defaults for the dataset kind.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
    #[arg(long, value_enum, env = "REFNPR_BACKEND")]
    pub backend: Option<BackendKind>,
    /// Continue from OUT/checkpoint.bin if it exists (with --steps: extend the run to that many steps).
    #[arg(long)]
    pub resume: bool,
    /// The number of steps ([optim] steps; for views larger than the grid's schedule was written for, times the square of the grid's growth, as a line says: `[grid] voxels_per_pixel = 0` keeps it exact).
    #[arg(long)]
    pub steps: Option<usize>,
    /// Train on the images this many times smaller ([data] downscale): LLFF picks images_N/ (fern at
    /// 1008x756 is 4, the default 8), or resizes images/ by N; Blender, NSVF and captures resize by N.
    #[arg(long)]
    pub downscale: Option<u32>,
    /// A COLMAP capture around the scene: fit it (OUT/first_fit), align its cameras to that field
    /// (`refine-poses`), write OUT/scene_refined and fit that in OUT (twice the time; sharper poses).
    #[arg(long, conflicts_with = "resume")]
    pub refine_poses: bool,
}

/// `refnpr train`.
pub fn train(args: TrainArgs, progress: &Console) -> Result<()> {
    let TrainArgs { data, out, config, backend, resume, steps, downscale, refine_poses } = args;
    let backend = backend_or_env(backend, progress)?;
    let how = TrainHow { resume, steps, downscale, refine_poses };
    run_train(&data, &out, config.as_deref(), backend, how, progress)
}

/// How `refnpr train` runs: resumed, for how many steps, on images how
/// many times smaller, with its poses refined.
struct TrainHow {
    resume: bool,
    steps: Option<usize>,
    downscale: Option<u32>,
    refine_poses: bool,
}

fn run_train(
    dir: &Path,
    out: &Path,
    config: Option<&Path>,
    backend: BackendKind,
    how: TrainHow,
    progress: &dyn Progress,
) -> Result<()> {
    let kind = data::detect_kind(dir)?;
    let base = TrainConfig::for_dir(dir)?;
    let mut cfg = match config {
        Some(p) => TrainConfig::from_file(p, &base)?,
        None => base,
    };
    if let Some(s) = how.steps {
        cfg.optim.steps = s;
    }
    if let Some(n) = how.downscale {
        cfg.data.downscale = n;
    }
    cfg.validate()?;
    let dataset = data::load(dir, &cfg.data)?;
    for w in &dataset.warnings {
        progress.warning(w.clone());
    }
    for n in &dataset.notes {
        progress.info(n.clone());
    }
    let size = dataset.train[0].camera.intrinsics;
    progress.info(format!(
        "{kind} scene {}: {} train / {} test views at {}x{}, backend {backend}",
        dir.display(),
        dataset.train.len(),
        dataset.test.len(),
        size.width,
        size.height
    ));
    let m = if how.refine_poses {
        let (first, _, second) = run_training_with_refined_poses(&dataset, cfg, out, backend, progress)?;
        println!("before the cameras were refined: test PSNR {:.2} dB", first.test_psnr);
        second
    } else {
        run_training(&dataset, cfg, out, backend, how.resume, progress)?
    };
    println!("test PSNR {:.2} dB, SSIM {:.4}, {} steps in {:.1} s", m.test_psnr, m.test_ssim, m.steps, m.train_seconds);
    let o = out.display();
    println!("wrote {o}/checkpoint.bin, {o}/metrics.json, {o}/test/ (the test views' renders)");
    println!(
        "next: refnpr views --run {o} (pick a reference view), refnpr reference --run {o} --view train:0 --out CASE"
    );
    Ok(())
}

// `refnpr refine-poses`'s arguments.
#[derive(clap::Args)]
pub struct RefinePosesArgs {
    /// The photoreal run trained on the capture.
    #[arg(long)]
    pub run: PathBuf,
    /// The dataset folder to write (images/, sparse/0/ in COLMAP's text form, test.txt).
    #[arg(long)]
    pub out: PathBuf,
    /// The capture (default: the run's dataset).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Gauss-Newton iterations (each renders every view once).
    #[arg(long, default_value_t = 6)]
    pub iterations: usize,
    /// Keep the focal length (refine the poses only).
    #[arg(long)]
    pub keep_focal: bool,
}

/// `refnpr refine-poses`.
pub fn refine_poses(args: RefinePosesArgs, progress: &Console) -> Result<()> {
    let RefinePosesArgs { run, out, data, iterations, keep_focal } = args;
    let settings = pose_refine::RefineSettings { iterations, focal: !keep_focal };
    run_refine_poses(&run, &out, data.as_deref(), &settings, progress)
}

fn run_refine_poses(
    run: &Path,
    out: &Path,
    data: Option<&Path>,
    settings: &pose_refine::RefineSettings,
    progress: &dyn Progress,
) -> Result<()> {
    let (ck, dataset) = checkpoint::load_run(run, data, &pose_refine::render_device(BackendKind::Flex))?;
    data::check_writable(&dataset, out)?;
    let r = pose_refine::refine_dataset(&ck.grid, &dataset, &ck.meta.render, settings, progress)?;
    println!("{}", r.describe());
    data::write_colmap(&dataset, &r.cameras, out)?;
    println!("wrote {} (train it: refnpr train --data {} --out RUN)", out.display(), out.display());
    Ok(())
}

// `refnpr render`'s arguments.
#[derive(clap::Args)]
pub struct RenderArgs {
    /// Run folder (or its checkpoint file), photoreal or stylized.
    #[arg(long = "run", alias = "ckpt", value_name = "RUN")]
    pub ckpt: PathBuf,
    /// The cameras: the dataset's test or train views, a spiral (forward-facing scenes) or an orbit.
    #[arg(long, value_enum, default_value_t = PathKind::Test)]
    pub path: PathKind,
    /// The folder to write the frames to.
    #[arg(long)]
    pub out: PathBuf,
    /// Frames of a spiral / orbit path.
    #[arg(long, default_value_t = 120)]
    pub frames: usize,
    /// Dataset folder (default: the one the run was trained on).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
    #[arg(long, value_enum, env = "REFNPR_BACKEND")]
    pub backend: Option<BackendKind>,
}

/// `refnpr render`: the frames of a camera path from a checkpoint.
pub fn render(args: RenderArgs, progress: &Console) -> Result<()> {
    let RenderArgs { ckpt, path, out, frames, data, backend } = args;
    let device = backend_or_env(backend, progress)?.device();
    let (ck, dataset) = checkpoint::load_run(&ckpt, data.as_deref(), &device)?;
    let cams = render_path::path_cameras(&dataset, path, frames)?;
    render_path::render_frames(&ck, &cams, &out, progress)?;
    println!("rendered {} frames to {}", cams.len(), out.display());
    Ok(())
}

// `refnpr views`'s arguments.
#[derive(clap::Args)]
pub struct ViewsArgs {
    /// Run folder (or its checkpoint file).
    #[arg(long = "run", alias = "ckpt", value_name = "RUN")]
    pub run: PathBuf,
    /// The PNG to write (default: RUN/views.png).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// The long side of each thumbnail, in pixels.
    #[arg(long, default_value_t = 128)]
    pub thumb: usize,
    /// Thumbnails per row.
    #[arg(long, default_value_t = 8)]
    pub columns: usize,
    /// Show every N-th of the render path's 120 frames (0: none; they are rendered from the field).
    #[arg(long, default_value_t = 4)]
    pub path_every: usize,
    /// Dataset folder (default: the one the run was trained on).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
    #[arg(long, value_enum, env = "REFNPR_BACKEND")]
    pub backend: Option<BackendKind>,
}

/// `refnpr views`: the contact sheet.
pub fn views(args: ViewsArgs, progress: &Console) -> Result<()> {
    let ViewsArgs { run, out, thumb, columns, path_every, data, backend } = args;
    let opts = refnpr::tools::views::SheetOptions { thumb, columns, path_every };
    let device = backend_or_env(backend, progress)?.device();
    let (ck, dataset) = checkpoint::load_run(&run, data.as_deref(), &device)?;
    let sheet = refnpr::tools::views::contact_sheet(&ck, &dataset, &opts, progress)?;
    let out = out.unwrap_or_else(|| run_folder(&run).join("views.png"));
    sheet.save_png(&out)?;
    println!(
        "wrote {} ({} train, {} test views{}): pick one, then `refnpr reference --run {} --view NAME --out CASE`",
        out.display(),
        dataset.train.len(),
        dataset.test.len(),
        if opts.path_every > 0 { ", every path frame's label is its path:N" } else { "" },
        run.display()
    );
    Ok(())
}
