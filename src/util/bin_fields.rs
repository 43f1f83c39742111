//! Bincode 1's layout (`bincode::serialize`, the fixint encoding that
//! `files::save` writes and `files::load` reads), written one field at a
//! time: a length is a little-endian `u64`, a string its bytes, a vector its
//! values little-endian, one after another. Serialising a struct writes its
//! fields in order with nothing between them, so writing the same fields
//! here gives the same bytes (tested), and a vector can be streamed in
//! blocks from where it lives (a grid-sized tensor) instead of first being
//! copied whole into a `Vec` and then encoded one value per call: on fern's
//! fine grid, a 1.3 GB checkpoint, that copy took about 3 s and the encoding
//! about as long again.

use std::io::{self, Write};

/// A vector's or string's length, which comes before its values.
pub fn write_len(w: &mut impl Write, len: usize) -> io::Result<()> {
    w.write_all(&(len as u64).to_le_bytes())
}

/// A string: its length, then its UTF-8 bytes.
pub fn write_str(w: &mut impl Write, s: &str) -> io::Result<()> {
    write_len(w, s.len())?;
    w.write_all(s.as_bytes())
}

/// `values` without a length (a whole vector is [`write_len`] and then its
/// values, in as many calls as it has blocks), encoded through `scratch`, a
/// buffer the caller keeps between blocks.
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
    use serde::Serialize;

    #[derive(Serialize)]
    struct Fields {
        name: String,
        ids: Vec<u32>,
        values: Vec<f32>,
        empty: Vec<f32>,
    }

    #[test]
    fn fields_written_one_by_one_are_the_bytes_bincode_writes_for_the_struct() {
        let values: Vec<f32> = (0..1000).map(|i| (i as f32 * 0.37).sin() * 1e3).chain([f32::MIN, -0.0]).collect();
        let fields = Fields { name: "grid ✓".into(), ids: vec![7, u32::MAX, 0], values, empty: Vec::new() };
        let expected = bincode::serialize(&fields).unwrap();

        let (mut out, mut scratch) = (Vec::new(), Vec::new());
        write_str(&mut out, &fields.name).unwrap();
        write_len(&mut out, fields.ids.len()).unwrap();
        write_values(&mut out, &fields.ids, u32::to_le_bytes, &mut scratch).unwrap();
        // The floats in uneven blocks, as a streamed tensor is written.
        write_len(&mut out, fields.values.len()).unwrap();
        for block in fields.values.chunks(333) {
            write_values(&mut out, block, f32::to_le_bytes, &mut scratch).unwrap();
        }
        write_len(&mut out, 0).unwrap();
        assert_eq!(out, expected);
    }
}
