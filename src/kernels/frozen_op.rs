//! The stylization's colour pass (`frozen::render_colour`) as GPU kernels,
//! forward and backward: the GPU path of that function (its Burn graph
//! stays the oracle, the CPU backends' path and the fallback).
//!
//! Why: with the density frozen, a ray's colour is `sum_i w_i max(C0 c_i +
//! 0.5, 0)`, `c_i` the 8 corner rows of sample `i` interpolated. The graph
//! gathers every sample's corners as an `[8 s, 3]` tensor, weights it,
//! reshapes and sums it, and its backward writes as many again (lego's
//! training view 0: 380,792 samples, 36.6 MB a gather; on lavapipe its
//! re-render with the gradient took 0.367 s, 0.150 s here:
//! `examples/colour_costs.rs`, docs/performance.md). Here the forward is
//! one thread per (ray, channel) reading each sample's corners from the
//! rows as it goes; the backward is one thread per (sample, channel) for
//! the gradient before the ReLU (`[s, 3]`, the only per-sample tensor),
//! then one thread per (row, channel) summing its entries through the
//! corners' transpose (`kernels::gather_op::RowIndex`), each times its colour
//! weight: no atomics, the same sums on every run. `frozen`'s
//! `graph_oracle` test holds it to the graph.

use burn::tensor::{Int, Tensor};

use crate::kernels::gather_op::RowIndex;

/// `[rays, 3]`: each ray's colour from degree-0 SH rows `sh` (`[rows, 3]`)
/// without its background, differentiable in `sh`. `corners` must carry
/// its transpose where `sh` is tracked (`RowIndex::transpose_parts`);
/// `ray_of_sample` (`[s]`) names each sample's ray and `ray_starts`
/// (`[rays + 1]`) where each ray's samples start. GPU devices only.
#[cfg(feature = "wgpu")]
pub fn colour_fused(
    sh: Tensor<2>,
    corners: &RowIndex,
    colour_weights: &Tensor<2>,
    weight: &Tensor<2>,
    ray_of_sample: &Tensor<1, Int>,
    ray_starts: Tensor<1, Int>,
) -> Tensor<2> {
    let device = sh.device();
    let empty = || Tensor::<1, Int>::zeros([0], &device);
    let (order, offsets, touched) = corners.transpose_parts().unwrap_or_else(|| (empty(), empty(), empty()));
    let out = <burn::backend::Dispatch as FrozenColourBackend>::frozen_colour(
        sh.into_dispatch(),
        corners.idx.clone().into_dispatch(),
        order.into_dispatch(),
        offsets.into_dispatch(),
        touched.into_dispatch(),
        colour_weights.clone().into_dispatch(),
        weight.clone().into_dispatch(),
        ray_of_sample.clone().into_dispatch(),
        ray_starts.into_dispatch(),
    );
    Tensor::from_dispatch(out)
}

#[cfg(feature = "wgpu")]
pub use cube_op::FrozenColourBackend;

/// The operation on the cubecl backend and autodiff over it.
#[cfg(feature = "wgpu")]
mod cube_op {
    use burn::backend::Cube;
    use burn::backend::autodiff::Autodiff;
    use burn::backend::autodiff::checkpoint::base::Checkpointer;
    use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
    use burn::backend::autodiff::grads::Gradients;
    use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
    use burn::backend::cubecl::dtype_to_storage_type as storage;
    use burn::backend::tensor::{FloatTensor, IntTensor};
    use burn::backend::{AutodiffBackend, Backend, Shape, TensorMetadata, backend_extension};
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;
    use burn_cubecl::kernel::into_contiguous;
    use burn_cubecl::ops::numeric::empty_device_dtype;
    use burn_cubecl::tensor::CubeTensor;

    use crate::kernels::gather_op::{one_per_value, sum_weighted_by_rows};
    use crate::scene::sh::C0;

