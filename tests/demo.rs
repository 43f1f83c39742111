//! The demo's pieces end to end on a reduced procedural scene (flex): scene,
//! photoreal fit, reference case from the stylized twin, stylization, orbit,
//! evaluation against the twin.

mod common;

use common::TempDir;
use refnpr::scene::data::procedural::SceneOptions;
use refnpr::tools::demo::{DemoOptions, run_demo};

#[test]
fn the_demo_pipeline_stylizes_the_scene_towards_its_twin() {
    let dir = TempDir::new("demo");
    let opts = DemoOptions {
        scene: SceneOptions { size: 48, num_train: 12, num_val: 2, num_test: 4, seed: 3, environment: false },
        steps: Some(300),
        epochs: Some(3),
        reference_view: 0,
    };
    let r = run_demo(dir.path(), common::backend(), &opts, &refnpr::Quiet).expect("the demo runs");
    for f in [
        "scene/stylized/transforms_test.json",
        "photo/checkpoint.bin",
        "orbit/path.gif",
        "case/reference.toml",
        "case/style.png",
        "stylized/checkpoint.bin",
        "stylized/stylize.json",
        "stylized/orbit/path.gif",
        "eval.json",
    ] {
        assert!(dir.path().join(f).exists(), "{f} is missing");
    }
    let e = &r.eval;
    let gt = e.gt_psnr.expect("ground truth given");
    assert!(gt > r.photo_gt_psnr + 0.5, "stylized {gt:.2} dB vs photoreal {:.2} dB against the twin", r.photo_gt_psnr);
    assert!(e.gt_psnr_occluded.is_some_and(f32::is_finite));
    assert!(e.occluded_fraction.is_some_and(|f| f > 0.0 && f < 1.0), "{:?}", e.occluded_fraction);
    assert!(e.ref_lpips.is_finite() && e.ref_lpips > 0.0);
    assert_eq!(e.stability.len(), 2);
    assert!(e.stability.iter().all(|s| s.pixels > 0 && s.rmse.is_finite()));
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("eval.json")).unwrap()).unwrap();
    assert_eq!(written["gt_psnr"].as_f64().map(|v| v as f32), e.gt_psnr);
}

#[test]
fn the_demo_configs_only_shorten_the_defaults() {
    // The demo must stay the method as shipped, only shorter: the stylization
    // config differs from the defaults in the number of epochs alone.
    let demo = refnpr::tools::demo::demo_stylize_config().expect("configs/demo_stylize.toml parses");
    let mut expected = refnpr::stylize::config::StylizeConfig::default();
    assert!(demo.schedule.image_epochs < expected.schedule.image_epochs);
    expected.schedule.image_epochs = demo.schedule.image_epochs;
    assert_eq!(demo, expected);
    let fit = refnpr::tools::demo::demo_config().expect("configs/demo.toml parses");
    assert!(fit.grid.upsample_steps.iter().all(|&s| s < fit.optim.steps));
}
