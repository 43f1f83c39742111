//! The differentiable half of volume rendering (paper eqs. 1-2): a Burn
//! graph over the packed samples of `march` - gather the 8 corner rows,
//! weight, sum; ReLU density; SH colour; per-ray transmittance in a padded
//! `[rays, K]` layout; weights and sums - so autodiff reaches the grid rows.
//! Views are rendered by `view::ViewRenderer`. On a GPU the same
//! equations run as one kernel per ray instead (`composite_op`).

use burn::tensor::{Device, Int, Tensor, activation::relu};

use crate::field::march::SampleBatch;
use crate::kernels::gather_op::{RowIndex, gather_rows};
use crate::util::backend::max_buffer_bytes;
use crate::util::tensor::{floats, indices, is_host_memory};

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

/// How a batch's samples are grouped into rays on the device.
#[allow(clippy::large_enum_variant)] // one per upload: its size does not matter
pub enum RayLayout {
    /// The graph's: rays padded to `k` samples each; for each padded slot
    /// the packed sample index, or `num_samples` for padding.
    Padded { k: usize, pad_map: RowIndex },
    /// The fused kernel's (`composite_op`, a GPU): where each ray's samples
    /// start, `[rays + 1]`.
    Runs(Tensor<1, Int>),
}

/// A sample batch uploaded to a device, ready for `composite`.
pub struct BatchTensors {
    pub num_rays: usize,
    pub num_samples: usize,
    pub layout: RayLayout,
    /// Each sample's 8 corner rows, `[s * 8]` (with their transpose when
    /// built for gradients on a GPU: `kernels::gather_op`).
    pub corners: RowIndex,
    pub corner_weights: Tensor<2>,
    pub colour_weights: Tensor<2>,
    pub basis: Tensor<3>,
    pub delta: Tensor<1>,
    pub t: Tensor<1>,
    /// The far background per ray, `[rays, 3]` (`SampleBatch::far`), or
    /// `None` for the constant background. A fit makes it a leaf of its
    /// graph to learn the far map.
    pub far: Option<Tensor<2>>,
}

/// Which renderer a batch is uploaded for.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Renderer {
    Graph,
    Fused,
}

impl BatchTensors {
    /// Uploads a batch. `remap` replaces each corner's grid row (e.g. by a
    /// local row of a training step's parameter subset).
    pub fn new(b: &SampleBatch, remap: Option<&dyn Fn(i32) -> i32>, device: &Device) -> Self {
        Self::upload(b, remap, false, renderer_for(device), device)
    }

    /// As [`new`](Self::new), for a graph that is differentiated: on a GPU
    /// the gathers' index transposes are uploaded too, which the backward
    /// sums the rows' gradients through (`kernels::gather_op`; the fused
    /// kernel's upload carries the corners' transpose either way).
    pub fn for_gradients(b: &SampleBatch, remap: Option<&dyn Fn(i32) -> i32>, device: &Device) -> Self {
        Self::upload(b, remap, true, renderer_for(device), device)
    }

    /// As [`for_gradients`](Self::for_gradients), for the Burn graph on any
    /// device, without the fused kernel (`ray_kernel = "unfused"`): the
    /// oracle of the fused kernel's tests and its fallback on a GPU.
    pub fn for_unfused_gradients(b: &SampleBatch, remap: Option<&dyn Fn(i32) -> i32>, device: &Device) -> Self {
        Self::upload(b, remap, true, Renderer::Graph, device)
    }

