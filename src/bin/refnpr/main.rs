//! The `refnpr` command line: parse the arguments, call the library, print
//! the result. One file per group of commands, in pipeline order (data in,
//! fit, reference and stylize, evaluate, out, the demo, developer tools),
//! each holding its commands' arguments beside the function that runs them;
//! this file holds the command list and the dispatch.

mod common;
mod data;
mod demo;
mod dev;
mod evaluate;
mod fit;
mod out;
mod stylize;

use anyhow::Result;
use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};
use refnpr::Console;
use refnpr::util::costs::Ledger;

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

#[derive(Subcommand)]
enum Command {
    /// Writes the built-in procedural scene (Blender layout, with depth, ids and a stylized twin).
    Scene(data::SceneArgs),
    /// A dataset from a folder of photos, through COLMAP (installed separately:
    /// `apt-get install colmap`): photos downsized, features, matching, mapping,
    /// undistortion; writes OUT/images/ and OUT/sparse/ for `train --data OUT`.
    Capture(data::CaptureArgs),
    /// Fits the photoreal radiance field of a dataset (Blender, LLFF, NSVF, COLMAP, transforms.json; detected).
    Train(fit::TrainArgs),
    /// Aligns each camera of a COLMAP capture around the scene to its photo with a field trained on it
    /// (its pose, and one focal length shared by all), and writes the dataset with the refined cameras:
    /// train again on OUT. COLMAP's poses of small or texture-poor photos are a fraction of a pixel off.
    RefinePoses(fit::RefinePosesArgs),
    /// Renders a run (photoreal or stylized) along a camera path: OUT/rgb/, OUT/depth/, OUT/path.gif.
    Render(fit::RenderArgs),
    /// A contact sheet of a run's views (training and test photos, frames of the render path), each labelled
    /// with the name `reference --view` takes: choose the view to paint by looking.
    Views(fit::ViewsArgs),
    /// Renders the content view I_R and its depth from a photoreal run and writes a
    /// reference-case skeleton: paint over OUT/content.png and save OUT/style.png.
    Reference(stylize::ReferenceArgs),
    /// A quick painterly repaint of an image (e.g. a reference case's content.png) to try stylization without painting.
    Paint(stylize::PaintArgs),
    /// Copies a dataset folder with every image colour-graded: the intended result of a
    /// reference graded the same way (`paint --grade`), for `eval --gt`.
    Recolour(stylize::RecolourArgs),
    /// R³: registers the stylized reference colours onto every training ray.
    Register(stylize::RegisterArgs),
    /// Stylizes a photoreal run after a reference case (Ref-NPR), or after a style image (ARF).
    Stylize(stylize::StylizeArgs),
    /// Stylization metrics of a stylized run (with --reference), or PSNR / SSIM of a run's test views.
    Eval(evaluate::EvalArgs),
    /// LPIPS (v0.1, as the `lpips` package computes it) between two images: B is resized to A's size when they differ.
    Lpips(evaluate::LpipsArgs),
    /// Exports a run's field for other tools: Gaussian splats (3DGS PLY), a coloured mesh (glb or PLY), an MP4, surface points.
    Export(out::ExportArgs),
    /// Shows runs in the browser: a local page that ray-marches the field in WebGL2 as refnpr renders it,
    /// reloading a run whose checkpoint changes (a fit or a stylization in progress).
    View(out::ViewArgs),
    /// The whole method on the built-in scene: writes it, fits the photoreal field, paints view 0 from the
    /// scene's stylized twin, stylizes, renders orbits of both fields and scores the result against the twin.
    Demo(demo::DemoArgs),
    /// Renderer throughput (rays/s, forward and forward+backward) per backend and resolution.
    #[command(hide = true)]
    Bench(dev::BenchArgs),
    /// VGG16 forward and forward+backward milliseconds per backend and image size, with
    /// onnxruntime's CPU forward on the same input as a yardstick.
    #[command(hide = true)]
    BenchVgg(dev::BenchVggArgs),
    /// A short stylization (a fraction of a refit epoch, one image epoch and, for Ref-NPR,
    /// one smooth epoch) timed step by step: seconds per step and where they go, per phase.
    #[command(hide = true)]
    BenchStylize(dev::BenchStylizeArgs),
    /// Feeds a parser of outside input (or the command line itself) mutated real files
    /// for a while: no input may panic or hang.
    #[command(hide = true)]
    Fuzz(dev::FuzzArgs),
    /// What this build runs on: backends, wgpu adapters, CPU threads and SIMD, memory, VGG16 weights.
    #[command(hide = true)]
    Info(dev::InfoArgs),
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
        Command::Scene(args) => data::scene(args),
        Command::Capture(args) => data::capture(args, &progress),
        Command::Train(args) => fit::train(args, &progress),
        Command::RefinePoses(args) => fit::refine_poses(args, &progress),
        Command::Render(args) => fit::render(args, &progress),
        Command::Views(args) => fit::views(args, &progress),
        Command::Reference(args) => stylize::reference(args),
        Command::Paint(args) => stylize::paint(args),
        Command::Recolour(args) => stylize::recolour(args),
        Command::Register(args) => stylize::register(args, &progress),
        Command::Stylize(args) => {
            let matches = matches.subcommand_matches("stylize").expect("the stylize subcommand was parsed");
            stylize::stylize(args, matches, &progress)
        }
        Command::Eval(args) => evaluate::eval(args, &progress),
        Command::Lpips(args) => evaluate::lpips(args, &progress),
        Command::Export(args) => out::export(args, &progress),
        Command::View(args) => out::view(args, &progress),
        Command::Demo(args) => demo::demo(args, &progress),
        Command::Bench(args) => dev::bench(args),
        Command::BenchVgg(args) => dev::bench_vgg(args),
        Command::BenchStylize(args) => dev::bench_stylize(args, &progress),
        Command::Fuzz(args) => dev::fuzz(args),
        Command::Info(args) => dev::info(args),
    }
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
    use std::path::Path;

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
        let Ok(Command::Stylize(stylize::StylizeArgs { epochs, register, .. })) =
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
        let config: toml::Table = toml::from_str(include_str!("../../../configs/stylize.toml")).expect("stylize.toml");
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
        let case = stylize::style_only_case(&t.join("s.png"), &t.join("out")).unwrap();
        let toml = std::fs::read_to_string(case.join("reference.toml")).unwrap();
        assert!(toml.contains("style = \"style.png\"") && toml.contains("train:0"), "{toml}");
        assert!(case.join("style.png").is_file());
        std::fs::remove_dir_all(&t).ok();
    }

    /// The run folder a parsed command names.
    fn run_of(command: &Command) -> Option<&Path> {
        match command {
            Command::Render(fit::RenderArgs { ckpt, .. }) => Some(ckpt),
            Command::Reference(stylize::ReferenceArgs { ckpt, .. }) => Some(ckpt),
            Command::Stylize(stylize::StylizeArgs { photo, .. }) => Some(photo),
            Command::Register(stylize::RegisterArgs { inputs, .. }) => Some(&inputs.photo),
            Command::Eval(evaluate::EvalArgs { run, .. }) => Some(run),
            _ => None,
        }
    }
}
