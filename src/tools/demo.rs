//! The one-command demo on the built-in procedural scene: write the scene,
//! fit a photorealistic grid, make a reference case from the scene's
//! ground-truth stylized twin at one training view, stylize, render an orbit
//! of the stylized field, and evaluate it against the stylized twin.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};

use crate::eval::stylization::{self, EvalJob, RobustnessViews, StylizationEval};
use crate::field::checkpoint::{self, Checkpoint};
use crate::field::render_path::{self, PathKind};
use crate::photo::config::TrainConfig;
use crate::photo::evaluate::evaluate;
use crate::photo::run::{TrainMetrics, run_training};
use crate::reference::case::CASE_TOML;
use crate::scene::camera::Camera;
use crate::scene::data::{self, Dataset, DatasetKind, procedural};
use crate::stylize::config::{Preset, StylizeConfig};
use crate::stylize::run::run_stylize;
use crate::stylize::{Method, StylizeJob, StylizeReport};
use crate::util::backend::BackendKind;
use crate::util::files;
use crate::util::progress::Progress;

/// The demo's training config (configs/demo.toml, compiled in).
pub fn demo_config() -> Result<TrainConfig> {
    TrainConfig::from_toml_str(
        include_str!("../../configs/demo.toml"),
        &TrainConfig::for_kind(DatasetKind::Blender),
        "configs/demo.toml",
    )
}

/// The demo's stylization config (configs/demo_stylize.toml, compiled in):
/// the defaults with a shorter schedule.
pub fn demo_stylize_config() -> Result<StylizeConfig> {
    Preset::Fast.config()
}

/// What the demo runs (defaults: the full demo).
#[derive(Debug, Clone, Default)]
pub struct DemoOptions {
    pub scene: procedural::SceneOptions,
    /// Photoreal training steps (default: configs/demo.toml).
    pub steps: Option<usize>,
    /// Stylization image epochs (default: configs/demo_stylize.toml).
    pub epochs: Option<usize>,
    /// Training view whose stylized twin is the reference.
    pub reference_view: usize,
}

/// The demo's outputs and figures.
pub struct DemoReport {
    pub photo: TrainMetrics,
    pub stylize: StylizeReport,
    pub eval: StylizationEval,
    /// Photoreal test views against the stylized twin (the starting point).
    pub photo_gt_psnr: f32,
    pub seconds: f64,
    pub out: PathBuf,
}

/// Writes the reference case: the stylized twin's image of training view `view`.
pub fn write_twin_case(scene: &Path, view: usize, out: &Path) -> Result<PathBuf> {
    let twin = data::load(&scene.join("stylized"), &Default::default())?;
    let v = twin.train.get(view).with_context(|| format!("the scene has no training view {view}"))?;
    v.camera.image_of(v.rgb.clone()).save_png(&out.join("style.png"))?;
    files::write_text(
        &out.join(CASE_TOML),
        &format!(
            "# The procedural scene's ground-truth stylized twin at training view {view} (an exact repaint).\n\n\
             [[reference]]\nstyle = \"style.png\"\nview = \"train:{view}\"\n"
        ),
    )?;
    Ok(out.to_path_buf())
}

