//! `refnpr view`'s server over real sockets: the page, the runs' files and
//! a live reload when a checkpoint is replaced; the refusals (path
//! traversal in its spellings, other methods, request bodies, oversized and
//! malformed requests), and that serving writes nothing. The page in a
//! browser is `scripts/check_view.sh`'s part.

mod common;

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};

use common::TempDir;
use refnpr::field::checkpoint;
use refnpr::field::grid::RadianceGrid;
use refnpr::photo::run::run_training;
use refnpr::scene::data::{self, procedural};
use refnpr::view::server::{MAX_HEAD, Site, serve};
use refnpr::view::{ViewRun, pack::FieldHeader};

/// A tiny fitted run.
fn fitted(t: &TempDir) -> PathBuf {
    let scene = t.path().join("scene");
    let opts =
        procedural::SceneOptions { seed: 5, size: 24, num_train: 12, num_val: 1, num_test: 2, environment: false };
    procedural::write_scene(&scene, &opts).unwrap();
    let ds = data::load(&scene, &Default::default()).unwrap();
    let run = t.path().join("run");
    let config = common::quick_blender_config(24, 20, 30, 60, 512);
    run_training(&ds, config, &run, common::backend(), false, &refnpr::Quiet).unwrap();
    run
}

/// Sends `request` as it is and returns (status, headers, body).
fn send(at: SocketAddr, request: &[u8]) -> (u16, String, Vec<u8>) {
    let mut s = TcpStream::connect(at).unwrap();
    // A refused request may be answered before it is all sent.
    let _ = s.write_all(request);
    let mut answer = Vec::new();
    let _ = s.read_to_end(&mut answer);
    let split = answer.windows(4).position(|w| w == b"\r\n\r\n").expect("an HTTP answer") + 4;
    let head = String::from_utf8_lossy(&answer[..split]).to_string();
    let status = head[9..12].parse().unwrap();
    (status, head, answer[split..].to_vec())
}

fn get(at: SocketAddr, path: &str) -> (u16, Vec<u8>) {
    let (status, _, body) = send(at, format!("GET {path} HTTP/1.1\r\nHost: x\r\n\r\n").as_bytes());
    (status, body)
}

fn header_of(field: &[u8]) -> FieldHeader {
    let n = u32::from_le_bytes(field[..4].try_into().unwrap()) as usize;
    serde_json::from_slice(&field[4..4 + n]).unwrap()
}

fn listing(dir: &Path) -> Vec<(PathBuf, u64)> {
    let mut out: Vec<_> =
        std::fs::read_dir(dir).unwrap().map(|e| e.unwrap()).map(|e| (e.path(), e.metadata().unwrap().len())).collect();
    out.sort();
    out
}

