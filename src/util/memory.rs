//! Memory readings from the OS (Linux; None elsewhere).

/// Peak resident memory of this process, in MB.
pub fn peak_rss_mb() -> Option<f64> {
    proc_status_mb("VmHWM:")
}

/// A memory line of /proc/self/status (`VmRSS:`, `VmHWM:`, ...) in MB.
pub fn proc_status_mb(key: &str) -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let l = s.lines().find(|l| l.starts_with(key))?;
    Some(l.split_whitespace().nth(1)?.parse::<f64>().ok()? / 1024.0)
}

/// Resident and peak resident memory (MB) at one moment: where a long
/// job's memory goes, phase by phase.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct MemoryNow {
    pub resident_mb: Option<f64>,
    pub peak_mb: Option<f64>,
    /// The wgpu device's pools, where the process runs on wgpu.
    pub device: Option<crate::util::device_stats::DeviceMemory>,
}

impl MemoryNow {
    pub fn read() -> Self {
        Self {
            resident_mb: proc_status_mb("VmRSS:"),
            peak_mb: peak_rss_mb(),
            device: crate::util::device_stats::device_memory(),
        }
    }
}

/// Memory the OS reports as available.
pub fn available_memory_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Resets the process's peak-RSS counter (Linux >= 4.0), so `peak_rss_mb` measures what follows.
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}
