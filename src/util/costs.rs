//! Time and memory estimates for the long commands (`train`, `stylize`),
//! from measured costs: every finished command appends what it did and
//! what it took to a ledger on this machine (one JSON line per job,
//! `$REFNPR_COSTS` or the user's cache folder); a new job is estimated from
//! the most similar record (same job, backend and capture shape), scaled by
//! the work. Before the machine has a record of that kind, the figures
//! measured on the project's 2-core reference machine stand in
//! (`docs/performance.md`), and the line says so.
//!
//! Scaling is linear: time by the work units (fit: steps x rays per step;
//! stylization: training pixels x epochs), memory above the process's floor
//! ([`BASE_MB`]) by the training pixels.
//! That is a rough guide, which is all the line claims; a rerun of the same
//! scene and schedule is estimated from its own measurement.

use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// What a long job is about to do.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Work {
    /// `train`, `stylize refnpr` or `stylize arf` (the method as `--method` names it).
    pub job: String,
    /// The backend's name (`flex`, `ndarray`, `wgpu`).
    pub backend: String,
    /// `around` or `forward-facing`.
    pub shape: String,
    /// What the time scales with: fit steps x rays per step; stylization:
    /// training pixels x epochs (refit + image).
    pub units: f64,
    /// Training pixels (all views): what the memory scales with.
    pub pixels: f64,
    /// A resumed job does part of its work: neither estimated nor recorded.
    #[serde(default)]
    pub resumed: bool,
}

/// One finished job's cost.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CostRecord {
    pub work: Work,
    /// Wall seconds from the job's start to its end.
    pub seconds: f64,
    /// The process's peak resident memory, MB.
    pub peak_mb: f64,
    /// The machine's core count when it was measured.
    pub cores: usize,
}

/// Where an estimate came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Basis {
    /// A job measured on this machine.
    Ledger,
    /// The project's 2-core reference machine (no record of this kind here yet).
    Reference,
}

/// An estimate of a job's wall time and peak memory.
#[derive(Debug, Clone, PartialEq)]
pub struct Estimate {
    pub seconds: f64,
    pub peak_mb: f64,
    /// The record it was scaled from.
    pub from: CostRecord,
    pub basis: Basis,
}

impl std::fmt::Display for Estimate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let from = &self.from;
        let measured = format!("{} and {}", duration(from.seconds), megabytes(from.peak_mb));
        let origin = match self.basis {
            Basis::Ledger => format!("scaled from a {} measured on this machine: {measured}", from.work.job),
            Basis::Reference => format!(
                "scaled from the {} of a reference scene on a 2-core machine, {measured}; this machine has {} cores, \
                 and its own runs refine the estimate",
                from.work.job,
                cores()
            ),
        };
        write!(f, "estimate: about {} and {} peak memory ({origin})", duration(self.seconds), megabytes(self.peak_mb))
    }
}

/// `2 min 30 s`, `45 s`, `1 h 05 min`.
fn duration(seconds: f64) -> String {
    let s = seconds.round().max(0.0) as u64;
    match s {
        0..60 => format!("{s} s"),
        60..3600 => format!("{} min {:02} s", s / 60, s % 60),
        _ => format!("{} h {:02} min", s / 3600, s % 3600 / 60),
    }
}

/// `850 MB`, `2.8 GB`.
fn megabytes(mb: f64) -> String {
    if mb < 1000.0 { format!("{mb:.0} MB") } else { format!("{:.1} GB", mb / 1000.0) }
}

fn cores() -> usize {
    std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
}

/// The jobs measured on the reference machine (2 cores, flex backend; the
/// commands and their figures are in `docs/performance.md`): the default
/// schedules on lego (100 views of 200x200) and fern (17 views of 504x378).
fn reference_records() -> Vec<CostRecord> {
    const LEGO_PIXELS: f64 = 100.0 * 200.0 * 200.0;
    const FERN_PIXELS: f64 = 17.0 * 504.0 * 378.0;
    // Ref-NPR and ARF's default schedules: 2 refit + 10 image epochs.
    const STYLIZE_EPOCHS: f64 = 12.0;
    let record = |job: &str, shape: &str, units: f64, pixels: f64, seconds: f64, peak_mb: f64| CostRecord {
        work: Work { job: job.into(), backend: "flex".into(), shape: shape.into(), units, pixels, resumed: false },
        seconds,
        peak_mb,
        cores: 2,
    };
    vec![
        record("train", "around", 3600.0 * 4096.0, LEGO_PIXELS, 147.0, 1350.0),
        record("train", "forward-facing", 3000.0 * 4096.0, FERN_PIXELS, 657.0, 3400.0),
        record("stylize refnpr", "around", LEGO_PIXELS * STYLIZE_EPOCHS, LEGO_PIXELS, 739.0, 2840.0),
        record("stylize arf", "around", LEGO_PIXELS * STYLIZE_EPOCHS, LEGO_PIXELS, 436.0, 2050.0),
        record("stylize refnpr", "forward-facing", FERN_PIXELS * STYLIZE_EPOCHS, FERN_PIXELS, 1407.0, 5710.0),
    ]
}