#[test]
fn the_server_sends_the_page_and_the_runs_reloads_a_new_checkpoint_and_refuses_the_rest() {
    let t = TempDir::new("view");
    let run = fitted(&t);
    let before = listing(&run);
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let at = listener.local_addr().unwrap();
    let site = Site::new(vec![ViewRun::new(&run, None)], common::device(), true);
    std::thread::spawn(move || serve(listener, site));

    let (status, page) = get(at, "/");
    assert_eq!(status, 200);
    assert!(String::from_utf8_lossy(&page).contains("<canvas"));
    assert_eq!(get(at, "/viewer.js").0, 200);
    let (_, runs) = get(at, "/runs.json");
    let runs: serde_json::Value = serde_json::from_slice(&runs).unwrap();
    assert_eq!(runs["runs"][0], "run");
    assert_eq!(runs["live"], true);
    let (status, field) = get(at, "/runs/0/field.bin");
    assert_eq!(status, 200);
    let header = header_of(&field);
    let start = (4 + u32::from_le_bytes(field[..4].try_into().unwrap()) as usize).next_multiple_of(4);
    assert_eq!(field.len(), start + header.index_bytes + header.density_bytes + header.sh_bytes + header.far_bytes);
    assert!(header.slots > 0);
    let (status, cameras) = get(at, "/runs/0/cameras.json");
    assert_eq!(status, 200);
    let cameras: serde_json::Value = serde_json::from_slice(&cameras).unwrap();
    assert_eq!(cameras["test"].as_array().unwrap().len(), 2, "the dataset's test cameras");
    // HEAD: the length, no body.
    let (status, head, body) = send(at, b"HEAD /runs/0/field.bin HTTP/1.1\r\n\r\n");
    assert_eq!(status, 200);
    assert!(head.contains(&format!("Content-Length: {}", field.len())) && body.is_empty(), "{head}");

    // Live: a replaced checkpoint changes the version and the field.
    let (_, version) = get(at, "/runs/0/version");
    let dev = common::device();
    let ck = checkpoint::load(&run, &dev).unwrap();
    let g = &ck.grid;
    let doubled: Vec<f32> = g.density_cpu.iter().map(|d| 2.0 * d).collect();
    let changed = RadianceGrid::from_rows(ck.meta.geometry, g.sh_degree, g.coords.clone(), doubled, g.sh_cpu(), &dev);
    std::thread::sleep(std::time::Duration::from_millis(20)); // a modification time apart
    checkpoint::save(&run.join("checkpoint.bin"), &ck.meta, &changed, &ck.opt_density, &ck.opt_sh, &ck.opt_far)
        .unwrap();
    let (_, version_after) = get(at, "/runs/0/version");
    assert_ne!(version, version_after, "the version follows the checkpoint");
    let (_, field_after) = get(at, "/runs/0/field.bin");
    assert_ne!(header_of(&field_after).fingerprint, header.fingerprint, "the new field is served");
    let before: Vec<_> = before.into_iter().map(|(p, _)| p).collect();
    let after: Vec<_> = listing(&run).into_iter().map(|(p, _)| p).collect();
    assert_eq!(before, after, "serving wrote no file into the run");

    // Refusals.
    for path in
        ["/../Cargo.toml", "/%2e%2e/Cargo.toml", "/runs/0/../../../etc/passwd", "//etc/passwd", "/runs/0/..%2fx"]
    {
        assert_eq!(get(at, path).0, 400, "{path}");
    }
    for path in ["/runs/0/checkpoint.bin", "/runs/1/field.bin", "/runs/x/field.bin", "/Cargo.toml", "/runs/0"] {
        assert_eq!(get(at, path).0, 404, "{path}");
    }
    let (status, head, _) = send(at, b"POST /runs.json HTTP/1.1\r\nContent-Length: 4\r\n\r\nabcd");
    assert_eq!(status, 405);
    assert!(head.contains("Allow: GET, HEAD"));
    assert_eq!(send(at, b"PUT /index.html HTTP/1.1\r\n\r\n").0, 405);
    assert_eq!(send(at, b"GET / HTTP/1.1\r\nContent-Length: 10\r\n\r\n0123456789").0, 413);
    let long = format!("GET / HTTP/1.1\r\nX-Padding: {}\r\n\r\n", "a".repeat(2 * MAX_HEAD));
    assert_eq!(send(at, long.as_bytes()).0, 431);
    assert_eq!(get(at, &format!("/{}", "a".repeat(300))).0, 414);
    assert_eq!(send(at, b"\x16\x03\x01 not http\r\n\r\n").0, 400);
    assert_eq!(send(at, b"GET /\r\n\r\n").0, 400);
    assert_eq!(get(at, "/").0, 200, "still serving after the refusals");
}

#[test]
fn the_static_copy_holds_the_page_and_each_runs_files() {
    let t = TempDir::new("view-static");
    let run = fitted(&t);
    let site = t.path().join("site");
    let bytes = refnpr::view::write_static(&[ViewRun::new(&run, None)], &site, &common::device()).unwrap();
    for file in ["index.html", "viewer.js", "runs.json", "runs/0/field.bin", "runs/0/cameras.json"] {
        assert!(site.join(file).is_file(), "{file}");
    }
    let listing: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(site.join("runs.json")).unwrap()).unwrap();
    assert_eq!(listing["live"], false, "a static copy does not poll");
    let field = std::fs::read(site.join("runs/0/field.bin")).unwrap();
    assert!(bytes as usize > field.len());
    assert!(header_of(&field).slots > 0);
}
