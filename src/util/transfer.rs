//! Host <-> device traffic, counted where it happens.
//!
//! Every plain buffer that becomes a tensor and every tensor whose values
//! come back to plain Rust goes through `util::tensor` (and the VGG16
//! weights through `Vgg16::load`), which records it here. On the CPU
//! backends these are copies in memory; on wgpu they are what a GPU run
//! pays for in bus transfers, and every read is also a synchronisation
//! point (the host waits for the device's queue). The counts depend only on
//! the library's calls, not on the backend, so they are measured on flex.
//!
//! Counted per thread: the library moves tensors only from the thread that
//! drives a job (its parallel loops are plain-Rust marching and loading), so
//! two jobs on two threads (the tests) never mix their counts.

use std::cell::Cell;
use std::fmt;

use serde::{Deserialize, Serialize};

/// Counts of host-to-device uploads and device-to-host reads.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Transfers {
    /// Plain buffers turned into tensors.
    pub uploads: u64,
    pub upload_bytes: u64,
    /// Tensors read back into plain buffers.
    pub reads: u64,
    pub read_bytes: u64,
    /// GPU kernels launched (`util::device_stats::kernel_launches`); 0 on the
    /// CPU backends.
    #[serde(default)]
    pub launches: u64,
}

thread_local! {
    static COUNTED: Cell<Transfers> =
        const { Cell::new(Transfers { uploads: 0, upload_bytes: 0, reads: 0, read_bytes: 0, launches: 0 }) };
}

/// Records one upload of `bytes`.
pub fn record_upload(bytes: usize) {
    COUNTED.with(|c| {
        let mut t = c.get();
        t.uploads += 1;
        t.upload_bytes += bytes as u64;
        c.set(t);
    });
}

/// Records one read of `bytes`.
pub fn record_read(bytes: usize) {
    COUNTED.with(|c| {
        let mut t = c.get();
        t.reads += 1;
        t.read_bytes += bytes as u64;
        c.set(t);
    });
}

/// Everything this thread has moved so far; subtract two readings with
/// [`Transfers::since`] to get what a piece of work moved.
pub fn counted() -> Transfers {
    Transfers { launches: crate::util::device_stats::kernel_launches(), ..COUNTED.with(Cell::get) }
}

/// A piece of work's value, what it moved and how long it took.
pub struct Measured<T> {
    pub value: T,
    pub moved: Transfers,
    pub seconds: f64,
}

/// Runs `work`, counting what it moves and timing it: every phase and
/// step whose traffic is reported is measured through here.
pub fn measure<T>(work: impl FnOnce() -> T) -> Measured<T> {
    let (before, started) = (counted(), std::time::Instant::now());
    let value = work();
    Measured { value, moved: counted().since(before), seconds: started.elapsed().as_secs_f64() }
}

impl Transfers {
    /// What was moved between `earlier` and `self` (two readings of [`counted`]).
    pub fn since(self, earlier: Transfers) -> Transfers {
        Transfers {
            uploads: self.uploads - earlier.uploads,
            upload_bytes: self.upload_bytes - earlier.upload_bytes,
            reads: self.reads - earlier.reads,
            read_bytes: self.read_bytes - earlier.read_bytes,
            launches: self.launches - earlier.launches,
        }
    }

    /// The sum of two counts.
    pub fn plus(self, other: Transfers) -> Transfers {
        Transfers {
            uploads: self.uploads + other.uploads,
            upload_bytes: self.upload_bytes + other.upload_bytes,
            reads: self.reads + other.reads,
            read_bytes: self.read_bytes + other.read_bytes,
            launches: self.launches + other.launches,
        }
    }

    /// The mean per step over `steps` steps (rounded down; `steps` 0 counts as 1).
    pub fn per_step(self, steps: usize) -> Transfers {
        let n = steps.max(1) as u64;
        Transfers {
            uploads: self.uploads / n,
            upload_bytes: self.upload_bytes / n,
            reads: self.reads / n,
            read_bytes: self.read_bytes / n,
            launches: self.launches / n,
        }
    }
}

/// A phase's traffic: the total, its steps, and the mean per step.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PhaseTransfers {
    pub steps: usize,
    pub total: Transfers,
    pub per_step: Transfers,
}

impl PhaseTransfers {
    pub fn new(total: Transfers, steps: usize) -> Self {
        Self { steps, total, per_step: total.per_step(steps) }
    }

    /// A line for `--verbose` output: `refit: 12 steps, per step 9 uploads (...), ...`.
    pub fn describe(&self, phase: &str) -> String {
        if self.steps == 0 {
            return format!("transfers, {phase}: {}", self.total);
        }
        format!("transfers, {phase}: {} steps, per step {}; in all {}", self.steps, self.per_step, self.total)
    }
}

/// A byte count for people: `512 B`, `3.4 kB`, `12.0 MB`, `1.2 GB`.
pub fn human_bytes(bytes: u64) -> String {
    let b = bytes as f64;
    match bytes {
        0..1_000 => format!("{bytes} B"),
        1_000..1_000_000 => format!("{:.1} kB", b / 1e3),
        1_000_000..1_000_000_000 => format!("{:.1} MB", b / 1e6),
        _ => format!("{:.2} GB", b / 1e9),
    }
}

impl fmt::Display for Transfers {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} uploads ({}), {} reads ({})",
            self.uploads,
            human_bytes(self.upload_bytes),
            self.reads,
            human_bytes(self.read_bytes)
        )?;
        match self.launches {
            0 => Ok(()),
            n => write!(f, ", {n} kernel launches"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_are_per_thread_and_subtract() {
        let before = counted();
        record_upload(100);
        record_upload(28);
        record_read(4);
        let moved = counted().since(before);
        assert_eq!(moved, Transfers { uploads: 2, upload_bytes: 128, reads: 1, read_bytes: 4, launches: 0 });
        // Another thread's traffic is not this thread's.
        std::thread::spawn(|| record_upload(1 << 20)).join().unwrap();
        assert_eq!(counted().since(before), moved);
        assert_eq!(moved.plus(moved).per_step(2), moved);
        assert_eq!(moved.to_string(), "2 uploads (128 B), 1 reads (4 B)");
        assert_eq!(human_bytes(1_234_567), "1.2 MB");
    }
}

/// What each phase of a run cost: wall seconds, memory when it ended, and
/// host-device traffic. Both runs (`photo::run`, `stylize::run`) measure
/// their phases through [`PhaseLog::run`], one call a phase.
#[derive(Default)]
pub struct PhaseLog {
    pub seconds: std::collections::BTreeMap<String, f64>,
    pub memory: std::collections::BTreeMap<String, crate::util::memory::MemoryNow>,
    pub transfers: std::collections::BTreeMap<String, PhaseTransfers>,
}

impl PhaseLog {
    /// Runs `work` as phase `name` of `steps` steps and records its cost
    /// (nothing when it fails: the run stops there).
    pub fn run<T, E>(&mut self, name: &str, steps: usize, work: impl FnOnce() -> Result<T, E>) -> Result<T, E> {
        let m = measure(work);
        let value = m.value?;
        self.record(name, m.seconds, PhaseTransfers::new(m.moved, steps));
        Ok(value)
    }

    /// Records a phase measured by its own loop.
    pub fn record(&mut self, name: &str, seconds: f64, moved: PhaseTransfers) {
        self.seconds.insert(name.to_string(), seconds);
        self.memory.insert(name.to_string(), crate::util::memory::MemoryNow::read());
        self.transfers.insert(name.to_string(), moved);
    }
}
