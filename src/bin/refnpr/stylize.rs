//! The reference and the stylization: `refnpr reference` (the view to paint),
//! `paint` and `recolour` (a painting or a grade without painting),
//! `register` (R³) and `stylize`.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::ArgMatches;
use clap::parser::ValueSource;
use refnpr::reference::case::{ReferenceCase, ViewSpec};
use refnpr::reference::r3::RegisterParams;
use refnpr::reference::registration;
use refnpr::scene::data;
use refnpr::stylize::config::{Preset, StylizeConfig};
use refnpr::stylize::region;
use refnpr::stylize::run::run_stylize;
use refnpr::stylize::{Method, StylizeJob};
use refnpr::tools::paint;
use refnpr::util::{config, files, image};
use refnpr::{BackendKind, Console, Progress};

use crate::common::{backend_or_env, load_run};

/// The inputs of the R³ and stylization commands.
#[derive(clap::Args)]
pub struct PhotoAndCase {
    /// Photoreal run folder (or its checkpoint file), as `refnpr train --out` wrote it.
    #[arg(long = "run", alias = "photo", value_name = "RUN")]
    pub photo: PathBuf,
    /// Reference case folder (reference.toml or the authors' data_config.json).
    #[arg(long)]
    pub reference: PathBuf,
    /// Dataset folder (default: the one the photoreal run was trained on).
    #[arg(long)]
    pub data: Option<PathBuf>,
}

// `refnpr reference`'s arguments.
#[derive(clap::Args)]
pub struct ReferenceArgs {
    /// Photoreal run folder (or its checkpoint file).
    #[arg(long = "run", alias = "ckpt", value_name = "RUN")]
    pub ckpt: PathBuf,
    /// train:N | test:N | path:N (path = the standard render path, 120 poses; `refnpr views` shows them all),
    /// or a training or test image's file name (r_12.png, IMG_0042).
    #[arg(long)]
    pub view: String,
    /// The reference case folder to write (content.png, depth, reference.toml).
    #[arg(long)]
    pub out: PathBuf,
    /// Dataset folder (default: the one the run was trained on).
    #[arg(long)]
    pub data: Option<PathBuf>,
}

/// `refnpr reference`: the content view and a case skeleton to paint over.
pub fn reference(args: ReferenceArgs) -> Result<()> {
    let ReferenceArgs { ckpt, view, out, data } = args;
    let (ck, dataset) = load_run(&ckpt, data)?;
    let spec = ViewSpec::parse_in(&view, &dataset)?;
    let content = registration::write_reference_skeleton(&ck, &dataset, &spec, &out)?;
    println!("wrote {} (and depth.png, depth.npy, reference.toml)", content.display());
    println!("paint over it and save the result as {}", out.join("style.png").display());
    Ok(())
}

// `refnpr paint`'s arguments.
#[derive(clap::Args)]
pub struct PaintArgs {
    /// The image to repaint (a case's content.png).
    #[arg(long)]
    pub input: PathBuf,
    /// The painted image to write (a case's style.png).
    #[arg(long)]
    pub out: PathBuf,
    /// Seed of the brush strokes.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// A colour grade instead of the painterly repaint (a recolouring reference).
    #[arg(long, value_enum)]
    pub grade: Option<paint::Grade>,
    /// Repaint only these objects (ids of the procedural scene's `*_id.png`:
    /// 1 ground, 2 sphere, 3 box, 4 cylinder), read from `--ids`: a local edit.
    #[arg(long, value_delimiter = ',', requires = "ids")]
    pub objects: Vec<u8>,
    /// The object-id map of the image (the reference view's `r_N_id.png`).
    #[arg(long, requires = "objects")]
    pub ids: Option<PathBuf>,
    /// Repaint only where this mask image (the image's size) is white: a
    /// local edit, whose case can name the same mask as its `region`.
    #[arg(long, conflicts_with = "objects")]
    pub mask: Option<PathBuf>,
}