    /// The fused frozen-density colour pass (module docs).
    #[backend_extension(Cube, Autodiff)]
    pub trait FrozenColourBackend: Backend {
        /// `[rays, 3]`, the rays' colours without their background. `order`,
        /// `offsets` and `touched` are `corners`' transpose, kept for the
        /// backward (`touched` empty for a full one).
        #[allow(clippy::too_many_arguments)]
        fn frozen_colour(
            sh: FloatTensor<Self>,
            corners: IntTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            touched: IntTensor<Self>,
            colour_weights: FloatTensor<Self>,
            weight: FloatTensor<Self>,
            ray_of_sample: IntTensor<Self>,
            ray_starts: IntTensor<Self>,
        ) -> FloatTensor<Self>;

        /// The backward's first half: `[s, 3]`, the gradient of each
        /// sample's interpolated coefficients given the colours' gradient
        /// `grad` (`[rays, 3]`).
        fn frozen_sample_grads(
            sh: FloatTensor<Self>,
            corners: IntTensor<Self>,
            colour_weights: FloatTensor<Self>,
            weight: FloatTensor<Self>,
            ray_of_sample: IntTensor<Self>,
            grad: FloatTensor<Self>,
        ) -> FloatTensor<Self>;

        /// The backward's second half: the samples' gradients summed into
        /// `rows` rows through the corners' transpose, each entry times its
        /// colour weight, `[rows, 3]`.
        fn frozen_row_grads(
            sample_grads: FloatTensor<Self>,
            colour_weights: FloatTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            touched: IntTensor<Self>,
            rows: usize,
        ) -> FloatTensor<Self>;
    }

    /// A sample's channel `ch` before its ReLU: its corners' coefficients
    /// interpolated in corner order (the graph's sum over the corner axis),
    /// times C0, plus 0.5.
    #[cube]
    fn sample_value<F: Float, I: Numeric>(
        sh: &Tensor<F>,
        corners: &Tensor<I>,
        colour_weights: &Tensor<F>,
        i: usize,
        ch: usize,
    ) -> F {
        let mut value = F::new(0.0);
        for c in 0..8usize {
            let row = u32::cast_from(corners[i * 8 + c]) as usize;
            value += sh[row * 3 + ch] * colour_weights[i * 8 + c];
        }
        value * F::new(C0) + F::new(0.5)
    }

    /// One thread per (ray, channel): the ray's samples summed front to back.
    #[cube(launch)]
    fn forward_kernel<F: Float, I: Numeric>(
        sh: &Tensor<F>,
        corners: &Tensor<I>,
        colour_weights: &Tensor<F>,
        weight: &Tensor<F>,
        ray_starts: &Tensor<I>,
        out: &mut Tensor<F>,
        #[define(F, I)] _dtypes: [ElemType; 2],
    ) {
        let pos = ABSOLUTE_POS;
        if pos >= out.len() {
            terminate!();
        }
        let (ray, ch) = (pos / 3, pos % 3);
        let lo = u32::cast_from(ray_starts[ray]) as usize;
        let hi = u32::cast_from(ray_starts[ray + 1]) as usize;
        let mut sum = F::new(0.0);
        for i in lo..hi {
            let value = sample_value::<F, I>(sh, corners, colour_weights, i, ch);
            // ReLU as Burn's: NaN stays NaN (a diverged field must show).
            let mut colour = value;
            if value <= F::new(0.0) {
                colour = F::new(0.0);
            }
            sum += colour * weight[i];
        }
        out[pos] = sum;
    }

