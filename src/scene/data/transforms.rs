//! One `transforms.json`, as nerfstudio (`ns-process-data`) and
//! instant-ngp (`colmap2nerf.py`) write it: OpenGL camera-to-world
//! `transform_matrix` per frame (used as they are: `applied_transform`,
//! when present, is what the writer already applied), intrinsics global or
//! per frame (`fl_x fl_y cx cy w h`, `camera_angle_x` / `camera_angle_y`
//! when there is no focal length), distortion `k1 k2 k3 p1 p2` (removed at
//! load), `mask_path` masks (zero = not the scene: composited over the
//! background colour, as a Blender image's alpha).
//!
//! The split: nerfstudio's `train_filenames` / `val_filenames` /
//! `test_filenames` lists when present (the test split is the test list,
//! else the val list; train is the train list, else every other frame),
//! otherwise every 8th frame, in file order, is held out for testing.

use super::posed::{self, Capture};
use super::undistort::{Lens, undistort};
use super::{Dataset, DatasetKind, LoadOptions, View, check_sizes, read_rgb};
use crate::scene::camera::{Camera, Intrinsics, pose_is_valid};
use crate::util::input::InputError;
use anyhow::{Context, Result};
use glam::{Mat3, Mat4};
use rayon::prelude::*;
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// Intrinsics and distortion, as the file's top level or a frame holds them.
#[derive(Debug, Default, Clone, Deserialize)]
struct Lensing {
    camera_model: Option<String>,
    fl_x: Option<f64>,
    fl_y: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    w: Option<f64>,
    h: Option<f64>,
    camera_angle_x: Option<f64>,
    camera_angle_y: Option<f64>,
    k1: Option<f64>,
    k2: Option<f64>,
    k3: Option<f64>,
    k4: Option<f64>,
    p1: Option<f64>,
    p2: Option<f64>,
}

impl Lensing {
    /// This frame's values where it has them, the file's otherwise.
    fn over(&self, base: &Lensing) -> Lensing {
        macro_rules! pick {
            ($($f:ident),*) => { Lensing { $($f: self.$f.clone().or(base.$f.clone())),* } };
        }
        pick!(camera_model, fl_x, fl_y, cx, cy, w, h, camera_angle_x, camera_angle_y, k1, k2, k3, k4, p1, p2)
    }

    /// The lens of an image of `width` x `height` (the size stored on disk).
    fn lens(&self, width: u32, height: u32) -> std::result::Result<Lens, String> {
        match self.camera_model.as_deref() {
            None | Some("OPENCV" | "PINHOLE" | "SIMPLE_PINHOLE" | "SIMPLE_RADIAL" | "RADIAL") => {}
            Some(other) => {
                return Err(format!("camera_model {other} is not supported (OPENCV and the pinhole models are)"));
            }
        }
        if self.k4.is_some_and(|k| k != 0.0) {
            return Err("k4 (a fisheye term) is not supported".into());
        }
        let (w, h) = (self.w.unwrap_or(width as f64), self.h.unwrap_or(height as f64));
        if (w.round() as u32, h.round() as u32) != (width, height) {
            return Err(format!("w x h say {w}x{h} but the image is {width}x{height}"));
        }
        let from_angle = |size: f64, angle: Option<f64>| angle.map(|a| 0.5 * size / (0.5 * a).tan());
        let fx = self.fl_x.or(from_angle(w, self.camera_angle_x)).or(self.fl_y);
        let fy = self.fl_y.or(from_angle(h, self.camera_angle_y)).or(fx);
        let (Some(fx), Some(fy)) = (fx, fy) else {
            return Err("no focal length: give fl_x (and fl_y) or camera_angle_x".into());
        };
        let lens = Lens {
            k1: self.k1.unwrap_or(0.0),
            k2: self.k2.unwrap_or(0.0),
            k3: self.k3.unwrap_or(0.0),
            p1: self.p1.unwrap_or(0.0),
            p2: self.p2.unwrap_or(0.0),
            ..Lens::pinhole(fx, fy, self.cx.unwrap_or(w / 2.0), self.cy.unwrap_or(h / 2.0))
        };
        let all = [lens.fx, lens.fy, lens.cx, lens.cy, lens.k1, lens.k2, lens.k3, lens.p1, lens.p2];
        if !(all.iter().all(|v| v.is_finite()) && fx > 0.0 && fy > 0.0) {
            return Err(format!("intrinsics {all:?} are not finite positive focal lengths and finite terms"));
        }
        Ok(lens)
    }
}

#[derive(Debug, Deserialize)]
struct Frame {
    file_path: String,
    transform_matrix: Vec<Vec<f64>>,
    mask_path: Option<String>,
    #[serde(flatten)]
    lensing: Lensing,
}

