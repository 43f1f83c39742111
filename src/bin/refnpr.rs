//! The `refnpr` command line: parse, call the library, print.

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use refnpr::config::TrainConfig;
use refnpr::data::{self, procedural};
use refnpr::render_path::{self, PathKind};
use refnpr::{BackendKind, checkpoint, train};
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "refnpr", version, about = "Reference-based non-photorealistic radiance fields (Ref-NPR) on Burn")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The demo: writes the procedural scene, fits it, renders an orbit (OUT/orbit/path.gif).
    Demo {
        #[arg(long, default_value = "demo-out")]
        out: PathBuf,
        #[arg(long)]
        backend: Option<BackendKind>,
        /// Override the number of training steps.
        #[arg(long)]
        steps: Option<usize>,
    },
    /// Renderer throughput (rays/s, forward and forward+backward) per backend and resolution.
    Bench {
        /// Backends to measure (default: all three).
        #[arg(long, value_delimiter = ',')]
        backends: Option<Vec<BackendKind>>,
        /// Grid resolutions.
        #[arg(long, value_delimiter = ',', default_value = "128,256")]
        res: Vec<usize>,
        #[arg(long, default_value_t = 4096)]
        rays: usize,
        #[arg(long, default_value_t = 5)]
        repeats: usize,
        /// Also write the results as JSON here.
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// Writes the built-in procedural scene (Blender layout, with depth, ids and a stylized twin).
    Scene {
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Square image size in pixels.
        #[arg(long, default_value_t = 96)]
        size: u32,
    },
    /// Fits a photorealistic radiance grid to a dataset.
    Train {
        #[arg(long)]
        data: PathBuf,
        #[arg(long)]
        out: PathBuf,
        /// TOML config; fields it leaves out take the defaults for the dataset kind.
        #[arg(long)]
        config: Option<PathBuf>,
        /// flex | ndarray | wgpu (default: $REFNPR_BACKEND, else flex).
        #[arg(long)]
        backend: Option<BackendKind>,
        /// Continue from OUT/checkpoint.bin if it exists.
        #[arg(long)]
        resume: bool,
        /// Override the number of steps.
        #[arg(long)]
        steps: Option<usize>,
    },
    /// Renders a camera path from a trained run.
    Render {
        /// Run folder (or checkpoint file).
        #[arg(long)]
        ckpt: PathBuf,
        /// test | train | spiral | orbit
        #[arg(long, default_value = "test")]
        path: PathKind,
        #[arg(long)]
        out: PathBuf,
        /// Frames of a spiral / orbit path.
        #[arg(long, default_value_t = 120)]
        frames: usize,
        /// Dataset folder (default: the one the run was trained on).
        #[arg(long)]
        data: Option<PathBuf>,
        #[arg(long)]
        backend: Option<BackendKind>,
    },
}

fn backend_or_env(b: Option<BackendKind>) -> Result<BackendKind> {
    match b {
        Some(b) => Ok(b),
        None => BackendKind::from_env(),
    }
}

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> Result<()> {
    match Cli::parse().command {
        Command::Demo { out, backend, steps } => {
            let backend = backend_or_env(backend)?;
            let m = refnpr::demo::run_demo(&out, backend, steps)?;
            println!(
                "demo done: test PSNR {:.2} dB, SSIM {:.4} in {:.1} s; see {}",
                m.test_psnr, m.test_ssim, m.train_seconds, out.join("orbit/path.gif").display()
            );
        }
        Command::Bench { backends, res, rays, repeats, json } => {
            let mut results = Vec::new();
            println!("{:<8} {:>5} {:>9} {:>12} {:>14} {:>18}", "backend", "res", "voxels", "samples/ray", "fwd rays/s", "fwd+bwd rays/s");
            for b in backends.unwrap_or(BackendKind::ALL.to_vec()) {
                for &r in &res {
                    let m = refnpr::bench::renderer_throughput(b, r, rays, repeats)?;
                    println!(
                        "{:<8} {:>5} {:>9} {:>12.1} {:>14.0} {:>18.0}",
                        m.backend, m.res, m.active_voxels, m.samples_per_ray, m.forward_rays_per_s, m.forward_backward_rays_per_s
                    );
                    results.push(m);
                }
            }
            if let Some(p) = json {
                std::fs::write(&p, serde_json::to_string_pretty(&results)?)
                    .with_context(|| format!("cannot write {}", p.display()))?;
            }
        }
        Command::Scene { out, seed, size } => {
            let opts = procedural::SceneOptions { seed, size, ..Default::default() };
            procedural::write_scene(&out, &opts)?;
            println!("wrote the procedural scene to {}", out.display());
        }
        Command::Train { data: dir, out, config, backend, resume, steps } => {
            let backend = backend_or_env(backend)?;
            let kind = data::detect_kind(&dir)?;
            let base = TrainConfig::for_kind(kind);
            let mut cfg = match &config {
                Some(p) => TrainConfig::from_file(p, &base)?,
                None => base,
            };
            if let Some(s) = steps {
                cfg.optim.steps = s;
                cfg.validate()?;
            }
            let dataset = data::load(&dir, &cfg.data)?;
            eprintln!(
                "{} scene {}: {} train / {} test views at {}x{}, backend {backend}",
                kind, dir.display(), dataset.train.len(), dataset.test.len(),
                dataset.train[0].camera.intrinsics.width, dataset.train[0].camera.intrinsics.height
            );
            let m = train::run_training(&dataset, cfg, &out, backend, resume)?;
            println!(
                "test PSNR {:.2} dB, SSIM {:.4}, {} steps in {:.1} s; wrote {}",
                m.test_psnr, m.test_ssim, m.steps, m.train_seconds, out.join("metrics.json").display()
            );
        }
        Command::Render { ckpt, path, out, frames, data: data_dir, backend } => {
            let backend = backend_or_env(backend)?;
            let ck = checkpoint::load(&ckpt, &backend.device())?;
            let dir = data_dir.unwrap_or_else(|| ck.meta.data_dir.clone());
            let dataset = data::load(&dir, &ck.meta.config.data)
                .with_context(|| format!("loading the run's dataset {} (pass --data to use another)", dir.display()))?;
            let cams = render_path::path_cameras(&dataset, path, frames)?;
            render_path::render_frames(&ck, &cams, &out, true)?;
            println!("rendered {} frames to {}", cams.len(), out.display());
        }
    }
    Ok(())
}

// mimalloc keeps freed pages mapped: the renderer allocates and frees
// tensors of tens of MB every step, which the system allocator returns to
// the OS and page-faults back in (measured: a third of the time in the kernel).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;
