//! A row gather whose backward is parallel on the GPU: `x.select(0, idx)`
//! with the gradient summed into `x`'s rows by one GPU thread per
//! (row, column), through the index's transpose computed on the host.
//!
//! Why: burn-cubecl 0.22.1's backward of `select` is `select_assign`, whose
//! kernel runs one thread per column and loops over every index in order
//! (`select_assign_kernel`): the gradient of a step's 8 corners x 45,000
//! samples into 27 SH columns is 27 threads of 360,000 serial additions, one
//! thread for the density. On an H200 that made a lego training step about
//! 280 ms for 4,096 rays (flex on the same machine's 16 cores: 11 ms).
//!
//! The gather's index lists come from the host march, so the host also
//! builds their transpose (`RowIndex`: for each row, which gathered entries
//! read it, a counting sort), and the backward sums each row's entries in
//! that order. The sum is deterministic (no atomics, which wgpu offers for
//! floats only on some adapters) and needs nothing but plain loads.
//!
//! The CPU backends never come here (`gather_rows` checks
//! `is_host_memory`): their `select` backward is already a loop over host
//! memory, and their results stay bit for bit what they were.

use burn::tensor::{IndexingUpdateOp, Int, Tensor};

use crate::util::tensor::{indices, is_host_memory, select_rows};

/// A gather index with, on a GPU device, its transpose for the backward.
#[derive(Clone)]
pub struct RowIndex {
    /// The rows to gather, `[n]`.
    pub idx: Tensor<1, Int>,
    /// On a GPU: the gathered entries ordered by the row they read
    /// (`order`, `[n']`) and where each row's entries start (`offsets`,
    /// `[rows + 1]`). Entries reading a row `>= rows` are left out: that
    /// row gets no gradient (the constant padding row of a packed layout),
    /// and neither do table rows beyond `rows`.
    transpose: Option<(Tensor<1, Int>, Tensor<1, Int>)>,
    /// With a compact transpose (`compact_transpose_of`): the rows read,
    /// ascending, run `k` of `order` being row `touched[k]`'s; empty when
    /// run `k` is row `k`'s.
    touched: Option<Tensor<1, Int>>,
}

impl RowIndex {
    /// The index `idx` into a table of `rows` rows, uploaded to `device`.
    /// Entries `>= rows` are gathered but get no gradient (see `transpose`).
    pub fn new(idx: Vec<i32>, rows: usize, device: &burn::tensor::Device) -> Self {
        let transpose = (!is_host_memory(device)).then(|| {
            let (order, offsets) = transpose_of(&idx, rows);
            (indices(order, device), indices(offsets, device))
        });
        Self { idx: indices(idx, device), transpose, touched: None }
    }

    /// `idx` already on its device, `host` its values: on a GPU with a
    /// compact transpose (the rows read only), whose size is the entries',
    /// not the table's. For indices kept on the device for many steps (a
    /// stylization's cached sample lists), where a table-sized `offsets`
    /// per index would add up.
    pub fn compact(idx: Tensor<1, Int>, host: &[i32]) -> Self {
        let device = idx.device();
        if is_host_memory(&device) {
            return Self::plain(idx);
        }
        let (touched, order, offsets) = compact_transpose_of(host);
        Self {
            idx,
            transpose: Some((indices(order, &device), indices(offsets, &device))),
            touched: Some(indices(touched, &device)),
        }
    }

    /// The transpose (`order`, `offsets`; `transpose_of`), when built.
    /// A compact one (`RowIndex::compact`) is not given out.
    pub fn transpose(&self) -> Option<(&Tensor<1, Int>, &Tensor<1, Int>)> {
        match self.touched {
            Some(_) => None,
            None => self.transpose.as_ref().map(|(order, offsets)| (order, offsets)),
        }
    }

    /// The transpose as a fused kernel's backward reads it (`order`,
    /// `offsets`, and `touched`, empty for a full transpose), when built.
    pub fn transpose_parts(&self) -> Option<(Tensor<1, Int>, Tensor<1, Int>, Tensor<1, Int>)> {
        let (order, offsets) = self.transpose.clone()?;
        let touched = self.touched.clone().unwrap_or_else(|| Tensor::zeros([0], &order.device()));
        Some((order, offsets, touched))
    }

