//! Image quality metrics: PSNR and SSIM (Gaussian window 11, sigma 1.5, as
//! in the NeRF / Plenoxels evaluations), and the speckle count (isolated
//! pixel colour noise), on interleaved RGB images in [0, 1].

use rayon::prelude::*;

/// Peak signal-to-noise ratio in dB.
pub fn psnr(a: &[f32], b: &[f32]) -> f32 {
    psnr_from_mse((squared_error(a, b) / a.len() as f64) as f32)
}

/// Sum of squared differences, in f64: pooled over several images (add the
/// sums and the value counts) it gives one PSNR over all of them.
pub fn squared_error(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum()
}

pub fn psnr_from_mse(mse: f32) -> f32 {
    -10.0 * mse.max(1e-10).log10()
}

fn gaussian_kernel() -> [f32; 11] {
    let mut k = [0.0f32; 11];
    for (i, v) in k.iter_mut().enumerate() {
        let x = i as f32 - 5.0;
        *v = (-(x * x) / (2.0 * 1.5 * 1.5)).exp();
    }
    let s: f32 = k.iter().sum();
    k.map(|v| v / s)
}

/// Separable "valid" Gaussian filter of one channel.
fn filter(img: &[f32], w: usize, h: usize) -> (Vec<f32>, usize, usize) {
    let k = gaussian_kernel();
    let (ow, oh) = (w - 10, h - 10);
    let mut tmp = vec![0.0f32; ow * h];
    for y in 0..h {
        for x in 0..ow {
            tmp[y * ow + x] = (0..11).map(|i| k[i] * img[y * w + x + i]).sum();
        }
    }
    let mut out = vec![0.0f32; ow * oh];
    for y in 0..oh {
        for x in 0..ow {
            out[y * ow + x] = (0..11).map(|i| k[i] * tmp[(y + i) * ow + x]).sum();
        }
    }
    (out, ow, oh)
}

/// Mean SSIM over the three channels of interleaved RGB images.
pub fn ssim(a: &[f32], b: &[f32], width: usize, height: usize) -> f32 {
    assert_eq!(a.len(), width * height * 3);
    assert_eq!(b.len(), a.len());
    if width < 11 || height < 11 {
        return f32::NAN;
    }
    let (c1, c2) = (0.01f32.powi(2), 0.03f32.powi(2));
    let mut total = 0.0f64;
    for c in 0..3 {
        let x: Vec<f32> = (0..width * height).map(|i| a[i * 3 + c]).collect();
        let y: Vec<f32> = (0..width * height).map(|i| b[i * 3 + c]).collect();
        let xx: Vec<f32> = x.iter().map(|v| v * v).collect();
        let yy: Vec<f32> = y.iter().map(|v| v * v).collect();
        let xy: Vec<f32> = x.iter().zip(&y).map(|(p, q)| p * q).collect();
        let (mx, ow, oh) = filter(&x, width, height);
        let (my, ..) = filter(&y, width, height);
        let (sxx, ..) = filter(&xx, width, height);
        let (syy, ..) = filter(&yy, width, height);
        let (sxy, ..) = filter(&xy, width, height);
        let mut s = 0.0f64;
        for i in 0..ow * oh {
            let (mx, my) = (mx[i], my[i]);
            let vx = sxx[i] - mx * mx;
            let vy = syy[i] - my * my;
            let cxy = sxy[i] - mx * my;
            let v = ((2.0 * mx * my + c1) * (2.0 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2));
            s += v as f64;
        }
        total += s / (ow * oh) as f64;
    }
    (total / 3.0) as f32
}

/// A pixel is speckle when some channel differs from that channel's median
/// over its 3x3 neighbourhood by more than this.
pub const SPECKLE_THRESHOLD: f32 = 0.1;

/// Speckle: (speckled pixels, pixels counted) over the pixels of `mask`
/// whose whole 3x3 neighbourhood is in `mask` too (so silhouettes against
/// the background do not count). A 3x3 median keeps edges and flat regions
/// and removes single-pixel noise, so a pixel far from it is noise, or a
/// one-pixel-wide detail (compare with the same count on the ground truth).
pub fn speckle(rgb: &[f32], width: usize, height: usize, mask: &[bool]) -> (usize, usize) {
    assert_eq!(rgb.len(), width * height * 3, "speckle: image size");
    assert_eq!(mask.len(), width * height, "speckle: mask size");
    // Rows in parallel (an eval scores 120 frames of 190,000 pixels, each
    // with three 9-value medians); integer counts, so the sum is exact.
    (1..height.saturating_sub(1))
        .into_par_iter()
        .map(|y| {
            let (mut speckled, mut counted) = (0, 0);
            for x in 1..width.saturating_sub(1) {
                let around = |dy: usize, dx: usize| (y + dy - 1) * width + x + dx - 1;
                if !(0..3).all(|dy| (0..3).all(|dx| mask[around(dy, dx)])) {
                    continue;
                }
                counted += 1;
                let centre = y * width + x;
                let noisy = (0..3).any(|c| {
                    let mut v: [f32; 9] = std::array::from_fn(|k| rgb[around(k / 3, k % 3) * 3 + c]);
                    let (_, median, _) = v.select_nth_unstable_by(4, f32::total_cmp);
                    (rgb[centre * 3 + c] - *median).abs() > SPECKLE_THRESHOLD
                });
                speckled += usize::from(noisy);
            }
            (speckled, counted)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_images_score_perfectly_and_noise_lowers_scores() {
        let (w, h) = (32, 24);
        let a: Vec<f32> = (0..w * h * 3).map(|i| ((i * 37) % 101) as f32 / 100.0).collect();
        assert!((ssim(&a, &a, w, h) - 1.0).abs() < 1e-4);
        assert!(psnr(&a, &a) > 90.0);
        let b: Vec<f32> =
            a.iter().enumerate().map(|(i, v)| (v + if i % 2 == 0 { 0.1 } else { -0.1 }).clamp(0.0, 1.0)).collect();
        assert!(ssim(&a, &b, w, h) < 0.95);
        let p = psnr(&a, &b);
        assert!(p > 19.0 && p < 21.5, "{p}");
    }

    /// A smooth image with two flat regions has no speckle (edges are not
    /// speckle); flipping 40 isolated pixels gives exactly 40; pixels next
    /// to the mask's edge are not counted.
    #[test]
    fn speckle_counts_isolated_pixels_not_edges_or_gradients() {
        let (w, h) = (40, 30);
        let mut img: Vec<f32> = (0..w * h)
            .flat_map(|i| {
                let (x, y) = (i % w, i / w);
                let base = if x < 17 { 0.2 } else { 0.8 };
                [base + 0.004 * y as f32, 0.5, 0.3 + 0.005 * x as f32]
            })
            .collect();
        let mask = vec![true; w * h];
        let (s, n) = speckle(&img, w, h, &mask);
        assert_eq!((s, n), (0, (w - 2) * (h - 2)));
        let mut flipped = 0;
        for y in (3..h - 3).step_by(5) {
            for x in (3..w - 3).step_by(6) {
                img[(y * w + x) * 3 + 1] += 0.3;
                flipped += 1;
            }
        }
        assert_eq!(speckle(&img, w, h, &mask).0, flipped);
        // A mask that leaves out the left 10 columns: fewer pixels counted.
        let right: Vec<bool> = (0..w * h).map(|i| i % w >= 10).collect();
        let (_, counted) = speckle(&img, w, h, &right);
        assert_eq!(counted, (w - 12) * (h - 2));
    }
}
