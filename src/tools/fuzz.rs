//! Fuzzing on stable Rust: every parser of outside input is fed mutations of
//! real files (bit flips, interesting numbers, cut, repeated and spliced
//! pieces) and must answer with `Ok` or an error, never a panic, a hang or a
//! huge allocation. No nightly toolchain or coverage instrumentation is
//! needed: the mutations are structure-aware enough (numbers in text are
//! replaced by edge values, length fields by huge ones) to reach the checks
//! behind the syntax. `refnpr fuzz TARGET` runs one target for a while (the
//! script `scripts/fuzz.sh`); the test suite runs every target briefly.

use std::cell::{Cell, RefCell};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Once};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use glam::{Mat4, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::field::checkpoint::{self, CheckpointMeta};
use crate::field::grid::{GridGeometry, RadianceGrid};
use crate::photo::config::TrainConfig;
use crate::reference::case::{ReferenceCase, read_style};
use crate::reference::r3::{RegisterParams, ViewRegistration};
use crate::reference::registration::{NamedRegistration, PhotoRun, ReferencePixels, RegistrationFile};
use crate::scene::camera::{Camera, Intrinsics};
use crate::scene::data::{self, DatasetKind, colmap_model, procedural, transforms};
use crate::stylize::config::StylizeConfig;
use crate::util::backend::BackendKind;
use crate::util::{files, npy};

/// What one case does with its input: anything but a panic is fine.
pub type Check = Box<dyn Fn(&[u8]) + Send + Sync>;

/// A parser under test: real inputs to start from, and the call.
pub struct Target {
    pub name: String,
    pub seeds: Vec<Vec<u8>>,
    pub check: Check,
}

/// How long to fuzz, and the bounds a case must keep.
#[derive(Debug, Clone)]
pub struct Limits {
    pub max_cases: u64,
    pub max_seconds: f64,
    /// A case running longer is a hang: the input is saved and the process stops.
    pub case_seconds: f64,
    pub seed: u64,
}

/// Panics at one place in the code: how many inputs hit it, the first one
/// saved to `input` for replay.
#[derive(Debug, Clone, Serialize)]
pub struct Crash {
    /// The panic's message and where it was raised.
    pub message: String,
    pub count: u64,
    pub input: PathBuf,
}

thread_local! {
    /// Whether this thread is running fuzz cases (its panics are recorded, not printed).
    static FUZZING: Cell<bool> = const { Cell::new(false) };
    /// The last panic's message and location on this thread.
    static LAST_PANIC: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Marks this thread as fuzzing until dropped (also on an early return).
struct FuzzingThread;

impl FuzzingThread {
    fn start() -> Self {
        FUZZING.with(|f| f.set(true));
        Self
    }
}

impl Drop for FuzzingThread {
    fn drop(&mut self) {
        FUZZING.with(|f| f.set(false));
    }
}

/// Installs, once per process, a panic hook that records the panics of
/// fuzzing threads and passes every other panic to the hook before it (so
/// concurrent tests keep their own panic messages).
fn install_panic_hook() {
    static INSTALLED: Once = Once::new();
    INSTALLED.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !FUZZING.with(Cell::get) {
                return previous(info);
            }
            let place = info.location().map(|l| format!(" at {}:{}", l.file(), l.line())).unwrap_or_default();
            let message = format!("{}{place}", panic_text(info.payload()));
            LAST_PANIC.with(|p| *p.borrow_mut() = Some(message));
        }));
    });
}

#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub target: String,
    pub cases: u64,
    pub seconds: f64,
    pub crashes: Vec<Crash>,
    pub slowest_case_ms: f64,
    /// The process's peak resident memory (`VmHWM`) at the end.
    pub peak_rss_mb: Option<f64>,
}

/// Where crashing and hanging inputs are saved.
pub fn crash_dir() -> PathBuf {
    std::env::temp_dir().join("refnpr-fuzz-crashes")
}

