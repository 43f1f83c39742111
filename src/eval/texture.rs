//! The texture figure: whether a stylization carries the painting's strokes
//! or is a tinted photo.
//!
//! Ref-LPIPS mixes colour and texture: a photo recoloured to the
//! painting's palette already scores well on it. Here each image is first
//! colour-transferred to the painting's colour statistics (mean and
//! covariance, `stylize::colour_transfer`), which removes what a tint can
//! do, and is then compared with the painting by the Gram matrices of its
//! VGG16 features (Gatys et al.'s texture statistics, relu1_2 to relu4_3):
//! per layer the Frobenius norm of the difference over the painting's own,
//! averaged over the layers. 0 is the painting's texture; the photo under
//! the painting, tinted the same way, is the "tinted photo" mark a
//! stylization is read against (`StylizationEval::texture`).

use anyhow::Result;
use burn::tensor::Device;

use crate::stylize::colour_transfer::{ColourStats, ColourTransfer};
use crate::util::image::Image;
use crate::util::tensor::to_vec;
use crate::vgg::{Vgg16, VggLayer};

/// The layers whose Gram matrices make the texture statistics.
pub const TEXTURE_LAYERS: [VggLayer; 4] = [VggLayer::Relu1_2, VggLayer::Relu2_2, VggLayer::Relu3_3, VggLayer::Relu4_3];

/// An image's texture statistics: one Gram matrix per layer of
/// [`TEXTURE_LAYERS`] (`[C, C]`, row-major, over the layer's positions).
pub struct Grams(Vec<Vec<f32>>);

impl Grams {
    /// The texture statistics of `image` through `vgg`.
    pub fn of(vgg: &Vgg16, image: &Image, device: &Device) -> Result<Self> {
        let mut maps = vgg.features(image.tensor(device), &TEXTURE_LAYERS)?;
        let grams = TEXTURE_LAYERS
            .iter()
            .map(|&layer| {
                let [_, c, h, w] = maps.get(layer).dims();
                let f = maps.take(layer).reshape([c, h * w]);
                to_vec(f.clone().matmul(f.transpose()) / (h * w) as f32)
            })
            .collect();
        Ok(Grams(grams))
    }

    /// How far `self`'s texture is from `to`'s: per layer
    /// ||G_self - G_to|| / ||G_to|| (Frobenius), averaged over the layers.
    pub fn distance(&self, to: &Grams) -> f32 {
        let per_layer = self.0.iter().zip(&to.0).map(|(a, b)| {
            let diff: f64 = a.iter().zip(b).map(|(&x, &y)| ((x - y) as f64).powi(2)).sum();
            let norm: f64 = b.iter().map(|&y| (y as f64).powi(2)).sum();
            (diff / norm.max(1e-20)).sqrt()
        });
        (per_layer.sum::<f64>() / self.0.len().max(1) as f64) as f32
    }
}

/// `image` with its colours transferred to the colour statistics of
/// `painting` (mean and covariance over all pixels): what a tint can do.
pub fn tinted_like(image: &Image, painting: &Image) -> Result<Image> {
    let stats = |rgb: &[f32]| ColourStats::of(rgb.chunks_exact(3).map(|c| [c[0], c[1], c[2]]));
    let transfer = ColourTransfer::between(&stats(&image.rgb)?, &stats(&painting.rgb)?);
    let rgb = image.rgb.chunks_exact(3).flat_map(|c| transfer.apply([c[0], c[1], c[2]])).collect();
    Ok(Image::new(image.width, image.height, rgb))
}

/// The texture distance of `image`, tinted like the painting, to the
/// painting's statistics `painting_grams`.
pub fn texture_distance(
    vgg: &Vgg16,
    image: &Image,
    painting: &Image,
    painting_grams: &Grams,
    device: &Device,
) -> Result<f32> {
    Ok(Grams::of(vgg, &tinted_like(image, painting)?, device)?.distance(painting_grams))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::device;

    /// A 64x64 picture whose channels switch between 0.2 and 0.8 in three
    /// independent patterns of cells `cell` pixels wide, each channel then
    /// mapped by `gain` and `offset`.
    fn pattern(cell: usize, gain: [f32; 3], offset: [f32; 3]) -> Image {
        let (w, h) = (64, 64);
        let on = |bit: bool| if bit { 0.8 } else { 0.2 };
        let rgb = (0..w * h)
            .flat_map(|p| {
                let (x, y) = ((p % w) / cell, (p / w) / cell);
                let hash = (x * 7 + y * 13 + x * y * 5) % 11 > 5;
                let raw = [on(x % 2 == 0), on((x + y) % 2 == 0), on(hash)];
                std::array::from_fn::<f32, 3, _>(|c| raw[c] * gain[c] + offset[c])
            })
            .collect();
        Image::new(w, h, rgb)
    }

    /// The painting recoloured channel by channel is at (nearly) no
    /// distance once tinted back; the same colours in broad cells (the
    /// painting's palette without its texture) are far.
    #[test]
    fn a_tint_is_forgiven_a_missing_texture_is_not() {
        let d = device();
        let vgg = Vgg16::load(&d);
        let painting = pattern(1, [1.0; 3], [0.0; 3]);
        let grams = Grams::of(&vgg, &painting, &d).unwrap();
        let recoloured = pattern(1, [0.5, 0.8, 0.6], [0.3, 0.0, 0.2]);
        let broad = pattern(16, [1.0; 3], [0.0; 3]);
        let itself = texture_distance(&vgg, &painting, &painting, &grams, &d).unwrap();
        let tinted = texture_distance(&vgg, &recoloured, &painting, &grams, &d).unwrap();
        let untextured = texture_distance(&vgg, &broad, &painting, &grams, &d).unwrap();
        let figures = format!("itself {itself}, tinted {tinted}, untextured {untextured}");
        assert!(itself < 1e-3 && tinted < 0.1 && untextured > 5.0 * tinted.max(0.01), "{figures}");
    }
}
