//! The library as a notebook uses it (evcxr, the Rust Jupyter kernel; see
//! `notebooks/`): one type per stage (`Scene`, `Photo`, `Reference`,
//! `Registered`, `Stylized`) whose methods make the same library calls as
//! the `refnpr` subcommands, and values that show themselves in a cell
//! (`display`: images, galleries, plots, tables).
//!
//! Errors are [`Error`]: its `Display` is the whole chain of causes, the
//! message the CLI prints, so a `?` in a cell shows it in full (evcxr prints
//! a cell's error with `{}`).

pub mod display;

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use crate::eval::stylization::{self, EvalJob, RobustnessViews, StylizationEval};
use crate::field::checkpoint::{self, Checkpoint};
use crate::field::render_path::{self, PathKind};
use crate::photo::config::TrainConfig;
use crate::photo::run::{TrainMetrics, run_training};
use crate::reference::case::{ReferenceCase, ViewSpec};
use crate::reference::r3::RegisterParams;
use crate::reference::registration::{self, RegisterReport, RegistrationFile};
use crate::scene::camera::Camera;
use crate::scene::data::{self, Dataset, LoadOptions, Split, procedural};
use crate::stylize::config::StylizeConfig;
use crate::stylize::run::run_stylize;
use crate::stylize::{Method, StepKind, StylizeJob, StylizeReport};
use crate::tools::{demo, paint};
use crate::util::backend::BackendKind;
use crate::util::files;
use crate::util::image::Image;
use crate::util::progress::{Event, Phase, Progress};
pub use display::{Difference, Gallery, Plot, Series, Table};

/// How two renders of one view differ (see [`display::difference`]).
pub fn difference(a: &Image, b: &Image, gain: f32) -> Result<Difference> {
    Ok(display::difference(a, b, gain)?)
}

/// An error of a notebook call: the library's error, displayed with its
/// causes (`a: b: c`), as the CLI prints it.
pub struct Error(pub anyhow::Error);

impl std::fmt::Display for Error {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "error: {:#}", self.0)
    }
}

// Debug as Display: anyhow's Debug adds a backtrace when RUST_BACKTRACE is set.
impl std::fmt::Debug for Error {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{self}")
    }
}

/// A call's error as a cell shows it (`?` prints it and stops the cell;
/// this keeps it as the cell's value), or "no error".
pub struct ErrorText(pub Option<String>);

/// The error `result` holds, to show in a cell.
pub fn error_text<T>(result: Result<T>) -> ErrorText {
    ErrorText(result.err().map(|e| e.to_string()))
}

impl ErrorText {
    pub fn evcxr_display(&self) {
        let text = self.0.as_deref().unwrap_or("no error");
        #[allow(clippy::print_stdout)] // evcxr reads displays from stdout
        {
            print!("{}", display::content_block("text/plain", text));
        }
    }
}

impl<E: Into<anyhow::Error>> From<E> for Error {
    fn from(e: E) -> Self {
        Error(e.into())
    }
}

pub type Result<T> = std::result::Result<T, Error>;

/// Progress for a notebook cell: what is done and written, warnings, and
/// each phase at a few points (a bar would redraw nothing in a cell).
#[derive(Default)]
pub struct Cells {
    /// The last fifth of each running phase that was reported.
    reported: Mutex<Vec<(Phase, usize)>>,
}

/// Lines per phase.
const LINES_PER_PHASE: usize = 5;

