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
    let stride = 3 * num_basis;
    let (lo, hi) = (batch.ray_offsets[r] as usize, batch.ray_offsets[r + 1] as usize);
    let (mut rgb, mut depth, mut optical) = ([0.0f32; 3], 0.0f32, 0.0f32);
    let mut coefficients = [0.0f32; 3 * 16];
    for s in lo..hi {
        let corners = s * 8..s * 8 + 8;
        let rows = &batch.corner_rows[corners.clone()];
        let mut sigma = 0.0f32;
        for (w, &row) in batch.corner_weights[corners.clone()].iter().zip(rows) {
            sigma += w * density[row as usize];
        }
        let coefficients = &mut coefficients[..stride];
        coefficients.fill(0.0);
        for (w, &row) in batch.colour_weights[corners].iter().zip(rows) {
            let sh_row = &sh[row as usize * stride..(row as usize + 1) * stride];
            for (c, v) in coefficients.iter_mut().zip(sh_row) {
                *c += w * v;
            }
        }
        let basis = &batch.basis[s * num_basis..(s + 1) * num_basis];
        let tau = relu(sigma) * batch.delta[s];
        let weight = (-optical).exp() * (1.0 - (-tau).exp());
        optical += tau;
        for (ch, value) in rgb.iter_mut().enumerate() {
            let channel = &coefficients[ch * num_basis..(ch + 1) * num_basis];
            let pre: f32 = channel.iter().zip(basis).map(|(c, b)| c * b).sum();
            *value += weight * relu(pre + 0.5);
        }
        depth += weight * batch.t[s];
    }
    let left = (-optical).exp();
    for (value, b) in rgb.iter_mut().zip(background) {
        *value += left * b;
    }
    (rgb, depth, 1.0 - left)
}
