//! Stylization metrics (paper section 4.3, supplementary A; SNeRF's
//! consistency measure), computed from a stylized run and its reference case:
//! - `ref_lpips`: the paper's Ref-LPIPS: LPIPS (`eval::lpips`, net vgg, as
//!   the `lpips` package computes it) between each style reference and the
//!   stylized renders of the 10 render-path views nearest its camera, by the
//!   distance between camera centres (the paper's "nearest test novel
//!   views": the path frames that see what the reference saw from about
//!   where it saw it), averaged; `ref_lpips_alex` the same through AlexNet;
//!   `ref_lpips_uncalibrated` the figure refnpr printed before: LPIPS's
//!   unweighted form (`lpips=False`) on Oxford's VGG16, comparable only with
//!   itself;
//! - `reference_views`: how closely the stylized field holds each reference
//!   at the reference's own camera (the one view it is told exactly): LPIPS
//!   (vgg) and PSNR between the painting and the render there;
//! - `texture`: the texture figure (`eval::texture`): whether the renders
//!   near each reference and far from it carry the painting's texture or
//!   are a tinted photo, against the tinted photo under the painting;
//! - `gt_psnr`, `gt_psnr_occluded`: PSNR of the stylized test views against a
//!   ground-truth stylized dataset (the procedural scene's `stylized/`), over
//!   all pixels and over the surface pixels no reference camera sees; also
//!   `gt_psnr_seen` (the surface some reference sees), `gt_psnr_near` /
//!   `gt_psnr_far` (views within 45° of a reference's viewing direction and
//!   the others) and `gt_views` (each view's angle and PSNRs);
//! - `stability`: colour RMSE between render-path frames warped into each
//!   other with the field's depth (frames 1 and 7 apart), over points visible
//!   in both;
//! - `speckle`: the fraction of surface pixels of the path frames that
//!   differ from the median of their 3x3 neighbourhood by more than 0.1 in
//!   some channel (`metrics::speckle`); with a ground truth also on the test
//!   views (`speckle_test`) and on the ground truth itself (`gt_speckle`,
//!   same pixels), which says how much of it is real detail;
//! - `robustness_psnr`, `robustness_psnr_authors`: filled by the robustness
//!   study, `tools::robustness` (refnpr's protocol and the authors').

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail, ensure};
use glam::Vec3;
use rayon::prelude::*;
use serde::Serialize;

use crate::eval::lpips::{Lpips, LpipsNet};
use crate::eval::texture;
use crate::field::checkpoint::{self, Checkpoint};
use crate::field::view::ViewRenderer;
use crate::reference::case::{self, ReferenceCase};
use crate::scene::camera::{Camera, from_ndc};
use crate::scene::data::Dataset;
use crate::util::backend::BackendKind;
use crate::util::image::Image;
use crate::util::metrics;
use crate::util::progress::Progress;
use crate::util::tensor::scalar;
use crate::vgg::{FeatureMaps, Vgg16, VggLayer};

/// The layers of LPIPS's VGG variant.
pub const LPIPS_LAYERS: [VggLayer; 5] =
    [VggLayer::Relu1_2, VggLayer::Relu2_2, VggLayer::Relu3_3, VggLayer::Relu4_3, VggLayer::Relu5_3];

/// Path views per reference for `ref_lpips` (paper: 10).
pub const REF_LPIPS_VIEWS: usize = 10;

/// Frame gaps of the short- and long-range consistency (SNeRF, StyleRF: 1 and 7).
pub const STABILITY_GAPS: [usize; 2] = [1, 7];

/// A rendered view with the world point each pixel sees (equation-4 depth;
/// None = background).
pub struct SurfaceRender {
    pub camera: Camera,
    pub image: Image,
    pub points: Vec<Option<Vec3>>,
}