#[allow(clippy::print_stdout)] // the notebook's sink: a cell shows stdout
impl Progress for Cells {
    fn event(&self, event: Event) {
        match event {
            Event::Start { phase, done, total } => {
                let mut r = self.reported.lock().unwrap_or_else(|e| e.into_inner());
                r.retain(|(p, _)| *p != phase);
                r.push((phase, done * LINES_PER_PHASE / total.max(1)));
                println!(
                    "{phase}: {total} steps{}",
                    if done > 0 { format!(" ({done} done before)") } else { "".into() }
                );
            }
            Event::Step { phase, done, total, message } => {
                let part = done * LINES_PER_PHASE / total.max(1);
                let mut r = self.reported.lock().unwrap_or_else(|e| e.into_inner());
                if let Some(entry) = r.iter_mut().find(|(p, _)| *p == phase)
                    && part > entry.1
                {
                    entry.1 = part;
                    let sep = if message.is_empty() { "" } else { ": " };
                    println!("  {phase} {done}/{total}{sep}{message}");
                }
            }
            Event::PhaseDone { phase, seconds } => println!("{phase} done in {seconds:.1} s"),
            Event::Info(m) => println!("{m}"),
            Event::Warning(m) => println!("warning: {m}"),
            Event::Detail(_) | Event::JobStart(_) | Event::JobDone => {}
        }
    }
}

/// A dataset folder and its loaded views.
pub struct Scene {
    pub dir: PathBuf,
    pub dataset: Dataset,
    /// How it was loaded (a fit records them, so the run reloads the same views).
    pub options: LoadOptions,
    /// The generator's options, for the procedural scene.
    pub procedural: Option<procedural::SceneOptions>,
}

impl Scene {
    /// Writes the built-in procedural scene (square views of `size` pixels,
    /// with its stylized twin in `dir/stylized`) and loads it.
    pub fn procedural(dir: impl AsRef<Path>, size: u32) -> Result<Scene> {
        let dir = dir.as_ref();
        let options = procedural::SceneOptions { size, ..Default::default() };
        procedural::write_scene(dir, &options)?;
        Ok(Scene { procedural: Some(options), ..Scene::load(dir)? })
    }

    /// A dataset from a folder of photos through COLMAP (`refnpr capture`,
    /// `docs/own_scene.md`), written to `out` and loaded.
    pub fn capture(photos: impl AsRef<Path>, out: impl AsRef<Path>) -> Result<Scene> {
        let options = crate::tools::capture::CaptureOptions::default();
        crate::tools::capture::capture(photos.as_ref(), out.as_ref(), &options, &Cells::default())?;
        Scene::load(out)
    }

    /// Loads a dataset folder of any layout (Blender, LLFF, NSVF, a COLMAP
    /// model, `transforms.json`) with its kind's default loading options.
    pub fn load(dir: impl AsRef<Path>) -> Result<Scene> {
        let dir = dir.as_ref();
        Scene::load_with(dir, &TrainConfig::for_dir(dir)?.data)
    }

    /// Loads a folder with these options (for example a `downscale`).
    pub fn load_with(dir: impl AsRef<Path>, options: &LoadOptions) -> Result<Scene> {
        let dir = dir.as_ref().to_path_buf();
        let dataset = data::load(&dir, options)?;
        Ok(Scene { dir, dataset, options: *options, procedural: None })
    }

    /// The procedural scene's exact image of any camera: `stylized` picks
    /// its stylized twin (the ground truth of a stylization).
    pub fn truth(&self, camera: &Camera, stylized: bool) -> Result<Image> {
        let options = self.procedural.ok_or_else(|| {
            anyhow::anyhow!("{} is not the procedural scene: its truth exists only at its photos", self.dir.display())
        })?;
        let (rgba, _, _) = procedural::Scene::new(options.seed).render(camera, stylized);
        let background = self.dataset.background;
        let rgb =
            rgba.chunks(4).flat_map(|p| (0..3).map(move |c| p[c] * p[3] + background[c] * (1.0 - p[3]))).collect();
        Ok(camera.image_of(rgb))
    }

    /// The procedural scene's ground-truth stylized twin (`dir/stylized`).
    pub fn stylized_twin(&self) -> Result<Scene> {
        let twin = self.dir.join("stylized");
        if !twin.is_dir() {
            return Err(anyhow::anyhow!(
                "{} has no stylized twin (only the procedural scene has one)",
                self.dir.display()
            )
            .into());
        }
        Scene::load(twin)
    }