/// `refnpr paint`: the painterly repaint filter (or a colour grade) on an image.
pub fn paint(args: PaintArgs) -> Result<()> {
    let PaintArgs { input, out, seed, grade, objects, ids, mask } = args;
    let img = ::image::open(&input).with_context(|| format!("cannot read image {}", input.display()))?.to_rgba32f();
    let (w, h) = (img.width(), img.height());
    let rgb = data::composite_over(&img, [1.0; 3]);
    let mut painted = match grade {
        Some(g) => g.image(&rgb),
        None => paint::painterly(&rgb, w as usize, h as usize, seed),
    };
    let only = match (ids, mask) {
        (Some(ids), _) => Some(paint::object_mask(&ids, &objects, w, h)?),
        (None, Some(mask)) => Some(region::mask_region(&mask, w as usize, h as usize)?.inside),
        (None, None) => None,
    };
    if let Some(only) = only {
        painted = paint::only_where(&rgb, &painted, &only);
    }
    image::save_png(&out, w, h, &painted)?;
    println!("wrote {}", out.display());
    Ok(())
}

// `refnpr recolour`'s arguments.
#[derive(clap::Args)]
pub struct RecolourArgs {
    /// The dataset folder (Blender or procedural layout).
    #[arg(long)]
    pub data: PathBuf,
    /// The new folder.
    #[arg(long)]
    pub out: PathBuf,
    /// The colour grade, as `paint --grade` applies it.
    #[arg(long, value_enum)]
    pub grade: paint::Grade,
    /// Grade only these objects (ids of the procedural scene's `*_id.png`,
    /// as `paint --objects`): the intended result of a local edit.
    #[arg(long, value_delimiter = ',')]
    pub objects: Vec<u8>,
}

/// `refnpr recolour`: a dataset with every image graded (or only some objects' pixels).
pub fn recolour(args: RecolourArgs) -> Result<()> {
    let RecolourArgs { data, out, grade, objects } = args;
    let only = (!objects.is_empty()).then_some(&objects[..]);
    let done = paint::recolour_dataset(&data, &out, grade, only)?;
    println!("wrote {} with {} images graded ({grade:?})", out.display(), done.graded);
    if done.without_ids > 0 {
        println!("{} images have no object-id map beside them: copied unchanged", done.without_ids);
    }
    anyhow::ensure!(
        only.is_none() || done.graded > 0,
        "no image of {} has an object-id map (NAME_id.png) beside it: nothing was graded",
        data.display()
    );
    Ok(())
}

// `refnpr register`'s arguments.
#[derive(clap::Args)]
pub struct RegisterArgs {
    #[command(flatten)]
    pub inputs: PhotoAndCase,
    /// The folder to write: registration.bin, register.json, overlays/.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub params: RegisterParams,
    /// Overlay PNGs for the first N training views.
    #[arg(long, default_value_t = 8)]
    pub overlays: usize,
}

