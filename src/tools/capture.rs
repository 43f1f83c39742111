//! `refnpr capture PHOTOS --out DATA`: a folder of photos to a dataset
//! folder `train` reads, through COLMAP's command line (Debian:
//! `apt-get install colmap`; every stage on the CPU).
//!
//! 1. the photos, decoded (alpha composited over white), downsized to a
//!    long side of at most `max_side`, written as PNG to `DATA/colmap/input/`;
//! 2. `feature_extractor` (one shared camera by default: phone photos;
//!    photos under `SMALL_PHOTO_SIDE` pixels get SIFT one octave finer and
//!    COLMAP's pixel thresholds scaled to their size: `SizeSettings`);
//! 3. `exhaustive_matcher` (up to `SEQUENTIAL_FROM` photos; beyond that
//!    `sequential_matcher`, which assumes the photos' order follows the walk);
//! 4. `mapper`; the model with the most registered photos is kept;
//! 5. `image_undistorter` writes `DATA/images/` and `DATA/sparse/` (pinhole
//!    cameras), which `data::colmap` reads.
//!
//! COLMAP's output goes to `DATA/colmap.log`.

use crate::scene::data::colmap_model::{self, Form};
use crate::util::progress::{Event, Phase, Progress};
use anyhow::{Context, Result, bail};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

/// From this many photos on, matching is sequential instead of exhaustive.
pub const SEQUENTIAL_FROM: usize = 300;

/// The fewest photos COLMAP must register, as a fraction of those given.
pub const MIN_REGISTERED_FRACTION: f64 = 0.5;

/// The long side photos are downsized to unless told (`--max-side`):
/// the paper's synthetic size, pictures rather than previews, at a cost two
/// cores carry (docs/own_scene.md, "Size"): COLMAP on 20 photos 20 s at
/// 504 px and 2:42 at 1008, a forward-facing fit at 1008x756 13 min and
/// its stylization with `--coarse-scale 2` 32 min; a capture around the
/// scene grows its grid with the photos (512³ at 800 px, 48 min to fit),
/// for which `--max-side 400` is the first look.
pub const DEFAULT_MAX_SIDE: u32 = 800;

/// What `capture` can be told.
#[derive(Debug, Clone)]
pub struct CaptureOptions {
    /// The longest side the photos are downsized to (pixels).
    pub max_side: u32,
    /// COLMAP's camera model for the photos (undistorted at the end).
    pub camera_model: String,
    /// All photos from one camera with one lens setting (true for a phone capture).
    pub single_camera: bool,
    /// The COLMAP executable.
    pub colmap: PathBuf,
}

impl Default for CaptureOptions {
    fn default() -> Self {
        Self {
            max_side: DEFAULT_MAX_SIDE,
            camera_model: "SIMPLE_RADIAL".into(),
            single_camera: true,
            colmap: "colmap".into(),
        }
    }
}

/// What a capture did.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CaptureReport {
    pub photos: usize,
    pub registered: usize,
    pub points: usize,
    /// (width, height) of the dataset's images.
    pub size: (u32, u32),
    pub seconds: f64,
}

const INSTALL: &str = "install it (Debian/Ubuntu: sudo apt-get install colmap; macOS: brew install colmap; \
     others: https://colmap.github.io/install.html), or run COLMAP yourself (feature_extractor, \
     exhaustive_matcher, mapper, image_undistorter) and give `refnpr train --data` the folder holding its \
     images/ and sparse/";

/// The photos of a folder (PNG, JPEG), sorted by name.
fn list_photos(dir: &Path) -> Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        bail!("{} is not a folder of photos", dir.display());
    }
    let mut photos: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot read {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let ext = p.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
            matches!(ext.as_deref(), Some("png" | "jpg" | "jpeg"))
        })
        .collect();
    photos.sort();
    if photos.len() < 3 {
        bail!(
            "{} holds {} photos (PNG or JPEG); a capture needs at least 3, better 20-100",
            dir.display(),
            photos.len()
        );
    }
    Ok(photos)
}

