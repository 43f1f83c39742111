//! The differentiable half of volume rendering (paper eqs. 1-2): a Burn
//! graph over the packed samples of `march` - gather the 8 corner rows,
//! weight, sum; ReLU density; SH colour; per-ray transmittance in a padded
//! `[rays, K]` layout; weights and sums - so autodiff reaches the grid rows.
//! Views are rendered by `view::ViewRenderer`, with this graph on a GPU.

use burn::tensor::{Device, Tensor, activation::relu};

use crate::field::march::SampleBatch;
use crate::util::backend::max_buffer_bytes;
use crate::util::gather_op::{RowIndex, gather_rows};
use crate::util::tensor::{floats, indices};

/// The most samples one [`composite`] call may take on `device` with
/// `columns` colour coefficients a row: its largest tensors, the 8 corner
/// rows gathered per sample and their gradient, must each fit in one of
/// the device's buffers (wgpu's storage-buffer limit: 128 MiB on Mesa's
/// lavapipe, where a larger binding reads garbage instead of failing).
/// Unbounded on the CPU backends. Callers cut larger batches into runs of
/// rays ([`SampleBatch::ray_runs`]).
pub fn max_samples_per_call(device: &Device, columns: usize) -> usize {
    match max_buffer_bytes(device) {
        Some(limit) => (limit / (8 * columns.max(1) as u64 * 4)).max(1) as usize,
        None => usize::MAX,
    }
}

/// A sample batch uploaded to a device, ready for `composite`.
pub struct BatchTensors {
    pub num_rays: usize,
    pub num_samples: usize,
    /// Samples per ray in the padded [rays, K] layout.
    pub k: usize,
    /// Each sample's 8 corner rows, `[s * 8]` (with their transpose when
    /// built for gradients on a GPU: `util::gather_op`).
    pub corners: RowIndex,
    pub corner_weights: Tensor<2>,
    pub colour_weights: Tensor<2>,
    pub basis: Tensor<3>,
    pub delta: Tensor<1>,
    pub t: Tensor<1>,
    /// For each padded slot, the packed sample index, or `num_samples` for padding.
    pub pad_map: RowIndex,
    /// The far background per ray, `[rays, 3]` (`SampleBatch::far`), or
    /// `None` for the constant background. A fit makes it a leaf of its
    /// graph to learn the far map.
    pub far: Option<Tensor<2>>,
}

impl BatchTensors {
    /// Uploads a batch. `remap` replaces each corner's grid row (e.g. by a
    /// local row of a training step's parameter subset).
    pub fn new(b: &SampleBatch, remap: Option<&dyn Fn(i32) -> i32>, device: &Device) -> Self {
        Self::upload(b, remap, false, device)
    }

    /// As [`new`](Self::new), for a graph that is differentiated: on a GPU
    /// the gathers' index transposes are uploaded too, so that their
    /// backward runs in parallel (`util::gather_op`).
    pub fn for_gradients(b: &SampleBatch, remap: Option<&dyn Fn(i32) -> i32>, device: &Device) -> Self {
        Self::upload(b, remap, true, device)
    }

    fn upload(b: &SampleBatch, remap: Option<&dyn Fn(i32) -> i32>, gradients: bool, device: &Device) -> Self {
        let s = b.num_samples();
        let nb = b.basis.len().checked_div(s).unwrap_or(1);
        let k = b.max_samples_per_ray().max(1);
        let mut pad = vec![s as i32; b.num_rays * k];
        for r in 0..b.num_rays {
            let (lo, hi) = (b.ray_offsets[r] as usize, b.ray_offsets[r + 1] as usize);
            for (j, i) in (lo..hi).enumerate() {
                pad[r * k + j] = i as i32;
            }
        }
        let corners: Vec<i32> = match remap {
            Some(f) => b.corner_rows.iter().map(|&r| f(r)).collect(),
            None => b.corner_rows.clone(),
        };
        let index = |idx: Vec<i32>, rows: usize| match gradients {
            true => RowIndex::new(idx, rows, device),
            false => RowIndex::plain(indices(idx, device)),
        };
        // The corner rows' table is the grid (or the step's rows): rows past
        // the largest one read get no gradient from this batch anyway. A
        // render-only upload needs no bound.
        let corner_rows = match gradients {
            true => corners.iter().copied().max().map_or(0, |m| m as usize + 1),
            false => 0,
        };
        Self {
            num_rays: b.num_rays,
            num_samples: s,
            k,
            corners: index(corners, corner_rows),
            corner_weights: floats(b.corner_weights.clone(), [s * 8, 1], device),
            colour_weights: floats(b.colour_weights.clone(), [s * 8, 1], device),
            basis: floats(b.basis.clone(), [s, 1, nb], device),
            delta: floats(b.delta.clone(), [s], device),
            t: floats(b.t.clone(), [s], device),
            // The padding slots read row `s`, a constant zero: no gradient.
            pad_map: index(pad, s),
            far: (!b.far.is_empty()).then(|| floats(b.far.concat(), [b.num_rays, 3], device)),
        }
    }
}

