//! Dataset loaders on tiny fixtures written by the tests, the procedural
//! scene, and every bad input the loaders must reject with a clear error.

mod common;

use common::TempDir;
use glam::{Mat4, Vec3};
use refnpr::scene::data::{self, DatasetKind, LoadOptions, procedural};
use refnpr::util::npy;
use serde_json::json;
use std::path::Path;

fn write_png(path: &Path, w: u32, h: u32, rgba: [u8; 4]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    image::RgbaImage::from_pixel(w, h, image::Rgba(rgba)).save(path).unwrap();
}

fn pose(eye: Vec3) -> [[f32; 4]; 4] {
    refnpr::scene::camera::look_at(eye, Vec3::ZERO, Vec3::Z).transpose().to_cols_array_2d()
}

/// A 3-split Blender fixture with `n` frames per split.
fn blender_fixture(dir: &Path, n: usize, size: u32) {
    for split in ["train", "val", "test"] {
        let frames: Vec<_> = (0..n)
            .map(|i| {
                write_png(&dir.join(split).join(format!("r_{i}.png")), size, size, [200, 100, 50, 128]);
                json!({"file_path": format!("./{split}/r_{i}"), "transform_matrix": pose(Vec3::new(3.0, i as f32, 2.0))})
            })
            .collect();
        let doc = json!({"camera_angle_x": 0.69, "frames": frames});
        std::fs::write(dir.join(format!("transforms_{split}.json")), doc.to_string()).unwrap();
    }
}

fn err_of(dir: &Path) -> String {
    format!("{:#}", data::load(dir, &LoadOptions::default()).unwrap_err())
}

#[test]
fn blender_loader_composites_alpha_on_the_background() {
    let t = TempDir::new("blender");
    blender_fixture(t.path(), 2, 8);
    let ds = data::load(t.path(), &LoadOptions::default()).unwrap();
    assert_eq!(ds.kind, DatasetKind::Blender);
    assert_eq!((ds.train.len(), ds.val.len(), ds.test.len()), (2, 2, 2));
    // 200/255 at alpha 128/255 over white.
    let a = 128.0 / 255.0;
    let want = 200.0 / 255.0 * a + (1.0 - a);
    assert!((ds.train[0].rgb[0] - want).abs() < 1e-3);
    let k = ds.train[0].camera.intrinsics;
    assert!((k.fx - 4.0 / (0.69f32 / 2.0).tan()).abs() < 1e-3);
    assert_eq!(ds.bbox_min, Vec3::splat(-1.5));
    // Downscale halves the resolution and the focal length.
    let half = data::load(t.path(), &LoadOptions { downscale: 2, ..Default::default() }).unwrap();
    assert_eq!(half.train[0].camera.intrinsics.width, 4);
    assert!((half.train[0].camera.intrinsics.fx - k.fx / 2.0).abs() < 1e-3);
    // A black background changes the composite.
    let black = data::load(t.path(), &LoadOptions { background: [0.0; 3], ..Default::default() }).unwrap();
    assert!((black.train[0].rgb[0] - 200.0 / 255.0 * a).abs() < 1e-3);
}

