//! Reference cases: the stylized image(s) S_R and the camera(s) they were
//! painted from.
//!
//! A case is a folder with either our `reference.toml`:
//!
//! ```toml
//! color_pre = true            # optional: colour-matching loss on (default true)
//! path_frames = 120           # optional: length of the render path "path:N" indexes
//! [[reference]]
//! style = "style.png"
//! view = "train:3"            # train:N | test:N | path:N
//! region = "difference"     # optional: a local edit (below)
//! [[reference]]
//! style = "style2.png"
//! c2w = [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]   # row-major camera-to-world (OpenGL)
//! intrinsics = { width = 200, height = 200, fx = 280.0, fy = 280.0, cx = 100.0, cy = 100.0 }
//! ```
//!
//! A reference with `region` is a local edit: only the surfaces its
//! painting changes are stylized, and everything else keeps the photoreal
//! field (`stylize::region`). `region = "difference"` takes the pixels where
//! the style image differs from the photoreal render by more than
//! `region_threshold` (a top-level key, default 0.1 of the colour range, in
//! any channel); `region = "mask.png"` names a mask image of the view's
//! size (white = edited).
//!
//! or the authors' `data_config.json`, unchanged: `style_img` (a string or a
//! list), exactly one of `tmpl_idx_train` / `tmpl_idx_test` non-null (an index
//! or a list; `tmpl_idx_test` indexes the standard render path, 120 poses),
//! `color_pre`, `style_name`; `dataset_type` and `scene_name` are informative.
//! Paths in `style_img` are tried relative to the case folder, then by file
//! name inside it (the authors' files say `./data/ref_case/...`).

use std::path::{Path, PathBuf};
use std::str::FromStr;

use anyhow::{Context, Result, bail, ensure};

use glam::Mat4;
use serde::Deserialize;

use crate::scene::camera::{Camera, Intrinsics};
use crate::scene::data::Dataset;
use crate::util::input::InputError;

pub const CASE_TOML: &str = "reference.toml";
pub const CASE_JSON: &str = "data_config.json";
/// The standard render path's length (the LLFF spiral of the NeRF code).
pub const DEFAULT_PATH_FRAMES: usize = 120;

/// The longest render path a case may ask for (the evaluation renders every
/// frame; a larger number is a typo, and would allocate without bound).
pub const MAX_PATH_FRAMES: usize = 10_000;

/// Which camera a reference was painted from.
#[derive(Debug, Clone, PartialEq)]
pub enum ViewSpec {
    Train(usize),
    Test(usize),
    /// Index into the standard render path (`Dataset::render_path`).
    Path(usize),
    Pose(Camera),
}

impl FromStr for ViewSpec {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        let (kind, idx) =
            s.split_once(':').with_context(|| format!("view {s:?}: expected train:N, test:N or path:N"))?;
        let i: usize = idx.trim().parse().with_context(|| format!("view {s:?}: {idx:?} is not an index"))?;
        Ok(match kind.trim() {
            "train" => ViewSpec::Train(i),
            "test" => ViewSpec::Test(i),
            "path" => ViewSpec::Path(i),
            other => bail!("view {s:?}: unknown kind {other:?} (train, test or path)"),
        })
    }
}

impl std::fmt::Display for ViewSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ViewSpec::Train(i) => write!(f, "train:{i}"),
            ViewSpec::Test(i) => write!(f, "test:{i}"),
            ViewSpec::Path(i) => write!(f, "path:{i}"),
            ViewSpec::Pose(_) => write!(f, "pose"),
        }
    }
}

