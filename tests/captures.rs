//! Captures made with a camera: COLMAP models (binary and text) and
//! nerfstudio / instant-ngp `transforms.json`, checked against the
//! procedural scene written in those forms (its Blender poses are the
//! truth), and every bad input they must refuse with a clear error.

mod common;

use common::TempDir;
use glam::{DQuat, Mat4, Vec4};
use refnpr::scene::data::colmap_model::{self, CameraModel, ColmapCamera, ColmapImage, Model};
use refnpr::scene::data::{self, Dataset, DatasetKind, LoadOptions, Shape, View, procedural};
use refnpr::tools::capture::{self, CaptureOptions};
use serde_json::json;
use std::collections::HashMap;
use std::path::Path;

/// The procedural scene (Blender layout) at `size` pixels, loaded.
fn blender_scene(dir: &Path, size: u32) -> Dataset {
    let opts = procedural::SceneOptions { seed: 3, size, num_train: 12, num_val: 0, num_test: 4, environment: false };
    procedural::write_scene(dir, &opts).unwrap();
    data::load(dir, &LoadOptions::default()).unwrap()
}

fn all_views(ds: &Dataset) -> Vec<&View> {
    ds.train.iter().chain(&ds.val).chain(&ds.test).collect()
}

/// A view's file as a flat name (`train/r_0` -> `train_r_0.png`).
fn flat(name: &str) -> String {
    format!("{}.png", name.trim_start_matches("./").replace('/', "_"))
}

/// The scene's views as a COLMAP model (one PINHOLE camera) with its images in `dir/images/`.
fn as_colmap(ds: &Dataset, dir: &Path) -> Model {
    std::fs::create_dir_all(dir.join("images")).unwrap();
    let k = ds.train[0].camera.intrinsics;
    let params = vec![k.fx as f64, k.fy as f64, k.cx as f64, k.cy as f64];
    let camera = ColmapCamera { model: CameraModel::Pinhole, width: k.width, height: k.height, params };
    let mut images = Vec::new();
    for v in all_views(ds) {
        std::fs::copy(ds.root.join(format!("{}.png", v.name)), dir.join("images").join(flat(&v.name))).unwrap();
        // OpenGL camera-to-world -> OpenCV world-to-camera.
        let w2c = (v.camera.c2w * Mat4::from_diagonal(Vec4::new(1.0, -1.0, -1.0, 1.0))).inverse().as_dmat4();
        let q = DQuat::from_mat4(&w2c);
        let t = w2c.w_axis.truncate();
        images.push(ColmapImage {
            camera_id: 1,
            name: flat(&v.name),
            qvec: [q.w, q.x, q.y, q.z],
            tvec: t.to_array(),
            point_ids: vec![],
        });
    }
    images.sort_by(|a, b| a.name.cmp(&b.name));
    Model { cameras: HashMap::from([(1, camera)]), images, points: HashMap::new() }
}

/// The scene's views as a nerfstudio `transforms.json` in `dir` (intrinsics
/// per frame for the test views, globally for the rest; its own split lists).
fn as_transforms(ds: &Dataset, dir: &Path) {
    let k = ds.train[0].camera.intrinsics;
    let frame = |v: &View, own_intrinsics: bool| {
        let m = v.camera.c2w.transpose().to_cols_array_2d();
        let mut f = json!({"file_path": ds.root.join(format!("{}.png", v.name)), "transform_matrix": m});
        if own_intrinsics {
            f["fl_x"] = json!(k.fx);
            f["fl_y"] = json!(k.fy);
        }
        f
    };
    let frames: Vec<_> =
        ds.train.iter().map(|v| frame(v, false)).chain(ds.test.iter().map(|v| frame(v, true))).collect();
    let test: Vec<_> = ds.test.iter().map(|v| ds.root.join(format!("{}.png", v.name))).collect();
    let doc = json!({
        "camera_model": "OPENCV", "fl_x": k.fx * 2.0, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": k.width, "h": k.height,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "aabb_scale": 4, "frames": frames, "test_filenames": test,
        "applied_transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]],
    });
    std::fs::write(dir.join("transforms.json"), doc.to_string()).unwrap();
}

