//! The one image type of the library, and writing what a person looks at:
//! PNG images, depth maps, GIF animations.

use anyhow::Result;
use burn::tensor::{Device, Tensor};
use image::codecs::gif::{GifEncoder, Repeat};
use image::codecs::png::PngEncoder;
use image::{Delay, Frame, RgbImage, RgbaImage};
use std::path::Path;

use crate::util::files;

/// An RGB image: interleaved, row-major, values in [0, 1].
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<f32>,
}

impl Image {
    pub fn new(width: usize, height: usize, rgb: Vec<f32>) -> Self {
        assert_eq!(rgb.len(), width * height * 3, "an RGB buffer of {width}x{height}");
        Self { width, height, rgb }
    }

    /// The `[1, 3, H, W]` tensor of the image (VGG16's input layout).
    pub fn tensor(&self, device: &Device) -> Tensor<4> {
        crate::util::tensor::image_tensor(&self.rgb, self.width, self.height, device)
    }

    /// The image at half size, each pixel the mean of a 2x2 block (an odd
    /// last row or column is dropped): what a 0.5x bilinear resize computes.
    pub fn half(&self) -> Image {
        let (w, h) = (self.width / 2, self.height / 2);
        let at = |x: usize, y: usize, c: usize| self.rgb[(y * self.width + x) * 3 + c];
        let mut rgb = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    let sum = at(2 * x, 2 * y, c)
                        + at(2 * x + 1, 2 * y, c)
                        + at(2 * x, 2 * y + 1, c)
                        + at(2 * x + 1, 2 * y + 1, c);
                    rgb.push(sum / 4.0);
                }
            }
        }
        Image::new(w, h, rgb)
    }

    /// The image `n` times smaller, each pixel the mean of an `n` x `n`
    /// block (an incomplete last row or column of blocks is dropped).
    pub fn block_mean(&self, n: usize) -> Image {
        let (w, h) = (self.width / n, self.height / n);
        let mut rgb = vec![0.0f32; w * h * 3];
        let scale = 1.0 / (n * n) as f32;
        for (y, row) in rgb.chunks_exact_mut(w * 3).enumerate() {
            for (x, out) in row.chunks_exact_mut(3).enumerate() {
                for dy in 0..n {
                    let start = ((y * n + dy) * self.width + x * n) * 3;
                    for px in self.rgb[start..start + n * 3].chunks_exact(3) {
                        out.iter_mut().zip(px).for_each(|(o, p)| *o += p);
                    }
                }
                out.iter_mut().for_each(|o| *o *= scale);
            }
        }
        Image::new(w, h, rgb)
    }

    /// The image resized to `width` x `height` (triangle filter, widened when
    /// shrinking, so it averages like an area resize).
    pub fn resized(&self, width: usize, height: usize) -> Image {
        let src = image::Rgb32FImage::from_raw(self.width as u32, self.height as u32, self.rgb.clone())
            .expect("an RGB buffer of its size");
        let out = image::imageops::resize(&src, width as u32, height as u32, image::imageops::FilterType::Triangle);
        Image::new(width, height, out.into_raw())
    }

    pub fn to_rgb8(&self) -> RgbImage {
        to_rgb8(self.width as u32, self.height as u32, &self.rgb)
    }

    pub fn save_png(&self, path: &Path) -> Result<()> {
        save_png(path, self.width as u32, self.height as u32, &self.rgb)
    }
}

/// The pixels of an interleaved RGB buffer as `[r, g, b]` triples.
pub fn pixels(rgb: &[f32]) -> impl Iterator<Item = [f32; 3]> + '_ {
    rgb.chunks_exact(3).map(|c| [c[0], c[1], c[2]])
}

/// Quantises RGB floats in `[0, 1]` to bytes.
pub fn to_rgb8(w: u32, h: u32, rgb: &[f32]) -> RgbImage {
    let bytes = rgb.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
    RgbImage::from_raw(w, h, bytes).expect("buffer matches image size")
}