/// Runs `target` on mutated seeds until a limit. Panics are caught and
/// reported; a case over `case_seconds` saves its input and exits the
/// process with status 3 (a hang cannot be interrupted from outside).
pub fn run(target: &Target, limits: &Limits) -> Result<Report> {
    if target.seeds.is_empty() {
        bail!("fuzz target {} has no seed inputs", target.name);
    }
    let started = Instant::now();
    let mut rng = ChaCha8Rng::seed_from_u64(limits.seed);
    let current = Arc::new(Mutex::new(Vec::new()));
    let case_started_ms = Arc::new(AtomicU64::new(u64::MAX));
    let done = Arc::new(AtomicBool::new(false));
    let watchdog = spawn_watchdog(&target.name, limits.case_seconds, started, &current, &case_started_ms, &done);
    install_panic_hook();
    let _fuzzing = FuzzingThread::start();
    let (mut crashes, mut cases, mut slowest) = (Vec::new(), 0u64, Duration::ZERO);
    while cases < limits.max_cases && started.elapsed().as_secs_f64() < limits.max_seconds {
        let input = mutate(&target.seeds, &mut rng);
        current.lock().unwrap().clone_from(&input);
        let t = Instant::now();
        case_started_ms.store(started.elapsed().as_millis() as u64, Ordering::SeqCst);
        let outcome = catch_unwind(AssertUnwindSafe(|| (target.check)(&input)));
        case_started_ms.store(u64::MAX, Ordering::SeqCst);
        slowest = slowest.max(t.elapsed());
        cases += 1;
        if outcome.is_err() {
            let message = LAST_PANIC.with(|p| p.borrow_mut().take()).unwrap_or_default();
            match crashes.iter_mut().find(|c: &&mut Crash| c.message == message) {
                Some(c) => c.count += 1,
                None => {
                    let input = save_input(&target.name, "crash", &input)?;
                    crashes.push(Crash { message, count: 1, input });
                }
            }
        }
    }
    done.store(true, Ordering::SeqCst);
    watchdog.join().ok();
    Ok(Report {
        target: target.name.clone(),
        cases,
        seconds: started.elapsed().as_secs_f64(),
        crashes,
        slowest_case_ms: slowest.as_secs_f64() * 1e3,
        peak_rss_mb: crate::util::memory::peak_rss_mb(),
    })
}

fn spawn_watchdog(
    name: &str,
    case_seconds: f64,
    started: Instant,
    current: &Arc<Mutex<Vec<u8>>>,
    case_started_ms: &Arc<AtomicU64>,
    done: &Arc<AtomicBool>,
) -> std::thread::JoinHandle<()> {
    let (name, current, case_started_ms, done) =
        (name.to_string(), current.clone(), case_started_ms.clone(), done.clone());
    let limit_ms = (case_seconds * 1e3) as u64;
    std::thread::spawn(move || {
        while !done.load(Ordering::SeqCst) {
            std::thread::sleep(Duration::from_millis(50));
            let since = case_started_ms.load(Ordering::SeqCst);
            let now = started.elapsed().as_millis() as u64;
            if since != u64::MAX && now.saturating_sub(since) > limit_ms {
                let input = current.lock().map(|i| i.clone()).unwrap_or_default();
                let saved = save_input(&name, "hang", &input).map(|p| p.display().to_string());
                // Library code reports through `Progress`; a hang has no
                // caller left to report to, so it goes to stderr and exits.
                #[allow(clippy::print_stderr)]
                {
                    eprintln!(
                        "fuzz target {name}: a case ran over {case_seconds} s (a hang); input saved as {saved:?}"
                    );
                }
                std::process::exit(3);
            }
        }
    })
}

fn panic_text(panic: &(dyn std::any::Any + Send)) -> String {
    panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic without a message".into())
}

fn save_input(target: &str, kind: &str, input: &[u8]) -> Result<PathBuf> {
    let hash = input.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3));
    let path = crash_dir().join(format!("{target}-{kind}-{hash:016x}.bin"));
    files::write_bytes(&path, input)?;
    Ok(path)
}

/// Text numbers a parser should refuse or survive.
const NUMBERS: &[&str] = &[
    "0",
    "-0",
    "1",
    "-1",
    "2",
    "255",
    "256",
    "65535",
    "65536",
    "4294967295",
    "4294967296",
    "2147483648",
    "9223372036854775807",
    "18446744073709551616",
    "1000000000000",
    "1e308",
    "-1e308",
    "1e-320",
    "NaN",
    "inf",
    "-inf",
    "0.0",
    "1.5",
    "3.4e38",
    "99999999999999999999999",
];
/// Binary values for length and count fields.
const WORDS: &[u64] =
    &[0, 1, 0xff, 0xffff, 0x7fff_ffff, 0xffff_ffff, 1 << 32, 1_000_000_000_000, u64::MAX / 2, u64::MAX];
