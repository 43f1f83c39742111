//! Binary little-endian PLY, the few lines every exporter here needs: one
//! `vertex` element of named float (or byte) properties and an optional
//! `face` element of triangles. Written by hand: the format is a text
//! header and packed records, and the PLY crates on crates.io either read
//! only or bring a generic property model far larger than these lines.

use std::io::Write;

use anyhow::{Result, bail};

/// The storage type of one vertex property.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scalar {
    Float,
    UChar,
}

impl Scalar {
    fn name(self) -> &'static str {
        match self {
            Scalar::Float => "float",
            Scalar::UChar => "uchar",
        }
    }
}

/// A PLY file's content: vertex properties as columns (every column as
/// long as the vertex count) and optional triangles.
#[derive(Debug, Default)]
pub struct Ply {
    pub columns: Vec<(String, Scalar, Vec<f32>)>,
    pub triangles: Vec<[u32; 3]>,
    /// `comment` lines of the header (what wrote the file and from what).
    pub comments: Vec<String>,
}

impl Ply {
    pub fn add(&mut self, name: &str, kind: Scalar, values: Vec<f32>) {
        self.columns.push((name.to_string(), kind, values));
    }

    pub fn num_vertices(&self) -> usize {
        self.columns.first().map_or(0, |c| c.2.len())
    }

    /// Writes the file (binary little-endian). Columns of unequal length
    /// and triangles naming missing vertices are refused.
    pub fn write(&self, w: &mut impl Write) -> Result<()> {
        let n = self.num_vertices();
        if let Some((name, _, v)) = self.columns.iter().find(|c| c.2.len() != n) {
            bail!("PLY column {name} has {} values, the first has {n}", v.len());
        }
        if self.triangles.iter().flatten().any(|&i| i as usize >= n) {
            bail!("a PLY triangle names a vertex past the {n} written");
        }
        let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
        for c in &self.comments {
            header += &format!("comment {}\n", c.replace('\n', " "));
        }
        header += &format!("element vertex {n}\n");
        for (name, kind, _) in &self.columns {
            header += &format!("property {} {name}\n", kind.name());
        }
        if !self.triangles.is_empty() {
            header += &format!("element face {}\nproperty list uchar uint vertex_indices\n", self.triangles.len());
        }
        header += "end_header\n";
        w.write_all(header.as_bytes())?;
        let mut record = Vec::new();
        for i in 0..n {
            record.clear();
            for (_, kind, values) in &self.columns {
                match kind {
                    Scalar::Float => record.extend_from_slice(&values[i].to_le_bytes()),
                    Scalar::UChar => record.push(values[i].round().clamp(0.0, 255.0) as u8),
                }
            }
            w.write_all(&record)?;
        }
        for t in &self.triangles {
            record.clear();
            record.push(3u8);
            for i in t {
                record.extend_from_slice(&i.to_le_bytes());
            }
            w.write_all(&record)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_and_records_have_the_declared_sizes() {
        let mut ply = Ply::default();
        ply.add("x", Scalar::Float, vec![1.0, 2.0]);
        ply.add("red", Scalar::UChar, vec![255.0, 300.0]);
        ply.triangles.push([0, 1, 1]);
        let mut bytes = Vec::new();
        ply.write(&mut bytes).unwrap();
        let end = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let header = std::str::from_utf8(&bytes[..end]).unwrap();
        assert!(header.contains("element vertex 2\nproperty float x\nproperty uchar red\nelement face 1\n"));
        // 2 vertices of 5 bytes, one face of 1 + 3 x 4 bytes.
        assert_eq!(bytes.len() - end, 2 * 5 + 13);
        assert_eq!(&bytes[end..end + 4], &1.0f32.to_le_bytes());
        assert_eq!(bytes[end + 9], 255, "values past 255 are clamped");
    }

    #[test]
    fn ragged_columns_and_bad_triangles_are_refused() {
        let mut ply = Ply::default();
        ply.add("x", Scalar::Float, vec![1.0, 2.0]);
        ply.add("y", Scalar::Float, vec![1.0]);
        assert!(ply.write(&mut Vec::new()).unwrap_err().to_string().contains("column y"));
        let mut ply = Ply::default();
        ply.add("x", Scalar::Float, vec![1.0]);
        ply.triangles.push([0, 0, 1]);
        assert!(ply.write(&mut Vec::new()).is_err());
    }
}