    /// One thread per (sample, channel): the ray's gradient times the
    /// sample's weight and C0, zero where its ReLU was off.
    #[cube(launch)]
    fn sample_grads_kernel<F: Float, I: Numeric>(
        sh: &Tensor<F>,
        corners: &Tensor<I>,
        colour_weights: &Tensor<F>,
        weight: &Tensor<F>,
        ray_of_sample: &Tensor<I>,
        grad: &Tensor<F>,
        out: &mut Tensor<F>,
        #[define(F, I)] _dtypes: [ElemType; 2],
    ) {
        let pos = ABSOLUTE_POS;
        if pos >= out.len() {
            terminate!();
        }
        let (i, ch) = (pos / 3, pos % 3);
        let value = sample_value::<F, I>(sh, corners, colour_weights, i, ch);
        let ray = u32::cast_from(ray_of_sample[i]) as usize;
        let mut g = grad[ray * 3 + ch] * weight[i] * F::new(C0);
        if value <= F::new(0.0) {
            g = F::new(0.0);
        }
        out[pos] = g;
    }

    fn empty_like(like: &CubeTensor, shape: Shape) -> CubeTensor {
        empty_device_dtype(like.client.clone(), like.device.clone(), shape, like.dtype)
    }

    impl FrozenColourBackend for Cube {
        fn frozen_colour(
            sh: FloatTensor<Self>,
            corners: IntTensor<Self>,
            _order: IntTensor<Self>,
            _offsets: IntTensor<Self>,
            _touched: IntTensor<Self>,
            colour_weights: FloatTensor<Self>,
            weight: FloatTensor<Self>,
            _ray_of_sample: IntTensor<Self>,
            ray_starts: IntTensor<Self>,
        ) -> FloatTensor<Self> {
            let (sh, corners, colour_weights) =
                (into_contiguous(sh), into_contiguous(corners), into_contiguous(colour_weights));
            let (weight, ray_starts) = (into_contiguous(weight), into_contiguous(ray_starts));
            let rays = ray_starts.shape()[0].saturating_sub(1);
            let out = empty_like(&sh, Shape::new([rays, 3]));
            if rays == 0 {
                return out;
            }
            let (cube_count, cube_dim) = one_per_value(&out.client, rays * 3);
            let dtypes = [storage(sh.dtype), storage(corners.dtype)];
            forward_kernel::launch(
                &out.client,
                cube_count,
                cube_dim,
                sh.into_tensor_arg(),
                corners.into_tensor_arg(),
                colour_weights.into_tensor_arg(),
                weight.into_tensor_arg(),
                ray_starts.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                dtypes,
            );
            out
        }

        fn frozen_sample_grads(
            sh: FloatTensor<Self>,
            corners: IntTensor<Self>,
            colour_weights: FloatTensor<Self>,
            weight: FloatTensor<Self>,
            ray_of_sample: IntTensor<Self>,
            grad: FloatTensor<Self>,
        ) -> FloatTensor<Self> {
            let (sh, corners, colour_weights) =
                (into_contiguous(sh), into_contiguous(corners), into_contiguous(colour_weights));
            let (weight, ray_of_sample, grad) =
                (into_contiguous(weight), into_contiguous(ray_of_sample), into_contiguous(grad));
            let samples = ray_of_sample.shape()[0];
            let out = empty_like(&sh, Shape::new([samples, 3]));
            if samples == 0 {
                return out;
            }
            let (cube_count, cube_dim) = one_per_value(&out.client, samples * 3);
            let dtypes = [storage(sh.dtype), storage(corners.dtype)];
            sample_grads_kernel::launch(
                &out.client,
                cube_count,
                cube_dim,
                sh.into_tensor_arg(),
                corners.into_tensor_arg(),
                colour_weights.into_tensor_arg(),
                weight.into_tensor_arg(),
                ray_of_sample.into_tensor_arg(),
                grad.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                dtypes,
            );
            out
        }

        fn frozen_row_grads(
            sample_grads: FloatTensor<Self>,
            colour_weights: FloatTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            touched: IntTensor<Self>,
            rows: usize,
        ) -> FloatTensor<Self> {
            // Entry `e` is sample `e / 8`'s corner `e % 8`.
            sum_weighted_by_rows(sample_grads, Some((colour_weights, 8)), order, offsets, touched, rows)
        }
    }

