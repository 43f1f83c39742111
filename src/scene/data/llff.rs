//! LLFF forward-facing layout: `poses_bounds.npy` + `images[_N]/`.
//!
//! Follows the NeRF / Plenoxels conventions: axes [down, right, back] are
//! turned into [right, up, back], the scene is scaled so the nearest bound
//! sits at 1/0.75, poses are recentred on their average, every 8th image is
//! held out for testing, and rays are warped to NDC (near plane 1).

use super::{Dataset, DatasetKind, LoadOptions, View, check_pose, check_sizes, read_rgb};
use crate::scene::camera::{Camera, Intrinsics, NdcParams, average_pose, to_ndc};
use crate::util::npy;
use anyhow::{Context, Result, bail};
use glam::{Mat4, Vec3};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// Hold out every `LLFF_HOLD`-th image as the test split.
pub const LLFF_HOLD: usize = 8;

fn list_images(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot read {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            matches!(
                p.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).as_deref(),
                Some("png" | "jpg" | "jpeg")
            )
        })
        .collect();
    v.sort();
    Ok(v)
}

/// Picks the image folder for a downscale factor: `images_<f>/` when present,
/// else `images/` resized by f, else the most reduced `images_<n>/` with n
/// dividing f, resized by f / n (the LLFF archives ship `images_8/` alone);
/// with f = 1 and no `images/`, the first `images_<n>/` found (its own resolution).
pub(crate) fn image_folder(dir: &Path, factor: u32) -> Result<(PathBuf, u32)> {
    let exact = if factor > 1 { dir.join(format!("images_{factor}")) } else { dir.join("images") };
    if exact.is_dir() {
        return Ok((exact, 1));
    }
    if dir.join("images").is_dir() {
        return Ok((dir.join("images"), factor));
    }
    for n in [16, 8, 4, 2] {
        let p = dir.join(format!("images_{n}"));
        if factor > n && factor.is_multiple_of(n) && p.is_dir() {
            return Ok((p, factor / n));
        }
    }
    if factor == 1 {
        for f in [2, 4, 8, 16] {
            let p = dir.join(format!("images_{f}"));
            if p.is_dir() {
                return Ok((p, 1));
            }
        }
    }
    bail!("{}: no image folder (looked for images_{factor}/ and images/)", dir.display())
}

/// Margin added on each side of the rays' x/y extent, as a fraction of it.
const NDC_BOX_MARGIN: f32 = 0.02;
/// The largest |x| and |y| of the NDC box (fern needs 1.5).
const NDC_BOX_MAX: f32 = 3.0;

/// The NDC box the grid covers: z spans [-1, 1] (near plane to infinity);
/// x and y span what the rays of every view (train and test) reach, at least
/// [-1, 1]. The NDC warp is defined by the average camera, so the border rays
/// of the other cameras leave [-1, 1] sideways (on fern up to |x| = 1.44,
/// and 12-40% of each view's rays): a [-1, 1] box would cut them off and
/// render the background there. Plenoxels widens x/y by a fixed factor
/// (about 1.5); measuring the extent adapts it to the capture.
fn ndc_box(views: &[View], ndc: &NdcParams, source: &Path) -> (Vec3, Vec3, Option<String>) {
    let mut lo = Vec3::new(-1.0, -1.0, -1.0);
    let mut hi = Vec3::new(1.0, 1.0, 1.0);
    for v in views {
        let (w, h) = (v.camera.intrinsics.width, v.camera.intrinsics.height);
        // x_ndc and y_ndc at either end of a ray are projective functions of
        // the pixel position, so their extremes lie on the image border.
        let border = (0..w).flat_map(|x| [(x, 0), (x, h - 1)]).chain((0..h).flat_map(|y| [(0, y), (w - 1, y)]));
        for (x, y) in border {
            let r = to_ndc(v.camera.ray(x as f32, y as f32), ndc);
            // The ray starts on the near plane (z = -1) and reaches
            // infinity at z = 1.
            let far = r.origin + r.dir * ((1.0 - r.origin.z) / r.dir.z);
            for p in [r.origin, far] {
                if p.is_finite() {
                    lo = lo.min(p);
                    hi = hi.max(p);
                }
            }
        }
    }
    let margin = (hi - lo) * NDC_BOX_MARGIN;
    let (lo, hi) = (lo - margin, hi + margin);
    let mut warning = None;
    // A camera looking far off the average direction would stretch the box
    // (and the voxels) without bound: cap it, and say so.
    if lo.x < -NDC_BOX_MAX || lo.y < -NDC_BOX_MAX || hi.x > NDC_BOX_MAX || hi.y > NDC_BOX_MAX {
        warning = Some(format!(
            "{}: some views' rays reach NDC x/y {:?}..{:?}; the grid covers only up to ±{NDC_BOX_MAX} \
             (those rays render the background beyond it)",
            source.display(),
            lo.truncate(),
            hi.truncate()
        ));
    }
    let cap = Vec3::splat(NDC_BOX_MAX);
    (lo.max(-cap).with_z(-1.0), hi.min(cap).with_z(1.0), warning)
}