/// Renders `camera` from `ck` with its surface points in world space
/// (forward-facing scenes: marched in NDC, points mapped back). Many views:
/// [`surface_of`] with one `ck.renderer()`.
pub fn render_surface(ck: &Checkpoint, camera: &Camera) -> SurfaceRender {
    surface_of(&ck.renderer(), camera)
}

/// [`render_surface`] by a renderer built once for many views.
pub fn surface_of(renderer: &ViewRenderer, camera: &Camera) -> SurfaceRender {
    let ndc = renderer.ndc();
    let r = renderer.view(camera);
    let rays = camera.rays(ndc);
    let points = r
        .threshold_depth
        .iter()
        .zip(&rays)
        .map(|(d, ray)| {
            let p = ray.origin + (*d)? * ray.dir;
            match ndc {
                Some(n) => from_ndc(p, n),
                None => Some(p),
            }
        })
        .collect();
    SurfaceRender { camera: *camera, image: r.image, points }
}

/// How far apart two depths may be and still be the same surface:
/// `absolute + relative * depth` (world units).
#[derive(Debug, Clone, Copy)]
pub struct Tolerance {
    pub absolute: f32,
    pub relative: f32,
}

/// The pixel of `view` that sees world point `p`, when its own surface there
/// lies at `p`'s depth within `tolerance` (not occluded, inside the frame).
fn pixel_seeing(view: &SurfaceRender, p: Vec3, tolerance: Tolerance) -> Option<usize> {
    let (x, y, z) = view.camera.project(p)?;
    let (w, h) = (view.camera.intrinsics.width as i64, view.camera.intrinsics.height as i64);
    let (px, py) = (x.round() as i64, y.round() as i64);
    if px < 0 || py < 0 || px >= w || py >= h {
        return None;
    }
    let i = (py * w + px) as usize;
    let q = view.points[i]?;
    let (_, _, zq) = view.camera.project(q)?;
    ((z - zq).abs() <= tolerance.absolute + tolerance.relative * z).then_some(i)
}

/// For each point: whether any of the `references` sees it.
pub fn visible_from(points: &[Option<Vec3>], references: &[SurfaceRender], tolerance: Tolerance) -> Vec<bool> {
    points
        .iter()
        .map(|p| p.is_some_and(|p| references.iter().any(|r| pixel_seeing(r, p, tolerance).is_some())))
        .collect()
}

/// Sum of squared colour differences (over channels) and the number of
/// pixels, between the pixels of `to` and the pixels of `from` that see the
/// same surface point.
pub fn warp_error(from: &SurfaceRender, to: &SurfaceRender, tolerance: Tolerance) -> (f64, usize) {
    let mut sum = 0.0f64;
    let mut count = 0;
    for (i, p) in to.points.iter().enumerate() {
        let Some(j) = p.and_then(|p| pixel_seeing(from, p, tolerance)) else { continue };
        sum += (0..3).map(|c| ((to.image.rgb[i * 3 + c] - from.image.rgb[j * 3 + c]) as f64).powi(2)).sum::<f64>();
        count += 1;
    }
    (sum, count)
}

/// PSNR over the pixels where `mask` is true (None when there are none).
pub fn psnr_masked(a: &[f32], b: &[f32], mask: &[bool]) -> Option<(f64, usize)> {
    assert_eq!(a.len(), b.len());
    assert_eq!(a.len(), mask.len() * 3);
    let mut sum = 0.0f64;
    let mut n = 0;
    for (p, &m) in mask.iter().enumerate() {
        if m {
            sum += (0..3).map(|c| ((a[p * 3 + c] - b[p * 3 + c]) as f64).powi(2)).sum::<f64>();
            n += 3;
        }
    }
    (n > 0).then_some((sum, n))
}

/// LPIPS's baseline distance between two sets of feature maps (see the module notes).
pub fn normalised_feature_distance(a: &FeatureMaps, b: &FeatureMaps, layers: &[VggLayer]) -> f32 {
    layers
        .iter()
        .map(|&l| {
            let unit = |t: burn::tensor::Tensor<4>| {
                let norm = (t.clone() * t.clone()).sum_dim(1).sqrt() + 1e-10;
                t / norm
            };
            let d = unit(a.get(l).clone()) - unit(b.get(l).clone());
            let [_, _, h, w] = d.dims();
            scalar((d.clone() * d).sum().reshape([1])) / (h * w) as f32
        })
        .sum()
}