/// Each view of `found` matched to `truth`'s by flat name: same pixels and
/// intrinsics; the poses one similarity transform apart.
fn assert_same_views(found: &Dataset, truth: &Dataset) {
    let key = |n: &str| {
        let n = n.replace(".png", "");
        flat(n.rsplit_once("/scene/").map_or(&n, |p| p.1))
    };
    let truth_views: HashMap<String, &View> = all_views(truth).into_iter().map(|v| (flat(&v.name), v)).collect();
    let (mut f, mut t) = (Vec::new(), Vec::new());
    for v in all_views(found) {
        let w = truth_views.get(&key(&v.name)).unwrap_or_else(|| panic!("{} has no match", v.name));
        assert_eq!(v.rgb, w.rgb, "{}", v.name);
        let (a, b) = (v.camera.intrinsics, w.camera.intrinsics);
        assert!((a.fx - b.fx).abs() < 1e-3 && (a.fy - b.fy).abs() < 1e-3 && (a.cx - b.cx).abs() < 1e-3, "{a:?} {b:?}");
        f.push(v.camera.c2w);
        t.push(w.camera.c2w);
    }
    assert_eq!(f.len(), all_views(truth).len());
    let e = capture::pose_error(&f, &t);
    assert!(e.rotation_worst_deg < 0.05 && e.translation_worst < 1e-3, "{e:?}");
}

#[test]
fn the_procedural_scene_as_a_colmap_model_or_transforms_json_loads_the_same_views() {
    let t = TempDir::new("captures");
    let truth = blender_scene(&t.path().join("scene"), 24);
    let model = as_colmap(&truth, &t.path().join("colmap"));
    colmap_model::write_binary(&model, &t.path().join("colmap/sparse/0")).unwrap();
    colmap_model::write_text(&model, &t.path().join("colmap_text/sparse")).unwrap();
    copy_dir(&t.path().join("colmap/images"), &t.path().join("colmap_text/images"));
    let binary = data::load(&t.path().join("colmap"), &LoadOptions::default()).unwrap();
    let text = data::load(&t.path().join("colmap_text"), &LoadOptions::default()).unwrap();
    assert_eq!(binary.kind, DatasetKind::Colmap);
    // The orbit goes around the scene: a bounded box, no NDC; the box is
    // where the cameras look (no sparse points), scaled to [-1.5, 1.5].
    assert!(binary.ndc.is_none() && binary.bbox_max == glam::Vec3::splat(1.5));
    assert!(binary.notes.iter().any(|n| n.contains("around the scene")), "{:?}", binary.notes);
    // Every 8th image by name is a test view.
    assert_eq!((binary.train.len(), binary.test.len()), (14, 2));
    assert_same_views(&binary, &truth);
    let same = |a: &Dataset, b: &Dataset| {
        all_views(a).iter().zip(all_views(b)).all(|(x, y)| x.camera == y.camera && x.rgb == y.rgb && x.name == y.name)
    };
    assert!(same(&binary, &text), "the text and binary forms of one model load differently");
    // test.txt names the test split.
    std::fs::write(t.path().join("colmap/test.txt"), "test_r_0.png\ntest_r_3.png\ntrain_r_5.png\n").unwrap();
    let listed = data::load(&t.path().join("colmap"), &LoadOptions::default()).unwrap();
    let names: Vec<&str> = listed.test.iter().map(|v| v.name.as_str()).collect();
    assert_eq!(names, ["test_r_0.png", "test_r_3.png", "train_r_5.png"]);

    std::fs::create_dir_all(t.path().join("ns")).unwrap();
    as_transforms(&truth, &t.path().join("ns"));
    // The file's fl_x is twice the truth, the test frames carry the true one:
    // a frame's own intrinsics win over the file's.
    let ns = data::load(&t.path().join("ns"), &LoadOptions::default()).unwrap();
    assert_eq!(ns.kind, DatasetKind::Transforms);
    assert_eq!((ns.train.len(), ns.test.len()), (12, 4));
    for v in &ns.test {
        assert!((v.camera.intrinsics.fx - truth.train[0].camera.intrinsics.fx).abs() < 1e-3);
    }
    for v in &ns.train {
        assert!((v.camera.intrinsics.fx - 2.0 * truth.train[0].camera.intrinsics.fx).abs() < 1e-3);
    }
    // Forcing the shape is honoured (a forward-facing set-up needs sparse points).
    let forced = LoadOptions { shape: Shape::ForwardFacing, ..Default::default() };
    let e = format!("{:#}", data::load(&t.path().join("ns"), &forced).unwrap_err());
    assert!(e.contains("transforms.json") && e.contains("sparse points"), "{e}");
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}