    /// The index alone, with Burn's `select` backward (the CPU backends, or
    /// a forward without gradients).
    pub fn plain(idx: Tensor<1, Int>) -> Self {
        Self { idx, transpose: None, touched: None }
    }
}

/// [`transpose_of`] over the rows `idx` reads only: those rows ascending
/// (`touched`), the positions reading each, ascending (`order`), and where
/// each touched row's positions start (`offsets`, `touched.len() + 1`
/// values). Negative entries are left out.
pub fn compact_transpose_of(idx: &[i32]) -> (Vec<i32>, Vec<i32>, Vec<i32>) {
    let rows = idx.iter().copied().max().map_or(0, |m| (m + 1).max(0) as usize);
    let (order, dense) = transpose_of(idx, rows);
    let touched: Vec<i32> = (0..rows).filter(|&r| dense[r + 1] > dense[r]).map(|r| r as i32).collect();
    let offsets = touched.iter().map(|&r| dense[r as usize]).chain([dense[rows]]).collect();
    (touched, order, offsets)
}

/// For each row below `rows`, the positions in `idx` that read it, rows in
/// order and positions ascending within a row (a counting sort): `order`
/// and the start of each row's run, `offsets` (`rows + 1` values).
pub fn transpose_of(idx: &[i32], rows: usize) -> (Vec<i32>, Vec<i32>) {
    let mut offsets = vec![0i32; rows + 1];
    for &r in idx {
        if (0..rows as i32).contains(&r) {
            offsets[r as usize + 1] += 1;
        }
    }
    for i in 0..rows {
        offsets[i + 1] += offsets[i];
    }
    let mut next: Vec<i32> = offsets[..rows].to_vec();
    let mut order = vec![0i32; offsets[rows] as usize];
    for (k, &r) in idx.iter().enumerate() {
        if (0..rows as i32).contains(&r) {
            order[next[r as usize] as usize] = k as i32;
            next[r as usize] += 1;
        }
    }
    (order, offsets)
}

/// `x.select(0, index.idx)` for a 2-D `x`; on a GPU with the transpose, its
/// backward sums the gradient by rows in parallel (module docs).
pub fn gather_rows(x: Tensor<2>, index: &RowIndex) -> Tensor<2> {
    #[cfg(feature = "wgpu")]
    if let Some((order, offsets)) = &index.transpose {
        // An empty `touched` says the runs are the rows 0, 1, ... in order.
        let touched = index.touched.clone().unwrap_or_else(|| Tensor::zeros([0], &x.device()));
        let out = <burn::backend::Dispatch as GatherBackend>::gather_rows(
            x.into_dispatch(),
            index.idx.clone().into_dispatch(),
            order.clone().into_dispatch(),
            offsets.clone().into_dispatch(),
            touched.into_dispatch(),
        );
        return Tensor::from_dispatch(out);
    }
    select_rows(x, index.idx.clone())
}

/// `values` `[n, cols]` summed by runs of consecutive rows, `[runs, cols]`:
/// `run_of` (`[n]`, nondecreasing) names each row's run and `starts`
/// (host values, `runs + 1`) where each run starts, the last being `n`.
/// Differentiable in `values`. On a GPU one thread per output value
/// (`select_assign`, the CPU backends' way, is serial there).
pub fn sum_runs(values: Tensor<2>, run_of: &Tensor<1, Int>, starts: &[i32]) -> Tensor<2> {
    let runs = starts.len() - 1;
    #[cfg(feature = "wgpu")]
    if !is_host_memory(&values.device()) {
        let device = values.device();
        let n = values.dims()[0];
        let out = <burn::backend::Dispatch as GatherBackend>::sum_runs(
            values.into_dispatch(),
            Tensor::<1, Int>::arange(0..n as i64, &device).into_dispatch(),
            indices(starts.to_vec(), &device).into_dispatch(),
            run_of.clone().into_dispatch(),
            runs,
        );
        return Tensor::from_dispatch(out);
    }
    let cols = values.dims()[1];
    let zeros = Tensor::zeros([runs, cols], &values.device());
    crate::util::tensor::assign_rows(zeros, run_of.clone(), values, IndexingUpdateOp::Add)
}

