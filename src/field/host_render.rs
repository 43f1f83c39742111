//! The renderer's forward pass (`composite::composite`) in plain Rust, for
//! views rendered without autodiff on the CPU backends: evaluation, path
//! renders, test views.
//!
//! The Burn graph gathers 8 corner rows of density and SH per sample,
//! materialises every intermediate `[samples, ...]` tensor and pads rays to
//! the longest one; this loop walks each ray once, reading the rows it
//! needs (issue 19: `refnpr eval` rendered hundreds of views through the
//! graph). The same arithmetic in the same order per ray; the graph stays
//! the path on a GPU and the oracle of `host_render_matches_the_graph`.

use rayon::prelude::*;

use crate::field::relu;

use crate::field::march::SampleBatch;

/// Rays rendered at once per rayon task.
const RAYS_PER_TASK: usize = 512;

/// Colours (interleaved, not clamped), expected depth and opacity of the
/// rays of `batch`: `density` one value per grid row (the density mirror),
/// `sh` the SH rows `[rows, 3 * num_basis]` (channel-major within a row).
pub fn render_batch(
    density: &[f32],
    sh: &[f32],
    num_basis: usize,
    batch: &SampleBatch,
    background: [f32; 3],
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let n = batch.num_rays;
    let mut rgb = vec![0.0f32; n * 3];
    let mut depth = vec![0.0f32; n];
    let mut opacity = vec![0.0f32; n];
    rgb.par_chunks_mut(3 * RAYS_PER_TASK)
        .zip(depth.par_chunks_mut(RAYS_PER_TASK))
        .zip(opacity.par_chunks_mut(RAYS_PER_TASK))
        .enumerate()
        .for_each(|(task, ((rgb, depth), opacity))| {
            for i in 0..depth.len() {
                let r = task * RAYS_PER_TASK + i;
                let (colour, d, o) = render_ray(density, sh, num_basis, batch, r, background);
                rgb[i * 3..i * 3 + 3].copy_from_slice(&colour);
                depth[i] = d;
                opacity[i] = o;
            }
        });
    (rgb, depth, opacity)
}

/// One ray: `max(sigma, 0)` and the SH coefficients interpolated at each
/// sample, colour `max(sum_b coeff_b basis_b + 0.5, 0)`, alpha-composited
/// front to back over the background.
fn render_ray(
    density: &[f32],
    sh: &[f32],
    num_basis: usize,
    batch: &SampleBatch,
    r: usize,
    background: [f32; 3],
) -> ([f32; 3], f32, f32) {
    let (lo, hi) = (batch.ray_offsets[r] as usize, batch.ray_offsets[r + 1] as usize);
    let (mut rgb, mut depth, mut optical) = ([0.0f32; 3], 0.0f32, 0.0f32);
    for s in lo..hi {
        let (sigma, pre) = sample_values(density, sh, num_basis, batch, &batch.corner_rows[s * 8..s * 8 + 8], s);
        let tau = relu(sigma) * batch.delta[s];
        let weight = (-optical).exp() * (1.0 - (-tau).exp());
        optical += tau;
        for (value, pre) in rgb.iter_mut().zip(pre) {
            *value += weight * relu(pre);
        }
        depth += weight * batch.t[s];
    }
    let left = (-optical).exp();
    for (value, b) in rgb.iter_mut().zip(background) {
        *value += left * b;
    }
    (rgb, depth, 1.0 - left)
}

/// Sample `s`'s interpolated density (before the ReLU) and its colour
/// before the ReLU, `sum_b coeff_b basis_b + 0.5` per channel, the
/// coefficients interpolated from the SH rows; `rows` are the sample's 8
/// corner rows into `density` and `sh` (`[rows, 3 * num_basis]`).
pub(crate) fn sample_values(
    density: &[f32],
    sh: &[f32],
    num_basis: usize,
    batch: &SampleBatch,
    rows: &[i32],
    s: usize,
) -> (f32, [f32; 3]) {
    assert!(num_basis <= 16, "SH degree 3 at most");
    let stride = 3 * num_basis;
    let corners = s * 8..s * 8 + 8;
    let mut sigma = 0.0f32;
    for (w, &row) in batch.corner_weights[corners.clone()].iter().zip(rows) {
        sigma += w * density[row as usize];
    }
    let mut coefficients = [0.0f32; 3 * 16];
    let coefficients = &mut coefficients[..stride];
    for (w, &row) in batch.colour_weights[corners].iter().zip(rows) {
        for (c, v) in coefficients.iter_mut().zip(&sh[row as usize * stride..(row as usize + 1) * stride]) {
            *c += w * v;
        }
    }
    let basis = &batch.basis[s * num_basis..(s + 1) * num_basis];
    let pre = std::array::from_fn(|ch| {
        coefficients[ch * num_basis..(ch + 1) * num_basis].iter().zip(basis).map(|(c, b)| c * b).sum::<f32>() + 0.5
    });
    (sigma, pre)
}