fn err_of(dir: &Path) -> String {
    format!("{:#}", data::load(dir, &LoadOptions::default()).unwrap_err())
}

#[test]
fn bad_captures_give_errors_that_name_the_file_and_the_fix() {
    let t = TempDir::new("badcaptures");
    let truth = blender_scene(&t.path().join("scene"), 16);
    let dir = t.path().join("colmap");
    let mut model = as_colmap(&truth, &dir);
    colmap_model::write_text(&model, &dir.join("sparse/0")).unwrap();
    // An image of the model missing on disk.
    std::fs::remove_file(dir.join("images/train_r_3.png")).unwrap();
    let e = err_of(&dir);
    assert!(e.contains("images.txt") && e.contains("train_r_3.png") && e.contains("does not exist"), "{e}");
    std::fs::copy(truth.root.join("train/r_3.png"), dir.join("images/train_r_3.png")).unwrap();
    // An unsupported camera model: named, with the undistorter's command.
    let cams = "1 OPENCV_FISHEYE 16 16 20 20 8 8 0.1 0 0 0\n";
    std::fs::write(dir.join("sparse/0/cameras.txt"), cams).unwrap();
    let e = err_of(&dir);
    assert!(e.contains("cameras.txt") && e.contains("OPENCV_FISHEYE") && e.contains("colmap image_undistorter"), "{e}");
    // A distorted camera is undistorted at load (its pixels change, its intrinsics stay).
    model.cameras.get_mut(&1).unwrap().model = CameraModel::Opencv;
    model.cameras.get_mut(&1).unwrap().params.extend([0.2, 0.0, 0.0, 0.0]);
    colmap_model::write_text(&model, &dir.join("sparse/0")).unwrap();
    let undistorted = data::load(&dir, &LoadOptions::default()).unwrap();
    let v = &undistorted.train[0];
    let raw = all_views(&truth).into_iter().find(|w| flat(&w.name) == v.name).unwrap();
    assert_ne!(v.rgb, raw.rgb);
    assert_eq!(v.camera.intrinsics, raw.camera.intrinsics);
    // test.txt naming an image the model lacks.
    std::fs::write(dir.join("test.txt"), "nope.png\n").unwrap();
    let e = err_of(&dir);
    assert!(e.contains("test.txt") && e.contains("nope.png"), "{e}");

    // transforms.json: a non-rigid pose, a NaN (JSON has none: null), a mask of another size.
    let ns = t.path().join("ns");
    std::fs::create_dir_all(&ns).unwrap();
    let img = truth.root.join("train/r_0.png");
    let frame = |m: serde_json::Value, mask: Option<&str>| {
        json!({"fl_x": 20, "frames": [{"file_path": img, "transform_matrix": m, "mask_path": mask}]}).to_string()
    };
    std::fs::write(
        ns.join("transforms.json"),
        frame(json!([[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]), None),
    )
    .unwrap();
    let e = err_of(&ns);
    assert!(e.contains("transforms.json") && e.contains("not a rigid transform"), "{e}");
    std::fs::write(
        ns.join("transforms.json"),
        frame(json!([[null, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]), None),
    )
    .unwrap();
    let e = err_of(&ns);
    assert!(e.contains("transforms.json") && e.contains("malformed"), "{e}");
    image::GrayImage::new(5, 5).save(ns.join("mask.png")).unwrap();
    let id = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]);
    std::fs::write(ns.join("transforms.json"), frame(id, Some("mask.png"))).unwrap();
    let e = err_of(&ns);
    assert!(e.contains("mask.png") && e.contains("5x5") && e.contains("16x16"), "{e}");

    // capture: too few photos, and no COLMAP where it was said to be.
    let photos = t.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    for i in 0..2 {
        std::fs::copy(&img, photos.join(format!("{i}.png"))).unwrap();
    }
    let out = t.path().join("captured");
    let e = format!("{:#}", capture::capture(&photos, &out, &CaptureOptions::default(), &refnpr::Quiet).unwrap_err());
    assert!(e.contains("holds 2 photos"), "{e}");
    std::fs::copy(&img, photos.join("2.png")).unwrap();
    let missing = CaptureOptions { colmap: t.path().join("no-colmap-here"), ..Default::default() };
    let e = format!("{:#}", capture::capture(&photos, &out, &missing, &refnpr::Quiet).unwrap_err());
    assert!(e.contains("not installed") && e.contains("apt-get install colmap"), "{e}");
}

