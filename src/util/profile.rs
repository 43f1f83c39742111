//! Where a repeated step spends its time: wall seconds per named part,
//! summed over the steps (`stylize.json`'s `step_profile`, `refnpr
//! bench-stylize`).
//!
//! Host wall time: on the CPU backends work runs when it is issued, so each
//! part gets its own cost. On a GPU the queue runs asynchronously and a
//! part's time lands where the host next waits for the device (a read).
//! A profile made by [`StepProfile::syncing`] waits for the device at the
//! end of each part instead (`refnpr bench-stylize --sync-parts`).
//! Parts timed with [`StepProfile::time`] also get the process's CPU time
//! (all threads), so CPU seconds over wall seconds says how much of the
//! machine a part used: about 1 for a serial part, up to the core count.

use std::cell::RefCell;
use std::time::Instant;

use burn::tensor::Device;

use serde::{Deserialize, Serialize};

/// One part's total.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PartTime {
    pub part: String,
    pub seconds: f64,
    /// How many times it was timed.
    pub calls: usize,
    /// The process's CPU seconds (all threads) over the same calls, where
    /// the part was timed by [`StepProfile::time`] on a system that has
    /// the clock.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cpu_seconds: Option<f64>,
}

impl PartTime {
    /// This total as a mean over `steps` steps (wall and CPU seconds; the
    /// call count stays the total).
    pub fn per_step(&self, steps: usize) -> PartTime {
        let n = steps.max(1) as f64;
        PartTime { seconds: self.seconds / n, cpu_seconds: self.cpu_seconds.map(|c| c / n), ..self.clone() }
    }
}

/// Seconds per part, in the order the parts were first timed.
#[derive(Debug, Default)]
pub struct StepProfile {
    parts: RefCell<Vec<PartTime>>,
    /// The device waited for at the end of each part ([`syncing`](Self::syncing)).
    sync: Option<Device>,
}

impl StepProfile {
    /// A profile that, with `device`, waits for it to finish its queue at
    /// the end of each part, so that on a GPU a part's time is its own work
    /// (the queue is drained between parts, which changes how work
    /// overlaps: compare whole steps without it); `None`
    /// is the default profile.
    pub fn syncing(device: Option<Device>) -> Self {
        Self { sync: device, ..Self::default() }
    }

    /// Runs `f`, adding its wall time to `part`.
    pub fn time<T>(&self, part: &str, f: impl FnOnce() -> T) -> T {
        let (started, cpu_started) = (Instant::now(), process_cpu_seconds());
        let value = f();
        self.wait();
        let cpu = cpu_started.zip(process_cpu_seconds()).map(|(a, b)| b - a);
        self.record(part, started.elapsed().as_secs_f64(), cpu);
        value
    }

    /// Adds `seconds` (wall) to `part`.
    pub fn add(&self, part: &str, seconds: f64) {
        self.record(part, seconds, None);
    }

    /// Adds the wall time since `started` to `part` (after the wait of a
    /// [`syncing`](Self::syncing) profile).
    pub fn add_since(&self, part: &str, started: Instant) {
        self.wait();
        self.record(part, started.elapsed().as_secs_f64(), None);
    }

    /// A syncing profile's wait for its device. A failed wait is the
    /// device's error, which the step's next read reports.
    fn wait(&self) {
        if let Some(device) = &self.sync {
            let _ = device.sync();
        }
    }

    fn record(&self, part: &str, seconds: f64, cpu_seconds: Option<f64>) {
        let mut parts = self.parts.borrow_mut();
        match parts.iter_mut().find(|p| p.part == part) {
            Some(p) => {
                p.seconds += seconds;
                p.calls += 1;
                // A part timed both ways has no CPU total.
                p.cpu_seconds = p.cpu_seconds.zip(cpu_seconds).map(|(a, b)| a + b);
            }
            None => parts.push(PartTime { part: part.to_string(), seconds, calls: 1, cpu_seconds }),
        }
    }

    /// The totals so far.
    pub fn parts(&self) -> Vec<PartTime> {
        self.parts.borrow().clone()
    }

    /// Forgets every total.
    pub fn clear(&self) {
        self.parts.borrow_mut().clear();
    }
}

