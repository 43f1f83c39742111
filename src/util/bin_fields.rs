//! Bincode 1's layout (its fixint encoding), as checkpoints before
//! safetensors hold it (read for old runs; the writers are kept for the
//! tests; the bincode crate itself is no longer a dependency), written and read one
//! field at a time: a length is a little-endian `u64`, a string its bytes, a vector its
//! values little-endian, one after another. Serialising a struct writes its
//! fields in order with nothing between them, so writing the same fields
//! here gives the same bytes (tested), and a vector can be streamed in
//! blocks from where it lives (a grid-sized tensor) instead of first being
//! copied whole into a `Vec` and then encoded one value per call: on fern's
//! fine grid, a 1.3 GB checkpoint, that copy took about 3 s and the encoding
//! about as long again.

#[cfg(test)]
use std::io::Write;
use std::io::{self, BufRead, Seek, SeekFrom};

/// A vector's or string's length, which comes before its values.
#[cfg(test)]
pub fn write_len(w: &mut impl Write, len: usize) -> io::Result<()> {
    w.write_all(&(len as u64).to_le_bytes())
}

/// A string: its length, then its UTF-8 bytes. (A vector's values follow
/// its length as `safetensors::write_values` writes them.)
#[cfg(test)]
pub fn write_str(w: &mut impl Write, s: &str) -> io::Result<()> {
    write_len(w, s.len())?;
    w.write_all(s.as_bytes())
}

/// Bytes read at a time into a vector.
const READ_BLOCK: usize = 1 << 20;

/// Reads the layout the writers above write, from a stream of known
/// length: each length is checked against the bytes left before anything
/// is allocated (a corrupt length is an error, not a huge allocation), and
/// a vector is read a block of bytes at a time rather than a value per call.
pub struct FieldReader<R> {
    inner: R,
    left: u64,
    block: Vec<u8>,
}

impl<R: BufRead + Seek> FieldReader<R> {
    /// A reader of the next `len` bytes of `inner`.
    pub fn new(inner: R, len: u64) -> Self {
        Self { inner, left: len, block: Vec::new() }
    }

    /// A length, of a vector whose values take `size` bytes each.
    pub fn read_len(&mut self, size: usize) -> io::Result<usize> {
        let mut bytes = [0u8; 8];
        self.read_exact(&mut bytes)?;
        let len = u64::from_le_bytes(bytes);
        if len.checked_mul(size as u64).is_none_or(|need| need > self.left) {
            let left = self.left;
            return Err(io::Error::new(
                io::ErrorKind::InvalidData,
                format!("a length of {len} values of {size} bytes, with {left} bytes left"),
            ));
        }
        usize::try_from(len).map_err(|e| io::Error::new(io::ErrorKind::InvalidData, e))
    }

    /// A string.
    pub fn read_str(&mut self) -> io::Result<String> {
        let len = self.read_len(1)?;
        let mut bytes = vec![0u8; len];
        self.read_exact(&mut bytes)?;
        String::from_utf8(bytes).map_err(|e| io::Error::new(io::ErrorKind::InvalidData, e))
    }

    /// A vector: its length, then its values.
    pub fn read_vec<T, const N: usize>(&mut self, from_le_bytes: fn([u8; N]) -> T) -> io::Result<Vec<T>> {
        let len = self.read_len(N)?;
        let mut values = Vec::with_capacity(len);
        while values.len() < len {
            let count = (len - values.len()).min(READ_BLOCK / N);
            let mut block = std::mem::take(&mut self.block);
            block.resize(count * N, 0);
            self.read_exact(&mut block)?;
            let (chunks, _) = block.as_chunks::<N>();
            values.extend(chunks.iter().map(|&bytes| from_le_bytes(bytes)));
            self.block = block;
        }
        Ok(values)
    }

    /// Passes over a vector of values of `N` bytes.
    pub fn skip_vec<const N: usize>(&mut self) -> io::Result<()> {
        let bytes = (self.read_len(N)? * N) as u64;
        self.inner.seek(SeekFrom::Current(bytes as i64))?;
        self.left -= bytes;
        Ok(())
    }

    fn read_exact(&mut self, buf: &mut [u8]) -> io::Result<()> {
        self.inner.read_exact(buf)?;
        self.left = self.left.saturating_sub(buf.len() as u64);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    // A vector's values are the same little-endian run in both layouts.
    use crate::util::safetensors::write_values;

    struct Fields {
        name: String,
        ids: Vec<u32>,
        values: Vec<f32>,
        empty: Vec<f32>,
    }

    /// The bytes `bincode::serialize` (bincode 1, fixint) wrote for a
    /// struct `{ name: "ab", ids: vec![7u32], values: vec![1.5f32], empty: Vec<f32> }`:
    /// each length a little-endian u64, then the values, fields in order.
    #[test]
    fn the_writers_lay_out_fields_as_bincode_did() {
        let mut out = Vec::new();
        write_str(&mut out, "ab").unwrap();
        write_len(&mut out, 1).unwrap();
        write_values(&mut out, &[7u32], u32::to_le_bytes, &mut Vec::new()).unwrap();
        write_len(&mut out, 1).unwrap();
        write_values(&mut out, &[1.5f32], f32::to_le_bytes, &mut Vec::new()).unwrap();
        write_len(&mut out, 0).unwrap();
        #[rustfmt::skip]
        let expected: Vec<u8> = [
            &[2, 0, 0, 0, 0, 0, 0, 0, b'a', b'b'][..],
            &[1, 0, 0, 0, 0, 0, 0, 0, 7, 0, 0, 0],
            &[1, 0, 0, 0, 0, 0, 0, 0, 0x00, 0x00, 0xc0, 0x3f],
            &[0, 0, 0, 0, 0, 0, 0, 0],
        ]
        .concat();
        assert_eq!(out, expected);
    }

    #[test]
    fn fields_written_one_by_one_read_back() {
        let values: Vec<f32> = (0..1000).map(|i| (i as f32 * 0.37).sin() * 1e3).chain([f32::MIN, -0.0]).collect();
        let fields = Fields { name: "grid ✓".into(), ids: vec![7, u32::MAX, 0], values, empty: Vec::new() };

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
        let expected_len = 8 + fields.name.len() + 8 + 4 * 3 + 8 + 4 * fields.values.len() + 8;
        assert_eq!(out.len(), expected_len);

        // Read back, the ids skipped.
        let mut r = FieldReader::new(io::Cursor::new(&out), out.len() as u64);
        assert_eq!(r.read_str().unwrap(), fields.name);
        r.skip_vec::<4>().unwrap();
        assert_eq!(r.read_vec(f32::from_le_bytes).unwrap(), fields.values);
        assert_eq!(r.read_vec(f32::from_le_bytes).unwrap(), fields.empty);
        assert!(r.read_len(1).is_err(), "read past the end");
    }

    /// A length beyond what is left is refused before it is allocated.
    #[test]
    fn a_corrupt_length_is_an_error_not_an_allocation() {
        let mut bytes = u64::MAX.to_le_bytes().to_vec();
        bytes.extend_from_slice(&[0; 12]);
        let mut r = FieldReader::new(io::Cursor::new(&bytes), bytes.len() as u64);
        let e = r.read_vec(u32::from_le_bytes).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidData);
        let mut short = 4u64.to_le_bytes().to_vec();
        short.extend_from_slice(&[0; 12]);
        let mut r = FieldReader::new(io::Cursor::new(&short), short.len() as u64);
        assert!(r.read_vec(u32::from_le_bytes).is_err(), "16 bytes of u32s with 12 left");
    }
}
