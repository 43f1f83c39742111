//! The one-command demo on the built-in procedural scene: write the scene,
//! fit a photorealistic grid, make a reference case from the scene's
//! ground-truth stylized twin at one training view, stylize, render an orbit
//! of the stylized field, and evaluate it against the stylized twin.

use crate::backend::BackendKind;
use crate::checkpoint;
use crate::config::TrainConfig;
use crate::data::{self, DatasetKind, procedural};
use crate::evaluation::{self, EvalJob, StylizationEval};
use crate::render_path::{self, PathKind};
use crate::stylize::config::StylizeConfig;
use crate::stylize::{Method, StylizeJob, StylizeReport, run_stylize};
use crate::train::{self, TrainMetrics};
use anyhow::{Context, Result};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The demo's training config (configs/demo.toml, compiled in).
pub fn demo_config() -> Result<TrainConfig> {
    TrainConfig::from_toml_str(include_str!("../configs/demo.toml"), &TrainConfig::for_kind(DatasetKind::Blender), "configs/demo.toml")
}

/// The demo's stylization config (configs/demo_stylize.toml, compiled in):
/// the defaults with a shorter schedule.
pub fn demo_stylize_config() -> Result<StylizeConfig> {
    StylizeConfig::from_toml_str(include_str!("../configs/demo_stylize.toml"), "configs/demo_stylize.toml")
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
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let twin = data::load(&scene.join("stylized"), &Default::default())?;
    let v = twin.train.get(view).with_context(|| format!("the scene has no training view {view}"))?;
    let (w, h) = (v.camera.intrinsics.width, v.camera.intrinsics.height);
    crate::imageio::save_png(&out.join("style.png"), w, h, &v.rgb)?;
    std::fs::write(
        out.join(crate::reference::CASE_TOML),
        format!("# The procedural scene's ground-truth stylized twin at training view {view} (an exact repaint).\n\n[[reference]]\nstyle = \"style.png\"\nview = \"train:{view}\"\n"),
    )
    .with_context(|| format!("cannot write the reference case in {}", out.display()))?;
    Ok(out.to_path_buf())
}

/// Runs the demo into `out`: `scene/`, `photo/` (photoreal run), `orbit/`
/// (its orbit), `case/` (the reference), `stylized/` (the stylized run,
/// with `orbit/path.gif`), `eval.json`.
pub fn run_demo(out: &Path, backend: BackendKind, opts: &DemoOptions) -> Result<DemoReport> {
    let started = Instant::now();
    let scene = out.join("scene");
    eprintln!("[1/5] writing the procedural scene to {}", scene.display());
    procedural::write_scene(&scene, &opts.scene)?;
    let mut cfg = demo_config()?;
    let demo_steps = cfg.optim.steps;
    if let Some(s) = opts.steps {
        cfg.optim.steps = s;
        cfg.grid.upsample_steps = cfg.grid.upsample_steps.iter().map(|&u| u * s / demo_steps).filter(|&u| u > 0 && u < s).collect();
        cfg.grid.upsample_res.truncate(cfg.grid.upsample_steps.len());
        cfg.validate()?;
    }
    let dataset = data::load(&scene, &cfg.data)?;
    let photo = out.join("photo");
    eprintln!("[2/5] fitting the photorealistic grid ({} steps, backend {backend}) into {}", cfg.optim.steps, photo.display());
    let photo_metrics = train::run_training(&dataset, cfg, &photo, backend, false)?;
    let cams = render_path::path_cameras(&dataset, PathKind::Orbit, 60)?;
    let ck = checkpoint::load(&photo, &backend.device())?;
    render_path::render_frames(&ck, &cams, &out.join("orbit"), true)?;

    eprintln!("[3/5] reference case: the stylized twin at training view {}", opts.reference_view);
    let case = write_twin_case(&scene, opts.reference_view, &out.join("case"))?;

    let stylized = out.join("stylized");
    let mut config = demo_stylize_config()?;
    if let Some(e) = opts.epochs {
        config.schedule.image_epochs = e;
    }
    eprintln!("[4/5] stylizing ({} image epochs) into {}", config.schedule.image_epochs, stylized.display());
    let job = StylizeJob {
        photo: photo.clone(),
        case: case.clone(),
        out: stylized.clone(),
        config,
        method: Method::RefNpr,
        backend,
        style: None,
        data: None,
        render_test: false,
    };
    let stylize = run_stylize(&job)?;
    let style_ck = checkpoint::load_with(&stylized, &backend.device(), false)?;
    render_path::render_frames(&style_ck, &cams, &stylized.join("orbit"), true)?;

    eprintln!("[5/5] evaluating against the stylized twin");
    let twin = scene.join("stylized");
    let eval = evaluation::evaluate_stylization(&EvalJob { run: stylized.clone(), case, gt: Some(twin.clone()), robustness: 0, backend, data: None, robustness_epochs: None })?;
    evaluation::write_json(&out.join("eval.json"), &eval)?;
    let truth = data::load(&twin, &ck.meta.config.data)?;
    let photo_gt = train::evaluate(&ck.grid, &dataset, &truth.test, &ck.meta.config, None)?;
    Ok(DemoReport { photo: photo_metrics, stylize, eval, photo_gt_psnr: photo_gt.psnr, seconds: started.elapsed().as_secs_f64(), out: out.to_path_buf() })
}
