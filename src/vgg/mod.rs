//! VGG16 feature extractor: a thin wrapper over the model burn-onnx generates
//! from `models/vgg16_features.onnx` (committed as `models/vgg16_features.rs`,
//! checked by tests/vgg.rs (model_is_burn_onnx_import_of_the_onnx_file); see models/README.md).
//!
//! Two sets of ImageNet weights ([`VggWeights`], both in `vgg::weights`):
//! Oxford's original release (the ONNX file's initializers, the default) and
//! torchvision's (the network the authors' losses and LPIPS use), loaded into
//! the same graph.
//!
//! Input: a batch of RGB images `[N, 3, H, W]` with values in [0, 1]. Each
//! set's input normalisation happens inside the model (Oxford: x*255 minus
//! the Caffe mean; torchvision: minus the mean, over the std; LPIPS: its
//! scaling layer), so callers never normalise.
//!
//! Image sizes: any H, W >= 32. The four 2x2 max-pools floor odd sizes (as
//! PyTorch's `ceil_mode=False`), so stage s (relu{s}_x) has size
//! `floor(H / 2^(s-1))` x `floor(W / 2^(s-1))`, and feature position (i, j) of
//! stage s covers pixels `[i*2^(s-1), (i+1)*2^(s-1))`; when H or W is not a
//! multiple of 16 the last rows/columns of pixels fall outside the relu5 map.
//! Nothing is padded or resized: callers that need exact alignment pass
//! multiples of 16.
//!
//! The weights are embedded in the binary; loading parses them (about 59 MB)
//! once per `Vgg16::load`, so keep the value around.

use std::collections::BTreeMap;
use std::sync::Arc;

use burn::module::Module;
use burn::tensor::{Device, Tensor};
use thiserror::Error;

use crate::kernels::conv_op::PreparedSlot;
pub use crate::util::tensor::image_tensor;
use crate::vgg::model::Model;

pub mod alexnet;
pub mod features;
pub(crate) mod model;
pub(crate) mod staged;
pub mod weights;

/// SHA-256 over the 13 convolutions' weights and biases (float32 LE, in
/// network order, weight before bias): the value `models/make_vgg16_onnx.py`
/// checks after conversion, checked again on the imported model by the tests.
pub const WEIGHTS_SHA256: &str = "25d244c5fdb86c278c3442bce00783954c822e6564e34bea523f31bddfdcc4d1";

/// The smallest image side the extractor accepts: relu5 is then 2x2.
pub const MIN_SIDE: usize = 32;

/// One of VGG16's 13 ReLU outputs, in network order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum VggLayer {
    Relu1_1,
    Relu1_2,
    Relu2_1,
    Relu2_2,
    Relu3_1,
    Relu3_2,
    Relu3_3,
    Relu4_1,
    Relu4_2,
    Relu4_3,
    Relu5_1,
    Relu5_2,
    Relu5_3,
}

impl VggLayer {
    pub const ALL: [VggLayer; 13] = [
        VggLayer::Relu1_1,
        VggLayer::Relu1_2,
        VggLayer::Relu2_1,
        VggLayer::Relu2_2,
        VggLayer::Relu3_1,
        VggLayer::Relu3_2,
        VggLayer::Relu3_3,
        VggLayer::Relu4_1,
        VggLayer::Relu4_2,
        VggLayer::Relu4_3,
        VggLayer::Relu5_1,
        VggLayer::Relu5_2,
        VggLayer::Relu5_3,
    ];
    /// TCM's correspondence layers (paper: relu3_x and relu4_x).
    pub const TCM: [VggLayer; 6] = [
        VggLayer::Relu3_1,
        VggLayer::Relu3_2,
        VggLayer::Relu3_3,
        VggLayer::Relu4_1,
        VggLayer::Relu4_2,
        VggLayer::Relu4_3,
    ];
    /// Colour matching's layers (relu5_x).
    pub const COLOUR: [VggLayer; 3] = [VggLayer::Relu5_1, VggLayer::Relu5_2, VggLayer::Relu5_3];
    /// One layer per stage, as used by LPIPS-style perceptual metrics.
    pub const PERCEPTUAL: [VggLayer; 5] =
        [VggLayer::Relu1_2, VggLayer::Relu2_2, VggLayer::Relu3_3, VggLayer::Relu4_3, VggLayer::Relu5_3];

