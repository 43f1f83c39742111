//! Arrays with JSON beside them, in one safetensors file: the stylization's
//! resume state and R³'s registration. The header's metadata holds
//! `format` (what the file is) and `meta` (the JSON of everything that is
//! not a large array); each array is a tensor (F32 or U32) of its own, so
//! Python reads the file with `safetensors` or numpy, as it reads a
//! checkpoint. Written atomically (`files::write_atomic`); read whole (these
//! files hold at most a few copies of a field's colour coefficients).

use std::collections::BTreeMap;
use std::io::{self, Read, Seek, Write};
use std::path::Path;

use anyhow::{Context, Result};
use serde::Serialize;
use serde::de::DeserializeOwned;

use crate::util::files;
use crate::util::input::InputError;
use crate::util::safetensors::{self, DType, Entry};

/// One array to write: its name, shape and values.
pub enum ArrayRef<'a> {
    F32(&'a str, Vec<usize>, &'a [f32]),
    U32(&'a str, Vec<usize>, &'a [u32]),
}

impl ArrayRef<'_> {
    fn describe(&self) -> (&str, DType, Vec<usize>) {
        match self {
            ArrayRef::F32(name, shape, _) => (name, DType::F32, shape.clone()),
            ArrayRef::U32(name, shape, _) => (name, DType::U32, shape.clone()),
        }
    }

    /// How many values it holds.
    fn len(&self) -> usize {
        match self {
            ArrayRef::F32(_, _, v) => v.len(),
            ArrayRef::U32(_, _, v) => v.len(),
        }
    }
}

