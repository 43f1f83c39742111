//! `refnpr view`: a run's field in the browser. The page (`page/`:
//! HTML and JavaScript with its GLSL, written here) ray-marches the field
//! in WebGL2 with refnpr's own arithmetic (`field::march`,
//! `field::host_render`); `pack` lays the sparse lattice out as textures;
//! `server` serves the page and the runs on localhost, live (the page
//! reloads a run whose checkpoint changes); `write_static` writes the same
//! files as a folder any static web host serves.
//!
//! The files, served or written, are one tree: `index.html`, `viewer.js`,
//! `runs.json` (the runs' names and whether the page should poll them),
//! and per run `runs/N/field.bin` (a header's length as u32, its JSON,
//! zero padding to 4 bytes, then `pack`'s textures), `runs/N/cameras.json`
//! (`export`'s cameras) and, served only, `runs/N/version`.

pub mod pack;
pub mod server;

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use burn::tensor::Device;

use crate::export::cameras_json;
use crate::field::checkpoint::{self, Checkpoint};
use crate::util::files;

/// The page.
pub const INDEX_HTML: &str = include_str!("page/index.html");
/// The page's script (controls, the WebGL2 renderer and its shaders).
pub const VIEWER_JS: &str = include_str!("page/viewer.js");

/// A run to show: its checkpoint and, when the dataset moved, where it is.
#[derive(Debug, Clone)]
pub struct ViewRun {
    pub name: String,
    pub checkpoint: PathBuf,
    pub data: Option<PathBuf>,
}

impl ViewRun {
    /// The run at `path` (a run folder or a checkpoint file).
    pub fn new(path: &Path, data: Option<&Path>) -> Self {
        let checkpoint = checkpoint::resolve(path);
        let folder = if path.is_dir() { path } else { path.parent().unwrap_or(path) };
        let name = folder.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "run".into());
        Self { name, checkpoint, data: data.map(Path::to_path_buf) }
    }
}

/// `runs.json`: the runs' names, and `live` (poll `runs/N/version`).
pub fn runs_json<'a>(names: impl IntoIterator<Item = &'a str>, live: bool) -> String {
    let names: Vec<&str> = names.into_iter().collect();
    serde_json::json!({ "live": live, "runs": names }).to_string()
}

/// `field.bin` of a checkpoint (`pack::PackedField::to_file`).
pub fn field_file(ck: &Checkpoint) -> Result<Vec<u8>> {
    pack::pack(ck).and_then(|p| p.to_file()).with_context(|| format!("packing {} for the viewer", ck.source.display()))
}

/// `cameras.json` of a run: the dataset's cameras, or none (and why) when
/// the dataset cannot be read (the page then places its own camera).
pub fn cameras_file(ck: &Checkpoint, data: Option<&Path>) -> String {
    match checkpoint::load_dataset(ck, data) {
        Ok(dataset) => cameras_json(&dataset, ck).to_string(),
        Err(e) => serde_json::json!({
            "background": ck.meta.background, "forward_facing": ck.meta.ndc.is_some(),
            "train": [], "test": [], "note": format!("no cameras: {e:#}"),
        })
        .to_string(),
    }
}

/// Writes the page and `runs` into `dir` as a self-contained static site.
pub fn write_static(runs: &[ViewRun], dir: &Path, device: &Device) -> Result<u64> {
    files::create_dir(dir)?;
    files::write_text(&dir.join("index.html"), INDEX_HTML)?;
    files::write_text(&dir.join("viewer.js"), VIEWER_JS)?;
    files::write_text(&dir.join("runs.json"), &runs_json(runs.iter().map(|r| r.name.as_str()), false))?;
    let mut bytes = (INDEX_HTML.len() + VIEWER_JS.len()) as u64;
    for (i, run) in runs.iter().enumerate() {
        let ck = checkpoint::load_with(&run.checkpoint, device, false)?;
        let folder = dir.join("runs").join(i.to_string());
        files::create_dir(&folder)?;
        let field = field_file(&ck)?;
        files::write_bytes(&folder.join("field.bin"), &field)?;
        let cameras = cameras_file(&ck, run.data.as_deref());
        files::write_text(&folder.join("cameras.json"), &cameras)?;
        bytes += (field.len() + cameras.len()) as u64;
    }
    Ok(bytes)
}
