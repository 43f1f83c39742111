//! What several commands share: the backend brought up, a run's folder, a
//! photoreal run loaded for R³.

use std::path::{Path, PathBuf};

use anyhow::Result;
use refnpr::field::checkpoint::{self, Checkpoint};
use refnpr::scene::data::Dataset;
use refnpr::{BackendKind, Console, Progress};

/// The folder of a run given as a folder or as its checkpoint file.
pub fn run_folder(run: &Path) -> PathBuf {
    if run.is_dir() { run.to_path_buf() } else { run.parent().map(Path::to_path_buf).unwrap_or_default() }
}

/// The backend asked for (or `REFNPR_BACKEND`'s), brought up: wgpu names
/// its adapter here, or says why it has none.
pub fn backend_or_env(b: Option<BackendKind>, progress: &dyn Progress) -> Result<BackendKind> {
    let kind = match b {
        Some(b) => b,
        None => BackendKind::from_env()?,
    };
    kind.open(progress)?;
    Ok(kind)
}

/// A photoreal run and its dataset on the default backend (R³ needs no autodiff).
pub fn load_run(ckpt: &Path, data_dir: Option<PathBuf>) -> Result<(Checkpoint, Dataset)> {
    checkpoint::load_run(ckpt, data_dir.as_deref(), &backend_or_env(None, &Console::default())?.device())
}
