//! A mesh as binary glTF 2.0 (`.glb`): one mesh, one primitive, POSITION,
//! NORMAL and COLOR_0 attributes and 32-bit indices, with an unlit material
//! (`KHR_materials_unlit`) so a viewer shows the field's baked colours
//! rather than relighting them. Written by hand: a glb is a JSON chunk and
//! a binary chunk, and the glTF crates on crates.io are readers first.

use std::io::Write;

use anyhow::Result;
use serde_json::json;

use crate::export::mesh::Mesh;

/// sRGB to linear (glTF's COLOR_0 is linear; viewers encode back to sRGB).
fn linear(c: f32) -> f32 {
    if c <= 0.04045 { c / 12.92 } else { ((c + 0.055) / 1.055).powf(2.4) }
}

/// Writes `mesh` as a glb.
pub fn write_glb(mesh: &Mesh, w: &mut impl Write) -> Result<()> {
    let n = mesh.positions.len();
    let mut bin: Vec<u8> = Vec::with_capacity(n * 36 + mesh.triangles.len() * 12);
    for p in &mesh.positions {
        bin.extend(p.to_array().iter().flat_map(|v| v.to_le_bytes()));
    }
    for p in &mesh.normals {
        bin.extend(p.to_array().iter().flat_map(|v| v.to_le_bytes()));
    }
    for c in &mesh.colours {
        bin.extend(c.iter().flat_map(|&v| linear(v).to_le_bytes()));
    }
    for t in &mesh.triangles {
        bin.extend(t.iter().flat_map(|v| v.to_le_bytes()));
    }
    let (lo, hi) = mesh.positions.iter().fold(([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]), |(lo, hi), p| {
        (std::array::from_fn(|a| lo[a].min(p[a])), std::array::from_fn(|a| hi[a].max(p[a])))
    });
    let vec3 = n * 12;
    let view = |i: usize, length: usize, target: u32| json!({"buffer": 0, "byteOffset": i * vec3, "byteLength": length, "target": target});
    let doc = json!({
        "asset": {"version": "2.0", "generator": "refnpr"},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "materials": [{
            "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0, "roughnessFactor": 1},
            "doubleSided": true,
            "extensions": {"KHR_materials_unlit": {}}
        }],
        "meshes": [{"primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "COLOR_0": 2},
            "indices": 3,
            "material": 0,
            "mode": 4
        }]}],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": [
            view(0, vec3, 34962),
            view(1, vec3, 34962),
            view(2, vec3, 34962),
            view(3, mesh.triangles.len() * 12, 34963)
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": n, "type": "VEC3", "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5126, "count": n, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": n, "type": "VEC3"},
            {"bufferView": 3, "componentType": 5125, "count": mesh.triangles.len() * 3, "type": "SCALAR"}
        ]
    });
    let mut json_bytes = serde_json::to_vec(&doc)?;
    // Chunks are 4-byte aligned: JSON padded with spaces, binary with zeros.
    while !json_bytes.len().is_multiple_of(4) {
        json_bytes.push(b' ');
    }
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + json_bytes.len() + 8 + bin.len();
    w.write_all(b"glTF")?;
    w.write_all(&2u32.to_le_bytes())?;
    w.write_all(&(total as u32).to_le_bytes())?;
    w.write_all(&(json_bytes.len() as u32).to_le_bytes())?;
    w.write_all(b"JSON")?;
    w.write_all(&json_bytes)?;
    w.write_all(&(bin.len() as u32).to_le_bytes())?;
    w.write_all(b"BIN\0")?;
    w.write_all(&bin)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn a_triangle_makes_a_well_formed_glb() {
        let mesh = Mesh {
            positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y],
            normals: vec![Vec3::Z; 3],
            colours: vec![[1.0, 0.5, 0.0]; 3],
            triangles: vec![[0, 1, 2]],
        };
        let mut bytes = Vec::new();
        write_glb(&mesh, &mut bytes).unwrap();
        assert_eq!(&bytes[0..4], b"glTF");
        assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()) as usize, bytes.len());
        let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
        let doc: serde_json::Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
        assert_eq!(doc["accessors"][0]["max"], json!([1.0, 1.0, 0.0]));
        let bin_len = u32::from_le_bytes(bytes[20 + json_len..24 + json_len].try_into().unwrap()) as usize;
        assert_eq!(bin_len, doc["buffers"][0]["byteLength"].as_u64().unwrap() as usize);
        assert_eq!(bin_len, 3 * 36 + 12);
        assert!((linear(0.5) - 0.214).abs() < 1e-3);
    }
}
