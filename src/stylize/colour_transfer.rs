//! Linear colour transfer (ARF's preprocessing): an affine map of RGB that
//! gives a set of content colours the mean and covariance of a set of style
//! colours. With content covariance C_c and style covariance C_s the map is
//! `x -> C_s^{1/2} C_c^{-1/2} (x - mu_c) + mu_s` (whiten, then colour), the
//! symmetric square roots taken through an eigendecomposition. ARF recolours
//! the training photos with it before stylizing, so the field starts from the
//! style's palette and the feature loss only has to move textures.
//!
//! Plain Rust: the statistics are 3x3 and computed once.

use anyhow::{Result, ensure};
use serde::Serialize;

/// Eigenvalues below this (colour variance, [0, 1] units squared) are
/// clamped: a flat image (one colour) must not divide by zero.
const MIN_VARIANCE: f64 = 1e-8;

/// `rgb -> matrix * rgb + offset`, clamped to [0, 1].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ColourTransfer {
    pub matrix: [[f32; 3]; 3],
    pub offset: [f32; 3],
}

/// Mean and covariance of a set of colours (f64: millions of pixels).
#[derive(Debug, Clone, Copy)]
pub struct ColourStats {
    pub mean: [f64; 3],
    pub covariance: [[f64; 3]; 3],
    pub count: usize,
}

impl ColourStats {
    pub fn of(colours: impl IntoIterator<Item = [f32; 3]>) -> Result<Self> {
        let mut sum = [0.0f64; 3];
        let mut outer = [[0.0f64; 3]; 3];
        let mut count = 0usize;
        for c in colours {
            let c = c.map(f64::from);
            for i in 0..3 {
                sum[i] += c[i];
                for j in 0..3 {
                    outer[i][j] += c[i] * c[j];
                }
            }
            count += 1;
        }
        ensure!(count > 0, "no colours to take statistics of");
        let n = count as f64;
        let mean = sum.map(|s| s / n);
        let covariance = std::array::from_fn(|i| std::array::from_fn(|j| outer[i][j] / n - mean[i] * mean[j]));
        Ok(Self { mean, covariance, count })
    }
}

impl ColourTransfer {
    pub const IDENTITY: ColourTransfer =
        ColourTransfer { matrix: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], offset: [0.0; 3] };

    /// The map that gives colours with statistics `content` the statistics `style`.
    pub fn between(content: &ColourStats, style: &ColourStats) -> Self {
        let whiten = symmetric_power(&content.covariance, -0.5);
        let colour = symmetric_power(&style.covariance, 0.5);
        let m = mat_mul(&colour, &whiten);
        let offset =
            std::array::from_fn(|i| (style.mean[i] - (0..3).map(|j| m[i][j] * content.mean[j]).sum::<f64>()) as f32);
        Self { matrix: m.map(|row| row.map(|v| v as f32)), offset }
    }

    /// The mapped colour without clamping.
    pub fn apply_unclamped(&self, c: [f32; 3]) -> [f32; 3] {
        std::array::from_fn(|i| {
            self.matrix[i][0] * c[0] + self.matrix[i][1] * c[1] + self.matrix[i][2] * c[2] + self.offset[i]
        })
    }

    /// The mapped colour, clamped to [0, 1].
    pub fn apply(&self, c: [f32; 3]) -> [f32; 3] {
        self.apply_unclamped(c).map(|v| v.clamp(0.0, 1.0))
    }
}

fn mat_mul(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

/// `S^p` of a symmetric positive semi-definite 3x3 matrix (eigenvalues
/// clamped to `MIN_VARIANCE` first).
fn symmetric_power(s: &[[f64; 3]; 3], p: f64) -> [[f64; 3]; 3] {
    let (values, vectors) = symmetric_eigen(s);
    let scaled = values.map(|v| v.max(MIN_VARIANCE).powf(p));
    // V diag(scaled) V^T, eigenvectors in the columns of V.
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| vectors[i][k] * scaled[k] * vectors[j][k]).sum()))
}

