//! A learned far background for captures around the scene: an
//! equirectangular map of colours indexed by the ray's world direction
//! (z up), seen through what the grid leaves of each ray
//! (`C = sum w_i c_i + T_last * env(d)`). A far environment has no
//! parallax, so a direction is all it needs; the procedural scene's
//! `--environment` twin is exactly such a skybox.
//!
//! Texel (i, j) covers azimuth `[i, i + 1) * 2 pi / width` (from -pi, about
//! +z) and polar angle `[j, j + 1) * pi / height` (from +z); lookups are
//! bilinear between texel centres, wrapping in azimuth and clamped at the
//! poles, and gradients are splatted with the same weights.

use glam::Vec3;
use std::f32::consts::{PI, TAU};

/// An equirectangular colour map.
#[derive(Debug, Clone, PartialEq)]
pub struct Environment {
    pub width: usize,
    pub height: usize,
    /// Interleaved RGB, row by row from the +z pole.
    pub rgb: Vec<f32>,
}

/// The four texels around a direction and their bilinear weights.
struct Taps {
    index: [usize; 4],
    weight: [f32; 4],
}

impl Environment {
    /// A map of one colour.
    pub fn uniform(width: usize, height: usize, colour: [f32; 3]) -> Self {
        assert!(width >= 1 && height >= 1, "a map of at least one texel");
        Self { width, height, rgb: colour.repeat(width * height) }
    }

    fn taps(&self, dir: Vec3) -> Taps {
        let d = dir.normalize_or(Vec3::Z);
        let u = (d.y.atan2(d.x) + PI) / TAU * self.width as f32 - 0.5;
        let v = d.z.clamp(-1.0, 1.0).acos() / PI * self.height as f32 - 0.5;
        let (u0, v0) = (u.floor(), v.floor());
        let (fu, fv) = (u - u0, v - v0);
        let column = |k: f32| (k as i64).rem_euclid(self.width as i64) as usize;
        let row = |k: f32| (k as i64).clamp(0, self.height as i64 - 1) as usize;
        let (c0, c1, r0, r1) = (column(u0), column(u0 + 1.0), row(v0), row(v0 + 1.0));
        Taps {
            index: [r0 * self.width + c0, r0 * self.width + c1, r1 * self.width + c0, r1 * self.width + c1],
            weight: [(1.0 - fu) * (1.0 - fv), fu * (1.0 - fv), (1.0 - fu) * fv, fu * fv],
        }
    }

    /// The colour seen in direction `dir`.
    pub fn colour(&self, dir: Vec3) -> [f32; 3] {
        let taps = self.taps(dir);
        let mut out = [0.0; 3];
        for (i, w) in taps.index.iter().zip(taps.weight) {
            for (c, value) in out.iter_mut().enumerate() {
                *value += w * self.rgb[i * 3 + c];
            }
        }
        out
    }

    /// The direction through the centre of texel `(column, row)`.
    fn texel_direction(&self, column: usize, row: usize) -> Vec3 {
        let azimuth = (column as f32 + 0.5) / self.width as f32 * TAU - PI;
        let polar = (row as f32 + 0.5) / self.height as f32 * PI;
        Vec3::new(polar.sin() * azimuth.cos(), polar.sin() * azimuth.sin(), polar.cos())
    }

    /// This map resampled to `width` x `height` texels (each new texel the
    /// bilinear colour at its centre): a fit's coarse map carried to a
    /// finer one, whose texels no ray has reached yet keep the coarse colour.
    pub fn resampled(&self, width: usize, height: usize) -> Self {
        let mut out = Self::uniform(width, height, [0.0; 3]);
        for row in 0..height {
            for column in 0..width {
                let colour = self.colour(out.texel_direction(column, row));
                let at = (row * width + column) * 3;
                out.rgb[at..at + 3].copy_from_slice(&colour);
            }
        }
        out
    }

    /// Hands each texel `colour(dir)` reads, with its bilinear weight, to `visit`.
    pub fn splat(&self, dir: Vec3, mut visit: impl FnMut(usize, f32)) {
        let taps = self.taps(dir);
        for (&i, w) in taps.index.iter().zip(taps.weight) {
            visit(i, w);
        }
    }

    /// Adds `d(loss)/d(colour(dir)) = g` into `grad` (one value per entry of `rgb`).
    pub fn add_gradient(&self, dir: Vec3, g: [f32; 3], grad: &mut [f32]) {
        assert_eq!(grad.len(), self.rgb.len(), "one gradient per colour value");
        self.splat(dir, |i, w| {
            for (c, gc) in g.iter().enumerate() {
                grad[i * 3 + c] += w * gc;
            }
        });
    }
}

