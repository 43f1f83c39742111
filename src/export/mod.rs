//! Results out: a run's field in the formats other tools open. Gaussian
//! splats (`splat`, the 3DGS PLY), the density's iso-surface as a coloured
//! mesh (`mesh`, simplified by `decimate`, written as glb by `gltf` and as
//! PLY), a camera path as an MP4 (`video`, through ffmpeg) and the surface
//! as coloured points (`points`). Every file is written atomically.

pub mod decimate;
pub mod gltf;
pub mod mesh;
pub mod ply;
pub mod points;
pub mod splat;
pub mod video;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Result, bail};

use crate::field::checkpoint::Checkpoint;
use crate::field::render_path::{PathKind, path_cameras};
use crate::scene::camera::Camera;
use crate::scene::data::Dataset;
use crate::util::files;
use crate::util::image::Image;
use crate::util::progress::{Event, Phase, Progress};

/// What to export.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// Gaussian splats, the 3DGS PLY layout.
    Splat,
    /// The density's iso-surface, coloured: `.glb` (binary glTF) or `.ply` by the file's extension.
    Mesh,
    /// A camera path as an MP4 (H.264) through ffmpeg.
    Video,
    /// The training views' surface points, coloured, as PLY.
    Points,
    /// The dataset's cameras as JSON (intrinsics, camera-to-world in the
    /// OpenGL convention of three.js and Blender) and the run's background:
    /// to place a viewer at the views refnpr renders.
    Cameras,
}

impl Format {
    /// The file an export writes when none is named.
    pub fn default_file(self) -> &'static str {
        match self {
            Format::Splat => "splats.ply",
            Format::Mesh => "mesh.glb",
            Format::Video => "path.mp4",
            Format::Points => "points.ply",
            Format::Cameras => "cameras.json",
        }
    }
}

/// The choices of every format (each reads its own).
#[derive(Debug, Clone)]
pub struct ExportOptions {
    pub splat: splat::SplatOptions,
    /// The mesh's density level (None: `mesh::default_level`).
    pub level: Option<f32>,
    /// The mesh's most triangles (None: the iso-surface as marched).
    pub max_triangles: Option<usize>,
    /// The video's camera path, frame count and rate, and its width
    /// (None: the dataset's; the height follows the aspect).
    pub path: PathKind,
    pub frames: usize,
    pub fps: u32,
    pub width: Option<u32>,
    /// The ffmpeg executable.
    pub ffmpeg: String,
    /// Every `stride`-th pixel of the training views becomes a point.
    pub stride: usize,
}

impl Default for ExportOptions {
    fn default() -> Self {
        Self {
            splat: splat::SplatOptions::default(),
            level: None,
            max_triangles: None,
            path: PathKind::Orbit,
            frames: 120,
            fps: 30,
            width: None,
            ffmpeg: "ffmpeg".into(),
            stride: 2,
        }
    }
}

/// What an export wrote.
#[derive(Debug, Clone)]
pub struct ExportReport {
    pub file: PathBuf,
    pub bytes: u64,
    /// What was written, for a person ("104,211 splats, SH degree 2").
    pub summary: String,
    pub seconds: f64,
}

/// Whether an export needs the run's dataset (its cameras).
pub fn needs_dataset(format: Format, options: &ExportOptions) -> bool {
    match format {
        Format::Splat => options.splat.viewer_blur > 0.0,
        Format::Mesh => false,
        Format::Video | Format::Points | Format::Cameras => true,
    }
}