    /// Position in the network (0..13), also the position in the ONNX outputs.
    pub fn index(self) -> usize {
        self as usize
    }

    /// The ONNX output name, e.g. `relu3_1`.
    pub fn name(self) -> &'static str {
        const NAMES: [&str; 13] = [
            "relu1_1", "relu1_2", "relu2_1", "relu2_2", "relu3_1", "relu3_2", "relu3_3", "relu4_1", "relu4_2",
            "relu4_3", "relu5_1", "relu5_2", "relu5_3",
        ];
        NAMES[self.index()]
    }

    pub fn from_name(name: &str) -> Option<VggLayer> {
        Self::ALL.into_iter().find(|l| l.name() == name)
    }

    /// Stage 1..=5 (the block the layer sits in).
    pub fn stage(self) -> usize {
        match self.index() {
            0..=1 => 1,
            2..=3 => 2,
            4..=6 => 3,
            7..=9 => 4,
            _ => 5,
        }
    }

    /// Pixels per feature position along each axis: 2^(stage-1).
    pub fn stride(self) -> usize {
        1 << (self.stage() - 1)
    }

    pub fn channels(self) -> usize {
        [64, 128, 256, 512, 512][self.stage() - 1]
    }

    /// Feature map size `[h, w]` for an image of `[height, width]` (floor pooling).
    pub fn map_size(self, height: usize, width: usize) -> [usize; 2] {
        [height / self.stride(), width / self.stride()]
    }
}

impl std::fmt::Display for VggLayer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[derive(Debug, Error, PartialEq)]
pub enum VggError {
    #[error(
        "VGG16 takes RGB images [N, 3, H, W]; got {0} channel(s). Composite RGBA over a background \
         (drop alpha) or repeat a grey channel three times first"
    )]
    Channels(usize),
    #[error(
        "VGG16 needs images of at least {MIN_SIDE}x{MIN_SIDE} pixels; got {width}x{height}. Render or resize larger"
    )]
    TooSmall { width: usize, height: usize },
    #[error("VGG16 got an empty batch")]
    EmptyBatch,
}

/// Feature maps by layer, each `[N, C, h, w]`.
#[derive(Debug, Clone)]
pub struct FeatureMaps {
    maps: BTreeMap<VggLayer, Tensor<4>>,
}

impl FeatureMaps {
    /// Maps given by hand (tests, other feature extractors).
    pub fn from_maps(maps: impl IntoIterator<Item = (VggLayer, Tensor<4>)>) -> Self {
        Self { maps: maps.into_iter().collect() }
    }

    /// The map of `layer`; panics if it was not requested (a programming error).
    pub fn get(&self, layer: VggLayer) -> &Tensor<4> {
        self.maps.get(&layer).unwrap_or_else(|| panic!("feature map {layer} was not requested"))
    }

    pub fn take(&mut self, layer: VggLayer) -> Tensor<4> {
        self.maps.remove(&layer).unwrap_or_else(|| panic!("feature map {layer} was not requested"))
    }

    pub fn layers(&self) -> impl Iterator<Item = VggLayer> + '_ {
        self.maps.keys().copied()
    }

    pub fn iter(&self) -> impl Iterator<Item = (VggLayer, &Tensor<4>)> {
        self.maps.iter().map(|(l, t)| (*l, t))
    }
}

