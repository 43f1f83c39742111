//! R³ on a trained photoreal run: `refnpr reference` (render the content
//! view I_R and write a case skeleton to paint over) and `refnpr register`
//! (depth of every view from the field, registration, `registration.bin`,
//! report and overlays). The algorithm itself is `r3`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

use crate::field::checkpoint::Checkpoint;
use crate::field::march::Marcher;
use crate::reference::case::{self, ReferenceCase, ViewSpec};
use crate::reference::r3::{Dictionary, Reference, RegisterParams, Surface, ViewRegistration, register_view};
use crate::scene::camera::Camera;
use crate::scene::data::Dataset;
use crate::util::files;
use crate::util::image::{self, Image};
use crate::util::progress::{Progress, WarningLog};
use crate::util::tensor_file::{self, ArrayRef};

pub const REGISTRATION_FILE: &str = "registration.bin";
/// The file's `format` (a safetensors file: `util::tensor_file`).
const FORMAT: &str = "refnpr-registration";
/// The tag of the files older versions wrote (bincode), refused with advice.
const OLD_MAGIC: &[u8; 8] = b"REFNPRR3";

/// The surface a camera sees in the photoreal field (equation-4 depth).
pub fn field_surface(ck: &Checkpoint, camera: &Camera) -> Surface {
    surface_with(&Marcher::new(&ck.grid), ck, camera)
}

fn surface_with(marcher: &Marcher, ck: &Checkpoint, camera: &Camera) -> Surface {
    let rays = camera.rays(ck.meta.ndc.as_ref());
    let depth = marcher.depths(&rays, &ck.meta.render.march);
    Surface::from_depth(&rays, &depth, camera.intrinsics.width as usize, camera.intrinsics.height as usize)
}

/// `refnpr reference`: renders the content view and its depth at `view` and
/// writes a case skeleton (`reference.toml` naming `style.png`).
pub fn write_reference_skeleton(ck: &Checkpoint, dataset: &Dataset, view: &ViewSpec, out: &Path) -> Result<PathBuf> {
    let camera = view.camera(dataset, case::DEFAULT_PATH_FRAMES)?;
    files::create_dir(out)?;
    let r = ck.render_view(&camera);
    let (w, h) = (r.image.width, r.image.height);
    r.image.save_png(&out.join("content.png"))?;
    image::save_png(&out.join("depth.png"), w as u32, h as u32, &image::depth_to_rgb(&r.threshold_depth))?;
    let depth: Vec<f32> = r.threshold_depth.iter().map(|d| d.unwrap_or(0.0)).collect();
    crate::util::npy::write_f32(&out.join("depth.npy"), &[h, w], &depth)?;
    let view_line = match view {
        ViewSpec::Pose(c) => {
            let m = c.c2w.transpose().to_cols_array_2d();
            let k = c.intrinsics;
            format!(
                "c2w = {m:?}\nintrinsics = {{ width = {}, height = {}, fx = {}, fy = {}, cx = {}, cy = {} }}",
                k.width, k.height, k.fx, k.fy, k.cx, k.cy
            )
        }
        v => format!("view = \"{v}\""),
    };
    files::write_text(
        &out.join(case::CASE_TOML),
        &format!(
            "# Reference case: paint over content.png (same size, {w}x{h}) and save it as style.png.\n\
             # Several references: add more [[reference]] blocks.\n\
             color_pre = true\n\n[[reference]]\nstyle = \"style.png\"\n{view_line}\n"
        ),
    )?;
    Ok(out.join("content.png"))
}

/// Which photoreal run a registration was made on: its checkpoint file and
/// a fingerprint of its grid (geometry, step, density), which decides.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PhotoRun {
    pub file: PathBuf,
    pub fingerprint: u64,
}

impl PhotoRun {
    pub fn of(ck: &Checkpoint) -> Self {
        Self { file: ck.source.clone(), fingerprint: ck.fingerprint() }
    }
}

impl std::fmt::Display for PhotoRun {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} (grid fingerprint {:016x})", self.file.display(), self.fingerprint)
    }
}

