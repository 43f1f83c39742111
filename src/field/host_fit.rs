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
    /// d(mse)/d(background colour) per ray, `[rays, 3]`, when the batch
    /// carries a far background (`SampleBatch::far`); else empty.
    pub far: Vec<f32>,
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
    /// For the parts after the first: one bit per step row that the part's
    /// rays may have written (the rows of all their samples' corners).
    /// Every other value of the part's buffers is zero.
    touched: Vec<u64>,
    samples: Vec<SampleState>,
}

impl PartBuffers {
    /// Zeroed gradients for `rows` rows, keeping the allocations: the first
    /// part's buffers, which carry the gradient out and come back holding
    /// other values. Zeroed in parallel, before the parts start: inside
    /// the first part it made that part the last to finish (76 MB a fern
    /// step).
    fn reset(&mut self, rows: usize, stride: usize) {
        for (buffer, len) in [(&mut self.density, rows), (&mut self.sh, rows * stride)] {
            buffer.truncate(len);
            buffer.resize(len, 0.0);
            buffer.par_chunks_mut(1 << 16).for_each(|chunk| chunk.fill(0.0));
        }
    }

    /// At least `rows` rows for the parts after the first. Their buffers
    /// are zero but for the touched rows, and the sum
    /// (`add_touched_in_order`) zeroes those as it reads them: only new
    /// rows need zeros. Zeroing all of them every step cost about 50 ms a
    /// fern step (four buffers of 90 MB), while a part's rays touch about a
    /// quarter of the rows.
    fn grow(&mut self, rows: usize, stride: usize) {
        if self.density.len() < rows {
            self.density.resize(rows, 0.0);
        }
        if self.sh.len() < rows * stride {
            self.sh.resize(rows * stride, 0.0);
        }
        if self.touched.len() < rows.div_ceil(64) {
            self.touched.resize(rows.div_ceil(64), 0);
        }
    }

    /// Marks the rows of corner entries `local`.
    fn mark(&mut self, local: &[i32]) {
        for &row in local {
            self.touched[row as usize / 64] |= 1 << (row as usize % 64);
        }
    }
}

