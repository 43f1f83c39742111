//! `refnpr render`: frames of a camera path from a checkpoint.

use crate::camera::Camera;
use crate::checkpoint::Checkpoint;
use crate::data::{self, Dataset};
use crate::imageio;
use crate::render;
use anyhow::{Result, bail};
use std::path::Path;
use std::str::FromStr;

/// Which cameras to render.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PathKind {
    Test,
    Train,
    Spiral,
    Orbit,
}

impl FromStr for PathKind {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "test" => PathKind::Test,
            "train" => PathKind::Train,
            "spiral" => PathKind::Spiral,
            "orbit" => PathKind::Orbit,
            o => bail!("unknown path '{o}': expected test, train, spiral or orbit"),
        })
    }
}

/// The cameras of a path for a dataset (`frames` for spiral / orbit).
pub fn path_cameras(dataset: &Dataset, kind: PathKind, frames: usize) -> Result<Vec<Camera>> {
    Ok(match kind {
        PathKind::Test => dataset.test.iter().map(|v| v.camera).collect(),
        PathKind::Train => dataset.train.iter().map(|v| v.camera).collect(),
        PathKind::Spiral => {
            if dataset.kind != data::DatasetKind::Llff {
                bail!("the spiral path is for forward-facing (LLFF) scenes; use --path orbit");
            }
            dataset.render_path(frames)
        }
        PathKind::Orbit => dataset.render_path(frames),
    })
}

/// Renders the cameras to `out/rgb/NNNN.png`, `out/depth/NNNN.png`, `out/path.gif`.
pub fn render_frames(ck: &Checkpoint, cameras: &[Camera], out: &Path, show_progress: bool) -> Result<()> {
    let cfg = &ck.meta.config;
    let bar = crate::train::progress_bar(cameras.len() as u64, 0);
    if !show_progress {
        bar.finish_and_clear();
    }
    let mut gif_frames = Vec::new();
    for (i, cam) in cameras.iter().enumerate() {
        let r = render::render_view(&ck.grid, cam, ck.meta.ndc.as_ref(), &cfg.march, ck.meta.background, cfg.render_chunk);
        imageio::save_png(&out.join("rgb").join(format!("{i:04}.png")), r.width, r.height, &r.rgb)?;
        let depth_rgb = imageio::depth_to_rgb(&r.threshold_depth);
        imageio::save_png(&out.join("depth").join(format!("{i:04}.png")), r.width, r.height, &depth_rgb)?;
        gif_frames.push(imageio::to_rgb8(r.width, r.height, &r.rgb));
        bar.inc(1);
    }
    bar.finish_and_clear();
    imageio::save_gif(&out.join("path.gif"), &gif_frames, 66)
}