/// What `poses_bounds.npy` says besides the images.
struct LlffPoses {
    /// Camera-to-world, rescaled and centred.
    poses: Vec<Mat4>,
    /// (height, width, focal) of the full-size images.
    hwf: (f32, f32, f32),
    /// The scene's depth bounds, rescaled.
    near_far: (f32, f32),
}

/// The poses of `poses_bounds.npy` (`n` rows of a 3x5 matrix, then near
/// and far), rescaled so the nearest bound is at 4/3 and centred on the
/// average pose; also (height, width, focal) of the full-size images and
/// the rescaled (near, far) of the scene.
fn read_poses(data: &[f64], n: usize, npy_path: &Path) -> Result<LlffPoses> {
    let mut poses = Vec::with_capacity(n);
    let mut bounds = Vec::with_capacity(n);
    let mut hwf = (0.0f32, 0.0f32, 0.0f32);
    for i in 0..n {
        let row = &data[i * 17..(i + 1) * 17];
        let m = |r: usize, c: usize| row[r * 5 + c] as f32;
        let col = |c: usize| Vec3::new(m(0, c), m(1, c), m(2, c));
        // [down, right, back] -> [right, up, back]: x = old y, y = -old x.
        let x = col(1);
        let y = -col(0);
        let z = col(2);
        let t = col(3);
        hwf = (m(0, 4), m(1, 4), m(2, 4));
        poses.push(Mat4::from_cols(x.extend(0.0), y.extend(0.0), z.extend(0.0), t.extend(1.0)));
        bounds.push((row[15] as f32, row[16] as f32));
    }
    let min_near = bounds.iter().map(|b| b.0).fold(f32::INFINITY, f32::min);
    let max_far = bounds.iter().map(|b| b.1).fold(0.0f32, f32::max);
    let (poses, near_far) = normalise_forward(&poses, (min_near, max_far), npy_path)?;
    Ok(LlffPoses { poses, hwf, near_far })
}

/// The NeRF / Plenoxels normalisation of a forward-facing capture: the
/// scene scaled so the nearest depth bound sits at 4/3 (NDC's near plane is
/// at 1), the poses re-expressed relative to their average pose; returns
/// them and the rescaled (near, far).
pub(crate) fn normalise_forward(
    poses: &[Mat4],
    (min_near, max_far): (f32, f32),
    source: &Path,
) -> Result<(Vec<Mat4>, (f32, f32))> {
    if min_near.is_nan() || min_near <= 0.0 {
        bail!("{}: near bounds must be positive (found {min_near})", source.display());
    }
    let scale = 1.0 / (min_near * 0.75);
    let mut poses = poses.to_vec();
    for p in poses.iter_mut() {
        p.w_axis = (p.w_axis.truncate() * scale).extend(1.0);
    }
    let avg = average_pose(&poses);
    let inv = avg.inverse();
    let poses: Vec<Mat4> = poses.iter().map(|p| inv * *p).collect();
    for (i, p) in poses.iter().enumerate() {
        check_pose(p, source, &format!("image {i}"))?;
    }
    Ok((poses, (min_near * scale, max_far * scale)))
}