/// How the forward pass runs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum VggForward {
    /// The imported ONNX graph's generated `forward` (all 13 layers).
    Graph,
    /// The same modules in the same order, stopping after the deepest
    /// requested layer (`vgg::staged`; the same numbers, less work).
    Staged,
    /// As `Staged`, with the 3x3 convolutions run by the project's Winograd
    /// kernel on the CPU backends (`kernels::conv3x3`, `kernels::conv_op`; Burn's
    /// own convolution on wgpu): the default.
    #[default]
    Winograd,
}

/// Which ImageNet weights VGG16 carries.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum VggWeights {
    /// Oxford's original Caffe release (Simonyan & Zisserman; the weights
    /// of Gatys et al.'s style transfer): input x*255 minus the Caffe mean.
    #[default]
    Oxford,
    /// torchvision's `vgg16-397923af` (PyTorch's retraining; the network of
    /// the authors' TCM and NNFM losses and of LPIPS): input minus
    /// torchvision's mean, over its std.
    Torchvision,
}

/// torchvision's input normalisation (ImageNet mean and std, RGB).
const TORCH_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const TORCH_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// LPIPS's scaling layer, on inputs mapped from [0, 1] to [-1, 1].
pub const LPIPS_SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
pub const LPIPS_SCALE: [f32; 3] = [0.458, 0.448, 0.450];

/// Convolutions whose kernel weights are prepared once and kept: those up
/// to relu4_3, the deepest layer a loss back-propagates through (TCM).
/// Stage 5 (relu5_x: colour matching's descriptors, a forward per view
/// before the stylization) prepares its weights per call: keeping them
/// would hold 140 MB for a few seconds' gain.
const PREPARED_LAYERS: usize = VggLayer::Relu4_3 as usize + 1;

/// The VGG16 feature stack (13 convolutions, ImageNet weights).
#[derive(Debug, Clone)]
pub struct Vgg16 {
    model: Model,
    forward: VggForward,
    /// The Winograd kernel's weights of the first [`PREPARED_LAYERS`]
    /// convolutions, prepared on first use (the weights are frozen); clones
    /// share them.
    prepared: Arc<[PreparedSlot; PREPARED_LAYERS]>,
}

impl Vgg16 {
    /// The ImageNet weights embedded at build time, on `device`. The weights
    /// never require gradients (gradients flow to the input image only).
    pub fn load(device: &Device) -> Self {
        let convs = weights::OXFORD.convs("", 13, device);
        let scale = weights::OXFORD.tensor("scale", device);
        let mean = weights::OXFORD.tensor("mean", device);
        Self::with_model(Model::new(device).with_weights(convs, scale, mean))
    }

    /// The ImageNet weights `weights` names, on `device`.
    pub fn load_weights(device: &Device, weights: VggWeights) -> Self {
        match weights {
            VggWeights::Oxford => Self::load(device),
            VggWeights::Torchvision => Self::torchvision(device, TORCH_MEAN, TORCH_STD),
        }
    }

    /// torchvision's weights behind LPIPS's scaling layer: an image `x` in
    /// [0, 1] enters as `(2x - 1 - shift) / scale`, i.e. `(x - (1 + shift) / 2)
    /// / (scale / 2)`.
    pub fn lpips(device: &Device) -> Self {
        Self::torchvision(device, LPIPS_SHIFT.map(|s| (1.0 + s) / 2.0), LPIPS_SCALE.map(|s| s / 2.0))
    }

    /// torchvision's weights for inputs `(x - mean) / std`. The division is
    /// folded into conv1_1's weights (per input channel), which is exact,
    /// zero padding included: a padded zero of `(x - mean) / std` is a
    /// padded zero of `x - mean`.
    fn torchvision(device: &Device, mean: [f32; 3], std: [f32; 3]) -> Self {
        let mut convs = weights::LPIPS.convs("vgg.", 13, device);
        let inv_std = crate::util::tensor::floats(std.map(|s| 1.0 / s).to_vec(), [1, 3, 1, 1], device);
        convs[0].0 = convs[0].0.clone() * inv_std;
        let scale = crate::util::tensor::floats(vec![1.0], [1], device);
        let mean = crate::util::tensor::floats(mean.to_vec(), [1, 3, 1, 1], device);
        Self::with_model(Model::new(device).with_weights(convs, scale, mean))
    }

