//! Equations 1-2 as one GPU kernel per ray, forward and backward: the
//! GPU path of `composite::composite` (the Burn graph there stays the
//! oracle, and the path of the CPU backends' graph code).
//!
//! Why: the graph materialises every sample's 8 corner rows (`[8 s, 27]`
//! for SH degree 2), pads the rays to the longest, and launches about a
//! hundred kernels a step; on an H200 a lego step at 256³ spent 44 of its
//! 55 ms there. Here one thread walks a ray's samples front to back,
//! reading each sample's 8 corner rows from the grid rows as it goes (as
//! `field::host_fit` does on the CPU), and writes the ray's colour, depth
//! and opacity. The backward walks the ray twice - front to back for each
//! sample's weight and transmittance, back to front for its gradient - and
//! writes 4 values a sample: the gradient
//! of its interpolated density and of its 3 colour channels before their
//! ReLUs. The rows' gradients are then summed by one thread per (row,
//! column) through the corner index's transpose (`kernels::gather_op`'s
//! `RowIndex`), which multiplies by the trilinear weights and the SH basis
//! on the fly: no atomics (floats have them only on some adapters), the
//! same sums on every run, and nothing of size `[8 s, 27]` allocated.
//!
//! The gradient of the density, with `tau_i = sigma_i delta_i`, `w_i =
//! T_i (1 - e^-tau_i)` and per-sample value `v_i = g . c_i + g_depth t_i`:
//! `dL/dtau_i = T_{i+1} v_i - (sum_{j>i} w_j v_j + T_N (g . bg -
//! g_opacity))`, the bracket summed from the back of the ray (as the graph's
//! autodiff of a cumulative sum does; the ray's total less a running prefix
//! would lose digits where both are large).

use burn::tensor::{Int, Tensor};

/// The fused kernel's inputs on the device: the batch's samples as
/// `composite::BatchTensors` uploads them, and the rays' sample ranges.
pub struct FusedInputs<'a> {
    pub corners: &'a Tensor<1, Int>,
    /// `corners`' transpose (`kernels::gather_op::transpose_of`), which the
    /// backward sums the rows' gradients through.
    pub transpose: (&'a Tensor<1, Int>, &'a Tensor<1, Int>),
    pub corner_weights: &'a Tensor<2>,
    pub colour_weights: &'a Tensor<2>,
    pub basis: &'a Tensor<3>,
    pub delta: &'a Tensor<1>,
    pub t: &'a Tensor<1>,
    /// Where each ray's samples start, `[rays + 1]`.
    pub ray_offsets: &'a Tensor<1, Int>,
}

/// Colour, depth and opacity of every ray, `[rays, 5]`, differentiable in
/// `density_rows` `[rows, 1]`, `sh_rows` `[rows, 3 nb]` and `background`
/// (`[rays, 3]`; a constant `[1, 3]` is not differentiated). GPU devices
/// only (the backend extension is `Cube`'s).
#[cfg(feature = "wgpu")]
pub fn composite_fused(
    density_rows: Tensor<2>,
    sh_rows: Tensor<2>,
    background: Tensor<2>,
    x: &FusedInputs,
) -> Tensor<2> {
    let out = <burn::backend::Dispatch as CompositeBackend>::composite_rays(
        density_rows.into_dispatch(),
        sh_rows.into_dispatch(),
        background.into_dispatch(),
        x.corners.clone().into_dispatch(),
        x.transpose.0.clone().into_dispatch(),
        x.transpose.1.clone().into_dispatch(),
        x.corner_weights.clone().into_dispatch(),
        x.colour_weights.clone().into_dispatch(),
        x.basis.clone().into_dispatch(),
        x.delta.clone().into_dispatch(),
        x.t.clone().into_dispatch(),
        x.ray_offsets.clone().into_dispatch(),
    );
    Tensor::from_dispatch(out)
}

