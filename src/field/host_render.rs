//! The renderer's forward pass (`composite::composite`) in plain Rust, for
//! views rendered without autodiff on the CPU backends: evaluation, path
//! renders, test views.
//!
//! The Burn graph gathers 8 corner rows of density and SH per sample,
//! materialises every intermediate `[samples, ...]` tensor and pads rays to
//! the longest one; `render_rays` marches and renders each ray in one
//! pass, reading the rows it needs as the march finds its samples (issue
//! 19: `refnpr eval` rendered hundreds of views through the graph, then
//! through a packed batch of every sample). The same arithmetic in the same
//! order per ray; the graph stays the path on a GPU and the oracle of
//! `host_render_matches_the_graph`.

use rayon::prelude::*;

use crate::field::relu;

use crate::field::march::{MarchParams, Marcher, SampleBatch};
use crate::scene::camera::Ray;
use crate::scene::sh;

/// Rays rendered without autodiff, in plain buffers (colours not clamped).
#[derive(Debug, Clone, Default)]
pub struct RaysRender {
    /// Interleaved RGB.
    pub rgb: Vec<f32>,
    pub expected_depth: Vec<f32>,
    pub threshold_depth: Vec<Option<f32>>,
    pub opacity: Vec<f32>,
}

/// Rays rendered at once per rayon task.
const RAYS_PER_TASK: usize = 512;

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
    let corners = s * 8..s * 8 + 8;
    let mut sigma = 0.0f32;
    for (w, &row) in batch.corner_weights[corners.clone()].iter().zip(rows) {
        sigma += w * density[row as usize];
    }
    let basis = &batch.basis[s * num_basis..(s + 1) * num_basis];
    (sigma, sample_colour(sh, num_basis, rows, &batch.colour_weights[corners], basis))
}

/// A sample's colour before the ReLU: the SH coefficients interpolated
/// from its 8 corner `rows` with `colour_weights`, `sum_b coeff_b basis_b +
/// 0.5` per channel. The SH degrees a grid has get a copy each with the
/// row length fixed at compile time (unrolled, vectorised: 12 % of a fern
/// path render with the length a run-time number); the same arithmetic in
/// the same order, so the same bits.
pub(crate) fn sample_colour(
    sh: &[f32],
    num_basis: usize,
    rows: &[i32],
    colour_weights: &[f32],
    basis: &[f32],
) -> [f32; 3] {
    match num_basis {
        1 => sample_colour_of::<3>(sh, rows, colour_weights, basis),
        4 => sample_colour_of::<12>(sh, rows, colour_weights, basis),
        9 => sample_colour_of::<27>(sh, rows, colour_weights, basis),
        16 => sample_colour_of::<48>(sh, rows, colour_weights, basis),
        _ => panic!("SH degree 3 at most ({num_basis} basis functions)"),
    }
}

/// `sample_colour` with rows of `STRIDE` = 3 x basis functions.
#[inline(always)]
fn sample_colour_of<const STRIDE: usize>(sh: &[f32], rows: &[i32], colour_weights: &[f32], basis: &[f32]) -> [f32; 3] {
    let num_basis = STRIDE / 3;
    let mut coefficients = [0.0f32; STRIDE];
    for (w, &row) in colour_weights.iter().zip(rows) {
        let start = row as usize * STRIDE;
        let values: &[f32; STRIDE] = sh[start..start + STRIDE].try_into().expect("a whole SH row");
        for (c, v) in coefficients.iter_mut().zip(values) {
            *c += w * v;
        }
    }
    std::array::from_fn(|ch| {
        coefficients[ch * num_basis..(ch + 1) * num_basis].iter().zip(basis).map(|(c, b)| c * b).sum::<f32>() + 0.5
    })
}

/// Marches and renders `rays` in one pass per ray (`composite::composite`'s
/// arithmetic, per ray, on the samples as `Marcher::walk` finds them:
/// no packed batch, no per-sample tensors): the views rendered on the CPU
/// backends. `sh` is the grid's SH rows as host numbers; each sample's
/// density is the march's own (`MarchSample::sigma`, read from the
/// density mirror), not read again.
pub fn render_rays(
    marcher: &Marcher,
    sh: &[f32],
    rays: &[Ray],
    params: &MarchParams,
    background: [f32; 3],
) -> RaysRender {
    let grid = marcher.grid();
    let (degree, num_basis) = (grid.sh_degree, grid.num_basis());
    let n = rays.len();
    let mut out = RaysRender {
        rgb: vec![0.0; n * 3],
        expected_depth: vec![0.0; n],
        threshold_depth: vec![None; n],
        opacity: vec![0.0; n],
    };
    out.rgb
        .par_chunks_mut(3 * RAYS_PER_TASK)
        .zip(out.expected_depth.par_chunks_mut(RAYS_PER_TASK))
        .zip(out.threshold_depth.par_chunks_mut(RAYS_PER_TASK))
        .zip(out.opacity.par_chunks_mut(RAYS_PER_TASK))
        .zip(rays.par_chunks(RAYS_PER_TASK))
        .for_each(|((((rgb, depth), threshold), opacity), rays)| {
            let mut basis = vec![0.0f32; num_basis];
            for (i, ray) in rays.iter().enumerate() {
                sh::eval_basis(degree, ray.view_dir, &mut basis);
                let (mut colour, mut d, mut optical) = ([0.0f32; 3], 0.0f32, 0.0f32);
                threshold[i] = marcher.walk(ray, params, |s| {
                    let pre = sample_colour(sh, num_basis, &s.rows, &s.colour_weights, &basis);
                    let tau = relu(s.sigma) * s.delta;
                    let weight = (-optical).exp() * (1.0 - (-tau).exp());
                    optical += tau;
                    for (value, pre) in colour.iter_mut().zip(pre) {
                        *value += weight * relu(pre);
                    }
                    d += weight * s.t;
                });
                let left = (-optical).exp();
                let behind = grid.far.as_ref().map_or(background, |far| far.colour(ray.view_dir));
                for (value, b) in colour.iter_mut().zip(behind) {
                    *value += left * b;
                }
                rgb[i * 3..i * 3 + 3].copy_from_slice(&colour);
                depth[i] = d;
                opacity[i] = 1.0 - left;
            }
        });
    out
}