/// For each of `total` rows, the run it belongs to (`starts`: where each
/// run starts, nondecreasing from 0, `total` last; empty runs allowed), on
/// the GPU: one thread per row. `None` on the CPU backends, where the
/// caller's own way is as fast.
pub fn runs_of(starts: &[i32], total: usize, device: &burn::tensor::Device) -> Option<Tensor<1, Int>> {
    #[cfg(feature = "wgpu")]
    if !is_host_memory(device) {
        let t = indices(starts.to_vec(), device).into_dispatch();
        let out = <burn::backend::Dispatch as GatherBackend>::runs_of(t, total);
        return Some(Tensor::from_dispatch(out));
    }
    let _ = (starts, total, device);
    None
}

/// `tensor` with its rows `idx` replaced by `values` (`op` `Assign`) or
/// `values` added to them (`Add`); the rows must be distinct. On a GPU one
/// thread per value (burn-cubecl's `select_assign` runs one thread per
/// column, looping over the rows).
pub fn write_rows(tensor: Tensor<2>, idx: &Tensor<1, Int>, values: Tensor<2>, op: IndexingUpdateOp) -> Tensor<2> {
    #[cfg(feature = "wgpu")]
    if !is_host_memory(&tensor.device()) && matches!(op, IndexingUpdateOp::Assign | IndexingUpdateOp::Add) {
        let out = <burn::backend::Dispatch as GatherBackend>::write_rows(
            tensor.into_dispatch(),
            idx.clone().into_dispatch(),
            values.into_dispatch(),
            op == IndexingUpdateOp::Add,
        );
        return Tensor::from_dispatch(out);
    }
    crate::util::tensor::assign_rows(tensor, idx.clone(), values, op)
}