/// Writes each photo downsized to `max_side` as `input/<stem>.png`.
/// Returns the longest side written.
fn prepare_photos(photos: &[PathBuf], input: &Path, max_side: u32) -> Result<u32> {
    std::fs::create_dir_all(input)?;
    let mut stems: Vec<_> = photos.iter().map(|p| p.file_stem().map(|s| s.to_owned())).collect();
    stems.sort();
    if stems.windows(2).any(|w| w[0] == w[1]) {
        bail!("two photos share a name with different extensions (a.jpg and a.png): rename one");
    }
    let written: Vec<Result<u32>> = photos
        .par_iter()
        .map(|p| {
            let img = image::open(p).with_context(|| format!("cannot decode the photo {}", p.display()))?;
            let rgb = crate::scene::data::composite_over(&img.to_rgba32f(), [1.0; 3]);
            let (w, h) = (img.width(), img.height());
            let scale = (max_side as f64 / w.max(h) as f64).min(1.0);
            let (nw, nh) = (((w as f64 * scale).round() as u32).max(1), ((h as f64 * scale).round() as u32).max(1));
            let img = crate::util::image::to_rgb8(w, h, &rgb);
            let img = image::imageops::resize(&img, nw, nh, image::imageops::FilterType::Lanczos3);
            let stem = p.file_stem().expect("a listed file has a name");
            let out = input.join(stem).with_extension("png");
            img.save(&out).with_context(|| format!("cannot write {}", out.display()))?;
            Ok(nw.max(nh))
        })
        .collect();
    written.into_iter().try_fold(0, |most, side| Ok(most.max(side?)))
}

/// From this long side down, photos count as small for COLMAP (below).
pub const SMALL_PHOTO_SIDE: u32 = 400;

/// COLMAP's settings that depend on the photos' size: its pixel
/// thresholds (a match's epipolar error 4 px, a point's reprojection error
/// 4 px, a new image's pose 12 px) suit photos of a thousand pixels or more;
/// photos with a long side under [`SMALL_PHOTO_SIDE`] get them scaled down in
/// proportion, and SIFT one octave finer (it already doubles the image).
/// Lego's 125 renders at 200 px: 115 registered at 0.45° / 1.44° median /
/// worst rotation error with COLMAP's defaults; 122 at 0.23-0.24° / 0.73-0.74° so (two runs; the
/// finer octave alone: 122 at 0.37° / 1.60°; the thresholds alone: 114 at
/// 0.37° / 1.19°). Fern's 504 px photos keep the defaults.
struct SizeSettings {
    first_octave: String,
    match_error: String,
    reprojection_error: String,
    pose_error: String,
}

impl SizeSettings {
    fn for_long_side(side: u32) -> Self {
        let (scale, first_octave) = match side < SMALL_PHOTO_SIDE {
            true => (side as f64 / SMALL_PHOTO_SIDE as f64, -2),
            false => (1.0, -1),
        };
        let px = |default: f64| format!("{}", (default * scale).max(1.0));
        Self {
            first_octave: first_octave.to_string(),
            match_error: px(4.0),
            reprojection_error: px(4.0),
            pose_error: px(12.0),
        }
    }
}

/// COLMAP's command line, each run's output appended to one log.
struct Colmap<'a> {
    exe: &'a Path,
    log: &'a Path,
}

impl Colmap<'_> {
    /// Runs `colmap COMMAND --KEY VALUE ...`.
    fn run(&self, command: &str, options: &[(&str, &dyn AsRef<std::ffi::OsStr>)]) -> Result<()> {
        let file = std::fs::OpenOptions::new().create(true).append(true).open(self.log)?;
        let mut cmd = Command::new(self.exe);
        cmd.arg(command);
        for (key, value) in options {
            cmd.arg(format!("--{key}")).arg(value);
        }
        let status = cmd
            .env("QT_QPA_PLATFORM", "offscreen")
            .stdout(Stdio::from(file.try_clone()?))
            .stderr(Stdio::from(file))
            .status();
        match status {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                bail!("COLMAP ({}) is not installed or not on the PATH: {INSTALL}", self.exe.display())
            }
            Err(e) => bail!("cannot run {}: {e}", self.exe.display()),
            Ok(s) if !s.success() => bail!("colmap {command} failed ({s}); its output is in {}", self.log.display()),
            Ok(_) => Ok(()),
        }
    }
}