/// What the differentiable renderer returns per ray.
pub struct Rendered {
    /// [rays, 3]
    pub rgb: Tensor<2>,
    /// Expected depth sum(w_i t_i), `[rays]`
    pub depth: Tensor<1>,
    /// Accumulated opacity 1 - T_final, `[rays]`
    pub opacity: Tensor<1>,
}

/// Trilinear interpolation at `s` samples: gathers the 8 corner rows of each
/// (`corners`, `[s * 8]`), weights them (`weights`, `[s * 8, 1]`) and sums,
/// giving `[s, columns]`.
pub fn interpolate_corners(rows: Tensor<2>, corners: &RowIndex, weights: Tensor<2>) -> Tensor<2> {
    let columns = rows.dims()[1];
    let s = corners.idx.dims()[0] / 8;
    (gather_rows(rows, corners) * weights).reshape([s, 8, columns]).sum_dim(1).reshape([s, columns])
}

/// Moves packed per-sample values into the padded [rays, K] layout (zero padding).
fn to_padded<const D: usize>(packed: Tensor<D>, bt: &BatchTensors, tail: [usize; D]) -> Tensor<D> {
    let mut zshape = tail;
    zshape[0] = 1;
    let zero = Tensor::zeros(zshape, &packed.device());
    let table = Tensor::cat(vec![packed, zero], 0);
    let rows = table.dims()[0];
    // Gathered as rows of one column or more, then given the caller's rank.
    let columns = table.shape().num_elements() / rows.max(1);
    let padded = gather_rows(table.reshape([rows, columns]), &bt.pad_map);
    let mut out_shape = tail;
    out_shape[0] = bt.pad_map.idx.dims()[0];
    padded.reshape(out_shape)
}

/// Equations 1-2 on the packed samples: density and colour by trilinear
/// interpolation of the given rows (colour over the active corners only), then alpha compositing per ray, with
/// the background (the batch's far colours, else `background`) weighted by
/// the remaining transmittance.
pub fn composite(density_rows: Tensor<2>, sh_rows: Tensor<2>, bt: &BatchTensors, background: [f32; 3]) -> Rendered {
    let device = density_rows.device();
    let (r, s, k) = (bt.num_rays, bt.num_samples, bt.k);
    let bg = match &bt.far {
        Some(far) => far.clone(),
        None => floats(background.to_vec(), [1, 3], &device).repeat_dim(0, r),
    };
    if s == 0 {
        return Rendered { rgb: bg, depth: Tensor::zeros([r], &device), opacity: Tensor::zeros([r], &device) };
    }
    let nb = sh_rows.dims()[1] / 3;
    let sigma = relu(interpolate_corners(density_rows, &bt.corners, bt.corner_weights.clone()).reshape([s]));
    let coeffs = interpolate_corners(sh_rows, &bt.corners, bt.colour_weights.clone()).reshape([s, 3, nb]);
    let colour = relu((coeffs * bt.basis.clone()).sum_dim(2).reshape([s, 3]) + 0.5);

    let tau = to_padded(sigma * bt.delta.clone(), bt, [s]).reshape([r, k]);
    let optical = tau.clone().cumsum(1);
    let transmittance = (tau.clone() - optical.clone()).exp(); // T_i = exp(-sum_{j<i} tau_j)
    let weights = transmittance * (-(tau.neg().exp()) + 1.0);
    let final_t = optical.narrow(1, k - 1, 1).neg().exp(); // [r, 1]

    let colour = to_padded(colour, bt, [s, 3]).reshape([r, k, 3]);
    let rgb = (weights.clone().reshape([r, k, 1]) * colour).sum_dim(1).reshape([r, 3]) + final_t.clone() * bg;
    let t = to_padded(bt.t.clone(), bt, [s]).reshape([r, k]);
    let depth = (weights * t).sum_dim(1).reshape([r]);
    let opacity = (-final_t + 1.0).reshape([r]);
    Rendered { rgb, depth, opacity }
}