#[cfg(feature = "wgpu")]
pub use cube_op::GatherBackend;
#[cfg(feature = "wgpu")]
pub(crate) use cube_op::{one_per_value, sum_weighted_by_rows};

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
    use burn::backend::ops::FloatTensorOps;
    use burn::backend::tensor::{FloatTensor, IntTensor};
    use burn::backend::{AutodiffBackend, Backend, Shape, TensorMetadata, backend_extension};
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::client::Client;
    use burn_cubecl::cubecl::prelude::*;
    use burn_cubecl::cubecl::{CubeDim, calculate_cube_count_elemwise};
    use burn_cubecl::kernel::into_contiguous;
    use burn_cubecl::ops::numeric::{empty_device_dtype, zeros_client};
    use burn_cubecl::tensor::CubeTensor;

    /// A row gather with a parallel backward (module docs).
    #[backend_extension(Cube, Autodiff)]
    pub trait GatherBackend: Backend {
        /// `x` `[rows, cols]` gathered at `idx` `[n]`: `[n, cols]`.
        /// `order` and `offsets` are `idx`'s transpose (`transpose_of`),
        /// or its compact form with `touched` (`compact_transpose_of`;
        /// `touched` empty for the full form).
        fn gather_rows(
            x: FloatTensor<Self>,
            idx: IntTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            touched: IntTensor<Self>,
        ) -> FloatTensor<Self>;

        /// The gather's backward: `grad` `[n, cols]` summed by the rows
        /// its entries read, `[rows, cols]`; rows the transpose does not
        /// cover (`offsets` has fewer than `rows + 1` values, or they are
        /// not among `touched`) get zeros.
        fn sum_by_rows(
            grad: FloatTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            touched: IntTensor<Self>,
            rows: usize,
        ) -> FloatTensor<Self>;

        /// `values` `[n, cols]` summed over consecutive runs of rows: output
        /// row `r` is the sum of rows `offsets[r]..offsets[r + 1]`, `rows`
        /// of them (`order` is `0..n`). The backward gathers the output's
        /// gradient back at `run_of` (`[n]`, each input row's run).
        fn sum_runs(
            values: FloatTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            run_of: IntTensor<Self>,
            rows: usize,
        ) -> FloatTensor<Self>;

        /// For each of `total` rows, the run it belongs to: the last `k`
        /// with `starts[k] <= row` (`starts`: `runs + 1` nondecreasing
        /// values from 0, the last `total`).
        fn runs_of(starts: IntTensor<Self>, total: usize) -> IntTensor<Self>;

        /// `tensor` `[rows, cols]` with its rows `idx` `[n]` replaced by
        /// `values` `[n, cols]` (with `add`: `values` added to them), in
        /// place when `tensor` is uniquely owned. The rows must be distinct
        /// (an optimiser step's rows).
        fn write_rows(
            tensor: FloatTensor<Self>,
            idx: IntTensor<Self>,
            values: FloatTensor<Self>,
            add: bool,
        ) -> FloatTensor<Self>;
    }

    /// One thread per output value: the row's entries summed in `order`.
    /// `compact`: the runs are those of the rows `touched` (the other rows'
    /// zeros are already written), else run `k` is row `k`'s. `weighted`:
    /// entry `e` adds `grad`'s row `e / group` times `weights[e]` (the
    /// fused colour pass's backward, `kernels::frozen_op`), else `grad`'s
    /// row `e`.
    #[cube(launch)]
    #[allow(clippy::too_many_arguments)]
    fn sum_by_rows_kernel<F: Float, I: Numeric>(
        grad: &Tensor<F>,
        weights: &Tensor<F>,
        order: &Tensor<I>,
        offsets: &Tensor<I>,
        touched: &Tensor<I>,
        out: &mut Tensor<F>,
        cols: u32,
        group: u32,
        #[comptime] compact: bool,
        #[comptime] weighted: bool,
        #[define(F, I)] _dtypes: [ElemType; 2],
    ) {
        let pos = ABSOLUTE_POS;
        let c = cols as usize;
        let mut units = out.len();
        if compact {
            units = touched.len() * c;
        }
        if pos >= units {
            terminate!();
        }
        let run = pos / c;
        let col = pos % c;
        let mut acc = F::new(0.0);
        if run + 1 < offsets.len() {
            let start = u32::cast_from(offsets[run]) as usize;
            let end = u32::cast_from(offsets[run + 1]) as usize;
            for k in start..end {
                let entry = u32::cast_from(order[k]) as usize;
                if weighted {
                    acc += grad[(entry / group as usize) * c + col] * weights[entry];
                } else {
                    acc += grad[entry * c + col];
                }
            }
        }
        let mut row = run;
        if compact {
            row = u32::cast_from(touched[run]) as usize;
        }
        out[row * c + col] = acc;
    }

    /// One thread per written value.
    #[cube(launch)]
    fn write_rows_kernel<F: Float, I: Numeric>(
        tensor: &mut Tensor<F>,
        idx: &Tensor<I>,
        values: &Tensor<F>,
        cols: u32,
        #[comptime] add: bool,
        #[define(F, I)] _dtypes: [ElemType; 2],
    ) {
        let pos = ABSOLUTE_POS;
        if pos >= values.len() {
            terminate!();
        }
        let c = cols as usize;
        let at = (u32::cast_from(idx[pos / c]) as usize) * c + pos % c;
        if add {
            tensor[at] += values[pos];
        } else {
            tensor[at] = values[pos];
        }
    }

    /// One thread per row: a binary search of the run starts.
    #[cube(launch)]
    fn runs_of_kernel<I: Numeric>(starts: &Tensor<I>, out: &mut Tensor<I>, #[define(I)] _dtype: ElemType) {
        let row = ABSOLUTE_POS;
        if row >= out.len() {
            terminate!();
        }
        // starts[lo] <= row < starts[hi] throughout (starts[runs] is the total).
        let mut lo = 0usize;
        let mut hi = starts.len() - 1;
        while hi - lo > 1 {
            let mid = (lo + hi) / 2;
            if u32::cast_from(starts[mid]) as usize <= row {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        out[row] = I::cast_from(lo as u32);
    }

    impl GatherBackend for Cube {
        fn gather_rows(
            x: FloatTensor<Self>,
            idx: IntTensor<Self>,
            _order: IntTensor<Self>,
            _offsets: IntTensor<Self>,
            _touched: IntTensor<Self>,
        ) -> FloatTensor<Self> {
            // The forward is Burn's own gather: one thread per output value.
            <Cube as FloatTensorOps<Cube>>::float_select(x, 0, idx)
        }

        fn sum_by_rows(
            grad: FloatTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            touched: IntTensor<Self>,
            rows: usize,
        ) -> FloatTensor<Self> {
            sum_by_rows(grad, order, offsets, touched, rows)
        }

        fn sum_runs(
            values: FloatTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            _run_of: IntTensor<Self>,
            rows: usize,
        ) -> FloatTensor<Self> {
            let none = empty_device_dtype(order.client.clone(), order.device.clone(), Shape::new([0]), order.dtype);
            sum_by_rows(values, order, offsets, none, rows)
        }

        fn runs_of(starts: IntTensor<Self>, total: usize) -> IntTensor<Self> {
            let starts = into_contiguous(starts);
            let out =
                empty_device_dtype(starts.client.clone(), starts.device.clone(), Shape::new([total]), starts.dtype);
            if total == 0 {
                return out;
            }
            let client = starts.client.clone();
            let (cube_count, cube_dim) = one_per_value(&client, total);
            let dtype = storage(starts.dtype);
            runs_of_kernel::launch(
                &client,
                cube_count,
                cube_dim,
                starts.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                dtype,
            );
            out
        }

        fn write_rows(
            tensor: FloatTensor<Self>,
            idx: IntTensor<Self>,
            values: FloatTensor<Self>,
            add: bool,
        ) -> FloatTensor<Self> {
            write_rows(tensor, idx, values, add)
        }
    }

    /// One unit per value: the cube count and size for `units` values
    /// (every kernel of ours launches this way, `kernels::composite_op`'s too).
    pub(crate) fn one_per_value(client: &Client, units: usize) -> (CubeCount, CubeDim) {
        let cube_dim = CubeDim::new(client, units);
        (calculate_cube_count_elemwise(client, units, cube_dim), cube_dim)
    }

    fn write_rows(tensor: CubeTensor, idx: CubeTensor, values: CubeTensor, add: bool) -> CubeTensor {
        let tensor = match tensor.can_mut() && tensor.is_contiguous() {
            true => tensor,
            false => into_contiguous(tensor.copy()),
        };
        let (idx, values) = (into_contiguous(idx), into_contiguous(values));
        let units = values.shape().num_elements();
        if units == 0 {
            return tensor;
        }
        let cols = values.shape()[1];
        let client = tensor.client.clone();
        let (cube_count, cube_dim) = one_per_value(&client, units);
        let dtypes = [storage(tensor.dtype), storage(idx.dtype)];
        write_rows_kernel::launch(
            &client,
            cube_count,
            cube_dim,
            tensor.clone().into_tensor_arg(),
            idx.into_tensor_arg(),
            values.into_tensor_arg(),
            cols as u32,
            add,
            dtypes,
        );
        tensor
    }

    /// `grad`'s entries summed by rows (`sum_by_rows_kernel`); `touched`
    /// empty for a full transpose, else a compact one's rows.
    fn sum_by_rows(
        grad: CubeTensor,
        order: CubeTensor,
        offsets: CubeTensor,
        touched: CubeTensor,
        rows: usize,
    ) -> CubeTensor {
        sum_weighted_by_rows(grad, None, order, offsets, touched, rows)
    }

    /// `sum_by_rows` where `weighted` is `Some((weights, group))`: entry
    /// `e` of the transpose adds `grad`'s row `e / group` times
    /// `weights[e]` (`[entries]`), the fused colour pass's backward.
    pub(crate) fn sum_weighted_by_rows(
        grad: CubeTensor,
        weighted: Option<(CubeTensor, usize)>,
        order: CubeTensor,
        offsets: CubeTensor,
        touched: CubeTensor,
        rows: usize,
    ) -> CubeTensor {
        let grad = into_contiguous(grad);
        let (order, offsets, touched) = (into_contiguous(order), into_contiguous(offsets), into_contiguous(touched));
        let cols = grad.shape()[1];
        let compact = touched.shape().num_elements() > 0;
        let (shape, client, device) = (Shape::new([rows, cols]), grad.client.clone(), grad.device.clone());
        // A compact transpose writes only the rows it reads: the others are zeros.
        let out = match compact {
            true => zeros_client(client.clone(), device, shape, grad.dtype),
            false => empty_device_dtype(client.clone(), device, shape, grad.dtype),
        };
        let units = match compact {
            true => touched.shape().num_elements() * cols,
            false => rows * cols,
        };
        if units == 0 {
            return out;
        }
        let (cube_count, cube_dim) = one_per_value(&client, units);
        let dtypes = [storage(grad.dtype), storage(order.dtype)];
        // The full form never reads `touched`, nor the plain sum `weights`:
        // any bound buffer will do (not an empty one).
        let touched = if compact { touched } else { offsets.clone() };
        let is_weighted = weighted.is_some();
        let (weights, group) = match weighted {
            Some((weights, group)) => (into_contiguous(weights), group),
            None => (grad.clone(), 1),
        };
        sum_by_rows_kernel::launch(
            &client,
            cube_count,
            cube_dim,
            grad.into_tensor_arg(),
            weights.into_tensor_arg(),
            order.into_tensor_arg(),
            offsets.into_tensor_arg(),
            touched.into_tensor_arg(),
            out.clone().into_tensor_arg(),
            cols as u32,
            group as u32,
            compact,
            is_weighted,
            dtypes,
        );
        out
    }

    /// The gather's backward step.
    #[derive(Debug)]
    struct GatherBackward;

    impl<B: GatherBackend> Backward<B, 1> for GatherBackward {
        /// The transpose (`order`, `offsets`, `touched`) and the table's rows.
        type State = (IntTensor<B>, IntTensor<B>, IntTensor<B>, usize);

        fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
            let [node_x] = ops.parents;
            let grad = grads.consume::<B>(&ops.node);
            let (order, offsets, touched, rows) = ops.state;
            if let Some(node) = node_x {
                grads.register::<B>(node.id, B::sum_by_rows(grad, order, offsets, touched, rows));
            }
        }
    }

    /// The backward of a sum over runs: each input row gets its run's gradient.
    #[derive(Debug)]
    struct RunsBackward;

    impl<B: GatherBackend> Backward<B, 1> for RunsBackward {
        /// Each input row's run.
        type State = IntTensor<B>;

        fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
            let [node_values] = ops.parents;
            let grad = grads.consume::<B>(&ops.node);
            if let Some(node) = node_values {
                grads.register::<B>(node.id, B::float_select(grad, 0, ops.state));
            }
        }
    }

    impl<B: GatherBackend, C: CheckpointStrategy> GatherBackend for Autodiff<B, C> {
        fn gather_rows(
            x: FloatTensor<Self>,
            idx: IntTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            touched: IntTensor<Self>,
        ) -> FloatTensor<Self> {
            let rows = x.shape()[0];
            match GatherBackward.prepare::<C>([x.node()]).compute_bound().stateful() {
                OpsKind::Tracked(prep) => {
                    let out = B::gather_rows(x.into_primitive(), idx, order.clone(), offsets.clone(), touched.clone());
                    prep.finish((order, offsets, touched, rows), out)
                }
                OpsKind::UnTracked(prep) => {
                    prep.finish(B::gather_rows(x.into_primitive(), idx, order, offsets, touched))
                }
            }
        }

        fn sum_by_rows(
            grad: FloatTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            touched: IntTensor<Self>,
            rows: usize,
        ) -> FloatTensor<Self> {
            // Only ever called inside a backward, on the inner backend.
            let out = B::sum_by_rows(grad.into_primitive(), order, offsets, touched, rows);
            <Self as AutodiffBackend>::from_inner(out)
        }

        fn sum_runs(
            values: FloatTensor<Self>,
            order: IntTensor<Self>,
            offsets: IntTensor<Self>,
            run_of: IntTensor<Self>,
            rows: usize,
        ) -> FloatTensor<Self> {
            match RunsBackward.prepare::<C>([values.node()]).compute_bound().stateful() {
                OpsKind::Tracked(prep) => {
                    let out = B::sum_runs(values.into_primitive(), order, offsets, run_of.clone(), rows);
                    prep.finish(run_of, out)
                }
                OpsKind::UnTracked(prep) => {
                    prep.finish(B::sum_runs(values.into_primitive(), order, offsets, run_of, rows))
                }
            }
        }

        fn runs_of(starts: IntTensor<Self>, total: usize) -> IntTensor<Self> {
            B::runs_of(starts, total)
        }

        fn write_rows(
            tensor: FloatTensor<Self>,
            idx: IntTensor<Self>,
            values: FloatTensor<Self>,
            add: bool,
        ) -> FloatTensor<Self> {
            // An optimiser's write: never differentiated.
            let out = B::write_rows(tensor.into_primitive(), idx, values.into_primitive(), add);
            <Self as AutodiffBackend>::from_inner(out)
        }
    }
}

