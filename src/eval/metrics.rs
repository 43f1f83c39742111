//! Image quality metrics: PSNR and SSIM (Gaussian window 11, sigma 1.5, as
//! in the NeRF / Plenoxels evaluations), on RGB images in [0, 1].

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
}
