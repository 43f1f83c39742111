//! Files with errors that name them. Every file the library writes goes
//! through [`write_atomic`]: a temporary file beside the target, synced, then
//! renamed over it, so a reader (or a run killed half-way, or a full disk)
//! never leaves a half-written file, and a failed write keeps the previous
//! good one. Our binary files are safetensors files (checkpoints:
//! `field::checkpoint`; registrations and resume states:
//! `util::tensor_file`); checkpoints of older versions, an 8-byte magic tag
//! then bincode's layout, are still read ([`open_tagged`], `util::bin_fields`).

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use crate::util::input::InputError;
use serde::Serialize;
use serde::de::DeserializeOwned;

/// Writes `path` with `write`, atomically: into a temporary file in the same
/// folder (created if missing), flushed and synced, then renamed over `path`.
/// On any failure (`write`'s own error, a full disk, a read-only folder) the
/// temporary file is removed, `path` keeps its previous content, and the
/// error names `path` and the cause.
pub fn write_atomic(path: &Path, write: impl FnOnce(&mut BufWriter<File>) -> Result<()>) -> Result<()> {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    create_dir(dir)?;
    let tmp = temporary_sibling(path);
    let result = (|| -> Result<()> {
        let file = File::create(&tmp).map_err(|e| io_error(e, path))?;
        let mut w = BufWriter::new(file);
        write(&mut w)?;
        w.flush().map_err(|e| io_error(e, path))?;
        // The data must be on disk before the rename makes it the file:
        // otherwise a crash could leave an empty `path` behind.
        w.get_ref().sync_all().map_err(|e| io_error(e, path))?;
        drop(w);
        std::fs::rename(&tmp, path).map_err(|e| io_error(e, path))
    })();
    if result.is_err() {
        std::fs::remove_file(&tmp).ok();
    }
    result.map_err(|e| match path.exists() {
        true => anyhow::anyhow!("{e:#}; {} keeps its previous content", path.display()),
        false => e,
    })
}

/// Writes `bytes` to `path` atomically (see [`write_atomic`]).
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic(path, |w| w.write_all(bytes).map_err(|e| io_error(e, path)))
}

/// `.NAME.PID.tmp` beside `path`: hidden, and two processes never share one.
fn temporary_sibling(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    path.with_file_name(format!(".{name}.{}.tmp", std::process::id()))
}

/// An I/O error writing `path`, with the two causes a user can act on said
/// in words (the OS's text alone reads "os error 28").
pub fn io_error(e: std::io::Error, path: &Path) -> anyhow::Error {
    let hint = hint(&e);
    anyhow::Error::new(e).context(format!("cannot write {}{hint}", path.display()))
}

fn hint(e: &std::io::Error) -> &'static str {
    match e.raw_os_error() {
        Some(28) => " (the disk is full: free some space or choose another output folder)",
        Some(30) => " (the file system is read-only: choose another output folder)",
        _ if e.kind() == std::io::ErrorKind::PermissionDenied => {
            " (no permission to write there: choose another output folder)"
        }
        _ => "",
    }
}

/// Opens a file of an older version (a magic tag, then bincode's layout:
/// `util::bin_fields`) past its magic tag; with the file's size, the most its payload can hold.
pub fn open_tagged(path: &Path, magic: &[u8; 8], what: &str) -> Result<(BufReader<File>, u64)> {
    if !path.exists() {
        let message = format!("{} does not exist (expected {what})", path.display());
        return Err(InputError::Missing { path: path.into(), message }.into());
    }
    let file = File::open(path).with_context(|| format!("cannot read {}", path.display()))?;
    let size = file.metadata().map(|m| m.len()).unwrap_or(0);
    let mut reader = BufReader::new(file);
    let mut tag = [0u8; 8];
    if reader.read_exact(&mut tag).is_err() || &tag != magic {
        let message = format!("{} is not {what}", path.display());
        return Err(InputError::WrongKind { path: path.into(), message }.into());
    }
    Ok((reader, size.saturating_sub(8)))
}

/// Creates `dir` and its parents.
pub fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| {
        let hint = hint(&e);
        anyhow::Error::new(e).context(format!("cannot create {}{hint}", dir.display()))
    })
}

/// Writes `text` to `path` atomically, creating its folder.
pub fn write_text(path: &Path, text: &str) -> Result<()> {
    write_bytes(path, text.as_bytes())
}

/// Writes `value` as pretty JSON to `path`, creating its folder.
pub fn write_json<T: Serialize + ?Sized>(path: &Path, value: &T) -> Result<()> {
    let text = serde_json::to_string_pretty(value).with_context(|| format!("serialising {}", path.display()))?;
    write_text(path, &text)
}

/// Writes `value` as TOML to `path`, creating its folder.
pub fn write_toml<T: Serialize + ?Sized>(path: &Path, value: &T) -> Result<()> {
    let text = toml::to_string_pretty(value).with_context(|| format!("serialising {}", path.display()))?;
    write_text(path, &text)
}

/// Reads a JSON file, naming it in errors.
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("malformed {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failed_write_keeps_the_previous_file_and_leaves_no_temporary() {
        let dir = std::env::temp_dir().join(format!("refnpr-files-{}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        let path = dir.join("out.json");
        write_text(&path, "good").unwrap();
        let err = write_atomic(&path, |w| {
            w.write_all(b"half of a new fi").unwrap();
            anyhow::bail!("the encoder failed")
        })
        .unwrap_err();
        assert!(format!("{err:#}").contains("keeps its previous content"), "{err:#}");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "good");
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1, "a temporary file was left behind");
        // A folder that cannot exist (its parent is a file): the error names it.
        let err = format!("{:#}", write_text(&path.join("x.png"), "").unwrap_err());
        assert!(err.contains("out.json") && err.contains("cannot create"), "{err}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