/// Against Burn's `select` and `select_assign`: what the test command runs on
/// wgpu (`cargo test --lib graph_oracle`), where the kernels above run.
#[cfg(test)]
mod graph_oracle {
    use burn::tensor::{IndexingUpdateOp, Tensor};

    use super::{RowIndex, gather_rows, write_rows};
    use crate::test_support::device;
    use crate::util::tensor::{assign_rows, floats, indices, is_host_memory, to_vec};

    /// A gather that reads rows several times, some not at all, and one
    /// row past the transpose (no gradient, as a padding row): the same
    /// values as `select`, and a gradient equal to `select`'s backward up to
    /// the summation order (1e-6 of the largest value), zero on the row left out.
    #[test]
    fn the_parallel_gather_backward_matches_select() {
        let dev = device();
        let (rows, cols) = (50, 7);
        let idx: Vec<i32> = (0..3000i32).map(|i| (i * 7919) % 61 % rows as i32).collect();
        let table: Vec<f32> = (0..rows * cols).map(|i| ((i * 37) % 23) as f32 / 23.0 - 0.4).collect();
        let weights =
            floats((0..idx.len() * cols).map(|i| ((i * 13) % 17) as f32 / 17.0).collect(), [idx.len(), cols], &dev);
        let run = |index: &RowIndex| {
            let x = floats(table.clone(), [rows, cols], &dev).autodiff().require_grad();
            let out = gather_rows(x.clone(), index);
            let grads = (out.clone() * weights.clone()).sum().backward();
            (to_vec(out), to_vec(x.grad(&grads).expect("the table has a gradient")))
        };
        // Row rows - 1 is left out of the transpose: it gets no gradient.
        let ours = RowIndex::new(idx.clone(), rows - 1, &dev);
        assert_eq!(ours.transpose.is_some(), !is_host_memory(&dev), "the transpose is built on a GPU only");
        let (out, grad) = run(&ours);
        let (want_out, want_grad) = run(&RowIndex::plain(indices(idx.clone(), &dev)));
        assert!(out == want_out, "the forward is select's");
        let last = (rows - 1) * cols;
        let scale = want_grad.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let worst = grad[..last].iter().zip(&want_grad[..last]).fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(worst <= 1e-6 * scale, "gradient off by {worst} of {scale}");
        if ours.transpose.is_some() {
            assert!(grad[last..].iter().all(|&g| g == 0.0), "the row left out has no gradient");
        }
        // The compact transpose, over an index that leaves two rows in three
        // unread (they get zeros): select's values and gradient again.
        let gappy: Vec<i32> = idx.iter().map(|r| r / 3 * 3).collect();
        let compact = RowIndex::compact(indices(gappy.clone(), &dev), &gappy);
        assert_eq!(compact.touched.is_some(), !is_host_memory(&dev), "the compact transpose is built on a GPU only");
        let (out, grad) = run(&compact);
        let (want_out, want_grad) = run(&RowIndex::plain(indices(gappy, &dev)));
        assert!(out == want_out, "the forward is select's");
        let worst = grad.iter().zip(&want_grad).fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(worst <= 1e-6 * scale, "compact: gradient off by {worst} of {scale}");
        assert!((0..rows).filter(|r| r % 3 != 0).all(|r| grad[r * cols..(r + 1) * cols].iter().all(|&g| g == 0.0)));
    }