/// Eigenvalues and eigenvectors (columns) of a symmetric 3x3 matrix by
/// cyclic Jacobi rotations: each rotation zeroes one off-diagonal entry;
/// a few sweeps reach machine precision for 3x3.
pub fn symmetric_eigen(s: &[[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    let mut a = *s;
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _sweep in 0..32 {
        let off = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
        let scale = (0..3).map(|i| a[i][i] * a[i][i]).sum::<f64>();
        if off <= 1e-30 * scale.max(1e-300) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            // The rotation angle that zeroes a[p][q] (Golub & Van Loan, sym.schur2).
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let c = 1.0 / (t * t + 1.0).sqrt();
            let sn = t * c;
            // a <- J^T a J, v <- v J, with J the rotation in the (p, q) plane.
            for row in a.iter_mut().chain(v.iter_mut()) {
                let (xp, xq) = (row[p], row[q]);
                row[p] = c * xp - sn * xq;
                row[q] = sn * xp + c * xq;
            }
            let (rp, rq) = (a[p], a[q]);
            a[p] = std::array::from_fn(|k| c * rp[k] - sn * rq[k]);
            a[q] = std::array::from_fn(|k| sn * rp[k] + c * rq[k]);
        }
    }
    ([a[0][0], a[1][1], a[2][2]], v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reconstruct(values: [f64; 3], v: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
        std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| v[i][k] * values[k] * v[j][k]).sum()))
    }

    #[test]
    fn jacobi_reconstructs_a_symmetric_matrix() {
        let s = [[4.0, 1.0, -2.0], [1.0, 2.0, 0.5], [-2.0, 0.5, 3.0]];
        let (values, v) = symmetric_eigen(&s);
        let r = reconstruct(values, &v);
        for i in 0..3 {
            for j in 0..3 {
                assert!((r[i][j] - s[i][j]).abs() < 1e-12, "{r:?} vs {s:?}");
                let dot: f64 = (0..3).map(|k| v[k][i] * v[k][j]).sum();
                assert!((dot - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12, "eigenvectors not orthonormal");
            }
        }
        // Trace and determinant are preserved: 9 and 4(6 - 0.25) - 1(3 + 1) - 2(0.5 + 4) = 10.
        assert!((values.iter().sum::<f64>() - 9.0).abs() < 1e-12);
        assert!((values.iter().product::<f64>() - 10.0).abs() < 1e-10);
    }

    /// Correlated colours from a seeded generator: `base + mix * uniform`.
    fn colours(seed: u64, n: usize, base: [f32; 3], mix: [[f32; 3]; 3]) -> Vec<[f32; 3]> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                let u: [f32; 3] = std::array::from_fn(|_| rng.random::<f32>());
                std::array::from_fn(|i| base[i] + (0..3).map(|j| mix[i][j] * u[j]).sum::<f32>())
            })
            .collect()
    }

    #[test]
    fn recoloured_content_has_the_style_mean_and_covariance() {
        let content = colours(1, 20_000, [0.1, 0.2, 0.1], [[0.6, 0.1, 0.0], [0.3, 0.4, 0.0], [0.1, 0.1, 0.3]]);
        let style = colours(2, 5_000, [0.5, 0.1, 0.3], [[0.1, 0.0, 0.2], [0.2, 0.3, 0.0], [0.0, 0.1, 0.5]]);
        let (c, s) =
            (ColourStats::of(content.iter().copied()).unwrap(), ColourStats::of(style.iter().copied()).unwrap());
        let tf = ColourTransfer::between(&c, &s);
        let mapped: Vec<[f32; 3]> = content.iter().map(|&x| tf.apply_unclamped(x)).collect();
        let m = ColourStats::of(mapped).unwrap();
        for i in 0..3 {
            assert!((m.mean[i] - s.mean[i]).abs() < 1e-5, "mean {:?} vs {:?}", m.mean, s.mean);
            for j in 0..3 {
                assert!(
                    (m.covariance[i][j] - s.covariance[i][j]).abs() < 1e-5,
                    "covariance {:?} vs {:?}",
                    m.covariance,
                    s.covariance
                );
            }
        }
        // The map is symmetric-root based, not just any map with those statistics:
        // content already distributed like the style is left alone.
        let same = ColourTransfer::between(&s, &s);
        for i in 0..3 {
            assert!((same.offset[i]).abs() < 1e-5, "{same:?}");
            for j in 0..3 {
                assert!((same.matrix[i][j] - if i == j { 1.0 } else { 0.0 }).abs() < 1e-5, "{same:?}");
            }
        }
    }

    #[test]
    fn a_flat_style_maps_everything_to_its_colour() {
        let content = colours(3, 1000, [0.2, 0.2, 0.2], [[0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5]]);
        let style = vec![[0.8f32, 0.3, 0.1]; 50];
        let tf = ColourTransfer::between(
            &ColourStats::of(content.iter().copied()).unwrap(),
            &ColourStats::of(style.iter().copied()).unwrap(),
        );
        for x in &content {
            let y = tf.apply(*x);
            assert!(y.iter().zip(style[0]).all(|(a, b)| (a - b).abs() < 1e-3), "{x:?} -> {y:?}");
        }
        // A flat content image does not divide by zero either.
        let tf = ColourTransfer::between(
            &ColourStats::of(style.iter().copied()).unwrap(),
            &ColourStats::of(content.iter().copied()).unwrap(),
        );
        assert!(tf.matrix.iter().flatten().chain(&tf.offset).all(|v| v.is_finite()), "{tf:?}");
        assert!(ColourStats::of([]).is_err());
    }

    #[test]
    fn a_diagonal_matrix_is_already_diagonal() {
        let (values, v) = symmetric_eigen(&[[2.0, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 1.0]]);
        assert_eq!(values, [2.0, 0.5, 1.0]);
        assert_eq!(v, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
    }
}
