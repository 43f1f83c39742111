//! The R³ commands on a trained photoreal run: `refnpr reference` (render the
//! content view I_R and write a case skeleton to paint over) and
//! `refnpr register` (depth of every view from the field, registration,
//! pseudo-ray file, report and overlays). The algorithm is in `register`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::checkpoint::Checkpoint;
use crate::data::Dataset;
use crate::imageio;
use crate::reference::{self, ReferenceCase, ViewSpec};
use crate::register::{Dictionary, Reference, RegisterParams, Surface, ViewRegistration, register_view};
use crate::render;

pub const REGISTRATION_FILE: &str = "registration.bin";
const MAGIC: &[u8; 8] = b"REFNPRR1";

/// The surface a camera sees in the photoreal field (equation-4 depth).
pub fn field_surface(ck: &Checkpoint, camera: &Camera) -> Surface {
    surface_with(&render::Marcher::new(&ck.grid), ck, camera)
}

fn surface_with(marcher: &render::Marcher, ck: &Checkpoint, camera: &Camera) -> Surface {
    let rays = camera.rays(ck.meta.ndc.as_ref());
    let depth = marcher.depths(&rays, &ck.meta.config.march);
    Surface::from_depth(&rays, &depth, camera.intrinsics.width as usize, camera.intrinsics.height as usize)
}

fn content_render(ck: &Checkpoint, camera: &Camera) -> render::ImageRender {
    let cfg = &ck.meta.config;
    render::render_view(&ck.grid, camera, ck.meta.ndc.as_ref(), &cfg.march, ck.meta.background, cfg.render_chunk)
}

/// `refnpr reference`: renders the content view and its depth at `view` and
/// writes a case skeleton (`reference.toml` naming `style.png`).
pub fn write_reference_skeleton(ck: &Checkpoint, dataset: &Dataset, view: &ViewSpec, out: &Path) -> Result<PathBuf> {
    let camera = view.camera(dataset, reference::DEFAULT_PATH_FRAMES)?;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let r = content_render(ck, &camera);
    let (w, h) = (r.width, r.height);
    imageio::save_png(&out.join("content.png"), w, h, &r.rgb)?;
    imageio::save_png(&out.join("depth.png"), w, h, &imageio::depth_to_rgb(&r.threshold_depth))?;
    let depth: Vec<f32> = r.threshold_depth.iter().map(|d| d.unwrap_or(0.0)).collect();
    crate::data::npy::write_f32(&out.join("depth.npy"), &[h as usize, w as usize], &depth)?;
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
    let toml_path = out.join(reference::CASE_TOML);
    std::fs::write(
        &toml_path,
        format!(
            "# Reference case: paint over content.png (same size, {w}x{h}) and save it as style.png.\n\
             # Several references: add more [[reference]] blocks.\n\
             color_pre = true\n\n[[reference]]\nstyle = \"style.png\"\n{view_line}\n"
        ),
    )
    .with_context(|| format!("cannot write {}", toml_path.display()))?;
    Ok(out.join("content.png"))
}

/// The pseudo-rays of a registration, as written to `registration.bin`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RegistrationFile {
    /// The reference pixels themselves (every pixel of each reference view
    /// with its stylized colour; `hits` marks the ones with a surface).
    pub references: Vec<ReferencePixels>,
    /// One entry per training view, in the dataset's order.
    pub views: Vec<NamedRegistration>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
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

impl RegistrationFile {
    pub fn save(&self, path: &Path) -> Result<()> {
        crate::binfile::save(path, MAGIC, self)
    }