/// Exports `ck`'s field as `format` into `out`; `dataset` (the run's
/// cameras) is read only by the formats that need it (`needs_dataset`).
pub fn export(
    ck: &Checkpoint,
    dataset: Option<&Dataset>,
    format: Format,
    out: &Path,
    options: &ExportOptions,
    progress: &dyn Progress,
) -> Result<ExportReport> {
    let started = Instant::now();
    let source = ck.source.display().to_string();
    let ndc = ck.meta.ndc.as_ref();
    let cameras_of = || dataset.ok_or_else(|| anyhow::anyhow!("a {format:?} export needs the run's dataset"));
    let summary = match format {
        Format::Splat => {
            let cameras: Vec<Camera> = match dataset {
                Some(d) if options.splat.viewer_blur > 0.0 => d.train.iter().map(|v| v.camera).collect(),
                _ => Vec::new(),
            };
            let s = splat::splats_of(&ck.grid, ndc, &options.splat, &cameras)?;
            if s.is_empty() {
                bail!("{source}: no point of the field is opaque enough for a splat (is the run trained?)");
            }
            write_ply(out, &splat::to_ply(&s, &source))?;
            format!("{} splats, SH degree {}", s.len(), s.sh_degree)
        }
        Format::Mesh => {
            let level = options.level.unwrap_or_else(|| mesh::default_level(&ck.grid, ndc));
            let mut m = mesh::mesh_of(&ck.grid, ndc, level)?;
            if let Some(target) = options.max_triangles {
                if target < 4 {
                    bail!("a mesh of at most {target} triangles cannot enclose anything: ask for 4 or more");
                }
                m = decimate::decimate(&m, target);
            }
            match extension(out).as_str() {
                "glb" => files::write_atomic(out, |w| gltf::write_glb(&m, w))?,
                "ply" => write_ply(out, &mesh::to_ply(&m, &source))?,
                other => bail!("{}: a mesh is written as .glb or .ply, not .{other}", out.display()),
            }
            format!("{} vertices, {} triangles at density level {level}", m.positions.len(), m.triangles.len())
        }
        Format::Video => {
            let mut cameras = path_cameras(cameras_of()?, options.path, options.frames)?;
            if let Some(w) = options.width {
                for c in &mut cameras {
                    let k = c.intrinsics;
                    let h = ((w as f32 * k.height as f32 / k.width as f32).round() as u32).max(1);
                    c.intrinsics = k.resized(w.max(1), h);
                }
            }
            let frames = render(ck, &cameras, progress);
            video::write_mp4(&frames, options.fps, out, &options.ffmpeg)?;
            format!("{} frames at {} fps", frames.len(), options.fps)
        }
        Format::Points => {
            let cameras: Vec<_> = cameras_of()?.train.iter().map(|v| v.camera).collect();
            let p = points::points_of(ck, &cameras, options.stride, progress);
            if p.positions.is_empty() {
                bail!("{source}: no training view's ray hits the surface; nothing to write");
            }
            write_ply(out, &points::to_ply(&p, &source))?;
            format!("{} points from {} views", p.positions.len(), cameras.len())
        }
        Format::Cameras => {
            let d = cameras_of()?;
            let json = cameras_json(d, ck);
            files::write_json(out, &json)?;
            format!("{} training and {} test cameras", d.train.len(), d.test.len())
        }
    };
    let bytes = std::fs::metadata(out).map_err(|e| files::io_error(e, out))?.len();
    Ok(ExportReport { file: out.to_path_buf(), bytes, summary, seconds: started.elapsed().as_secs_f64() })
}

/// The cameras of `dataset` and `ck`'s background as JSON: per view its
/// name, size, pinhole intrinsics in pixels and the camera-to-world matrix
/// as 16 numbers, column-major (OpenGL convention: x right, y up, looking
/// down -z, as three.js and Blender; world units of the run's field).
pub fn cameras_json(dataset: &Dataset, ck: &Checkpoint) -> serde_json::Value {
    let views = |views: &[crate::scene::data::View]| -> Vec<serde_json::Value> {
        views
            .iter()
            .map(|v| {
                let k = v.camera.intrinsics;
                serde_json::json!({
                    "name": v.name, "width": k.width, "height": k.height,
                    "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy,
                    "c2w": v.camera.c2w.to_cols_array(),
                })
            })
            .collect()
    };
    serde_json::json!({
        "background": ck.meta.background,
        "forward_facing": ck.meta.ndc.is_some(),
        "train": views(&dataset.train),
        "test": views(&dataset.test),
    })
}

/// The cameras' views, with progress.
fn render(ck: &Checkpoint, cameras: &[Camera], progress: &dyn Progress) -> Vec<Image> {
    let started = Instant::now();
    progress.event(Event::Start { phase: Phase::Render, done: 0, total: cameras.len() });
    let renderer = ck.renderer();
    let mut frames = Vec::with_capacity(cameras.len());
    for (i, c) in cameras.iter().enumerate() {
        frames.push(renderer.view(c).image);
        progress.event(Event::Step { phase: Phase::Render, done: i + 1, total: cameras.len(), message: String::new() });
    }
    progress.event(Event::PhaseDone { phase: Phase::Render, seconds: started.elapsed().as_secs_f64() });
    frames
}

fn write_ply(out: &Path, ply: &ply::Ply) -> Result<()> {
    files::write_atomic(out, |w| ply.write(w))
}

fn extension(path: &Path) -> String {
    path.extension().map(|e| e.to_string_lossy().to_lowercase()).unwrap_or_default()
}