#[cfg(feature = "wgpu")]
pub use cube_op::CompositeBackend;

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

    use crate::kernels::gather_op::one_per_value;

    /// The fused compositing of a packed sample batch (module docs).
    #[backend_extension(Cube, Autodiff)]
    pub trait CompositeBackend: Backend {
        /// `[rays, 5]`: colour, depth, opacity. `order` and `offsets` are
        /// `corners`' transpose, kept for the backward.
        #[allow(clippy::too_many_arguments)]
        fn composite_rays(
            density: FloatTensor<Self>,
            sh: FloatTensor<Self>,
            background: FloatTensor<Self>,
            corners: IntTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            corner_weights: FloatTensor<Self>,
            colour_weights: FloatTensor<Self>,
            basis: FloatTensor<Self>,
            delta: FloatTensor<Self>,
            t: FloatTensor<Self>,
            ray_offsets: IntTensor<Self>,
        ) -> FloatTensor<Self>;

        /// The backward's first half: for each sample, `[s, 4]`, the
        /// gradient of its interpolated density and of its 3 colour
        /// channels before their ReLUs, given the output's gradient `grad`
        /// `[rays, 5]`.
        #[allow(clippy::too_many_arguments)]
        fn composite_sample_grads(
            density: FloatTensor<Self>,
            sh: FloatTensor<Self>,
            background: FloatTensor<Self>,
            corners: IntTensor<Self>,
            corner_weights: FloatTensor<Self>,
            colour_weights: FloatTensor<Self>,
            basis: FloatTensor<Self>,
            delta: FloatTensor<Self>,
            t: FloatTensor<Self>,
            ray_offsets: IntTensor<Self>,
            grad: FloatTensor<Self>,
        ) -> FloatTensor<Self>;

        /// The backward's second half: the per-sample gradients' columns
        /// `first..first + channels` summed into `rows` rows through the
        /// corners' transpose, each entry times its corner weight and (with
        /// `with_basis`) each channel spread over the sample's SH basis:
        /// `[rows, channels]` or `[rows, channels nb]`.
        #[allow(clippy::too_many_arguments)]
        fn composite_row_grads(
            sample_grads: FloatTensor<Self>,
            weights: FloatTensor<Self>,
            basis: FloatTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            rows: usize,
            first: usize,
            channels: usize,
            with_basis: bool,
        ) -> FloatTensor<Self>;

        /// The background's gradient, `[rays, 3]`: the colour's gradient
        /// times the final transmittance (1 - the output's opacity).
        fn composite_background_grads(grad: FloatTensor<Self>, out: FloatTensor<Self>) -> FloatTensor<Self>;
    }

    /// `max(x, 0)` as Burn's ReLU has it: NaN stays NaN (a diverged field
    /// must show in the loss; WGSL's `max` may drop it).
    #[cube]
    fn relu<F: Float>(x: F) -> F {
        if x <= F::new(0.0) { F::new(0.0) } else { x }
    }

    /// ReLU's backward as Burn's: `grad`, except zero where the input is
    /// not positive (NaN passes).
    #[cube]
    fn masked<F: Float>(input: F, grad: F) -> F {
        if input <= F::new(0.0) { F::new(0.0) } else { grad }
    }

    /// A sample's interpolated density before its ReLU.
    #[cube]
    fn sample_sigma<F: Float, I: Numeric>(
        density: &Tensor<F>,
        corners: &Tensor<I>,
        weights: &Tensor<F>,
        i: usize,
    ) -> F {
        let mut sigma = F::new(0.0);
        for c in 0..8usize {
            let row = u32::cast_from(corners[i * 8 + c]) as usize;
            sigma += weights[i * 8 + c] * density[row];
        }
        sigma
    }

    /// A sample's colour channel `ch` before its ReLU: each SH coefficient
    /// interpolated from the corners, dotted with the sample's basis, plus
    /// 0.5 (`host_render::sample_colour`'s order of operations).
    #[cube]
    fn sample_colour<F: Float, I: Numeric>(
        sh: &Tensor<F>,
        corners: &Tensor<I>,
        weights: &Tensor<F>,
        basis: &Tensor<F>,
        i: usize,
        ch: usize,
        nb: usize,
    ) -> F {
        let mut value = F::new(0.0);
        for b in 0..nb {
            let mut coefficient = F::new(0.0);
            for c in 0..8usize {
                let row = u32::cast_from(corners[i * 8 + c]) as usize;
                coefficient += weights[i * 8 + c] * sh[row * 3 * nb + ch * nb + b];
            }
            value += coefficient * basis[i * nb + b];
        }
        value + F::new(0.5)
    }

    /// One thread per ray: its samples composited front to back.
    #[cube(launch)]
    fn forward_kernel<F: Float, I: Numeric>(
        density: &Tensor<F>,
        sh: &Tensor<F>,
        background: &Tensor<F>,
        corners: &Tensor<I>,
        corner_weights: &Tensor<F>,
        colour_weights: &Tensor<F>,
        basis: &Tensor<F>,
        delta: &Tensor<F>,
        t: &Tensor<F>,
        ray_offsets: &Tensor<I>,
        out: &mut Tensor<F>,
        nb: u32,
        #[define(F, I)] _dtypes: [ElemType; 2],
    ) {
        let ray = ABSOLUTE_POS;
        if ray + 1 >= ray_offsets.len() {
            terminate!();
        }
        let nb = nb as usize;
        let zero = F::new(0.0);
        let lo = u32::cast_from(ray_offsets[ray]) as usize;
        let hi = u32::cast_from(ray_offsets[ray + 1]) as usize;
        // Transmittance as exp(-optical depth so far), as the host's kernels
        // and the graph compute it.
        let mut optical = zero;
        let mut red = zero;
        let mut green = zero;
        let mut blue = zero;
        let mut depth = zero;
        for i in lo..hi {
            let tau = relu::<F>(sample_sigma::<F, I>(density, corners, corner_weights, i)) * delta[i];
            let w = (zero - optical).exp() * (F::new(1.0) - (zero - tau).exp());
            optical += tau;
            red += w * relu::<F>(sample_colour::<F, I>(sh, corners, colour_weights, basis, i, 0, nb));
            green += w * relu::<F>(sample_colour::<F, I>(sh, corners, colour_weights, basis, i, 1, nb));
            blue += w * relu::<F>(sample_colour::<F, I>(sh, corners, colour_weights, basis, i, 2, nb));
            depth += w * t[i];
        }
        let transmittance = (zero - optical).exp();
        // A constant background is one row for every ray.
        let mut bg = ray * 3;
        if background.len() <= 3 {
            bg = 0;
        }
        out[ray * 5] = red + transmittance * background[bg];
        out[ray * 5 + 1] = green + transmittance * background[bg + 1];
        out[ray * 5 + 2] = blue + transmittance * background[bg + 2];
        out[ray * 5 + 3] = depth;
        out[ray * 5 + 4] = F::new(1.0) - transmittance;
    }

    /// One thread per ray: the ray walked front to back, then back to front
    /// for each sample's gradients (module docs).
    #[cube(launch)]
    fn sample_grads_kernel<F: Float, I: Numeric>(
        density: &Tensor<F>,
        sh: &Tensor<F>,
        background: &Tensor<F>,
        corners: &Tensor<I>,
        corner_weights: &Tensor<F>,
        colour_weights: &Tensor<F>,
        basis: &Tensor<F>,
        delta: &Tensor<F>,
        t: &Tensor<F>,
        ray_offsets: &Tensor<I>,
        grad: &Tensor<F>,
        out: &mut Tensor<F>,
        nb: u32,
        #[define(F, I)] _dtypes: [ElemType; 2],
    ) {
        let ray = ABSOLUTE_POS;
        if ray + 1 >= ray_offsets.len() {
            terminate!();
        }
        let nb = nb as usize;
        let (zero, one) = (F::new(0.0), F::new(1.0));
        let lo = u32::cast_from(ray_offsets[ray]) as usize;
        let hi = u32::cast_from(ray_offsets[ray + 1]) as usize;
        let g0 = grad[ray * 5];
        let g1 = grad[ray * 5 + 1];
        let g2 = grad[ray * 5 + 2];
        let g_depth = grad[ray * 5 + 3];
        let g_opacity = grad[ray * 5 + 4];
        // Front to back: each sample's weight, value and the transmittance
        // behind it, kept in its output slots for the walk back.
        let mut optical = zero;
        for i in lo..hi {
            let tau = relu::<F>(sample_sigma::<F, I>(density, corners, corner_weights, i)) * delta[i];
            let w = (zero - optical).exp() * (one - (zero - tau).exp());
            optical += tau;
            let mut v = g_depth * t[i];
            v += g0 * relu::<F>(sample_colour::<F, I>(sh, corners, colour_weights, basis, i, 0, nb));
            v += g1 * relu::<F>(sample_colour::<F, I>(sh, corners, colour_weights, basis, i, 1, nb));
            v += g2 * relu::<F>(sample_colour::<F, I>(sh, corners, colour_weights, basis, i, 2, nb));
            out[i * 4] = w;
            out[i * 4 + 1] = v;
            out[i * 4 + 2] = (zero - optical).exp();
        }
        let transmittance = (zero - optical).exp();
        let mut bg = ray * 3;
        if background.len() <= 3 {
            bg = 0;
        }
        let behind = g0 * background[bg] + g1 * background[bg + 1] + g2 * background[bg + 2];
        // Back to front: what lies behind each sample summed from the back
        // (no difference of two large sums).
        let mut suffix = transmittance * (behind - g_opacity);
        for k in 0..hi - lo {
            let i = hi - 1 - k;
            let (w, v, next) = (out[i * 4], out[i * 4 + 1], out[i * 4 + 2]);
            let d_tau = next * v - suffix;
            suffix += w * v;
            let raw = sample_sigma::<F, I>(density, corners, corner_weights, i);
            out[i * 4] = masked::<F>(raw, d_tau * delta[i]);
            out[i * 4 + 1] = masked::<F>(sample_colour::<F, I>(sh, corners, colour_weights, basis, i, 0, nb), w * g0);
            out[i * 4 + 2] = masked::<F>(sample_colour::<F, I>(sh, corners, colour_weights, basis, i, 1, nb), w * g1);
            out[i * 4 + 3] = masked::<F>(sample_colour::<F, I>(sh, corners, colour_weights, basis, i, 2, nb), w * g2);
        }
    }

    /// One thread per output value: a row's entries (sample `e / 8`'s
    /// corner `e % 8`) in transpose order.
    #[cube(launch)]
    fn row_grads_kernel<F: Float, I: Numeric>(
        sample_grads: &Tensor<F>,
        weights: &Tensor<F>,
        basis: &Tensor<F>,
        order: &Tensor<I>,
        offsets: &Tensor<I>,
        out: &mut Tensor<F>,
        first: u32,
        channels: u32,
        nb: u32,
        #[comptime] with_basis: bool,
        #[define(F, I)] _dtypes: [ElemType; 2],
    ) {
        let pos = ABSOLUTE_POS;
        if pos >= out.len() {
            terminate!();
        }
        let nb = nb as usize;
        let mut spread = 1usize;
        if with_basis {
            spread = nb;
        }
        let cols = channels as usize * spread;
        let row = pos / cols;
        let channel = first as usize + (pos % cols) / spread;
        let b = pos % spread;
        let mut acc = F::new(0.0);
        if row + 1 < offsets.len() {
            let start = u32::cast_from(offsets[row]) as usize;
            let end = u32::cast_from(offsets[row + 1]) as usize;
            for k in start..end {
                let entry = u32::cast_from(order[k]) as usize;
                let sample = entry / 8;
                let mut value = weights[entry] * sample_grads[sample * 4 + channel];
                if with_basis {
                    value *= basis[sample * nb + b];
                }
                acc += value;
            }
        }
        out[pos] = acc;
    }

    /// One thread per value: colour gradient times the final transmittance.
    #[cube(launch)]
    fn background_grads_kernel<F: Float>(
        grad: &Tensor<F>,
        out_fwd: &Tensor<F>,
        out: &mut Tensor<F>,
        #[define(F)] _dtype: ElemType,
    ) {
        let pos = ABSOLUTE_POS;
        if pos >= out.len() {
            terminate!();
        }
        let ray = pos / 3;
        out[pos] = grad[ray * 5 + pos % 3] * (F::new(1.0) - out_fwd[ray * 5 + 4]);
    }

    fn empty_like(like: &CubeTensor, shape: Shape) -> CubeTensor {
        empty_device_dtype(like.client.clone(), like.device.clone(), shape, like.dtype)
    }

    /// The packed sample batch, contiguous on the device.
    struct Samples {
        density: CubeTensor,
        sh: CubeTensor,
        background: CubeTensor,
        corners: CubeTensor,
        corner_weights: CubeTensor,
        colour_weights: CubeTensor,
        basis: CubeTensor,
        delta: CubeTensor,
        t: CubeTensor,
        ray_offsets: CubeTensor,
    }

    impl Samples {
        fn rays(&self) -> usize {
            self.ray_offsets.shape()[0].saturating_sub(1)
        }

        fn num_basis(&self) -> u32 {
            (self.sh.shape()[1] / 3) as u32
        }
    }

    /// Every tensor of the batch made contiguous (the kernels index flat).
    macro_rules! samples {
        ($($field:ident),*) => {
            Samples { $($field: into_contiguous($field)),* }
        };
    }

    impl CompositeBackend for Cube {
        fn composite_rays(
            density: FloatTensor<Self>,
            sh: FloatTensor<Self>,
            background: FloatTensor<Self>,
            corners: IntTensor<Self>,
            _order: IntTensor<Self>,
            _offsets: IntTensor<Self>,
            corner_weights: FloatTensor<Self>,
            colour_weights: FloatTensor<Self>,
            basis: FloatTensor<Self>,
            delta: FloatTensor<Self>,
            t: FloatTensor<Self>,
            ray_offsets: IntTensor<Self>,
        ) -> FloatTensor<Self> {
            let x = samples!(
                density,
                sh,
                background,
                corners,
                corner_weights,
                colour_weights,
                basis,
                delta,
                t,
                ray_offsets
            );
            let rays = x.rays();
            let out = empty_like(&x.density, Shape::new([rays, 5]));
            if rays == 0 {
                return out;
            }
            let (cube_count, cube_dim) = one_per_value(&out.client, rays);
            let dtypes = [storage(x.density.dtype), storage(x.corners.dtype)];
            let nb = x.num_basis();
            forward_kernel::launch(
                &out.client,
                cube_count,
                cube_dim,
                x.density.into_tensor_arg(),
                x.sh.into_tensor_arg(),
                x.background.into_tensor_arg(),
                x.corners.into_tensor_arg(),
                x.corner_weights.into_tensor_arg(),
                x.colour_weights.into_tensor_arg(),
                x.basis.into_tensor_arg(),
                x.delta.into_tensor_arg(),
                x.t.into_tensor_arg(),
                x.ray_offsets.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                nb,
                dtypes,
            );
            out
        }

        fn composite_sample_grads(
            density: FloatTensor<Self>,
            sh: FloatTensor<Self>,
            background: FloatTensor<Self>,
            corners: IntTensor<Self>,
            corner_weights: FloatTensor<Self>,
            colour_weights: FloatTensor<Self>,
            basis: FloatTensor<Self>,
            delta: FloatTensor<Self>,
            t: FloatTensor<Self>,
            ray_offsets: IntTensor<Self>,
            grad: FloatTensor<Self>,
        ) -> FloatTensor<Self> {
            let x = samples!(
                density,
                sh,
                background,
                corners,
                corner_weights,
                colour_weights,
                basis,
                delta,
                t,
                ray_offsets
            );
            let grad = into_contiguous(grad);
            let (rays, samples) = (x.rays(), x.delta.shape()[0]);
            let out = empty_like(&x.density, Shape::new([samples, 4]));
            if rays == 0 || samples == 0 {
                return out;
            }
            let (cube_count, cube_dim) = one_per_value(&out.client, rays);
            let dtypes = [storage(x.density.dtype), storage(x.corners.dtype)];
            let nb = x.num_basis();
            sample_grads_kernel::launch(
                &out.client,
                cube_count,
                cube_dim,
                x.density.into_tensor_arg(),
                x.sh.into_tensor_arg(),
                x.background.into_tensor_arg(),
                x.corners.into_tensor_arg(),
                x.corner_weights.into_tensor_arg(),
                x.colour_weights.into_tensor_arg(),
                x.basis.into_tensor_arg(),
                x.delta.into_tensor_arg(),
                x.t.into_tensor_arg(),
                x.ray_offsets.into_tensor_arg(),
                grad.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                nb,
                dtypes,
            );
            out
        }

        fn composite_row_grads(
            sample_grads: FloatTensor<Self>,
            weights: FloatTensor<Self>,
            basis: FloatTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            rows: usize,
            first: usize,
            channels: usize,
            with_basis: bool,
        ) -> FloatTensor<Self> {
            let (sample_grads, weights, basis) =
                (into_contiguous(sample_grads), into_contiguous(weights), into_contiguous(basis));
            let (order, offsets) = (into_contiguous(order), into_contiguous(offsets));
            let samples = sample_grads.shape()[0];
            let nb = basis.shape().num_elements().checked_div(samples).unwrap_or(1);
            let cols = channels * if with_basis { nb } else { 1 };
            let out = empty_like(&sample_grads, Shape::new([rows, cols]));
            if rows * cols == 0 {
                return out;
            }
            let (cube_count, cube_dim) = one_per_value(&out.client, rows * cols);
            let dtypes = [storage(sample_grads.dtype), storage(order.dtype)];
            row_grads_kernel::launch(
                &out.client,
                cube_count,
                cube_dim,
                sample_grads.into_tensor_arg(),
                weights.into_tensor_arg(),
                basis.into_tensor_arg(),
                order.into_tensor_arg(),
                offsets.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                first as u32,
                channels as u32,
                nb as u32,
                with_basis,
                dtypes,
            );
            out
        }

        fn composite_background_grads(grad: FloatTensor<Self>, out_fwd: FloatTensor<Self>) -> FloatTensor<Self> {
            let (grad, out_fwd) = (into_contiguous(grad), into_contiguous(out_fwd));
            let rays = grad.shape()[0];
            let out = empty_like(&grad, Shape::new([rays, 3]));
            if rays == 0 {
                return out;
            }
            let (cube_count, cube_dim) = one_per_value(&out.client, rays * 3);
            let dtype = storage(grad.dtype);
            background_grads_kernel::launch(
                &out.client,
                cube_count,
                cube_dim,
                grad.into_tensor_arg(),
                out_fwd.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                dtype,
            );
            out
        }
    }

    /// What the backward needs: the forward's inputs and output.
    #[derive(Debug, Clone)]
    struct State<B: Backend> {
        density: FloatTensor<B>,
        sh: FloatTensor<B>,
        background: FloatTensor<B>,
        corners: IntTensor<B>,
        order: IntTensor<B>,
        offsets: IntTensor<B>,
        corner_weights: FloatTensor<B>,
        colour_weights: FloatTensor<B>,
        basis: FloatTensor<B>,
        delta: FloatTensor<B>,
        t: FloatTensor<B>,
        ray_offsets: IntTensor<B>,
        out: FloatTensor<B>,
    }

    /// The fused compositing's backward step.
    #[derive(Debug)]
    struct CompositeBackward;

    impl<B: CompositeBackend> Backward<B, 3> for CompositeBackward {
        type State = State<B>;

        fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
            let [node_density, node_sh, node_background] = ops.parents;
            let grad = grads.consume::<B>(&ops.node);
            let x = ops.state;
            let rows = x.density.shape()[0];
            let per_sample = B::composite_sample_grads(
                x.density,
                x.sh,
                x.background,
                x.corners,
                x.corner_weights.clone(),
                x.colour_weights.clone(),
                x.basis.clone(),
                x.delta,
                x.t,
                x.ray_offsets,
                grad.clone(),
            );
            let (order, offsets) = (x.order, x.offsets);
            if let Some(node) = node_density {
                let g = B::composite_row_grads(
                    per_sample.clone(),
                    x.corner_weights,
                    x.basis.clone(),
                    order.clone(),
                    offsets.clone(),
                    rows,
                    0,
                    1,
                    false,
                );
                grads.register::<B>(node.id, g);
            }
            if let Some(node) = node_sh {
                let g = B::composite_row_grads(per_sample, x.colour_weights, x.basis, order, offsets, rows, 1, 3, true);
                grads.register::<B>(node.id, g);
            }
            if let Some(node) = node_background {
                grads.register::<B>(node.id, B::composite_background_grads(grad, x.out));
            }
        }
    }

    impl<B: CompositeBackend, C: CheckpointStrategy> CompositeBackend for Autodiff<B, C> {
        fn composite_rays(
            density: FloatTensor<Self>,
            sh: FloatTensor<Self>,
            background: FloatTensor<Self>,
            corners: IntTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            corner_weights: FloatTensor<Self>,
            colour_weights: FloatTensor<Self>,
            basis: FloatTensor<Self>,
            delta: FloatTensor<Self>,
            t: FloatTensor<Self>,
            ray_offsets: IntTensor<Self>,
        ) -> FloatTensor<Self> {
            let (cw, kw) = (corner_weights.into_primitive(), colour_weights.into_primitive());
            let (basis, delta, t) = (basis.into_primitive(), delta.into_primitive(), t.into_primitive());
            let rays = ray_offsets.shape()[0].saturating_sub(1);
            let background_ok = !background.is_tracked() || background.shape()[0] == rays;
            let prep = CompositeBackward.prepare::<C>([density.node(), sh.node(), background.node()]);
            match prep.compute_bound().stateful() {
                OpsKind::Tracked(prep) => {
                    debug_assert!(background_ok, "a differentiated background has a row per ray");
                    let (density, sh, background) =
                        (density.into_primitive(), sh.into_primitive(), background.into_primitive());
                    let out = B::composite_rays(
                        density.clone(),
                        sh.clone(),
                        background.clone(),
                        corners.clone(),
                        order.clone(),
                        offsets.clone(),
                        cw.clone(),
                        kw.clone(),
                        basis.clone(),
                        delta.clone(),
                        t.clone(),
                        ray_offsets.clone(),
                    );
                    let state = State {
                        density,
                        sh,
                        background,
                        corners,
                        order,
                        offsets,
                        corner_weights: cw,
                        colour_weights: kw,
                        basis,
                        delta,
                        t,
                        ray_offsets,
                        out: out.clone(),
                    };
                    prep.finish(state, out)
                }
                OpsKind::UnTracked(prep) => prep.finish(B::composite_rays(
                    density.into_primitive(),
                    sh.into_primitive(),
                    background.into_primitive(),
                    corners,
                    order,
                    offsets,
                    cw,
                    kw,
                    basis,
                    delta,
                    t,
                    ray_offsets,
                )),
            }
        }

        fn composite_sample_grads(
            density: FloatTensor<Self>,
            sh: FloatTensor<Self>,
            background: FloatTensor<Self>,
            corners: IntTensor<Self>,
            corner_weights: FloatTensor<Self>,
            colour_weights: FloatTensor<Self>,
            basis: FloatTensor<Self>,
            delta: FloatTensor<Self>,
            t: FloatTensor<Self>,
            ray_offsets: IntTensor<Self>,
            grad: FloatTensor<Self>,
        ) -> FloatTensor<Self> {
            // Only ever called inside a backward, on the inner backend.
            <Self as AutodiffBackend>::from_inner(B::composite_sample_grads(
                density.into_primitive(),
                sh.into_primitive(),
                background.into_primitive(),
                corners,
                corner_weights.into_primitive(),
                colour_weights.into_primitive(),
                basis.into_primitive(),
                delta.into_primitive(),
                t.into_primitive(),
                ray_offsets,
                grad.into_primitive(),
            ))
        }

        fn composite_row_grads(
            sample_grads: FloatTensor<Self>,
            weights: FloatTensor<Self>,
            basis: FloatTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            rows: usize,
            first: usize,
            channels: usize,
            with_basis: bool,
        ) -> FloatTensor<Self> {
            <Self as AutodiffBackend>::from_inner(B::composite_row_grads(
                sample_grads.into_primitive(),
                weights.into_primitive(),
                basis.into_primitive(),
                order,
                offsets,
                rows,
                first,
                channels,
                with_basis,
            ))
        }

        fn composite_background_grads(grad: FloatTensor<Self>, out: FloatTensor<Self>) -> FloatTensor<Self> {
            let g = B::composite_background_grads(grad.into_primitive(), out.into_primitive());
            <Self as AutodiffBackend>::from_inner(g)
        }
    }
}
