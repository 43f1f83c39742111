//! `refnpr export`: a fitted procedural scene as Gaussian splats, a mesh
//! (glb and PLY), surface points, cameras and an MP4, each file read back
//! and checked; the refusals (no checkpoint, a level outside the density,
//! an empty field, a missing ffmpeg, an unwritable output) leave no file.
//! The files in other tools (a browser splat renderer, three.js's glTF
//! loader, trimesh, ffprobe) are `scripts/check_exports.sh`'s part.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use common::TempDir;
use refnpr::export::mesh::edge_uses;
use refnpr::field::checkpoint;
use refnpr::field::grid::RadianceGrid;
use refnpr::photo::run::run_training;
use refnpr::scene::data::{self, procedural};

/// One fitted tiny scene shared by the tests (a fit is the slow part).
fn fitted() -> &'static PathBuf {
    static RUN: OnceLock<(TempDir, PathBuf)> = OnceLock::new();
    &RUN.get_or_init(|| {
        let t = TempDir::new("export");
        let scene = t.path().join("scene");
        let opts =
            procedural::SceneOptions { seed: 3, size: 32, num_train: 24, num_val: 1, num_test: 3, environment: false };
        procedural::write_scene(&scene, &opts).unwrap();
        let ds = data::load(&scene, &Default::default()).unwrap();
        let run = t.path().join("run");
        let config = common::quick_blender_config(24, 40, 60, 150, 1024);
        run_training(&ds, config, &run, common::backend(), false, &refnpr::Quiet).unwrap();
        (t, run)
    })
    .1
}

/// `refnpr export RUN --format F --out OUT ARGS...`: (success, stdout + stderr).
fn export(run: &Path, format: &str, out: &Path, args: &[&str]) -> (bool, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_refnpr"))
        .args(["export", "--format", format, "--out"])
        .arg(out)
        .arg(run)
        .args(args)
        .output()
        .unwrap();
    (o.status.success(), String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr))
}

/// A binary PLY's header lines and the bytes after it.
fn read_ply(path: &Path) -> (Vec<String>, Vec<u8>) {
    let bytes = std::fs::read(path).unwrap();
    let end = bytes.windows(11).position(|w| w == b"end_header\n").expect("a PLY header") + 11;
    let header = std::str::from_utf8(&bytes[..end]).unwrap().lines().map(str::to_string).collect();
    (header, bytes[end..].to_vec())
}

fn element_count(header: &[String], element: &str) -> usize {
    let line = header.iter().find(|l| l.starts_with(&format!("element {element} "))).expect("the element");
    line.rsplit(' ').next().unwrap().parse().unwrap()
}

fn floats(bytes: &[u8]) -> impl Iterator<Item = f32> + '_ {
    bytes.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap()))
}