/// Bytes that are syntax in the formats we read.
const BYTES: &[u8] = b"\0\x01\x7f\x80\xff0-.,:;[]{}()\"'=\n #e";

/// One mutated input: a seed with 1 to 8 mutations.
fn mutate(seeds: &[Vec<u8>], rng: &mut ChaCha8Rng) -> Vec<u8> {
    let mut input = seeds[rng.random_range(0..seeds.len())].clone();
    let n = 1usize << rng.random_range(0..4);
    for _ in 0..n {
        mutate_once(&mut input, seeds, rng);
    }
    input
}

fn mutate_once(input: &mut Vec<u8>, seeds: &[Vec<u8>], rng: &mut ChaCha8Rng) {
    let len = input.len();
    let pos = |rng: &mut ChaCha8Rng| if len == 0 { 0 } else { rng.random_range(0..len) };
    match rng.random_range(0..9) {
        0 if len > 0 => {
            let i = pos(rng);
            input[i] ^= 1 << rng.random_range(0..8);
        }
        1 if len > 0 => {
            let i = pos(rng);
            input[i] = BYTES[rng.random_range(0..BYTES.len())];
        }
        2 if len > 0 => {
            let i = pos(rng);
            let n = rng.random_range(1..=16).min(len - i);
            input.drain(i..i + n);
        }
        3 => {
            let i = pos(rng);
            let bytes: Vec<u8> = (0..rng.random_range(1..=16)).map(|_| rng.random()).collect();
            input.splice(i..i, bytes);
        }
        4 if len > 0 => {
            let (i, j) = (pos(rng), pos(rng));
            let n = rng.random_range(1..=64).min(len - i);
            let piece = input[i..i + n].to_vec();
            input.splice(j..j, piece);
        }
        5 if len > 0 => input.truncate(pos(rng)),
        6 => replace_number(input, rng),
        7 => {
            let other = &seeds[rng.random_range(0..seeds.len())];
            if !other.is_empty() {
                let i = rng.random_range(0..other.len());
                let n = rng.random_range(1..=64).min(other.len() - i);
                let at = pos(rng);
                input.splice(at..at, other[i..i + n].iter().copied());
            }
        }
        _ if len >= 8 => {
            let w = WORDS[rng.random_range(0..WORDS.len())];
            let width = if rng.random() { 8 } else { 4 };
            let i = rng.random_range(0..=len - width);
            input[i..i + width].copy_from_slice(&w.to_le_bytes()[..width]);
        }
        _ => input.push(rng.random()),
    }
}

/// Replaces a run of number characters (digits, '.', '-', 'e') with an
/// interesting number; appends one where the input has none.
fn replace_number(input: &mut Vec<u8>, rng: &mut ChaCha8Rng) {
    let is_num = |b: u8| b.is_ascii_digit() || b == b'.' || b == b'-';
    let starts: Vec<usize> =
        (0..input.len()).filter(|&i| is_num(input[i]) && (i == 0 || !is_num(input[i - 1]))).collect();
    let new = NUMBERS[rng.random_range(0..NUMBERS.len())].as_bytes();
    match starts.len() {
        0 => input.extend_from_slice(new),
        n => {
            let s = starts[rng.random_range(0..n)];
            let mut e = s;
            while e < input.len() && (is_num(input[e]) || input[e] == b'e') {
                e += 1;
            }
            input.splice(s..e, new.iter().copied());
        }
    }
}

/// The names of the library's fuzz targets.
pub const TARGETS: &[&str] = &[
    "npy",
    "transforms",
    "reference_toml",
    "data_config",
    "train_config",
    "stylize_config",
    "checkpoint",
    "registration",
    "image",
    "poses_bounds",
    "nsvf_intrinsics",
    "nsvf_pose",
    "nsvf_bbox",
    "colmap_cameras_bin",
    "colmap_images_bin",
    "colmap_points3d_bin",
    "colmap_cameras_txt",
    "colmap_images_txt",
    "colmap_points3d_txt",
    "transforms_json",
];

/// Seeds and a check: what a target is made of.
type Seeded = (Vec<Vec<u8>>, Check);
/// A real file of `../shared/data` by its relative path, when present.
type Real<'r> = dyn Fn(&str) -> std::io::Result<Option<Vec<u8>>> + 'r;