#[derive(Debug, Deserialize)]
struct TransformsFile {
    frames: Vec<Frame>,
    #[serde(flatten)]
    lensing: Lensing,
    applied_transform: Option<Vec<Vec<f64>>>,
    train_filenames: Option<Vec<String>>,
    val_filenames: Option<Vec<String>>,
    test_filenames: Option<Vec<String>>,
}

fn malformed(path: &Path, message: String) -> anyhow::Error {
    InputError::Malformed { path: path.into(), message: format!("{}: {message}", path.display()) }.into()
}

/// A frame's pose: a 4x4 (or 3x4) rigid OpenGL camera-to-world matrix.
fn pose(m: &[Vec<f64>]) -> std::result::Result<Mat4, String> {
    if !(m.len() == 3 || m.len() == 4) || m.iter().any(|r| r.len() != 4) {
        return Err("transform_matrix must be 4x4 (or 3x4)".into());
    }
    let mut a = [[0.0f32; 4]; 4];
    a[3][3] = 1.0;
    for (r, row) in m.iter().enumerate() {
        for (c, v) in row.iter().enumerate() {
            a[r][c] = *v as f32;
        }
    }
    // JSON rows -> glam columns.
    let c2w = Mat4::from_cols_array_2d(&a).transpose();
    if !pose_is_valid(&c2w) {
        return Err("transform_matrix holds NaN/inf or a singular rotation".into());
    }
    let r = Mat3::from_mat4(c2w);
    let off = (r.transpose() * r - Mat3::IDENTITY).to_cols_array().iter().fold(0.0f32, |a, v| a.max(v.abs()));
    if off > 1e-3 || r.determinant() < 0.0 || c2w.row(3) != glam::Vec4::W {
        return Err(format!("transform_matrix is not a rigid transform (rotation off orthonormal by {off:.2e})"));
    }
    Ok(c2w)
}