/// Removes what an earlier capture into the same folder left.
fn remove_stale(paths: &[PathBuf]) -> Result<()> {
    for p in paths {
        if p.is_dir() {
            std::fs::remove_dir_all(p)?;
        } else if p.exists() {
            std::fs::remove_file(p)?;
        }
    }
    Ok(())
}

/// The model folder under `sparse` with the most registered images, and that count.
fn largest_model(sparse: &Path) -> Result<Option<(PathBuf, usize)>> {
    let mut best: Option<(PathBuf, usize)> = None;
    let Ok(entries) = std::fs::read_dir(sparse) else { return Ok(None) };
    let mut dirs: Vec<PathBuf> = entries.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_dir()).collect();
    dirs.sort();
    for d in dirs {
        let n = colmap_model::read(&d, Form::Binary)?.images.len();
        if best.as_ref().is_none_or(|b| n > b.1) {
            best = Some((d, n));
        }
    }
    Ok(best)
}

/// Runs the capture (see the module's doc) and checks that enough photos were registered.
pub fn capture(photos_dir: &Path, out: &Path, opts: &CaptureOptions, progress: &dyn Progress) -> Result<CaptureReport> {
    let started = Instant::now();
    let photos = list_photos(photos_dir)?;
    let work = out.join("colmap");
    let (input, sparse, db) = (work.join("input"), work.join("sparse"), work.join("database.db"));
    remove_stale(&[input.clone(), sparse.clone(), db.clone()])?;
    std::fs::create_dir_all(&sparse)?;
    let log = out.join("colmap.log");
    std::fs::write(&log, "")?;
    let colmap = Colmap { exe: &opts.colmap, log: &log };
    let total = 5;
    let step = |done: usize, what: &str| {
        progress.event(Event::Step { phase: Phase::Capture, done, total, message: what.to_string() });
    };
    progress.event(Event::Start { phase: Phase::Capture, done: 0, total });
    step(0, "photos");
    let by_size = SizeSettings::for_long_side(prepare_photos(&photos, &input, opts.max_side)?);
    step(1, "features");
    let single = if opts.single_camera { "1" } else { "0" };
    colmap.run(
        "feature_extractor",
        &[
            ("database_path", &db),
            ("image_path", &input),
            ("ImageReader.camera_model", &opts.camera_model),
            ("ImageReader.single_camera", &single),
            ("SiftExtraction.use_gpu", &"0"),
            ("SiftExtraction.first_octave", &by_size.first_octave),
        ],
    )?;
    step(2, "matching");
    let matcher = if photos.len() < SEQUENTIAL_FROM { "exhaustive_matcher" } else { "sequential_matcher" };
    colmap.run(
        matcher,
        &[("database_path", &db), ("SiftMatching.use_gpu", &"0"), ("SiftMatching.max_error", &by_size.match_error)],
    )?;
    step(3, "mapping");
    // The mapper fails outright when it finds no initial pair: that is a
    // capture registering nothing, reported below like one registering too little.
    let mapped = colmap.run(
        "mapper",
        &[
            ("database_path", &db),
            ("image_path", &input),
            ("output_path", &sparse),
            ("Mapper.init_max_error", &by_size.reprojection_error),
            ("Mapper.filter_max_reproj_error", &by_size.reprojection_error),
            ("Mapper.abs_pose_max_error", &by_size.pose_error),
        ],
    );
    let largest = largest_model(&sparse)?;
    if largest.is_some() {
        mapped?;
    }
    let needed = ((photos.len() as f64 * MIN_REGISTERED_FRACTION).ceil() as usize).max(3);
    let n = largest.as_ref().map_or(0, |r| r.1);
    let Some((best, registered)) = largest.filter(|(_, n)| *n >= needed) else {
        bail!(
            "COLMAP registered {n} of {} photos (at least {needed} are needed); the photos need more overlap \
             (each part of the scene in 3 or more photos, 60-80% overlap between neighbours), sharp focus and \
             texture; its output is in {}",
            photos.len(),
            log.display()
        );
    };
    step(4, "undistortion");
    remove_stale(&[out.join("images"), out.join("sparse")])?;
    let output_type = "COLMAP";
    colmap.run(
        "image_undistorter",
        &[("image_path", &input), ("input_path", &best), ("output_path", &out), ("output_type", &output_type)],
    )?;
    let model = colmap_model::read(&out.join("sparse"), Form::Binary)?;
    let size = model.cameras.values().next().map_or((0, 0), |c| (c.width, c.height));
    let seconds = started.elapsed().as_secs_f64();
    progress.event(Event::PhaseDone { phase: Phase::Capture, seconds });
    Ok(CaptureReport { photos: photos.len(), registered, points: model.points.len(), size, seconds })
}

