//! Real spherical-harmonic basis, degrees 0-2, with the constants and sign
//! conventions of Plenoxels (svox2), so colour = max(SH . basis + 0.5, 0).

use glam::Vec3;

/// The degree-0 basis constant: a view-independent colour is max(C0 c + 0.5, 0).
pub const C0: f32 = 0.282_094_8;
const C1: f32 = 0.488_602_5;
const C2: [f32; 5] = [1.092_548_4, -1.092_548_4, 0.315_391_57, -1.092_548_4, 0.546_274_2];

/// Number of basis functions for a degree (1, 4 or 9).
pub fn num_basis(degree: u32) -> usize {
    ((degree + 1) * (degree + 1)) as usize
}

/// Evaluates the basis for a unit direction into `out` (length `num_basis(degree)`).
pub fn eval_basis(degree: u32, d: Vec3, out: &mut [f32]) {
    out[0] = C0;
    if degree >= 1 {
        out[1] = -C1 * d.y;
        out[2] = C1 * d.z;
        out[3] = -C1 * d.x;
    }
    if degree >= 2 {
        let (x, y, z) = (d.x, d.y, d.z);
        out[4] = C2[0] * x * y;
        out[5] = C2[1] * y * z;
        out[6] = C2[2] * (2.0 * z * z - x * x - y * y);
        out[7] = C2[3] * x * z;
        out[8] = C2[4] * (x * x - y * y);
    }
}

/// The degree-0 coefficient that gives a flat colour `c` (inverse of
/// `C0 * k + 0.5`).
pub fn dc_for_colour(c: f32) -> f32 {
    (c - 0.5) / C0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[allow(clippy::needless_range_loop)] // a Gram matrix reads best indexed
    fn basis_is_orthonormal_on_the_sphere() {
        // Monte-Carlo check of <Y_i, Y_j> = delta_ij * (1 / 4pi) * 4pi.
        let n = 20000;
        let mut gram = [[0.0f64; 9]; 9];
        let mut b = [0.0f32; 9];
        for k in 0..n {
            // Fibonacci sphere: a deterministic uniform cover.
            let z = 1.0 - 2.0 * (k as f32 + 0.5) / n as f32;
            let phi = k as f32 * 2.399_963;
            let r = (1.0 - z * z).sqrt();
            eval_basis(2, Vec3::new(r * phi.cos(), r * phi.sin(), z), &mut b);
            for i in 0..9 {
                for j in 0..9 {
                    gram[i][j] += (b[i] * b[j]) as f64 * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for i in 0..9 {
            for j in 0..9 {
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((gram[i][j] - want).abs() < 1e-2, "{i} {j} {}", gram[i][j]);
            }
        }
    }
}