#[test]
fn a_mask_makes_its_zero_pixels_the_background() {
    let t = TempDir::new("mask");
    let truth = blender_scene(&t.path().join("scene"), 16);
    let v = &truth.train[0];
    let mut mask = image::GrayImage::from_pixel(16, 16, image::Luma([255]));
    for x in 0..8 {
        for y in 0..16 {
            mask.put_pixel(x, y, image::Luma([0]));
        }
    }
    mask.save(t.path().join("mask.png")).unwrap();
    let frames: Vec<_> = (0..3)
        .map(|i| {
            let c2w = truth.train[i].camera.c2w.transpose().to_cols_array_2d();
            json!({"file_path": truth.root.join(format!("{}.png", truth.train[i].name)), "transform_matrix": c2w, "mask_path": "mask.png"})
        })
        .collect();
    let k = v.camera.intrinsics;
    let doc = json!({"fl_x": k.fx, "fl_y": k.fy, "frames": frames, "test_filenames": []});
    std::fs::write(t.path().join("transforms.json"), doc.to_string()).unwrap();
    let opts = LoadOptions { background: [0.0, 1.0, 0.0], shape: Shape::Around, ..Default::default() };
    let ds = data::load(t.path(), &opts);
    // No test view listed: the split is refused (a dataset needs both).
    let e = format!("{:#}", ds.unwrap_err());
    assert!(e.contains("test split is empty"), "{e}");
    let doc = json!({"fl_x": k.fx, "fl_y": k.fy, "frames": frames});
    std::fs::write(t.path().join("transforms.json"), doc.to_string()).unwrap();
    let ds = data::load(t.path(), &opts).unwrap();
    let rgb = &ds.test[0].rgb;
    for y in 0..16 {
        assert_eq!(&rgb[(y * 16) * 3..(y * 16) * 3 + 3], &[0.0, 1.0, 0.0], "masked pixel at row {y}");
    }
}

#[test]
fn a_capture_written_back_with_its_own_cameras_loads_the_same_views_in_the_same_box() {
    let t = TempDir::new("captures");
    let truth = blender_scene(&t.path().join("scene"), 24);
    let model = as_colmap(&truth, &t.path().join("colmap"));
    colmap_model::write_binary(&model, &t.path().join("colmap/sparse/0")).unwrap();
    let loaded = data::load(&t.path().join("colmap"), &LoadOptions::default()).unwrap();
    assert!(loaded.source_frame.is_some(), "a capture around the scene records its frame");
    let cameras: Vec<_> = loaded.train.iter().chain(&loaded.test).map(|v| v.camera).collect();
    data::write_colmap(&loaded, &cameras, &t.path().join("again")).unwrap();
    let again = data::load(&t.path().join("again"), &LoadOptions::default()).unwrap();
    assert_eq!((again.bbox_min, again.bbox_max), (loaded.bbox_min, loaded.bbox_max));
    let names: Vec<&str> = again.test.iter().map(|v| v.name.as_str()).collect();
    assert_eq!(names, loaded.test.iter().map(|v| v.name.as_str()).collect::<Vec<_>>(), "the same test split");
    for (a, b) in again.train.iter().chain(&again.test).zip(loaded.train.iter().chain(&loaded.test)) {
        assert_eq!(a.camera.intrinsics, b.camera.intrinsics, "{}", a.name);
        assert!(a.camera.c2w.abs_diff_eq(b.camera.c2w, 1e-4), "{}: {} vs {}", a.name, a.camera.c2w, b.camera.c2w);
        // 8-bit PNGs: the source's alpha composited over white is rounded once.
        let worst = a.rgb.iter().zip(&b.rgb).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max);
        assert!(worst <= 0.5 / 255.0 + 1e-6, "{}: colours {worst} apart", a.name);
    }
    let e = format!("{:#}", data::write_colmap(&loaded, &cameras, &t.path().join("colmap")).unwrap_err());
    assert!(e.contains("already holds a dataset"), "the source is not overwritten: {e}");
    let blender: Vec<_> = truth.train.iter().chain(&truth.test).map(|v| v.camera).collect();
    let e = format!("{:#}", data::write_colmap(&truth, &blender, &t.path().join("no")).unwrap_err());
    assert!(e.contains("only a COLMAP capture around the scene") && e.contains("blender"), "{e}");
}

