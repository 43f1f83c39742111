//! The developer's commands, hidden from `--help`'s list: `bench`,
//! `bench-vgg`, `bench-stylize` (speed), `fuzz` (the parsers of outside
//! input, and this command line) and `info` (what the build runs on).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, ensure};
use clap::{CommandFactory, FromArgMatches};
use refnpr::stylize::{Method, StylizeJob};
use refnpr::tools::info::SystemInfo;
use refnpr::tools::{bench, fuzz};
use refnpr::util::{files, profile};
use refnpr::{BackendKind, Console, Progress};

use crate::common::backend_or_env;
use crate::stylize::{PhotoAndCase, stylize_config};

// `refnpr bench`'s arguments.
#[derive(clap::Args)]
pub struct BenchArgs {
    /// Backends to measure (default: all three).
    #[arg(long, value_enum, value_delimiter = ',')]
    pub backends: Option<Vec<BackendKind>>,
    /// Grid resolutions.
    #[arg(long, value_delimiter = ',', default_value = "128,256")]
    pub res: Vec<usize>,
    /// Rays per measured batch.
    #[arg(long, default_value_t = 4096)]
    pub rays: usize,
    /// Measured repetitions (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub repeats: usize,
    /// Also write the results as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// `refnpr bench`.
pub fn bench(args: BenchArgs) -> Result<()> {
    let BenchArgs { backends, res, rays, repeats, json } = args;
    run_bench(backends, &res, rays, repeats, json)
}

fn run_bench(
    backends: Option<Vec<BackendKind>>,
    res: &[usize],
    rays: usize,
    repeats: usize,
    json: Option<PathBuf>,
) -> Result<()> {
    let mut results = Vec::new();
    println!(
        "{:<8} {:>5} {:>9} {:>12} {:>14} {:>18}",
        "backend", "res", "voxels", "samples/ray", "fwd rays/s", "fwd+bwd rays/s"
    );
    for b in backends.unwrap_or(BackendKind::ALL.to_vec()) {
        for &r in res {
            let m = bench::renderer_throughput(b, r, rays, repeats)?;
            println!(
                "{:<8} {:>5} {:>9} {:>12.1} {:>14.0} {:>18.0}",
                m.backend,
                m.res,
                m.active_voxels,
                m.samples_per_ray,
                m.forward_rays_per_s,
                m.forward_backward_rays_per_s
            );
            results.push(m);
        }
    }
    if let Some(p) = json {
        files::write_json(&p, &results)?;
    }
    Ok(())
}

// `refnpr bench-vgg`'s arguments.
#[derive(clap::Args)]
pub struct BenchVggArgs {
    /// Backends to measure (default: all three).
    #[arg(long, value_enum, value_delimiter = ',')]
    pub backends: Option<Vec<BackendKind>>,
    /// Image sizes, WIDTHxHEIGHT.
    #[arg(long, value_delimiter = ',', default_value = "256x256,504x378")]
    pub sizes: Vec<String>,
    /// Unmeasured passes first (kernel compilation, allocator warm-up).
    #[arg(long, default_value_t = 1)]
    pub warmup: usize,
    /// Measured repetitions (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub repeats: usize,
    /// Skip the onnxruntime yardstick (needs python3 with onnxruntime).
    #[arg(long)]
    pub no_onnxruntime: bool,
    /// How the forward pass runs (default: staged).
    #[arg(long, value_enum)]
    pub forward: Option<refnpr::vgg::VggForward>,
    /// Also write the results as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// `refnpr bench-vgg`.
pub fn bench_vgg(args: BenchVggArgs) -> Result<()> {
    let BenchVggArgs { backends, sizes, warmup, repeats, no_onnxruntime, forward, json } = args;
    run_bench_vgg(backends, &sizes, warmup, repeats, no_onnxruntime, forward, json)
}

fn run_bench_vgg(
    backends: Option<Vec<BackendKind>>,
    sizes: &[String],
    warmup: usize,
    repeats: usize,
    no_onnxruntime: bool,
    forward: Option<refnpr::vgg::VggForward>,
    json: Option<PathBuf>,
) -> Result<()> {
    let mut sizes_wh = Vec::new();
    for s in sizes {
        let parsed = s.split_once('x').and_then(|(w, h)| Some((w.parse::<usize>().ok()?, h.parse::<usize>().ok()?)));
        sizes_wh.push(parsed.with_context(|| format!("--sizes: {s:?} is not WIDTHxHEIGHT"))?);
    }
    let mut ort = Vec::new();
    for &(w, h) in &sizes_wh {
        let ms = if no_onnxruntime {
            None
        } else {
            bench::onnxruntime_forward_ms(w, h, repeats)
                .map_err(|e| eprintln!("onnxruntime yardstick unavailable: {e:#}"))
                .ok()
        };
        if let Some(ms) = ms {
            println!("onnxruntime (CPU) {w}x{h}: forward {ms:.0} ms");
        }
        ort.push(ms);
    }
    println!(
        "{:<8} {:>9} {:>10} {:>14} {:>12} {:>18}",
        "backend", "size", "fwd ms", "fwd+bwd ms", "fwd+bwd MB", "fwd+bwd / ort fwd"
    );
    let mut results = Vec::new();
    for b in backends.unwrap_or(BackendKind::ALL.to_vec()) {
        for (&(w, h), ort_ms) in sizes_wh.iter().zip(&ort) {
            let m = bench::vgg_timing(b, w, h, warmup, repeats, forward)?;
            let ratio = ort_ms.map(|o| format!("{:.2}", m.forward_backward_ms / o)).unwrap_or("-".into());
            let mem = m.forward_backward_peak_mb.map(|v| format!("{v:.0}")).unwrap_or("-".into());
            let size = format!("{w}x{h}");
            println!(
                "{:<8} {:>9} {:>10.0} {:>14.0} {:>12} {:>18}",
                m.backend, size, m.forward_ms, m.forward_backward_ms, mem, ratio
            );
            results.push(serde_json::json!({ "result": m, "onnxruntime_forward_ms": ort_ms }));
        }
    }
    if let Some(p) = json {
        files::write_json(&p, &results)?;
    }
    Ok(())
}

// `refnpr bench-stylize`'s arguments.
#[derive(clap::Args)]
pub struct BenchStylizeArgs {
    #[command(flatten)]
    pub inputs: PhotoAndCase,
    /// Output run folder of the short stylization (stylize.json has every step's time).
    #[arg(long)]
    pub out: PathBuf,
    /// TOML config, as for `stylize` (its schedule is shortened).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// refnpr or arf.
    #[arg(long, value_enum, default_value_t = Method::RefNpr)]
    pub method: Method,
    /// Ray epochs of the refit (a fraction of one: its steps all cost the same).
    #[arg(long, default_value_t = 0.1)]
    pub refit_epochs: f32,
    /// Image epochs; with Ref-NPR and 2 or more, the last is the smooth update.
    #[arg(long, default_value_t = 2)]
    pub image_epochs: usize,
    /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
    #[arg(long, value_enum, env = "REFNPR_BACKEND")]
    pub backend: Option<BackendKind>,
    /// On a GPU, wait for the device at the end of each part of a step, so that each
    /// part's time is its own work (the config's `sync_parts`; compare whole steps without it).
    #[arg(long)]
    pub sync_parts: bool,
    /// Also write the results as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// `refnpr bench-stylize`.
pub fn bench_stylize(args: BenchStylizeArgs, progress: &Console) -> Result<()> {
    let BenchStylizeArgs { inputs, out, config, method, refit_epochs, image_epochs, backend, sync_parts, json } = args;
    let PhotoAndCase { photo, reference: case, data } = inputs;
    let mut config = stylize_config(config.as_deref())?;
    config.sync_parts |= sync_parts;
    let job = StylizeJob {
        photo,
        case,
        out,
        config,
        method,
        backend: backend_or_env(backend, progress)?,
        style: None,
        data,
        registration: None,
        render_test: false,
        resume: false,
    };
    run_bench_stylize(job, refit_epochs, image_epochs, json.as_deref(), progress)
}

/// `refnpr bench-stylize`: the short stylization's per-phase step costs, printed.
fn run_bench_stylize(
    job: StylizeJob,
    refit_epochs: f32,
    image_epochs: usize,
    json: Option<&Path>,
    progress: &dyn Progress,
) -> Result<()> {
    let r = bench::stylize_timing(job, refit_epochs, image_epochs, progress)?;
    let phases: Vec<String> = r.seconds.iter().map(|(k, v)| format!("{k} {v:.1} s")).collect();
    let [w, h] = r.image_size;
    println!("{} on {} ({} views, {w}x{h}), {}:", r.method, r.backend, r.views, phases.join(", "));
    for p in &r.phases {
        println!(
            "  {}: {} steps, median {:.3} s per step (mean {:.3}); per step: {}",
            p.phase,
            p.steps,
            p.median_step_seconds,
            p.mean_step_seconds,
            profile::describe(&p.parts)
        );
    }
    if let Some(mb) = r.peak_rss_mb {
        println!("  peak memory {mb:.0} MB");
    }
    if let Some(path) = json {
        files::write_json(path, &r)?;
    }
    Ok(())
}

// `refnpr fuzz`'s arguments.
#[derive(clap::Args)]
pub struct FuzzArgs {
    /// The parser to fuzz.
    #[arg(value_parser = clap::builder::PossibleValuesParser::new(fuzz_targets()))]
    pub target: String,
    /// Stop after this many seconds...
    #[arg(long, default_value_t = 60.0)]
    pub seconds: f64,
    /// ... or this many inputs.
    #[arg(long, default_value_t = u64::MAX)]
    pub cases: u64,
    /// A case running longer than this is a hang (its input is saved, the run stops).
    #[arg(long, default_value_t = 5.0)]
    pub case_seconds: f64,
    /// Seed of the mutations.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// The process's peak memory may not exceed this (a header claiming a huge size
    /// must be refused before allocating).
    #[arg(long, default_value_t = 256.0)]
    pub memory_mb: f64,
    /// Real scenes to add to the seed inputs, when the folder exists.
    #[arg(long, default_value = "../shared/data", hide = true)]
    pub shared_data: PathBuf,
}

/// `refnpr fuzz`.
pub fn fuzz(args: FuzzArgs) -> Result<()> {
    let FuzzArgs { target, seconds, cases, case_seconds, seed, memory_mb, shared_data } = args;
    let limits = fuzz::Limits { max_cases: cases, max_seconds: seconds, case_seconds, seed };
    run_fuzz(&target, &limits, memory_mb, &shared_data)
}

/// The fuzz targets: every parser of outside input, and the command line.
pub fn fuzz_targets() -> Vec<&'static str> {
    fuzz::TARGETS.iter().copied().chain(["cli"]).collect()
}

/// `refnpr fuzz`: one target, a JSON report; crashes make it fail.
fn run_fuzz(target: &str, limits: &fuzz::Limits, memory_mb: f64, shared: &Path) -> Result<()> {
    let scratch = std::env::temp_dir().join(format!("refnpr-fuzz-{target}-{}", std::process::id()));
    let t = match target {
        "cli" => fuzz::Target { name: "cli".into(), seeds: cli_fuzz_seeds(), check: Box::new(parse_cli_bytes) },
        name => fuzz::target(name, &scratch, shared.is_dir().then_some(shared))?,
    };
    let report = fuzz::run(&t, limits);
    std::fs::remove_dir_all(&scratch).ok();
    let report = report?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    let crashes: u64 = report.crashes.iter().map(|c| c.count).sum();
    let saved = fuzz::crash_dir();
    ensure!(
        crashes == 0,
        "{crashes} inputs of {target} panicked (the first of each kind saved under {})",
        saved.display()
    );
    let peak = report.peak_rss_mb.unwrap_or(0.0);
    ensure!(peak <= memory_mb, "fuzzing {target} peaked at {peak:.0} MB, over the {memory_mb:.0} MB budget");
    Ok(())
}

/// Command lines of every subcommand, for the `cli` fuzz target.
fn cli_fuzz_seeds() -> Vec<Vec<u8>> {
    [
        "demo --out demo-out --steps 100 --epochs 2 --backend flex",
        "train --data scene --out run --config c.toml --steps 40 --resume",
        "stylize --photo run --reference case --out style --config s.toml --epochs 2 --method arf --style s.png",
        "eval --run style --reference case --gt twin --robustness 2 --robustness-views near --out e.json",
        "register --photo run --reference case --out reg --overlays",
        "render --ckpt run --path orbit --out frames --frames 12",
        "bench --backends flex,ndarray --res 64 --rays 4096 --repeats 3 --json",
        "scene --out s --seed 3 --size 32",
        "fuzz npy --seconds 1.5 --cases 10",
        "reference --ckpt run --view train:3 --out case",
        "info --json",
    ]
    .iter()
    .map(|s| s.as_bytes().to_vec())
    .collect()
}

/// Parses mutated bytes as a command line (split at spaces): an error is
/// fine, a panic is not.
fn parse_cli_bytes(bytes: &[u8]) {
    let text = String::from_utf8_lossy(bytes);
    let args = std::iter::once("refnpr").chain(text.split(' ').filter(|a| !a.is_empty()));
    if let Ok(matches) = crate::Cli::command().try_get_matches_from(args) {
        drop(crate::Cli::from_arg_matches(&matches));
    }
}

// `refnpr info`'s arguments.
#[derive(clap::Args)]
pub struct InfoArgs {
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `refnpr info`: what this build runs on.
pub fn info(args: InfoArgs) -> Result<()> {
    let info = SystemInfo::gather();
    match args.json {
        true => println!("{}", serde_json::to_string_pretty(&info)?),
        false => println!("{info}"),
    }
    Ok(())
}