/// Builds target `name`. `scratch` is a private folder for files the
/// parsers read; `shared_data` (`../shared/data`), when present, adds real
/// files to the seeds.
pub fn target(name: &str, scratch: &Path, shared_data: Option<&Path>) -> Result<Target> {
    files::create_dir(scratch)?;
    let real = |rel: &str| shared_data.map(|d| d.join(rel)).filter(|p| p.exists()).map(std::fs::read).transpose();
    let (seeds, check) = match name {
        "npy" | "transforms" | "poses_bounds" | "nsvf_intrinsics" | "nsvf_pose" | "nsvf_bbox" => {
            dataset_files(name, scratch, &real)?
        }
        "reference_toml" | "data_config" | "train_config" | "stylize_config" => {
            case_and_config_files(name, scratch, &real)?
        }
        "checkpoint" | "registration" | "image" => binary_files(name, scratch)?,
        n if n.starts_with("colmap_") => colmap_files(n, scratch)?,
        "transforms_json" => transforms_json(),
        other => bail!("no fuzz target '{other}' (targets: {}, cli)", TARGETS.join(", ")),
    };
    Ok(Target { name: name.to_string(), seeds, check })
}

/// Seeds and checks of the dataset files' targets (npy, transforms.json,
/// poses_bounds.npy, NSVF's text files).
fn dataset_files(name: &str, scratch: &Path, real: &Real) -> Result<Seeded> {
    let seeded: Seeded = match name {
        "npy" => {
            let mut seeds =
                vec![npy_bytes(scratch, &[2, 3])?, npy_bytes(scratch, &[4])?, npy_bytes(scratch, &[1, 17])?];
            seeds.extend(real("nerf_llff_data/fern/poses_bounds.npy")?);
            (seeds, Box::new(|b| drop(npy::parse(b))))
        }
        "transforms" => {
            let scene = tiny_scene(scratch)?;
            let mut seeds = vec![std::fs::read(scene.join("transforms_train.json"))?];
            seeds.extend(real("nerf_synthetic/lego/transforms_train.json")?.map(|b| b[..b.len().min(4096)].to_vec()));
            let file = scene.join("transforms_train.json");
            (seeds, Box::new(move |b| parse_file(&file, b, || data::load(&scene, &Default::default()).map(drop))))
        }
        "poses_bounds" => {
            let dir = tiny_llff(scratch)?;
            let file = dir.join("poses_bounds.npy");
            let mut seeds = vec![std::fs::read(&file)?];
            seeds.extend(real("nerf_llff_data/fern/poses_bounds.npy")?);
            (seeds, Box::new(move |b| parse_file(&file, b, || data::load(&dir, &Default::default()).map(drop))))
        }
        "nsvf_intrinsics" | "nsvf_pose" | "nsvf_bbox" => {
            let dir = tiny_nsvf(scratch)?;
            let file = match name {
                "nsvf_intrinsics" => dir.join("intrinsics.txt"),
                "nsvf_pose" => dir.join("pose").join("0_000.txt"),
                _ => dir.join("bbox.txt"),
            };
            let mut seeds = vec![std::fs::read(&file)?];
            if name == "nsvf_intrinsics" {
                seeds.push(b"10 4 3 0\n0 0 0\n1\n".to_vec()); // the DeepVoxels form
            }
            (seeds, Box::new(move |b| parse_file(&file, b, || data::load(&dir, &Default::default()).map(drop))))
        }
        _ => unreachable!("not a dataset files target: {name}"),
    };
    Ok(seeded)
}