impl ViewSpec {
    /// `train:N`, `test:N`, `path:N`, or the file name of one of `dataset`'s
    /// training or test images, with or without its extension and folders
    /// (`r_12.png`, `test/r_12`, `IMG_0042`); a name two views share is
    /// refused with both.
    pub fn parse_in(s: &str, dataset: &Dataset) -> Result<ViewSpec> {
        if s.contains(':') {
            return s.parse();
        }
        // A view's name without "./" and its extension, '/'-separated.
        let bare = |name: &str| {
            let p = Path::new(name.trim_start_matches("./"));
            let p = p.with_extension("");
            p.to_string_lossy().replace('\\', "/")
        };
        let wanted = bare(s);
        let suffix = format!("/{wanted}");
        let named = |v: &crate::scene::data::View| {
            let b = bare(&v.name);
            !wanted.is_empty() && (b == wanted || b.ends_with(&suffix))
        };
        let train = dataset.train.iter().enumerate().filter(|(_, v)| named(v)).map(|(i, _)| ViewSpec::Train(i));
        let test = dataset.test.iter().enumerate().filter(|(_, v)| named(v)).map(|(i, _)| ViewSpec::Test(i));
        let mut found: Vec<ViewSpec> = train.chain(test).collect();
        match found.len() {
            1 => Ok(found.remove(0)),
            0 => bail!(
                "view {s:?}: expected train:N, test:N or path:N, or the file name of a training or test image \
                 (none of the {} training and {} test images is named so; `refnpr views` shows them)",
                dataset.train.len(),
                dataset.test.len()
            ),
            _ => {
                let all: Vec<String> = found.iter().map(ToString::to_string).collect();
                bail!("view {s:?} names {} images ({}): say which, e.g. {}", found.len(), all.join(", "), all[0])
            }
        }
    }

    /// The camera this spec names in `dataset`.
    pub fn camera(&self, dataset: &Dataset, path_frames: usize) -> Result<Camera> {
        let pick = |views: &[crate::scene::data::View], i: usize, what: &str| -> Result<Camera> {
            views.get(i).map(|v| v.camera).with_context(|| {
                format!("reference view {what}:{i} is out of range: the scene has {} {what} views", views.len())
            })
        };
        match self {
            ViewSpec::Train(i) => pick(&dataset.train, *i, "train"),
            ViewSpec::Test(i) => pick(&dataset.test, *i, "test"),
            ViewSpec::Path(i) => {
                ensure!(
                    *i < path_frames,
                    "reference view path:{i} is out of range: the render path has {path_frames} poses"
                );
                Ok(dataset.render_path(path_frames)[*i])
            }
            ViewSpec::Pose(c) => Ok(*c),
        }
    }
}

/// Which pixels of a reference a local edit paints (`region` in `reference.toml`).
#[derive(Debug, Clone, PartialEq)]
pub enum RegionSpec {
    /// Where the style image differs from the photoreal render (`region = "difference"`).
    Difference,
    /// A mask image, white where edited (`region = "mask.png"`).
    Mask(PathBuf),
}

/// The `region` value that asks for the difference to the photoreal render.
pub const REGION_DIFFERENCE: &str = "difference";
/// `region_threshold`'s default: a tenth of the colour range in some channel.
pub const DEFAULT_REGION_THRESHOLD: f32 = 0.1;

/// One reference: its style image and camera, and its region when it is a local edit.
#[derive(Debug, Clone)]
pub struct ReferenceSpec {
    pub style: PathBuf,
    pub view: ViewSpec,
    pub region: Option<RegionSpec>,
}

