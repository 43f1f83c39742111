//! The frozen-density colour pass in plain Rust, fused with its gradient:
//! the CPU backends' fast path for the stylization's ray losses.
//!
//! `frozen::render_colour` builds the same computation as a Burn graph
//! (gather the 8 corner rows of each sample, interpolate, `max(C0 c + 0.5,
//! 0)`, weight, sum per ray) and autodiff reverses it, materialising every
//! intermediate (lego's 100,000 pseudo-rays a step are about 3.5 M samples,
//! 28 M gathered rows). On the CPU that graph is the step's largest cost.
//! Here one loop per ray renders the colour, asks the loss for its
//! gradient with respect to that colour, and scatters the gradient into
//! the corner rows at once: what a fused kernel would do on a GPU. The
//! Burn graph stays the path on a GPU and the oracle the tests compare
//! this one against.
//!
//! Deterministic: rays are split into a fixed number of parts (not one per
//! thread), each part sums into its own buffer, and the buffers are added
//! in part order.

use rayon::prelude::*;

use crate::field::relu;

use crate::field::frozen::{FrozenSamples, ListedSample};
use crate::scene::sh;
use crate::util::pool::{BufferPool, sum_in_order};

/// Parts the rays are split into (each with its own gradient buffer).
const PARTS: usize = 8;

/// How many rays ahead a pass starts loading a ray's cells
/// (`FrozenSamples::prefetch_ray`).
const AHEAD: usize = 2;

/// The parts' gradient buffers, kept between calls (see `util::pool`).
static PART_BUFFERS: BufferPool = BufferPool::new(PARTS);

/// For each ray of `rays` (indices into `samples`; all of them when None):
/// its colour from the degree-0 SH rows `sh` (`[rows * 3]`, interleaved),
/// then `loss(k, rgb)` for the k-th ray of the batch returns d(loss)/d(rgb)
/// and the ray's loss value. Returns the gradient with respect to the SH
/// rows, laid out by `slot` (grid row -> buffer row; `slots` buffer rows),
/// and the summed loss.
pub fn colour_gradient<L>(
    sh: &[f32],
    samples: &FrozenSamples,
    rays: Option<&[usize]>,
    background: [f32; 3],
    slots: usize,
    slot: &(dyn Fn(i32) -> i32 + Sync),
    loss: L,
) -> (Vec<f32>, f64)
where
    L: Fn(usize, [f32; 3]) -> ([f32; 3], f32) + Sync,
{
    let n = rays.map_or(samples.num_rays, <[usize]>::len);
    let per_part = n.div_ceil(PARTS).max(1);
    let parts: Vec<(Vec<f32>, f64)> = (0..n.div_ceil(per_part))
        .into_par_iter()
        .map(|p| {
            let mut grad = PART_BUFFERS.zeroed(slots * 3);
            let mut total = 0.0f64;
            // The ray's samples and interpolated coefficients, kept from the colour for the gradient.
            let mut listed: Vec<(ListedSample, [f32; 3])> = Vec::new();
            let end = ((p + 1) * per_part).min(n);
            for k in p * per_part..end {
                let r = rays.map_or(k, |rs| rs[k]);
                if k + AHEAD < end {
                    samples.prefetch_ray(rays.map_or(k + AHEAD, |rs| rs[k + AHEAD]));
                }
                listed.clear();
                listed.extend(samples.ray_samples(r).map(|s| {
                    let pre = interpolate(sh, &s);
                    (s, pre)
                }));
                let rgb = composite(samples, listed.iter().map(|(s, pre)| (s.index, *pre)), r, background);
                let (d_rgb, value) = loss(k, rgb);
                total += value as f64;
                if d_rgb == [0.0; 3] {
                    continue;
                }
                for (s, pre) in &listed {
                    let w = samples.weight[s.index] * sh::C0;
                    for (c, &pre_c) in pre.iter().enumerate() {
                        // d/d(coefficient) of max(C0 x + 0.5, 0), zero where clamped.
                        let g = if sh::C0 * pre_c + 0.5 > 0.0 { w * d_rgb[c] } else { 0.0 };
                        if g == 0.0 {
                            continue;
                        }
                        for (&t, &row) in s.colour_weights.iter().zip(&s.rows) {
                            if t != 0.0 {
                                grad[slot(row) as usize * 3 + c] += t * g;
                            }
                        }
                    }
                }
            }
            (grad, total)
        })
        .collect();
    if parts.is_empty() {
        return (vec![0.0; slots * 3], 0.0);
    }
    let grads: Vec<&[f32]> = parts.iter().map(|(g, _)| &g[..]).collect();
    let grad = sum_in_order(&grads, slots * 3);
    let total = parts.iter().map(|(_, t)| t).sum();
    for (g, _) in parts {
        PART_BUFFERS.give_back(g);
    }
    (grad, total)
}

/// The colours (`[rays * 3]`, interleaved) of `rays` of `samples` (all when None).
pub fn render(sh: &[f32], samples: &FrozenSamples, rays: Option<&[usize]>, background: [f32; 3]) -> Vec<f32> {
    let n = rays.map_or(samples.num_rays, <[usize]>::len);
    let mut out = vec![0.0f32; n * 3];
    out.par_chunks_mut(3 * 1024).enumerate().for_each(|(p, chunk)| {
        for (i, px) in chunk.chunks_mut(3).enumerate() {
            let k = p * 1024 + i;
            let r = rays.map_or(k, |rs| rs[k]);
            if k + AHEAD < n {
                samples.prefetch_ray(rays.map_or(k + AHEAD, |rs| rs[k + AHEAD]));
            }
            let coefficients = samples.ray_samples(r).map(|s| (s.index, interpolate(sh, &s)));
            px.copy_from_slice(&composite(samples, coefficients, r, background));
        }
    });
    out
}

/// The interpolated SH coefficients of a sample.
fn interpolate(sh: &[f32], s: &ListedSample) -> [f32; 3] {
    let mut pre = [0.0f32; 3];
    for (&t, &row) in s.colour_weights.iter().zip(&s.rows) {
        let row = row as usize;
        for c in 0..3 {
            pre[c] += t * sh[row * 3 + c];
        }
    }
    pre
}

/// The colour of ray `r`, whose samples (by index) have the interpolated
/// coefficients `coefficients`, composited over the background.
fn composite(
    samples: &FrozenSamples,
    coefficients: impl IntoIterator<Item = (usize, [f32; 3])>,
    r: usize,
    background: [f32; 3],
) -> [f32; 3] {
    let behind = samples.far.get(r).copied().unwrap_or(background);
    let mut rgb = behind.map(|b| b * samples.final_transmittance[r]);
    for (s, pre) in coefficients {
        for c in 0..3 {
            rgb[c] += samples.weight[s] * relu(sh::C0 * pre[c] + 0.5);
        }
    }
    rgb
}