    fn upload(
        b: &SampleBatch,
        remap: Option<&dyn Fn(i32) -> i32>,
        gradients: bool,
        renderer: Renderer,
        device: &Device,
    ) -> Self {
        let s = b.num_samples();
        let nb = b.basis.len().checked_div(s).unwrap_or(1);
        let corners: Vec<i32> = match remap {
            Some(f) => b.corner_rows.iter().map(|&r| f(r)).collect(),
            None => b.corner_rows.clone(),
        };
        // The fused kernel's backward always goes through the corners'
        // transpose (so that any upload can be differentiated); the graph's
        // needs it on a GPU only (`RowIndex::new`), for gradients.
        let with_transpose = gradients || renderer == Renderer::Fused;
        let index = |idx: Vec<i32>, rows: usize| match with_transpose {
            true => RowIndex::new(idx, rows, device),
            false => RowIndex::plain(indices(idx, device)),
        };
        // The corner rows' table is the grid (or the step's rows): rows past
        // the largest one read get no gradient from this batch anyway. An
        // upload without a transpose needs no bound.
        let corner_rows = match with_transpose {
            true => corners.iter().copied().max().map_or(0, |m| m as usize + 1),
            false => 0,
        };
        let layout = match renderer {
            Renderer::Graph => {
                let k = b.max_samples_per_ray().max(1);
                let mut pad = vec![s as i32; b.num_rays * k];
                for r in 0..b.num_rays {
                    let (lo, hi) = (b.ray_offsets[r] as usize, b.ray_offsets[r + 1] as usize);
                    for (j, i) in (lo..hi).enumerate() {
                        pad[r * k + j] = i as i32;
                    }
                }
                // The padding slots read row `s`, a constant zero: no gradient.
                RayLayout::Padded { k, pad_map: index(pad, s) }
            }
            Renderer::Fused => RayLayout::Runs(indices(b.ray_offsets.iter().map(|&o| o as i32).collect(), device)),
        };
        Self {
            num_rays: b.num_rays,
            num_samples: s,
            layout,
            corners: index(corners, corner_rows),
            corner_weights: floats(b.corner_weights.clone(), [s * 8, 1], device),
            colour_weights: floats(b.colour_weights.clone(), [s * 8, 1], device),
            basis: floats(b.basis.clone(), [s, 1, nb], device),
            delta: floats(b.delta.clone(), [s], device),
            t: floats(b.t.clone(), [s], device),
            far: (!b.far.is_empty()).then(|| floats(b.far.concat(), [b.num_rays, 3], device)),
        }
    }
}