/// Points over the procedural scene's objects (its ground disc has radius 1.25).
fn scene_points() -> Vec<glam::Vec3> {
    (0..75)
        .map(|i| glam::Vec3::new((i % 5) as f32 * 0.4 - 0.8, ((i / 5) % 5) as f32 * 0.4 - 0.8, (i / 25) as f32 * 0.3))
        .collect()
}

/// How far (pixels, mean) the scene's points land between two sets of cameras.
fn points_off_by(cams: &[refnpr::scene::camera::Camera], truth: &[refnpr::scene::camera::Camera]) -> f32 {
    let points = scene_points();
    let mut sum = 0.0;
    for (c, t) in cams.iter().zip(truth) {
        for p in &points {
            let ((x, y, _), (u, v, _)) = (c.project(*p).unwrap(), t.project(*p).unwrap());
            sum += ((x - u).powi(2) + (y - v).powi(2)).sqrt();
        }
    }
    sum / (cams.len() * points.len()) as f32
}

/// Six cameras turned 1.5 degrees, moved 1.5 % of the box and given a
/// focal length 2 % long are aligned back to their photos by a field fitted
/// to the true cameras: the scene's points land at least eight times closer
/// to where the true cameras see them. (A small turn and a sideways move
/// look alike from afar, so each alone is recovered less well than the two
/// together: that is what the images can tell.)
#[test]
fn cameras_knocked_off_their_poses_and_focal_are_aligned_back_to_their_photos() {
    use glam::{Mat3, Vec3};
    use refnpr::field::view::ViewRenderer;
    use refnpr::photo::pose_refine::{RefineSettings, refine_cameras};
    use refnpr::photo::trainer::Trainer;
    use refnpr::scene::camera::Camera;
    let t = TempDir::new("refine");
    let opts =
        procedural::SceneOptions { seed: 1, size: 48, num_train: 24, num_val: 0, num_test: 1, environment: false };
    procedural::write_scene(t.path(), &opts).unwrap();
    let ds = data::load(t.path(), &LoadOptions::default()).unwrap();
    let mut trainer =
        Trainer::new(&ds, common::quick_blender_config(32, 64, 200, 500, 2048), &common::device()).unwrap();
    for _ in 0..500 {
        trainer.step_once().unwrap();
    }
    let renderer = ViewRenderer::new(&trainer.grid, None, &trainer.config.render_settings(), ds.background);
    let truth: Vec<Camera> = ds.train.iter().step_by(4).map(|v| v.camera).collect();
    let photos: Vec<&[f32]> = ds.train.iter().step_by(4).map(|v| v.rgb.as_slice()).collect();
    let knocked: Vec<Camera> = truth
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let axis = Vec3::new(1.0, i as f32 - 2.5, 0.5 * i as f32).normalize();
            let turn = Mat4::from_mat3(Mat3::from_axis_angle(axis, 1.5f32.to_radians()));
            let shift = Mat4::from_translation(Vec3::new(0.03, -0.02, 0.03 * (i % 2) as f32));
            let mut k = *c;
            k.c2w = c.c2w * turn * shift;
            k.intrinsics.fx *= 1.02;
            k.intrinsics.fy *= 1.02;
            k
        })
        .collect();
    let r =
        refine_cameras(&renderer, &knocked, &photos, &RefineSettings { iterations: 8, focal: true }, &refnpr::Quiet);
    let (before, after) = (points_off_by(&knocked, &truth), points_off_by(&r.cameras, &truth));
    eprintln!("{}; points off by {before:.2} -> {after:.2} px; residual by iteration {:?}", r.describe(), r.rms);
    assert!(after < before / 8.0, "points off by {before} px, then {after}");
    assert!((r.focal_scale * 1.02 - 1.0).abs() < 0.005, "focal x{} (1 / 1.02 expected)", r.focal_scale);
    assert!(r.rms.last() < r.rms.first(), "{:?}", r.rms);
}

