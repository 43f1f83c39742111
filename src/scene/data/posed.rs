//! What a capture made with a camera (a COLMAP model, a `transforms.json`)
//! needs beyond its poses: whether it is forward-facing or goes around the
//! scene, the box the grid covers, and a frame the render paths and the
//! training defaults expect.
//!
//! Forward-facing captures get the LLFF set-up (`llff::normalise_forward`,
//! NDC), their depth bounds from the sparse points. Captures around the
//! scene are moved into the frame of the Blender scenes: up (the mean of
//! the cameras' up vectors) along +z, the box centred on the origin and
//! scaled to [-1.5, 1.5] on its longest side, which is what the Blender
//! training defaults (grid resolution, step, density init) are tuned for.

use super::llff::{self, Forward, LLFF_HOLD};
use super::{Dataset, DatasetKind, LoadOptions, Shape, SourceFrame, View};
use crate::scene::camera::percentile;
use anyhow::{Result, bail};
use glam::{Mat3, Mat4, Quat, Vec3};
use std::path::Path;

/// The widest angle between a camera's viewing direction and the mean one
/// at which a capture still counts as forward-facing (LLFF's scenes: under
/// 20 degrees; a half orbit: 90).
pub const FORWARD_MAX_DEGREES: f32 = 45.0;

/// Half the side of the box a capture around the scene is scaled to.
const AROUND_HALF_SIDE: f32 = 1.5;

/// How much larger than the sparse points' 2nd-98th percentiles the box of a
/// capture around the scene is. Sparse points miss thin, untextured
/// extremities, and a box that cuts the scene costs far more than a coarser
/// voxel: lego captured through COLMAP fitted to 27.3 dB with a 10 % margin
/// (training views fitted to 28 dB against 32 through the Blender loader),
/// 29.9 dB with this 50 % (30.95 through the Blender loader).
const POINTS_BOX_MARGIN: f32 = 1.5;

/// The widest angle (degrees) between a camera's viewing direction and the mean viewing direction.
pub fn viewing_spread(c2ws: &[Mat4]) -> f32 {
    let forward = |m: &Mat4| -m.z_axis.truncate().normalize();
    let mean = c2ws.iter().map(forward).sum::<Vec3>().normalize_or_zero();
    if mean == Vec3::ZERO {
        return 180.0;
    }
    c2ws.iter().map(|m| forward(m).dot(mean).clamp(-1.0, 1.0).acos().to_degrees()).fold(0.0, f32::max)
}

/// The shape a capture is treated as: `shape` unless it is `auto`, else
/// decided by the cameras' viewing spread.
pub fn is_forward_facing(c2ws: &[Mat4], shape: Shape) -> bool {
    match shape {
        Shape::ForwardFacing => true,
        Shape::Around => false,
        Shape::Auto => viewing_spread(c2ws) <= FORWARD_MAX_DEGREES,
    }
}

/// A capture as its loader reads it: views with OpenGL camera-to-world
/// poses in the capture's own frame, which views are held out for testing,
/// and the sparse points (empty when the format has none).
pub(crate) struct Capture<'a> {
    pub kind: DatasetKind,
    pub root: &'a Path,
    /// The file that holds the poses (named in messages).
    pub source: &'a Path,
    pub views: Vec<View>,
    pub is_test: Vec<bool>,
    pub points: Vec<Vec3>,
}

/// Every `LLFF_HOLD`-th view (in the loader's order) held out for testing.
pub(crate) fn every_nth_test(n: usize) -> Vec<bool> {
    (0..n).map(|i| i % LLFF_HOLD == 0).collect()
}

