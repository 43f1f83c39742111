//! The photoreal fit's optimiser arithmetic as GPU kernels: RMSprop's lazy
//! step on a step's rows (the GPU path of `optim::Rmsprop::step_rows`) and
//! the gradient of Plenoxels' per-channel TV (the GPU path of
//! `optim::add_tv_gradient`, which the trainer takes on a GPU instead of
//! the TV terms' graph). The host arithmetic in `optim` is the oracle
//! (its `graph_oracle` tests).
//!
//! Why: as tensor operations the RMSprop step is a row gather, nine
//! elementwise operations and two row writes, for the density and again
//! for the SH; the TV terms are three row gathers and a dozen operations
//! per tensor, forward and backward through autodiff: together about half
//! of a training step's launches, each reading and writing `[rows, cols]`
//! buffers. Here one thread per value does each: RMSprop reads the average,
//! the parameter and the gradient once and writes the first two in place
//! (`Rmsprop::coordinate_step`'s arithmetic, in its order: the average
//! gets `v_new - v` added, the parameter its step); the TV gradient is
//! four launches of one thread per (centre, channel): one subtracts each
//! centre's terms from its own row, then one per axis adds them to the
//! centres' neighbours along it. Within a launch no two threads write one
//! value (on a lattice a row is the +x neighbour of at most one row), so
//! there are no atomics and the sums are the same on every run.

#[cfg(feature = "wgpu")]
pub use cube_op::OptimBackend;

#[cfg(feature = "wgpu")]
mod cube_op {
    use burn::backend::Cube;
    use burn::backend::autodiff::Autodiff;
    use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
    use burn::backend::cubecl::dtype_to_storage_type as storage;
    use burn::backend::tensor::{FloatTensor, IntTensor};
    use burn::backend::{AutodiffBackend, Backend, TensorMetadata, backend_extension};
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;
    use burn_cubecl::kernel::into_contiguous;
    use burn_cubecl::tensor::CubeTensor;

    use crate::kernels::gather_op::one_per_value;

    /// RMSprop's step on chosen rows (module docs).
    #[backend_extension(Cube, Autodiff)]
    pub trait OptimBackend: Backend {
        /// `param` and its running average `avg` (`[rows, cols]`) after a
        /// step on the rows `rows` (`[n]`, distinct) with the gradients
        /// `grad` (`[n, cols]`): `v = beta v + (1 - beta) g^2` (with
        /// `first_grad`, `g^2` where `v` is 0), `x -= lr g / (sqrt(v) +
        /// eps)`. In place when the tensors are uniquely owned.
        #[allow(clippy::too_many_arguments)]
        fn rmsprop_rows(
            param: FloatTensor<Self>,
            avg: FloatTensor<Self>,
            rows: IntTensor<Self>,
            grad: FloatTensor<Self>,
            beta: f32,
            eps: f32,
            lr: f32,
            first_grad: bool,
        ) -> (FloatTensor<Self>, FloatTensor<Self>);

        /// `grad` plus the per-channel TV gradient of `values` (both
        /// `[rows, cols]`) times `scale`, over the centres of `links`
        /// (`TvLinks`). In place when `grad` is uniquely owned.
        fn add_tv_gradient(
            grad: FloatTensor<Self>,
            values: FloatTensor<Self>,
            links: IntTensor<Self>,
            num_core: usize,
            scale: f32,
        ) -> FloatTensor<Self>;
    }

    /// One thread per gradient value.
    #[cube(launch)]
    #[allow(clippy::too_many_arguments)]
    fn rmsprop_rows_kernel<F: Float, I: Numeric>(
        param: &mut Tensor<F>,
        avg: &mut Tensor<F>,
        rows: &Tensor<I>,
        grad: &Tensor<F>,
        cols: u32,
        beta: f32,
        eps: f32,
        lr: f32,
        #[comptime] first_grad: bool,
        #[define(F, I)] _dtypes: [ElemType; 2],
    ) {
        let pos = ABSOLUTE_POS;
        if pos >= grad.len() {
            terminate!();
        }
        let c = cols as usize;
        let at = (u32::cast_from(rows[pos / c]) as usize) * c + pos % c;
        let v = avg[at];
        let g = grad[pos];
        let sq = g * g;
        let beta = F::cast_from(beta);
        let mut v_new = v * beta + sq * (F::new(1.0) - beta);
        // `first_grad` is known when the kernel is compiled, `v` only when it runs.
        #[allow(clippy::collapsible_if)]
        if first_grad {
            if v == F::new(0.0) {
                v_new = sq;
            }
        }
        avg[at] = v + (v_new - v);
        param[at] += g / (v_new.sqrt() + F::cast_from(eps)) * F::cast_from(-lr);
    }

    /// Centre `i`'s difference to its neighbour along `axis`, channel `ch`.
    #[cube]
    fn tv_difference<F: Float, I: Numeric>(
        values: &Tensor<F>,
        links: &Tensor<I>,
        core: usize,
        i: usize,
        axis: usize,
        c: usize,
        ch: usize,
    ) -> F {
        let nb = u32::cast_from(links[axis * core + i]) as usize;
        values[nb * c + ch] - values[i * c + ch]
    }

    /// Centre `i`'s `scale / sqrt(sum of squared differences + 1e-9)`, channel `ch`.
    #[cube]
    fn tv_inverse<F: Float, I: Numeric>(
        values: &Tensor<F>,
        links: &Tensor<I>,
        core: usize,
        i: usize,
        c: usize,
        ch: usize,
        scale: F,
    ) -> F {
        let d0 = tv_difference::<F, I>(values, links, core, i, 0, c, ch);
        let d1 = tv_difference::<F, I>(values, links, core, i, 1, c, ch);
        let d2 = tv_difference::<F, I>(values, links, core, i, 2, c, ch);
        scale / (d0 * d0 + d1 * d1 + d2 * d2 + F::new(1e-9)).sqrt()
    }