/// How far a capture's poses are from known ones, after the similarity
/// transform that best maps the first onto the second.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct PoseError {
    /// Views present in both.
    pub matched: usize,
    pub rotation_median_deg: f64,
    pub rotation_worst_deg: f64,
    /// Camera-centre errors as fractions of the scene size (the diameter of the known camera centres).
    pub translation_median: f64,
    pub translation_worst: f64,
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The error of `found` against `truth` (camera-to-world, matched by
/// index): the rotation that aligns them is the mean of the per-camera
/// rotations truth * found^-1 (the quaternion mean), then the scale and
/// translation are the least-squares fit of the camera centres under it.
pub fn pose_error(found: &[glam::Mat4], truth: &[glam::Mat4]) -> PoseError {
    use glam::{DQuat, DVec3};
    let rot = |m: &glam::Mat4| DQuat::from_mat3(&glam::Mat3::from_mat4(*m).as_dmat3()).normalize();
    let centre = |m: &glam::Mat4| m.w_axis.truncate().as_dvec3();
    let n = found.len().min(truth.len());
    let mut sum = glam::DVec4::ZERO;
    let first = rot(&truth[0]) * rot(&found[0]).inverse();
    for i in 0..n {
        let q = rot(&truth[i]) * rot(&found[i]).inverse();
        // q and -q are one rotation: take the sign nearest the first.
        let q = if q.dot(first) < 0.0 { -q } else { q };
        sum += glam::DVec4::from(q);
    }
    let align = DQuat::from_vec4(sum).normalize();
    let (fx, ty): (Vec<DVec3>, Vec<DVec3>) = (0..n).map(|i| (align * centre(&found[i]), centre(&truth[i]))).unzip();
    let (mf, mt) = (fx.iter().sum::<DVec3>() / n as f64, ty.iter().sum::<DVec3>() / n as f64);
    let num: f64 = fx.iter().zip(&ty).map(|(f, t)| (*f - mf).dot(*t - mt)).sum();
    let den: f64 = fx.iter().map(|f| (*f - mf).length_squared()).sum();
    let scale = if den > 0.0 { num / den } else { 1.0 };
    let size = 2.0 * ty.iter().map(|t| (*t - mt).length()).fold(0.0, f64::max);
    // The angle of the residual rotation, in [0, 180] degrees.
    let angle = |q: DQuat| 2.0 * q.w.abs().min(1.0).acos().to_degrees();
    let rot_err: Vec<f64> = (0..n).map(|i| angle(rot(&truth[i]) * (align * rot(&found[i])).inverse())).collect();
    let trans_err: Vec<f64> =
        fx.iter().zip(&ty).map(|(f, t)| ((*f - mf) * scale + mt - *t).length() / size.max(1e-12)).collect();
    PoseError {
        matched: n,
        rotation_median_deg: median(&mut rot_err.clone()),
        rotation_worst_deg: rot_err.iter().copied().fold(0.0, f64::max),
        translation_median: median(&mut trans_err.clone()),
        translation_worst: trans_err.iter().copied().fold(0.0, f64::max),
    }
}

/// A view's name as a key shared by a capture and its source dataset:
/// without extension, `./` and with `/` as `_` (`train/r_0` -> `train_r_0`).
fn name_key(name: &str) -> String {
    let name = name.trim_start_matches("./");
    let stem = Path::new(name).with_extension("");
    stem.to_string_lossy().replace(['/', '\\'], "_")
}

/// The pose error of the dataset in `captured` against the dataset in
/// `truth` (any layout), views matched by file name (a photo named
/// `train_r_0.png` matches Blender's `train/r_0`).
pub fn compare_poses(captured: &Path, truth: &Path) -> Result<PoseError> {
    use crate::photo::config::TrainConfig;
    use crate::scene::data;
    let load = |dir: &Path| -> Result<Vec<(String, glam::Mat4)>> {
        let ds = data::load(dir, &TrainConfig::for_dir(dir)?.data)?;
        Ok(ds.train.iter().chain(&ds.val).chain(&ds.test).map(|v| (name_key(&v.name), v.camera.c2w)).collect())
    };
    let (found, known) = (load(captured)?, load(truth)?);
    let pairs: Vec<(glam::Mat4, glam::Mat4)> =
        found.iter().filter_map(|(k, f)| known.iter().find(|(kk, _)| kk == k).map(|(_, t)| (*f, *t))).collect();
    if pairs.len() < 3 {
        bail!("only {} views of {} match views of {} by name", pairs.len(), captured.display(), truth.display());
    }
    let (f, t): (Vec<_>, Vec<_>) = pairs.into_iter().unzip();
    Ok(pose_error(&f, &t))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::camera::orbit;
    use glam::{Mat4, Quat, Vec3};

    #[test]
    fn small_photos_get_a_finer_octave_and_thresholds_scaled_to_their_size() {
        let lego = SizeSettings::for_long_side(200);
        let got = [&lego.first_octave, &lego.match_error, &lego.reprojection_error, &lego.pose_error];
        assert_eq!(got, ["-2", "2", "2", "6"]);
        for side in [SMALL_PHOTO_SIDE, 504, 800] {
            let s = SizeSettings::for_long_side(side);
            assert_eq!([&s.first_octave, &s.match_error, &s.reprojection_error, &s.pose_error], ["-1", "4", "4", "12"]);
        }
        assert_eq!(SizeSettings::for_long_side(40).reprojection_error, "1", "at least a pixel");
    }

    #[test]
    fn poses_moved_by_a_similarity_have_no_error_and_a_turned_camera_has_its_angle() {
        let truth = orbit(Vec3::ZERO, 4.0, 30.0, 10);
        let sim = Mat4::from_scale_rotation_translation(
            Vec3::splat(0.3),
            Quat::from_rotation_y(1.1),
            Vec3::new(2.0, -1.0, 5.0),
        );
        let found: Vec<Mat4> = truth
            .iter()
            .map(|m| {
                let mut f = Mat4::from_quat(Quat::from_rotation_y(1.1)) * *m;
                f.w_axis = sim.transform_point3(m.w_axis.truncate()).extend(1.0);
                f
            })
            .collect();
        let e = pose_error(&found, &truth);
        assert!(e.rotation_worst_deg < 0.01 && e.translation_worst < 1e-4, "{e:?}");
        let mut turned = found.clone();
        turned[3] *= Mat4::from_rotation_x(5f32.to_radians());
        let e = pose_error(&turned, &truth);
        assert!((e.rotation_worst_deg - 5.0).abs() < 0.6, "{e:?}");
        assert_eq!(name_key("./train/r_0.png"), "train_r_0");
    }
}
