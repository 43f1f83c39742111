//! What a GPU step costs, counted: kernel launches (cubecl's launch
//! observer) and the wgpu device's memory (its pools' report). These are the
//! proxies for a GPU's speed that a machine without one can measure
//! (docs/performance.md). Both read nothing where wgpu is not up.

use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use serde::Serialize;

thread_local! {
    /// Kernel launches this thread issued so far.
    static LAUNCHES: Cell<u64> = const { Cell::new(0) };
}

/// Set once the wgpu runtime is up (`util::backend`): before that, asking
/// the device for its memory would bring it up.
static WGPU_UP: AtomicBool = AtomicBool::new(false);

/// Called by `util::backend` when the wgpu runtime has come up.
#[cfg_attr(not(feature = "wgpu"), allow(dead_code))]
pub(crate) fn wgpu_is_up() {
    WGPU_UP.store(true, Ordering::Relaxed);
}

#[cfg(feature = "wgpu")]
struct LaunchCounter;

#[cfg(feature = "wgpu")]
impl burn_cubecl::cubecl::logging::LaunchObserver for LaunchCounter {
    // Called on the thread that issues the launch, so the count is that thread's.
    fn launched(&self, _kernel: &'static str) {
        LAUNCHES.with(|n| n.set(n.get() + 1));
    }
}

/// Starts counting launches, for as long as the guard lives (the wgpu
/// runtime keeps it for the process's life).
#[cfg(feature = "wgpu")]
pub(crate) fn count_launches() -> burn_cubecl::cubecl::logging::LaunchObservation {
    burn_cubecl::cubecl::logging::LaunchObservation::new(std::sync::Arc::new(LaunchCounter))
}

/// GPU kernels this thread launched so far (per thread, as `util::transfer`
/// counts traffic); 0 on the CPU backends, which launch none.
pub fn kernel_launches() -> u64 {
    LAUNCHES.with(Cell::get)
}

/// What the wgpu device's memory pools hold, in bytes: `in_use` by live
/// tensors, `reserved` in the pools' pages (what the work so far needed at
/// once, less pages the pools gave back).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct DeviceMemory {
    pub in_use: u64,
    pub reserved: u64,
}

/// The wgpu device's memory now, where this process brought wgpu up (it
/// waits for the device's queue); None otherwise.
pub fn device_memory() -> Option<DeviceMemory> {
    if !WGPU_UP.load(Ordering::Relaxed) {
        return None;
    }
    #[cfg(feature = "wgpu")]
    {
        let client = burn_cubecl::CubeDevice::Wgpu(Default::default()).client();
        let usage = client.memory_report(burn_cubecl::cubecl::MemoryScope::Device).usage();
        Some(DeviceMemory { in_use: usage.bytes_in_use, reserved: usage.bytes_reserved })
    }
    #[cfg(not(feature = "wgpu"))]
    None
}

/// The most device memory in use seen where a step calls [`note`](Self::note),
/// when enabled: a step's widest points (its forward's tensors held for the
/// backward, then the gradients) above what stays resident. Each note waits
/// for the device's queue, so only measurements enable it
/// (examples/step_costs.rs).
#[derive(Debug, Default)]
pub struct PeakProbe {
    enabled: bool,
    peak: AtomicU64,
}

impl PeakProbe {
    pub fn enabled() -> Self {
        Self { enabled: true, ..Self::default() }
    }

    pub fn note(&self) {
        if let Some(m) = self.enabled.then(device_memory).flatten() {
            self.peak.fetch_max(m.in_use, Ordering::Relaxed);
        }
    }

    /// The peak in bytes; None when disabled or off a GPU.
    pub fn peak(&self) -> Option<u64> {
        Some(self.peak.load(Ordering::Relaxed)).filter(|&p| self.enabled && p > 0)
    }
}