fn write_poses_bounds(path: &Path, n: usize, h: f32, w: f32, f: f32, nan_at: Option<usize>) {
    let mut data = Vec::new();
    for i in 0..n {
        // LLFF axes: columns are [down, right, back] in world coordinates.
        let m = [[0.0f32, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        let t = [0.1 * i as f32, 0.05 * i as f32, 0.0];
        for r in 0..3 {
            data.extend([m[r][0], m[r][1], m[r][2], t[r], [h, w, f][r]]);
        }
        data.extend([2.0, 20.0]);
        if Some(i) == nan_at {
            data[i * 17 + 3] = f32::NAN;
        }
    }
    npy::write_f32(path, &[n, 17], &data).unwrap();
}

#[test]
fn llff_loader_holds_out_every_eighth_image_and_uses_ndc() {
    let t = TempDir::new("llff");
    let n = 10;
    write_poses_bounds(&t.path().join("poses_bounds.npy"), n, 48.0, 64.0, 50.0, None);
    for i in 0..n {
        write_png(&t.path().join("images_8").join(format!("image{i:03}.png")), 8, 6, [10, 20, 30, 255]);
    }
    let ds = data::load(t.path(), &LoadOptions { downscale: 8, ..Default::default() }).unwrap();
    assert_eq!(ds.kind, DatasetKind::Llff);
    assert_eq!(ds.test.len(), 2); // images 0 and 8
    assert_eq!(ds.train.len(), 8);
    assert_eq!(ds.test[1].name, "image008.png");
    let ndc = ds.ndc.expect("LLFF is rendered in NDC");
    assert!((ndc.focal - 50.0 * 8.0 / 64.0).abs() < 1e-4);
    // Recentred: the average pose is the identity.
    let poses: Vec<Mat4> = ds.train.iter().chain(&ds.test).map(|v| v.camera.c2w).collect();
    let avg = refnpr::scene::camera::average_pose(&poses);
    assert!(avg.abs_diff_eq(Mat4::IDENTITY, 1e-4), "{avg:?}");
    let (near, _far) = ds.near_far.unwrap();
    assert!((near - 1.0 / 0.75).abs() < 1e-4);
    // The cameras are translated sideways, so their rays leave the average
    // camera's [-1, 1] at the near plane: the box must have grown to hold them.
    assert!(ds.bbox_min.x < -1.0 && ds.bbox_max.x > 1.0, "{:?} {:?}", ds.bbox_min, ds.bbox_max);
    common::assert_ndc_rays_inside_box(&ds);
    assert_eq!(ds.render_path(120).len(), 120);
}

#[test]
fn nsvf_loader_splits_by_prefix_and_normalises_the_box() {
    let t = TempDir::new("nsvf");
    std::fs::create_dir_all(t.path().join("pose")).unwrap();
    std::fs::write(t.path().join("intrinsics.txt"), "10 0 4 0\n0 10 3 0\n0 0 1 0\n0 0 0 1\n").unwrap();
    std::fs::write(t.path().join("bbox.txt"), "-2 -2 -2 2 2 2 0.1\n").unwrap();
    for (i, name) in ["0_000", "0_001", "1_000", "2_000"].iter().enumerate() {
        write_png(&t.path().join("rgb").join(format!("{name}.png")), 8, 6, [1, 2, 3, 255]);
        let z = 4.0 + i as f32;
        std::fs::write(
            t.path().join("pose").join(format!("{name}.txt")),
            format!("1 0 0 0\n0 1 0 0\n0 0 1 {z}\n0 0 0 1\n"),
        )
        .unwrap();
    }
    let ds = data::load(t.path(), &LoadOptions::default()).unwrap();
    assert_eq!(ds.kind, DatasetKind::Nsvf);
    assert_eq!((ds.train.len(), ds.val.len(), ds.test.len()), (2, 1, 1));
    // bbox [-2,2] -> [-1,1]: a camera at z=4 lands at z=2; OpenCV +z forward becomes -(-z).
    assert!((ds.train[0].camera.position().z - 2.0).abs() < 1e-5);
    assert!((ds.train[0].camera.forward() - Vec3::Z).length() < 1e-5);
}

#[test]
fn procedural_scene_is_deterministic_and_loads() {
    let a = TempDir::new("proc-a");
    let b = TempDir::new("proc-b");
    let opts =
        procedural::SceneOptions { seed: 3, size: 24, num_train: 4, num_val: 1, num_test: 2, environment: false };
    procedural::write_scene(a.path(), &opts).unwrap();
    procedural::write_scene(b.path(), &opts).unwrap();
    for f in ["train/r_1.png", "test/r_0_depth.npy", "train/r_2_id.png", "stylized/train/r_1.png"] {
        assert_eq!(std::fs::read(a.path().join(f)).unwrap(), std::fs::read(b.path().join(f)).unwrap(), "{f} differs");
    }
    let ds = data::load(a.path(), &LoadOptions::default()).unwrap();
    assert_eq!(ds.train.len(), 4);
    assert_eq!(ds.bbox_max, Vec3::from(procedural::SCENE_BBOX[1]));
    let sty = data::load(&a.path().join("stylized"), &LoadOptions::default()).unwrap();
    assert_eq!(sty.train[1].camera.c2w, ds.train[1].camera.c2w);
    assert_ne!(sty.train[1].rgb, ds.train[1].rgb, "the stylized twin must look different");
    // Depth is consistent with the id map: hits have depth, background has none.
    let depth = npy::read(&a.path().join("train/r_0_depth.npy")).unwrap();
    let ids = image::open(a.path().join("train/r_0_id.png")).unwrap().to_luma8();
    let mut seen = std::collections::HashSet::new();
    for (d, id) in depth.data.iter().zip(ids.pixels()) {
        assert_eq!(*d > 0.0, id[0] != procedural::ID_BACKGROUND);
        seen.insert(id[0]);
    }
    assert!(seen.len() >= 4, "several objects visible: {seen:?}");
}

#[test]
fn bad_inputs_give_errors_that_name_the_file() {
    // Missing folder.
    let e = err_of(Path::new("/definitely/not/here"));
    assert!(e.contains("/definitely/not/here") && e.contains("does not exist"), "{e}");
    // A folder that is no dataset.
    let t = TempDir::new("bad");
    let e = err_of(t.path());
    assert!(e.contains("not a dataset folder"), "{e}");
    // Malformed JSON.
    std::fs::write(t.path().join("transforms_train.json"), "{ not json").unwrap();
    let e = err_of(t.path());
    assert!(e.contains("transforms_train.json") && e.contains("malformed"), "{e}");
    // Frame pointing to a missing image.
    blender_fixture(t.path(), 2, 8);
    std::fs::remove_file(t.path().join("train/r_1.png")).unwrap();
    let e = err_of(t.path());
    assert!(e.contains("missing image") && e.contains("r_1"), "{e}");
    // Mixed sizes.
    write_png(&t.path().join("train/r_1.png"), 9, 8, [0, 0, 0, 255]);
    let e = err_of(t.path());
    assert!(e.contains("mixed sizes"), "{e}");
    write_png(&t.path().join("train/r_1.png"), 8, 8, [0, 0, 0, 255]);
    // NaN pose.
    let bad = json!({"camera_angle_x": 0.69, "frames": [{"file_path": "./train/r_0", "transform_matrix": [[f32::NAN,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]});
    std::fs::write(t.path().join("transforms_train.json"), bad.to_string().replace("null", "NaN")).unwrap();
    let e = err_of(t.path());
    assert!(e.contains("transforms_train.json"), "{e}");
    // Non-invertible pose.
    let bad = json!({"camera_angle_x": 0.69, "frames": [{"file_path": "./train/r_0", "transform_matrix": [[0,0,0,0],[0,0,0,0],[0,0,0,0],[0,0,0,1]]}]});
    std::fs::write(t.path().join("transforms_train.json"), bad.to_string()).unwrap();
    let e = err_of(t.path());
    assert!(e.contains("not invertible"), "{e}");
    // Empty split.
    std::fs::write(t.path().join("transforms_train.json"), json!({"camera_angle_x": 0.69, "frames": []}).to_string())
        .unwrap();
    let e = err_of(t.path());
    assert!(e.contains("no frames") || e.contains("empty"), "{e}");
}

#[test]
fn bad_llff_inputs_are_reported() {
    let t = TempDir::new("badllff");
    std::fs::write(t.path().join("poses_bounds.npy"), b"garbage").unwrap();
    let e = err_of(t.path());
    assert!(e.contains("poses_bounds.npy") && e.contains("not a valid .npy"), "{e}");
    write_poses_bounds(&t.path().join("poses_bounds.npy"), 3, 48.0, 64.0, 50.0, Some(1));
    for i in 0..3 {
        write_png(&t.path().join("images").join(format!("{i}.png")), 8, 6, [0, 0, 0, 255]);
    }
    let e = err_of(t.path());
    assert!(e.contains("NaN"), "{e}");
    write_poses_bounds(&t.path().join("poses_bounds.npy"), 4, 48.0, 64.0, 50.0, None);
    let e = err_of(t.path());
    assert!(e.contains("4 poses but 3 images"), "{e}");
}

/// Refused outside input carries a typed reason (`util::input::InputError`)
/// inside the pipeline's `anyhow` error, so a library caller can tell a
/// folder that is no dataset from one that is missing, a file of another
/// kind from a corrupt one; the message a user reads stays the same.
#[test]
fn refused_input_has_a_typed_reason_a_caller_can_match() {
    use refnpr::util::input::InputError;
    let t = TempDir::new("typed-errors");
    let p = t.path().to_path_buf();

    let missing = data::load(&p.join("nope"), &LoadOptions::default()).unwrap_err();
    assert!(matches!(InputError::of(&missing), Some(InputError::Missing { .. })), "{missing:#}");
    assert!(missing.to_string().contains("does not exist"), "{missing:#}");

    let not_a_dataset = data::load(&p, &LoadOptions::default()).unwrap_err();
    match InputError::of(&not_a_dataset) {
        Some(InputError::NotADataset { path, .. }) => assert_eq!(path, &p),
        other => panic!("expected NotADataset, got {other:?}"),
    }
    assert!(not_a_dataset.to_string().contains("is not a dataset folder"), "{not_a_dataset:#}");

    let text = p.join("checkpoint.bin");
    std::fs::write(&text, "not a checkpoint").unwrap();
    let wrong = refnpr::field::checkpoint::load(&text, &common::device()).err().expect("a text file is refused");
    assert!(matches!(InputError::of(&wrong), Some(InputError::WrongKind { .. })), "{wrong:#}");

    let gone = refnpr::reference::registration::RegistrationFile::load(&p.join("registration.bin")).err().unwrap();
    assert!(matches!(InputError::of(&gone), Some(InputError::Missing { .. })), "{gone:#}");

    let npy_file = p.join("poses.npy");
    std::fs::write(&npy_file, b"\x93NUMPY\x01\x00garbage").unwrap();
    let corrupt = npy::read(&npy_file).err().expect("a cut header is refused");
    match InputError::of(&corrupt) {
        Some(e @ InputError::Malformed { .. }) => assert_eq!(e.path(), npy_file),
        other => panic!("expected Malformed, got {other:?}"),
    }
    assert!(format!("{corrupt:#}").contains("truncated header"), "the cause stays in the chain: {corrupt:#}");
}