#[test]
fn splats_are_the_3dgs_layout_one_per_visible_point() {
    let run = fitted();
    let t = TempDir::new("splat");
    let out = t.path().join("s.ply");
    let (ok, log) = export(run, "splat", &out, &[]);
    assert!(ok, "{log}");
    assert!(log.contains("splats, SH degree 1") && log.contains("MB"), "{log}");
    let (header, body) = read_ply(&out);
    let props: Vec<&str> = header.iter().filter_map(|l| l.strip_prefix("property float ")).collect();
    let mut expected = vec!["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"];
    let rest: Vec<String> = (0..9).map(|i| format!("f_rest_{i}")).collect();
    expected.extend(rest.iter().map(String::as_str));
    expected.extend(["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]);
    assert_eq!(props, expected, "the 3DGS property order, SH degree 1");
    let n = element_count(&header, "vertex");
    assert_eq!(body.len(), n * expected.len() * 4);
    let ck = checkpoint::load(run, &common::device()).unwrap();
    assert!(
        n > 100 && n < ck.grid.num_rows(),
        "{n} splats of {} points: empty and buried ones dropped",
        ck.grid.num_rows()
    );
    let values: Vec<f32> = floats(&body).collect();
    let g = ck.meta.geometry;
    for s in values.chunks_exact(expected.len()) {
        assert!(s.iter().all(|v| v.is_finite()));
        let p = glam::Vec3::new(s[0], s[1], s[2]);
        assert!(p.cmpge(g.bbox_min).all() && p.cmple(g.bbox_max).all(), "a splat outside the box");
        let alpha = 1.0 / (1.0 + (-s[18]).exp());
        assert!(alpha >= 1.0 / 255.0 - 1e-4, "opacity {alpha}");
        assert_eq!(s[22], 1.0, "axis-aligned splats: identity rotation");
    }
    // Degree 0 and a budget.
    let (ok, log) = export(run, "splat", &out, &["--sh-degree", "0", "--max-splats", "50"]);
    assert!(ok && log.contains("50 splats, SH degree 0"), "{log}");
    let (ok, log) = export(run, "splat", &out, &["--sh-degree", "3"]);
    assert!(!ok && log.contains("SH degree 1"), "{log}");
}

#[test]
fn the_mesh_is_a_closed_coloured_surface_in_glb_and_ply() {
    let run = fitted();
    let t = TempDir::new("mesh");
    let ply = t.path().join("m.ply");
    let (ok, log) = export(run, "mesh", &ply, &[]);
    assert!(ok, "{log}");
    let (header, body) = read_ply(&ply);
    let (nv, nf) = (element_count(&header, "vertex"), element_count(&header, "face"));
    assert!(nv > 100 && nf > 100, "{nv} vertices, {nf} faces");
    let vertex_bytes = nv * (6 * 4 + 3);
    assert_eq!(body.len(), vertex_bytes + nf * 13);
    let triangles: Vec<[u32; 3]> = body[vertex_bytes..]
        .chunks_exact(13)
        .map(|f| {
            assert_eq!(f[0], 3);
            std::array::from_fn(|i| u32::from_le_bytes(f[1 + 4 * i..5 + 4 * i].try_into().unwrap()))
        })
        .collect();
    assert!(edge_uses(&triangles).values().all(|&n| n == 2), "a closed surface");
    let colours: Vec<[u8; 3]> = body[..vertex_bytes].chunks_exact(27).map(|v| [v[24], v[25], v[26]]).collect();
    let distinct: std::collections::HashSet<_> = colours.iter().collect();
    assert!(distinct.len() > 20, "the scene's colours, not one grey ({} distinct)", distinct.len());

    let glb = t.path().join("m.glb");
    let (ok, log) = export(run, "mesh", &glb, &[]);
    assert!(ok, "{log}");
    let bytes = std::fs::read(&glb).unwrap();
    assert_eq!(&bytes[..4], b"glTF");
    let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    let doc: serde_json::Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
    assert_eq!(doc["accessors"][0]["count"].as_u64().unwrap() as usize, nv);
    assert_eq!(doc["accessors"][3]["count"].as_u64().unwrap() as usize, 3 * nf);

    let (ok, log) = export(run, "mesh", &t.path().join("m.obj"), &[]);
    assert!(!ok && log.contains(".glb or .ply"), "{log}");

    // Simplified to a quarter: still closed, within the budget.
    let small = t.path().join("small.ply");
    let (ok, log) = export(run, "mesh", &small, &["--max-triangles", &(nf / 4).to_string()]);
    assert!(ok, "{log}");
    let (header, _) = read_ply(&small);
    let small_faces = element_count(&header, "face");
    assert!(small_faces <= nf / 4 && small_faces > nf / 8, "{small_faces} of {nf}");
    let (ok, log) = export(run, "mesh", &small, &["--max-triangles", "3"]);
    assert!(!ok && log.contains("4 or more"), "{log}");
}

#[test]
fn points_and_cameras_describe_the_training_views() {
    let run = fitted();
    let t = TempDir::new("points");
    let out = t.path().join("p.ply");
    let (ok, log) = export(run, "points", &out, &["--stride", "4"]);
    assert!(ok, "{log}");
    let (header, body) = read_ply(&out);
    let n = element_count(&header, "vertex");
    // 24 views of 32x32 pixels, every 4th along both axes: at most 24 x 64.
    assert!(n > 100 && n <= 24 * 64, "{n} points");
    assert_eq!(body.len(), n * 15);

    let cams = t.path().join("cameras.json");
    let (ok, log) = export(run, "cameras", &cams, &[]);
    assert!(ok, "{log}");
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&cams).unwrap()).unwrap();
    assert_eq!(json["train"].as_array().unwrap().len(), 24);
    assert_eq!(json["test"].as_array().unwrap().len(), 3);
    assert_eq!(json["test"][0]["c2w"].as_array().unwrap().len(), 16);
}