/// `normalised_feature_distance` of two images of the same size, through VGG16.
pub fn perceptual_distance(vgg: &Vgg16, a: &Image, b: &Image, device: &burn::tensor::Device) -> Result<f32> {
    ensure!(
        a.width == b.width && a.height == b.height,
        "images of {}x{} and {}x{}",
        a.width,
        a.height,
        b.width,
        b.height
    );
    let fa = vgg.features(a.tensor(device), &LPIPS_LAYERS)?;
    let fb = vgg.features(b.tensor(device), &LPIPS_LAYERS)?;
    Ok(normalised_feature_distance(&fa, &fb, &LPIPS_LAYERS))
}

/// Indices of the `k` cameras nearest `to` (camera centres; ties by index).
pub fn nearest_cameras(cameras: &[Camera], to: &Camera, k: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..cameras.len()).collect();
    order.sort_by(|&a, &b| {
        cameras[a]
            .position()
            .distance(to.position())
            .total_cmp(&cameras[b].position().distance(to.position()))
            .then(a.cmp(&b))
    });
    order.truncate(k);
    order
}

/// Short- and long-range consistency.
#[derive(Debug, Clone, Serialize)]
pub struct Stability {
    pub gap: usize,
    /// RMSE of colours in [0, 1] over the warped pixels of all frame pairs.
    pub rmse: f32,
    pub pixels: usize,
}

/// How closely a stylized field holds one reference at the reference's
/// own camera: LPIPS (net vgg) and PSNR between the painting and the render.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct ReferenceHeld {
    pub lpips: f32,
    pub psnr: f32,
    /// Speckle (`metrics::speckle`) of the render there and of the painting
    /// itself, over the same surface pixels: a painting's strokes count as
    /// speckle, so this is what the path's `speckle` compares with on a
    /// case without a ground truth.
    pub speckle: f32,
    pub painting_speckle: f32,
}

/// The texture distance (`eval::texture`) of the renders to the
/// painting, averaged over the references: 0 is the painting's texture,
/// `tinted_photo` what a tinted photo scores.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct TextureFigure {
    /// The render at each reference's own camera.
    pub at_reference: f32,
    /// Over the path frames Ref-LPIPS uses (nearest each reference camera).
    pub near: f32,
    /// Over as many path frames farthest from each reference camera.
    pub far: f32,
    /// The photo the painting was painted over (the case's content.png),
    /// tinted like the painting; None for a case without one.
    pub tinted_photo: Option<f32>,
}

/// What `refnpr eval --reference` writes.
#[derive(Debug, Clone, Serialize)]
pub struct StylizationEval {
    pub run: PathBuf,
    pub reference: PathBuf,
    /// LPIPS (net vgg) as the paper's Ref-LPIPS.
    pub ref_lpips: f32,
    /// The same through AlexNet.
    pub ref_lpips_alex: f32,
    /// LPIPS's unweighted form on Oxford's VGG16 (refnpr's earlier figure).
    pub ref_lpips_uncalibrated: f32,
    /// The path frames `ref_lpips` used, per reference.
    pub ref_lpips_frames: Vec<Vec<usize>>,
    /// Each reference against the render at its own camera.
    pub reference_views: Vec<ReferenceHeld>,
    pub texture: TextureFigure,
    pub gt: Option<PathBuf>,
    pub gt_psnr: Option<f32>,
    pub gt_psnr_occluded: Option<f32>,
    /// Over the surface pixels some reference sees.
    pub gt_psnr_seen: Option<f32>,
    /// Over the test views within [`NEAR_DEGREES`] of a reference camera, and the others.
    pub gt_psnr_near: Option<f32>,
    pub gt_psnr_far: Option<f32>,
    /// Each test view's angle to the nearest reference and its PSNRs.
    pub gt_views: Vec<TruthView>,
    /// Fraction of the test views' surface pixels no reference sees.
    pub occluded_fraction: Option<f32>,
    pub stability: Vec<Stability>,
    /// Speckled fraction of the path frames' surface pixels.
    pub speckle: f32,
    /// The same on the test views, and on the ground truth at those pixels.
    pub speckle_test: Option<f32>,
    pub gt_speckle: Option<f32>,
    /// refnpr's protocol: PSNR over all the path frames' pixels, averaged over the restylizations.
    pub robustness_psnr: Option<f32>,
    /// The authors' protocol: each frame at 400x400 in 8 bits, per-frame
    /// PSNR, the best 100 frames averaged, averaged over the restylizations.
    pub robustness_psnr_authors: Option<f32>,
    /// The path frames used as new references by the robustness test.
    pub robustness_frames: Vec<usize>,
    pub path_frames: usize,
}