/// The fused kernel on a GPU (`composite_op`), the graph on the CPU
/// backends (whose training step has its own fused loop, `host_fit`).
fn renderer_for(device: &Device) -> Renderer {
    match cfg!(feature = "wgpu") && !is_host_memory(device) {
        true => Renderer::Fused,
        false => Renderer::Graph,
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
fn to_padded<const D: usize>(packed: Tensor<D>, pad_map: &RowIndex, tail: [usize; D]) -> Tensor<D> {
    let mut zshape = tail;
    zshape[0] = 1;
    let zero = Tensor::zeros(zshape, &packed.device());
    let table = Tensor::cat(vec![packed, zero], 0);
    let rows = table.dims()[0];
    // Gathered as rows of one column or more, then given the caller's rank.
    let columns = table.shape().num_elements() / rows.max(1);
    let padded = gather_rows(table.reshape([rows, columns]), pad_map);
    let mut out_shape = tail;
    out_shape[0] = pad_map.idx.dims()[0];
    padded.reshape(out_shape)
}

/// Equations 1-2 on the packed samples: density and colour by trilinear
/// interpolation of the given rows (colour over the active corners only), then alpha compositing per ray, with
/// the background (the batch's far colours, else `background`) weighted by
/// the remaining transmittance.
pub fn composite(density_rows: Tensor<2>, sh_rows: Tensor<2>, bt: &BatchTensors, background: [f32; 3]) -> Rendered {
    let device = density_rows.device();
    let (r, s) = (bt.num_rays, bt.num_samples);
    let bg = match &bt.far {
        Some(far) => far.clone(),
        None => floats(background.to_vec(), [1, 3], &device),
    };
    if s == 0 {
        let rgb = one_row_per_ray(bg, r);
        return Rendered { rgb, depth: Tensor::zeros([r], &device), opacity: Tensor::zeros([r], &device) };
    }
    match &bt.layout {
        RayLayout::Padded { k, pad_map } => composite_graph(density_rows, sh_rows, bt, bg, *k, pad_map),
        RayLayout::Runs(ray_offsets) => composite_fused(density_rows, sh_rows, bt, bg, ray_offsets),
    }
}

/// The background as `[rays, 3]`: a far map's rows, or the constant
/// background's one row repeated.
fn one_row_per_ray(bg: Tensor<2>, rays: usize) -> Tensor<2> {
    match bg.dims()[0] == rays {
        true => bg,
        false => bg.repeat_dim(0, rays),
    }
}

/// The fused kernel's path (`composite_op`): one `[rays, 5]` output cut
/// into colour, depth and opacity.
fn composite_fused(
    density_rows: Tensor<2>,
    sh_rows: Tensor<2>,
    bt: &BatchTensors,
    bg: Tensor<2>,
    ray_offsets: &Tensor<1, Int>,
) -> Rendered {
    #[cfg(feature = "wgpu")]
    {
        let idx = &bt.corners.idx;
        let transpose = bt.corners.transpose().expect("a fused upload carries the corners' transpose");
        let inputs = crate::kernels::composite_op::FusedInputs {
            corners: idx,
            transpose,
            corner_weights: &bt.corner_weights,
            colour_weights: &bt.colour_weights,
            basis: &bt.basis,
            delta: &bt.delta,
            t: &bt.t,
            ray_offsets,
        };
        let r = bt.num_rays;
        let out = crate::kernels::composite_op::composite_fused(density_rows, sh_rows, bg, &inputs);
        Rendered {
            rgb: out.clone().narrow(1, 0, 3),
            depth: out.clone().narrow(1, 3, 1).reshape([r]),
            opacity: out.narrow(1, 4, 1).reshape([r]),
        }
    }
    #[cfg(not(feature = "wgpu"))]
    {
        let _ = (density_rows, sh_rows, bt, bg, ray_offsets);
        unreachable!("the fused layout is chosen on a GPU device only")
    }
}

/// The Burn graph's path: per-sample tensors, padded per ray.
fn composite_graph(
    density_rows: Tensor<2>,
    sh_rows: Tensor<2>,
    bt: &BatchTensors,
    bg: Tensor<2>,
    k: usize,
    pad_map: &RowIndex,
) -> Rendered {
    let (r, s) = (bt.num_rays, bt.num_samples);
    let bg = one_row_per_ray(bg, r);
    let nb = sh_rows.dims()[1] / 3;
    let sigma = relu(interpolate_corners(density_rows, &bt.corners, bt.corner_weights.clone()).reshape([s]));
    let coeffs = interpolate_corners(sh_rows, &bt.corners, bt.colour_weights.clone()).reshape([s, 3, nb]);
    let colour = relu((coeffs * bt.basis.clone()).sum_dim(2).reshape([s, 3]) + 0.5);

    let tau = to_padded(sigma * bt.delta.clone(), pad_map, [s]).reshape([r, k]);
    let optical = tau.clone().cumsum(1);
    let transmittance = (tau.clone() - optical.clone()).exp(); // T_i = exp(-sum_{j<i} tau_j)
    let weights = transmittance * (-(tau.neg().exp()) + 1.0);
    let final_t = optical.narrow(1, k - 1, 1).neg().exp(); // [r, 1]

    let colour = to_padded(colour, pad_map, [s, 3]).reshape([r, k, 3]);
    let rgb = (weights.clone().reshape([r, k, 1]) * colour).sum_dim(1).reshape([r, 3]) + final_t.clone() * bg;
    let t = to_padded(bt.t.clone(), pad_map, [s]).reshape([r, k]);
    let depth = (weights * t).sum_dim(1).reshape([r]);
    let opacity = (-final_t + 1.0).reshape([r]);
    Rendered { rgb, depth, opacity }
}

/// The fused kernel (`composite_op`) against the Burn graph and `host_fit`, on
/// every backend the test command runs (`cargo test --lib graph_oracle`):
/// the kernel runs on wgpu; on the CPU backends both sides are the graph.
#[cfg(test)]
#[allow(clippy::print_stdout)] // the measured errors, shown with --nocapture
mod graph_oracle {
    use glam::Vec3;

    use super::{BatchTensors, RayLayout, Rendered, composite};
    use crate::field::grid::{GridGeometry, RadianceGrid};
    use crate::field::{host_fit, march};
    use crate::scene::sh;
    use crate::test_support::{device, params, sparse_degree2_grid, test_camera};
    use crate::util::tensor::{floats, is_host_memory, to_vec};

    /// Colour, depth and opacity, and the gradients of density, SH and a
    /// far background per ray, on rays that hit, graze and miss, over
    /// negative and positive densities and colours clipped at zero, to 1e-5
    /// of each one's largest value. Both sides do the same arithmetic (the
    /// kernel follows the graph's and `host_fit`'s order: coefficients
    /// interpolated before the basis, transmittance as the exponential of
    /// the optical depth so far) but sum in other orders, and a GPU may
    /// fuse multiply-adds: measured on lavapipe, 4e-8 of the largest value.
    /// A wrong term (a missing ReLU mask, the depth or opacity left out of
    /// the density gradient) is off by whole percents.
    #[test]
    fn the_fused_kernel_matches_the_graph() {
        let (grid, dens, shd, rays) = sparse_degree2_grid(3.5);
        let (n, nb, dev) = (dens.len(), sh::num_basis(2), device());
        let mut batch = march::generate_samples(&grid, &rays, &params(0.25));
        batch.far = (0..rays.len()).map(|i| [0.1 * (i % 7) as f32, 0.5, 1.0 - 0.02 * i as f32]).collect();
        let longest = batch.max_samples_per_ray();
        assert!(batch.num_samples() > 200 && longest > 10, "{} samples, {longest} on one ray", batch.num_samples());
        let weights: Vec<f32> = (0..rays.len() * 5).map(|i| ((i * 37) % 11) as f32 / 11.0 - 0.4).collect();
        let run = |mut bt: BatchTensors| {
            let ld = floats(dens.clone(), [n, 1], &dev).autodiff().require_grad();
            let ls = floats(shd.clone(), [n, 3 * nb], &dev).autodiff().require_grad();
            let far_leaf = bt.far.take().expect("the batch has a far background").autodiff().require_grad();
            bt.far = Some(far_leaf.clone());
            let out = composite(ld.clone(), ls.clone(), &bt, [0.0; 3]);
            let all = outputs(&out);
            let loss = (all.clone() * floats(weights.clone(), [rays.len(), 5], &dev)).sum();
            let grads = loss.backward();
            let grad = |t: &burn::tensor::Tensor<2>| to_vec(t.grad(&grads).expect("a gradient"));
            (to_vec(all), grad(&ld), grad(&ls), grad(&far_leaf))
        };
        let fused = BatchTensors::for_gradients(&batch, None, &dev);
        let on_gpu = !is_host_memory(&dev);
        assert_eq!(matches!(fused.layout, RayLayout::Runs(_)), on_gpu, "the kernel is the GPU's path");
        let (ours, theirs) = (run(fused), run(BatchTensors::for_unfused_gradients(&batch, None, &dev)));
        for (name, a, b) in [
            ("outputs", &ours.0, &theirs.0),
            ("density gradient", &ours.1, &theirs.1),
            ("SH gradient", &ours.2, &theirs.2),
            ("far gradient", &ours.3, &theirs.3),
        ] {
            let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let err = a.iter().zip(b).fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            println!("{name}: max |fused - graph| = {err:.2e} of {scale:.2e}");
            assert!(scale > 0.0 && b.iter().filter(|v| **v != 0.0).count() > 10, "{name}: all zero");
            assert!(err <= 1e-5 * scale, "{name}: {err:.2e} of {scale:.2e}");
        }
        // A render-only upload gives the same forward.
        let plain = BatchTensors::new(&batch, None, &dev);
        let forward = to_vec(outputs(&composite(
            floats(dens.clone(), [n, 1], &dev),
            floats(shd.clone(), [n, 3 * nb], &dev),
            &plain,
            [0.0; 3],
        )));
        assert!(forward == ours.0, "the render-only forward is the differentiated one's");
    }

    /// The renderer against the plain-Rust kernel (`host_fit`) on long
    /// rays: a dense grid of SH degree 2, density 0.1 everywhere, seen by a
    /// whole camera, the gradients of an MSE. The oracle above has a few
    /// hundred samples and can miss what breaks only at scale: a kernel
    /// whose loops were ordered corner-outer, basis-inner passed it and the
    /// training tests, yet on lavapipe its gradients on such a grid were
    /// off by 1.6e-2 of a largest value of 2.4e-5 and it trained a scene to
    /// 16.6 dB instead of 24.7. Tolerance: 1e-3 of the largest value and a
    /// relative L2 error of 1e-3. What limits agreement is f32's
    /// `1 - exp(-tau)` at this density's tau of about 1e-3 (a rounding of
    /// exp is a relative error of some 1e-4 in the sample's alpha; a GPU's
    /// exp is not correctly rounded): measured on lavapipe at 64³ (4096
    /// rays, 860k samples, 291 on the longest) 8.6e-11 of 3.3e-6 and a
    /// relative L2 of 1.7e-5 (density), 9.0e-5 (SH); flex's graph at 64³
    /// 4.8e-7 and 5.4e-8. On a GPU the grid is 64³; the CPU backends run
    /// their graph on a 32³ one (at 64³ its `[8 samples, 27]` tensors take
    /// 740 MB).
    #[test]
    fn the_renderer_matches_host_fit_on_long_rays() {
        let dev = device();
        let on_gpu = !is_host_memory(&dev);
        let (res, pixels, min_longest) = if on_gpu { (64, 64, 150) } else { (32, 32, 75) };
        let geo = GridGeometry::new([res; 3], Vec3::splat(-1.0), Vec3::splat(1.0));
        let (n, nb) = (geo.num_points(), sh::num_basis(2));
        let dens = vec![0.1f32; n];
        let shd: Vec<f32> = (0..n * 3 * nb).map(|i| 0.5 * (((i * 104_729) % 17) as f32 / 17.0 - 0.3)).collect();
        let grid = RadianceGrid::from_rows(geo, 2, (0..n as u32).collect(), dens.clone(), shd.clone(), &dev);
        let rays = test_camera(pixels).rays(None);
        let batch = march::generate_samples(&grid, &rays, &params(0.25));
        let longest = batch.max_samples_per_ray();
        println!("{} rays, {} samples, {longest} on the longest", rays.len(), batch.num_samples());
        assert!(longest >= min_longest, "{longest} samples on the longest ray");
        let (target, bg) = (vec![0.3f32; rays.len() * 3], [0.2, 0.5, 0.9]);
        let host =
            host_fit::mse_gradient(&dens, &shd, nb, &batch, &batch.corner_rows, &target, bg, &mut Default::default());

        let bt = BatchTensors::for_gradients(&batch, None, &dev);
        assert_eq!(matches!(bt.layout, RayLayout::Runs(_)), on_gpu, "the kernel is the GPU's path");
        let ld = floats(dens, [n, 1], &dev).autodiff().require_grad();
        let ls = floats(shd, [n, 3 * nb], &dev).autodiff().require_grad();
        let diff = composite(ld.clone(), ls.clone(), &bt, bg).rgb - floats(target, [rays.len(), 3], &dev);
        let grads = (diff.clone() * diff).mean().backward();
        for (name, host, ours) in [
            ("density", host.density, to_vec(ld.grad(&grads).expect("a gradient"))),
            ("sh", host.sh, to_vec(ls.grad(&grads).expect("a gradient"))),
        ] {
            let scale = host.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let err = host.iter().zip(&ours).fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
            let l2 = |v: &mut dyn Iterator<Item = f32>| v.map(|x| (x as f64).powi(2)).sum::<f64>().sqrt();
            let rel_l2 = l2(&mut host.iter().zip(&ours).map(|(a, b)| a - b)) / l2(&mut host.iter().copied());
            println!("{name}: max |renderer - host_fit| = {err:.2e} of {scale:.2e}, relative L2 {rel_l2:.2e}");
            assert!(scale > 0.0 && host.iter().filter(|g| **g != 0.0).count() > 1000, "{name}: no gradient");
            assert!(
                err <= 1e-3 * scale && rel_l2 <= 1e-4,
                "{name}: {err:.2e} of {scale:.2e}, relative L2 {rel_l2:.2e}"
            );
        }
    }

    /// Colour, depth and opacity side by side, `[rays, 5]`.
    fn outputs(r: &Rendered) -> burn::tensor::Tensor<2> {
        let rays = r.depth.dims()[0];
        burn::tensor::Tensor::cat(
            vec![r.rgb.clone(), r.depth.clone().reshape([rays, 1]), r.opacity.clone().reshape([rays, 1])],
            1,
        )
    }
}
