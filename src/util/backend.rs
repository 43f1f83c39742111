//! Run-time choice of the Burn backend.
//!
//! Burn 0.22 picks the backend through the `Device`, so the whole library is
//! written once against `Tensor<D>` and the user chooses `flex`, `ndarray` or
//! `wgpu` on the command line (`--backend`) or through `REFNPR_BACKEND`.

use anyhow::{Result, anyhow, bail};
use burn::tensor::Device;
#[cfg(feature = "wgpu")]
use burn::tensor::wgpu::wgpu;
use clap::ValueEnum;
use serde::Serialize;
use std::fmt;
#[cfg(feature = "wgpu")]
use std::sync::OnceLock;
use std::sync::atomic::{AtomicBool, Ordering};

#[cfg(not(any(feature = "flex", feature = "ndarray", feature = "wgpu")))]
compile_error!("refnpr needs at least one backend feature: flex, ndarray or wgpu");

use crate::util::device_stats;
use crate::util::progress::Progress;
use crate::util::transfer::human_bytes;

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

    /// Whether this build has the backend (its cargo feature was on).
    pub fn is_compiled(self) -> bool {
        match self {
            BackendKind::Flex => cfg!(feature = "flex"),
            BackendKind::Ndarray => cfg!(feature = "ndarray"),
            BackendKind::Wgpu => cfg!(feature = "wgpu"),
        }
    }

    /// The plain (no autodiff) device of this backend. For wgpu this brings
    /// the runtime up on first use and panics if no adapter exists, and a
    /// backend left out of the build panics: entry points call
    /// [`BackendKind::open`] first, which says either as an error.
    pub fn device(self) -> Device {
        self.try_device().unwrap_or_else(|e| panic!("{e:#}"))
    }

    #[allow(deprecated)] // ndarray is deprecated upstream but still a supported choice here
    fn try_device(self) -> Result<Device> {
        if !self.is_compiled() {
            bail!(
                "this build of refnpr has no {self} backend: build it with the cargo feature `{self}` \
                 (a notebook: `:dep refnpr = {{ path = \"..\", features = [\"{self}\"] }}`)"
            );
        }
        match self {
            #[cfg(feature = "flex")]
            BackendKind::Flex => Ok(Device::flex()),
            #[cfg(feature = "ndarray")]
            BackendKind::Ndarray => Ok(Device::ndarray()),
            #[cfg(feature = "wgpu")]
            BackendKind::Wgpu => wgpu_runtime().map(|r| r.device.clone()),
            #[allow(unreachable_patterns)] // every backend compiled in
            _ => unreachable!("checked by is_compiled"),
        }
    }

    /// The device, brought up with a clear error when it cannot be: for
    /// wgpu, the first call in a process also reports the adapter it runs
    /// on (and warns when that adapter is a CPU).
    pub fn open(self, progress: &dyn Progress) -> Result<Device> {
        let device = self.try_device()?;
        if self == BackendKind::Wgpu {
            static ANNOUNCED: AtomicBool = AtomicBool::new(false);
            if !ANNOUNCED.swap(true, Ordering::SeqCst) {
                announce_wgpu(progress)?;
            }
        }
        Ok(device)
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

/// What wgpu runs on: the adapter as the graphics API describes it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct AdapterSummary {
    pub name: String,
    /// discrete GPU, integrated GPU, virtual GPU, CPU or other.
    pub kind: String,
    /// Vulkan, Metal, Dx12, Gl, ...
    pub api: String,
    pub driver: String,
    /// Software rendering (Mesa's llvmpipe/lavapipe, SwiftShader, WARP): a CPU.
    pub software: bool,
    /// The largest storage buffer a kernel may bind: no tensor may be larger
    /// (Mesa's lavapipe: 128 MiB; discrete GPUs: gigabytes).
    pub max_buffer_bytes: u64,
}

/// How much slower than flex wgpu runs on a software adapter, as measured
/// on the 2-core machine this project is built on with Mesa's lavapipe
/// (docs/performance.md, "wgpu without a GPU"): training steps 19086 vs 2770 rays/s
/// (6.9x), renderer forward + backward at 128³ 50076 vs 4292 rays/s (11.7x).
pub const SOFTWARE_ADAPTER_SLOWDOWN: &str = "7-12x";

impl AdapterSummary {
    #[cfg(feature = "wgpu")]
    pub fn of(info: &wgpu::AdapterInfo, limits: &wgpu::Limits) -> Self {
        let kind = match info.device_type {
            wgpu::DeviceType::DiscreteGpu => "discrete GPU",
            wgpu::DeviceType::IntegratedGpu => "integrated GPU",
            wgpu::DeviceType::VirtualGpu => "virtual GPU",
            wgpu::DeviceType::Cpu => "CPU",
            wgpu::DeviceType::Other => "other",
        };
        let driver = [info.driver.as_str(), info.driver_info.as_str()]
            .into_iter()
            .filter(|s| !s.is_empty())
            .collect::<Vec<_>>()
            .join(" ");
        Self {
            name: info.name.clone(),
            kind: kind.to_string(),
            api: format!("{:?}", info.backend),
            driver,
            software: info.device_type == wgpu::DeviceType::Cpu,
            max_buffer_bytes: limits.max_storage_buffer_binding_size,
        }
    }