/// Which path frames the robustness test restylizes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum RobustnessViews {
    /// The N path frames nearest the (first) reference camera: the new
    /// references show what the original reference showed.
    Near,
    /// N frames spread evenly along the path (k * frames / N), the second
    /// and later ones showing surfaces the reference never saw.
    Spread,
}

/// What to evaluate.
pub struct EvalJob {
    pub run: PathBuf,
    pub case: PathBuf,
    pub gt: Option<PathBuf>,
    pub robustness: usize,
    pub robustness_views: RobustnessViews,
    pub backend: BackendKind,
    pub data: Option<PathBuf>,
    /// Epochs of the robustness re-stylizations (None = the run's own schedule).
    pub robustness_epochs: Option<usize>,
    /// Keep the restylizations a killed evaluation finished (same method and
    /// config), and resume the one it was running.
    pub resume: bool,
}

/// Depth tolerance of the visibility tests: three voxels; in forward-facing
/// (NDC) scenes, whose voxels grow with depth in world units, 3 % of the depth.
pub fn tolerance(ck: &Checkpoint) -> Tolerance {
    match ck.meta.ndc {
        Some(_) => Tolerance { absolute: 0.0, relative: 0.03 },
        None => Tolerance { absolute: 3.0 * ck.grid.geometry.voxel_size().max_element(), relative: 0.0 },
    }
}

/// A stylized run as evaluated: its field, dataset, reference case and
/// path frames, and the metrics (the robustness study, which restylizes,
/// is `tools::robustness`: it fills the report's robustness fields).
pub struct EvaluatedRun {
    pub ck: Checkpoint,
    pub dataset: Dataset,
    pub case: ReferenceCase,
    pub frames: Vec<SurfaceRender>,
    pub report: StylizationEval,
}

/// `refnpr eval --run STYLE_RUN --reference CASE` without the robustness study.
pub fn evaluate_stylization(job: &EvalJob, progress: &dyn Progress) -> Result<StylizationEval> {
    Ok(evaluate_run(job, progress)?.report)
}

