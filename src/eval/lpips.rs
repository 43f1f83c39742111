//! LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep
//! Features as a Perceptual Metric"), version 0.1, as the `lpips` package
//! computes it with `normalize=True` — the metric of the paper's Ref-LPIPS:
//!
//! 1. each image in [0, 1] is mapped to [-1, 1] and through LPIPS's scaling
//!    layer, `(x - shift) / scale` (`vgg::LPIPS_SHIFT`, `vgg::LPIPS_SCALE`);
//! 2. the network's five feature maps: VGG16's relu1_2, relu2_2, relu3_3,
//!    relu4_3, relu5_3 (torchvision's weights), or AlexNet's five ReLUs;
//! 3. each map unit-normalised over channels, `f / (||f|| + 1e-10)`;
//! 4. the squared difference of the two images' maps, weighted per channel
//!    by the layer's learned linear head (a 1x1 convolution without bias),
//!    summed over channels, averaged over positions;
//! 5. the five layers' values summed.
//!
//! Weights: `vgg::weights` (embedded at build time). Checked against a numpy
//! implementation written from the same formula (`scripts/lpips_reference.py`,
//! run by the test command on real image pairs).

use anyhow::{Result, ensure};
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::util::image::Image;
use crate::util::tensor::{floats, scalar};
use crate::vgg::alexnet::AlexNet;
use crate::vgg::{LPIPS_SCALE, LPIPS_SHIFT, Vgg16, VggLayer, weights};

/// The feature network LPIPS compares through.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum LpipsNet {
    /// torchvision's VGG16 (the paper's Ref-LPIPS: `lpips.LPIPS(net="vgg")`).
    #[default]
    Vgg,
    /// torchvision's AlexNet (the `lpips` package's default network).
    Alex,
}

impl LpipsNet {
    /// The prefix of its arrays in the weights file.
    fn key(self) -> &'static str {
        match self {
            LpipsNet::Vgg => "vgg",
            LpipsNet::Alex => "alex",
        }
    }
}

/// VGG16's five LPIPS layers.
const VGG_LAYERS: [VggLayer; 5] =
    [VggLayer::Relu1_2, VggLayer::Relu2_2, VggLayer::Relu3_3, VggLayer::Relu4_3, VggLayer::Relu5_3];

/// The smallest image side LPIPS takes here (both networks' deepest map is then at least 1x1).
pub const MIN_SIDE: usize = 32;

enum Network {
    Vgg(Box<Vgg16>),
    Alex(Box<AlexInput>),
}

/// AlexNet, and its input map `x * scale - shift` (`[1, 3, 1, 1]` each):
/// [0, 1] to [-1, 1], then LPIPS's scaling layer, in one step.
struct AlexInput {
    net: AlexNet,
    scale: Tensor<4>,
    shift: Tensor<4>,
}

/// The LPIPS metric with one network's weights loaded.
pub struct Lpips {
    network: Network,
    /// The linear heads, `[1, C, 1, 1]` each.
    heads: Vec<Tensor<4>>,
    device: Device,
}

/// One image's five unit-normalised feature maps (computed once, compared with many).
pub struct LpipsFeatures {
    maps: Vec<Tensor<4>>,
    size: (usize, usize),
}

impl Lpips {
    /// LPIPS through `net`, on `device`.
    pub fn load(net: LpipsNet, device: &Device) -> Self {
        let network = match net {
            LpipsNet::Vgg => Network::Vgg(Box::new(Vgg16::lpips(device))),
            LpipsNet::Alex => Network::Alex(Box::new(AlexInput {
                net: AlexNet::load(device),
                scale: floats(LPIPS_SCALE.map(|s| 2.0 / s).to_vec(), [1, 3, 1, 1], device),
                shift: floats(
                    LPIPS_SHIFT.iter().zip(LPIPS_SCALE).map(|(sh, sc)| (1.0 + sh) / sc).collect(),
                    [1, 3, 1, 1],
                    device,
                ),
            })),
        };
        let heads = (0..5)
            .map(|k| {
                let head: Tensor<1> = weights::LPIPS.tensor(&format!("{}.lin{k}", net.key()), device);
                let c = head.dims()[0];
                head.reshape([1, c, 1, 1])
            })
            .collect();
        Self { network, heads, device: device.clone() }
    }

