//! Where a repeated step spends its time: wall seconds per named part,
//! summed over the steps (`stylize.json`'s `step_profile`, `refnpr
//! bench-stylize`).
//!
//! Host wall time: on the CPU backends work runs when it is issued, so each
//! part gets its own cost. On a GPU the queue runs asynchronously and a
//! part's time lands where the host next waits for the device (a read).

use std::cell::RefCell;
use std::time::Instant;

use serde::{Deserialize, Serialize};

/// One part's total.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PartTime {
    pub part: String,
    pub seconds: f64,
    /// How many times it was timed.
    pub calls: usize,
}

/// Seconds per part, in the order the parts were first timed.
#[derive(Debug, Default)]
pub struct StepProfile {
    parts: RefCell<Vec<PartTime>>,
}

impl StepProfile {
    /// Runs `f`, adding its wall time to `part`.
    pub fn time<T>(&self, part: &str, f: impl FnOnce() -> T) -> T {
        let started = Instant::now();
        let value = f();
        self.add(part, started.elapsed().as_secs_f64());
        value
    }

    /// Adds `seconds` to `part`.
    pub fn add(&self, part: &str, seconds: f64) {
        let mut parts = self.parts.borrow_mut();
        match parts.iter_mut().find(|p| p.part == part) {
            Some(p) => {
                p.seconds += seconds;
                p.calls += 1;
            }
            None => parts.push(PartTime { part: part.to_string(), seconds, calls: 1 }),
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

/// `1.2 s`, or `35 ms` below a second.
fn seconds(s: f64) -> String {
    if s >= 1.0 { format!("{s:.1} s") } else { format!("{:.0} ms", s * 1e3) }
}

/// A one-line summary: each part's share of the summed time.
pub fn describe(parts: &[PartTime]) -> String {
    let total: f64 = parts.iter().map(|p| p.seconds).sum();
    let shares: Vec<String> = parts
        .iter()
        .map(|p| format!("{} {} ({:.0} %)", p.part, seconds(p.seconds), 100.0 * p.seconds / total.max(1e-12)))
        .collect();
    shares.join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

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
        assert!(parts[0].seconds >= 1.0 && parts[0].seconds < 1.5);
        assert!(describe(&parts).starts_with("render 1.0 s (33 %), vgg 2.0 s (67 %)"));
        assert_eq!(seconds(0.035), "35 ms");
        p.clear();
        assert!(p.parts().is_empty());
    }
}