/// The stylization metrics of `job.run` (`robustness_psnr` left empty).
pub fn evaluate_run(job: &EvalJob, progress: &dyn Progress) -> Result<EvaluatedRun> {
    let device = job.backend.open(progress)?;
    let (ck, dataset) = checkpoint::load_run(&job.run, job.data.as_deref(), &device)?;
    let case = ReferenceCase::load(&job.case)?;
    if let Some(m) = case.scene_mismatch(&dataset) {
        bail!("{m}: the reference case does not belong to the run {}", job.run.display());
    }
    let path = dataset.render_path(case.path_frames);
    progress.info(format!("rendering {} path frames of {}", path.len(), job.run.display()));
    let started = std::time::Instant::now();
    let renderer = ck.renderer();
    let frames: Vec<SurfaceRender> = path.iter().map(|c| surface_of(&renderer, c)).collect();
    let at_references: Vec<SurfaceRender> = case.cameras(&dataset)?.iter().map(|c| surface_of(&renderer, c)).collect();
    drop(renderer);
    progress.info(format!("rendered the path in {:.1} s", started.elapsed().as_secs_f64()));
    let started = std::time::Instant::now();
    let paintings = paintings_at(&ck, &case, frames[0].camera.intrinsics.width, frames[0].camera.intrinsics.height)?;
    let lpips = ref_lpips(&ck, &dataset, &case, &frames, &paintings)?;
    let reference_views = references_held(&ck, &case, &paintings, &at_references)?;
    let at_references: Vec<Image> = at_references.into_iter().map(|r| r.image).collect();
    let texture = texture_figure(&ck, &dataset, &case, &frames, &paintings, &lpips.frames, &at_references)?;
    progress.info(format!("ref_lpips in {:.1} s", started.elapsed().as_secs_f64()));
    let truth = match &job.gt {
        Some(gt) => Some(ground_truth_psnrs(&ck, &dataset, &case, gt)?),
        None => None,
    };
    let started = std::time::Instant::now();
    let stability = stability(&frames, tolerance(&ck));
    let speckle = speckle_fraction(frames.iter().map(|f| speckle_of(f, &f.image.rgb)).fold((0, 0), add_counts));
    progress.info(format!("stability and speckle in {:.1} s", started.elapsed().as_secs_f64()));
    let report = StylizationEval {
        run: job.run.clone(),
        reference: job.case.clone(),
        ref_lpips: lpips.vgg,
        ref_lpips_alex: lpips.alex,
        ref_lpips_uncalibrated: lpips.uncalibrated,
        ref_lpips_frames: lpips.frames,
        reference_views,
        texture,
        gt: job.gt.clone(),
        gt_psnr: truth.as_ref().map(|t| t.all),
        gt_psnr_occluded: truth.as_ref().and_then(|t| t.occluded),
        gt_psnr_seen: truth.as_ref().and_then(|t| t.seen),
        gt_psnr_near: truth.as_ref().and_then(|t| t.near),
        gt_psnr_far: truth.as_ref().and_then(|t| t.far),
        occluded_fraction: truth.as_ref().map(|t| t.occluded_fraction),
        stability,
        speckle,
        speckle_test: truth.as_ref().map(|t| t.speckle),
        gt_speckle: truth.as_ref().map(|t| t.gt_speckle),
        gt_views: truth.map(|t| t.views).unwrap_or_default(),
        robustness_psnr: None,
        robustness_psnr_authors: None,
        robustness_frames: Vec::new(),
        path_frames: path.len(),
    };
    Ok(EvaluatedRun { ck, dataset, case, frames, report })
}

/// Ref-LPIPS's three figures and the frames they used.
struct RefLpips {
    vgg: f32,
    alex: f32,
    uncalibrated: f32,
    frames: Vec<Vec<usize>>,
}

/// Each reference's painting at `w` x `h`, in the case's order (read once
/// for every figure that compares with it).
fn paintings_at(ck: &Checkpoint, case: &ReferenceCase, w: u32, h: u32) -> Result<Vec<Image>> {
    case.references.iter().map(|spec| painting_at(ck, spec, w, h)).collect()
}

/// One reference's painting at `w` x `h`.
fn painting_at(ck: &Checkpoint, spec: &case::ReferenceSpec, w: u32, h: u32) -> Result<Image> {
    Ok(Image::new(w as usize, h as usize, case::read_style(&spec.style, w, h, ck.meta.background)?.0))
}