/// A parsed reference case.
#[derive(Debug, Clone)]
pub struct ReferenceCase {
    pub dir: PathBuf,
    pub references: Vec<ReferenceSpec>,
    /// Colour-matching loss on (the authors' `color_pre`).
    pub color_pre: bool,
    pub style_name: Option<String>,
    pub path_frames: usize,
    /// The scene the case was made for, when it says (checked against the dataset folder's name).
    pub scene_name: Option<String>,
    /// The least per-channel difference to the photoreal render that counts as painted (`region = "difference"`).
    pub region_threshold: f32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CaseToml {
    #[serde(default = "yes")]
    color_pre: bool,
    style_name: Option<String>,
    #[serde(default = "default_frames")]
    path_frames: usize,
    scene_name: Option<String>,
    #[serde(default = "default_threshold")]
    region_threshold: f32,
    reference: Vec<RefToml>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RefToml {
    style: PathBuf,
    view: Option<String>,
    c2w: Option<[[f32; 4]; 4]>,
    intrinsics: Option<Intrinsics>,
    region: Option<String>,
}

fn default_threshold() -> f32 {
    DEFAULT_REGION_THRESHOLD
}

fn yes() -> bool {
    true
}
fn default_frames() -> usize {
    DEFAULT_PATH_FRAMES
}

/// An index or a list of indices (the authors accept both).
#[derive(Deserialize)]
#[serde(untagged)]
enum OneOrMany<T> {
    One(T),
    Many(Vec<T>),
}

impl<T> OneOrMany<T> {
    fn into_vec(self) -> Vec<T> {
        match self {
            OneOrMany::One(t) => vec![t],
            OneOrMany::Many(v) => v,
        }
    }
}

#[derive(Deserialize)]
struct CaseJson {
    style_img: OneOrMany<String>,
    tmpl_idx_train: Option<OneOrMany<usize>>,
    tmpl_idx_test: Option<OneOrMany<usize>>,
    #[serde(default = "yes")]
    color_pre: bool,
    style_name: Option<String>,
    scene_name: Option<String>,
}

impl ReferenceCase {
    /// Reads `dir/reference.toml`, else `dir/data_config.json`.
    pub fn load(dir: &Path) -> Result<Self> {
        if !dir.is_dir() {
            let message = format!("reference case {} is not a folder", dir.display());
            return Err(InputError::Missing { path: dir.into(), message }.into());
        }
        let toml_path = dir.join(CASE_TOML);
        let json_path = dir.join(CASE_JSON);
        let case = if toml_path.exists() {
            let text =
                std::fs::read_to_string(&toml_path).with_context(|| format!("cannot read {}", toml_path.display()))?;
            Self::from_toml(dir, &text).with_context(|| InputError::Malformed {
                path: toml_path.clone(),
                message: format!("in {}", toml_path.display()),
            })?
        } else if json_path.exists() {
            let text =
                std::fs::read_to_string(&json_path).with_context(|| format!("cannot read {}", json_path.display()))?;
            Self::from_json(dir, &text).with_context(|| InputError::Malformed {
                path: json_path.clone(),
                message: format!("in {}", json_path.display()),
            })?
        } else {
            let message = format!("reference case {} has neither {CASE_TOML} nor {CASE_JSON}", dir.display());
            return Err(InputError::Missing { path: dir.into(), message }.into());
        };
        for r in &case.references {
            ensure!(r.style.exists(), "style image {} does not exist", r.style.display());
            if let Some(RegionSpec::Mask(mask)) = &r.region {
                ensure!(mask.exists(), "region mask {} does not exist", mask.display());
            }
        }
        Ok(case)
    }

    pub fn from_toml(dir: &Path, text: &str) -> Result<Self> {
        let t: CaseToml = toml::from_str(text).context("malformed reference TOML")?;
        ensure!(!t.reference.is_empty(), "no [[reference]] entries");
        ensure!(
            (1..=MAX_PATH_FRAMES).contains(&t.path_frames),
            "path_frames must be between 1 and {MAX_PATH_FRAMES}, got {}",
            t.path_frames
        );
        ensure!(
            t.region_threshold > 0.0 && t.region_threshold < 1.0,
            "region_threshold must be between 0 and 1 (a fraction of the colour range), got {}",
            t.region_threshold
        );
        let mut references = Vec::new();
        for (i, r) in t.reference.into_iter().enumerate() {
            let view = match (r.view, r.c2w, r.intrinsics) {
                (Some(v), None, None) => v.parse()?,
                (None, Some(m), Some(k)) => {
                    let c2w = Mat4::from_cols_array_2d(&m).transpose();
                    crate::scene::data::check_pose(&c2w, &dir.join(CASE_TOML), &format!("reference {i}"))?;
                    ensure!(
                        k.width > 0 && k.height > 0 && k.fx > 0.0 && k.fy > 0.0,
                        "reference {i}: invalid intrinsics"
                    );
                    ViewSpec::Pose(Camera::new(k, c2w))
                }
                _ => bail!("reference {i}: give either `view` or both `c2w` and `intrinsics`"),
            };
            let region = r.region.map(|name| match name.as_str() {
                REGION_DIFFERENCE => RegionSpec::Difference,
                _ => RegionSpec::Mask(dir.join(name)),
            });
            references.push(ReferenceSpec { style: dir.join(r.style), view, region });
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            references,
            color_pre: t.color_pre,
            style_name: t.style_name,
            path_frames: t.path_frames,
            scene_name: t.scene_name,
            region_threshold: t.region_threshold,
        })
    }

    pub fn from_json(dir: &Path, text: &str) -> Result<Self> {
        let j: CaseJson = serde_json::from_str(text).context("malformed data_config.json")?;
        let styles = j.style_img.into_vec();
        let views: Vec<ViewSpec> = match (j.tmpl_idx_train, j.tmpl_idx_test) {
            (Some(t), None) => t.into_vec().into_iter().map(ViewSpec::Train).collect(),
            (None, Some(t)) => t.into_vec().into_iter().map(ViewSpec::Path).collect(),
            (Some(_), Some(_)) => bail!("both tmpl_idx_train and tmpl_idx_test are set; one must be null"),
            (None, None) => bail!("neither tmpl_idx_train nor tmpl_idx_test is set"),
        };
        ensure!(!styles.is_empty(), "style_img is empty");
        // One index for several styles: the authors' multi-reference files list both.
        ensure!(
            views.len() == styles.len() || views.len() == 1,
            "{} style images but {} template indices",
            styles.len(),
            views.len()
        );
        let references = styles
            .iter()
            .enumerate()
            .map(|(i, s)| ReferenceSpec {
                style: resolve_style(dir, s),
                view: views[i.min(views.len() - 1)].clone(),
                region: None,
            })
            .collect();
        Ok(Self {
            dir: dir.to_path_buf(),
            references,
            color_pre: j.color_pre,
            style_name: j.style_name,
            path_frames: DEFAULT_PATH_FRAMES,
            scene_name: j.scene_name,
            region_threshold: DEFAULT_REGION_THRESHOLD,
        })
    }

    /// A warning when the case names a scene other than the dataset folder's name.
    pub fn scene_mismatch(&self, dataset: &Dataset) -> Option<String> {
        let want = self.scene_name.as_deref()?;
        let have = dataset.root.file_name()?.to_string_lossy();
        (want != have).then(|| {
            format!("the reference case says scene_name = {want:?} but the photoreal run's dataset folder is {have:?}")
        })
    }

    /// Whether any reference is a local edit.
    pub fn is_local(&self) -> bool {
        self.references.iter().any(|r| r.region.is_some())
    }

    /// The reference cameras in `dataset`.
    pub fn cameras(&self, dataset: &Dataset) -> Result<Vec<Camera>> {
        self.references.iter().map(|r| r.view.camera(dataset, self.path_frames)).collect()
    }
}

/// A `style_img` path of the authors' config: as given relative to the case
/// folder, else the file name inside it.
fn resolve_style(dir: &Path, s: &str) -> PathBuf {
    let direct = dir.join(s);
    if direct.exists() {
        return direct;
    }
    match Path::new(s).file_name() {
        Some(name) => dir.join(name),
        None => direct,
    }
}

/// Reads a style image as RGB in `[0, 1]` at the camera's resolution: alpha is
/// composited over `background`; another size is resized (Catmull-Rom, as
/// the authors' bicubic) and reported in the returned note.
pub fn read_style(path: &Path, width: u32, height: u32, background: [f32; 3]) -> Result<(Vec<f32>, Option<String>)> {
    let img = image::open(path).with_context(|| format!("cannot read style image {}", path.display()))?;
    ensure!(img.width() > 0 && img.height() > 0, "style image {} is empty", path.display());
    let mut img = img.to_rgba32f();
    let mut note = None;
    if img.dimensions() != (width, height) {
        note = Some(format!(
            "style image {} is {}x{}: resized to the view's {width}x{height}",
            path.display(),
            img.width(),
            img.height()
        ));
        img = image::imageops::resize(&img, width, height, image::imageops::FilterType::CatmullRom);
    }
    Ok((crate::scene::data::composite_over(&img, background), note))
}
