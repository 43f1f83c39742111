//! A COLMAP dataset folder: a sparse model (`sparse/0/`, or `sparse/` as
//! `colmap image_undistorter` and `refnpr capture` write it; binary or
//! text) and its images in `images/` (or `images_N/` for a downscale N).
//!
//! COLMAP stores world-to-camera poses with OpenCV camera axes (x right,
//! y down, z forward); they become OpenGL camera-to-world matrices here.
//! Distorted cameras (SIMPLE_RADIAL, RADIAL, OPENCV) are undistorted once,
//! at load, keeping their pinhole intrinsics. Images are sorted by name;
//! the test split is the images named in `test.txt` (one name per line)
//! when the folder has one, else every 8th image (the LLFF convention).

use super::colmap_model::{self, Model};
use super::posed::{self, Capture};
use super::undistort::undistort;
use super::{Dataset, DatasetKind, LoadOptions, View, check_pose, check_sizes, llff, read_rgb};
use crate::scene::camera::{Camera, Intrinsics};
use crate::util::input::InputError;
use anyhow::{Context, Result};
use glam::{DMat4, DVec4, Mat4, Vec3};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// The model of a dataset folder and the path of its `images` file.
fn read_model(dir: &Path) -> Result<(Model, PathBuf)> {
    let Some((model_dir, form)) = colmap_model::find_model(dir) else {
        let message =
            format!("{}: no COLMAP model (looked in sparse/0/, sparse/ and the folder itself)", dir.display());
        return Err(InputError::NotADataset { path: dir.into(), message }.into());
    };
    let model = colmap_model::read(&model_dir, form)?;
    let ext = if form == colmap_model::Form::Binary { "bin" } else { "txt" };
    let images_file = model_dir.join(format!("images.{ext}"));
    if model.images.is_empty() {
        let message = format!("{}: the model has no registered images", images_file.display());
        return Err(InputError::Malformed { path: images_file, message }.into());
    }
    Ok((model, images_file))
}

/// OpenCV camera axes (y down, z forward) <-> OpenGL (y up, z back): its own inverse.
const OPENCV_TO_OPENGL: DMat4 = DMat4::from_diagonal(DVec4::new(1.0, -1.0, -1.0, 1.0));

/// An image's OpenGL camera-to-world pose.
fn c2w_of(image: &colmap_model::ColmapImage) -> Mat4 {
    let r = image.rotation().transpose();
    let c = image.centre();
    let m = DMat4::from_cols(r.x_axis.extend(0.0), r.y_axis.extend(0.0), r.z_axis.extend(0.0), c.extend(1.0))
        * OPENCV_TO_OPENGL;
    m.as_mat4()
}

/// The inverse of [`c2w_of`]: an OpenGL camera-to-world pose as COLMAP's
/// world-to-camera quaternion (w, x, y, z) and translation.
fn qvec_tvec_of(c2w: Mat4) -> ([f64; 4], [f64; 3]) {
    let w2c = (c2w.as_dmat4() * OPENCV_TO_OPENGL).inverse();
    let q = glam::DQuat::from_mat3(&glam::DMat3::from_mat4(w2c)).normalize();
    ([q.w, q.x, q.y, q.z], w2c.w_axis.truncate().to_array())
}

/// The cameras' poses alone (no image decoded), in the model's frame.
pub(crate) fn poses(dir: &Path) -> Result<Vec<Mat4>> {
    Ok(read_model(dir)?.0.images.iter().map(c2w_of).collect())
}

/// Which views are held out for testing: those `test.txt` names, else every 8th.
fn test_split(dir: &Path, views: &[View]) -> Result<Vec<bool>> {
    let list = dir.join("test.txt");
    if !list.exists() {
        return Ok(posed::every_nth_test(views.len()));
    }
    let text = std::fs::read_to_string(&list).with_context(|| format!("cannot read {}", list.display()))?;
    let names: Vec<&str> = text.lines().map(str::trim).filter(|l| !l.is_empty()).collect();
    if let Some(missing) = names.iter().find(|n| !views.iter().any(|v| v.name == **n)) {
        let message =
            format!("{}: {missing} is not an image of the model (not registered, or misspelt)", list.display());
        return Err(InputError::Malformed { path: list, message }.into());
    }
    Ok(views.iter().map(|v| names.contains(&v.name.as_str())).collect())
}

pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let (model, images_file) = read_model(dir)?;
    let (folder, resize) = llff::image_folder(dir, opts.downscale)?;
    let loaded: Vec<Result<View>> = model
        .images
        .par_iter()
        .map(|im| {
            let path = folder.join(&im.name);
            if !path.exists() {
                let message = format!(
                    "{} lists the image {}, but {} does not exist (is the model's image folder {}?)",
                    images_file.display(),
                    im.name,
                    path.display(),
                    folder.display()
                );
                return Err(InputError::Missing { path, message }.into());
            }
            let c2w = c2w_of(im);
            check_pose(&c2w, &images_file, &im.name)?;
            let (w, h, rgb) = read_rgb(&path, opts.background, resize)?;
            let cam = &model.cameras[&im.camera_id];
            let lens = cam.lens().scaled(w as f64 / cam.width as f64, h as f64 / cam.height as f64);
            let rgb = if lens.is_distorted() { undistort(&rgb, w, h, &lens) } else { rgb };
            let (fx, fy, cx, cy) = (lens.fx as f32, lens.fy as f32, lens.cx as f32, lens.cy as f32);
            let intr = Intrinsics { width: w, height: h, fx, fy, cx, cy };
            Ok(View { name: im.name.clone(), camera: Camera::new(intr, c2w), rgb })
        })
        .collect();
    let views: Vec<View> = loaded.into_iter().collect::<Result<_>>()?;
    check_sizes(&views, &views[0].camera.intrinsics, &folder)?;
    let mut ids: Vec<u64> = model.points.keys().copied().collect();
    ids.sort_unstable();
    let points: Vec<Vec3> =
        ids.iter().map(|id| model.points[id]).map(|p| Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32)).collect();
    let is_test = test_split(dir, &views)?;
    let capture = Capture { kind: DatasetKind::Colmap, root: dir, source: &images_file, views, is_test, points };
    posed::assemble(capture, opts)
}

/// The frame `ds`'s cameras go back to when it is written as a COLMAP folder
/// to `out`; an error for anything but a COLMAP capture around the scene,
/// or for an `out` that already holds a dataset.
pub fn check_writable(ds: &Dataset, out: &Path) -> Result<super::SourceFrame> {
    let frame = match ds.source_frame {
        Some(frame) if ds.kind == DatasetKind::Colmap => frame,
        _ => anyhow::bail!(
            "{}: only a COLMAP capture around the scene can be written back with other cameras (this is a {} \
             dataset, {})",
            ds.root.display(),
            ds.kind,
            ds.shape_name()
        ),
    };
    if out.join("images").exists() || out.join("sparse").exists() {
        anyhow::bail!(
            "{} already holds a dataset (images/ or sparse/): write the refined capture to a new folder",
            out.display()
        );
    }
    Ok(frame)
}

/// Writes a COLMAP dataset folder (`images/` as PNG, `sparse/0/` in the text
/// form, `test.txt`) of `ds`'s train and test views seen by `cameras` (one
/// per view, train then test, in `ds`'s frame): the same scene with other
/// poses and intrinsics, e.g. refined ones. The poses go back to the source
/// model's frame and the source's sparse points are kept, so loading the
/// folder sets up the same box. Each view gets its own PINHOLE camera, as
/// the views are already undistorted.
pub fn write_colmap(ds: &Dataset, cameras: &[Camera], out: &Path) -> Result<()> {
    let views: Vec<&View> = ds.train.iter().chain(&ds.test).collect();
    assert_eq!(views.len(), cameras.len(), "one camera per train and test view");
    let frame = check_writable(ds, out)?;
    let (source, _) = read_model(&ds.root)?;
    let png_name = |name: &str| Path::new(name).with_extension("png").to_string_lossy().into_owned();
    let mut model = Model { points: source.points, ..Model::default() };
    for (i, (view, camera)) in views.iter().zip(cameras).enumerate() {
        let k = camera.intrinsics;
        let id = i as u32 + 1;
        let params = vec![k.fx as f64, k.fy as f64, k.cx as f64, k.cy as f64];
        let pinhole = colmap_model::CameraModel::Pinhole;
        model
            .cameras
            .insert(id, colmap_model::ColmapCamera { model: pinhole, width: k.width, height: k.height, params });
        let (qvec, tvec) = qvec_tvec_of(frame.to_source(camera.c2w));
        let name = png_name(&view.name);
        let path = out.join("images").join(&name);
        crate::util::files::create_dir(path.parent().unwrap_or(out))?;
        crate::util::image::save_png(&path, k.width, k.height, &view.rgb)?;
        model.images.push(colmap_model::ColmapImage { camera_id: id, name, qvec, tvec, point_ids: Vec::new() });
    }
    model.images.sort_by(|a, b| a.name.cmp(&b.name));
    let sparse = out.join("sparse").join("0");
    crate::util::files::create_dir(&sparse)?;
    colmap_model::write_text(&model, &sparse)?;
    let test: Vec<String> = ds.test.iter().map(|v| png_name(&v.name) + "\n").collect();
    std::fs::write(out.join("test.txt"), test.concat()).with_context(|| format!("cannot write {}", out.display()))?;
    Ok(())
}