/// Ref-LPIPS: the mean distance between each painting (`styles`, at the
/// frames' size) and the `REF_LPIPS_VIEWS` path frames nearest its camera,
/// through LPIPS (vgg and alex) and the uncalibrated distance; also which frames.
fn ref_lpips(
    ck: &Checkpoint,
    dataset: &Dataset,
    case: &ReferenceCase,
    frames: &[SurfaceRender],
    styles: &[Image],
) -> Result<RefLpips> {
    let device = ck.grid.device();
    let path: Vec<Camera> = frames.iter().map(|f| f.camera).collect();
    let used: Vec<Vec<usize>> =
        case.cameras(dataset)?.iter().map(|cam| nearest_cameras(&path, cam, REF_LPIPS_VIEWS)).collect();
    let mean = |d: Vec<f32>| d.iter().sum::<f32>() / d.len().max(1) as f32;
    let mut calibrated = [0.0; 2];
    for (slot, net) in calibrated.iter_mut().zip([LpipsNet::Vgg, LpipsNet::Alex]) {
        let lpips = Lpips::load(net, &device);
        let mut distances = Vec::new();
        for (style, near) in styles.iter().zip(&used) {
            // The style's features once, not once per frame.
            let style = lpips.features(style)?;
            for &i in near {
                distances.push(lpips.distance_of(&style, &lpips.features(&frames[i].image)?)?);
            }
        }
        *slot = mean(distances);
    }
    let vgg = Vgg16::load(&device);
    let mut distances = Vec::new();
    for (style, near) in styles.iter().zip(&used) {
        let style_features = vgg.features(style.tensor(&device), &LPIPS_LAYERS)?;
        for &i in near {
            let frame_features = vgg.features(frames[i].image.tensor(&device), &LPIPS_LAYERS)?;
            distances.push(normalised_feature_distance(&style_features, &frame_features, &LPIPS_LAYERS));
        }
    }
    Ok(RefLpips { vgg: calibrated[0], alex: calibrated[1], uncalibrated: mean(distances), frames: used })
}

/// Each reference's painting against `renders`, the stylized field at the
/// reference cameras (in the case's order); `paintings` are read again only
/// where a reference camera's size is not theirs.
fn references_held(
    ck: &Checkpoint,
    case: &ReferenceCase,
    paintings: &[Image],
    renders: &[SurfaceRender],
) -> Result<Vec<ReferenceHeld>> {
    let lpips = Lpips::load(LpipsNet::Vgg, &ck.grid.device());
    let mut held = Vec::new();
    for ((spec, painting), surface) in case.references.iter().zip(paintings).zip(renders) {
        let render = &surface.image;
        let style = match (painting.width, painting.height) == (render.width, render.height) {
            true => painting.clone(),
            false => painting_at(ck, spec, render.width as u32, render.height as u32)?,
        };
        let lpips = lpips.distance_of(&lpips.features(&style)?, &lpips.features(render)?)?;
        held.push(ReferenceHeld {
            lpips,
            psnr: metrics::psnr(&style.rgb, &render.rgb),
            speckle: speckle_fraction(speckle_of(surface, &render.rgb)),
            painting_speckle: speckle_fraction(speckle_of(surface, &style.rgb)),
        });
    }
    Ok(held)
}