    /// The training config this kind of scene starts from (`configs/*.toml`),
    /// with the options the scene was loaded with.
    pub fn default_config(&self) -> TrainConfig {
        TrainConfig { data: self.options, ..TrainConfig::for_setup(self.dataset.kind, self.dataset.ndc.is_some()) }
    }

    /// Kind, views and image size.
    pub fn summary(&self) -> Table {
        let k = self.dataset.train.first().map(|v| v.camera.intrinsics);
        Table::new(&["folder", "kind", "train views", "test views", "image size"]).row(vec![
            self.dir.display().to_string(),
            self.dataset.kind.to_string(),
            self.dataset.train.len().to_string(),
            self.dataset.test.len().to_string(),
            k.map_or("-".into(), |k| format!("{}x{}", k.width, k.height)),
        ])
    }

    /// Photos of one split, by index (out-of-range indices are an error).
    pub fn photos(&self, split: Split, indices: &[usize]) -> Result<Gallery> {
        let views = self.dataset.split(split);
        let mut items = Vec::new();
        for &i in indices {
            let v = views.get(i).ok_or_else(|| {
                anyhow::anyhow!("{split:?} view {i} is out of range: the scene has {} of them", views.len())
            })?;
            items.push((format!("{split:?} {i} ({})", v.name), v.camera.image_of(v.rgb.clone())));
        }
        Ok(Gallery::new(items))
    }

    /// The camera of `view` (`train:N`, `test:N` or `path:N` on the standard 120-frame path).
    pub fn camera(&self, view: &str) -> Result<Camera> {
        view_camera(&self.dataset, view)
    }
}

/// The camera `view` names in `dataset` (`train:N`, `test:N`, `path:N`), as a reference case resolves it.
fn view_camera(dataset: &Dataset, view: &str) -> Result<Camera> {
    let spec: ViewSpec = view.parse()?;
    Ok(spec.camera(dataset, crate::reference::case::DEFAULT_PATH_FRAMES)?)
}

/// A photorealistic run: its folder, field and dataset.
pub struct Photo {
    pub dir: PathBuf,
    pub checkpoint: Checkpoint,
    pub dataset: Dataset,
    pub backend: BackendKind,
    /// `metrics.json`, when the run finished.
    pub metrics: Option<TrainMetrics>,
}

impl Photo {
    /// Fits a field to `scene` into `out` (what `refnpr train` does). The
    /// config's `[data]` becomes the scene's loading options: the run
    /// reloads the views the notebook loaded.
    pub fn fit(scene: &Scene, config: TrainConfig, out: impl AsRef<Path>, backend: BackendKind) -> Result<Photo> {
        let out = out.as_ref();
        let config = TrainConfig { data: scene.options, ..config };
        config.validate()?;
        let progress = Cells::default();
        backend.open(&progress)?;
        let metrics = run_training(&scene.dataset, config, out, backend, false, &progress)?;
        progress.info(format!(
            "test PSNR {:.2} dB after {} steps ({:.0} s)",
            metrics.test_psnr, metrics.steps, metrics.train_seconds
        ));
        Photo::load(out, backend)
    }

    /// The run in `out` when it was fitted with exactly `config` to this
    /// scene; otherwise fits it (so a rerun notebook does not fit again).
    pub fn fit_or_load(
        scene: &Scene,
        config: TrainConfig,
        out: impl AsRef<Path>,
        backend: BackendKind,
    ) -> Result<Photo> {
        let out = out.as_ref();
        let config = TrainConfig { data: scene.options, ..config };
        // A run saves the schedule it ran: grown where the grid followed
        // the images (`TrainConfig::follow_images`).
        let followed = config.for_views(&scene.dataset);
        let same_config = std::fs::read_to_string(out.join("config.toml"))
            .ok()
            .and_then(|text| toml::from_str::<TrainConfig>(&text).ok())
            .is_some_and(|saved| saved == followed);
        if same_config && out.join("metrics.json").exists() {
            let photo = Photo::load(out, backend)?;
            if photo.dataset.root == scene.dataset.root {
                Cells::default()
                    .info(format!("{} was fitted with this config: loaded (delete it to fit again)", out.display()));
                return Ok(photo);
            }
        }
        Photo::fit(scene, config, out, backend)
    }