pub fn save_png(path: &Path, w: u32, h: u32, rgb: &[f32]) -> Result<()> {
    write_png(path, to_rgb8(w, h, rgb))
}

/// Writes a PNG (8-bit RGB, RGBA or grey) atomically.
pub fn write_png(path: &Path, img: impl Into<image::DynamicImage>) -> Result<()> {
    let img = img.into();
    files::write_atomic(path, |w| img.write_with_encoder(PngEncoder::new(w)).map_err(|e| encode_error(e, path)))
}

/// An encoder's error: an I/O one named like every other write's.
fn encode_error(e: image::ImageError, path: &Path) -> anyhow::Error {
    match e {
        image::ImageError::IoError(io) => files::io_error(io, path),
        other => anyhow::Error::new(other).context(format!("cannot encode {}", path.display())),
    }
}

/// A depth map as a colour image: near = bright yellow, far = dark purple
/// (a compact 'inferno'-like ramp), misses black. Range: 2nd-98th percentile of hits.
pub fn depth_to_rgb(depth: &[Option<f32>]) -> Vec<f32> {
    let mut hits: Vec<f32> = depth.iter().flatten().copied().collect();
    let (lo, hi) = if hits.is_empty() {
        (0.0, 1.0)
    } else {
        hits.sort_by(|a, b| a.total_cmp(b));
        let p = |q: f32| hits[((hits.len() - 1) as f32 * q) as usize];
        (p(0.02), p(0.98).max(p(0.02) + 1e-6))
    };
    let ramp = [[0.0, 0.0, 0.02], [0.34, 0.06, 0.43], [0.73, 0.21, 0.33], [0.98, 0.55, 0.04], [0.99, 1.0, 0.64]];
    let mut out = Vec::with_capacity(depth.len() * 3);
    for d in depth {
        match d {
            None => out.extend([0.0, 0.0, 0.0]),
            Some(d) => {
                let x = (1.0 - ((d - lo) / (hi - lo)).clamp(0.0, 1.0)) * 0.95 + 0.05;
                let f = x * (ramp.len() - 1) as f32;
                let i = (f.floor() as usize).min(ramp.len() - 2);
                let t = f - i as f32;
                out.extend(ramp[i].iter().zip(&ramp[i + 1]).map(|(a, b)| a * (1.0 - t) + b * t));
            }
        }
    }
    out
}

/// Writes an animated GIF (looping), one frame per image.
pub fn save_gif(path: &Path, frames: &[RgbImage], delay_ms: u32) -> Result<()> {
    files::write_atomic(path, |w| {
        let mut enc = GifEncoder::new_with_speed(w, 10);
        enc.set_repeat(Repeat::Infinite).map_err(|e| encode_error(e, path))?;
        for f in frames {
            let rgba: RgbaImage = image::DynamicImage::ImageRgb8(f.clone()).to_rgba8();
            enc.encode_frame(Frame::from_parts(rgba, 0, 0, Delay::from_numer_denom_ms(delay_ms, 1)))
                .map_err(|e| encode_error(e, path))?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::Image;

    /// A 2 x 2 block mean is `half`; a 3 x 3 one averages nine pixels and
    /// drops the incomplete last column.
    #[test]
    fn block_mean_averages_whole_blocks() {
        let rgb: Vec<f32> = (0..7 * 6 * 3).map(|i| (i * 37 % 101) as f32 / 100.0).collect();
        let image = Image::new(7, 6, rgb);
        assert_eq!(image.block_mean(2).rgb, image.half().rgb);
        let third = image.block_mean(3);
        assert_eq!((third.width, third.height), (2, 2));
        let at = |x: usize, y: usize, c: usize| image.rgb[(y * 7 + x) * 3 + c];
        let expected: f32 =
            (3..6).flat_map(|x| (3..6).map(move |y| (x, y))).map(|(x, y)| at(x, y, 1)).sum::<f32>() / 9.0;
        assert!((third.rgb[(2 + 1) * 3 + 1] - expected).abs() < 1e-6);
    }
}
