//! Run-time choice of the Burn backend.
//!
//! Burn 0.22 picks the backend through the `Device`, so the whole library is
//! written once against `Tensor<D>` and the user chooses `flex`, `ndarray` or
//! `wgpu` on the command line (`--backend`) or through `REFNPR_BACKEND`.

use anyhow::{Result, anyhow};
use burn::tensor::{Device, DeviceKind};
use clap::ValueEnum;
use std::fmt;

/// Environment variable that selects the backend for the tests and the CLI default.
pub const BACKEND_ENV: &str = "REFNPR_BACKEND";

/// The backends this build supports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize, ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum BackendKind {
    /// Burn's pure-Rust CPU backend (the default).
    #[default]
    Flex,
    /// The ndarray CPU backend (deprecated upstream, kept for comparison).
    Ndarray,
    /// wgpu: Vulkan / Metal / DX12 GPUs, or Mesa's software Vulkan on a CPU.
    Wgpu,
}

impl BackendKind {
    /// All backends, in the order tests and benchmarks report them.
    pub const ALL: [BackendKind; 3] = [BackendKind::Flex, BackendKind::Ndarray, BackendKind::Wgpu];

    /// The backend named by `REFNPR_BACKEND`, or flex when it is unset.
    pub fn from_env() -> Result<Self> {
        match std::env::var(BACKEND_ENV) {
            Ok(v) if !v.trim().is_empty() => BackendKind::from_str(v.trim(), true).map_err(|_| {
                anyhow!("unknown backend '{}' in {BACKEND_ENV}: expected one of flex, ndarray, wgpu", v.trim())
            }),
            _ => Ok(BackendKind::Flex),
        }
    }

    /// The plain (no autodiff) device of this backend.
    #[allow(deprecated)] // ndarray is deprecated upstream but still a supported choice here
    pub fn device(self) -> Device {
        match self {
            BackendKind::Flex => Device::flex(),
            BackendKind::Ndarray => Device::ndarray(),
            BackendKind::Wgpu => Device::wgpu(DeviceKind::DefaultDevice),
        }
    }

    /// The same device with autodiff enabled.
    pub fn autodiff_device(self) -> Device {
        self.device().autodiff()
    }
}

impl fmt::Display for BackendKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.to_possible_value().expect("no skipped variants").get_name())
    }
}