    /// Loads a run folder (or checkpoint file) on `backend`.
    pub fn load(dir: impl AsRef<Path>, backend: BackendKind) -> Result<Photo> {
        let dir = dir.as_ref().to_path_buf();
        let device = backend.open(&Cells::default())?;
        let (checkpoint, dataset) = checkpoint::load_run(&dir, None, &device)?;
        let metrics_path = checkpoint.source.with_file_name("metrics.json");
        let metrics = std::fs::read_to_string(&metrics_path).ok().and_then(|t| serde_json::from_str(&t).ok());
        Ok(Photo { dir, checkpoint, dataset, backend, metrics })
    }

    /// The same run loaded on another backend.
    pub fn on(&self, backend: BackendKind) -> Result<Photo> {
        Photo::load(&self.dir, backend)
    }

    /// Renders a camera.
    pub fn render(&self, camera: &Camera) -> Image {
        self.checkpoint.render_view(camera).image
    }

    /// Renders `train:N`, `test:N` or `path:N`.
    pub fn render_view(&self, view: &str) -> Result<Image> {
        Ok(self.render(&view_camera(&self.dataset, view)?))
    }

    /// The training loss (MSE, log scale) by step.
    pub fn loss_curve(&self) -> Result<Plot> {
        let m =
            self.metrics.as_ref().ok_or_else(|| anyhow::anyhow!("{} has no metrics.json yet", self.dir.display()))?;
        let points = m.loss_curve.iter().map(|p| (p.step as f32, p.mse)).collect();
        Ok(Plot::lines("photoreal fit", "step", "MSE", &[Series::new("training batch", points)], true)?)
    }

    /// Test renders (top) above the photos (bottom), by test index.
    pub fn test_views(&self, indices: &[usize]) -> Result<Gallery> {
        let mut renders = Vec::new();
        let mut photos = Vec::new();
        for &i in indices {
            let v = self.dataset.test.get(i).ok_or_else(|| {
                anyhow::anyhow!("test view {i} is out of range: the scene has {}", self.dataset.test.len())
            })?;
            let render = self.render(&v.camera);
            let psnr = crate::util::metrics::psnr(&render.rgb, &v.rgb);
            renders.push((format!("render test {i} ({psnr:.1} dB)"), render));
            photos.push((format!("photo test {i}"), v.camera.image_of(v.rgb.clone())));
        }
        Ok(Gallery::new(renders.into_iter().chain(photos).collect()).with_columns(indices.len()))
    }

    /// Renders `frames` cameras of the scene's standard path (an orbit, or
    /// LLFF's spiral) into `out` (PNGs and `path.gif`, as `refnpr render`);
    /// shows 8 of them.
    pub fn render_path(&self, frames: usize, out: impl AsRef<Path>) -> Result<Gallery> {
        render_path_of(&self.checkpoint, &self.dataset, frames, out.as_ref())
    }
}

fn render_path_of(ck: &Checkpoint, dataset: &Dataset, frames: usize, out: &Path) -> Result<Gallery> {
    let kind = if dataset.ndc.is_some() { PathKind::Spiral } else { PathKind::Orbit };
    let cams = render_path::path_cameras(dataset, kind, frames)?;
    let images = render_path::render_frames(ck, &cams, out, &Cells::default())?;
    let step = images.len().div_ceil(8).max(1);
    let items = images.into_iter().enumerate().step_by(step).map(|(i, img)| (format!("frame {i}"), img)).collect();
    Ok(Gallery::new(items).with_columns(8))
}

/// An image file as RGB (transparent pixels over white).
pub fn read_image(path: &Path) -> Result<Image> {
    let (w, h, rgb) = data::read_rgb(path, [1.0; 3], 1)?;
    Ok(Image::new(w as usize, h as usize, rgb))
}