/// Writes `meta` (as JSON) and `arrays` to `path`, tagged `format`. Each
/// array's values must fill its shape.
pub fn save<T: Serialize>(path: &Path, format: &str, meta: &T, arrays: &[ArrayRef<'_>]) -> Result<()> {
    let metadata = BTreeMap::from([
        ("format".to_string(), format.to_string()),
        ("meta".to_string(), serde_json::to_string(meta)?),
    ]);
    let tensors: Vec<_> = arrays.iter().map(ArrayRef::describe).collect();
    for ((name, _, shape), array) in tensors.iter().zip(arrays) {
        let len = array.len();
        anyhow::ensure!(
            len == shape.iter().product::<usize>(),
            "writing {}: array {name} holds {len} values, not {shape:?}",
            path.display()
        );
    }
    let (header, _) = safetensors::header(&tensors, &metadata);
    files::write_atomic(path, |w| {
        let io = |e| files::io_error(e, path);
        let mut scratch = Vec::new();
        w.write_all(&header).map_err(io)?;
        for array in arrays {
            match array {
                ArrayRef::F32(_, _, v) => safetensors::write_values(w, v, f32::to_le_bytes, &mut scratch),
                ArrayRef::U32(_, _, v) => safetensors::write_values(w, v, u32::to_le_bytes, &mut scratch),
            }
            .map_err(io)?;
        }
        Ok(())
    })
}

/// A file's arrays, read by name.
pub struct Arrays {
    file: std::path::PathBuf,
    entries: BTreeMap<String, Entry>,
    values: BTreeMap<String, Values>,
}

enum Values {
    F32(Vec<f32>),
    U32(Vec<u32>),
}

impl Arrays {
    /// Whether the file holds an array of this name.
    pub fn has(&self, name: &str) -> bool {
        self.values.contains_key(name)
    }

    /// The shape of array `name` (an error naming the file when it has none).
    pub fn shape(&self, name: &str) -> Result<&[usize]> {
        Ok(&self.entries.get(name).ok_or_else(|| self.missing(name, "an array"))?.shape)
    }

    /// Takes the F32 array `name` out of the file's arrays.
    pub fn f32(&mut self, name: &str) -> Result<Vec<f32>> {
        match self.values.remove(name) {
            Some(Values::F32(v)) => Ok(v),
            _ => Err(self.missing(name, "an F32 array")),
        }
    }

    /// Takes the U32 array `name` out of the file's arrays.
    pub fn u32(&mut self, name: &str) -> Result<Vec<u32>> {
        match self.values.remove(name) {
            Some(Values::U32(v)) => Ok(v),
            _ => Err(self.missing(name, "a U32 array")),
        }
    }

    /// Takes the F32 array `name` of shape `[n, 3]` out as `n` triples.
    pub fn f32_triples(&mut self, name: &str) -> Result<Vec<[f32; 3]>> {
        let shape = self.shape(name)?;
        if shape.len() != 2 || shape[1] != 3 {
            return Err(self.corrupt(format!("array {name} has shape {shape:?}, not [n, 3]")));
        }
        Ok(self.f32(name)?.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
    }

    /// The error for a file whose content does not hold together: `message` says how.
    pub fn corrupt(&self, message: String) -> anyhow::Error {
        let message = format!("{} is corrupt: {message}", self.file.display());
        InputError::Malformed { path: self.file.clone(), message }.into()
    }

    fn missing(&self, name: &str, what: &str) -> anyhow::Error {
        self.corrupt(format!("it holds no {what} {name}"))
    }
}

/// Reads a file `save` wrote with this `format`: its JSON (as `T`) and its
/// arrays. `what` names the kind in errors ("a refnpr registration file");
/// `older` says what to do with a file of an older refnpr (one in another
/// layout that starts with `old_magic`).
pub fn load<T: DeserializeOwned>(path: &Path, format: &str, what: &str, old: (&[u8; 8], &str)) -> Result<(T, Arrays)> {
    let (old_magic, older) = old;
    if !path.exists() {
        let message = format!("{} does not exist (expected {what})", path.display());
        return Err(InputError::Missing { path: path.into(), message }.into());
    }
    let malformed = |message: String| InputError::Malformed { path: path.into(), message };
    let cannot_read = || format!("cannot read {}", path.display());
    let mut file = std::fs::File::open(path).with_context(cannot_read)?;
    let len = file.metadata().map(|m| m.len()).unwrap_or(0);
    let mut start = [0u8; 9];
    let read = read_start(&mut file, &mut start).with_context(cannot_read)?;
    if read >= 8 && &start[..8] == old_magic {
        let message =
            format!("{} was written by an older refnpr, in a layout this one no longer reads: {older}", path.display());
        return Err(InputError::WrongKind { path: path.into(), message }.into());
    }
    let wrong_kind =
        || InputError::WrongKind { path: path.into(), message: format!("{} is not {what}", path.display()) };
    if !safetensors::looks_like(&start[..read], len) {
        return Err(wrong_kind().into());
    }
    file.seek(io::SeekFrom::Start(0)).with_context(cannot_read)?;
    let mut r = io::BufReader::new(file);
    let header =
        safetensors::read_header(&mut r, len).map_err(|e| malformed(format!("{} is corrupt: {e}", path.display())))?;
    if header.metadata.get("format").map(String::as_str) != Some(format) {
        return Err(wrong_kind().into());
    }
    let meta_json =
        header.metadata.get("meta").ok_or_else(|| malformed(format!("{} is corrupt: no meta", path.display())))?;
    let meta = serde_json::from_str(meta_json)
        .map_err(|e| malformed(format!("{} is corrupt: its meta: {e}", path.display())))?;
    let mut values = BTreeMap::new();
    for (name, entry) in &header.entries {
        let read = match entry.dtype {
            DType::F32 => {
                safetensors::read_values(&mut r, header.data_start, entry, f32::from_le_bytes).map(Values::F32)
            }
            DType::U32 => {
                safetensors::read_values(&mut r, header.data_start, entry, u32::from_le_bytes).map(Values::U32)
            }
        };
        values
            .insert(name.clone(), read.map_err(|e| malformed(format!("{} is corrupt: {name}: {e}", path.display())))?);
    }
    Ok((meta, Arrays { file: path.to_path_buf(), entries: header.entries, values }))
}

/// Reads up to `buf.len()` bytes (fewer only at the end of the file).
fn read_start(r: &mut impl Read, buf: &mut [u8]) -> io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..])? {
            0 => break,
            n => got += n,
        }
    }
    Ok(got)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(name: &str) -> std::path::PathBuf {
        std::env::temp_dir().join(format!("refnpr-tensor-file-{name}-{}", std::process::id()))
    }

    #[test]
    fn json_and_arrays_read_back_exactly() {
        let path = temp("roundtrip");
        let floats = [1.5f32, -0.0, f32::MIN_POSITIVE, 3.25e-7, f32::MAX, 0.1];
        let meta = serde_json::json!({"steps": 7, "name": "a ✓"});
        let arrays = [ArrayRef::F32("f", vec![2, 3], &floats), ArrayRef::U32("u", vec![2], &[7, u32::MAX])];
        save(&path, "test-format", &meta, &arrays).unwrap();
        let (back, mut a): (serde_json::Value, _) =
            load(&path, "test-format", "a test file", (b"OLDMAGIC", "")).unwrap();
        assert_eq!(back, meta);
        assert_eq!(a.shape("f").unwrap(), &[2, 3]);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a.f32("f").unwrap()), bits(&floats));
        assert_eq!(a.u32("u").unwrap(), vec![7, u32::MAX]);
        assert!(!a.has("u") && a.f32("u").is_err(), "taken once");
        std::fs::remove_file(&path).ok();
    }

    #[test]
    fn other_kinds_old_layouts_and_bad_shapes_are_refused_by_name() {
        let path = temp("kinds");
        save(&path, "one-format", &1, &[]).unwrap();
        let e = load::<i32>(&path, "other-format", "a test file", (b"OLDMAGIC", "")).err().unwrap();
        assert!(matches!(InputError::of(&e), Some(InputError::WrongKind { .. })), "{e:#}");
        std::fs::write(&path, b"OLDMAGIC and then bincode").unwrap();
        let e = load::<i32>(&path, "one-format", "a test file", (b"OLDMAGIC", "make it again")).err().unwrap();
        assert!(format!("{e:#}").contains("older refnpr") && format!("{e:#}").contains("make it again"), "{e:#}");
        let short = save(&path, "one-format", &1, &[ArrayRef::F32("f", vec![3], &[1.0])]);
        assert!(short.is_err());
        std::fs::remove_file(&path).ok();
        let e = load::<i32>(&path, "one-format", "a test file", (b"OLDMAGIC", "")).err().unwrap();
        assert!(matches!(InputError::of(&e), Some(InputError::Missing { .. })), "{e:#}");
    }
}