/// The views: each image (in parallel) with its pose and a centred pinhole,
/// the focal length `full_f` scaled from the full width `full_w`.
fn read_views(
    files: &[PathBuf],
    poses: &[Mat4],
    (full_w, full_f): (f32, f32),
    background: [f32; 3],
    resize: u32,
) -> Result<Vec<View>> {
    let loaded: Vec<Result<(u32, u32, Vec<f32>)>> = files.par_iter().map(|f| read_rgb(f, background, resize)).collect();
    let mut views = Vec::with_capacity(files.len());
    for (i, (img, file)) in loaded.into_iter().zip(files).enumerate() {
        let (w, h, rgb) = img?;
        let f = full_f * w as f32 / full_w;
        let intr = Intrinsics { width: w, height: h, fx: f, fy: f, cx: w as f32 * 0.5, cy: h as f32 * 0.5 };
        let name = file.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| format!("{i}"));
        views.push(View { name, camera: Camera::new(intr, poses[i]), rgb });
    }
    Ok(views)
}

pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let npy_path = dir.join("poses_bounds.npy");
    let arr = npy::read(&npy_path)?;
    if arr.shape.len() != 2 || arr.shape[1] != 17 {
        bail!("{}: expected shape (N, 17), found {:?}", npy_path.display(), arr.shape);
    }
    let n = arr.shape[0];
    if n == 0 {
        bail!("{}: holds no poses", npy_path.display());
    }
    if arr.data.iter().any(|v| !v.is_finite()) {
        bail!("{}: contains NaN or infinite values", npy_path.display());
    }
    let (folder, resize) = image_folder(dir, opts.downscale)?;
    let files = list_images(&folder)?;
    if files.len() != n {
        bail!("{}: {} poses but {} images in {}", npy_path.display(), n, files.len(), folder.display());
    }
    let LlffPoses { poses, hwf, near_far: (near, far) } = read_poses(&arr.data, n, &npy_path)?;
    let views = read_views(&files, &poses, (hwf.1, hwf.2), opts.background, resize)?;
    let (full_h, full_w) = (hwf.0, hwf.1);
    let intr = views[0].camera.intrinsics;
    check_sizes(&views, &intr, &folder)?;
    if (intr.height as f32 / intr.width as f32 - full_h / full_w).abs() > 0.02 {
        bail!(
            "{}: images are {}x{} but poses_bounds.npy says {}x{} (aspect ratios differ)",
            folder.display(),
            intr.width,
            intr.height,
            full_w,
            full_h
        );
    }
    let is_test: Vec<bool> = (0..views.len()).map(|i| i % LLFF_HOLD == 0).collect();
    let setup = Forward { kind: DatasetKind::Llff, root: dir, source: &npy_path, near_far: (near, far) };
    Ok(forward_facing(setup, views, &is_test, opts))
}

/// A forward-facing capture whose poses `normalise_forward` has made.
pub(crate) struct Forward<'a> {
    pub kind: DatasetKind,
    pub root: &'a Path,
    /// The file named in warnings.
    pub source: &'a Path,
    /// The rescaled depth bounds.
    pub near_far: (f32, f32),
}

/// The dataset of a forward-facing capture: rays warped to NDC (near plane
/// 1, the first view's intrinsics), the grid's box what the rays reach,
/// the views split by `is_test`.
pub(crate) fn forward_facing(setup: Forward, views: Vec<View>, is_test: &[bool], opts: &LoadOptions) -> Dataset {
    let intr = views[0].camera.intrinsics;
    let ndc = NdcParams { width: intr.width as f32, height: intr.height as f32, focal: intr.fx, near: 1.0 };
    let (mut bbox_min, mut bbox_max, warning) = ndc_box(&views, &ndc, setup.source);
    if let Some([lo, hi]) = opts.bbox {
        (bbox_min, bbox_max) = (Vec3::from(lo), Vec3::from(hi));
    }
    let mut train = Vec::new();
    let mut test = Vec::new();
    for (v, &t) in views.into_iter().zip(is_test) {
        if t { test.push(v) } else { train.push(v) }
    }
    Dataset {
        kind: setup.kind,
        root: setup.root.to_path_buf(),
        train,
        val: Vec::new(),
        test,
        background: opts.background,
        bbox_min,
        bbox_max,
        ndc: Some(ndc),
        near_far: Some(setup.near_far),
        warnings: warning.into_iter().collect(),
        notes: Vec::new(),
        source_frame: None,
    }
}