fn read_file(dir: &Path) -> Result<(TransformsFile, PathBuf)> {
    let path = dir.join("transforms.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("cannot read {}", path.display()))?;
    let file = parse(&text).map_err(|m| malformed(&path, m))?;
    Ok((file, path))
}

/// Parses and checks a `transforms.json` text (every pose rigid, an
/// `applied_transform` 3x4 or 4x4): what the fuzzer drives.
fn parse(text: &str) -> std::result::Result<TransformsFile, String> {
    let file: TransformsFile = serde_json::from_str(text).map_err(|e| format!("malformed JSON: {e}"))?;
    if file.frames.is_empty() {
        return Err("lists no frames".into());
    }
    for f in &file.frames {
        pose(&f.transform_matrix).map_err(|m| format!("frame {}: {m}", f.file_path))?;
    }
    if let Some(t) = &file.applied_transform
        && (!(t.len() == 3 || t.len() == 4) || t.iter().any(|r| r.len() != 4 || r.iter().any(|v| !v.is_finite())))
    {
        return Err("applied_transform must be a finite 3x4 or 4x4 matrix".into());
    }
    Ok(file)
}

/// Parses a `transforms.json` text, returning its frame count (the fuzzer's entry).
pub fn parse_text(text: &str) -> std::result::Result<usize, String> {
    parse(text).map(|f| f.frames.len())
}

/// The frames' poses alone (no image decoded).
pub(crate) fn poses(dir: &Path) -> Result<Vec<Mat4>> {
    let (file, path) = read_file(dir)?;
    file.frames.iter().map(|f| pose(&f.transform_matrix).map_err(|m| malformed(&path, m))).collect()
}

/// Which frames are held out for testing (see the module's doc).
fn test_frames(file: &TransformsFile) -> Vec<bool> {
    let norm = |s: &str| s.trim_start_matches("./").to_string();
    let listed = |l: &Option<Vec<String>>| l.as_ref().map(|v| v.iter().map(|s| norm(s)).collect::<Vec<_>>());
    match listed(&file.test_filenames).or(listed(&file.val_filenames)) {
        Some(test) => file.frames.iter().map(|f| test.contains(&norm(&f.file_path))).collect(),
        None => posed::every_nth_test(file.frames.len()),
    }
}

/// An image's mask (`mask_path`) applied: pixels where it is 0 become the background.
fn apply_mask(rgb: &mut [f32], mask_path: &Path, size: (u32, u32), downscale: u32, background: [f32; 3]) -> Result<()> {
    let mask =
        image::open(mask_path).map_err(|e| malformed(mask_path, format!("cannot decode the mask: {e}")))?.to_luma32f();
    let (w, h) = size;
    if (mask.width() / downscale.max(1), mask.height() / downscale.max(1)) != (w, h) {
        let message = format!(
            "{}: the mask is {}x{}, its image {}x{} (masks must have their image's size)",
            mask_path.display(),
            mask.width(),
            mask.height(),
            w * downscale,
            h * downscale
        );
        return Err(InputError::WrongSize { path: mask_path.into(), message }.into());
    }
    let mask = image::imageops::resize(&mask, w, h, image::imageops::FilterType::Triangle);
    for (px, m) in rgb.chunks_mut(3).zip(mask.pixels()) {
        let a = m[0].clamp(0.0, 1.0);
        for c in 0..3 {
            px[c] = px[c] * a + background[c] * (1.0 - a);
        }
    }
    Ok(())
}

fn load_frame(dir: &Path, path: &Path, base: &Lensing, f: &Frame, opts: &LoadOptions) -> Result<View> {
    let rel = f.file_path.trim_start_matches("./");
    let img_path = dir.join(rel);
    if !img_path.exists() {
        let message =
            format!("{}: frame '{}' points to a missing image {}", path.display(), f.file_path, img_path.display());
        return Err(InputError::Missing { path: img_path, message }.into());
    }
    let c2w = pose(&f.transform_matrix).map_err(|m| malformed(path, m))?;
    let (w, h, mut rgb) = read_rgb(&img_path, opts.background, opts.downscale)?;
    let stored = image::image_dimensions(&img_path).with_context(|| format!("cannot read {}", img_path.display()))?;
    let lens = f
        .lensing
        .over(base)
        .lens(stored.0, stored.1)
        .map_err(|m| malformed(path, format!("frame {}: {m}", f.file_path)))?;
    let lens = lens.scaled(w as f64 / stored.0 as f64, h as f64 / stored.1 as f64);
    if let Some(m) = &f.mask_path {
        apply_mask(&mut rgb, &dir.join(m.trim_start_matches("./")), (w, h), opts.downscale, opts.background)?;
    }
    let rgb = if lens.is_distorted() { undistort(&rgb, w, h, &lens) } else { rgb };
    let intr = Intrinsics {
        width: w,
        height: h,
        fx: lens.fx as f32,
        fy: lens.fy as f32,
        cx: lens.cx as f32,
        cy: lens.cy as f32,
    };
    Ok(View { name: rel.to_string(), camera: Camera::new(intr, c2w), rgb })
}

pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let (file, path) = read_file(dir)?;
    let loaded: Vec<Result<View>> =
        file.frames.par_iter().map(|f| load_frame(dir, &path, &file.lensing, f, opts)).collect();
    let views: Vec<View> = loaded.into_iter().collect::<Result<_>>()?;
    check_sizes(&views, &views[0].camera.intrinsics, &path)?;
    // Frames in neither a train nor a test list (when the file has lists) are left out.
    let norm = |s: &String| s.trim_start_matches("./").to_string();
    let train: Option<Vec<String>> = file.train_filenames.as_ref().map(|l| l.iter().map(norm).collect());
    let (views, is_test): (Vec<View>, Vec<bool>) = views
        .into_iter()
        .zip(test_frames(&file))
        .filter(|(v, t)| *t || train.as_ref().is_none_or(|l| l.contains(&v.name)))
        .unzip();
    let capture =
        Capture { kind: DatasetKind::Transforms, root: dir, source: &path, views, is_test, points: Vec::new() };
    posed::assemble(capture, opts)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_frames_are_refused_with_their_reason() {
        let frame =
            |m: &str| format!(r#"{{"fl_x": 100, "frames": [{{"file_path": "a.png", "transform_matrix": {m}}}]}}"#);
        let rigid = "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";
        assert_eq!(parse_text(&frame(rigid)), Ok(1));
        let stretched = "[[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";
        assert!(parse_text(&frame(stretched)).unwrap_err().contains("not a rigid"));
        // serde_json reads no NaN literal: a NaN arrives as null or a string.
        assert!(parse_text(&frame("[[null,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]")).unwrap_err().contains("malformed"));
        assert!(parse_text(&frame("[[1,0,0],[0,1,0]]")).unwrap_err().contains("4x4"));
        assert!(parse_text(r#"{"frames": []}"#).unwrap_err().contains("no frames"));
    }

    #[test]
    fn intrinsics_come_from_the_frame_then_the_file_then_the_field_of_view() {
        let base = Lensing { fl_x: Some(100.0), cx: Some(40.0), ..Default::default() };
        let frame = Lensing { fl_y: Some(120.0), ..Default::default() };
        let lens = frame.over(&base).lens(80, 60).unwrap();
        assert_eq!((lens.fx, lens.fy, lens.cx, lens.cy), (100.0, 120.0, 40.0, 30.0));
        let angle = Lensing { camera_angle_x: Some(std::f64::consts::FRAC_PI_2), ..Default::default() };
        let lens = angle.lens(80, 60).unwrap();
        assert!((lens.fx - 40.0).abs() < 1e-9 && lens.fx == lens.fy);
        let wrong = Lensing { w: Some(81.0), ..base.clone() };
        assert!(wrong.lens(80, 60).unwrap_err().contains("81x60"));
        let fisheye = Lensing { camera_model: Some("OPENCV_FISHEYE".into()), ..base };
        assert!(fisheye.lens(80, 60).unwrap_err().contains("not supported"));
    }
}
