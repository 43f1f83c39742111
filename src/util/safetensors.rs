//! The safetensors layout (Hugging Face's tensor file: an 8-byte
//! little-endian header length, a JSON header naming each tensor's dtype,
//! shape and byte range, then the tensors' bytes), written and read a block
//! at a time. Python reads it with `safetensors` or a few lines of numpy,
//! and so do PyTorch and Burn's `burn-store`. Written by hand rather than
//! with the `safetensors` crate: that crate serialises tensors it holds
//! whole in memory and reads from a whole buffer (or a memory map), while a
//! checkpoint streams grid-sized arrays (1.3 GB on fern) through 4 MB
//! blocks in both directions.

use std::collections::BTreeMap;
use std::io::{self, Read, Seek, SeekFrom, Write};

use serde_json::{Value, json};

/// The element types refnpr stores.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DType {
    F32,
    U32,
}

impl DType {
    fn name(self) -> &'static str {
        match self {
            DType::F32 => "F32",
            DType::U32 => "U32",
        }
    }

    fn parse(s: &str) -> Option<Self> {
        match s {
            "F32" => Some(DType::F32),
            "U32" => Some(DType::U32),
            _ => None,
        }
    }
}

/// One tensor of a file: its dtype, shape and where its bytes are
/// (`begin..end`, counted from the start of the data, after the header).
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    pub dtype: DType,
    pub shape: Vec<usize>,
    pub begin: u64,
    pub end: u64,
}

impl Entry {
    pub fn num_elements(&self) -> usize {
        self.shape.iter().product()
    }
}

/// The largest header read (a checkpoint's is a few kB of JSON).
const MAX_HEADER: u64 = 16 << 20;

/// The header for tensors in this order (name, dtype, shape), laid out one
/// after another, and string metadata (`__metadata__`): the length, then
/// the JSON padded with spaces to a multiple of 8 bytes (the data then
/// starts aligned). Returns the bytes and each tensor's entry.
pub fn header(tensors: &[(&str, DType, Vec<usize>)], metadata: &BTreeMap<String, String>) -> (Vec<u8>, Vec<Entry>) {
    let mut doc = serde_json::Map::new();
    doc.insert("__metadata__".into(), json!(metadata));
    let mut offset = 0u64;
    let mut entries = Vec::new();
    for (name, dtype, shape) in tensors {
        let bytes = 4 * shape.iter().product::<usize>() as u64;
        let entry = Entry { dtype: *dtype, shape: shape.clone(), begin: offset, end: offset + bytes };
        doc.insert(
            (*name).into(),
            json!({"dtype": dtype.name(), "shape": shape, "data_offsets": [entry.begin, entry.end]}),
        );
        offset += bytes;
        entries.push(entry);
    }
    let mut text = serde_json::to_vec(&Value::Object(doc)).expect("a JSON map");
    while !(8 + text.len()).is_multiple_of(8) {
        text.push(b' ');
    }
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend(text);
    (out, entries)
}

/// Whether a file starts like a safetensors file (a header length that
/// fits, then `{`), from its first 9 bytes.
pub fn looks_like(start: &[u8], file_len: u64) -> bool {
    start.len() >= 9 && {
        let n = u64::from_le_bytes(start[..8].try_into().expect("8 bytes"));
        (2..=MAX_HEADER).contains(&n) && 8 + n <= file_len && start[8] == b'{'
    }
}

fn invalid(message: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, message)
}

/// A file's header.
#[derive(Debug, Clone)]
pub struct Header {
    pub metadata: BTreeMap<String, String>,
    pub entries: BTreeMap<String, Entry>,
    /// Where the tensors' bytes begin in the file.
    pub data_start: u64,
}

/// A file's header, read from `r` at its start: the metadata strings and
/// the tensors by name, each checked (known dtype, bytes matching its
/// shape, inside the file), the tensors together covering the data exactly.
pub fn read_header(r: &mut impl Read, file_len: u64) -> io::Result<Header> {
    let mut len = [0u8; 8];
    r.read_exact(&mut len)?;
    let n = u64::from_le_bytes(len);
    if n > MAX_HEADER || 8 + n > file_len {
        return Err(invalid(format!("a header of {n} bytes in a file of {file_len}")));
    }
    let mut text = vec![0u8; n as usize];
    r.read_exact(&mut text)?;
    let doc: serde_json::Map<String, Value> =
        serde_json::from_slice(&text).map_err(|e| invalid(format!("the header is not JSON: {e}")))?;
    let data_len = file_len - 8 - n;
    let mut metadata = BTreeMap::new();
    let mut entries = BTreeMap::new();
    for (name, value) in doc {
        if name == "__metadata__" {
            let map = value.as_object().ok_or_else(|| invalid("__metadata__ is not a map".into()))?;
            for (k, v) in map {
                let v = v.as_str().ok_or_else(|| invalid(format!("metadata {k} is not a string")))?;
                metadata.insert(k.clone(), v.to_string());
            }
            continue;
        }
        let bad = |what: &str| invalid(format!("tensor {name}: {what}"));
        let dtype = value["dtype"].as_str().and_then(DType::parse).ok_or_else(|| bad("unknown dtype"))?;
        let shape: Vec<usize> = value["shape"]
            .as_array()
            .ok_or_else(|| bad("no shape"))?
            .iter()
            .map(|d| d.as_u64().map(|d| d as usize).ok_or_else(|| bad("a shape entry is not a size")))
            .collect::<io::Result<_>>()?;
        let offsets = value["data_offsets"].as_array().ok_or_else(|| bad("no data_offsets"))?;
        let (begin, end) = match offsets.as_slice() {
            [b, e] => (b.as_u64().ok_or_else(|| bad("bad offset"))?, e.as_u64().ok_or_else(|| bad("bad offset"))?),
            _ => return Err(bad("data_offsets is not two numbers")),
        };
        let elements = shape.iter().try_fold(1u64, |p, &d| p.checked_mul(d as u64));
        if begin > end || end > data_len || elements.and_then(|e| e.checked_mul(4)) != Some(end - begin) {
            return Err(bad(&format!("bytes {begin}..{end} do not hold shape {shape:?} in {data_len} bytes of data")));
        }
        entries.insert(name, Entry { dtype, shape, begin, end });
    }
    let mut ranges: Vec<(u64, u64)> = entries.values().map(|e| (e.begin, e.end)).collect();
    ranges.sort_unstable();
    let mut at = 0;
    for (b, e) in ranges {
        if b != at {
            return Err(invalid("the tensors' bytes overlap or leave gaps".into()));
        }
        at = e;
    }
    if at != data_len {
        return Err(invalid(format!("the tensors hold {at} bytes of the {data_len} after the header")));
    }
    Ok(Header { metadata, entries, data_start: 8 + n })
}

