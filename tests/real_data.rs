//! The real scenes in ../shared/data (lego 200x200, fern 504x378): loaders
//! and a short fit. A separately named group: these tests are #[ignore]d so a
//! fresh clone without ../shared passes `cargo test`; scripts/test.sh runs
//! them with `--ignored` when the data is there. Set REFNPR_SHARED_DATA to
//! point elsewhere.

mod common;

use refnpr::photo::config::TrainConfig;
use refnpr::scene::data::{self, DatasetKind};
use std::path::PathBuf;

fn shared(rel: &str) -> PathBuf {
    let root = std::env::var("REFNPR_SHARED_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|_| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    let p = root.join(rel);
    assert!(p.exists(), "{} not found: this group needs the shared data", p.display());
    p
}

#[test]
#[ignore = "needs ../shared/data; run with --ignored"]
fn lego_loads_with_the_standard_splits() {
    let dir = shared("nerf_synthetic/lego");
    let ds = data::load(&dir, &TrainConfig::for_kind(DatasetKind::Blender).data).unwrap();
    assert_eq!((ds.train.len(), ds.val.len(), ds.test.len()), (100, 8, 25));
    let k = ds.train[0].camera.intrinsics;
    assert_eq!((k.width, k.height), (200, 200));
    // camera_angle_x 0.6911 at 200 px -> focal about 277.8.
    assert!((k.fx - 277.8).abs() < 0.5, "{}", k.fx);
    // Cameras sit about 4 units from the origin and look at it.
    for v in &ds.train {
        let d = v.camera.position().length();
        assert!((3.9..4.2).contains(&d), "{d}");
        assert!(v.camera.forward().dot(-v.camera.position().normalize()) > 0.95);
    }
}

#[test]
#[ignore = "needs ../shared/data; run with --ignored"]
fn fern_loads_recentred_with_ndc_and_a_spiral() {
    let dir = shared("nerf_llff_data/fern");
    let ds = data::load(&dir, &TrainConfig::for_kind(DatasetKind::Llff).data).unwrap();
    assert_eq!((ds.train.len(), ds.test.len()), (17, 3));
    let k = ds.train[0].camera.intrinsics;
    assert_eq!((k.width, k.height), (504, 378));
    assert!(ds.ndc.is_some());
    // The other cameras' border rays leave the average camera's [-1, 1]
    // sideways; the grid's box must hold them (measured: |x| up to 1.44).
    common::assert_ndc_rays_inside_box(&ds);
    assert!(ds.bbox_max.x > 1.3 && ds.bbox_min.x < -1.3, "{:?} {:?}", ds.bbox_min, ds.bbox_max);
    let path = ds.render_path(120);
    assert_eq!(path.len(), 120);
    // The spiral stays near the capture cameras and looks the same way.
    for c in &path {
        assert!(c.position().length() < 1.0, "{:?}", c.position());
        assert!(c.forward().z < -0.9);
    }
}

#[test]
#[ignore = "needs ../shared/data; run with --ignored"]
fn lego_short_fit_learns_the_object() {
    // 400 steps at 64^3 -> 96^3: a smoke test of the real pipeline (the
    // quality figures come from `refnpr train` with the shipped config).
    let dir = shared("nerf_synthetic/lego");
    let mut cfg = TrainConfig::for_kind(DatasetKind::Blender);
    cfg.grid.initial_res = [64; 3];
    cfg.grid.upsample_steps = vec![200];
    cfg.grid.upsample_res = vec![[96; 3]];
    cfg.grid.sh_degree = 1;
    cfg.optim.steps = 400;
    let mut ds = data::load(&dir, &cfg.data).unwrap();
    ds.test.truncate(3);
    let out = std::env::temp_dir().join(format!("refnpr-lego-{}", std::process::id()));
    let m = refnpr::photo::run::run_training(&ds, cfg, &out, common::backend(), false, &refnpr::Quiet).unwrap();
    std::fs::remove_dir_all(&out).ok();
    eprintln!("lego short fit: {:.2} dB", m.test_psnr);
    assert!(m.test_psnr > 21.0, "lego short fit reached only {:.2} dB", m.test_psnr);
}