/// Adds the touched rows of `rest` into `density` and `sh` (`stride`
/// values a row), in part order, and zeroes what it read (rows and bits).
/// The same bits as adding every row of every part in order: an untouched
/// row of a part is +0.0, and adding +0.0 changes no sum that is not -0.0,
/// which a sum starting at +0.0 never is (in round-to-nearest, `x + -x` is
/// +0.0). In parallel over blocks of rows, each row's additions in order.
fn add_touched_in_order(density: &mut [f32], sh: &mut [f32], stride: usize, rest: &mut [PartBuffers]) {
    const WORDS: usize = 64;
    const ROWS: usize = WORDS * 64;
    let rows = density.len();
    type Block<'a> = (&'a mut [f32], &'a mut [f32], Vec<(&'a mut [f32], &'a mut [f32], &'a mut [u64])>);
    let mut blocks: Vec<Block> = density
        .chunks_mut(ROWS)
        .zip(sh.chunks_mut(ROWS * stride))
        .map(|(d, s)| (d, s, Vec::with_capacity(rest.len())))
        .collect();
    for part in rest.iter_mut() {
        let pieces = part.density[..rows]
            .chunks_mut(ROWS)
            .zip(part.sh[..rows * stride].chunks_mut(ROWS * stride))
            .zip(part.touched[..rows.div_ceil(64)].chunks_mut(WORDS));
        for (block, ((d, s), bits)) in blocks.iter_mut().zip(pieces) {
            block.2.push((d, s, bits));
        }
    }
    blocks.into_par_iter().for_each(|(density, sh, mut parts)| {
        for w in 0..density.len().div_ceil(64) {
            let mut any = parts.iter().fold(0u64, |acc, p| acc | p.2[w]);
            while any != 0 {
                let row = w * 64 + any.trailing_zeros() as usize;
                let bit = 1u64 << (row % 64);
                any &= any - 1;
                for (d, s, bits) in parts.iter_mut() {
                    if bits[w] & bit == 0 {
                        continue;
                    }
                    density[row] += d[row];
                    d[row] = 0.0;
                    let span = row * stride..(row + 1) * stride;
                    for (out, v) in sh[span.clone()].iter_mut().zip(&mut s[span]) {
                        *out += *v;
                        *v = 0.0;
                    }
                }
            }
            parts.iter_mut().for_each(|p| p.2[w] = 0);
        }
    });
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
    buffers.parts[0].reset(rows, stride);
    let with_far = !batch.far.is_empty();
    let per_part_results: Vec<(f64, Vec<f32>)> = buffers.parts[..num_parts]
        .par_iter_mut()
        .enumerate()
        .map(|(p, part)| {
            if p > 0 {
                part.grow(rows, stride);
            }
            let (mut squared, mut far) = (0.0f64, Vec::new());
            let part_rays = p * per_part..((p + 1) * per_part).min(n);
            if p > 0 {
                let (lo, hi) = (batch.ray_offsets[part_rays.start] as usize, batch.ray_offsets[part_rays.end] as usize);
                part.mark(&local[lo * 8..hi * 8]);
            }
            for r in part_rays {
                let behind = batch.background_of(r, background);
                let (rgb, left) = forward_ray(density, sh, num_basis, batch, local, r, behind, &mut part.samples);
                let mut g = [0.0f32; 3];
                for ch in 0..3 {
                    let e = rgb[ch] - target[r * 3 + ch];
                    squared += (e * e) as f64;
                    g[ch] = scale * e;
                }
                if with_far {
                    far.extend(g.map(|g| left * g));
                }
                backward_ray(num_basis, batch, local, r, rgb, g, &part.samples, &mut part.density, &mut part.sh);
            }
            (squared, far)
        })
        .collect();
    // The sum in part order, into the first part's buffers.
    let (first, rest) = buffers.parts[..num_parts].split_first_mut().expect("at least one part");
    add_touched_in_order(&mut first.density, &mut first.sh, stride, rest);
    FitGradient {
        mse: per_part_results.iter().map(|(squared, _)| squared).sum::<f64>() / (3 * n.max(1)) as f64,
        density: std::mem::take(&mut first.density),
        sh: std::mem::take(&mut first.sh),
        far: per_part_results.into_iter().flat_map(|(_, far)| far).collect(),
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

/// Ray `r`'s colour over `background` and the transmittance it leaves,
/// keeping each sample's state in `samples`.
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
) -> ([f32; 3], f32) {
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
    (rgb, left)
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

#[cfg(test)]
mod tests {
    use super::{PartBuffers, add_touched_in_order};
    use crate::util::pool::add_in_order;

    /// The sparse sum gives the same bits as adding every row of every part
    /// in order, over blocks of rows and rows that sums cancel to zero in,
    /// and leaves the parts zero with no touched rows.
    #[test]
    fn touched_rows_sum_as_the_dense_parts_do() {
        let (rows, stride) = (3 * 4096 + 77, 3);
        let value = |p: usize, i: usize| ((i * 7919 + p * 104_729) % 1000) as f32 * 1e-3 - 0.5;
        // Zero on every third row, so that cancelling parts sum to zero there.
        let mut first_d: Vec<f32> = (0..rows).map(|i| if i % 3 == 0 { 0.0 } else { value(9, i) }).collect();
        let mut first_s: Vec<f32> = (0..rows * stride).map(|i| value(8, i)).collect();
        let mut parts: Vec<PartBuffers> = (0..3).map(|_| PartBuffers::default()).collect();
        for (p, part) in parts.iter_mut().enumerate() {
            // A longer buffer than this step's rows, as after a larger step.
            part.grow(rows + 100, stride);
            let touched: Vec<i32> = (0..rows as i32).filter(|r| (*r as usize * (p + 3)) % 5 < 2).collect();
            part.mark(&touched);
            for &r in &touched {
                let r = r as usize;
                // Part 2 cancels part 1 where both touch: sums of exactly zero.
                part.density[r] = if p == 2 { -value(1, r) } else { value(p, r) };
                for k in 0..stride {
                    part.sh[r * stride + k] = value(p + 10, r * stride + k);
                }
            }
        }
        let (mut dense_d, mut dense_s) = (first_d.clone(), first_s.clone());
        add_in_order(&mut dense_d, &parts.iter().map(|p| &p.density[..rows]).collect::<Vec<_>>());
        add_in_order(&mut dense_s, &parts.iter().map(|p| &p.sh[..rows * stride]).collect::<Vec<_>>());
        add_touched_in_order(&mut first_d, &mut first_s, stride, &mut parts);
        assert!(first_d.contains(&0.0), "some sums cancel to zero");
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&first_d), bits(&dense_d));
        assert_eq!(bits(&first_s), bits(&dense_s));
        for part in &parts {
            assert!(part.density.iter().chain(&part.sh).all(|v| v.to_bits() == 0), "parts left at +0.0");
            assert!(part.touched.iter().all(|w| *w == 0), "no touched rows left");
        }
    }
}

