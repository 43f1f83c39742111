//! Blender / NeRF-synthetic layout: `transforms_{train,val,test}.json`.

use super::{Dataset, DatasetKind, LoadOptions, View, check_pose, check_sizes, read_rgb};
use crate::scene::camera::{Camera, Intrinsics};
use anyhow::{Context, Result, bail};
use glam::{Mat4, Vec3};
use rayon::prelude::*;
use serde::Deserialize;
use std::path::Path;

#[derive(Deserialize)]
struct Transforms {
    camera_angle_x: f32,
    frames: Vec<Frame>,
    /// Optional scene box (our procedural scenes write it); default [-1.5, 1.5]^3.
    #[serde(default)]
    bbox: Option<[[f32; 3]; 2]>,
}

#[derive(Deserialize)]
struct Frame {
    file_path: String,
    transform_matrix: [[f32; 4]; 4],
}

/// A split's views, and the scene box its file gives (`bbox`), if any.
type SplitViews = (Vec<View>, Option<[[f32; 3]; 2]>);

pub(crate) fn load_split(dir: &Path, split: &str, opts: &LoadOptions) -> Result<SplitViews> {
    let json_path = dir.join(format!("transforms_{split}.json"));
    if !json_path.exists() {
        if split == "val" {
            return Ok((Vec::new(), None));
        }
        bail!("{} is missing", json_path.display());
    }
    let text = std::fs::read_to_string(&json_path).with_context(|| format!("cannot read {}", json_path.display()))?;
    let tf: Transforms =
        serde_json::from_str(&text).with_context(|| format!("{} is malformed", json_path.display()))?;
    if !(tf.camera_angle_x.is_finite() && tf.camera_angle_x > 0.0 && tf.camera_angle_x < std::f32::consts::PI) {
        bail!("{}: camera_angle_x = {} is not a valid field of view", json_path.display(), tf.camera_angle_x);
    }
    let views: Vec<Result<View>> = tf
        .frames
        .par_iter()
        .map(|f| {
            let rel = f.file_path.trim_start_matches("./");
            let mut img_path = dir.join(rel);
            if img_path.extension().is_none() {
                img_path.set_extension("png");
            }
            if !img_path.exists() {
                bail!(
                    "{}: frame '{}' points to a missing image {}",
                    json_path.display(),
                    f.file_path,
                    img_path.display()
                );
            }
            let m = f.transform_matrix;
            // JSON rows -> glam columns.
            let c2w = Mat4::from_cols_array_2d(&m).transpose();
            check_pose(&c2w, &json_path, &f.file_path)?;
            let (w, h, rgb) = read_rgb(&img_path, opts.background, opts.downscale)?;
            let intr = Intrinsics::from_fov_x(w, h, tf.camera_angle_x);
            Ok(View { name: rel.to_string(), camera: Camera::new(intr, c2w), rgb })
        })
        .collect();
    let views: Vec<View> = views.into_iter().collect::<Result<_>>()?;
    if let Some(first) = views.first() {
        check_sizes(&views, &first.camera.intrinsics, &json_path)?;
    }
    Ok((views, tf.bbox))
}

pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let (train, bbox) = load_split(dir, "train", opts)?;
    let (val, _) = load_split(dir, "val", opts)?;
    let (test, _) = load_split(dir, "test", opts)?;
    if train.is_empty() {
        bail!("{}: transforms_train.json lists no frames", dir.display());
    }
    let size = train[0].camera.intrinsics;
    for (name, split) in [("val", &val), ("test", &test)] {
        if let Some(v) = split.first()
            && (v.camera.intrinsics.width, v.camera.intrinsics.height) != (size.width, size.height)
        {
            bail!(
                "{}: {name} images are {}x{}, train images {}x{}",
                dir.display(),
                v.camera.intrinsics.width,
                v.camera.intrinsics.height,
                size.width,
                size.height
            );
        }
    }
    let [lo, hi] = opts.bbox.or(bbox).unwrap_or([[-1.5; 3], [1.5; 3]]);
    Ok(Dataset {
        kind: DatasetKind::Blender,
        root: dir.to_path_buf(),
        train,
        val,
        test,
        background: opts.background,
        bbox_min: Vec3::from(lo),
        bbox_max: Vec3::from(hi),
        ndc: None,
        near_far: None,
        warnings: Vec::new(),
        notes: Vec::new(),
        source_frame: None,
    })
}