    /// What the backward needs: the forward's inputs.
    #[derive(Debug, Clone)]
    struct State<B: Backend> {
        sh: FloatTensor<B>,
        corners: IntTensor<B>,
        order: IntTensor<B>,
        offsets: IntTensor<B>,
        touched: IntTensor<B>,
        colour_weights: FloatTensor<B>,
        weight: FloatTensor<B>,
        ray_of_sample: IntTensor<B>,
    }

    /// The fused colour pass's backward step.
    #[derive(Debug)]
    struct FrozenColourBackward;

    impl<B: FrozenColourBackend> Backward<B, 1> for FrozenColourBackward {
        type State = State<B>;

        fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
            let [node_sh] = ops.parents;
            let grad = grads.consume::<B>(&ops.node);
            let Some(node) = node_sh else { return };
            let x = ops.state;
            let rows = x.sh.shape()[0];
            let per_sample =
                B::frozen_sample_grads(x.sh, x.corners, x.colour_weights.clone(), x.weight, x.ray_of_sample, grad);
            let g = B::frozen_row_grads(per_sample, x.colour_weights, x.order, x.offsets, x.touched, rows);
            grads.register::<B>(node.id, g);
        }
    }

    impl<B: FrozenColourBackend, C: CheckpointStrategy> FrozenColourBackend for Autodiff<B, C> {
        fn frozen_colour(
            sh: FloatTensor<Self>,
            corners: IntTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            touched: IntTensor<Self>,
            colour_weights: FloatTensor<Self>,
            weight: FloatTensor<Self>,
            ray_of_sample: IntTensor<Self>,
            ray_starts: IntTensor<Self>,
        ) -> FloatTensor<Self> {
            let (colour_weights, weight) = (colour_weights.into_primitive(), weight.into_primitive());
            match FrozenColourBackward.prepare::<C>([sh.node()]).compute_bound().stateful() {
                OpsKind::Tracked(prep) => {
                    debug_assert!(
                        order.shape()[0] > 0 || corners.shape()[0] == 0,
                        "a tracked colour pass needs the corners' transpose"
                    );
                    let sh = sh.into_primitive();
                    let out = B::frozen_colour(
                        sh.clone(),
                        corners.clone(),
                        order.clone(),
                        offsets.clone(),
                        touched.clone(),
                        colour_weights.clone(),
                        weight.clone(),
                        ray_of_sample.clone(),
                        ray_starts,
                    );
                    let state = State { sh, corners, order, offsets, touched, colour_weights, weight, ray_of_sample };
                    prep.finish(state, out)
                }
                OpsKind::UnTracked(prep) => prep.finish(B::frozen_colour(
                    sh.into_primitive(),
                    corners,
                    order,
                    offsets,
                    touched,
                    colour_weights,
                    weight,
                    ray_of_sample,
                    ray_starts,
                )),
            }
        }

        fn frozen_sample_grads(
            sh: FloatTensor<Self>,
            corners: IntTensor<Self>,
            colour_weights: FloatTensor<Self>,
            weight: FloatTensor<Self>,
            ray_of_sample: IntTensor<Self>,
            grad: FloatTensor<Self>,
        ) -> FloatTensor<Self> {
            // Only ever called inside a backward, on the inner backend.
            <Self as AutodiffBackend>::from_inner(B::frozen_sample_grads(
                sh.into_primitive(),
                corners,
                colour_weights.into_primitive(),
                weight.into_primitive(),
                ray_of_sample,
                grad.into_primitive(),
            ))
        }

        fn frozen_row_grads(
            sample_grads: FloatTensor<Self>,
            colour_weights: FloatTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            touched: IntTensor<Self>,
            rows: usize,
        ) -> FloatTensor<Self> {
            <Self as AutodiffBackend>::from_inner(B::frozen_row_grads(
                sample_grads.into_primitive(),
                colour_weights.into_primitive(),
                order,
                offsets,
                touched,
                rows,
            ))
        }
    }
}