/// A reference case folder: style images and the views they were painted from.
pub struct Reference {
    pub dir: PathBuf,
    pub case: ReferenceCase,
}

impl Reference {
    pub fn load(dir: impl AsRef<Path>) -> Result<Reference> {
        let dir = dir.as_ref().to_path_buf();
        let case = ReferenceCase::load(&dir)?;
        Ok(Reference { dir, case })
    }

    /// The procedural scene's stylized twin at training view `view`: an
    /// exact repaint, so stylizations can be scored against the truth.
    pub fn twin(scene: &Scene, view: usize, out: impl AsRef<Path>) -> Result<Reference> {
        let out = out.as_ref();
        files::create_dir(out)?;
        demo::write_twin_case(&scene.dir, view, out)?;
        Reference::load(out)
    }

    /// Writes the case skeleton at `view` (what `refnpr reference` does),
    /// then paints its content render with the painterly filter (what
    /// `refnpr paint` does) as the style image.
    pub fn painted(photo: &Photo, view: &str, out: impl AsRef<Path>, seed: u64) -> Result<Reference> {
        let out = out.as_ref();
        let spec: ViewSpec = view.parse()?;
        registration::write_reference_skeleton(&photo.checkpoint, &photo.dataset, &spec, out)?;
        let content = read_image(&out.join("content.png"))?;
        let painted = paint::painterly(&content.rgb, content.width, content.height, seed);
        Image::new(content.width, content.height, painted).save_png(&out.join("style.png"))?;
        Reference::load(out)
    }

    /// The style images, with the views they were painted from.
    pub fn styles(&self) -> Result<Gallery> {
        let mut items = Vec::new();
        for r in &self.case.references {
            items.push((format!("style at {}", r.view), read_image(&r.style)?));
        }
        Ok(Gallery::new(items))
    }

    /// Each reference beside the photoreal render of its view.
    pub fn beside_content(&self, photo: &Photo) -> Result<Gallery> {
        let mut items = Vec::new();
        for (r, cam) in self.case.references.iter().zip(self.case.cameras(&photo.dataset)?) {
            items.push((format!("content at {}", r.view), photo.render(&cam)));
            items.push((format!("style at {}", r.view), read_image(&r.style)?));
        }
        Ok(Gallery::new(items))
    }
}

/// R³'s result: the registered pseudo-rays of every training view.
pub struct Registered {
    pub dir: PathBuf,
    pub report: RegisterReport,
    pub file: RegistrationFile,
}

impl Registered {
    /// Runs R³ into `out` (what `refnpr register` does, overlays of the first 8 views included).
    pub fn run(
        photo: &Photo,
        reference: &Reference,
        params: &RegisterParams,
        out: impl AsRef<Path>,
    ) -> Result<Registered> {
        let out = out.as_ref().to_path_buf();
        let report = registration::run_register(
            &photo.checkpoint,
            &photo.dataset,
            &reference.case,
            params,
            &out,
            8,
            &Cells::default(),
        )?;
        let file = RegistrationFile::load(&out)?;
        Ok(Registered { dir: out, report, file })
    }

    /// The registered pixels in their colours over the dimmed content
    /// render of training views `indices` (the paper's figure A.2).
    pub fn overlays(&self, photo: &Photo, indices: &[usize]) -> Result<Gallery> {
        let mut items = Vec::new();
        for &i in indices {
            let (view, reg) = photo.dataset.train.get(i).zip(self.file.views.get(i)).ok_or_else(|| {
                anyhow::anyhow!("training view {i} is out of range: the scene has {}", photo.dataset.train.len())
            })?;
            let content = photo.render(&view.camera);
            let share = self.report.fraction_per_view.get(i).copied().unwrap_or(0.0);
            items.push((
                format!("train {i}: {:.0}% registered", 100.0 * share),
                registration::overlay(&content, &reg.registration),
            ));
        }
        Ok(Gallery::new(items))
    }

