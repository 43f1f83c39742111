//! The `refnpr` command line: parse the arguments, call the library, print
//! the result. One small function per subcommand.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail, ensure};
use clap::parser::ValueSource;
use clap::{ArgMatches, CommandFactory, FromArgMatches, Parser, Subcommand};
use refnpr::eval::lpips::LpipsNet;
use refnpr::eval::stylization::{EvalJob, RobustnessViews};
use refnpr::export::{self, ExportOptions, Format as ExportFormat};
use refnpr::field::checkpoint::{self, Checkpoint};
use refnpr::field::render_path::{self, PathKind};
use refnpr::photo::config::TrainConfig;
use refnpr::photo::evaluate::evaluate;
use refnpr::photo::pose_refine;
use refnpr::photo::run::{run_training, run_training_with_refined_poses};
use refnpr::reference::case::{ReferenceCase, ViewSpec};
use refnpr::reference::r3::RegisterParams;
use refnpr::reference::registration;
use refnpr::scene::data::{self, Dataset, procedural};
use refnpr::stylize::config::{Preset, StylizeConfig};
use refnpr::stylize::run::run_stylize;
use refnpr::stylize::{Method, StylizeJob};
use refnpr::tools::info::SystemInfo;
use refnpr::tools::{bench, capture, demo, fuzz, paint};
use refnpr::util::costs::Ledger;
use refnpr::util::{config, files, image, profile};
use refnpr::{BackendKind, Console, Progress};

/// The pipeline in five lines, and the commands `--help` does not list.
const WORKFLOW: &str = "\
The workflow (`refnpr demo` runs it on the built-in scene):
  1. refnpr train --data SCENE --out RUN          (photos first? refnpr capture PHOTOS --out SCENE)
  2. refnpr reference --run RUN --view train:0 --out CASE    then paint CASE/content.png, save CASE/style.png
  3. refnpr stylize --run RUN --reference CASE --out STYLE
  4. refnpr render --run STYLE --path orbit --out FRAMES     (or export STYLE, view STYLE)
  5. refnpr eval --run STYLE --reference CASE

Developer commands: bench, bench-vgg, bench-stylize (speed), fuzz (parsers), info (what the build runs on)";

#[derive(Parser)]
#[command(
    name = "refnpr",
    version,
    about = "Paint one view of a 3D scene; refnpr stylizes every other view to match (Ref-NPR, on Burn)",
    after_help = WORKFLOW
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Also print per-phase figures (host-device transfers).
    #[arg(long, global = true)]
    verbose: bool,
}

/// The inputs of the R³ and stylization commands.
#[derive(clap::Args)]
struct PhotoAndCase {
    /// Photoreal run folder (or its checkpoint file), as `refnpr train --out` wrote it.
    #[arg(long = "run", alias = "photo", value_name = "RUN")]
    photo: PathBuf,
    /// Reference case folder (reference.toml or the authors' data_config.json).
    #[arg(long)]
    reference: PathBuf,
    /// Dataset folder (default: the one the photoreal run was trained on).
    #[arg(long)]
    data: Option<PathBuf>,
}

