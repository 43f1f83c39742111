//! The photoreal fit's render, MSE and gradient in plain Rust: the CPU
//! backends' path for a training step (issue 19).
//!
//! `composite::composite` builds the renderer as a Burn graph (8 corner
//! rows gathered per sample for density and for every SH coefficient, rays
//! padded to the longest, every intermediate materialised) and autodiff
//! reverses it. Here one loop per ray renders it front to back, takes the
//! MSE's gradient with respect to its colour, and walks the samples again
//! for the gradients of density and SH (Plenoxels' CUDA backward does the
//! same per ray):
//!
//! - colour: `dL/dc_i = w_i g`, through `max(., 0)`, into the SH rows with
//!   the colour weights times the sample's SH basis;
//! - density: with `tau_i = sigma_i delta_i`, `w_i = T_i (1 - e^-tau_i)`
//!   and `C = sum_i w_i c_i + T_N bg`, `dC/dtau_i = T_{i+1} c_i - (C -
//!   sum_{j<=i} w_j c_j)`; `dL/dsigma_i = g . dC/dtau_i delta_i` where the
//!   interpolated density is positive, into the density rows with the
//!   trilinear weights.
//!
//! The Burn graph stays the path on a GPU and the oracle of the test
//! `host_fit_gradient_matches_autodiff`. Deterministic: a fixed number of
//! parts (not one per thread), each summing into its own buffers, added in
//! part order.

use rayon::prelude::*;

use crate::field::relu;

use crate::field::host_render::sample_values;
use crate::field::march::SampleBatch;
use crate::util::pool::add_in_order;

/// Parts the rays are split into, each with its own gradient buffers
/// (`rows * (1 + 3 num_basis)` values each: few, as SH degree 2 has 28
/// values per row).
const PARTS: usize = 4;

/// The MSE of a batch and its gradients with respect to the step's rows.
#[derive(Debug, Clone)]
pub struct FitGradient {
    /// Mean over rays and channels of the squared colour error.
    pub mse: f64,
    /// d(mse)/d(density) per step row.
    pub density: Vec<f32>,
    /// d(mse)/d(SH) per step row, `[rows, 3 * num_basis]`.
    pub sh: Vec<f32>,
}

/// The parts' gradient buffers, kept from one step to the next by the
/// trainer: on fern's fine grid they hold tens of MB per part, and fresh
/// ones every step were half of the step (see `util::pool`). The other
/// parts are added into the first part's buffers, which a `FitGradient`
/// then carries out and [`FitBuffers::keep`] gives back.
#[derive(Debug, Default)]
pub struct FitBuffers {
    parts: Vec<PartBuffers>,
}

impl FitBuffers {
    /// Takes back a step's gradient buffers for the next step.
    pub fn keep(&mut self, grad: FitGradient) {
        if let Some(first) = self.parts.first_mut() {
            (first.density, first.sh) = (grad.density, grad.sh);
        }
    }
}

#[derive(Debug, Default)]
struct PartBuffers {
    density: Vec<f32>,
    sh: Vec<f32>,
    samples: Vec<SampleState>,
}

impl PartBuffers {
    /// Zeroed gradients for `rows` rows, keeping the allocations.
    fn reset(&mut self, rows: usize, stride: usize) {
        self.density.clear();
        self.density.resize(rows, 0.0);
        self.sh.clear();
        self.sh.resize(rows * stride, 0.0);
    }
}

/// Renders the rays of `batch` and returns the MSE against `target`
/// (`[rays * 3]`) with its gradients. The step's rows hold `density`
/// (`[rows]`) and `sh` (`[rows, 3 * num_basis]`); `local[k]` is the step
/// row of corner `k` of the batch (`batch.corner_rows[k]` mapped).
/// `buffers` is scratch space a caller keeps between calls.
#[allow(clippy::too_many_arguments)]
pub fn mse_gradient(
    density: &[f32],
    sh: &[f32],
    num_basis: usize,
    batch: &SampleBatch,
    local: &[i32],
    target: &[f32],
    background: [f32; 3],
    buffers: &mut FitBuffers,
) -> FitGradient {
    let rows = density.len();
    let stride = 3 * num_basis;
    assert_eq!(sh.len(), rows * stride, "SH rows [{rows}, {stride}]");
    assert_eq!(local.len(), batch.corner_rows.len(), "one step row per corner");
    assert_eq!(target.len(), batch.num_rays * 3, "one target colour per ray");
    let n = batch.num_rays;
    // d(mse)/d(C) = 2 (C - target) / (3 n).
    let scale = 2.0 / (3 * n.max(1)) as f32;
    let per_part = n.div_ceil(PARTS).max(1);
    let num_parts = n.div_ceil(per_part).max(1);
    buffers.parts.resize_with(num_parts, PartBuffers::default);
    let squared: Vec<f64> = buffers.parts[..num_parts]
        .par_iter_mut()
        .enumerate()
        .map(|(p, part)| {
            part.reset(rows, stride);
            let mut squared = 0.0f64;
            for r in p * per_part..((p + 1) * per_part).min(n) {
                let rgb = forward_ray(density, sh, num_basis, batch, local, r, background, &mut part.samples);
                let mut g = [0.0f32; 3];
                for ch in 0..3 {
                    let e = rgb[ch] - target[r * 3 + ch];
                    squared += (e * e) as f64;
                    g[ch] = scale * e;
                }
                backward_ray(num_basis, batch, local, r, rgb, g, &part.samples, &mut part.density, &mut part.sh);
            }
            squared
        })
        .collect();
    // The sum in part order, into the first part's buffers.
    let (first, rest) = buffers.parts[..num_parts].split_first_mut().expect("at least one part");
    let density: Vec<&[f32]> = rest.iter().map(|p| &p.density[..]).collect();
    let sh: Vec<&[f32]> = rest.iter().map(|p| &p.sh[..]).collect();
    add_in_order(&mut first.density, &density);
    add_in_order(&mut first.sh, &sh);
    FitGradient {
        mse: squared.iter().sum::<f64>() / (3 * n.max(1)) as f64,
        density: std::mem::take(&mut first.density),
        sh: std::mem::take(&mut first.sh),
    }
}