    /// One thread per (centre, channel). `pass` 3: the centre's terms
    /// subtracted from its own row; `pass` 0, 1, 2: its term along that
    /// axis added to its neighbour there (none when it is its own).
    #[cube(launch)]
    #[allow(clippy::too_many_arguments)]
    fn tv_gradient_kernel<F: Float, I: Numeric>(
        grad: &mut Tensor<F>,
        values: &Tensor<F>,
        links: &Tensor<I>,
        cols: u32,
        num_core: u32,
        scale: f32,
        pass: u32,
        #[define(F, I)] _dtypes: [ElemType; 2],
    ) {
        let pos = ABSOLUTE_POS;
        let c = cols as usize;
        let core = num_core as usize;
        if pos >= core * c {
            terminate!();
        }
        let (i, ch) = (pos / c, pos % c);
        let inv = tv_inverse::<F, I>(values, links, core, i, c, ch, F::cast_from(scale));
        if pass == 3 {
            let mut g = grad[pos];
            for axis in 0..3usize {
                g -= tv_difference::<F, I>(values, links, core, i, axis, c, ch) * inv;
            }
            grad[pos] = g;
        } else {
            let axis = pass as usize;
            let nb = u32::cast_from(links[axis * core + i]) as usize;
            if nb != i {
                grad[nb * c + ch] += tv_difference::<F, I>(values, links, core, i, axis, c, ch) * inv;
            }
        }
    }

    /// `tensor` itself when it can be written in place, else a contiguous copy.
    fn writable(tensor: CubeTensor) -> CubeTensor {
        match tensor.can_mut() && tensor.is_contiguous() {
            true => tensor,
            false => into_contiguous(tensor.copy()),
        }
    }

    impl OptimBackend for Cube {
        fn rmsprop_rows(
            param: FloatTensor<Self>,
            avg: FloatTensor<Self>,
            rows: IntTensor<Self>,
            grad: FloatTensor<Self>,
            beta: f32,
            eps: f32,
            lr: f32,
            first_grad: bool,
        ) -> (FloatTensor<Self>, FloatTensor<Self>) {
            let (param, avg) = (writable(param), writable(avg));
            let (rows, grad) = (into_contiguous(rows), into_contiguous(grad));
            let units = grad.shape().num_elements();
            if units == 0 {
                return (param, avg);
            }
            let cols = grad.shape()[1];
            let client = param.client.clone();
            let (cube_count, cube_dim) = one_per_value(&client, units);
            let dtypes = [storage(param.dtype), storage(rows.dtype)];
            rmsprop_rows_kernel::launch(
                &client,
                cube_count,
                cube_dim,
                param.clone().into_tensor_arg(),
                avg.clone().into_tensor_arg(),
                rows.into_tensor_arg(),
                grad.into_tensor_arg(),
                cols as u32,
                beta,
                eps,
                lr,
                first_grad,
                dtypes,
            );
            (param, avg)
        }

        fn add_tv_gradient(
            grad: FloatTensor<Self>,
            values: FloatTensor<Self>,
            links: IntTensor<Self>,
            num_core: usize,
            scale: f32,
        ) -> FloatTensor<Self> {
            let grad = writable(grad);
            let (values, links) = (into_contiguous(values), into_contiguous(links));
            let cols = grad.shape()[1];
            let units = num_core * cols;
            if units == 0 {
                return grad;
            }
            let client = grad.client.clone();
            let (cube_count, cube_dim) = one_per_value(&client, units);
            let dtypes = [storage(grad.dtype), storage(links.dtype)];
            // The centres' own rows first, then their neighbours axis by axis.
            for pass in [3u32, 0, 1, 2] {
                tv_gradient_kernel::launch(
                    &client,
                    cube_count.clone(),
                    cube_dim,
                    grad.clone().into_tensor_arg(),
                    values.clone().into_tensor_arg(),
                    links.clone().into_tensor_arg(),
                    cols as u32,
                    num_core as u32,
                    scale,
                    pass,
                    dtypes,
                );
            }
            grad
        }
    }

    impl<B: OptimBackend, C: CheckpointStrategy> OptimBackend for Autodiff<B, C> {
        fn rmsprop_rows(
            param: FloatTensor<Self>,
            avg: FloatTensor<Self>,
            rows: IntTensor<Self>,
            grad: FloatTensor<Self>,
            beta: f32,
            eps: f32,
            lr: f32,
            first_grad: bool,
        ) -> (FloatTensor<Self>, FloatTensor<Self>) {
            // An optimiser's write: never differentiated.
            let (param, avg) = B::rmsprop_rows(
                param.into_primitive(),
                avg.into_primitive(),
                rows,
                grad.into_primitive(),
                beta,
                eps,
                lr,
                first_grad,
            );
            (<Self as AutodiffBackend>::from_inner(param), <Self as AutodiffBackend>::from_inner(avg))
        }

        fn add_tv_gradient(
            grad: FloatTensor<Self>,
            values: FloatTensor<Self>,
            links: IntTensor<Self>,
            num_core: usize,
            scale: f32,
        ) -> FloatTensor<Self> {
            // A gradient computed directly: never differentiated.
            let out = B::add_tv_gradient(grad.into_primitive(), values.into_primitive(), links, num_core, scale);
            <Self as AutodiffBackend>::from_inner(out)
        }
    }
}