/// Seeds and checks of the reference cases' and configs' targets.
fn case_and_config_files(name: &str, scratch: &Path, real: &Real) -> Result<Seeded> {
    let seeded: Seeded = match name {
        "reference_toml" => {
            let (dir, dataset) = (scratch.to_path_buf(), data::load(&tiny_scene(scratch)?, &Default::default())?);
            let seeds = [
                "[[reference]]\nstyle = \"style.png\"\nview = \"train:1\"\n",
                "color_pre = false\npath_frames = 60\nscene_name = \"tiny\"\n[[reference]]\nstyle = \"a.png\"\nview = \"path:12\"\n[[reference]]\nstyle = \"b.png\"\nview = \"test:0\"\n",
                "[[reference]]\nstyle = \"s.png\"\nc2w = [[1.0,0.0,0.0,0.0],[0.0,1.0,0.0,0.0],[0.0,0.0,1.0,3.0],[0.0,0.0,0.0,1.0]]\nintrinsics = { width = 8, height = 8, fx = 10.0, fy = 10.0, cx = 4.0, cy = 4.0 }\n",
            ];
            let check: Check = Box::new(move |b| {
                let text = String::from_utf8_lossy(b);
                if let Ok(case) = ReferenceCase::from_toml(&dir, &text) {
                    drop(case.cameras(&dataset));
                }
            });
            (seeds.iter().map(|s| s.as_bytes().to_vec()).collect(), check)
        }
        "data_config" => {
            let (dir, dataset) = (scratch.to_path_buf(), data::load(&tiny_scene(scratch)?, &Default::default())?);
            let mut seeds: Vec<Vec<u8>> = [
                r#"{"style_img": "style.png", "tmpl_idx_train": 1, "tmpl_idx_test": null, "color_pre": true, "scene_name": "tiny"}"#,
                r#"{"style_img": ["a.png", "b.png"], "tmpl_idx_train": null, "tmpl_idx_test": [3, 40], "style_name": "x"}"#,
            ]
            .iter()
            .map(|s| s.as_bytes().to_vec())
            .collect();
            seeds.extend(real("ref_case/flower_colorful/data_config.json")?);
            let check: Check = Box::new(move |b| {
                if let Ok(case) = ReferenceCase::from_json(&dir, &String::from_utf8_lossy(b)) {
                    drop(case.cameras(&dataset));
                }
            });
            (seeds, check)
        }
        "train_config" => {
            let seeds = [
                include_str!("../../configs/blender.toml"),
                include_str!("../../configs/llff.toml"),
                include_str!("../../configs/demo.toml"),
            ];
            let check: Check = Box::new(|b| {
                let base = TrainConfig::for_kind(DatasetKind::Blender);
                drop(TrainConfig::from_toml_str(&String::from_utf8_lossy(b), &base, "fuzz.toml"));
            });
            (seeds.iter().map(|s| s.as_bytes().to_vec()).collect(), check)
        }
        "stylize_config" => {
            let seeds = [include_str!("../../configs/stylize.toml"), include_str!("../../configs/demo_stylize.toml")];
            let check: Check =
                Box::new(|b| drop(StylizeConfig::from_toml_str(&String::from_utf8_lossy(b), "fuzz.toml")));
            (seeds.iter().map(|s| s.as_bytes().to_vec()).collect(), check)
        }
        _ => unreachable!("not a case and config files target: {name}"),
    };
    Ok(seeded)
}

/// Seeds and checks of the checkpoint, registration and image targets.
fn binary_files(name: &str, scratch: &Path) -> Result<Seeded> {
    let seeded: Seeded = match name {
        "checkpoint" => {
            let file = scratch.join(checkpoint::CHECKPOINT_FILE);
            write_tiny_checkpoint(&file)?;
            let seeds = vec![std::fs::read(&file)?];
            let check: Check = Box::new(move |b| {
                parse_file(&file, b, || checkpoint::load(&file, &BackendKind::Flex.device()).map(drop));
            });
            (seeds, check)
        }
        "registration" => {
            let file = scratch.join("registration.bin");
            tiny_registration().save(&file)?;
            let seeds = vec![std::fs::read(&file)?];
            (seeds, Box::new(move |b| parse_file(&file, b, || RegistrationFile::load(&file).map(drop))))
        }
        "image" => {
            let seeds = image_seeds()?;
            let file = scratch.join("style.png");
            let check: Check = Box::new(move |b| {
                parse_file(&file, b, || {
                    read_style(&file, 8, 8, [1.0; 3])?;
                    data::read_rgb(&file, [1.0; 3], 2).map(drop)
                })
            });
            (seeds, check)
        }
        _ => unreachable!("not a binary files target: {name}"),
    };
    Ok(seeded)
}

