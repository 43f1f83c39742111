//! Results out: `refnpr export` (splats, mesh, video, points, cameras) and
//! `refnpr view` (the browser viewer, live or as a static copy).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use refnpr::export::{self, ExportOptions, Format as ExportFormat};
use refnpr::field::checkpoint;
use refnpr::field::render_path::PathKind;
use refnpr::{BackendKind, Console};

use crate::common::{backend_or_env, run_folder};

// `refnpr export`'s arguments.
#[derive(clap::Args)]
pub struct ExportArgs {
    /// Run folder (or checkpoint file), photoreal or stylized.
    pub run: PathBuf,
    /// splat (3DGS PLY), mesh (glb or PLY), video (MP4), points (PLY), cameras (JSON).
    #[arg(long, value_enum)]
    pub format: ExportFormat,
    /// Output file (default: RUN/splats.ply, mesh.glb, path.mp4, points.ply or cameras.json).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Splats: the SH degree written (default: the field's).
    #[arg(long)]
    pub sh_degree: Option<u32>,
    /// Splats: keep at most this many, the most opaque first.
    #[arg(long)]
    pub max_splats: Option<usize>,
    /// Splats: keep the points buried inside opaque matter too.
    #[arg(long)]
    pub keep_buried: bool,
    /// Splats: their size relative to the Gaussian matched to a voxel's trilinear tent.
    #[arg(long, default_value_t = 1.0)]
    pub splat_scale: f32,
    /// Splats: thin each splat's opacity for a viewer that blurs splats by this many pixels squared
    /// without compensating (0.3 for 3DGS-style viewers), at the training views' resolution; 0: off.
    #[arg(long, default_value_t = 0.0)]
    pub viewer_blur: f32,
    /// Mesh: the density level of the surface (default: where four voxels absorb half the light).
    #[arg(long)]
    pub level: Option<f32>,
    /// Mesh: simplify to at most this many triangles (quadric edge collapse; the surface stays closed).
    #[arg(long)]
    pub max_triangles: Option<usize>,
    /// Video: the camera path.
    #[arg(long, value_enum, default_value_t = PathKind::Orbit)]
    pub path: PathKind,
    /// Video: frames of an orbit or spiral.
    #[arg(long, default_value_t = 120)]
    pub frames: usize,
    /// Video: frames per second.
    #[arg(long, default_value_t = 30)]
    pub fps: u32,
    /// Video: the frame width (default: the dataset's; the height keeps the aspect).
    #[arg(long)]
    pub width: Option<u32>,
    /// Video: the ffmpeg executable.
    #[arg(long, default_value = "ffmpeg")]
    pub ffmpeg: String,
    /// Points: every N-th pixel of the training views along both axes.
    #[arg(long, default_value_t = 2)]
    pub stride: usize,
    /// Dataset folder (default: the one the run was trained on); read for video, points, cameras and --viewer-blur.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
    #[arg(long, value_enum, env = "REFNPR_BACKEND")]
    pub backend: Option<BackendKind>,
}

/// `refnpr export`.
pub fn export(args: ExportArgs, progress: &Console) -> Result<()> {
    let ExportArgs {
        run,
        format,
        out,
        sh_degree,
        max_splats,
        keep_buried,
        splat_scale,
        viewer_blur,
        level,
        max_triangles,
        path,
        frames,
        fps,
        width,
        ffmpeg,
        stride,
        data,
        backend,
    } = args;
    let device = backend_or_env(backend, progress)?.device();
    let ck = checkpoint::load_with(&checkpoint::resolve(&run), &device, false)?;
    let out = out.unwrap_or_else(|| run_folder(&run).join(format.default_file()));
    let splat = export::splat::SplatOptions {
        sh_degree,
        max_splats,
        drop_buried: !keep_buried,
        scale: splat_scale,
        viewer_blur,
        ..Default::default()
    };
    let options = ExportOptions { splat, level, max_triangles, path, frames, fps, width, ffmpeg, stride };
    let dataset = if export::needs_dataset(format, &options) {
        Some(checkpoint::load_dataset(&ck, data.as_deref())?)
    } else {
        None
    };
    let r = export::export(&ck, dataset.as_ref(), format, &out, &options, progress)?;
    println!("wrote {} ({}; {:.1} MB in {:.1} s)", r.file.display(), r.summary, r.bytes as f64 / 1e6, r.seconds);
    Ok(())
}

// `refnpr view`'s arguments.
#[derive(clap::Args)]
pub struct ViewArgs {
    /// Run folders (or checkpoint files), photoreal or stylized: the page shows one and compares two.
    #[arg(required = true)]
    pub runs: Vec<PathBuf>,
    /// The port (0: any free one).
    #[arg(long, default_value_t = 8008)]
    pub port: u16,
    /// The address to listen on. Anything but 127.0.0.1 lets other machines see the runs.
    #[arg(long, default_value = "127.0.0.1")]
    pub host: String,
    /// Write a self-contained folder (the page and the runs' data) for any static web host, and stop.
    #[arg(long = "static", value_name = "DIR")]
    pub static_dir: Option<PathBuf>,
    /// Dataset folder for the cameras list (default: the one each run was trained on).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
    #[arg(long, value_enum, env = "REFNPR_BACKEND")]
    pub backend: Option<BackendKind>,
}

/// `refnpr view`.
pub fn view(args: ViewArgs, progress: &Console) -> Result<()> {
    let ViewArgs { runs, port, host, static_dir, data, backend } = args;
    run_view(&runs, port, &host, static_dir.as_deref(), data.as_deref(), backend, progress)
}

/// `refnpr view`.
fn run_view(
    paths: &[PathBuf],
    port: u16,
    host: &str,
    static_dir: Option<&Path>,
    data: Option<&Path>,
    backend: Option<BackendKind>,
    progress: &Console,
) -> Result<()> {
    let device = backend_or_env(backend, progress)?.device();
    let mut runs = Vec::new();
    for path in paths {
        let run = refnpr::view::ViewRun::new(path, data);
        if !run.checkpoint.is_file() {
            if static_dir.is_some() || !path.is_dir() {
                bail!("{}: no checkpoint here (expected {})", path.display(), run.checkpoint.display());
            }
            println!("waiting for {} (a run in progress: the page shows it when it appears)", run.checkpoint.display());
        }
        runs.push(run);
    }
    if let Some(dir) = static_dir {
        let bytes = refnpr::view::write_static(&runs, dir, &device)?;
        println!(
            "wrote {} ({:.1} MB): serve it with any static web server, e.g. `python3 -m http.server -d {}`",
            dir.display(),
            bytes as f64 / 1e6,
            dir.display()
        );
        return Ok(());
    }
    let listener = std::net::TcpListener::bind((host, port)).with_context(|| {
        format!("cannot listen on {host}:{port} (in use? pick another with --port, or --port 0 for any)")
    })?;
    let address = listener.local_addr()?;
    if !address.ip().is_loopback() {
        eprintln!("WARNING: listening on {address}: every machine that can reach it can see these runs (read-only)");
    }
    println!("serving {} run(s) at http://{address}/ (Ctrl-C stops)", runs.len());
    refnpr::view::server::serve(listener, refnpr::view::server::Site::new(runs, device, true));
    Ok(())
}
