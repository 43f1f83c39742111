//! `refnpr info`: what this build runs on, in the form a user pastes into a
//! bug report: the backends, the adapters wgpu sees and the one it picks,
//! the CPU's threads and SIMD features, memory, and the VGG16 weights.

use std::fmt;

use serde::Serialize;

use crate::util::backend::{AdapterSummary, BackendKind, wgpu_adapter, wgpu_adapters};
use crate::util::memory::available_memory_bytes;
use crate::util::transfer::human_bytes;
use crate::vgg::{Vgg16, WEIGHTS_SHA256};

/// Everything `refnpr info` reports.
#[derive(Debug, Clone, Serialize)]
pub struct SystemInfo {
    pub version: String,
    pub os: String,
    pub arch: String,
    /// The backends compiled into this build.
    pub backends: Vec<String>,
    /// `REFNPR_BACKEND`, when set.
    pub backend_env: Option<String>,
    /// Every adapter wgpu can see, on every graphics API.
    pub wgpu_adapters: Vec<AdapterSummary>,
    /// The adapter `--backend wgpu` runs on, or why there is none.
    pub wgpu_selected: Result<AdapterSummary, String>,
    pub cpu_model: Option<String>,
    /// Hardware threads, and the threads the CPU backends use (rayon).
    pub cpu_threads: usize,
    pub rayon_threads: usize,
    /// SIMD features this CPU has, of those the CPU backends can use.
    pub simd: Vec<String>,
    pub memory_total_bytes: Option<u64>,
    pub memory_available_bytes: Option<u64>,
    /// The VGG16 weights: embedded at build time from
    /// `models/vgg16_features.onnx`; SHA-256 of the loaded convolutions.
    pub vgg16_sha256: String,
    pub vgg16_sha256_expected: String,
}

impl SystemInfo {
    /// Gathers the report (loads VGG16, about a second, to checksum its weights).
    pub fn gather() -> Self {
        // The first backend compiled in (flex in a default build).
        let first = BackendKind::ALL.into_iter().find(|b| b.is_compiled()).expect("a build has a backend");
        let vgg16_sha256 = Vgg16::load(&first.device()).weights_sha256();
        Self {
            version: env!("CARGO_PKG_VERSION").to_string(),
            os: std::env::consts::OS.to_string(),
            arch: std::env::consts::ARCH.to_string(),
            backends: BackendKind::ALL.iter().filter(|b| b.is_compiled()).map(ToString::to_string).collect(),
            backend_env: std::env::var(crate::util::backend::BACKEND_ENV).ok(),
            wgpu_adapters: wgpu_adapters(),
            wgpu_selected: wgpu_adapter().map_err(|e| format!("{e:#}")),
            cpu_model: cpu_model(),
            cpu_threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            rayon_threads: rayon::current_num_threads(),
            simd: simd_features(),
            memory_total_bytes: meminfo_bytes("MemTotal:"),
            memory_available_bytes: available_memory_bytes(),
            vgg16_sha256,
            vgg16_sha256_expected: WEIGHTS_SHA256.to_string(),
        }
    }
}

/// The CPU's name as /proc/cpuinfo gives it (Linux).
fn cpu_model() -> Option<String> {
    let text = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("model name"))?;
    Some(line.split_once(':')?.1.trim().to_string())
}

/// A /proc/meminfo line in bytes (Linux).
fn meminfo_bytes(key: &str) -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let kb: u64 = text.lines().find(|l| l.starts_with(key))?.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// The SIMD extensions the CPU reports, of those that matter to the CPU backends' kernels.
fn simd_features() -> Vec<String> {
    #[allow(unused_mut)]
    let mut found: Vec<&str> = Vec::new();
    #[cfg(target_arch = "x86_64")]
    {
        macro_rules! check {
            ($($f:tt),*) => { $( if std::is_x86_feature_detected!($f) { found.push($f); } )* };
        }
        check!("sse4.1", "sse4.2", "avx", "avx2", "fma", "f16c", "avx512f", "avx512bw", "avx512vl");
    }
    #[cfg(target_arch = "aarch64")]
    {
        macro_rules! check {
            ($($f:tt),*) => { $( if std::arch::is_aarch64_feature_detected!($f) { found.push($f); } )* };
        }
        check!("neon", "fp16", "dotprod", "sve");
    }
    found.into_iter().map(String::from).collect()
}

impl fmt::Display for SystemInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let bytes = |b: Option<u64>| b.map_or("unknown".to_string(), human_bytes);
        writeln!(f, "refnpr {} ({} {})", self.version, self.os, self.arch)?;
        let env = self.backend_env.as_deref().map_or(String::new(), |v| format!("; REFNPR_BACKEND={v}"));
        writeln!(f, "backends: {} (default flex{env})", self.backends.join(", "))?;
        writeln!(f, "wgpu adapters seen: {}", self.wgpu_adapters.len())?;
        for a in &self.wgpu_adapters {
            writeln!(f, "  - {}", a.line().trim_start_matches("wgpu adapter: "))?;
        }
        match &self.wgpu_selected {
            Ok(a) => {
                writeln!(f, "wgpu runs on: {}", a.line().trim_start_matches("wgpu adapter: "))?;
                if let Some(w) = a.software_warning() {
                    writeln!(f, "  warning: {w}")?;
                }
            }
            Err(e) => writeln!(f, "wgpu runs on: nothing: {e}")?,
        }
        writeln!(f, "cpu: {}", self.cpu_model.as_deref().unwrap_or("unknown"))?;
        writeln!(f, "cpu threads: {} (CPU backends use {})", self.cpu_threads, self.rayon_threads)?;
        writeln!(f, "simd: {}", if self.simd.is_empty() { "none detected".into() } else { self.simd.join(" ") })?;
        writeln!(
            f,
            "memory: {} total, {} available",
            bytes(self.memory_total_bytes),
            bytes(self.memory_available_bytes)
        )?;
        let ok = if self.vgg16_sha256 == self.vgg16_sha256_expected { "matches" } else { "DOES NOT MATCH" };
        writeln!(f, "vgg16 weights: embedded at build time from models/vgg16_features.onnx")?;
        write!(f, "  sha256 {} ({ok} the expected value)", self.vgg16_sha256)
    }
}