/// The pseudo-rays of a registration, as written to `registration.bin`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RegistrationFile {
    /// The photoreal run it was made on.
    pub photo: PhotoRun,
    /// The settings it was made with.
    pub params: RegisterParams,
    /// The reference pixels themselves (every pixel of each reference view
    /// with its stylized colour; `hits` marks the ones with a surface).
    pub references: Vec<ReferencePixels>,
    /// One entry per training view, in the dataset's order.
    pub views: Vec<NamedRegistration>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReferencePixels {
    pub camera: Camera,
    pub colours: Vec<[f32; 3]>,
    pub hits: Vec<bool>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct NamedRegistration {
    pub name: String,
    pub registration: ViewRegistration,
}

/// What `registration.bin` holds besides its arrays: per reference its
/// camera (arrays `reference{i}.colours` `[pixels, 3]`, `reference{i}.hits`
/// 0/1), per training view its name, size and surface pixels (arrays
/// `view{i}.pixels`, `view{i}.colours` `[n, 3]`, `view{i}.reference`).
#[derive(Serialize, Deserialize)]
struct FileMeta {
    photo: PhotoRun,
    params: RegisterParams,
    references: Vec<Camera>,
    views: Vec<ViewMeta>,
}

#[derive(Serialize, Deserialize)]
struct ViewMeta {
    name: String,
    width: u32,
    height: u32,
    hits: u32,
}

impl RegistrationFile {
    pub fn save(&self, path: &Path) -> Result<()> {
        let meta = FileMeta {
            photo: self.photo.clone(),
            params: self.params,
            references: self.references.iter().map(|r| r.camera).collect(),
            views: self
                .views
                .iter()
                .map(|v| {
                    let r = &v.registration;
                    ViewMeta { name: v.name.clone(), width: r.width, height: r.height, hits: r.hits }
                })
                .collect(),
        };
        let hits: Vec<Vec<u32>> = self.references.iter().map(|r| r.hits.iter().map(|&h| h as u32).collect()).collect();
        let sources: Vec<Vec<u32>> =
            self.views.iter().map(|v| v.registration.reference.iter().map(|&r| r as u32).collect()).collect();
        let ref_names: Vec<_> = reference_names(self.references.len()).collect();
        let view_names: Vec<_> = view_names(self.views.len()).collect();
        let mut arrays = Vec::new();
        for ((r, hits), [colours, hit]) in self.references.iter().zip(&hits).zip(&ref_names) {
            arrays.push(ArrayRef::F32(colours, vec![r.colours.len(), 3], r.colours.as_flattened()));
            arrays.push(ArrayRef::U32(hit, vec![hits.len()], hits));
        }
        for ((v, sources), [pixels, colours, source]) in self.views.iter().zip(&sources).zip(&view_names) {
            let r = &v.registration;
            arrays.push(ArrayRef::U32(pixels, vec![r.pixels.len()], &r.pixels));
            arrays.push(ArrayRef::F32(colours, vec![r.colours.len(), 3], r.colours.as_flattened()));
            arrays.push(ArrayRef::U32(source, vec![sources.len()], sources));
        }
        tensor_file::save(path, FORMAT, &meta, &arrays)
    }

    /// The file itself for a `refnpr register` output folder or a file path.
    pub fn resolve(path: &Path) -> PathBuf {
        if path.is_dir() { path.join(REGISTRATION_FILE) } else { path.to_path_buf() }
    }

    /// Reads `registration.bin` (or the file in a `refnpr register` output folder).
    pub fn load(path: &Path) -> Result<Self> {
        let file = Self::resolve(path);
        let what = "a refnpr registration file (made by `refnpr register`)";
        let older = "run `refnpr register` again (a few seconds), or leave out --registration";
        let (meta, mut arrays): (FileMeta, _) = tensor_file::load(&file, FORMAT, what, (OLD_MAGIC, older))?;
        let mut references = Vec::new();
        for (camera, [colours, hits]) in meta.references.into_iter().zip(reference_names(usize::MAX)) {
            let colours = arrays.f32_triples(&colours)?;
            let hits: Vec<bool> = arrays.u32(&hits)?.into_iter().map(|h| h != 0).collect();
            if hits.len() != colours.len() {
                return Err(arrays.corrupt(format!(
                    "a reference of {} colours and {} hit marks",
                    colours.len(),
                    hits.len()
                )));
            }
            references.push(ReferencePixels { camera, colours, hits });
        }
        let mut views = Vec::new();
        for (view, [pixels, colours, sources]) in meta.views.into_iter().zip(view_names(usize::MAX)) {
            let pixels = arrays.u32(&pixels)?;
            let colours = arrays.f32_triples(&colours)?;
            let reference: Vec<u16> = match arrays.u32(&sources)?.into_iter().map(u16::try_from).collect() {
                Ok(sources) => sources,
                Err(_) => return Err(arrays.corrupt(format!("view {} names a reference past 65535", view.name))),
            };
            if colours.len() != pixels.len() || reference.len() != pixels.len() {
                return Err(arrays.corrupt(format!(
                    "view {} has {} pixels, {} colours, {} sources",
                    view.name,
                    pixels.len(),
                    colours.len(),
                    reference.len()
                )));
            }
            let registration = ViewRegistration {
                width: view.width,
                height: view.height,
                pixels,
                colours,
                reference,
                hits: view.hits,
            };
            views.push(NamedRegistration { name: view.name, registration });
        }
        Ok(Self { photo: meta.photo, params: meta.params, references, views })
    }

    /// Registered pixels over pixels with a surface, all training views together.
    pub fn fraction_overall(&self) -> f32 {
        let registered: usize = self.views.iter().map(|v| v.registration.pixels.len()).sum();
        let hits: usize = self.views.iter().map(|v| v.registration.hits as usize).sum();
        if hits == 0 { 0.0 } else { registered as f32 / hits as f32 }
    }

    /// Every registered pixel: (training view, pixel, colour).
    pub fn registered_pixels(&self) -> Vec<(u32, u32, [f32; 3])> {
        self.views
            .iter()
            .enumerate()
            .flat_map(|(v, r)| {
                r.registration.pixels.iter().zip(&r.registration.colours).map(move |(&p, &c)| (v as u32, p, c))
            })
            .collect()
    }

    /// Refuses a file made on another photoreal run (naming both), for other
    /// training views or another case (other cameras, or a style image
    /// repainted since), naming `source`.
    pub fn check_matches(
        &self,
        photo: &PhotoRun,
        dataset: &Dataset,
        references: &[ReferencePixels],
        source: &Path,
    ) -> Result<()> {
        if self.photo.fingerprint != photo.fingerprint {
            bail!(
                "{} was registered on the photoreal run {}, not on this stylization's photoreal run {}: \
                 run `refnpr register` on {} (or leave out --registration)",
                source.display(),
                self.photo,
                photo,
                photo.file.display()
            );
        }
        let names: Vec<&str> = self.views.iter().map(|v| v.name.as_str()).collect();
        let expected: Vec<&str> = dataset.train.iter().map(|v| v.name.as_str()).collect();
        if names != expected {
            bail!(
                "{} registers {} training views, the photoreal run's dataset has {} (or other names): \
                 run `refnpr register` again for this run",
                source.display(),
                names.len(),
                expected.len()
            );
        }
        if self.references != references {
            bail!(
                "{} was made for other reference cameras, style images or photoreal field than the case's and run's current ones: \
                 run `refnpr register` again (or leave out --registration)",
                source.display()
            );
        }
        Ok(())
    }
}

/// The array names of each reference: its colours and its hit marks.
fn reference_names(n: usize) -> impl Iterator<Item = [String; 2]> {
    (0..n).map(|i| [format!("reference{i}.colours"), format!("reference{i}.hits")])
}

/// The array names of each training view: its pixels, their colours and sources.
fn view_names(n: usize) -> impl Iterator<Item = [String; 3]> {
    (0..n).map(|i| [format!("view{i}.pixels"), format!("view{i}.colours"), format!("view{i}.reference")])
}

/// What `register.json` reports.
#[derive(Debug, Clone, Serialize)]
pub struct RegisterReport {
    pub params: RegisterParams,
    pub references: Vec<String>,
    pub dictionary_points: usize,
    pub dictionary_cells: usize,
    pub voxel_size: f32,
    /// Registered pixels / pixels with a surface, per training view.
    pub fraction_per_view: Vec<f32>,
    pub fraction_overall: f32,
    pub registered_pixels: usize,
    pub depth_seconds: f64,
    pub dictionary_seconds: f64,
    pub register_seconds: f64,
    pub warnings: Vec<String>,
}

/// The case's references lifted with the field's depth: what R³ stores, and
/// the reference pixels as the registration file keeps them.
pub fn lift_references(
    ck: &Checkpoint,
    marcher: &Marcher,
    dataset: &Dataset,
    case: &ReferenceCase,
    warnings: &mut WarningLog,
) -> Result<(Vec<Reference>, Vec<ReferencePixels>)> {
    let mut refs = Vec::new();
    let mut pixels = Vec::new();
    for (spec, cam) in case.references.iter().zip(&case.cameras(dataset)?) {
        let (w, h) = (cam.intrinsics.width, cam.intrinsics.height);
        let (rgb, note) = case::read_style(&spec.style, w, h, ck.meta.background)?;
        if let Some(n) = note {
            warnings.push(n);
        }
        let surface = surface_with(marcher, ck, cam);
        if surface.num_hits() == 0 {
            warnings.push(format!(
                "reference {} ({}) sees nothing of the scene: it contributes no rays",
                spec.style.display(),
                spec.view
            ));
        }
        let colours: Vec<[f32; 3]> = image::pixels(&rgb).collect();
        let hits = surface.points.iter().map(|p| p.is_some()).collect();
        pixels.push(ReferencePixels { camera: *cam, colours: colours.clone(), hits });
        refs.push(Reference { surface, colours });
    }
    Ok((refs, pixels))
}

/// Lifts the case's references with the field's depth and registers every
/// training view. Returns the pseudo-rays and the report (no files written).
/// `edited` (a local edit: per reference, row-major, its edited pixels)
/// keeps every other reference pixel out of the dictionary, so a training
/// ray takes a painted colour or none: a reference's unpainted pixels are
/// the photo, and would pull a surface another reference paints back to it.
pub fn register_case(
    ck: &Checkpoint,
    dataset: &Dataset,
    case: &ReferenceCase,
    params: &RegisterParams,
    edited: Option<&[Vec<bool>]>,
    progress: &dyn Progress,
) -> Result<(RegistrationFile, RegisterReport)> {
    params.validate()?;
    let mut warnings = WarningLog::new(progress);
    if let Some(w) = case.scene_mismatch(dataset) {
        warnings.push(w);
    }
    let t0 = Instant::now();
    let marcher = Marcher::new(&ck.grid);
    let (mut refs, ref_pixels) = lift_references(ck, &marcher, dataset, case, &mut warnings)?;
    for (r, edited) in refs.iter_mut().zip(edited.unwrap_or_default()) {
        r.surface.keep_points(edited);
    }
    let views: Vec<Surface> = dataset.train.iter().map(|v| surface_with(&marcher, ck, &v.camera)).collect();
    let depth_seconds = t0.elapsed().as_secs_f64();

    let t1 = Instant::now();
    let dict = Dictionary::build(&refs, params);
    let dictionary_seconds = t1.elapsed().as_secs_f64();
    let t2 = Instant::now();
    let regs: Vec<ViewRegistration> = match &dict {
        Some(d) => views.iter().map(|v| register_view(d, v, params)).collect(),
        None => {
            warnings.push(
                "no reference pixel hits the scene (camera pointing away, or a case for another scene?): nothing registered"
                    .to_string(),
            );
            views.iter().map(ViewRegistration::nothing_registered).collect()
        }
    };
    let register_seconds = t2.elapsed().as_secs_f64();
    let file = RegistrationFile {
        photo: PhotoRun::of(ck),
        params: *params,
        references: ref_pixels,
        views: dataset
            .train
            .iter()
            .zip(regs)
            .map(|(v, r)| NamedRegistration { name: v.name.clone(), registration: r })
            .collect(),
    };
    let report = RegisterReport {
        params: *params,
        references: case.references.iter().map(|r| format!("{} @ {}", r.style.display(), r.view)).collect(),
        dictionary_points: dict.as_ref().map_or(0, |d| d.num_points()),
        dictionary_cells: dict.as_ref().map_or(0, |d| d.num_cells()),
        voxel_size: dict.as_ref().map_or(0.0, |d| d.voxel_size()),
        fraction_per_view: file.views.iter().map(|r| r.registration.fraction_of_hits()).collect(),
        fraction_overall: file.fraction_overall(),
        registered_pixels: file.views.iter().map(|r| r.registration.pixels.len()).sum(),
        depth_seconds,
        dictionary_seconds,
        register_seconds,
        warnings: warnings.into_vec(),
    };
    Ok((file, report))
}

/// `refnpr register`: registration plus `registration.bin`, `register.json`
/// and overlay PNGs (registered pixels in their colours over the dimmed
/// content render) for the first `overlays` training views.
pub fn run_register(
    ck: &Checkpoint,
    dataset: &Dataset,
    case: &ReferenceCase,
    params: &RegisterParams,
    out: &Path,
    overlays: usize,
    progress: &dyn Progress,
) -> Result<RegisterReport> {
    files::create_dir(out)?;
    let (file, report) = register_case(ck, dataset, case, params, None, progress)?;
    file.save(&out.join(REGISTRATION_FILE))?;
    files::write_json(&out.join("register.json"), &report)?;
    let dir = out.join("overlays");
    let renderer = ck.renderer();
    for (view, reg) in dataset.train.iter().zip(&file.views).take(overlays) {
        let content = renderer.view(&view.camera).image;
        overlay(&content, &reg.registration).save_png(&dir.join(format!("{}.png", sanitize(&view.name))))?;
    }
    Ok(report)
}

/// The registered pixels in their stylized colours over the dimmed content
/// render of their view (the paper's figure A.2).
pub fn overlay(content: &Image, registration: &ViewRegistration) -> Image {
    let mut rgb: Vec<f32> = content.rgb.iter().map(|v| 0.25 + 0.35 * v).collect();
    for (&p, c) in registration.pixels.iter().zip(&registration.colours) {
        rgb[p as usize * 3..p as usize * 3 + 3].copy_from_slice(c);
    }
    Image::new(content.width, content.height, rgb)
}

fn sanitize(name: &str) -> String {
    name.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect()
}
