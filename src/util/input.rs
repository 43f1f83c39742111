//! Why outside input was refused, as a type a library caller can match on:
//! the dataset loaders, reference cases, checkpoint and registration
//! readers, npy arrays and images raise an [`InputError`] where they refuse
//! their input. The pipeline's functions return `anyhow` errors (causes and
//! context added on the way up, the whole chain in the message a user
//! reads); [`InputError::of`] finds the typed reason inside one.
//!
//! ```no_run
//! use refnpr::util::input::InputError;
//! match refnpr::Scene::load("photos/") {
//!     Err(e) => match InputError::of(&e.0) {
//!         Some(InputError::NotADataset { .. }) => eprintln!("not a dataset folder: {e}"),
//!         Some(InputError::Missing { .. }) => eprintln!("no such folder: {e}"),
//!         _ => eprintln!("{e}"),
//!     },
//!     Ok(scene) => println!("{} views", scene.dataset.train.len()),
//! }
//! ```

use std::path::PathBuf;

/// A refused input: which file or folder, and the message a user reads.
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    /// The file or folder does not exist.
    #[error("{message}")]
    Missing { path: PathBuf, message: String },
    /// A folder of none of the dataset layouts (Blender, LLFF, NSVF).
    #[error("{message}")]
    NotADataset { path: PathBuf, message: String },
    /// A file of another kind than the one asked for (its tag or format).
    #[error("{message}")]
    WrongKind { path: PathBuf, message: String },
    /// The right kind of file with content that cannot be used: unparseable,
    /// cut short, inconsistent sizes, a NaN or singular pose.
    #[error("{message}")]
    Malformed { path: PathBuf, message: String },
    /// Images whose sizes do not fit (mixed sizes in one dataset, a style
    /// image the size of no view, an image too small to downscale).
    #[error("{message}")]
    WrongSize { path: PathBuf, message: String },
}

impl InputError {
    /// The typed reason inside an error of the pipeline, when outside input was refused.
    pub fn of(err: &anyhow::Error) -> Option<&InputError> {
        err.downcast_ref::<InputError>()
    }

    /// The file or folder refused.
    pub fn path(&self) -> &std::path::Path {
        match self {
            InputError::Missing { path, .. }
            | InputError::NotADataset { path, .. }
            | InputError::WrongKind { path, .. }
            | InputError::Malformed { path, .. }
            | InputError::WrongSize { path, .. } => path,
        }
    }
}
