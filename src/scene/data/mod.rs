//! Posed-image datasets: one `Dataset` type and a loader per layout.

pub(crate) mod blender;
pub(crate) mod colmap;
pub use colmap::{check_writable, write_colmap};
pub mod colmap_model;
pub(crate) mod llff;
pub(crate) mod nsvf;
pub(crate) mod posed;
pub mod procedural;
pub mod transforms;
pub mod undistort;

use crate::scene::camera::{Camera, Intrinsics, NdcParams, Ray, pose_is_valid};
use crate::util::input::InputError;
use anyhow::{Context, Result, bail};

use glam::{Mat3, Mat4, Vec3};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Which layout a dataset came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum DatasetKind {
    /// NeRF-synthetic / Blender (`transforms_*.json`), also our procedural scene.
    Blender,
    /// LLFF forward-facing (`poses_bounds.npy`), rendered in NDC.
    Llff,
    /// NSVF / Tanks&Temples (`rgb/`, `pose/`, `intrinsics.txt`).
    Nsvf,
    /// A COLMAP sparse model (`sparse/0/` or `sparse/`, binary or text) and `images/`.
    Colmap,
    /// One `transforms.json` as nerfstudio and instant-ngp write it.
    Transforms,
}

/// Whether a capture looks at the scene from one side (rendered in NDC, as
/// LLFF) or goes around it (a bounded box, as Blender); `auto` decides from
/// the cameras' viewing directions (COLMAP and `transforms.json` captures;
/// the research layouts have a fixed shape).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Shape {
    #[default]
    Auto,
    ForwardFacing,
    Around,
}

impl std::fmt::Display for DatasetKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        use clap::ValueEnum;
        f.write_str(self.to_possible_value().expect("no skipped variants").get_name())
    }
}

/// Options the loaders share.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LoadOptions {
    /// Colour composited behind transparent pixels (Blender RGBA), and the
    /// renderer's background colour.
    pub background: [f32; 3],
    /// Integer downscale of the images (1 = as stored). For LLFF this picks
    /// `images_<factor>/` when it exists, else resizes `images/`.
    pub downscale: u32,
    /// Forward-facing or around (COLMAP and `transforms.json` captures).
    pub shape: Shape,
    /// The box the grid covers, `[[xmin, ymin, zmin], [xmax, ymax, zmax]]`,
    /// in the loaded scene's frame (the one `refnpr train` prints), instead
    /// of the one the loader finds.
    pub bbox: Option<[[f32; 3]; 2]>,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self { background: [1.0, 1.0, 1.0], downscale: 1, shape: Shape::Auto, bbox: None }
    }
}

/// One posed image (RGB in `[0, 1]`, row-major).
#[derive(Debug, Clone)]
pub struct View {
    pub name: String,
    pub camera: Camera,
    pub rgb: Vec<f32>,
}

/// A scene: images, poses, intrinsics, splits, background, bounds.
#[derive(Debug, Clone)]
pub struct Dataset {
    pub kind: DatasetKind,
    pub root: PathBuf,
    pub train: Vec<View>,
    pub val: Vec<View>,
    pub test: Vec<View>,
    pub background: [f32; 3],
    /// The box the radiance grid covers (for LLFF: NDC, z in [-1, 1], x and y
    /// as far as the views' rays reach).
    pub bbox_min: Vec3,
    pub bbox_max: Vec3,
    /// Present for forward-facing scenes: rays are warped to NDC.
    pub ndc: Option<NdcParams>,
    /// Scene depth bounds (LLFF, after rescaling).
    pub near_far: Option<(f32, f32)>,
    /// What the loader noticed that may give a poor result (the caller reports them).
    pub warnings: Vec<String>,
    /// What the loader decided from the data (the capture's shape, the
    /// box, the split), for the caller to print.
    pub notes: Vec<String>,
    /// How a capture around the scene was moved into this frame (None:
    /// the source's own frame, or a forward-facing capture's LLFF one).
    pub source_frame: Option<SourceFrame>,
}

/// The similarity that moved a capture's poses into a dataset's frame:
/// positions `(rotation * p - centre) * scale`, orientations `rotation * R`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SourceFrame {
    pub rotation: Mat3,
    pub centre: Vec3,
    pub scale: f32,
}

impl SourceFrame {
    /// A camera-to-world pose of the dataset's frame in the source's frame.
    pub fn to_source(&self, c2w: Mat4) -> Mat4 {
        let back = self.rotation.transpose();
        let r = back * Mat3::from_mat4(c2w);
        let c = back * (c2w.w_axis.truncate() / self.scale + self.centre);
        Mat4::from_cols(r.x_axis.extend(0.0), r.y_axis.extend(0.0), r.z_axis.extend(0.0), c.extend(1.0))
    }
}