/// The texture figure of `frames` (the path) and `at_references` (the
/// renders at the reference cameras) against the case's `paintings`: near
/// each reference the frames Ref-LPIPS used (`nearest`), far from it as many
/// of the frames farthest from its camera.
fn texture_figure(
    ck: &Checkpoint,
    dataset: &Dataset,
    case: &ReferenceCase,
    frames: &[SurfaceRender],
    paintings: &[Image],
    nearest: &[Vec<usize>],
    at_references: &[Image],
) -> Result<TextureFigure> {
    let device = ck.grid.device();
    let vgg = Vgg16::load(&device);
    let path: Vec<Camera> = frames.iter().map(|f| f.camera).collect();
    let (mut near, mut far, mut held) = (Vec::new(), Vec::new(), Vec::new());
    let cameras = case.cameras(dataset)?;
    for (((painting, cam), render), near_frames) in paintings.iter().zip(&cameras).zip(at_references).zip(nearest) {
        let grams = texture::Grams::of(&vgg, painting, &device)?;
        held.push(texture::texture_distance(&vgg, render, painting, &grams, &device)?);
        let order = nearest_cameras(&path, cam, path.len());
        let far_frames = &order[order.len() - near_frames.len()..];
        for (list, frames_used) in [(&mut near, near_frames.as_slice()), (&mut far, far_frames)] {
            for &i in frames_used {
                list.push(texture::texture_distance(&vgg, &frames[i].image, painting, &grams, &device)?);
            }
        }
    }
    let tinted_photo = match crate::stylize::styles::painted_over(case, dataset, ck.meta.background) {
        Some((content, painting)) => {
            let grams = texture::Grams::of(&vgg, &painting, &device)?;
            Some(texture::texture_distance(&vgg, &content, &painting, &grams, &device)?)
        }
        None => None,
    };
    let mean = |d: &[f32]| d.iter().sum::<f32>() / d.len().max(1) as f32;
    Ok(TextureFigure { at_reference: mean(&held), near: mean(&near), far: mean(&far), tinted_photo })
}

/// Views within this angle of a reference camera's viewing direction are
/// `near` it, the others `far` (the unseen-surface figures by distance).
pub const NEAR_DEGREES: f32 = 45.0;

/// PSNRs of the stylized test views against a ground-truth stylized dataset.
#[derive(Debug, Clone)]
struct TruthPsnrs {
    all: f32,
    /// Over the surface pixels no reference sees (None when there are none).
    occluded: Option<f32>,
    /// Over the surface pixels some reference sees.
    seen: Option<f32>,
    occluded_fraction: f32,
    speckle: f32,
    gt_speckle: f32,
    views: Vec<TruthView>,
    /// Over all pixels of the views within [`NEAR_DEGREES`] of a reference, and of the others.
    near: Option<f32>,
    far: Option<f32>,
}

/// One test view against the ground truth.
#[derive(Debug, Clone, Serialize)]
pub struct TruthView {
    /// Angle (degrees) between its viewing direction and the nearest reference camera's.
    pub angle: f32,
    pub psnr: f32,
    pub psnr_seen: Option<f32>,
    pub psnr_unseen: Option<f32>,
}

/// Squared error and value count, summed.
#[derive(Debug, Clone, Copy, Default)]
struct ErrorSum(f64, usize);

impl ErrorSum {
    fn add(&mut self, part: Option<(f64, usize)>) {
        if let Some((s, n)) = part {
            (self.0, self.1) = (self.0 + s, self.1 + n);
        }
    }

    fn psnr(self) -> Option<f32> {
        (self.1 > 0).then(|| metrics::psnr_from_mse((self.0 / self.1 as f64) as f32))
    }
}

/// (speckled, counted) pixels of `rgb` over the surface pixels of `render`:
/// `rgb` is the render's own colours or the ground truth's at its camera.
fn speckle_of(render: &SurfaceRender, rgb: &[f32]) -> (usize, usize) {
    let mask: Vec<bool> = render.points.iter().map(Option::is_some).collect();
    metrics::speckle(rgb, render.image.width, render.image.height, &mask)
}

fn add_counts(a: (usize, usize), b: (usize, usize)) -> (usize, usize) {
    (a.0 + b.0, a.1 + b.1)
}

fn speckle_fraction((speckled, counted): (usize, usize)) -> f32 {
    speckled as f32 / counted.max(1) as f32
}