/// The dataset of a capture: its shape decided (or taken from `opts`), its
/// frame and box set up for that shape; `notes` say what was decided.
pub(crate) fn assemble(capture: Capture, opts: &LoadOptions) -> Result<Dataset> {
    if capture.views.is_empty() {
        bail!("{}: the capture has no views", capture.source.display());
    }
    let c2ws: Vec<Mat4> = capture.views.iter().map(|v| v.camera.c2w).collect();
    let spread = viewing_spread(&c2ws);
    let forward = is_forward_facing(&c2ws, opts.shape);
    let why = match opts.shape {
        Shape::Auto => format!(
            "the cameras' viewing directions spread {spread:.0} degrees (forward-facing up to {FORWARD_MAX_DEGREES:.0})"
        ),
        _ => "set by data.shape".to_string(),
    };
    let n_test = capture.is_test.iter().filter(|&&t| t).count();
    let split = format!("{} train / {n_test} test views", capture.views.len() - n_test);
    let mut ds = if forward { forward_facing(capture)? } else { around(capture, opts)? };
    let kind = if forward { "forward-facing (NDC, as LLFF)" } else { "around the scene (a bounded box, as Blender)" };
    ds.notes.push(format!("{kind}: {why}; {split}"));
    if let Some([lo, hi]) = opts.bbox {
        (ds.bbox_min, ds.bbox_max) = (Vec3::from(lo), Vec3::from(hi));
    }
    ds.notes.push(format!("grid box {:.2?} .. {:.2?} (data.bbox sets it)", ds.bbox_min, ds.bbox_max));
    ds.background = opts.background;
    Ok(ds)
}

/// Depth bounds from the sparse points seen in front of the cameras: the
/// 0.5th and 99.5th percentiles of every (camera, point) depth.
fn depth_bounds(c2ws: &[Mat4], points: &[Vec3], source: &Path) -> Result<(f32, f32)> {
    let mut depths = Vec::new();
    for m in c2ws {
        let w2c = m.inverse();
        depths.extend(points.iter().map(|p| -w2c.transform_point3(*p).z).filter(|&z| z > 0.0));
    }
    if depths.len() < 20 {
        bail!(
            "{}: a forward-facing capture needs sparse points to find its depth range, and fewer than 20 lie in \
             front of the cameras; use a COLMAP model with its points3D, or set data.shape = \"around\"",
            source.display()
        );
    }
    let near = percentile(&mut depths, 0.5);
    let far = percentile(&mut depths, 99.5);
    Ok((near, far))
}

fn forward_facing(capture: Capture) -> Result<Dataset> {
    let c2ws: Vec<Mat4> = capture.views.iter().map(|v| v.camera.c2w).collect();
    let bounds = depth_bounds(&c2ws, &capture.points, capture.source)?;
    let (poses, near_far) = llff::normalise_forward(&c2ws, bounds, capture.source)?;
    let mut views = capture.views;
    for (v, p) in views.iter_mut().zip(poses) {
        v.camera.c2w = p;
    }
    let setup = Forward { kind: capture.kind, root: capture.root, source: capture.source, near_far };
    Ok(llff::forward_facing(setup, views, &capture.is_test, &LoadOptions::default()))
}

/// The point nearest (in least squares) to every camera's optical axis:
/// where an object capture's cameras look.
fn focus_point(c2ws: &[Mat4]) -> Option<Vec3> {
    let mut a = Mat3::ZERO;
    let mut b = Vec3::ZERO;
    for m in c2ws {
        let d = m.z_axis.truncate().normalize();
        let c = m.w_axis.truncate();
        let proj = Mat3::IDENTITY - Mat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += proj;
        b += proj * c;
    }
    (a.determinant().abs() > 1e-6).then(|| a.inverse() * b)
}