    /// The `n` training views R³ registered the largest share of, most
    /// covered first (ties: the lower index first): the views worth an
    /// overlay, where a fixed pick of views often lands on the far side.
    pub fn most_covered(&self, n: usize) -> Vec<usize> {
        let shares = &self.report.fraction_per_view;
        let mut views: Vec<usize> = (0..shares.len()).collect();
        views.sort_by(|&a, &b| shares[b].total_cmp(&shares[a]).then(a.cmp(&b)));
        views.truncate(n);
        views
    }

    /// The share of each training view's surface pixels that R³ registered.
    pub fn coverage(&self) -> Result<Plot> {
        let points = self.report.fraction_per_view.iter().enumerate().map(|(i, &f)| (i as f32, 100.0 * f)).collect();
        Ok(Plot::lines(
            "R³ coverage",
            "training view",
            "% of surface pixels registered",
            &[Series::new("registered", points)],
            false,
        )?)
    }

    /// Registered pixels and time per stage.
    pub fn figures(&self) -> Table {
        let r = &self.report;
        Table::new(&[
            "registered pixels",
            "of surface pixels",
            "views",
            "depth (s)",
            "dictionary (s)",
            "registration (s)",
        ])
        .row(vec![
            r.registered_pixels.to_string(),
            format!("{:.1}%", 100.0 * r.fraction_overall),
            r.fraction_per_view.len().to_string(),
            format!("{:.2}", r.depth_seconds),
            format!("{:.3}", r.dictionary_seconds),
            format!("{:.3}", r.register_seconds),
        ])
    }
}

/// A stylized run: its folder, report and field.
pub struct Stylized {
    pub dir: PathBuf,
    pub report: StylizeReport,
    pub checkpoint: Checkpoint,
    pub dataset: Dataset,
}

impl Stylized {
    /// Stylizes `photo` after `reference` into `out` (what `refnpr stylize`
    /// does; ARF uses the case's first style image).
    pub fn run(
        photo: &Photo,
        reference: &Reference,
        method: Method,
        config: StylizeConfig,
        out: impl AsRef<Path>,
    ) -> Result<Stylized> {
        let out = out.as_ref().to_path_buf();
        config.validate()?;
        let job = StylizeJob {
            photo: photo.dir.clone(),
            case: reference.dir.clone(),
            out: out.clone(),
            config,
            method,
            backend: photo.backend,
            style: None,
            data: None,
            registration: None,
            render_test: false,
            resume: false,
        };
        let report = run_stylize(&job, &Cells::default())?;
        let checkpoint = checkpoint::load_with(&out, &photo.backend.device(), false)?;
        Ok(Stylized { dir: out, report, checkpoint, dataset: photo.dataset.clone() })
    }

    /// Loss by step: L_ref (the refit's photo MSE), L_feat, L_color, content; log scale.
    pub fn loss_curves(&self) -> Result<Plot> {
        let image_steps: Vec<_> = self.report.curve.iter().filter(|p| p.phase != StepKind::Refit).collect();
        let series = |name: &str, f: &dyn Fn(&crate::stylize::CurvePoint) -> f32| {
            Series::new(name, image_steps.iter().map(|p| (p.step as f32, f(p))).collect())
        };
        let mut lines = vec![series("total", &|p| p.total), series("reference (L_ref)", &|p| p.reference)];
        lines.push(series(if self.report.method == Method::Arf { "NNFM" } else { "feature (L_feat)" }, &|p| p.feature));
        if self.report.method == Method::RefNpr {
            lines.push(series("colour (L_color)", &|p| p.colour));
        }
        lines.push(series("content", &|p| p.content));
        let title = format!("{} image steps (the smooth update from step {})", self.report.method, self.smooth_start());
        Ok(Plot::lines(&title, "image step", "loss", &lines, true)?)
    }

    fn smooth_start(&self) -> String {
        self.report.curve.iter().find(|p| p.phase == StepKind::Smooth).map_or("-".into(), |p| p.step.to_string())
    }