/// `train --refine-poses` on a capture whose poses are already exact: two
/// fits, the cameras barely moved, and the run reads the refined capture.
#[test]
fn training_with_refined_poses_keeps_exact_poses_and_runs_on_the_refined_capture() {
    use refnpr::field::checkpoint;
    use refnpr::photo::run::{REFINED_SCENE, run_training_with_refined_poses};
    let t = TempDir::new("refine_train");
    let opts =
        procedural::SceneOptions { seed: 1, size: 48, num_train: 24, num_val: 0, num_test: 2, environment: false };
    procedural::write_scene(&t.path().join("scene"), &opts).unwrap();
    let truth = data::load(&t.path().join("scene"), &LoadOptions::default()).unwrap();
    let model = as_colmap(&truth, &t.path().join("colmap"));
    colmap_model::write_binary(&model, &t.path().join("colmap/sparse/0")).unwrap();
    let capture = data::load(&t.path().join("colmap"), &LoadOptions::default()).unwrap();
    let out = t.path().join("run");
    let config = common::quick_blender_config(32, 64, 200, 500, 2048);
    let (first, refinement, second) =
        run_training_with_refined_poses(&capture, config, &out, common::backend(), &refnpr::Quiet).unwrap();
    eprintln!("{}; test PSNR {:.2} -> {:.2} dB", refinement.describe(), first.test_psnr, second.test_psnr);
    let exact: Vec<_> = capture.train.iter().chain(&capture.test).map(|v| v.camera).collect();
    let off = points_off_by(&refinement.cameras, &exact);
    eprintln!("the scene's points moved {off:.3} px");
    assert!(off < 0.2, "the scene's points moved {off} px");
    assert!((refinement.focal_scale - 1.0).abs() < 0.01, "focal x{}", refinement.focal_scale);
    assert!(second.test_psnr > first.test_psnr - 1.0, "{} then {}", first.test_psnr, second.test_psnr);
    let (_, dataset) = checkpoint::load_run(&out, None, &common::device()).unwrap();
    assert_eq!(dataset.root, out.join(REFINED_SCENE), "the run reads the refined capture");
    assert_eq!(dataset.train.len() + dataset.test.len(), capture.train.len() + capture.test.len());
}

/// `grid.far_background = "auto"` learns a far background for a capture
/// around the scene whose photos show a textured environment at their
/// borders, not for one on a plain backdrop nor for the research layouts;
/// `"off"` never does, and `"on"` refuses a forward-facing capture.
#[test]
fn auto_learns_a_far_background_only_behind_a_textured_capture() {
    use refnpr::photo::config::{FarBackground, GridConfig};
    use refnpr::photo::trainer::far_decision;
    let t = TempDir::new("far-decision");
    let capture = |environment: bool| {
        let scene = t.path().join(format!("scene-{environment}"));
        let opts = procedural::SceneOptions { seed: 3, size: 32, num_train: 6, num_val: 0, num_test: 2, environment };
        procedural::write_scene(&scene, &opts).unwrap();
        let ds = data::load(&scene, &LoadOptions::default()).unwrap();
        let dir = t.path().join(format!("capture-{environment}"));
        std::fs::create_dir_all(&dir).unwrap();
        as_transforms(&ds, &dir);
        (ds, data::load(&dir, &LoadOptions::default()).unwrap())
    };
    let grid = |far_background| GridConfig { far_background, ..GridConfig::default() };
    let (auto, off, on) = (grid(FarBackground::Auto), grid(FarBackground::Off), grid(FarBackground::On));
    let ((plain_blender, plain), (textured_blender, textured)) = (capture(false), capture(true));
    assert_eq!(textured.kind, DatasetKind::Transforms);
    let (learns, why) = far_decision(&textured, &auto).unwrap();
    assert!(learns, "{why}");
    let (learns, why) = far_decision(&plain, &auto).unwrap();
    assert!(!learns && why.contains("plain colour"), "{why}");
    assert!(!far_decision(&textured_blender, &auto).unwrap().0, "a Blender layout keeps its constant background");
    assert!(!far_decision(&textured, &off).unwrap().0);
    assert!(far_decision(&plain_blender, &on).unwrap().0);
    let mut forward = textured.clone();
    forward.ndc = Some(refnpr::scene::camera::NdcParams { width: 32.0, height: 32.0, focal: 30.0, near: 1.0 });
    let e = format!("{:#}", far_decision(&forward, &on).unwrap_err());
    assert!(e.contains("forward-facing"), "{e}");
    assert!(!far_decision(&forward, &auto).unwrap().0);
}