/// A small COLMAP model (two cameras, two images, two points).
fn tiny_colmap_model() -> colmap_model::Model {
    let text_cams = "1 OPENCV 40 30 50 51 20 15 0.01 -0.002 0.001 0.0005\n2 SIMPLE_RADIAL 40 30 45 20 15 0.02\n";
    let text_imgs = "1 1 0 0 0 0.5 -0.25 2 1 a.png\n10 20 3 30 40 4 50 60 -1\n2 0.7071 0 0.7071 0 0 0 1 2 b.png\n\n";
    let text_pts = "3 0.1 0.2 0.3 255 0 0 0.5 1 0 2 0\n4 -1 2 -3 0 0 0 0.1 1 1\n";
    let parse = |name: &str, text: &str| colmap_model::parse_file(name, text.as_bytes()).expect("a valid seed");
    parse("cameras.txt", text_cams);
    parse("images.txt", text_imgs);
    parse("points3D.txt", text_pts);
    colmap_model::Model::from_text(text_cams, text_imgs, text_pts).expect("a valid seed")
}

/// Seeds and checks of the COLMAP model files' targets: the text seeds as
/// COLMAP writes them (comments, an image without keypoints), the binary
/// seeds the same model written in binary.
fn colmap_files(name: &str, scratch: &Path) -> Result<Seeded> {
    let file = match name {
        "colmap_cameras_bin" => "cameras.bin",
        "colmap_images_bin" => "images.bin",
        "colmap_points3d_bin" => "points3D.bin",
        "colmap_cameras_txt" => "cameras.txt",
        "colmap_images_txt" => "images.txt",
        "colmap_points3d_txt" => "points3D.txt",
        other => bail!("no fuzz target '{other}' (targets: {})", TARGETS.join(", ")),
    };
    let dir = scratch.join("colmap");
    colmap_model::write_binary(&tiny_colmap_model(), &dir)?;
    colmap_model::write_text(&tiny_colmap_model(), &dir)?;
    let seeds = vec![std::fs::read(dir.join(file))?];
    Ok((seeds, Box::new(move |b| drop(colmap_model::parse_file(file, b)))))
}

/// Seeds and check of nerfstudio's / instant-ngp's `transforms.json`.
fn transforms_json() -> Seeded {
    let seeds = [
        r#"{"camera_model": "OPENCV", "fl_x": 50.5, "fl_y": 51, "cx": 20, "cy": 15, "w": 40, "h": 30, "k1": 0.01,
        "k2": -0.002, "p1": 0.001, "p2": 0.0005, "applied_transform": [[0,1,0,0],[1,0,0,0],[0,0,-1,0]],
        "frames": [{"file_path": "images/a.png", "mask_path": "masks/a.png",
        "transform_matrix": [[1,0,0,0.5],[0,0,-1,-2],[0,1,0,0.3],[0,0,0,1]]},
        {"file_path": "./images/b.png", "fl_x": 49, "transform_matrix": [[0,0,1,2],[1,0,0,0],[0,1,0,0.3],[0,0,0,1]]}],
        "train_filenames": ["images/a.png"], "test_filenames": ["images/b.png"]}"#,
        r#"{"camera_angle_x": 0.69, "aabb_scale": 16, "frames": [{"file_path": "x",
        "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]}]}"#,
    ];
    (
        seeds.iter().map(|s| s.as_bytes().to_vec()).collect(),
        Box::new(|b| drop(transforms::parse_text(&String::from_utf8_lossy(b)))),
    )
}

/// Writes `bytes` to `file`, then runs the parser that reads it.
fn parse_file(file: &Path, bytes: &[u8], parse: impl FnOnce() -> Result<()>) {
    if std::fs::write(file, bytes).is_ok() {
        drop(parse());
    }
}

fn npy_bytes(scratch: &Path, shape: &[usize]) -> Result<Vec<u8>> {
    let path = scratch.join("seed.npy");
    let data: Vec<f32> = (0..shape.iter().product::<usize>()).map(|i| i as f32 * 0.5).collect();
    npy::write_f32(&path, shape, &data)?;
    std::fs::read(&path).with_context(|| format!("reading {}", path.display()))
}

/// The procedural scene at 8x8 pixels, 2 training views: a real Blender
/// folder that loads in milliseconds.
fn tiny_scene(scratch: &Path) -> Result<PathBuf> {
    let dir = scratch.join("scene");
    if !dir.join("transforms_train.json").exists() {
        let opts =
            procedural::SceneOptions { seed: 1, size: 8, num_train: 2, num_val: 1, num_test: 1, environment: false };
        procedural::write_scene(&dir, &opts)?;
    }
    Ok(dir)
}