fn ground_truth_psnrs(ck: &Checkpoint, dataset: &Dataset, case: &ReferenceCase, gt_dir: &Path) -> Result<TruthPsnrs> {
    let tol = tolerance(ck);
    let gt = crate::scene::data::load(gt_dir, &ck.meta.data)
        .with_context(|| format!("ground truth {}", gt_dir.display()))?;
    ensure!(
        gt.test.len() == dataset.test.len(),
        "ground truth {} has {} test views, the run's dataset {}",
        gt_dir.display(),
        gt.test.len(),
        dataset.test.len()
    );
    let renderer = ck.renderer();
    let refs: Vec<SurfaceRender> = case.cameras(dataset)?.iter().map(|c| surface_of(&renderer, c)).collect();
    let [mut all, mut occ, mut seen_sum, mut near, mut far] = [ErrorSum::default(); 5];
    let (mut surface, mut hidden) = (0usize, 0usize);
    let (mut speckle, mut gt_speckle) = ((0, 0), (0, 0));
    let mut views = Vec::new();
    for (v, t) in gt.test.iter().enumerate() {
        ensure!(
            t.camera.intrinsics.width == dataset.test[v].camera.intrinsics.width,
            "ground truth test view {v} has another size"
        );
        let r = surface_of(&renderer, &t.camera);
        let seen = visible_from(&r.points, &refs, tol);
        let unseen: Vec<bool> = r.points.iter().zip(&seen).map(|(p, s)| p.is_some() && !s).collect();
        let seen: Vec<bool> = r.points.iter().zip(&seen).map(|(p, s)| p.is_some() && *s).collect();
        surface += r.points.iter().filter(|p| p.is_some()).count();
        hidden += unseen.iter().filter(|u| **u).count();
        let whole = (metrics::squared_error(&r.image.rgb, &t.rgb), r.image.rgb.len());
        let (on_seen, on_unseen) =
            (psnr_masked(&r.image.rgb, &t.rgb, &seen), psnr_masked(&r.image.rgb, &t.rgb, &unseen));
        all.add(Some(whole));
        occ.add(on_unseen);
        seen_sum.add(on_seen);
        let angle = angle_to_references(&t.camera, &refs);
        if angle <= NEAR_DEGREES {
            near.add(Some(whole))
        } else {
            far.add(Some(whole))
        }
        let psnr_of = |part: Option<(f64, usize)>| part.and_then(|p| ErrorSum(p.0, p.1).psnr());
        views.push(TruthView {
            angle,
            psnr: psnr_of(Some(whole)).unwrap_or(f32::INFINITY),
            psnr_seen: psnr_of(on_seen),
            psnr_unseen: psnr_of(on_unseen),
        });
        speckle = add_counts(speckle, speckle_of(&r, &r.image.rgb));
        gt_speckle = add_counts(gt_speckle, speckle_of(&r, &t.rgb));
    }
    Ok(TruthPsnrs {
        all: all.psnr().unwrap_or(f32::INFINITY),
        occluded: occ.psnr(),
        seen: seen_sum.psnr(),
        occluded_fraction: hidden as f32 / surface.max(1) as f32,
        speckle: speckle_fraction(speckle),
        gt_speckle: speckle_fraction(gt_speckle),
        views,
        near: near.psnr(),
        far: far.psnr(),
    })
}

/// The smallest angle (degrees) between `camera`'s viewing direction and a reference camera's.
fn angle_to_references(camera: &Camera, refs: &[SurfaceRender]) -> f32 {
    refs.iter()
        .map(|r| camera.forward().dot(r.camera.forward()).clamp(-1.0, 1.0).acos().to_degrees())
        .fold(f32::INFINITY, f32::min)
}

/// Short- and long-range consistency along the path.
fn stability(frames: &[SurfaceRender], tol: Tolerance) -> Vec<Stability> {
    STABILITY_GAPS
        .iter()
        .filter(|&&g| g < frames.len())
        .map(|&gap| {
            // Frame pairs in parallel, summed in order (the same bits as a serial loop).
            let pairs: Vec<(f64, usize)> = (0..frames.len() - gap)
                .into_par_iter()
                .map(|i| warp_error(&frames[i], &frames[i + gap], tol))
                .collect();
            let (mut sum, mut n) = (0.0, 0);
            for (s, c) in pairs {
                sum += s;
                n += c;
            }
            Stability { gap, rmse: ((sum / (3 * n).max(1) as f64) as f32).sqrt(), pixels: n }
        })
        .collect()
}
