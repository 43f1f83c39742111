//! Reference cases: our TOML form, the authors' data_config.json, style
//! images (resize, alpha, unreadable), and bad input.

mod common;

use common::TempDir;
use refnpr::reference::case::{ReferenceCase, ViewSpec, read_style};
use refnpr::scene::data::{self, procedural};
use std::path::Path;

fn tiny_dataset(dir: &Path) -> data::Dataset {
    let opts =
        procedural::SceneOptions { seed: 0, size: 32, num_train: 6, num_val: 1, num_test: 2, environment: false };
    procedural::write_scene(dir, &opts).unwrap();
    data::load(dir, &Default::default()).unwrap()
}

fn write_png(path: &Path, w: u32, h: u32, rgba: [u8; 4]) {
    image::RgbaImage::from_pixel(w, h, image::Rgba(rgba)).save(path).unwrap();
}

#[test]
fn authors_data_config_is_read_unchanged() {
    let t = TempDir::new("case-json");
    write_png(&t.path().join("style.png"), 32, 32, [255, 0, 0, 255]);
    // The authors' files name the style by its path in their repository.
    std::fs::write(
        t.path().join("data_config.json"),
        r#"{"dataset_type": "nerf_synthetic", "scene_name": "scene", "style_img": "./data/ref_case/scene/style.png",
            "tmpl_idx_train": 3, "tmpl_idx_test": null, "color_pre": false, "style_name": "red"}"#,
    )
    .unwrap();
    let case = ReferenceCase::load(t.path()).unwrap();
    assert_eq!(case.references.len(), 1);
    assert_eq!(case.references[0].view, ViewSpec::Train(3));
    assert_eq!(case.references[0].style, t.path().join("style.png"));
    assert!(!case.color_pre);
    assert_eq!(case.style_name.as_deref(), Some("red"));

    // Multi-reference and the render-path index.
    write_png(&t.path().join("b.png"), 32, 32, [0, 255, 0, 255]);
    std::fs::write(
        t.path().join("data_config.json"),
        r#"{"style_img": ["style.png", "b.png"], "tmpl_idx_train": null, "tmpl_idx_test": [5, 60]}"#,
    )
    .unwrap();
    let case = ReferenceCase::load(t.path()).unwrap();
    assert_eq!(
        case.references.iter().map(|r| r.view.clone()).collect::<Vec<_>>(),
        vec![ViewSpec::Path(5), ViewSpec::Path(60)]
    );
    assert!(case.color_pre, "color_pre defaults to true");
}