/// An LLFF folder: 3 images of 4x3 pixels and their `poses_bounds.npy`.
fn tiny_llff(scratch: &Path) -> Result<PathBuf> {
    let dir = scratch.join("llff");
    let mut poses = Vec::new();
    for i in 0..3 {
        // Columns [down, right, back] then [h, w, f]; then near and far.
        let rows = [[0.0, 1.0, 0.0, 0.1 * i as f32, 3.0], [-1.0, 0.0, 0.0, 0.0, 4.0], [0.0, 0.0, 1.0, 0.0, 5.0]];
        poses.extend(rows.iter().flatten());
        poses.extend([2.0, 20.0]);
        let img = image::RgbImage::from_pixel(4, 3, image::Rgb([10, 20, 30 * i as u8]));
        crate::util::image::write_png(&dir.join("images").join(format!("image{i:03}.png")), img)?;
    }
    npy::write_f32(&dir.join("poses_bounds.npy"), &[3, 17], &poses)?;
    Ok(dir)
}

/// An NSVF folder: 3 images (train, val, test), poses, intrinsics, box.
fn tiny_nsvf(scratch: &Path) -> Result<PathBuf> {
    let dir = scratch.join("nsvf");
    files::write_text(&dir.join("intrinsics.txt"), "10 0 4 0\n0 10 3 0\n0 0 1 0\n0 0 0 1\n")?;
    files::write_text(&dir.join("bbox.txt"), "-2 -2 -2 2 2 2 0.1\n")?;
    for (i, name) in ["0_000", "1_000", "2_000"].iter().enumerate() {
        let img = image::RgbImage::from_pixel(8, 6, image::Rgb([1, 2, 3]));
        crate::util::image::write_png(&dir.join("rgb").join(format!("{name}.png")), img)?;
        let pose = format!("1 0 0 0\n0 1 0 0\n0 0 1 {}\n0 0 0 1\n", 4 + i);
        files::write_text(&dir.join("pose").join(format!("{name}.txt")), &pose)?;
    }
    Ok(dir)
}

fn tiny_camera() -> Camera {
    let k = Intrinsics { width: 8, height: 8, fx: 10.0, fy: 10.0, cx: 4.0, cy: 4.0 };
    Camera::new(k, Mat4::from_translation(Vec3::new(0.0, 0.0, 3.0)))
}

fn write_tiny_checkpoint(file: &Path) -> Result<()> {
    let geometry = GridGeometry { res: [4, 4, 4], bbox_min: Vec3::splat(-1.0), bbox_max: Vec3::splat(1.0) };
    let coords = vec![0, 5, 21, 63];
    let density = vec![0.5, 1.0, 2.0, 0.0];
    let sh: Vec<f32> = (0..coords.len() * 12).map(|i| i as f32 * 0.1).collect();
    let device = BackendKind::Flex.device();
    let mut grid = RadianceGrid::from_rows(geometry, 1, coords, density, sh, &device);
    // A far background too, so that its tensor's header and values are mutated.
    grid.far = Some(crate::field::environment::Environment::uniform(4, 2, [0.3, 0.5, 0.7]));
    let config = TrainConfig::for_kind(DatasetKind::Blender);
    let meta = CheckpointMeta {
        step: 3,
        geometry,
        sh_degree: 1,
        ndc: None,
        kind: DatasetKind::Blender,
        background: [1.0; 3],
        near_far: None,
        data_dir: PathBuf::from("scene"),
        render: config.render_settings(),
        data: config.data,
        run_config: serde_json::to_value(&config)?,
        train_seconds: 1.0,
    };
    let zeros = |cols: usize| crate::util::tensor::floats(vec![0.0; 4 * cols], [4, cols], &device);
    checkpoint::save(file, &meta, &grid, &zeros(1), &zeros(12), &[0.01; 24])
}

fn tiny_registration() -> RegistrationFile {
    let registration = ViewRegistration {
        width: 8,
        height: 8,
        pixels: vec![1, 9, 40],
        colours: vec![[0.1, 0.2, 0.3]; 3],
        reference: vec![0; 3],
        hits: 50,
    };
    RegistrationFile {
        photo: PhotoRun { file: PathBuf::from("photo/checkpoint.bin"), fingerprint: 7 },
        params: RegisterParams::default(),
        references: vec![ReferencePixels { camera: tiny_camera(), colours: vec![[0.5; 3]; 64], hits: vec![true; 64] }],
        views: vec![NamedRegistration { name: "r_0".into(), registration }],
    }
}