#[derive(Subcommand)]
enum Command {
    /// Writes the built-in procedural scene (Blender layout, with depth, ids and a stylized twin).
    Scene {
        /// The folder to write (train it with `refnpr train --data OUT`).
        #[arg(long)]
        out: PathBuf,
        /// Seed of the scene's random layout and textures.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Square image size in pixels.
        #[arg(long, default_value_t = 96)]
        size: u32,
        /// Surround the scene with a textured far environment (a 360° capture of an object in a room)
        /// instead of an empty background; fit it with a far background: `refnpr train --config
        /// configs/far_background.toml` (`[grid] far_background = "on"`).
        #[arg(long)]
        environment: bool,
    },
    /// A dataset from a folder of photos, through COLMAP (installed separately:
    /// `apt-get install colmap`): photos downsized, features, matching, mapping,
    /// undistortion; writes OUT/images/ and OUT/sparse/ for `train --data OUT`.
    Capture {
        /// The folder of photos (PNG or JPEG, 20-100 of one scene).
        photos: PathBuf,
        /// The dataset folder to write (COLMAP's log: OUT/colmap.log).
        #[arg(long)]
        out: PathBuf,
        /// Photos are downsized to this long side first (pixels).
        #[arg(long, default_value_t = 800)]
        max_side: u32,
        /// COLMAP's camera model (SIMPLE_RADIAL, RADIAL, OPENCV, PINHOLE, ...).
        #[arg(long, default_value = "SIMPLE_RADIAL")]
        camera_model: String,
        /// The photos come from several cameras or zoom settings (one camera each).
        #[arg(long)]
        several_cameras: bool,
        /// The COLMAP executable.
        #[arg(long, default_value = "colmap")]
        colmap: PathBuf,
        /// A dataset of the same photos with known poses: print the recovered
        /// poses' error against it (views matched by file name).
        #[arg(long)]
        truth: Option<PathBuf>,
    },
    /// Fits the photoreal radiance field of a dataset (Blender, LLFF, NSVF, COLMAP, transforms.json; detected).
    Train {
        /// The dataset folder.
        #[arg(long)]
        data: PathBuf,
        /// The run folder to write: checkpoint.bin, metrics.json, test/ renders.
        #[arg(long)]
        out: PathBuf,
        /// TOML config; fields it leaves out take the defaults for the dataset kind.
        #[arg(long)]
        config: Option<PathBuf>,
        /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
        #[arg(long, value_enum, env = "REFNPR_BACKEND")]
        backend: Option<BackendKind>,
        /// Continue from OUT/checkpoint.bin if it exists (with --steps: extend the run to that many steps).
        #[arg(long)]
        resume: bool,
        /// The number of steps ([optim] steps).
        #[arg(long)]
        steps: Option<usize>,
        /// A COLMAP capture around the scene: fit it (OUT/first_fit), align its cameras to that field
        /// (`refine-poses`), write OUT/scene_refined and fit that in OUT (twice the time; sharper poses).
        #[arg(long, conflicts_with = "resume")]
        refine_poses: bool,
    },
    /// Aligns each camera of a COLMAP capture around the scene to its photo with a field trained on it
    /// (its pose, and one focal length shared by all), and writes the dataset with the refined cameras:
    /// train again on OUT. COLMAP's poses of small or texture-poor photos are a fraction of a pixel off.
    RefinePoses {
        /// The photoreal run trained on the capture.
        #[arg(long)]
        run: PathBuf,
        /// The dataset folder to write (images/, sparse/0/ in COLMAP's text form, test.txt).
        #[arg(long)]
        out: PathBuf,
        /// The capture (default: the run's dataset).
        #[arg(long)]
        data: Option<PathBuf>,
        /// Gauss-Newton iterations (each renders every view once).
        #[arg(long, default_value_t = 6)]
        iterations: usize,
        /// Keep the focal length (refine the poses only).
        #[arg(long)]
        keep_focal: bool,
    },
    /// Renders a run (photoreal or stylized) along a camera path: OUT/rgb/, OUT/depth/, OUT/path.gif.
    Render {
        /// Run folder (or its checkpoint file), photoreal or stylized.
        #[arg(long = "run", alias = "ckpt", value_name = "RUN")]
        ckpt: PathBuf,
        /// The cameras: the dataset's test or train views, a spiral (forward-facing scenes) or an orbit.
        #[arg(long, value_enum, default_value_t = PathKind::Test)]
        path: PathKind,
        /// The folder to write the frames to.
        #[arg(long)]
        out: PathBuf,
        /// Frames of a spiral / orbit path.
        #[arg(long, default_value_t = 120)]
        frames: usize,
        /// Dataset folder (default: the one the run was trained on).
        #[arg(long)]
        data: Option<PathBuf>,
        /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
        #[arg(long, value_enum, env = "REFNPR_BACKEND")]
        backend: Option<BackendKind>,
    },
    /// A contact sheet of a run's views (training and test photos, frames of the render path), each labelled
    /// with the name `reference --view` takes: choose the view to paint by looking.
    Views {
        /// Run folder (or its checkpoint file).
        #[arg(long = "run", alias = "ckpt", value_name = "RUN")]
        run: PathBuf,
        /// The PNG to write (default: RUN/views.png).
        #[arg(long)]
        out: Option<PathBuf>,
        /// The long side of each thumbnail, in pixels.
        #[arg(long, default_value_t = 128)]
        thumb: usize,
        /// Thumbnails per row.
        #[arg(long, default_value_t = 8)]
        columns: usize,
        /// Show every N-th of the render path's 120 frames (0: none; they are rendered from the field).
        #[arg(long, default_value_t = 4)]
        path_every: usize,
        /// Dataset folder (default: the one the run was trained on).
        #[arg(long)]
        data: Option<PathBuf>,
        /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
        #[arg(long, value_enum, env = "REFNPR_BACKEND")]
        backend: Option<BackendKind>,
    },
    /// Renders the content view I_R and its depth from a photoreal run and writes a
    /// reference-case skeleton: paint over OUT/content.png and save OUT/style.png.
    Reference {
        /// Photoreal run folder (or its checkpoint file).
        #[arg(long = "run", alias = "ckpt", value_name = "RUN")]
        ckpt: PathBuf,
        /// train:N | test:N | path:N (path = the standard render path, 120 poses; `refnpr views` shows them all),
        /// or a training or test image's file name (r_12.png, IMG_0042).
        #[arg(long)]
        view: String,
        /// The reference case folder to write (content.png, depth, reference.toml).
        #[arg(long)]
        out: PathBuf,
        /// Dataset folder (default: the one the run was trained on).
        #[arg(long)]
        data: Option<PathBuf>,
    },
    /// A quick painterly repaint of an image (e.g. a reference case's content.png) to try stylization without painting.
    Paint {
        /// The image to repaint (a case's content.png).
        #[arg(long)]
        input: PathBuf,
        /// The painted image to write (a case's style.png).
        #[arg(long)]
        out: PathBuf,
        /// Seed of the brush strokes.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// A colour grade instead of the painterly repaint (a recolouring reference).
        #[arg(long, value_enum)]
        grade: Option<paint::Grade>,
    },
    /// Copies a dataset folder with every image colour-graded: the intended result of a
    /// reference graded the same way (`paint --grade`), for `eval --gt`.
    Recolour {
        /// The dataset folder (Blender or procedural layout).
        #[arg(long)]
        data: PathBuf,
        /// The new folder.
        #[arg(long)]
        out: PathBuf,
        /// The colour grade, as `paint --grade` applies it.
        #[arg(long, value_enum)]
        grade: paint::Grade,
    },
    /// R³: registers the stylized reference colours onto every training ray.
    Register {
        #[command(flatten)]
        inputs: PhotoAndCase,
        /// The folder to write: registration.bin, register.json, overlays/.
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        params: RegisterParams,
        /// Overlay PNGs for the first N training views.
        #[arg(long, default_value_t = 8)]
        overlays: usize,
    },
    /// Stylizes a photoreal run after a reference case (Ref-NPR), or after a style image (ARF).
    Stylize {
        /// Photoreal run folder (or its checkpoint file), as `refnpr train --out` wrote it.
        #[arg(long = "run", alias = "photo", value_name = "RUN")]
        photo: PathBuf,
        /// Reference case folder (reference.toml or the authors' data_config.json); ARF can take --style alone.
        #[arg(long, required_unless_present = "style")]
        reference: Option<PathBuf>,
        /// Dataset folder (default: the one the photoreal run was trained on).
        #[arg(long)]
        data: Option<PathBuf>,
        /// Output run folder: checkpoint.bin (renders like any run), stylize.json, test/ renders.
        #[arg(long)]
        out: PathBuf,
        /// TOML config; fields it leaves out take the defaults of configs/stylize.toml.
        #[arg(long, conflicts_with = "preset")]
        config: Option<PathBuf>,
        /// A named config instead of --config: paper (the defaults, 10 image epochs), fast (6), authors (their code's).
        #[arg(long, value_enum)]
        preset: Option<Preset>,
        /// refnpr (Ref-NPR, the paper's method) or arf (the ARF baseline: style statistics, no reference view).
        #[arg(long, value_enum, default_value_t = Method::RefNpr)]
        method: Method,
        /// ARF: a style image (any size) instead of the case's first reference; without --reference it
        /// becomes a case of its own in OUT/style_case.
        #[arg(long)]
        style: Option<PathBuf>,
        /// Stylization epochs ([schedule] image_epochs; the last quarter is the smooth update).
        #[arg(long = "image-epochs", alias = "epochs")]
        epochs: Option<usize>,
        /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
        #[arg(long, value_enum, env = "REFNPR_BACKEND")]
        backend: Option<BackendKind>,
        /// Skip rendering the test views of the result.
        #[arg(long)]
        no_render: bool,
        /// Continue a killed run from OUT/resume.bin (written after the refit and every
        /// schedule.checkpoint_every image steps); the same command otherwise.
        #[arg(long)]
        resume: bool,
        /// A `refnpr register` output folder (or its registration.bin) to use instead of registering again.
        #[arg(long)]
        registration: Option<PathBuf>,
        /// R³ settings; a flag given here overrides the config file's [register].
        #[command(flatten)]
        register: RegisterParams,
    },
    /// Stylization metrics of a stylized run (with --reference), or PSNR / SSIM of a run's test views.
    Eval {
        /// Run folder (or its checkpoint file): a photoreal or a stylized run.
        #[arg(long, alias = "ckpt")]
        run: PathBuf,
        /// The stylized run's reference case: stylization metrics (ref_lpips,
        /// stability, and with --gt the ground-truth PSNRs). Without it: PSNR
        /// and SSIM of the run's test views.
        #[arg(long)]
        reference: Option<PathBuf>,
        /// Dataset whose test views are the ground truth (a procedural scene's `stylized/`).
        #[arg(long)]
        gt: Option<PathBuf>,
        /// Restylize from N of the run's own renders and report their PSNR (slow: N stylizations).
        #[arg(long, default_value_t = 0)]
        robustness: usize,
        /// Image epochs of each robustness stylization (default: the run's).
        #[arg(long)]
        robustness_epochs: Option<usize>,
        /// Which path frames --robustness restylizes from: the nearest to the reference camera, or spread along the path.
        #[arg(long, value_enum, default_value_t = RobustnessViews::Near)]
        robustness_views: RobustnessViews,
        /// Keep the restylizations a killed `eval --robustness` finished, and continue the one
        /// it was running from its resume.bin.
        #[arg(long)]
        resume: bool,
        /// Also write the JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
        /// The run's dataset folder, when it moved.
        #[arg(long)]
        data: Option<PathBuf>,
        /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
        #[arg(long, value_enum, env = "REFNPR_BACKEND")]
        backend: Option<BackendKind>,
    },
    /// LPIPS (v0.1, as the `lpips` package computes it) between two images: B is resized to A's size when they differ.
    Lpips {
        /// The first image (PNG or JPEG; alpha composited over --background).
        a: PathBuf,
        /// The second image.
        b: PathBuf,
        /// The feature network: vgg (the paper's Ref-LPIPS) or alex (the `lpips` package's default).
        #[arg(long, value_enum, default_value_t = LpipsNet::Vgg)]
        net: LpipsNet,
        /// The colour transparent pixels are composited over, as R,G,B in [0, 1].
        #[arg(long, value_delimiter = ',', num_args = 3, default_values_t = [1.0, 1.0, 1.0])]
        background: Vec<f32>,
        /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
        #[arg(long, value_enum, env = "REFNPR_BACKEND")]
        backend: Option<BackendKind>,
    },
    /// Exports a run's field for other tools: Gaussian splats (3DGS PLY), a coloured mesh (glb or PLY), an MP4, surface points.
    Export {
        /// Run folder (or checkpoint file), photoreal or stylized.
        run: PathBuf,
        /// splat (3DGS PLY), mesh (glb or PLY), video (MP4), points (PLY), cameras (JSON).
        #[arg(long, value_enum)]
        format: ExportFormat,
        /// Output file (default: RUN/splats.ply, mesh.glb, path.mp4, points.ply or cameras.json).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Splats: the SH degree written (default: the field's).
        #[arg(long)]
        sh_degree: Option<u32>,
        /// Splats: keep at most this many, the most opaque first.
        #[arg(long)]
        max_splats: Option<usize>,
        /// Splats: keep the points buried inside opaque matter too.
        #[arg(long)]
        keep_buried: bool,
        /// Splats: their size relative to the Gaussian matched to a voxel's trilinear tent.
        #[arg(long, default_value_t = 1.0)]
        splat_scale: f32,
        /// Splats: thin each splat's opacity for a viewer that blurs splats by this many pixels squared
        /// without compensating (0.3 for 3DGS-style viewers), at the training views' resolution; 0: off.
        #[arg(long, default_value_t = 0.0)]
        viewer_blur: f32,
        /// Mesh: the density level of the surface (default: where four voxels absorb half the light).
        #[arg(long)]
        level: Option<f32>,
        /// Mesh: simplify to at most this many triangles (quadric edge collapse; the surface stays closed).
        #[arg(long)]
        max_triangles: Option<usize>,
        /// Video: the camera path.
        #[arg(long, value_enum, default_value_t = PathKind::Orbit)]
        path: PathKind,
        /// Video: frames of an orbit or spiral.
        #[arg(long, default_value_t = 120)]
        frames: usize,
        /// Video: frames per second.
        #[arg(long, default_value_t = 30)]
        fps: u32,
        /// Video: the frame width (default: the dataset's; the height keeps the aspect).
        #[arg(long)]
        width: Option<u32>,
        /// Video: the ffmpeg executable.
        #[arg(long, default_value = "ffmpeg")]
        ffmpeg: String,
        /// Points: every N-th pixel of the training views along both axes.
        #[arg(long, default_value_t = 2)]
        stride: usize,
        /// Dataset folder (default: the one the run was trained on); read for video, points, cameras and --viewer-blur.
        #[arg(long)]
        data: Option<PathBuf>,
        /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
        #[arg(long, value_enum, env = "REFNPR_BACKEND")]
        backend: Option<BackendKind>,
    },
    /// Shows runs in the browser: a local page that ray-marches the field in WebGL2 as refnpr renders it,
    /// reloading a run whose checkpoint changes (a fit or a stylization in progress).
    View {
        /// Run folders (or checkpoint files), photoreal or stylized: the page shows one and compares two.
        #[arg(required = true)]
        runs: Vec<PathBuf>,
        /// The port (0: any free one).
        #[arg(long, default_value_t = 8008)]
        port: u16,
        /// The address to listen on. Anything but 127.0.0.1 lets other machines see the runs.
        #[arg(long, default_value = "127.0.0.1")]
        host: String,
        /// Write a self-contained folder (the page and the runs' data) for any static web host, and stop.
        #[arg(long = "static", value_name = "DIR")]
        static_dir: Option<PathBuf>,
        /// Dataset folder for the cameras list (default: the one each run was trained on).
        #[arg(long)]
        data: Option<PathBuf>,
        /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
        #[arg(long, value_enum, env = "REFNPR_BACKEND")]
        backend: Option<BackendKind>,
    },
    /// The whole method on the built-in scene: writes it, fits the photoreal field, paints view 0 from the
    /// scene's stylized twin, stylizes, renders orbits of both fields and scores the result against the twin.
    Demo {
        /// The folder to write: scene/, photo/, case/, stylized/, orbit/, eval.json.
        #[arg(long, default_value = "demo-out")]
        out: PathBuf,
        /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
        #[arg(long, value_enum, env = "REFNPR_BACKEND")]
        backend: Option<BackendKind>,
        /// Override the number of photoreal training steps.
        #[arg(long)]
        steps: Option<usize>,
        /// Override the number of stylization image epochs.
        #[arg(long = "image-epochs", alias = "epochs")]
        epochs: Option<usize>,
    },
    /// Renderer throughput (rays/s, forward and forward+backward) per backend and resolution.
    #[command(hide = true)]
    Bench {
        /// Backends to measure (default: all three).
        #[arg(long, value_enum, value_delimiter = ',')]
        backends: Option<Vec<BackendKind>>,
        /// Grid resolutions.
        #[arg(long, value_delimiter = ',', default_value = "128,256")]
        res: Vec<usize>,
        /// Rays per measured batch.
        #[arg(long, default_value_t = 4096)]
        rays: usize,
        /// Measured repetitions (the median is reported).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
        /// Also write the results as JSON here.
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// VGG16 forward and forward+backward milliseconds per backend and image size, with
    /// onnxruntime's CPU forward on the same input as a yardstick.
    #[command(hide = true)]
    BenchVgg {
        /// Backends to measure (default: all three).
        #[arg(long, value_enum, value_delimiter = ',')]
        backends: Option<Vec<BackendKind>>,
        /// Image sizes, WIDTHxHEIGHT.
        #[arg(long, value_delimiter = ',', default_value = "256x256,504x378")]
        sizes: Vec<String>,
        /// Unmeasured passes first (kernel compilation, allocator warm-up).
        #[arg(long, default_value_t = 1)]
        warmup: usize,
        /// Measured repetitions (the median is reported).
        #[arg(long, default_value_t = 3)]
        repeats: usize,
        /// Skip the onnxruntime yardstick (needs python3 with onnxruntime).
        #[arg(long)]
        no_onnxruntime: bool,
        /// How the forward pass runs (default: staged).
        #[arg(long, value_enum)]
        forward: Option<refnpr::vgg::VggForward>,
        /// Also write the results as JSON here.
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// A short stylization (a fraction of a refit epoch, one image epoch and, for Ref-NPR,
    /// one smooth epoch) timed step by step: seconds per step and where they go, per phase.
    #[command(hide = true)]
    BenchStylize {
        #[command(flatten)]
        inputs: PhotoAndCase,
        /// Output run folder of the short stylization (stylize.json has every step's time).
        #[arg(long)]
        out: PathBuf,
        /// TOML config, as for `stylize` (its schedule is shortened).
        #[arg(long)]
        config: Option<PathBuf>,
        /// refnpr or arf.
        #[arg(long, value_enum, default_value_t = Method::RefNpr)]
        method: Method,
        /// Ray epochs of the refit (a fraction of one: its steps all cost the same).
        #[arg(long, default_value_t = 0.1)]
        refit_epochs: f32,
        /// Image epochs; with Ref-NPR and 2 or more, the last is the smooth update.
        #[arg(long, default_value_t = 2)]
        image_epochs: usize,
        /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
        #[arg(long, value_enum, env = "REFNPR_BACKEND")]
        backend: Option<BackendKind>,
        /// On a GPU, wait for the device at the end of each part of a step, so that each
        /// part's time is its own work (the config's `sync_parts`; compare whole steps without it).
        #[arg(long)]
        sync_parts: bool,
        /// Also write the results as JSON here.
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// Feeds a parser of outside input (or the command line itself) mutated real files
    /// for a while: no input may panic or hang.
    #[command(hide = true)]
    Fuzz {
        /// The parser to fuzz.
        #[arg(value_parser = clap::builder::PossibleValuesParser::new(fuzz_targets()))]
        target: String,
        /// Stop after this many seconds...
        #[arg(long, default_value_t = 60.0)]
        seconds: f64,
        /// ... or this many inputs.
        #[arg(long, default_value_t = u64::MAX)]
        cases: u64,
        /// A case running longer than this is a hang (its input is saved, the run stops).
        #[arg(long, default_value_t = 5.0)]
        case_seconds: f64,
        /// Seed of the mutations.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// The process's peak memory may not exceed this (a header claiming a huge size
        /// must be refused before allocating).
        #[arg(long, default_value_t = 256.0)]
        memory_mb: f64,
        /// Real scenes to add to the seed inputs, when the folder exists.
        #[arg(long, default_value = "../shared/data", hide = true)]
        shared_data: PathBuf,
    },
    /// What this build runs on: backends, wgpu adapters, CPU threads and SIMD, memory, VGG16 weights.
    #[command(hide = true)]
    Info {
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
}

/// The fuzz targets: every parser of outside input, and the command line.
fn fuzz_targets() -> Vec<&'static str> {
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
    if let Ok(matches) = Cli::command().try_get_matches_from(args) {
        drop(Cli::from_arg_matches(&matches));
    }
}

fn main() {
    keep_freed_memory();
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> Result<()> {
    let matches = Cli::command().get_matches();
    let cli = Cli::from_arg_matches(&matches)?;
    let progress = Console::verbose(cli.verbose).with_costs(Ledger::default_location());
    match cli.command {
        Command::Demo { out, backend, steps, epochs } => {
            run_demo(&out, backend_or_env(backend, &progress)?, steps, epochs, &progress)
        }
        Command::Bench { backends, res, rays, repeats, json } => run_bench(backends, &res, rays, repeats, json),
        Command::BenchVgg { backends, sizes, warmup, repeats, no_onnxruntime, forward, json } => {
            run_bench_vgg(backends, &sizes, warmup, repeats, no_onnxruntime, forward, json)
        }
        Command::BenchStylize { .. } => run_bench_stylize_command(cli.command, &progress),
        Command::Reference { ckpt, view, out, data } => run_reference(&ckpt, &view, &out, data),
        Command::Register { inputs, out, params, overlays } => run_register(inputs, &out, &params, overlays, &progress),
        Command::Stylize { .. } => {
            let stylize = matches.subcommand_matches("stylize").expect("the stylize subcommand was parsed");
            run_stylize_command(cli.command, stylize, &progress)
        }
        Command::Eval { .. } => run_eval(cli.command, &progress),
        Command::Paint { input, out, seed, grade } => run_paint(&input, &out, seed, grade),
        Command::Recolour { data, out, grade } => {
            let n = paint::recolour_dataset(&data, &out, grade)?;
            println!("wrote {} with {n} images graded ({grade:?})", out.display());
            Ok(())
        }
        Command::Info { json } => run_info(json),
        Command::Lpips { a, b, net, background, backend } => run_lpips(&a, &b, net, &background, backend, &progress),
        Command::Fuzz { target, seconds, cases, case_seconds, seed, memory_mb, shared_data } => {
            let limits = fuzz::Limits { max_cases: cases, max_seconds: seconds, case_seconds, seed };
            run_fuzz(&target, &limits, memory_mb, &shared_data)
        }
        Command::Capture { photos, out, max_side, camera_model, several_cameras, colmap, truth } => {
            let opts = capture::CaptureOptions { max_side, camera_model, single_camera: !several_cameras, colmap };
            let r = capture::capture(&photos, &out, &opts, &progress)?;
            println!(
                "registered {} of {} photos ({} points, {}x{}) in {:.0} s; wrote {} (train it: refnpr train --data {} --out RUN)",
                r.registered,
                r.photos,
                r.points,
                r.size.0,
                r.size.1,
                r.seconds,
                out.display(),
                out.display()
            );
            if let Some(truth) = truth {
                let e = capture::compare_poses(&out, &truth)?;
                println!("{}", serde_json::to_string(&e)?);
            }
            Ok(())
        }
        Command::RefinePoses { run, out, data, iterations, keep_focal } => {
            let settings = pose_refine::RefineSettings { iterations, focal: !keep_focal };
            run_refine_poses(&run, &out, data.as_deref(), &settings, &progress)
        }
        Command::Scene { out, seed, size, environment } => {
            procedural::write_scene(&out, &procedural::SceneOptions { seed, size, environment, ..Default::default() })?;
            println!("wrote the procedural scene to {}", out.display());
            Ok(())
        }
        Command::Train { data, out, config, backend, resume, steps, refine_poses } => {
            let backend = backend_or_env(backend, &progress)?;
            let how = TrainHow { resume, steps, refine_poses };
            run_train(&data, &out, config.as_deref(), backend, how, &progress)
        }
        Command::Export { .. } => run_export(cli.command, &progress),
        Command::View { runs, port, host, static_dir, data, backend } => {
            run_view(&runs, port, &host, static_dir.as_deref(), data.as_deref(), backend, &progress)
        }
        Command::Views { run, out, thumb, columns, path_every, data, backend } => {
            let opts = refnpr::tools::views::SheetOptions { thumb, columns, path_every };
            run_views(&run, out, &opts, data.as_deref(), backend, &progress)
        }
        Command::Render { ckpt, path, out, frames, data, backend } => {
            run_render(&ckpt, path, &out, frames, data.as_deref(), backend, &progress)
        }
    }
}

/// `refnpr bench-stylize`.
fn run_bench_stylize_command(command: Command, progress: &Console) -> Result<()> {
    let Command::BenchStylize { inputs, out, config, method, refit_epochs, image_epochs, backend, sync_parts, json } =
        command
    else {
        unreachable!("called for bench-stylize")
    };
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

/// `refnpr lpips A B`: the distance on stdout alone (for scripts), a resize on stderr.
fn run_lpips(
    a: &Path,
    b: &Path,
    net: LpipsNet,
    background: &[f32],
    backend: Option<BackendKind>,
    progress: &Console,
) -> Result<()> {
    let device = backend_or_env(backend, progress)?.open(progress)?;
    let background = [background[0], background[1], background[2]];
    let (distance, note) = refnpr::eval::lpips::file_distance(a, b, net, background, &device)?;
    if let Some(note) = note {
        eprintln!("{note}");
    }
    println!("{distance:.6}");
    Ok(())
}

/// `refnpr eval`: the stylization metrics (with `--reference`), or a photoreal run's test PSNR.
fn run_eval(command: Command, progress: &Console) -> Result<()> {
    let Command::Eval {
        run,
        reference,
        gt,
        robustness,
        robustness_epochs,
        robustness_views,
        resume,
        out,
        data,
        backend,
    } = command
    else {
        unreachable!("called for eval")
    };
    let backend = backend_or_env(backend, progress)?;
    let json = match reference {
        Some(case) => {
            let job = EvalJob { run, case, gt, robustness, robustness_views, backend, data, robustness_epochs, resume };
            serde_json::to_value(refnpr::tools::robustness::evaluate(&job, progress)?)?
        }
        None => {
            ensure!(robustness == 0, "--robustness needs --reference (the stylized run's case)");
            photoreal_eval(&run, gt.or(data), backend)?
        }
    };
    if let Some(path) = out {
        files::write_json(&path, &json)?;
    }
    println!("{}", serde_json::to_string_pretty(&json)?);
    Ok(())
}

/// `refnpr paint`: the painterly repaint filter on an image.
fn run_paint(input: &Path, out: &Path, seed: u64, grade: Option<paint::Grade>) -> Result<()> {
    let img = ::image::open(input).with_context(|| format!("cannot read image {}", input.display()))?.to_rgba32f();
    let (w, h) = (img.width(), img.height());
    let rgb = data::composite_over(&img, [1.0; 3]);
    let painted = match grade {
        Some(g) => g.image(&rgb),
        None => paint::painterly(&rgb, w as usize, h as usize, seed),
    };
    image::save_png(out, w, h, &painted)?;
    println!("wrote {}", out.display());
    Ok(())
}

/// `refnpr info`: what this build runs on.
fn run_info(json: bool) -> Result<()> {
    let info = SystemInfo::gather();
    match json {
        true => println!("{}", serde_json::to_string_pretty(&info)?),
        false => println!("{info}"),
    }
    Ok(())
}

/// `refnpr render`: the frames of a camera path from a checkpoint.
fn run_render(
    ckpt: &Path,
    path: PathKind,
    out: &Path,
    frames: usize,
    data: Option<&Path>,
    backend: Option<BackendKind>,
    progress: &Console,
) -> Result<()> {
    let device = backend_or_env(backend, progress)?.device();
    let (ck, dataset) = checkpoint::load_run(ckpt, data, &device)?;
    let cams = render_path::path_cameras(&dataset, path, frames)?;
    render_path::render_frames(&ck, &cams, out, progress)?;
    println!("rendered {} frames to {}", cams.len(), out.display());
    Ok(())
}

/// `refnpr views`: the contact sheet.
fn run_views(
    run: &Path,
    out: Option<PathBuf>,
    opts: &refnpr::tools::views::SheetOptions,
    data: Option<&Path>,
    backend: Option<BackendKind>,
    progress: &Console,
) -> Result<()> {
    let device = backend_or_env(backend, progress)?.device();
    let (ck, dataset) = checkpoint::load_run(run, data, &device)?;
    let sheet = refnpr::tools::views::contact_sheet(&ck, &dataset, opts, progress)?;
    let out = out.unwrap_or_else(|| run_folder(run).join("views.png"));
    sheet.save_png(&out)?;
    println!(
        "wrote {} ({} train, {} test views{}): pick one, then `refnpr reference --run {} --view NAME --out CASE`",
        out.display(),
        dataset.train.len(),
        dataset.test.len(),
        if opts.path_every > 0 { ", every path frame's label is its path:N" } else { "" },
        run.display()
    );
    Ok(())
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

/// `refnpr export`.
fn run_export(command: Command, progress: &Console) -> Result<()> {
    let Command::Export {
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
    } = command
    else {
        unreachable!("called for export")
    };
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

/// The folder of a run given as a folder or as its checkpoint file.
fn run_folder(run: &Path) -> PathBuf {
    if run.is_dir() { run.to_path_buf() } else { run.parent().map(Path::to_path_buf).unwrap_or_default() }
}

/// The backend asked for (or `REFNPR_BACKEND`'s), brought up: wgpu names
/// its adapter here, or says why it has none.
fn backend_or_env(b: Option<BackendKind>, progress: &dyn Progress) -> Result<BackendKind> {
    let kind = match b {
        Some(b) => b,
        None => BackendKind::from_env()?,
    };
    kind.open(progress)?;
    Ok(kind)
}

/// A photoreal run and its dataset on the default backend (R³ needs no autodiff).
fn load_run(ckpt: &Path, data_dir: Option<PathBuf>) -> Result<(Checkpoint, Dataset)> {
    checkpoint::load_run(ckpt, data_dir.as_deref(), &backend_or_env(None, &Console::default())?.device())
}

fn run_demo(
    out: &Path,
    backend: BackendKind,
    steps: Option<usize>,
    epochs: Option<usize>,
    progress: &dyn Progress,
) -> Result<()> {
    let r = demo::run_demo(out, backend, &demo::DemoOptions { steps, epochs, ..Default::default() }, progress)?;
    let e = &r.eval;
    let fmt = |v: Option<f32>| v.map(|v| format!("{v:.2} dB")).unwrap_or_else(|| "-".into());
    println!("demo done in {:.0} s (backend {backend})", r.seconds);
    println!(
        "  photoreal fit:   {:.2} dB test PSNR ({:.0} s)  orbit: {}",
        r.photo.test_psnr,
        r.photo.train_seconds,
        out.join("orbit/path.gif").display()
    );
    println!("  reference:       {}", out.join("case/style.png").display());
    println!(
        "  stylized:        {:.0} s  orbit: {}",
        r.stylize.total_seconds,
        out.join("stylized/orbit/path.gif").display()
    );
    println!(
        "  vs ground truth: {} (photoreal field: {:.2} dB), on surfaces the reference does not see: {} ({:.0}% of the surface)",
        fmt(e.gt_psnr),
        r.photo_gt_psnr,
        fmt(e.gt_psnr_occluded),
        100.0 * e.occluded_fraction.unwrap_or(0.0)
    );
    let st: Vec<String> = e.stability.iter().map(|s| format!("{} frame(s) apart {:.4}", s.gap, s.rmse)).collect();
    println!(
        "  Ref-LPIPS {:.4} (LPIPS vgg, the paper's metric; alex {:.4}); stability (warp RMSE) {}",
        e.ref_lpips,
        e.ref_lpips_alex,
        st.join(", ")
    );
    println!(
        "  speckle {:.2}% of the surface pixels (test views {}, ground truth {})",
        100.0 * e.speckle,
        e.speckle_test.map_or("-".into(), |v| format!("{:.2}%", 100.0 * v)),
        e.gt_speckle.map_or("-".into(), |v| format!("{:.2}%", 100.0 * v))
    );
    println!("  all figures: {}", out.join("eval.json").display());
    Ok(())
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

fn run_register(
    inputs: PhotoAndCase,
    out: &Path,
    params: &RegisterParams,
    overlays: usize,
    progress: &dyn Progress,
) -> Result<()> {
    let (ck, dataset) = load_run(&inputs.photo, inputs.data)?;
    let case = ReferenceCase::load(&inputs.reference)?;
    let r = registration::run_register(&ck, &dataset, &case, params, out, overlays, progress)?;
    println!(
        "registered {} pixels ({:.1}% of surface pixels) over {} views; depth {:.2}s, dictionary {:.3}s, registration {:.3}s",
        r.registered_pixels,
        100.0 * r.fraction_overall,
        r.fraction_per_view.len(),
        r.depth_seconds,
        r.dictionary_seconds,
        r.register_seconds
    );
    println!("wrote {}/registration.bin, register.json, overlays/", out.display());
    Ok(())
}

fn run_reference(ckpt: &Path, view: &str, out: &Path, data: Option<PathBuf>) -> Result<()> {
    let (ck, dataset) = load_run(ckpt, data)?;
    let spec = ViewSpec::parse_in(view, &dataset)?;
    let content = registration::write_reference_skeleton(&ck, &dataset, &spec, out)?;
    println!("wrote {} (and depth.png, depth.npy, reference.toml)", content.display());
    println!("paint over it and save the result as {}", out.join("style.png").display());
    Ok(())
}

/// `refnpr stylize`: the config file (or the defaults), then the flags the
/// user gave (`--epochs`, and any R³ flag over the file's `[register]`).
fn run_stylize_command(command: Command, matches: &ArgMatches, progress: &dyn Progress) -> Result<()> {
    let Command::Stylize {
        photo,
        reference,
        data,
        out,
        config,
        preset,
        method,
        style,
        epochs,
        backend,
        no_render,
        resume,
        registration,
        register,
    } = command
    else {
        unreachable!("called for the stylize subcommand")
    };
    let mut config = match preset {
        Some(p) => p.config()?,
        None => stylize_config(config.as_deref())?,
    };
    if let Some(e) = epochs {
        config.schedule.image_epochs = e;
    }
    config.register =
        config::overlay(&config.register, given_flags(&register, matches)?, "the command line", "R³ flags")?;
    config.validate()?;
    let render_test = !no_render;
    let backend = backend_or_env(backend, progress)?;
    let case = match (reference, &style) {
        (Some(case), _) => case,
        (None, Some(style)) if method == Method::Arf => style_only_case(style, &out)?,
        (None, _) => {
            bail!("--reference CASE is needed (only ARF stylizes from a --style image alone: add --method arf)")
        }
    };
    let job = StylizeJob { photo, case, out, config, method, backend, style, data, registration, render_test, resume };
    let r = run_stylize(&job, progress)?;
    let phases: Vec<String> = r.seconds.iter().map(|(k, v)| format!("{k} {v:.1}s")).collect();
    println!("stylized ({}) in {:.1} s: {}", r.method, r.total_seconds, phases.join(", "));
    let o = job.out.display();
    println!(
        "wrote {o}/checkpoint.bin, {o}/stylize.json{}",
        if render_test { format!(", {o}/test/path.gif") } else { String::new() }
    );
    println!(
        "next: refnpr render --run {o} --path orbit --out {o}/orbit, refnpr view {o}, refnpr export {o} --format video"
    );
    Ok(())
}

/// ARF from a style image alone: a reference case of that image at
/// training view 0, written to `out/style_case` (ARF matches the image's
/// statistics from every view; the view only places it for `refnpr eval`).
fn style_only_case(style: &Path, out: &Path) -> Result<PathBuf> {
    let dir = out.join("style_case");
    let ext = style.extension().and_then(|e| e.to_str()).unwrap_or("png");
    let name = format!("style.{ext}");
    let bytes = std::fs::read(style).with_context(|| format!("cannot read the style image {}", style.display()))?;
    files::write_bytes(&dir.join(&name), &bytes)?;
    files::write_text(
        &dir.join("reference.toml"),
        &format!("[[reference]]\nstyle = \"{name}\"\nview = \"train:0\"\n"),
    )?;
    Ok(dir)
}

/// The stylize config of `--config` (the defaults without one).
fn stylize_config(path: Option<&Path>) -> Result<StylizeConfig> {
    match path {
        Some(p) => StylizeConfig::from_file(p),
        None => Ok(StylizeConfig::default()),
    }
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

/// The fields of `parsed` (a flattened `clap::Args` struct) whose flags were
/// given on the command line, as a TOML table to lay over a config.
fn given_flags<T: serde::Serialize>(parsed: &T, matches: &ArgMatches) -> Result<toml::Value> {
    let toml::Value::Table(all) = toml::Value::try_from(parsed)? else {
        unreachable!("a struct serialises to a table")
    };
    let given = all.into_iter().filter(|(k, _)| matches.value_source(k) == Some(ValueSource::CommandLine)).collect();
    Ok(toml::Value::Table(given))
}

/// `refnpr eval` without `--reference`: PSNR / SSIM of the run's test views
/// against its dataset's (or `truth`'s).
fn photoreal_eval(run: &Path, truth: Option<PathBuf>, backend: BackendKind) -> Result<serde_json::Value> {
    let (ck, dataset) = checkpoint::load_run(run, truth.as_deref(), &backend.device())?;
    let r = evaluate(&ck.grid, &dataset, &dataset.test, &ck.meta.render, None)?;
    Ok(serde_json::json!({"psnr": r.psnr, "ssim": r.ssim, "views": r.per_view_psnr.len(), "data": dataset.root}))
}

fn run_refine_poses(
    run: &Path,
    out: &Path,
    data: Option<&Path>,
    settings: &pose_refine::RefineSettings,
    progress: &dyn Progress,
) -> Result<()> {
    let (ck, dataset) = checkpoint::load_run(run, data, &pose_refine::render_device(BackendKind::Flex))?;
    data::check_writable(&dataset, out)?;
    let r = pose_refine::refine_dataset(&ck.grid, &dataset, &ck.meta.render, settings, progress)?;
    println!("{}", r.describe());
    data::write_colmap(&dataset, &r.cameras, out)?;
    println!("wrote {} (train it: refnpr train --data {} --out RUN)", out.display(), out.display());
    Ok(())
}

/// How `refnpr train` runs: resumed, for how many steps, with its poses refined.
struct TrainHow {
    resume: bool,
    steps: Option<usize>,
    refine_poses: bool,
}

fn run_train(
    dir: &Path,
    out: &Path,
    config: Option<&Path>,
    backend: BackendKind,
    how: TrainHow,
    progress: &dyn Progress,
) -> Result<()> {
    let kind = data::detect_kind(dir)?;
    let base = TrainConfig::for_dir(dir)?;
    let mut cfg = match config {
        Some(p) => TrainConfig::from_file(p, &base)?,
        None => base,
    };
    if let Some(s) = how.steps {
        cfg.optim.steps = s;
        cfg.validate()?;
    }
    let dataset = data::load(dir, &cfg.data)?;
    for w in &dataset.warnings {
        progress.warning(w.clone());
    }
    for n in &dataset.notes {
        progress.info(n.clone());
    }
    let size = dataset.train[0].camera.intrinsics;
    progress.info(format!(
        "{kind} scene {}: {} train / {} test views at {}x{}, backend {backend}",
        dir.display(),
        dataset.train.len(),
        dataset.test.len(),
        size.width,
        size.height
    ));
    let m = if how.refine_poses {
        let (first, _, second) = run_training_with_refined_poses(&dataset, cfg, out, backend, progress)?;
        println!("before the cameras were refined: test PSNR {:.2} dB", first.test_psnr);
        second
    } else {
        run_training(&dataset, cfg, out, backend, how.resume, progress)?
    };
    println!("test PSNR {:.2} dB, SSIM {:.4}, {} steps in {:.1} s", m.test_psnr, m.test_ssim, m.steps, m.train_seconds);
    let o = out.display();
    println!("wrote {o}/checkpoint.bin, {o}/metrics.json, {o}/test/ (the test views' renders)");
    println!(
        "next: refnpr views --run {o} (pick a reference view), refnpr reference --run {o} --view train:0 --out CASE"
    );
    Ok(())
}

// mimalloc keeps freed pages mapped: the renderer allocates and frees
// tensors of tens of MB every step, which the system allocator returns to
// the OS and page-faults back in (measured: a third of the time in the kernel).
//
// Not when the standard library is linked dynamically (`-C prefer-dynamic`:
// CI builds the tests so, for the notebooks' kernel to reuse the build; see
// build.rs): the shared libstd allocates with the system allocator before
// `main` and the program would free that memory with mimalloc (a crash at
// start). That build runs on the system allocator, slower but the same.
#[cfg(not(refnpr_dynamic_std))]
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

// mimalloc's own C entry point (linked in by the `mimalloc` crate, which
// does not wrap it). `mi_option_purge_delay` is 15 in mimalloc v2 and v3's
// `mi_option_e`.
#[cfg(not(refnpr_dynamic_std))]
unsafe extern "C" {
    fn mi_option_set(option: std::ffi::c_int, value: std::ffi::c_long);
}
#[cfg(not(refnpr_dynamic_std))]
const MI_OPTION_PURGE_DELAY: std::ffi::c_int = 15;

/// Never hand freed memory back to the OS. By default mimalloc purges it
/// after 10 ms, and a stylization step (VGG activations, gradient buffers
/// of tens of MB) then spends a quarter of its time in the kernel zeroing
/// fresh pages (measured on lego: 2.4 s per step instead of 3.6 s without
/// purging). Peak memory is unchanged; memory is only reused.
fn keep_freed_memory() {
    // SAFETY: sets a process-wide allocator option before any thread is started.
    #[cfg(not(refnpr_dynamic_std))]
    unsafe {
        mi_option_set(MI_OPTION_PURGE_DELAY, -1)
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The names of `cmd`'s arguments and subcommands that say nothing in `--help`.
    fn without_help(cmd: &clap::Command, path: &str, missing: &mut Vec<String>) {
        for arg in cmd.get_arguments() {
            let id = arg.get_id().as_str();
            if id != "help" && id != "version" && arg.get_help().is_none() && arg.get_long_help().is_none() {
                missing.push(format!("{path} {id}"));
            }
        }
        for sub in cmd.get_subcommands().filter(|c| c.get_name() != "help") {
            let name = format!("{path} {}", sub.get_name());
            if sub.get_about().is_none() {
                missing.push(format!("{name} (the command itself)"));
            }
            without_help(sub, &name, missing);
        }
    }

    #[test]
    fn every_command_and_argument_has_a_help_line() {
        let mut missing = Vec::new();
        without_help(&Cli::command(), "refnpr", &mut missing);
        assert!(missing.is_empty(), "no help text for: {missing:?}");
    }

    /// `refnpr --help` lists the user's commands in the order of the
    /// pipeline; the developer's are named after the list.
    #[test]
    fn the_listed_commands_come_in_pipeline_order() {
        let cli = Cli::command();
        let listed: Vec<&str> = cli.get_subcommands().filter(|c| !c.is_hide_set()).map(|c| c.get_name()).collect();
        let pipeline = [
            "scene",
            "capture",
            "train",
            "refine-poses",
            "render",
            "views",
            "reference",
            "paint",
            "recolour",
            "register",
            "stylize",
            "eval",
            "lpips",
            "export",
            "view",
            "demo",
        ];
        assert_eq!(listed, pipeline);
        for developer in ["bench", "bench-vgg", "bench-stylize", "fuzz", "info"] {
            assert!(WORKFLOW.contains(developer), "{developer} is hidden from the list and not named after it");
            assert!(cli.find_subcommand(developer).is_some(), "{developer} is gone");
        }
    }

    /// `--run` names a run folder everywhere; the old names still parse, so
    /// scripts written for them keep working.
    #[test]
    fn old_flag_names_still_parse_as_the_new_ones() {
        let parse = |line: &str| Cli::try_parse_from(line.split(' ')).map(|c| c.command);
        for (new, old) in [
            ("refnpr render --run r --out o", "refnpr render --ckpt r --out o"),
            ("refnpr reference --run r --view train:0 --out o", "refnpr reference --ckpt r --view train:0 --out o"),
            ("refnpr stylize --run r --reference c --out o", "refnpr stylize --photo r --reference c --out o"),
            ("refnpr register --run r --reference c --out o", "refnpr register --photo r --reference c --out o"),
            ("refnpr eval --run r --reference c", "refnpr eval --ckpt r --reference c"),
        ] {
            let (a, b) = (parse(new).expect(new), parse(old).expect(old));
            assert_eq!(format!("{:?}", run_of(&a)), format!("{:?}", run_of(&b)), "{new} vs {old}");
        }
        let Ok(Command::Stylize { epochs, register, .. }) =
            parse("refnpr stylize --photo r --reference c --out o --epochs 3 --erode 2 --no-footprint-cap")
        else {
            panic!("stylize with the old flag names did not parse")
        };
        assert_eq!((epochs, register.erode_reference, register.cap_to_footprint), (Some(3), 2, false));
    }

    /// A flag that sets a config key is named as the key (`--no-` before a
    /// switch that turns it off): every `[register]` key of the stylize
    /// config, `--image-epochs`, `--steps`.
    #[test]
    fn flags_are_named_as_their_config_keys() {
        let cli = Cli::command();
        let long_of = |command: &str, id: &str| {
            let sub = cli.find_subcommand(command).expect(command);
            let arg = sub.get_arguments().find(|a| a.get_id() == id).unwrap_or_else(|| panic!("{command}: no {id}"));
            arg.get_long().expect("a long flag").to_string()
        };
        let config: toml::Table = toml::from_str(include_str!("../../configs/stylize.toml")).expect("stylize.toml");
        let register = config["register"].as_table().expect("[register]");
        assert!(register.len() >= 7, "{register:?}");
        for command in ["stylize", "register"] {
            for (key, value) in register {
                let long = long_of(command, key);
                let named = key.replace('_', "-");
                let expected = if value.as_bool() == Some(true) { format!("no-{named}") } else { named };
                assert_eq!(long, expected, "{command}: the flag of register.{key}");
            }
        }
        assert!(config["schedule"].get("image_epochs").is_some());
        assert_eq!(long_of("stylize", "epochs"), "image-epochs");
        assert_eq!(long_of("train", "steps"), "steps");
    }

    /// ARF takes a style image alone; Ref-NPR needs its reference case.
    #[test]
    fn a_style_image_stands_in_for_the_case_only_in_parsing_arf() {
        let parse = |line: &str| Cli::try_parse_from(line.split(' ')).map(|c| c.command);
        assert!(parse("refnpr stylize --run r --out o --method arf --style s.png").is_ok());
        assert!(parse("refnpr stylize --run r --out o").is_err(), "neither --reference nor --style");
        let t = std::env::temp_dir().join(format!("refnpr-style-only-{}", std::process::id()));
        std::fs::create_dir_all(&t).unwrap();
        std::fs::write(t.join("s.png"), b"not checked here").unwrap();
        let case = style_only_case(&t.join("s.png"), &t.join("out")).unwrap();
        let toml = std::fs::read_to_string(case.join("reference.toml")).unwrap();
        assert!(toml.contains("style = \"style.png\"") && toml.contains("train:0"), "{toml}");
        assert!(case.join("style.png").is_file());
        std::fs::remove_dir_all(&t).ok();
    }

    /// The run folder a parsed command names.
    fn run_of(command: &Command) -> Option<&Path> {
        match command {
            Command::Render { ckpt, .. } | Command::Reference { ckpt, .. } => Some(ckpt),
            Command::Stylize { photo, .. } => Some(photo),
            Command::Register { inputs, .. } => Some(&inputs.photo),
            Command::Eval { run, .. } => Some(run),
            _ => None,
        }
    }
}