    /// The refit's photo MSE by step.
    pub fn refit_curve(&self) -> Result<Plot> {
        let points =
            self.report.curve.iter().filter(|p| p.phase == StepKind::Refit).map(|p| (p.step as f32, p.total)).collect();
        Ok(Plot::lines("colour refit", "step", "MSE", &[Series::new("refit", points)], true)?)
    }

    pub fn render(&self, camera: &Camera) -> Image {
        self.checkpoint.render_view(camera).image
    }

    /// Renders the standard path into `out` (PNGs and `path.gif`); shows 8 frames.
    pub fn render_path(&self, frames: usize, out: impl AsRef<Path>) -> Result<Gallery> {
        render_path_of(&self.checkpoint, &self.dataset, frames, out.as_ref())
    }

    /// The stylization metrics (what `refnpr eval --reference` computes);
    /// `truth`: a ground-truth stylized dataset (the procedural twin).
    pub fn evaluate(&self, reference: &Reference, truth: Option<&Scene>) -> Result<StylizationEval> {
        let job = EvalJob {
            run: self.dir.clone(),
            case: reference.dir.clone(),
            gt: truth.map(|s| s.dir.clone()),
            robustness: 0,
            robustness_views: RobustnessViews::Near,
            backend: backend_of(&self.report),
            data: None,
            robustness_epochs: None,
            resume: false,
        };
        Ok(stylization::evaluate_stylization(&job, &Cells::default())?)
    }
}

fn backend_of(report: &StylizeReport) -> BackendKind {
    <BackendKind as clap::ValueEnum>::from_str(&report.backend, true).unwrap_or_default()
}

/// Something that renders a camera: a field's `render`, a scene's truth.
pub type Renderer<'a> = &'a dyn Fn(&Camera) -> Image;

/// The same cameras rendered by several fields, a row per field.
pub fn side_by_side(rows: &[(&str, Renderer)], cameras: &[(String, Camera)]) -> Gallery {
    let mut items = Vec::new();
    for (name, render) in rows {
        for (label, cam) in cameras {
            items.push((format!("{name}, {label}"), render(cam)));
        }
    }
    Gallery::new(items).with_columns(cameras.len().max(1))
}

/// Stylization metrics of several runs, a row each.
pub fn eval_table(rows: &[(&str, &StylizationEval)]) -> Table {
    let db = |v: Option<f32>| v.map_or("-".into(), |v| format!("{v:.2}"));
    let mut t =
        Table::new(&["run", "gt_psnr (dB)", "gt_psnr_occluded (dB)", "ref_lpips", "stability (1 frame)", "speckle"]);
    for (name, e) in rows {
        t = t.row(vec![
            name.to_string(),
            db(e.gt_psnr),
            db(e.gt_psnr_occluded),
            format!("{:.4}", e.ref_lpips),
            e.stability.first().map_or("-".into(), |s| format!("{:.4}", s.rmse)),
            format!("{:.2}%", 100.0 * e.speckle),
        ]);
    }
    t
}

/// The demo's short configs, a starting point for small scenes.
pub fn demo_configs() -> Result<(TrainConfig, StylizeConfig)> {
    Ok((demo::demo_config()?, demo::demo_stylize_config()?))
}

/// A training config file (keys as in `configs/*.toml`) over the scene's defaults.
pub fn train_config_file(path: impl AsRef<Path>, scene: &Scene) -> Result<TrainConfig> {
    Ok(TrainConfig::from_file(path.as_ref(), &scene.default_config())?)
}

/// A TOML overlay on a training config (keys as in `configs/*.toml`); an
/// unknown key is refused, naming it, as in a config file.
pub fn train_config(base: &TrainConfig, toml_text: &str) -> Result<TrainConfig> {
    Ok(TrainConfig::from_toml_str(toml_text, base, "the notebook's config")?)
}

/// A TOML overlay on a stylization config; an unknown key is refused.
pub fn stylize_config(base: &StylizeConfig, toml_text: &str) -> Result<StylizeConfig> {
    let merged = crate::util::config::parse_over(base, toml_text, "the notebook's config", "stylize config")?;
    merged.validate()?;
    Ok(merged)
}
