//! NSVF / Tanks&Temples layout: `rgb/`, `pose/`, `intrinsics.txt`, optional
//! `bbox.txt`; file prefixes 0_ / 1_ / 2_ mark train / val / test.
//!
//! Poses are OpenCV camera-to-world (x right, y down, z forward) and are
//! turned into the OpenGL convention. The scene is normalised so that the
//! foreground box (from `bbox.txt`, else around the cameras' focus) is
//! [-1, 1]^3: the radiance grid covers that box, and everything outside it is
//! left to the background model (see `background` in docs/architecture.md's design
//! section: a constant colour blended with the remaining transmittance).

use super::{Dataset, DatasetKind, LoadOptions, View, check_pose, check_sizes, read_rgb};
use crate::scene::camera::{Camera, Intrinsics};
use anyhow::{Context, Result, bail};
use glam::{Mat4, Vec3};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

fn numbers(path: &Path) -> Result<Vec<f32>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    text.split_whitespace()
        .map(|s| s.parse::<f32>().with_context(|| format!("{}: '{s}' is not a number", path.display())))
        .collect()
}

/// Reads `intrinsics.txt`: a 4x4 (or 3x3) K matrix, or the DeepVoxels form `f cx cy 0 ...`.
fn read_intrinsics(path: &Path) -> Result<(f32, f32, f32, f32)> {
    let v = numbers(path)?;
    match v.len() {
        16 => Ok((v[0], v[5], v[2], v[6])),
        9 => Ok((v[0], v[4], v[2], v[5])),
        n if n >= 3 => Ok((v[0], v[0], v[1], v[2])),
        _ => bail!("{}: expected a 4x4 / 3x3 matrix or 'f cx cy', found {} numbers", path.display(), v.len()),
    }
}

/// An image as loaded: name, camera-to-world, width, height, RGB.
type LoadedImage = (String, Mat4, u32, u32, Vec<f32>);

/// (name, image, pose file) of every image in `rgb/`, sorted by name; an
/// image without its `pose/NAME.txt` is an error.
fn list_entries(dir: &Path, rgb_dir: &Path) -> Result<Vec<(String, PathBuf, PathBuf)>> {
    let mut names: Vec<PathBuf> = std::fs::read_dir(rgb_dir)
        .with_context(|| format!("cannot read {}", rgb_dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    names.sort();
    let mut entries = Vec::new();
    for img in names {
        let Some(stem) = img.file_stem().map(|s| s.to_string_lossy().into_owned()) else { continue };
        let pose = dir.join("pose").join(format!("{stem}.txt"));
        if !pose.exists() {
            bail!("{}: image {} has no pose file {}", dir.display(), img.display(), pose.display());
        }
        entries.push((stem, img, pose));
    }
    Ok(entries)
}

/// A camera-to-world pose file (4x4, or 3x4 with the last row implied), in
/// OpenCV axes, as an OpenGL camera-to-world matrix.
fn read_pose(pose: &Path, stem: &str) -> Result<Mat4> {
    let v = numbers(pose)?;
    if v.len() < 12 {
        bail!("{}: expected a 4x4 matrix, found {} numbers", pose.display(), v.len());
    }
    let mut a = [0.0f32; 16];
    a[..v.len().min(16)].copy_from_slice(&v[..v.len().min(16)]);
    if v.len() < 16 {
        a[15] = 1.0;
    }
    let flip = Mat4::from_diagonal(glam::Vec4::new(1.0, -1.0, -1.0, 1.0));
    let c2w = Mat4::from_cols_array(&a).transpose() * flip;
    check_pose(&c2w, pose, stem)?;
    Ok(c2w)
}

/// The foreground box as (centre, half side): `bbox.txt` when present, else
/// around the camera centres (half their mean distance from their mean).
fn scene_box(dir: &Path, cameras: &[Vec3]) -> Result<(Vec3, f32)> {
    let bbox_path = dir.join("bbox.txt");
    let (centre, half) = if bbox_path.exists() {
        let b = numbers(&bbox_path)?;
        if b.len() < 6 {
            bail!("{}: expected xmin ymin zmin xmax ymax zmax", bbox_path.display());
        }
        let (lo, hi) = (Vec3::new(b[0], b[1], b[2]), Vec3::new(b[3], b[4], b[5]));
        ((lo + hi) * 0.5, ((hi - lo) * 0.5).max_element())
    } else {
        let centre = cameras.iter().sum::<Vec3>() / cameras.len() as f32;
        let mean_dist = cameras.iter().map(|c| (*c - centre).length()).sum::<f32>() / cameras.len() as f32;
        (centre, 0.5 * mean_dist)
    };
    if half.is_nan() || half <= 0.0 {
        bail!("{}: cannot find a scene box (degenerate bounds)", dir.display());
    }
    Ok((centre, half))
}

pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let k_path = dir.join("intrinsics.txt");
    if !k_path.exists() {
        bail!("{} is missing", k_path.display());
    }
    let (fx, fy, cx, cy) = read_intrinsics(&k_path)?;
    let rgb_dir = dir.join("rgb");
    let entries = list_entries(dir, &rgb_dir)?;
    let loaded: Vec<Result<LoadedImage>> = entries
        .par_iter()
        .map(|(stem, img, pose)| {
            let c2w = read_pose(pose, stem)?;
            let (w, h, rgb) = read_rgb(img, opts.background, opts.downscale)?;
            Ok((stem.clone(), c2w, w, h, rgb))
        })
        .collect();
    let loaded: Vec<_> = loaded.into_iter().collect::<Result<_>>()?;
    if loaded.is_empty() {
        bail!("{}: rgb/ holds no images", dir.display());
    }
    // Normalise: foreground box -> [-1, 1]^3.
    let cameras: Vec<Vec3> = loaded.iter().map(|l| l.1.w_axis.truncate()).collect();
    let (centre, half) = scene_box(dir, &cameras)?;
    let (mut train, mut val, mut test) = (Vec::new(), Vec::new(), Vec::new());
    for (stem, mut c2w, w, h, rgb) in loaded {
        let (w0, _h0) = (w * opts.downscale, h * opts.downscale);
        let s = w as f32 / w0 as f32;
        let intr = Intrinsics { width: w, height: h, fx: fx * s, fy: fy * s, cx: cx * s, cy: cy * s };
        c2w.w_axis = ((c2w.w_axis.truncate() - centre) / half).extend(1.0);
        let view = View { name: stem.clone(), camera: Camera::new(intr, c2w), rgb };
        match stem.split('_').next() {
            Some("0") => train.push(view),
            Some("1") => val.push(view),
            Some("2") => test.push(view),
            _ => bail!("{}: image name '{stem}' lacks a 0_/1_/2_ split prefix", dir.display()),
        }
    }
    if let Some(first) = train.first() {
        let intr = first.camera.intrinsics;
        for split in [&train, &val, &test] {
            check_sizes(split, &intr, &rgb_dir)?;
        }
    }
    if test.is_empty() && !val.is_empty() {
        test = val.clone();
    }
    Ok(Dataset {
        kind: DatasetKind::Nsvf,
        root: dir.to_path_buf(),
        train,
        val,
        test,
        background: opts.background,
        bbox_min: opts.bbox.map_or(Vec3::splat(-1.0), |b| Vec3::from(b[0])),
        bbox_max: opts.bbox.map_or(Vec3::splat(1.0), |b| Vec3::from(b[1])),
        ndc: None,
        near_far: None,
        warnings: Vec::new(),
        notes: Vec::new(),
        source_frame: None,
    })
}