/// `refnpr register`: R³ alone, its file, report and overlays.
pub fn register(args: RegisterArgs, progress: &dyn Progress) -> Result<()> {
    let RegisterArgs { inputs, out, params, overlays } = args;
    let (ck, dataset) = load_run(&inputs.photo, inputs.data)?;
    let case = ReferenceCase::load(&inputs.reference)?;
    let r = registration::run_register(&ck, &dataset, &case, &params, &out, overlays, progress)?;
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

// `refnpr stylize`'s arguments.
#[derive(clap::Args)]
pub struct StylizeArgs {
    /// Photoreal run folder (or its checkpoint file), as `refnpr train --out` wrote it.
    #[arg(long = "run", alias = "photo", value_name = "RUN")]
    pub photo: PathBuf,
    /// Reference case folder (reference.toml or the authors' data_config.json); ARF can take --style alone.
    #[arg(long, required_unless_present = "style")]
    pub reference: Option<PathBuf>,
    /// Dataset folder (default: the one the photoreal run was trained on).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Output run folder: checkpoint.bin (renders like any run), stylize.json, test/ renders.
    #[arg(long)]
    pub out: PathBuf,
    /// TOML config; fields it leaves out take the defaults of configs/stylize.toml.
    #[arg(long, conflicts_with = "preset")]
    pub config: Option<PathBuf>,
    /// A named config instead of --config: paper (the defaults, 10 image epochs), fast (6), authors (their code's).
    #[arg(long, value_enum)]
    pub preset: Option<Preset>,
    /// refnpr (Ref-NPR, the paper's method) or arf (the ARF baseline: style statistics, no reference view).
    #[arg(long, value_enum, default_value_t = Method::RefNpr)]
    pub method: Method,
    /// ARF: a style image (any size) instead of the case's first reference; without --reference it
    /// becomes a case of its own in OUT/style_case.
    #[arg(long)]
    pub style: Option<PathBuf>,
    /// Stylization epochs ([schedule] image_epochs; the last quarter is the smooth update).
    #[arg(long = "image-epochs", alias = "epochs")]
    pub epochs: Option<usize>,
    /// The backend: flex (CPU, the default), ndarray (CPU) or wgpu (GPU).
    #[arg(long, value_enum, env = "REFNPR_BACKEND")]
    pub backend: Option<BackendKind>,
    /// Keep the photo's colours and take only the painting's light and dark ([controls] preserve_colour).
    #[arg(long)]
    pub preserve_colour: bool,
    /// 1 the stylized field, 0 the refit photo, between them the blend ([controls] style_strength).
    #[arg(long)]
    pub style_strength: Option<f32>,
    /// The painting's strokes this many times larger (1 to 4) ([controls] stroke_scale).
    #[arg(long)]
    pub stroke_scale: Option<f32>,
    /// Ref-NPR: R³, the refit and the image epochs on the training views this many times
    /// smaller, the smooth update at full size ([schedule] coarse_scale; 1: all at full size).
    #[arg(long)]
    pub coarse_scale: Option<u32>,
    /// The stylized colour on a lattice this many times finer per axis (1 to 3) than the
    /// photo grid's, the frozen density resampled with it ([top level] colour_grid_scale).
    #[arg(long)]
    pub colour_grid_scale: Option<u32>,
    /// With --coarse-scale: the smooth update's TCM matches found on the coarse views and
    /// carried to full size ([schedule] coarse_matches, on by default; false: matched again
    /// at full size).
    #[arg(long, num_args = 0..=1, default_missing_value = "true")]
    pub coarse_matches: Option<bool>,
    /// The run's memory budget in GB: the sample cache and the kept content features shrink
    /// to fit it, and a run that cannot fit is refused before the refit (memory_gb; 0: 90 %
    /// of the free memory).
    #[arg(long)]
    pub memory_gb: Option<f32>,
    /// Skip rendering the test views of the result.
    #[arg(long)]
    pub no_render: bool,
    /// Continue a killed run from OUT/resume.bin (written after the refit and every
    /// schedule.checkpoint_every image steps); the same command otherwise.
    #[arg(long)]
    pub resume: bool,
    /// A `refnpr register` output folder (or its registration.bin) to use instead of registering again.
    #[arg(long)]
    pub registration: Option<PathBuf>,
    /// R³ settings; a flag given here overrides the config file's [register].
    #[command(flatten)]
    pub register: RegisterParams,
}

/// `refnpr stylize`: the config file (or the defaults), then the flags the
/// user gave (`--epochs`, and any R³ flag over the file's `[register]`).
pub fn stylize(args: StylizeArgs, matches: &ArgMatches, progress: &Console) -> Result<()> {
    let StylizeArgs {
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
        preserve_colour,
        style_strength,
        stroke_scale,
        coarse_scale,
        colour_grid_scale,
        coarse_matches,
        memory_gb,
        no_render,
        resume,
        registration,
        register,
    } = args;
    let mut config = match preset {
        Some(p) => p.config()?,
        None => stylize_config(config.as_deref())?,
    };
    if let Some(e) = epochs {
        config.schedule.image_epochs = e;
    }
    config.controls.preserve_colour |= preserve_colour;
    config.controls.style_strength = style_strength.unwrap_or(config.controls.style_strength);
    config.controls.stroke_scale = stroke_scale.unwrap_or(config.controls.stroke_scale);
    config.schedule.coarse_scale = coarse_scale.unwrap_or(config.schedule.coarse_scale);
    config.schedule.coarse_matches = coarse_matches.unwrap_or(config.schedule.coarse_matches);
    config.colour_grid_scale = colour_grid_scale.unwrap_or(config.colour_grid_scale);
    config.memory_gb = memory_gb.unwrap_or(config.memory_gb);
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
pub fn style_only_case(style: &Path, out: &Path) -> Result<PathBuf> {
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
pub fn stylize_config(path: Option<&Path>) -> Result<StylizeConfig> {
    match path {
        Some(p) => StylizeConfig::from_file(p),
        None => Ok(StylizeConfig::default()),
    }
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