    /// `wgpu adapter: NAME (KIND, API; driver DRIVER; buffers up to SIZE)`.
    pub fn line(&self) -> String {
        let driver = if self.driver.is_empty() { String::new() } else { format!("; driver {}", self.driver) };
        let buffers = human_bytes(self.max_buffer_bytes);
        format!("wgpu adapter: {} ({}, {}{driver}; buffers up to {buffers})", self.name, self.kind, self.api)
    }

    /// The warning a software adapter deserves (None for a GPU).
    pub fn software_warning(&self) -> Option<String> {
        self.software.then(|| {
            format!(
                "wgpu found no GPU and runs on {}, a software rasterizer on the CPU: {SOFTWARE_ADAPTER_SLOWDOWN} \
                 slower than the flex backend. Use `--backend flex` (or REFNPR_BACKEND=flex) unless you are testing wgpu.",
                self.name
            )
        })
    }
}

/// The wgpu device of this process and its adapter.
#[cfg(feature = "wgpu")]
struct WgpuRuntime {
    device: Device,
    adapter: AdapterSummary,
    /// Counts kernel launches for the process's life (`device_stats`).
    _launches: burn_cubecl::cubecl::logging::LaunchObservation,
}

#[cfg(feature = "wgpu")]
static RUNTIME: OnceLock<std::result::Result<WgpuRuntime, String>> = OnceLock::new();

/// Brings the wgpu runtime up once per process (Burn registers one runtime
/// per device selector; a second registration is refused).
#[cfg(feature = "wgpu")]
fn wgpu_runtime() -> Result<&'static WgpuRuntime> {
    RUNTIME
        .get_or_init(|| {
            Device::wgpu_options()
                .init_with_setup()
                .map(|(device, setup)| WgpuRuntime {
                    device,
                    adapter: AdapterSummary::of(&setup.adapter.get_info(), &setup.device.limits()),
                    _launches: device_stats::count_launches(),
                })
                .inspect(|_| device_stats::wgpu_is_up())
                .map_err(|e| e.to_string())
        })
        .as_ref()
        .map_err(|e| {
            anyhow!(
                "the wgpu backend found no usable adapter ({e}). Without a GPU, Mesa's software Vulkan \
                 provides one (Debian/Ubuntu: apt-get install mesa-vulkan-drivers libvulkan1); or use --backend flex"
            )
        })
}

/// Reports the adapter wgpu runs on (and warns when it is a CPU): what
/// [`BackendKind::open`] says the first time in a process.
pub fn announce_wgpu(progress: &dyn Progress) -> Result<AdapterSummary> {
    let adapter = wgpu_adapter()?;
    progress.info(adapter.line());
    if let Some(w) = adapter.software_warning() {
        progress.warning(w);
    }
    Ok(adapter)
}

/// The largest tensor, in bytes, a kernel on `device` may bind: the wgpu
/// adapter's storage-buffer limit; None on the CPU backends (no limit but memory).
pub fn max_buffer_bytes(device: &Device) -> Option<u64> {
    if crate::util::tensor::is_host_memory(device) {
        return None;
    }
    wgpu_adapter().ok().map(|a| a.max_buffer_bytes)
}

/// A CPU backend's device, for what is kept in host memory beside a GPU's
/// work (`field::grid::placement`): flex, else ndarray; None in a build with neither.
pub fn host_device() -> Option<Device> {
    [BackendKind::Flex, BackendKind::Ndarray].into_iter().find(|b| b.is_compiled()).map(BackendKind::device)
}

/// The adapter wgpu runs on in this process (bringing the runtime up).
pub fn wgpu_adapter() -> Result<AdapterSummary> {
    #[cfg(feature = "wgpu")]
    return Ok(wgpu_runtime()?.adapter.clone());
    #[cfg(not(feature = "wgpu"))]
    BackendKind::Wgpu.try_device().map(|_| unreachable!("no wgpu in this build"))
}

/// Every adapter wgpu can see, on every graphics API compiled in (for
/// `refnpr info`; does not bring the runtime up). None without the wgpu feature.
#[cfg(not(feature = "wgpu"))]
pub fn wgpu_adapters() -> Vec<AdapterSummary> {
    Vec::new()
}

/// Every adapter wgpu can see, on every graphics API compiled in (for
/// `refnpr info`; does not bring the runtime up).
#[cfg(feature = "wgpu")]
pub fn wgpu_adapters() -> Vec<AdapterSummary> {
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
        backends: wgpu::Backends::all(),
        ..wgpu::InstanceDescriptor::new_without_display_handle()
    });
    futures_lite::future::block_on(instance.enumerate_adapters(wgpu::Backends::all()))
        .iter()
        .map(|a| AdapterSummary::of(&a.get_info(), &a.limits()))
        .collect()
}