/// What the backward needs of one sample.
#[derive(Debug, Clone, Copy)]
struct SampleState {
    /// Whether the interpolated density was positive (else no density gradient).
    sigma_positive: bool,
    /// Whether each channel's pre-activation colour was positive.
    colour_positive: [bool; 3],
    colour: [f32; 3],
    weight: f32,
    /// Transmittance after the sample, T_{i+1}.
    transmittance_after: f32,
}

/// Ray `r`'s colour, keeping each sample's state in `samples`.
#[allow(clippy::too_many_arguments)]
fn forward_ray(
    density: &[f32],
    sh: &[f32],
    num_basis: usize,
    batch: &SampleBatch,
    local: &[i32],
    r: usize,
    background: [f32; 3],
    samples: &mut Vec<SampleState>,
) -> [f32; 3] {
    let (lo, hi) = (batch.ray_offsets[r] as usize, batch.ray_offsets[r + 1] as usize);
    samples.clear();
    let (mut rgb, mut optical) = ([0.0f32; 3], 0.0f32);
    for s in lo..hi {
        let (sigma, pre) = sample_values(density, sh, num_basis, batch, &local[s * 8..s * 8 + 8], s);
        let tau = relu(sigma) * batch.delta[s];
        let transmittance = (-optical).exp();
        let weight = transmittance * (1.0 - (-tau).exp());
        optical += tau;
        let colour = pre.map(relu);
        for (value, c) in rgb.iter_mut().zip(colour) {
            *value += weight * c;
        }
        let colour_positive = pre.map(|p| p > 0.0);
        samples.push(SampleState {
            sigma_positive: sigma > 0.0,
            colour_positive,
            colour,
            weight,
            transmittance_after: (-optical).exp(),
        });
    }
    let left = (-optical).exp();
    for (value, b) in rgb.iter_mut().zip(background) {
        *value += left * b;
    }
    rgb
}

/// Adds ray `r`'s gradients, given d(loss)/d(colour) `g`, into the step rows.
#[allow(clippy::too_many_arguments)]
fn backward_ray(
    num_basis: usize,
    batch: &SampleBatch,
    local: &[i32],
    r: usize,
    rgb: [f32; 3],
    g: [f32; 3],
    samples: &[SampleState],
    grad_d: &mut [f32],
    grad_sh: &mut [f32],
) {
    let stride = 3 * num_basis;
    let lo = batch.ray_offsets[r] as usize;
    // sum_{j<=i} w_j c_j, so that C - front is what lies behind sample i.
    let mut front = [0.0f32; 3];
    for (i, state) in samples.iter().enumerate() {
        let s = lo + i;
        let corners = s * 8..s * 8 + 8;
        let rows = &local[corners.clone()];
        let mut d_tau = 0.0f32;
        for ch in 0..3 {
            front[ch] += state.weight * state.colour[ch];
            d_tau += g[ch] * (state.transmittance_after * state.colour[ch] - (rgb[ch] - front[ch]));
        }
        if state.sigma_positive {
            let d_sigma = d_tau * batch.delta[s];
            for (w, &row) in batch.corner_weights[corners.clone()].iter().zip(rows) {
                grad_d[row as usize] += w * d_sigma;
            }
        }
        let basis = &batch.basis[s * num_basis..(s + 1) * num_basis];
        for (ch, (&g_ch, &positive)) in g.iter().zip(&state.colour_positive).enumerate() {
            if !positive {
                continue;
            }
            let d_pre = state.weight * g_ch;
            for (w, &row) in batch.colour_weights[corners.clone()].iter().zip(rows) {
                let at = row as usize * stride + ch * num_basis;
                for (gs, b) in grad_sh[at..at + num_basis].iter_mut().zip(basis) {
                    *gs += w * d_pre * b;
                }
            }
        }
    }
}
