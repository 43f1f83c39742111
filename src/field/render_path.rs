//! `refnpr render`: the frames of a camera path from a checkpoint, as PNGs
//! (colour and equation-4 depth) and a GIF.

use std::path::Path;
use std::time::Instant;

use anyhow::{Result, bail};

use crate::field::checkpoint::Checkpoint;
use crate::scene::camera::Camera;
use crate::scene::data::Dataset;
use crate::util::image::{self, Image};
use crate::util::progress::{Event, Phase, Progress};

/// Which cameras to render.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PathKind {
    Test,
    Train,
    /// The LLFF spiral (forward-facing scenes).
    Spiral,
    /// A circular orbit.
    Orbit,
}

/// The cameras of a path for a dataset (`frames` for spiral / orbit).
pub fn path_cameras(dataset: &Dataset, kind: PathKind, frames: usize) -> Result<Vec<Camera>> {
    Ok(match kind {
        PathKind::Test => dataset.test.iter().map(|v| v.camera).collect(),
        PathKind::Train => dataset.train.iter().map(|v| v.camera).collect(),
        PathKind::Spiral => {
            if dataset.ndc.is_none() {
                bail!("the spiral path is for forward-facing scenes; use --path orbit");
            }
            dataset.render_path(frames)
        }
        PathKind::Orbit => dataset.render_path(frames),
    })
}

/// Renders the cameras to `out/rgb/NNNN.png`, `out/depth/NNNN.png`,
/// `out/path.gif`, and returns the frames.
pub fn render_frames(ck: &Checkpoint, cameras: &[Camera], out: &Path, progress: &dyn Progress) -> Result<Vec<Image>> {
    let started = Instant::now();
    progress.event(Event::Start { phase: Phase::Render, done: 0, total: cameras.len() });
    let mut gif_frames = Vec::new();
    let mut frames = Vec::with_capacity(cameras.len());
    let renderer = ck.renderer();
    for (i, cam) in cameras.iter().enumerate() {
        let r = renderer.view(cam);
        r.image.save_png(&out.join("rgb").join(format!("{i:04}.png")))?;
        let depth_rgb = image::depth_to_rgb(&r.threshold_depth);
        image::save_png(
            &out.join("depth").join(format!("{i:04}.png")),
            cam.intrinsics.width,
            cam.intrinsics.height,
            &depth_rgb,
        )?;
        gif_frames.push(r.image.to_rgb8());
        frames.push(r.image);
        let message = out.display().to_string();
        progress.event(Event::Step { phase: Phase::Render, done: i + 1, total: cameras.len(), message });
    }
    image::save_gif(&out.join("path.gif"), &gif_frames, 66)?;
    progress.event(Event::PhaseDone { phase: Phase::Render, seconds: started.elapsed().as_secs_f64() });
    Ok(frames)
}