/// Which split of a dataset.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Dataset {
    /// Pixels of all training views.
    pub fn train_pixels(&self) -> f64 {
        self.train.iter().map(|v| v.camera.intrinsics.width as f64 * v.camera.intrinsics.height as f64).sum()
    }

    /// How many pixels of a training view the grid's box spans along x, y
    /// and z at its centre (the median view): what the fit's grid follows
    /// (`GridConfig::follow_images`). A forward-facing scene's box is in
    /// NDC, where ±1 in x and y is the reference camera's image edge: x
    /// and y at half the image's width and height per unit, z 0 (depth is
    /// not across pixels).
    pub fn box_pixels_across(&self) -> [f32; 3] {
        let extent = self.bbox_max - self.bbox_min;
        if let Some(ndc) = &self.ndc {
            return [extent.x * ndc.width / 2.0, extent.y * ndc.height / 2.0, 0.0];
        }
        let centre = (self.bbox_min + self.bbox_max) / 2.0;
        let mut per_unit: Vec<f32> = (self.train.iter())
            .map(|v| v.camera.intrinsics.fx / (v.camera.c2w.w_axis.truncate() - centre).length().max(1e-6))
            .filter(|p| p.is_finite())
            .collect();
        if per_unit.is_empty() {
            return [0.0; 3];
        }
        per_unit.sort_by(f32::total_cmp);
        (extent * per_unit[per_unit.len() / 2]).to_array()
    }

    /// The dataset with its training views `n` times smaller: each pixel the
    /// mean of an `n` x `n` block, the cameras to match
    /// ([`Intrinsics::downscaled`]); the test and validation views stay.
    pub fn with_train_downscaled(&self, n: u32) -> Dataset {
        let train = self
            .train
            .iter()
            .map(|v| {
                let k = v.camera.intrinsics;
                let image = crate::util::image::Image::new(k.width as usize, k.height as usize, v.rgb.clone());
                let small = image.block_mean(n as usize);
                let camera = Camera { intrinsics: k.downscaled(n), ..v.camera };
                View { name: v.name.clone(), camera, rgb: small.rgb }
            })
            .collect();
        Dataset { train, ..self.clone() }
    }

    /// `forward-facing` (rendered in NDC) or `around`.
    pub fn shape_name(&self) -> &'static str {
        if self.ndc.is_some() { "forward-facing" } else { "around" }
    }

    /// The ray (NDC-warped for forward-facing scenes) and colour of every pixel of `views`.
    pub fn pixel_rays(&self, views: &[View]) -> (Vec<Ray>, Vec<[f32; 3]>) {
        let mut rays = Vec::new();
        let mut colours = Vec::new();
        for v in views {
            rays.extend(v.camera.rays(self.ndc.as_ref()));
            colours.extend(crate::util::image::pixels(&v.rgb));
        }
        (rays, colours)
    }

    pub fn split(&self, s: Split) -> &[View] {
        match s {
            Split::Train => &self.train,
            Split::Val => &self.val,
            Split::Test => &self.test,
        }
    }

    /// The standard render path: the LLFF spiral (120 poses, 2 rotations,
    /// zrate 0.5) for forward-facing scenes, a circular orbit otherwise.
    pub fn render_path(&self, n: usize) -> Vec<Camera> {
        let intr = self.train[0].camera.intrinsics;
        let poses: Vec<Mat4> = self.train.iter().chain(&self.test).chain(&self.val).map(|v| v.camera.c2w).collect();
        let path = match (self.ndc, self.near_far) {
            (Some(_), Some((near, far))) => crate::scene::camera::llff_spiral(&poses, near, far, n, 2.0, 0.5),
            _ => {
                let centre = (self.bbox_min + self.bbox_max) * 0.5;
                let (mut radius, mut elev) = (0.0, 0.0);
                for p in &poses {
                    let d = p.w_axis.truncate() - centre;
                    radius += d.length();
                    elev += (d.z / d.length()).asin();
                }
                let n_p = poses.len() as f32;
                crate::scene::camera::orbit(centre, radius / n_p, (elev / n_p).to_degrees(), n)
            }
        };
        path.into_iter().map(|c2w| Camera::new(intr, c2w)).collect()
    }
}