/// Checked against the Burn graph and autodiff, on every backend the test
/// command runs (`cargo test --lib graph_oracle`).
#[cfg(test)]
#[allow(clippy::print_stdout, clippy::print_stderr)] // the measured errors, shown with --nocapture
mod graph_oracle {
    use crate::field::composite::{BatchTensors, composite};
    use crate::field::march;
    use crate::scene::sh;
    use crate::test_support::{device, params, sparse_degree2_grid, tol};
    use crate::util::tensor::{floats, to_vec};

    /// The photoreal fit's plain-Rust pass (`field::host_fit`: render, MSE
    /// and gradient per ray, the training step on the CPU backends) against the
    /// Burn graph and autodiff: the MSE and the gradients of density and SH
    /// (degree 2) to 1e-5 of their largest value, with step rows mapped as a
    /// training step maps them (a permutation of the grid rows), on rays that
    /// hit, graze and miss, over negative and positive densities.
    #[test]
    fn host_fit_gradient_matches_autodiff() {
        let (grid, dens, shd, rays) = sparse_degree2_grid(3.5);
        let (n, nb, dev) = (dens.len(), sh::num_basis(2), device());
        let batch = march::generate_samples(&grid, &rays, &params(0.25));
        let target: Vec<f32> = (0..rays.len() * 3).map(|i| ((i * 37) % 11) as f32 / 11.0).collect();
        let bg = [0.2, 0.5, 0.9];
        // Step rows in reverse grid order: step row k holds grid row n - 1 - k.
        let local = |r: i32| n as i32 - 1 - r;
        let step_dens: Vec<f32> = (0..n).map(|k| dens[n - 1 - k]).collect();
        let step_sh: Vec<f32> = (0..n).flat_map(|k| shd[(n - 1 - k) * 3 * nb..(n - k) * 3 * nb].to_vec()).collect();
        let corners: Vec<i32> = batch.corner_rows.iter().map(|&r| local(r)).collect();
        let fit = |target: &[f32], buffers: &mut crate::field::host_fit::FitBuffers| {
            crate::field::host_fit::mse_gradient(&step_dens, &step_sh, nb, &batch, &corners, target, bg, buffers)
        };
        // The buffers a trainer keeps between steps: a previous step's gradients
        // left in them must not leak into the next, whether it had more step
        // rows (here 70 more, the step rows in another order) or the same.
        let mut buffers = Default::default();
        let more = n + 70;
        let (more_dens, more_sh) = (vec![0.3f32; more], vec![0.1f32; more * 3 * nb]);
        let shifted: Vec<i32> = corners.iter().map(|&r| (r + 70) % more as i32).collect();
        let reversed: Vec<f32> = target.iter().rev().copied().collect();
        let earlier = crate::field::host_fit::mse_gradient(
            &more_dens,
            &more_sh,
            nb,
            &batch,
            &shifted,
            &reversed,
            bg,
            &mut buffers,
        );
        buffers.keep(earlier);
        let first = fit(&reversed, &mut buffers);
        buffers.keep(first.clone());
        let host = fit(&target, &mut buffers);
        let fresh = fit(&target, &mut Default::default());
        assert!(first.sh != host.sh, "a different target gives different gradients");
        assert!(host.sh == fresh.sh && host.density == fresh.density, "reused buffers change the gradient");

        let bt = BatchTensors::for_gradients(&batch, Some(&local), &dev);
        let ld = floats(step_dens, [n, 1], &dev).autodiff().require_grad();
        let ls = floats(step_sh, [n, 3 * nb], &dev).autodiff().require_grad();
        let out = composite(ld.clone(), ls.clone(), &bt, bg);
        let diff = out.rgb - floats(target, [rays.len(), 3], &dev);
        let mse = (diff.clone() * diff).mean();
        let grads = mse.clone().backward();
        let mse = to_vec(mse.inner())[0];
        println!("mse: host {} graph {mse}", host.mse);
        assert!((host.mse as f32 - mse).abs() <= tol(1e-5) * mse, "mse {} vs {mse}", host.mse);
        for (name, host, graph) in [
            ("density", host.density, to_vec(ld.grad(&grads).unwrap())),
            ("sh", host.sh, to_vec(ls.grad(&grads).unwrap())),
        ] {
            let scale = graph.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let err = host.iter().zip(&graph).fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
            println!("{name}: max |host - graph| = {err:.2e} of {scale:.2e}");
            assert!(scale > 0.0 && host.iter().filter(|g| **g != 0.0).count() > 10, "{name}: no gradient");
            assert!(err <= tol(1e-5) * scale, "{name}: {err:.2e} of {scale:.2e}");
        }
    }
}