/// Runs the demo into `out`: `scene/`, `photo/` (photoreal run), `orbit/`
/// (its orbit), `case/` (the reference), `stylized/` (the stylized run,
/// with `orbit/path.gif`), `eval.json`.
pub fn run_demo(out: &Path, backend: BackendKind, opts: &DemoOptions, progress: &dyn Progress) -> Result<DemoReport> {
    let started = Instant::now();
    let scene = out.join("scene");
    progress.info(format!("[1/5] writing the procedural scene to {}", scene.display()));
    procedural::write_scene(&scene, &opts.scene)?;
    let cfg = demo_fit_config(opts.steps)?;
    let dataset = data::load(&scene, &cfg.data)?;
    let photo = out.join("photo");
    progress.info(format!(
        "[2/5] fitting the photorealistic grid ({} steps, backend {backend}) into {}",
        cfg.optim.steps,
        photo.display()
    ));
    let photo_metrics = run_training(&dataset, cfg, &photo, backend, false, progress)?;
    let cams = render_path::path_cameras(&dataset, PathKind::Orbit, 60)?;
    let ck = checkpoint::load(&photo, &backend.device())?;
    render_path::render_frames(&ck, &cams, &out.join("orbit"), progress)?;

    progress.info(format!("[3/5] reference case: the stylized twin at training view {}", opts.reference_view));
    let case = write_twin_case(&scene, opts.reference_view, &out.join("case"))?;
    let stylized = out.join("stylized");
    let stylize = stylize_demo(&photo, &case, &stylized, backend, opts.epochs, &cams, progress)?;

    progress.info("[5/5] evaluating against the stylized twin".to_string());
    let (eval, photo_gt_psnr) = evaluate_demo(&ck, &dataset, &scene, &stylized, case, backend, progress)?;
    files::write_json(&out.join("eval.json"), &eval)?;
    Ok(DemoReport {
        photo: photo_metrics,
        stylize,
        eval,
        photo_gt_psnr,
        seconds: started.elapsed().as_secs_f64(),
        out: out.to_path_buf(),
    })
}

/// The demo's fit config, with `steps` (and the upsampling steps scaled to it) when given.
fn demo_fit_config(steps: Option<usize>) -> Result<TrainConfig> {
    let mut cfg = demo_config()?;
    let demo_steps = cfg.optim.steps;
    if let Some(s) = steps {
        cfg.optim.steps = s;
        cfg.grid.upsample_steps =
            cfg.grid.upsample_steps.iter().map(|&u| u * s / demo_steps).filter(|&u| u > 0 && u < s).collect();
        cfg.grid.upsample_res.truncate(cfg.grid.upsample_steps.len());
        cfg.validate()?;
    }
    Ok(cfg)
}

/// Stylizes the demo's photoreal run with its case, then renders the orbit.
fn stylize_demo(
    photo: &Path,
    case: &Path,
    stylized: &Path,
    backend: BackendKind,
    epochs: Option<usize>,
    orbit: &[Camera],
    progress: &dyn Progress,
) -> Result<StylizeReport> {
    let mut config = demo_stylize_config()?;
    if let Some(e) = epochs {
        config.schedule.image_epochs = e;
    }
    progress.info(format!(
        "[4/5] stylizing ({} image epochs) into {}",
        config.schedule.image_epochs,
        stylized.display()
    ));
    let job = StylizeJob {
        resume: false,
        photo: photo.to_path_buf(),
        case: case.to_path_buf(),
        out: stylized.to_path_buf(),
        config,
        method: Method::RefNpr,
        backend,
        style: None,
        data: None,
        registration: None,
        render_test: false,
    };
    let report = run_stylize(&job, progress)?;
    let style_ck = checkpoint::load_with(stylized, &backend.device(), false)?;
    render_path::render_frames(&style_ck, orbit, &stylized.join("orbit"), progress)?;
    Ok(report)
}

/// The stylized run's metrics against the twin, and the photoreal field's
/// PSNR against the twin (the starting point).
fn evaluate_demo(
    ck: &Checkpoint,
    dataset: &Dataset,
    scene: &Path,
    stylized: &Path,
    case: PathBuf,
    backend: BackendKind,
    progress: &dyn Progress,
) -> Result<(StylizationEval, f32)> {
    let twin = scene.join("stylized");
    let job = EvalJob {
        run: stylized.to_path_buf(),
        case,
        gt: Some(twin.clone()),
        robustness: 0,
        robustness_views: RobustnessViews::Near,
        backend,
        data: None,
        robustness_epochs: None,
        resume: false,
    };
    let eval = stylization::evaluate_stylization(&job, progress)?;
    let truth = data::load(&twin, &ck.meta.data)?;
    let photo_gt = evaluate(&ck.grid, dataset, &truth.test, &ck.meta.render, None)?;
    Ok((eval, photo_gt.psnr))
}
