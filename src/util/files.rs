//! Files with errors that name them: JSON/TOML/text writes (parent folders
//! created), and our binary files (checkpoints, registrations): an 8-byte
//! magic tag then a bincode payload, written atomically (temporary file, then
//! rename) and read as a stream with the file's size as the decoding limit,
//! so a corrupt length field is an error rather than a huge allocation.

use std::io::{Read, Write};
use std::path::Path;

use anyhow::{Context, Result, bail};
use bincode::Options;
use serde::Serialize;
use serde::de::DeserializeOwned;

/// The encoding of `bincode::serialize`, plus a size limit.
fn options(limit: u64) -> impl Options {
    bincode::DefaultOptions::new().with_fixint_encoding().allow_trailing_bytes().with_limit(limit)
}

/// Writes `magic` + `value` to `path` through `path.tmp` and a rename.
pub fn save<T: Serialize>(path: &Path, magic: &[u8; 8], value: &T) -> Result<()> {
    let mut tmp_name = path.as_os_str().to_owned();
    tmp_name.push(".tmp");
    let tmp = std::path::PathBuf::from(tmp_name);
    {
        let file = std::fs::File::create(&tmp).with_context(|| format!("cannot create {}", tmp.display()))?;
        let mut w = std::io::BufWriter::new(file);
        w.write_all(magic)?;
        bincode::serialize_into(&mut w, value).with_context(|| format!("serialising {}", path.display()))?;
        w.flush()?;
        w.get_ref().sync_all().ok();
    }
    std::fs::rename(&tmp, path).with_context(|| format!("cannot move {} to {}", tmp.display(), path.display()))
}

/// Reads a file written by `save`; `what` names the kind in errors
/// ("a refnpr checkpoint").
pub fn load<T: DeserializeOwned>(path: &Path, magic: &[u8; 8], what: &str) -> Result<T> {
    let file = std::fs::File::open(path).with_context(|| format!("cannot read {}", path.display()))?;
    let limit = file.metadata().map(|m| m.len()).unwrap_or(0);
    let mut reader = std::io::BufReader::new(file);
    let mut tag = [0u8; 8];
    if reader.read_exact(&mut tag).is_err() || &tag != magic {
        bail!("{} is not {what}", path.display());
    }
    options(limit).deserialize_from(&mut reader).with_context(|| format!("{} is corrupt", path.display()))
}

/// Creates `dir` and its parents.
pub fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))
}

/// Writes `text` to `path`, creating its folder.
pub fn write_text(path: &Path, text: &str) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        create_dir(dir)?;
    }
    std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))
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