    /// The unit-normalised feature maps of `image`.
    pub fn features(&self, image: &Image) -> Result<LpipsFeatures> {
        ensure!(
            image.width >= MIN_SIDE && image.height >= MIN_SIDE,
            "LPIPS needs images of at least {MIN_SIDE}x{MIN_SIDE} pixels; got {}x{}",
            image.width,
            image.height
        );
        let x = image.tensor(&self.device);
        let maps = match &self.network {
            // The scaling layer is inside the VGG16 model (`Vgg16::lpips`).
            Network::Vgg(vgg) => {
                let mut maps = vgg.features(x, &VGG_LAYERS)?;
                VGG_LAYERS.iter().map(|&l| maps.take(l)).collect::<Vec<_>>()
            }
            Network::Alex(alex) => alex.net.features(x * alex.scale.clone() - alex.shift.clone()),
        };
        let maps = maps.into_iter().map(unit_normalised).collect();
        Ok(LpipsFeatures { maps, size: (image.width, image.height) })
    }

    /// The LPIPS distance between two images' features (same image size).
    pub fn distance_of(&self, a: &LpipsFeatures, b: &LpipsFeatures) -> Result<f32> {
        ensure!(a.size == b.size, "LPIPS compares images of one size; got {:?} and {:?}", a.size, b.size);
        let mut total: Option<Tensor<1>> = None;
        for ((fa, fb), head) in a.maps.iter().zip(&b.maps).zip(&self.heads) {
            let d = fa.clone() - fb.clone();
            let weighted = (d.clone() * d * head.clone()).sum_dim(1);
            let layer = weighted.mean().reshape([1]);
            total = Some(match total {
                Some(t) => t + layer,
                None => layer,
            });
        }
        Ok(scalar(total.expect("five layers")))
    }

    /// The LPIPS distance between two images of the same size.
    pub fn distance(&self, a: &Image, b: &Image) -> Result<f32> {
        ensure!(
            (a.width, a.height) == (b.width, b.height),
            "LPIPS compares images of one size; got {}x{} and {}x{}",
            a.width,
            a.height,
            b.width,
            b.height
        );
        self.distance_of(&self.features(a)?, &self.features(b)?)
    }
}

/// `f / (||f|| + 1e-10)`, the norm over channels at each position.
fn unit_normalised(f: Tensor<4>) -> Tensor<4> {
    let norm = (f.clone() * f.clone()).sum_dim(1).sqrt() + 1e-10;
    f / norm
}

/// `refnpr lpips A B`: the LPIPS distance between two image files, alpha
/// composited over `background`. When B's size differs from A's, B is
/// resized to A's (bilinear) and the returned note says so.
pub fn file_distance(
    a: &std::path::Path,
    b: &std::path::Path,
    net: LpipsNet,
    background: [f32; 3],
    device: &Device,
) -> Result<(f32, Option<String>)> {
    use crate::scene::data::read_rgb;
    let (wa, ha, rgb_a) = read_rgb(a, background, 1)?;
    let (wb, hb, rgb_b) = read_rgb(b, background, 1)?;
    let image_a = Image::new(wa as usize, ha as usize, rgb_a);
    let mut image_b = Image::new(wb as usize, hb as usize, rgb_b);
    let mut note = None;
    if (wa, ha) != (wb, hb) {
        note = Some(format!("{} is {wb}x{hb}: resized to {}'s {wa}x{ha}", b.display(), a.display()));
        image_b = image_b.resized(wa as usize, ha as usize);
    }
    let lpips = Lpips::load(net, device);
    let distance =
        lpips.distance(&image_a, &image_b).map_err(|e| anyhow::anyhow!("{} and {}: {e}", a.display(), b.display()))?;
    Ok((distance, note))
}