    /// Sums over runs of consecutive rows (one empty): `select_assign`'s
    /// values to 1e-6, and the gradient of each row is its run's.
    #[test]
    fn sums_over_runs_match_select_assign_and_their_gradient_is_the_runs() {
        let dev = device();
        let starts = vec![0, 3, 3, 10, 11, 40];
        let run_of: Vec<i32> = (0..5).flat_map(|r| vec![r as i32; (starts[r + 1] - starts[r]) as usize]).collect();
        let n = run_of.len();
        let values: Vec<f32> = (0..n * 3).map(|i| ((i * 29) % 13) as f32 / 13.0).collect();
        let x = floats(values.clone(), [n, 3], &dev).autodiff().require_grad();
        let run_t = indices(run_of.clone(), &dev);
        let out = super::sum_runs(x.clone(), &run_t, &starts);
        let want = to_vec(assign_rows(
            Tensor::zeros([5, 3], &dev),
            run_t.clone(),
            floats(values, [n, 3], &dev),
            IndexingUpdateOp::Add,
        ));
        let got = to_vec(out.clone());
        assert!(got.iter().zip(&want).all(|(a, b)| (a - b).abs() <= 1e-6 * b.abs().max(1.0)), "sums differ");
        let w: Vec<f32> = (0..15).map(|i| i as f32).collect();
        let grads = (out * floats(w.clone(), [5, 3], &dev)).sum().backward();
        let g = to_vec(x.grad(&grads).expect("values have a gradient"));
        let expected: Vec<f32> = run_of.iter().flat_map(|&r| w[r as usize * 3..r as usize * 3 + 3].to_vec()).collect();
        assert!(g == expected, "each row's gradient is its run's");
    }