/// The box (centre, half side) of a capture around the scene, in the
/// rotated frame: the 2nd-98th percentiles of the sparse points with a
/// [`POINTS_BOX_MARGIN`], when there are enough points, else around the
/// cameras' focus point (0.4 of the median camera distance: lego's cameras
/// sit 4 units from a 1.5 box).
fn around_box(c2ws: &[Mat4], points: &[Vec3], source: &Path) -> Result<(Vec3, f32, String)> {
    if points.len() >= 50 {
        let mut lo = Vec3::ZERO;
        let mut hi = Vec3::ZERO;
        for axis in 0..3 {
            let mut v: Vec<f32> = points.iter().map(|p| p[axis]).collect();
            lo[axis] = percentile(&mut v, 2.0);
            hi[axis] = percentile(&mut v, 98.0);
        }
        let half = ((hi - lo) * 0.5).max_element() * POINTS_BOX_MARGIN;
        return Ok((
            (lo + hi) * 0.5,
            half,
            format!(
                "the 2nd-98th percentiles of {} sparse points, {:.0} % wider",
                points.len(),
                (POINTS_BOX_MARGIN - 1.0) * 100.0
            ),
        ));
    }
    let Some(centre) = focus_point(c2ws) else {
        bail!("{}: the cameras' axes are parallel; cannot find what they look at (set data.bbox)", source.display());
    };
    let mut dist: Vec<f32> = c2ws.iter().map(|m| (m.w_axis.truncate() - centre).length()).collect();
    let half = 0.4 * percentile(&mut dist, 50.0);
    Ok((centre, half, "the point the cameras look at (no sparse points)".to_string()))
}

fn around(capture: Capture, opts: &LoadOptions) -> Result<Dataset> {
    let c2ws: Vec<Mat4> = capture.views.iter().map(|v| v.camera.c2w).collect();
    let up = c2ws.iter().map(|m| m.y_axis.truncate().normalize()).sum::<Vec3>().normalize_or(Vec3::Z);
    let rot = Mat4::from_quat(Quat::from_rotation_arc(up, Vec3::Z));
    let rotated: Vec<Mat4> = c2ws.iter().map(|m| rot * *m).collect();
    let points: Vec<Vec3> = capture.points.iter().map(|p| rot.transform_point3(*p)).collect();
    let (centre, half, from) = around_box(&rotated, &points, capture.source)?;
    if !(half.is_finite() && half > 0.0) {
        bail!("{}: cannot find a scene box (degenerate bounds); set data.bbox", capture.source.display());
    }
    let scale = AROUND_HALF_SIDE / half;
    let (mut train, mut test) = (Vec::new(), Vec::new());
    for ((mut v, m), t) in capture.views.into_iter().zip(rotated).zip(capture.is_test) {
        let mut c2w = m;
        c2w.w_axis = ((m.w_axis.truncate() - centre) * scale).extend(1.0);
        v.camera.c2w = c2w;
        if t { test.push(v) } else { train.push(v) }
    }
    let mut ds = Dataset {
        kind: capture.kind,
        root: capture.root.to_path_buf(),
        train,
        val: Vec::new(),
        test,
        background: opts.background,
        bbox_min: Vec3::splat(-AROUND_HALF_SIDE),
        bbox_max: Vec3::splat(AROUND_HALF_SIDE),
        ndc: None,
        near_far: None,
        warnings: Vec::new(),
        notes: Vec::new(),
        source_frame: Some(SourceFrame { rotation: Mat3::from_mat4(rot), centre, scale }),
    };
    ds.notes.push(format!("box from {from}; up = the cameras' mean up vector, now +z"));
    Ok(ds)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::camera::{look_at, orbit};

    #[test]
    fn an_orbit_goes_around_and_a_row_of_cameras_faces_forward() {
        let ring = orbit(Vec3::new(3.0, -2.0, 1.0), 4.0, 30.0, 12);
        // Cameras 30 degrees above the ring look 60 degrees off the mean (straight down).
        assert!((viewing_spread(&ring) - 60.0).abs() < 0.1);
        assert!(!is_forward_facing(&ring, Shape::Auto));
        assert!(is_forward_facing(&ring, Shape::ForwardFacing));
        let row: Vec<Mat4> =
            (0..5).map(|i| look_at(Vec3::new(i as f32 * 0.2, 0.0, 0.0), Vec3::new(0.4, 0.0, -10.0), Vec3::Y)).collect();
        assert!(viewing_spread(&row) < 5.0);
        assert!(is_forward_facing(&row, Shape::Auto));
    }

    #[test]
    fn the_focus_of_an_orbit_is_its_target() {
        let target = Vec3::new(3.0, -2.0, 1.0);
        let f = focus_point(&orbit(target, 4.0, 30.0, 12)).unwrap();
        assert!((f - target).length() < 1e-3, "{f}");
    }
}
