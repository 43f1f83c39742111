//! A short run of every fuzz target (`refnpr fuzz`; long runs:
//! `scripts/fuzz.sh TARGET SECONDS`): mutated real files fed to every parser
//! of outside input, none may panic. Plus the inputs the fuzzer found
//! panicking before they were fixed, kept as regressions.

mod common;

use common::TempDir;
use refnpr::tools::fuzz::{self, Limits};

fn shared_data() -> Option<std::path::PathBuf> {
    let d = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data")).to_path_buf();
    d.is_dir().then_some(d)
}

/// `cases` mutated inputs of target `name`: no panic, none slower than 5 s.
fn fuzz_briefly(name: &str, cases: u64) {
    let t = TempDir::new(&format!("fuzz-{name}"));
    let target = fuzz::target(name, t.path(), shared_data().as_deref()).unwrap();
    let limits = Limits { max_cases: cases, max_seconds: 120.0, case_seconds: 5.0, seed: 7 };
    let report = fuzz::run(&target, &limits).unwrap();
    assert!(report.crashes.is_empty(), "{name}: {:#?}", report.crashes);
    // The limit in cases, not the one in time, ended the run: the figure is what it says.
    assert_eq!(report.cases, cases, "{name}: ran out of time after {} cases", report.cases);
}

#[test]
fn fuzz_text_parsers() {
    for name in [
        "npy",
        "reference_toml",
        "data_config",
        "train_config",
        "stylize_config",
        "transforms_json",
        "colmap_cameras_bin",
        "colmap_images_bin",
        "colmap_points3d_bin",
        "colmap_cameras_txt",
        "colmap_images_txt",
        "colmap_points3d_txt",
    ] {
        fuzz_briefly(name, 20_000);
    }
}

#[test]
fn fuzz_file_parsers() {
    for name in [
        "checkpoint",
        "registration",
        "image",
        "transforms",
        "poses_bounds",
        "nsvf_intrinsics",
        "nsvf_pose",
        "nsvf_bbox",
    ] {
        fuzz_briefly(name, 2000);
    }
}

#[test]
fn fuzz_the_command_line() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_refnpr"))
        .args(["fuzz", "cli", "--cases", "5000", "--seed", "7"])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}{}", String::from_utf8_lossy(&out.stderr));
    assert!(text.contains("\"cases\": 5000") && text.contains("\"crashes\": []"), "{text}");
}

/// A version-1 `.npy` file: magic, header length, `header`, then `body`.
fn npy_bytes(header: &str, body: &[u8]) -> Vec<u8> {
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend_from_slice(&(header.len() as u16).to_le_bytes());
    npy.extend_from_slice(header.as_bytes());
    npy.extend_from_slice(body);
    npy
}

/// Headers that claim 10^12 elements are refused before anything that size
/// is allocated (an attempt would abort the test process).
#[test]
fn headers_claiming_huge_sizes_are_refused_before_allocating() {
    let npy = npy_bytes("{'descr': '<f8', 'fortran_order': False, 'shape': (1000000, 1000000), }", &[0u8; 64]);
    let e = format!("{:#}", refnpr::util::npy::parse(&npy).err().unwrap());
    assert!(e.contains("truncated"), "{e}");

    let t = TempDir::new("fuzz-huge");
    let target = fuzz::target("checkpoint", t.path(), None).unwrap();
    let file = t.path().join("huge.bin");
    // A safetensors checkpoint: the header's length, a tensor's shape, and
    // the lattice the metadata claims, each 10^12 or more.
    let seed = &target.seeds[0];
    let n = u64::from_le_bytes(seed[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&seed[8..8 + n]).unwrap();
    let rewrite = |edit: &dyn Fn(&mut serde_json::Value)| {
        let mut h = header.clone();
        edit(&mut h);
        let text = serde_json::to_vec(&h).unwrap();
        [&(text.len() as u64).to_le_bytes()[..], &text, &seed[8 + n..]].concat()
    };
    let mut long_header = seed.clone();
    long_header[..8].copy_from_slice(&1_000_000_000_000u64.to_le_bytes());
    let huge_shape = rewrite(&|h| h["sh"]["shape"] = serde_json::json!([1_000_000, 1_000_000]));
    let huge_lattice = rewrite(&|h| {
        let meta = h["__metadata__"]["meta"].as_str().unwrap().replace("[4,4,4]", "[100000,100000,100000]");
        assert!(meta.contains("100000"), "the seed's lattice is 4x4x4");
        h["__metadata__"]["meta"] = serde_json::Value::String(meta);
    });
    for bytes in [long_header, huge_shape, huge_lattice] {
        std::fs::write(&file, &bytes).unwrap();
        let e =
            format!("{:#}", refnpr::field::checkpoint::load(&file, &refnpr::BackendKind::Flex.device()).err().unwrap());
        assert!(e.contains("huge.bin"), "{e}");
    }
}

/// Inputs the fuzzer found panicking (fixed since): each is now a clear error.
#[test]
fn inputs_the_fuzzer_found_are_refused() {
    // An .npy header whose shape multiplies past usize: refused before any allocation.
    let npy = npy_bytes("{'descr': '<f4', 'fortran_order': False, 'shape': (4294967296, 4294967296, 17), }", &[]);
    let e = format!("{:#}", refnpr::util::npy::parse(&npy).err().unwrap());
    assert!(e.contains("truncated"), "{e}");
    // ... and one whose ')' comes before its '('.
    let npy = npy_bytes("{'descr': '<f4', 'fortran_order': False, 'shape': ), (2, }", &[]);
    assert!(refnpr::util::npy::parse(&npy).is_err());
    // A reference case asking for a render path of 2^31 frames (it hung, building them).
    let text = "path_frames = 2147483648\n[[reference]]\nstyle = \"s.png\"\nview = \"path:1\"\n";
    let e = format!(
        "{:#}",
        refnpr::reference::case::ReferenceCase::from_toml(std::path::Path::new("."), text).unwrap_err()
    );
    assert!(e.contains("path_frames must be between 1 and"), "{e}");
}