/// The far map's optimiser: RMSprop over its colour values (Plenoxels'
/// optimiser for the grid, here dense: the map holds a few thousand
/// texels), colours kept in [0, 1].
#[derive(Debug, Clone, Default)]
pub struct FarOptimiser {
    /// Running average of each value's squared gradient (empty: all zero).
    pub mean_square: Vec<f32>,
}

impl FarOptimiser {
    /// One step on `env` with `grad` (one value per entry of `env.rgb`).
    pub fn step(&mut self, env: &mut Environment, grad: &[f32], lr: f32, beta: f32, eps: f32) {
        assert_eq!(grad.len(), env.rgb.len(), "one gradient per colour value");
        self.mean_square.resize(grad.len(), 0.0);
        for ((value, avg), &g) in env.rgb.iter_mut().zip(&mut self.mean_square).zip(grad) {
            *avg = beta * *avg + (1.0 - beta) * g * g;
            *value = (*value - lr * g / (avg.sqrt() + eps)).clamp(0.0, 1.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(width: usize, height: usize) -> Environment {
        let rgb = (0..width * height).flat_map(|i| [i as f32 / 7.0, (i % 5) as f32 * 0.1, 0.3]).collect();
        Environment { width, height, rgb }
    }

    #[test]
    fn a_uniform_map_is_its_colour_in_every_direction() {
        let env = Environment::uniform(8, 4, [0.2, 0.5, 0.9]);
        for d in [Vec3::Z, -Vec3::Z, Vec3::X, Vec3::new(-1.0, -1e-7, 0.3), Vec3::new(0.3, -0.8, -0.2)] {
            for (a, b) in env.colour(d).iter().zip([0.2, 0.5, 0.9]) {
                assert!((a - b).abs() < 1e-6, "{d}: {:?}", env.colour(d));
            }
        }
    }

    #[test]
    fn a_texel_centre_reads_its_texel_and_the_seam_is_continuous() {
        let env = ramp(8, 4);
        // Texel (2, 1): azimuth centre (2.5 / 8) 2 pi - pi, polar centre (1.5 / 4) pi.
        let (az, polar) = (2.5 / 8.0 * TAU - PI, 1.5 / 4.0 * PI);
        let d = Vec3::new(polar.sin() * az.cos(), polar.sin() * az.sin(), polar.cos());
        let want = &env.rgb[(8 + 2) * 3..(8 + 2) * 3 + 3];
        for (a, b) in env.colour(d).iter().zip(want) {
            assert!((a - b).abs() < 1e-5, "{:?} vs {want:?}", env.colour(d));
        }
        // Just either side of azimuth +-pi.
        let across = |s: f32| env.colour(Vec3::new(-1.0, s * 1e-5, 0.2));
        for (a, b) in across(1.0).iter().zip(across(-1.0)) {
            assert!((a - b).abs() < 1e-3, "{:?} vs {:?}", across(1.0), across(-1.0));
        }
    }

    #[test]
    fn a_resampled_map_keeps_its_colours() {
        let env = ramp(8, 4);
        // The same size: every texel reads itself back.
        let same = env.resampled(8, 4);
        for (a, b) in same.rgb.iter().zip(&env.rgb) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
        // Twice as fine: the colour in any direction moves less than one coarse texel's step.
        let fine = env.resampled(16, 8);
        let step =
            env.rgb.chunks(3).zip(env.rgb.chunks(3).skip(1)).map(|(a, b)| (a[0] - b[0]).abs()).fold(0.0, f32::max);
        for d in [Vec3::new(0.3, 0.2, 0.5), Vec3::new(-0.7, 0.1, -0.2), Vec3::new(0.1, -0.9, 0.05)] {
            let (a, b) = (env.colour(d), fine.colour(d));
            assert!((a[0] - b[0]).abs() <= step, "{d}: {a:?} vs {b:?}");
            assert!((a[2] - b[2]).abs() < 1e-5, "{d}: a constant channel stays");
        }
    }

    #[test]
    fn the_gradient_is_the_lookups_derivative() {
        let env = ramp(6, 3);
        let d = Vec3::new(0.4, -0.7, 0.35);
        let g = [0.3, -1.2, 0.5];
        let mut grad = vec![0.0; env.rgb.len()];
        env.add_gradient(d, g, &mut grad);
        let loss = |e: &Environment| e.colour(d).iter().zip(g).map(|(c, g)| c * g).sum::<f32>();
        for (k, analytic) in grad.iter().enumerate() {
            let mut moved = env.clone();
            moved.rgb[k] += 1e-2;
            let numeric = (loss(&moved) - loss(&env)) / 1e-2;
            assert!((numeric - analytic).abs() < 1e-4, "value {k}: {numeric} vs {analytic}");
        }
    }
}