    pub fn load(path: &Path) -> Result<Self> {
        let path = if path.is_dir() { path.join(REGISTRATION_FILE) } else { path.to_path_buf() };
        crate::binfile::load(&path, MAGIC, "a refnpr registration file")
    }
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

/// Lifts the case's references with the field's depth and registers every
/// training view. Returns the pseudo-rays and the report (no files written).
pub fn register_case(ck: &Checkpoint, dataset: &Dataset, case: &ReferenceCase, params: &RegisterParams) -> Result<(RegistrationFile, RegisterReport)> {
    params.validate()?;
    let mut warnings = Vec::new();
    if let Some(w) = case.scene_mismatch(dataset) {
        eprintln!("warning: {w}");
        warnings.push(w);
    }
    let t0 = Instant::now();
    let marcher = render::Marcher::new(&ck.grid);
    let cameras = case.cameras(dataset)?;
    let mut refs = Vec::new();
    let mut ref_pixels = Vec::new();
    for (spec, cam) in case.references.iter().zip(&cameras) {
        let (w, h) = (cam.intrinsics.width, cam.intrinsics.height);
        let (rgb, note) = reference::read_style(&spec.style, w, h, ck.meta.background)?;
        if let Some(n) = note {
            eprintln!("note: {n}");
            warnings.push(n);
        }
        let surface = surface_with(&marcher, ck, cam);
        if surface.num_hits() == 0 {
            let msg = format!("reference {} ({}) sees nothing of the scene: it contributes no rays", spec.style.display(), spec.view);
            eprintln!("warning: {msg}");
            warnings.push(msg);
        }
        let colours: Vec<[f32; 3]> = crate::imageio::pixels(&rgb).collect();
        ref_pixels.push(ReferencePixels { camera: *cam, colours: colours.clone(), hits: surface.points.iter().map(|p| p.is_some()).collect() });
        refs.push(Reference { surface, colours });
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
            let msg = "no reference pixel hits the scene (camera pointing away, or a case for another scene?): nothing registered".to_string();
            eprintln!("warning: {msg}");
            warnings.push(msg);
            views
                .iter()
                .map(|v| ViewRegistration { width: v.width as u32, height: v.height as u32, hits: v.num_hits() as u32, ..Default::default() })
                .collect()
        }
    };
    let register_seconds = t2.elapsed().as_secs_f64();

    let registered: usize = regs.iter().map(|r| r.pixels.len()).sum();
    let hits: usize = regs.iter().map(|r| r.hits as usize).sum();
    let report = RegisterReport {
        params: *params,
        references: case.references.iter().map(|r| format!("{} @ {}", r.style.display(), r.view)).collect(),
        dictionary_points: dict.as_ref().map_or(0, |d| d.num_points()),
        dictionary_cells: dict.as_ref().map_or(0, |d| d.num_cells()),
        voxel_size: dict.as_ref().map_or(0.0, |d| d.voxel_size()),
        fraction_per_view: regs.iter().map(|r| r.fraction_of_hits()).collect(),
        fraction_overall: if hits == 0 { 0.0 } else { registered as f32 / hits as f32 },
        registered_pixels: registered,
        depth_seconds,
        dictionary_seconds,
        register_seconds,
        warnings,
    };
    let file = RegistrationFile {
        references: ref_pixels,
        views: dataset.train.iter().zip(regs).map(|(v, r)| NamedRegistration { name: v.name.clone(), registration: r }).collect(),
    };
    Ok((file, report))
}

/// `refnpr register`: registration plus `registration.bin`, `register.json`
/// and overlay PNGs (registered pixels in their colours over the dimmed
/// content render) for the first `overlays` training views.
pub fn run_register(ck: &Checkpoint, dataset: &Dataset, case: &ReferenceCase, params: &RegisterParams, out: &Path, overlays: usize) -> Result<RegisterReport> {
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let (file, report) = register_case(ck, dataset, case, params)?;
    file.save(&out.join(REGISTRATION_FILE))?;
    let json = out.join("register.json");
    std::fs::write(&json, serde_json::to_string_pretty(&report)?).with_context(|| format!("cannot write {}", json.display()))?;
    let dir = out.join("overlays");
    std::fs::create_dir_all(&dir)?;
    for (view, reg) in dataset.train.iter().zip(&file.views).take(overlays) {
        let content = content_render(ck, &view.camera);
        let mut rgb: Vec<f32> = content.rgb.iter().map(|v| 0.25 + 0.35 * v).collect();
        for (&p, c) in reg.registration.pixels.iter().zip(&reg.registration.colours) {
            rgb[p as usize * 3..p as usize * 3 + 3].copy_from_slice(c);
        }
        imageio::save_png(&dir.join(format!("{}.png", sanitize(&view.name))), content.width, content.height, &rgb)?;
    }
    Ok(report)
}

fn sanitize(name: &str) -> String {
    name.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect()
}