#[test]
fn the_video_is_an_h264_mp4_or_a_clear_error_without_ffmpeg() {
    let run = fitted();
    let t = TempDir::new("video");
    let out = t.path().join("v.mp4");
    let (ok, log) = export(run, "video", &out, &["--frames", "6", "--ffmpeg", "/nonexistent/ffmpeg"]);
    assert!(!ok && log.contains("apt install ffmpeg"), "{log}");
    assert!(!out.exists());
    // The test command installs ffmpeg (.ci/run): the encode itself is checked.
    let (ok, log) = export(run, "video", &out, &["--frames", "6", "--fps", "12", "--width", "33"]);
    assert!(ok, "{log}");
    let probe = Command::new("ffprobe")
        .args(["-v", "error", "-select_streams", "v:0", "-count_frames", "-show_entries"])
        .args(["stream=codec_name,pix_fmt,width,height,nb_read_frames", "-of", "json"])
        .arg(&out)
        .output()
        .expect("ffprobe (installed with ffmpeg)");
    let json: serde_json::Value = serde_json::from_slice(&probe.stdout).unwrap();
    let s = &json["streams"][0];
    assert_eq!(s["codec_name"], "h264");
    assert_eq!(s["pix_fmt"], "yuv420p");
    assert_eq!((s["width"].as_u64(), s["height"].as_u64()), (Some(34), Some(34)), "33 x 33 padded to even sides");
    assert_eq!(s["nb_read_frames"], "6");
    assert!(std::fs::read_dir(t.path()).unwrap().count() == 1, "no temporary file left");
}

#[test]
fn bad_exports_are_refused_and_leave_no_file() {
    let run = fitted();
    let t = TempDir::new("bad");
    let out = t.path().join("x.ply");
    let (ok, log) = export(t.path(), "splat", &out, &[]);
    assert!(!ok && log.contains("checkpoint.bin"), "no checkpoint: {log}");
    let (ok, log) = export(run, "mesh", &out, &["--level", "1e9"]);
    assert!(!ok && log.contains("outside the field's density range"), "{log}");
    let blocked = t.path().join("a-file");
    std::fs::write(&blocked, "not a folder").unwrap();
    let (ok, log) = export(run, "splat", &blocked.join("s.ply"), &[]);
    assert!(!ok && log.contains("a-file"), "unwritable output: {log}");
    // An empty field: every density zero.
    let dev = common::device();
    let ck = checkpoint::load(run, &dev).unwrap();
    let g = &ck.grid;
    let zeros = vec![0.0; g.num_rows()];
    let empty = RadianceGrid::from_rows(ck.meta.geometry, g.sh_degree, g.coords.clone(), zeros, g.sh_cpu(), &dev);
    let empty_run = t.path().join("empty");
    checkpoint::save(&empty_run.join("checkpoint.bin"), &ck.meta, &empty, &ck.opt_density, &ck.opt_sh, &ck.opt_far)
        .unwrap();
    let (ok, log) = export(&empty_run, "splat", &out, &[]);
    assert!(!ok && log.contains("no point of the field"), "{log}");
    let (ok, log) = export(&empty_run, "mesh", &out, &[]);
    assert!(!ok && log.contains("the field is empty"), "{log}");
    assert!(!out.exists(), "a refused export writes nothing");
}