/// Memory a job takes whatever its scene (the program, the backend's
/// pools): a 48-pixel procedural scene's 200-step fit peaks at 276 MB on
/// the flex backend. Estimates scale only what lies above it.
pub const BASE_MB: f64 = 250.0;

/// The records a ledger keeps (older ones are dropped when it grows past).
pub const KEEP: usize = 200;

/// The cost records of this machine, one JSON line each.
#[derive(Debug, Clone)]
pub struct Ledger {
    path: PathBuf,
}

impl Ledger {
    pub fn at(path: impl Into<PathBuf>) -> Self {
        Self { path: path.into() }
    }

    /// `$REFNPR_COSTS` (empty: no ledger), else `costs.jsonl` in the
    /// user's cache folder (`$XDG_CACHE_HOME/refnpr`, `~/.cache/refnpr`).
    pub fn default_location() -> Option<Self> {
        if let Some(p) = std::env::var_os("REFNPR_COSTS") {
            return (!p.is_empty()).then(|| Self::at(p));
        }
        let cache = std::env::var_os("XDG_CACHE_HOME")
            .filter(|p| !p.is_empty())
            .map(PathBuf::from)
            .or_else(|| std::env::var_os("HOME").map(|h| Path::new(&h).join(".cache")))?;
        Some(Self::at(cache.join("refnpr").join("costs.jsonl")))
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The records in the file, oldest first; a missing file has none and
    /// a line that does not parse (a crash mid-write, an older format) is skipped.
    pub fn records(&self) -> Vec<CostRecord> {
        let Ok(text) = std::fs::read_to_string(&self.path) else { return Vec::new() };
        text.lines().filter_map(|l| serde_json::from_str(l).ok()).collect()
    }

    /// Appends a record, keeping the newest [`KEEP`].
    pub fn record(&self, record: &CostRecord) -> std::io::Result<()> {
        if let Some(dir) = self.path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        let line = serde_json::to_string(record).map_err(std::io::Error::other)?;
        let mut records = self.records();
        if records.len() >= KEEP {
            records.drain(..records.len() + 1 - KEEP);
            let mut text: String =
                records.iter().filter_map(|r| serde_json::to_string(r).ok()).map(|l| l + "\n").collect();
            text.push_str(&line);
            text.push('\n');
            return crate::util::files::write_text(&self.path, &text).map_err(std::io::Error::other);
        }
        let mut file = std::fs::OpenOptions::new().create(true).append(true).open(&self.path)?;
        writeln!(file, "{line}")
    }

    /// The estimate for `work`: from this machine's most similar record,
    /// else from the reference machine's (flex backend only), else none.
    pub fn estimate(&self, work: &Work) -> Option<Estimate> {
        if work.resumed || work.units <= 0.0 || work.pixels <= 0.0 {
            return None;
        }
        let scaled = |from: &CostRecord, basis| Estimate {
            seconds: from.seconds * work.units / from.work.units,
            peak_mb: BASE_MB + (from.peak_mb - BASE_MB).max(0.0) * work.pixels / from.work.pixels,
            from: from.clone(),
            basis,
        };
        // This machine's pace wins, unless its nearest record is a job of
        // another size and the reference machine has one of this size:
        // costs are not linear over an order of magnitude (a small scene
        // never reaches the large grid), so a 96-pixel demo says less of
        // lego than lego's own row does.
        match (nearest(&self.records(), work), nearest(&reference_records(), work)) {
            (Some(here), Some(reference)) if distance(&reference, work) + SIZE_SLACK < distance(&here, work) => {
                Some(scaled(&reference, Basis::Reference))
            }
            (Some(here), _) => Some(scaled(&here, Basis::Ledger)),
            (None, reference) => reference.map(|r| scaled(&r, Basis::Reference)),
        }
    }
}

/// How much closer in size (summed log ratios of work and pixels) a
/// reference record must be than this machine's nearest one to be used
/// instead: a factor of 4.
const SIZE_SLACK: f64 = std::f64::consts::LN_2 * 2.0;

/// How far a record's job is from `work` in size: the summed absolute log
/// ratios of their work units and training pixels.
fn distance(r: &CostRecord, work: &Work) -> f64 {
    (r.work.units / work.units).ln().abs() + (r.work.pixels / work.pixels).ln().abs()
}

/// The record of the same job, backend and shape whose work is closest
/// (the newest among equals: a machine's pace changes).
fn nearest(records: &[CostRecord], work: &Work) -> Option<CostRecord> {
    let distance = |r: &CostRecord| distance(r, work);
    records
        .iter()
        .filter(|r| {
            r.work.job == work.job
                && r.work.backend == work.backend
                && r.work.shape == work.shape
                && r.work.units > 0.0
                && r.work.pixels > 0.0
                && r.seconds.is_finite()
                && r.peak_mb.is_finite()
        })
        .rev()
        .min_by(|a, b| distance(a).total_cmp(&distance(b)))
        .cloned()
}

/// The record of a finished job (the peak memory as the OS reports it).
pub fn finished(work: Work, seconds: f64, peak_mb: f64) -> CostRecord {
    CostRecord { work, seconds, peak_mb, cores: cores() }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn work(job: &str, units: f64, pixels: f64) -> Work {
        Work { job: job.into(), backend: "flex".into(), shape: "around".into(), units, pixels, resumed: false }
    }

    #[test]
    fn an_estimate_scales_the_nearest_record_of_the_same_kind() {
        let ledger = Ledger::at(crate::test_support::temp_dir("costs-estimate").join("sub/costs.jsonl"));
        // No record here: the reference machine's lego train, scaled by the steps.
        let half = ledger.estimate(&work("train", 1800.0 * 4096.0, 4e6)).unwrap();
        assert_eq!(half.basis, Basis::Reference);
        assert!((half.seconds - 147.0 / 2.0).abs() < 1e-6 && (half.peak_mb - 1350.0).abs() < 1e-6);
        let quarter = ledger.estimate(&work("train", 3600.0 * 4096.0, 1e6)).unwrap();
        assert!((quarter.peak_mb - (BASE_MB + (1350.0 - BASE_MB) / 4.0)).abs() < 1e-6);
        assert!(
            half.to_string().starts_with("estimate: about 1 min 14 s and 1.4 GB peak memory (scaled from the train")
        );
        // Nothing to go on for another backend.
        let gpu = Work { backend: "wgpu".into(), ..work("train", 1.0, 1.0) };
        assert_eq!(ledger.estimate(&gpu), None);
        // Measured records win, the nearest in work; other jobs and shapes are ignored.
        ledger.record(&finished(work("train", 100.0, 10.0), 10.0, 350.0)).unwrap();
        ledger.record(&finished(work("train", 1000.0, 100.0), 50.0, 400.0)).unwrap();
        ledger.record(&finished(work("stylize arf", 200.0, 20.0), 1.0, 1.0)).unwrap();
        let other_shape = Work { shape: "forward-facing".into(), ..work("train", 200.0, 20.0) };
        ledger.record(&finished(other_shape, 1.0, 1.0)).unwrap();
        let e = ledger.estimate(&work("train", 200.0, 20.0)).unwrap();
        assert_eq!((e.basis, e.from.seconds), (Basis::Ledger, 10.0));
        assert!((e.seconds - 20.0).abs() < 1e-9 && (e.peak_mb - 450.0).abs() < 1e-9);
        assert!(e.to_string().contains("measured on this machine: 10 s and 350 MB"), "{e}");
        // A lego-sized job is scaled from lego's reference row, not from a
        // record a hundred times smaller; a record near its size wins again.
        let lego = work("train", 3600.0 * 4096.0, 4e6);
        assert_eq!(ledger.estimate(&lego).unwrap().basis, Basis::Reference);
        ledger.record(&finished(work("train", 3000.0 * 4096.0, 3e6), 120.0, 1200.0)).unwrap();
        assert_eq!(ledger.estimate(&lego).unwrap().basis, Basis::Ledger);
        // A resumed job is not estimated.
        assert_eq!(ledger.estimate(&Work { resumed: true, ..work("train", 200.0, 20.0) }), None);
    }

    #[test]
    fn a_ledger_skips_bad_lines_and_keeps_the_newest_records() {
        let ledger = Ledger::at(crate::test_support::temp_dir("costs-ledger").join("costs.jsonl"));
        std::fs::write(ledger.path(), "{not json\n").unwrap();
        assert!(ledger.records().is_empty());
        for i in 0..KEEP + 3 {
            ledger.record(&finished(work("train", 1.0 + i as f64, 1.0), 1.0, 1.0)).unwrap();
        }
        let records = ledger.records();
        assert_eq!(records.len(), KEEP);
        assert_eq!(records.last().unwrap().work.units, (KEEP + 3) as f64);
    }

    #[test]
    fn durations_and_sizes_read_as_a_person_writes_them() {
        assert_eq!(duration(44.6), "45 s");
        assert_eq!(duration(147.0), "2 min 27 s");
        assert_eq!(duration(3900.0), "1 h 05 min");
        assert_eq!(megabytes(830.0), "830 MB");
        assert_eq!(megabytes(2840.0), "2.8 GB");
    }
}