/// Bytes read at a time into a vector.
const READ_BLOCK: usize = 1 << 20;

/// Reads a tensor's values (`data_start`: where the data begins in the file).
pub fn read_values<R: Read + Seek, T, const N: usize>(
    r: &mut R,
    data_start: u64,
    entry: &Entry,
    from_le_bytes: fn([u8; N]) -> T,
) -> io::Result<Vec<T>> {
    r.seek(SeekFrom::Start(data_start + entry.begin))?;
    let mut left = (entry.end - entry.begin) as usize;
    let mut out = Vec::with_capacity(left / N);
    let mut block = vec![0u8; READ_BLOCK.min(left)];
    while left > 0 {
        let take = READ_BLOCK.min(left);
        r.read_exact(&mut block[..take])?;
        out.extend(block[..take].chunks_exact(N).map(|c| from_le_bytes(c.try_into().expect("N bytes"))));
        left -= take;
    }
    Ok(out)
}

/// Writes `values` little-endian through `scratch` (a buffer kept between blocks).
pub fn write_values<T: Copy, const N: usize>(
    w: &mut impl Write,
    values: &[T],
    to_le_bytes: fn(T) -> [u8; N],
    scratch: &mut Vec<u8>,
) -> io::Result<()> {
    scratch.clear();
    scratch.resize(values.len() * N, 0);
    for (bytes, &v) in scratch.chunks_exact_mut(N).zip(values) {
        bytes.copy_from_slice(&to_le_bytes(v));
    }
    w.write_all(scratch)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    fn file() -> Vec<u8> {
        let meta = BTreeMap::from([("format".to_string(), "test".to_string())]);
        let (mut bytes, _) = header(&[("a", DType::U32, vec![2]), ("b", DType::F32, vec![1, 3])], &meta);
        let mut scratch = Vec::new();
        write_values(&mut bytes, &[7u32, 9], u32::to_le_bytes, &mut scratch).unwrap();
        write_values(&mut bytes, &[1.5f32, -2.0, 0.25], f32::to_le_bytes, &mut scratch).unwrap();
        bytes
    }

    #[test]
    fn written_tensors_read_back_and_the_data_is_aligned() {
        let bytes = file();
        assert!(looks_like(&bytes, bytes.len() as u64));
        let Header { metadata: meta, entries, data_start: start } =
            read_header(&mut Cursor::new(&bytes), bytes.len() as u64).unwrap();
        assert_eq!(start % 8, 0);
        assert_eq!(meta["format"], "test");
        let mut r = Cursor::new(&bytes);
        assert_eq!(read_values(&mut r, start, &entries["a"], u32::from_le_bytes).unwrap(), vec![7, 9]);
        assert_eq!(read_values(&mut r, start, &entries["b"], f32::from_le_bytes).unwrap(), vec![1.5, -2.0, 0.25]);
        assert_eq!(entries["b"].shape, vec![1, 3]);
    }

    #[test]
    fn truncated_or_inconsistent_files_are_refused() {
        let bytes = file();
        let short = &bytes[..bytes.len() - 4];
        assert!(read_header(&mut Cursor::new(short), short.len() as u64).is_err(), "data missing");
        let mut huge = bytes.clone();
        huge[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(read_header(&mut Cursor::new(&huge), huge.len() as u64).is_err());
        assert!(!looks_like(&huge, huge.len() as u64));
        let text = String::from_utf8_lossy(&bytes[8..]).replace("[1,3]", "[2,3]");
        let mut wrong = bytes[..8].to_vec();
        wrong.extend(text.as_bytes());
        assert!(read_header(&mut Cursor::new(&wrong), wrong.len() as u64).is_err(), "shape and bytes disagree");
    }
}
