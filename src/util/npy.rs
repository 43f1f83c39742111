//! A minimal reader and writer for NumPy `.npy` files (little-endian f4/f8,
//! C order), enough for `poses_bounds.npy` and our depth maps.

use anyhow::{Context, Result, bail};

use crate::util::input::InputError;
use std::path::Path;

/// An array read from a `.npy` file, converted to f64.
pub struct NpyArray {
    pub shape: Vec<usize>,
    pub data: Vec<f64>,
}

pub fn read(path: &Path) -> Result<NpyArray> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    parse(&bytes).with_context(|| InputError::Malformed {
        path: path.into(),
        message: format!("{} is not a valid .npy file", path.display()),
    })
}

pub fn parse(bytes: &[u8]) -> Result<NpyArray> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        bail!("missing the NUMPY magic bytes");
    }
    let major = bytes[6];
    let (header_len, start) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                bail!("truncated header");
            }
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        v => bail!("unsupported .npy version {v}"),
    };
    let end = start + header_len;
    if bytes.len() < end {
        bail!("truncated header");
    }
    let header = std::str::from_utf8(&bytes[start..end]).context("header is not text")?;
    let field = |key: &str| -> Result<&str> {
        let i = header.find(key).with_context(|| format!("header has no {key}"))?;
        Ok(&header[i + key.len()..])
    };
    let descr = field("'descr':")?.trim_start();
    let dtype = descr.trim_start_matches(['\'', '"']).split(['\'', '"']).next().unwrap_or("");
    let elem = match dtype {
        "<f8" => 8,
        "<f4" => 4,
        other => bail!("unsupported dtype '{other}' (expected little-endian float32 or float64)"),
    };
    if field("'fortran_order':")?.trim_start().starts_with("True") {
        bail!("Fortran-ordered arrays are not supported");
    }
    let shape_txt = field("'shape':")?;
    let open = shape_txt.find('(').context("shape has no '('")?;
    let close = open + shape_txt[open..].find(')').context("shape has no ')'")?;
    let shape: Vec<usize> = shape_txt[open + 1..close]
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().with_context(|| format!("bad shape entry '{s}'")))
        .collect::<Result<_>>()?;
    // Checked: a header may claim any shape; the data must be in the file
    // before anything is allocated for it.
    let count = shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
    let body = &bytes[end..];
    match count.and_then(|c| c.checked_mul(elem)) {
        Some(needed) if needed <= body.len() => {}
        _ => bail!("data is truncated: shape {shape:?} needs more bytes than the file's {}", body.len()),
    }
    let count = count.unwrap_or(0);
    let data = (0..count)
        .map(|i| {
            let b = &body[i * elem..(i + 1) * elem];
            if elem == 8 {
                f64::from_le_bytes(b.try_into().unwrap())
            } else {
                f32::from_le_bytes(b.try_into().unwrap()) as f64
            }
        })
        .collect();
    Ok(NpyArray { shape, data })
}

/// Writes a float32 array.
pub fn write_f32(path: &Path, shape: &[usize], data: &[f32]) -> Result<()> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape_txt = if dims.len() == 1 { format!("({},)", dims[0]) } else { format!("({})", dims.join(", ")) };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape_txt}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + data.len() * 4);
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    crate::util::files::write_bytes(path, &out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_rejects_garbage() {
        let dir = std::env::temp_dir().join(format!("refnpr-npy-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("a.npy");
        write_f32(&p, &[2, 3], &[1.0, 2.0, 3.0, 4.0, 5.0, 6.5]).unwrap();
        let a = read(&p).unwrap();
        assert_eq!(a.shape, vec![2, 3]);
        assert_eq!(a.data[5], 6.5);
        assert!(parse(b"not an npy file at all").is_err());
        std::fs::remove_dir_all(&dir).ok();
    }
}