/// Finds the layout of a dataset folder.
pub fn detect_kind(dir: &Path) -> Result<DatasetKind> {
    if !dir.exists() {
        let message = format!("dataset folder {} does not exist", dir.display());
        return Err(InputError::Missing { path: dir.into(), message }.into());
    }
    if !dir.is_dir() {
        bail!("{} is not a folder", dir.display());
    }
    std::fs::read_dir(dir).with_context(|| format!("cannot read the folder {}", dir.display()))?;
    if dir.join("transforms_train.json").exists() {
        Ok(DatasetKind::Blender)
    } else if dir.join("poses_bounds.npy").exists() {
        Ok(DatasetKind::Llff)
    } else if dir.join("pose").is_dir() && dir.join("rgb").is_dir() {
        Ok(DatasetKind::Nsvf)
    } else if dir.join("transforms.json").exists() {
        Ok(DatasetKind::Transforms)
    } else if colmap_model::find_model(dir).is_some() {
        Ok(DatasetKind::Colmap)
    } else {
        let message = format!(
            "{} is not a dataset folder: expected transforms_train.json (Blender), \
             poses_bounds.npy (LLFF), rgb/ + pose/ + intrinsics.txt (NSVF / Tanks&Temples), \
             transforms.json (nerfstudio / instant-ngp) or a COLMAP model in sparse/0/ or sparse/ \
             (from a folder of photos: refnpr capture PHOTOS --out DATA)",
            dir.display()
        );
        Err(InputError::NotADataset { path: dir.into(), message }.into())
    }
}

/// Loads a dataset of any supported layout.
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    if opts.downscale == 0 {
        bail!("downscale must be at least 1");
    }
    let ds = match detect_kind(dir)? {
        DatasetKind::Blender => blender::load(dir, opts)?,
        DatasetKind::Llff => llff::load(dir, opts)?,
        DatasetKind::Nsvf => nsvf::load(dir, opts)?,
        DatasetKind::Colmap => colmap::load(dir, opts)?,
        DatasetKind::Transforms => transforms::load(dir, opts)?,
    };
    if ds.train.is_empty() {
        bail!("{}: the training split is empty", dir.display());
    }
    if ds.test.is_empty() {
        bail!("{}: the test split is empty", dir.display());
    }
    Ok(ds)
}

/// The layout of a dataset folder and whether it is forward-facing
/// (rendered in NDC), read from its poses alone (no image is decoded): what
/// picks a training config's defaults before the dataset is loaded.
pub fn probe(dir: &Path, shape: Shape) -> Result<(DatasetKind, bool)> {
    let kind = detect_kind(dir)?;
    let forward = match kind {
        DatasetKind::Llff => true,
        DatasetKind::Blender | DatasetKind::Nsvf => false,
        DatasetKind::Colmap => posed::is_forward_facing(&colmap::poses(dir)?, shape),
        DatasetKind::Transforms => posed::is_forward_facing(&transforms::poses(dir)?, shape),
    };
    Ok((kind, forward))
}

/// Reads an image as RGB in `[0, 1]`, compositing alpha over `background`,
/// optionally downscaled by an integer factor.
pub fn read_rgb(path: &Path, background: [f32; 3], downscale: u32) -> Result<(u32, u32, Vec<f32>)> {
    if !path.exists() {
        let message = format!("image {} does not exist", path.display());
        return Err(InputError::Missing { path: path.into(), message }.into());
    }
    let img = image::open(path).with_context(|| InputError::Malformed {
        path: path.into(),
        message: format!("cannot decode image {}", path.display()),
    })?;
    let mut img = img.to_rgba32f();
    if downscale > 1 {
        let (w, h) = (img.width() / downscale, img.height() / downscale);
        if w == 0 || h == 0 {
            let message = format!("image {} is too small to downscale by {downscale}", path.display());
            return Err(InputError::WrongSize { path: path.into(), message }.into());
        }
        img = image::imageops::resize(&img, w, h, image::imageops::FilterType::Triangle);
    }
    let (w, h) = img.dimensions();
    Ok((w, h, composite_over(&img, background)))
}

/// Interleaved RGB in `[0, 1]` of an RGBA image composited over `background`.
pub fn composite_over(img: &image::Rgba32FImage, background: [f32; 3]) -> Vec<f32> {
    let mut rgb = Vec::with_capacity(img.pixels().len() * 3);
    for p in img.pixels() {
        let a = p[3].clamp(0.0, 1.0);
        for c in 0..3 {
            rgb.push(p[c].clamp(0.0, 1.0) * a + background[c] * (1.0 - a));
        }
    }
    rgb
}

/// Checks a pose for NaN / non-invertible rotation, naming the file.
pub fn check_pose(m: &Mat4, source: &Path, what: &str) -> Result<()> {
    if !pose_is_valid(m) {
        let message = format!("{}: the pose of {what} contains NaN/inf or is not invertible", source.display());
        return Err(InputError::Malformed { path: source.into(), message }.into());
    }
    Ok(())
}

/// Checks that all views of a dataset share one image size.
pub fn check_sizes(views: &[View], intr: &Intrinsics, source: &Path) -> Result<()> {
    for v in views {
        let k = &v.camera.intrinsics;
        if (k.width, k.height) != (intr.width, intr.height) {
            let message = format!(
                "{}: images have mixed sizes ({} is {}x{}, expected {}x{})",
                source.display(),
                v.name,
                k.width,
                k.height,
                intr.width,
                intr.height
            );
            return Err(InputError::WrongSize { path: source.into(), message }.into());
        }
    }
    Ok(())
}