/// PNGs of every layout a user's tool may write: RGB, RGBA, grey, grey +
/// alpha, 16-bit, odd sizes; 8x8 (the reference size) and others.
fn image_seeds() -> Result<Vec<Vec<u8>>> {
    use image::{DynamicImage, ImageBuffer, ImageFormat};
    let rgb = ImageBuffer::from_fn(8, 8, |x, y| image::Rgb([(x * 30) as u8, (y * 30) as u8, 7]));
    let images = [
        DynamicImage::ImageRgb8(rgb.clone()),
        DynamicImage::ImageRgba8(DynamicImage::ImageRgb8(rgb.clone()).to_rgba8()),
        DynamicImage::ImageLuma8(DynamicImage::ImageRgb8(rgb.clone()).to_luma8()),
        DynamicImage::ImageLumaA8(DynamicImage::ImageRgb8(rgb.clone()).to_luma_alpha8()),
        DynamicImage::ImageRgb16(DynamicImage::ImageRgb8(rgb.clone()).to_rgb16()),
        DynamicImage::ImageRgb8(image::imageops::resize(&rgb, 5, 3, image::imageops::FilterType::Nearest)),
        DynamicImage::ImageRgba16(DynamicImage::ImageRgb8(rgb).to_rgba16()),
    ];
    let mut seeds = images
        .iter()
        .map(|img| {
            let mut bytes = std::io::Cursor::new(Vec::new());
            img.write_to(&mut bytes, ImageFormat::Png).context("encoding a seed PNG")?;
            Ok(bytes.into_inner())
        })
        .collect::<Result<Vec<_>>>()?;
    seeds.push(palette_png().context("encoding a palette seed PNG")?);
    Ok(seeds)
}

/// An 8x8 palette PNG with a transparent entry (what some paint tools save).
fn palette_png() -> std::result::Result<Vec<u8>, png::EncodingError> {
    let mut bytes = Vec::new();
    let mut enc = png::Encoder::new(&mut bytes, 8, 8);
    enc.set_color(png::ColorType::Indexed);
    enc.set_depth(png::BitDepth::Eight);
    enc.set_palette(vec![255, 0, 0, 0, 255, 0, 0, 0, 255, 9, 9, 9]);
    enc.set_trns(vec![255, 255, 128, 0]);
    let mut w = enc.write_header()?;
    w.write_image_data(&(0..64).map(|i| (i % 4) as u8).collect::<Vec<_>>())?;
    w.finish()?;
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The fixtures load: the fuzzer starts from inputs that reach the
    /// parsers' ends, not from ones refused at once.
    #[test]
    fn the_seed_folders_and_files_are_accepted() {
        let scratch = std::env::temp_dir().join(format!("refnpr-fuzz-seeds-{}", std::process::id()));
        let llff = data::load(&tiny_llff(&scratch).unwrap(), &Default::default()).unwrap();
        assert_eq!(llff.kind, DatasetKind::Llff);
        let nsvf = data::load(&tiny_nsvf(&scratch).unwrap(), &Default::default()).unwrap();
        assert_eq!((nsvf.kind, nsvf.train.len()), (DatasetKind::Nsvf, 1));
        data::load(&tiny_scene(&scratch).unwrap(), &Default::default()).unwrap();
        let ck = scratch.join("c.bin");
        write_tiny_checkpoint(&ck).unwrap();
        checkpoint::load(&ck, &BackendKind::Flex.device()).unwrap();
        for png in image_seeds().unwrap() {
            image::load_from_memory(&png).unwrap();
        }
        std::fs::remove_dir_all(&scratch).ok();
    }

    #[test]
    fn mutations_are_deterministic_under_a_seed_and_vary() {
        let seeds = vec![b"{\"a\": [1, 2.5, -3]}".to_vec()];
        let run = |s| {
            let mut rng = ChaCha8Rng::seed_from_u64(s);
            (0..50).map(|_| mutate(&seeds, &mut rng)).collect::<Vec<_>>()
        };
        assert_eq!(run(1), run(1));
        let distinct: std::collections::HashSet<_> = run(1).into_iter().collect();
        assert!(distinct.len() > 40, "{} distinct inputs of 50", distinct.len());
    }
}
