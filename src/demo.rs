//! The one-command demo: write the built-in procedural scene, fit a
//! photorealistic grid to it, render an orbit around it.

use crate::backend::BackendKind;
use crate::checkpoint;
use crate::config::TrainConfig;
use crate::data::{self, DatasetKind, procedural};
use crate::render_path::{self, PathKind};
use crate::train::{self, TrainMetrics};
use anyhow::Result;
use std::path::Path;

/// The demo's training config (configs/demo.toml, compiled in).
pub fn demo_config() -> Result<TrainConfig> {
    TrainConfig::from_toml_str(include_str!("../configs/demo.toml"), &TrainConfig::for_kind(DatasetKind::Blender), "configs/demo.toml")
}

/// Runs the demo into `out`: `out/scene`, `out/photo` (the run), `out/orbit` (frames + GIF).
pub fn run_demo(out: &Path, backend: BackendKind, steps: Option<usize>) -> Result<TrainMetrics> {
    let scene = out.join("scene");
    eprintln!("writing the procedural scene to {}", scene.display());
    procedural::write_scene(&scene, &procedural::SceneOptions::default())?;
    let mut cfg = demo_config()?;
    if let Some(s) = steps {
        cfg.optim.steps = s;
        cfg.grid.upsample_steps = cfg.grid.upsample_steps.iter().map(|&u| u * s / 1500).filter(|&u| u > 0 && u < s).collect();
        cfg.grid.upsample_res.truncate(cfg.grid.upsample_steps.len());
        cfg.validate()?;
    }
    let dataset = data::load(&scene, &cfg.data)?;
    let run = out.join("photo");
    eprintln!("fitting the photorealistic grid ({} steps, backend {backend}) into {}", cfg.optim.steps, run.display());
    let metrics = train::run_training(&dataset, cfg, &run, backend, false)?;
    let ck = checkpoint::load(&run, &backend.device())?;
    let cams = render_path::path_cameras(&dataset, PathKind::Orbit, 60)?;
    eprintln!("rendering a 60-frame orbit into {}", out.join("orbit").display());
    render_path::render_frames(&ck, &cams, &out.join("orbit"), true)?;
    Ok(metrics)
}