    /// Each row's run, empty runs included (on the CPU backends there is
    /// no kernel: `None`).
    #[test]
    fn each_row_finds_its_run() {
        let dev = device();
        let starts = vec![0, 2, 2, 2, 5, 6, 9];
        let Some(t) = super::runs_of(&starts, 9, &dev) else {
            assert!(is_host_memory(&dev), "a GPU has the kernel");
            return;
        };
        let got: Vec<i64> = t.into_data().convert::<i64>().try_to_vec::<i64>().expect("ints");
        assert_eq!(got, vec![0, 0, 3, 3, 3, 4, 5, 5, 5]);
    }

    /// Row writes and adds on distinct rows: `select_assign`'s values.
    #[test]
    fn parallel_row_writes_match_select_assign() {
        let dev = device();
        let (rows, cols) = (40, 5);
        let grid = floats((0..rows * cols).map(|i| i as f32 * 0.5).collect(), [rows, cols], &dev);
        let picked: Vec<i32> = vec![31, 2, 17, 0, 39, 8];
        let values: Tensor<2> =
            floats((0..picked.len() * cols).map(|i| 100.0 + i as f32).collect(), [picked.len(), cols], &dev);
        let idx = indices(picked, &dev);
        for op in [IndexingUpdateOp::Assign, IndexingUpdateOp::Add] {
            let ours = to_vec(write_rows(grid.clone(), &idx, values.clone(), op));
            let want = to_vec(assign_rows(grid.clone(), idx.clone(), values.clone(), op));
            assert!(ours == want, "{op:?} differs from select_assign");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_transpose_lists_each_rows_readers_in_order() {
        let (order, offsets) = transpose_of(&[2, 0, 2, 5, 1, 0], 3);
        assert_eq!(offsets, vec![0, 2, 3, 5], "row 5 is beyond the table and left out");
        assert_eq!(order, vec![1, 5, 4, 0, 2]);
    }

    #[test]
    fn the_compact_transpose_lists_only_the_rows_read() {
        let (touched, order, offsets) = compact_transpose_of(&[7, 0, 7, -1, 3, 0]);
        assert_eq!(touched, vec![0, 3, 7], "the negative entry is left out");
        assert_eq!(offsets, vec![0, 2, 3, 5]);
        assert_eq!(order, vec![1, 5, 4, 0, 2]);
        assert_eq!(compact_transpose_of(&[]), (vec![], vec![], vec![0]));
    }
}