/// CPU seconds the process (all its threads) has used, where the system
/// has the clock.
fn process_cpu_seconds() -> Option<f64> {
    #[cfg(unix)]
    {
        let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
        // SAFETY: `ts` is a valid timespec for the call to write.
        let rc = unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
        (rc == 0).then_some(ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9)
    }
    #[cfg(not(unix))]
    {
        None
    }
}

/// `1.2 s`, or `35 ms` below a second.
fn seconds(s: f64) -> String {
    if s >= 1.0 { format!("{s:.1} s") } else { format!("{:.0} ms", s * 1e3) }
}

/// A one-line summary: each part's share of the summed time, and its CPU
/// share (CPU over wall time; 200 % is two busy cores) where known.
pub fn describe(parts: &[PartTime]) -> String {
    let total: f64 = parts.iter().map(|p| p.seconds).sum();
    let shares: Vec<String> = parts
        .iter()
        .map(|p| {
            let share = 100.0 * p.seconds / total.max(1e-12);
            match p.cpu_seconds {
                Some(cpu) => format!(
                    "{} {} ({share:.0} %, CPU {:.0} %)",
                    p.part,
                    seconds(p.seconds),
                    100.0 * cpu / p.seconds.max(1e-12)
                ),
                None => format!("{} {} ({share:.0} %)", p.part, seconds(p.seconds)),
            }
        })
        .collect();
    shares.join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A syncing profile waits for its device and records exactly what a
    /// plain one does: the same parts, in the same order, the same calls.
    #[test]
    fn a_syncing_profile_records_the_parts_a_plain_one_does() {
        let device = crate::util::backend::BackendKind::from_env().expect("REFNPR_BACKEND names a backend").device();
        let record = |p: &StepProfile| {
            let x = p.time("render", || {
                burn::tensor::Tensor::<2>::ones([64, 64], &device).matmul(burn::tensor::Tensor::ones([64, 64], &device))
            });
            let started = Instant::now();
            let _ = crate::util::tensor::to_vec(x);
            p.add_since("read", started);
            p.time("render", || ());
            p.parts().into_iter().map(|t| (t.part, t.calls)).collect::<Vec<_>>()
        };
        let plain = record(&StepProfile::default());
        assert_eq!(plain, [("render".to_string(), 2), ("read".to_string(), 1)]);
        assert_eq!(record(&StepProfile::syncing(Some(device.clone()))), plain);
    }

    #[test]
    fn parts_sum_per_name_in_first_seen_order() {
        let p = StepProfile::default();
        p.add("render", 1.0);
        p.add("vgg", 2.0);
        let v = p.time("render", || 7);
        assert_eq!(v, 7);
        let parts = p.parts();
        assert_eq!(parts.iter().map(|t| t.part.as_str()).collect::<Vec<_>>(), ["render", "vgg"]);
        assert_eq!((parts[0].calls, parts[1].calls), (2, 1));
        // Only the parts timed with `time` alone carry CPU time.
        assert_eq!((parts[0].cpu_seconds, parts[1].cpu_seconds), (None, None));
        p.time("spin", || {
            std::hint::black_box((0..3_000_000u64).fold(0u64, |a, i| a.wrapping_mul(31).wrapping_add(i)))
        });
        let spin = &p.parts()[2];
        if cfg!(unix) {
            let cpu = spin.cpu_seconds.expect("CPU time on unix");
            assert!(cpu > 0.0 && cpu <= spin.seconds * 64.0, "{cpu} CPU s in {} s", spin.seconds);
        }
        assert!(parts[0].seconds >= 1.0 && parts[0].seconds < 1.5);
        assert!(describe(&parts).starts_with("render 1.0 s (33 %), vgg 2.0 s (67 %)"));
        let timed = PartTime { part: "march".into(), seconds: 2.0, calls: 4, cpu_seconds: Some(3.0) };
        assert_eq!(describe(&[timed]), "march 2.0 s (100 %, CPU 150 %)");
        assert_eq!(seconds(0.035), "35 ms");
        p.clear();
        assert!(p.parts().is_empty());
    }
}