#[test]
fn bad_data_configs_are_clear_errors() {
    let t = TempDir::new("case-bad");
    write_png(&t.path().join("style.png"), 32, 32, [255, 0, 0, 255]);
    let cases = [
        (r#"{"style_img": "style.png", "tmpl_idx_train": 1, "tmpl_idx_test": 2}"#, "one must be null"),
        (r#"{"style_img": "style.png", "tmpl_idx_train": null, "tmpl_idx_test": null}"#, "neither"),
        (r#"{"style_img": "style.png", "tmpl_idx_train": 1"#, "malformed"),
        (r#"{"style_img": "missing.png", "tmpl_idx_train": 1}"#, "does not exist"),
        (r#"{"style_img": ["style.png", "style.png", "style.png"], "tmpl_idx_train": [1, 2]}"#, "template indices"),
    ];
    for (json, expect) in cases {
        std::fs::write(t.path().join("data_config.json"), json).unwrap();
        let err = format!("{:#}", ReferenceCase::load(t.path()).unwrap_err());
        assert!(err.contains(expect), "{json}: {err}");
        assert!(err.contains("data_config.json") || err.contains("missing.png"), "names the file: {err}");
    }
    let empty = TempDir::new("case-empty");
    let err = format!("{:#}", ReferenceCase::load(empty.path()).unwrap_err());
    assert!(err.contains("neither reference.toml nor data_config.json"), "{err}");
}

#[test]
fn toml_cases_and_view_specs() {
    let t = TempDir::new("case-toml");
    let ds = tiny_dataset(&t.path().join("scene"));
    let case_dir = t.path().join("case");
    std::fs::create_dir_all(&case_dir).unwrap();
    write_png(&case_dir.join("style.png"), 32, 32, [0, 0, 255, 255]);
    std::fs::write(
        case_dir.join("reference.toml"),
        r#"
scene_name = "scene"
[[reference]]
style = "style.png"
view = "test:1"
[[reference]]
style = "style.png"
c2w = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0], [0.0, 0.0, 0.0, 1.0]]
intrinsics = { width = 32, height = 32, fx = 40.0, fy = 40.0, cx = 16.0, cy = 16.0 }
"#,
    )
    .unwrap();
    let case = ReferenceCase::load(&case_dir).unwrap();
    let cams = case.cameras(&ds).unwrap();
    assert_eq!(cams[0], ds.test[1].camera);
    assert_eq!(cams[1].position(), glam::Vec3::new(0.0, 0.0, 4.0));
    assert!(case.scene_mismatch(&ds).is_none());

    // Out of range indices name the split and its size.
    let err = ViewSpec::Train(99).camera(&ds, 120).unwrap_err().to_string();
    assert!(err.contains("train:99") && err.contains("6 train views"), "{err}");
    let err = ViewSpec::Path(120).camera(&ds, 120).unwrap_err().to_string();
    assert!(err.contains("120 poses"), "{err}");
    assert!("side:3".parse::<ViewSpec>().is_err());

    // A view by its image's file name: with or without folders and extension;
    // a name the train and test splits share must say which.
    let file = Path::new(&ds.train[3].name).file_name().unwrap().to_string_lossy().into_owned();
    let in_folder = format!("train/{file}");
    assert_eq!(ViewSpec::parse_in(&in_folder, &ds).unwrap(), ViewSpec::Train(3), "{}", ds.train[3].name);
    let stem = Path::new(&file).file_stem().unwrap().to_string_lossy().into_owned();
    assert_eq!(ViewSpec::parse_in(&format!("train/{stem}"), &ds).unwrap(), ViewSpec::Train(3));
    let test_file = Path::new(&ds.test[1].name).file_name().unwrap().to_string_lossy().into_owned();
    assert_eq!(ViewSpec::parse_in(&format!("test/{test_file}"), &ds).unwrap(), ViewSpec::Test(1));
    assert_eq!(ViewSpec::parse_in("test:1", &ds).unwrap(), ViewSpec::Test(1));
    let err = format!("{:#}", ViewSpec::parse_in("no_such_image.png", &ds).unwrap_err());
    assert!(err.contains("6 training and 2 test images"), "{err}");
    if ds.test.iter().any(|v| v.name.ends_with(&file) || v.name.ends_with(&stem)) {
        let err = format!("{:#}", ViewSpec::parse_in(&stem, &ds).unwrap_err());
        assert!(err.contains("train:3") && err.contains("say which"), "{err}");
    } else {
        assert_eq!(ViewSpec::parse_in(&stem, &ds).unwrap(), ViewSpec::Train(3));
    }
    assert!("train:x".parse::<ViewSpec>().is_err());

    // A case made for another scene is reported.
    std::fs::write(
        case_dir.join("reference.toml"),
        "scene_name = \"fern\"\n[[reference]]\nstyle = \"style.png\"\nview = \"train:0\"\n",
    )
    .unwrap();
    let case = ReferenceCase::load(&case_dir).unwrap();
    assert!(case.scene_mismatch(&ds).unwrap().contains("fern"));

    // Unknown keys and half-given cameras are errors.
    std::fs::write(
        case_dir.join("reference.toml"),
        "[[reference]]\nstyle = \"style.png\"\nview = \"train:0\"\nweight = 2\n",
    )
    .unwrap();
    assert!(format!("{:#}", ReferenceCase::load(&case_dir).unwrap_err()).contains("weight"));
    std::fs::write(case_dir.join("reference.toml"), "[[reference]]\nstyle = \"style.png\"\nc2w = [[1.0,0.0,0.0,0.0],[0.0,1.0,0.0,0.0],[0.0,0.0,1.0,0.0],[0.0,0.0,0.0,1.0]]\n").unwrap();
    assert!(format!("{:#}", ReferenceCase::load(&case_dir).unwrap_err()).contains("both `c2w` and `intrinsics`"));
}

#[test]
fn style_images_are_resized_composited_and_checked() {
    let t = TempDir::new("style");
    // Another size: resized, and the note says so.
    write_png(&t.path().join("big.png"), 64, 48, [255, 128, 0, 255]);
    let (rgb, note) = read_style(&t.path().join("big.png"), 32, 32, [1.0; 3]).unwrap();
    assert_eq!(rgb.len(), 32 * 32 * 3);
    assert!(note.unwrap().contains("resized"));
    assert!((rgb[0] - 1.0).abs() < 1e-3 && (rgb[1] - 128.0 / 255.0).abs() < 1e-2 && rgb[2].abs() < 1e-3);
    // Alpha: half-transparent black over a white background is mid grey.
    write_png(&t.path().join("alpha.png"), 32, 32, [0, 0, 0, 128]);
    let (rgb, note) = read_style(&t.path().join("alpha.png"), 32, 32, [1.0; 3]).unwrap();
    assert!(note.is_none());
    assert!((rgb[0] - (1.0 - 128.0 / 255.0)).abs() < 1e-3);
    // Unreadable file.
    std::fs::write(t.path().join("broken.png"), b"not a png").unwrap();
    let err = format!("{:#}", read_style(&t.path().join("broken.png"), 32, 32, [1.0; 3]).unwrap_err());
    assert!(err.contains("broken.png"), "{err}");
}