    /// `model`, frozen, with the default forward pass. (The weights' upload
    /// was counted by `floats`.)
    fn with_model(model: Model) -> Self {
        Self { model: model.no_grad(), forward: VggForward::default(), prepared: Arc::default() }
    }

    /// The same architecture with Burn's default random initialisation under
    /// `seed`: the control for tests that must prove the real weights matter.
    pub fn random(device: &Device, seed: u64) -> Self {
        device.seed(seed);
        Self::with_model(Model::new(device))
    }

    /// The same weights, the forward pass run as `forward` says.
    pub fn with_forward(self, forward: VggForward) -> Self {
        Self { forward, ..self }
    }

    /// SHA-256 of the loaded convolution weights, in the layout of
    /// [`WEIGHTS_SHA256`] (equal to it for `load`).
    pub fn weights_sha256(&self) -> String {
        use burn_store::ModuleSnapshot;
        use sha2::{Digest, Sha256};
        let tensors = self.model.collect(None, None, false);
        let mut hasher = Sha256::new();
        for i in 1..=13 {
            for part in ["weight", "bias"] {
                let name = format!("conv2d{i}.{part}");
                let t =
                    tensors.iter().find(|t| t.name == name).unwrap_or_else(|| panic!("generated model lacks {name}"));
                hasher.update(&t.to_bytes().expect("parameter bytes")[..]);
            }
        }
        hasher.finalize().iter().map(|b| format!("{b:02x}")).collect()
    }

    /// conv1_1's weight at `[out, in, ky, kx]` (in = R, G, B).
    pub fn conv1_1_weight(&self, index: [usize; 4]) -> f32 {
        use burn_store::ModuleSnapshot;
        let tensors = self.model.collect(None, None, false);
        let t = tensors.iter().find(|t| t.name == "conv2d1.weight").expect("generated model has conv2d1.weight");
        let bytes = t.to_bytes().expect("parameter bytes");
        let [o, i, y, x] = index;
        let at = ((o * 3 + i) * 3 + y) * 3 + x;
        f32::from_le_bytes(bytes[at * 4..at * 4 + 4].try_into().expect("4 bytes"))
    }

    /// The requested feature maps of `image` (`[N, 3, H, W]`, RGB in [0, 1]).
    /// On an autodiff device the maps carry gradients back to `image`.
    pub fn features(&self, image: Tensor<4>, layers: &[VggLayer]) -> Result<FeatureMaps, VggError> {
        let [n, c, h, w] = image.dims();
        if n == 0 {
            return Err(VggError::EmptyBatch);
        }
        if c != 3 {
            return Err(VggError::Channels(c));
        }
        if h < MIN_SIDE || w < MIN_SIDE {
            return Err(VggError::TooSmall { width: w, height: h });
        }
        let all: Vec<Option<Tensor<4>>> = match self.forward {
            VggForward::Graph => {
                let o = self.model.forward(image);
                [o.0, o.1, o.2, o.3, o.4, o.5, o.6, o.7, o.8, o.9, o.10, o.11, o.12].into_iter().map(Some).collect()
            }
            VggForward::Staged => staged::forward(&self.model, image, layers, None),
            VggForward::Winograd => staged::forward(&self.model, image, layers, Some(&self.prepared[..])),
        };
        let mut maps = BTreeMap::new();
        for (layer, map) in VggLayer::ALL.into_iter().zip(all) {
            if let (true, Some(map)) = (layers.contains(&layer), map) {
                maps.insert(layer, map);
            }
        }
        Ok(FeatureMaps { maps })
    }
}
