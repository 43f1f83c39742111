//! Reading and adding to chosen rows of a grid-sized 2-D tensor, in
//! parallel and in place on flex: the lazy optimisers' row gathers and
//! row updates (`field::optim`).
//!
//! Burn's `select` and `select_assign` are serial loops on flex (its
//! `select_update_2d`), and a step's rows are spread over a tensor of
//! hundreds of MB (fern's fine grid: about 400,000 rows of 27 SH
//! coefficients, out of 5.5 M), so each row costs a cache miss and the
//! loop waits on memory one row at a time: 35 ms per update of the SH on
//! fern, four of them a step. Here the rows are split over threads.
//!
//! A backend extension trait (as `vgg::conv_op`): flex implements it on its
//! storage; ndarray implements it with Burn's own operations; wgpu (and any
//! other backend) never gets here, since the callers check
//! `is_host_memory` first and use `select` / `select_assign` otherwise.

// NdArray is deprecated upstream and stays a supported backend here; the
// code the extension macro generates names it too.
#![allow(deprecated)]

use burn::tensor::{IndexingUpdateOp, Int, Tensor};

#[cfg(any(feature = "flex", feature = "ndarray"))]
use crate::util::tensor::is_host_memory;
use crate::util::tensor::{assign_rows, select_rows, to_vec};

#[cfg(any(feature = "flex", feature = "ndarray"))]
mod host_op {
    #[cfg(feature = "flex")]
    use burn::backend::DType;
    #[cfg(feature = "flex")]
    use burn::backend::Flex;
    #[cfg(feature = "ndarray")]
    use burn::backend::NdArray;
    use burn::backend::tensor::FloatTensor;
    use burn::backend::{Backend, TensorMetadata, backend_extension};

    /// Row gathers and row adds on a CPU backend's 2-D float tensor.
    #[cfg_attr(all(feature = "flex", feature = "ndarray"), backend_extension(Flex, NdArray))]
    #[cfg_attr(all(feature = "flex", not(feature = "ndarray")), backend_extension(Flex))]
    #[cfg_attr(all(not(feature = "flex"), feature = "ndarray"), backend_extension(NdArray))]
    pub trait RowsBackend: Backend {
        /// `tensor`'s rows `rows`, in that order, as a `[rows.len(), cols]` tensor.
        fn gather_rows(tensor: FloatTensor<Self>, rows: &[i32]) -> FloatTensor<Self>;
        /// `tensor` with `values` (`[rows.len(), cols]`) added to its rows
        /// `rows` (a repeated row gets each addition, in order).
        fn add_to_rows(tensor: FloatTensor<Self>, rows: &[i32], values: FloatTensor<Self>) -> FloatTensor<Self>;
    }

    #[cfg(feature = "flex")]
    impl RowsBackend for Flex {
        fn gather_rows(tensor: FloatTensor<Self>, rows: &[i32]) -> FloatTensor<Self> {
            if !(tensor.dtype() == DType::F32 && tensor.is_contiguous()) {
                return generic_gather::<Self>(tensor, rows);
            }
            let cols = tensor.shape()[1];
            let (start, len) = (tensor.layout().start_offset(), tensor.layout().num_elements());
            let out = super::kernel::gather(&tensor.storage::<f32>()[start..start + len], cols, rows);
            from_values::<Self>(out, [rows.len(), cols], &tensor.device())
        }

        fn add_to_rows(tensor: FloatTensor<Self>, rows: &[i32], values: FloatTensor<Self>) -> FloatTensor<Self> {
            let mut tensor = tensor;
            let cols = tensor.shape()[1];
            let in_place =
                tensor.dtype() == DType::F32 && tensor.is_unique() && tensor.layout().is_dense_unique_storage();
            let values_f32 = values.dtype() == DType::F32 && values.is_contiguous();
            if !(in_place && values_f32) {
                return generic_add::<Self>(tensor, rows, values);
            }
            let (start, len) = (tensor.layout().start_offset(), tensor.layout().num_elements());
            let offset = values.layout().start_offset();
            let values = &values.storage::<f32>()[offset..offset + rows.len() * cols];
            super::kernel::add(&mut tensor.storage_mut::<f32>()[start..start + len], cols, rows, values);
            tensor
        }
    }

    #[cfg(feature = "ndarray")]
    impl RowsBackend for NdArray {
        fn gather_rows(tensor: FloatTensor<Self>, rows: &[i32]) -> FloatTensor<Self> {
            generic_gather::<Self>(tensor, rows)
        }

        fn add_to_rows(tensor: FloatTensor<Self>, rows: &[i32], values: FloatTensor<Self>) -> FloatTensor<Self> {
            generic_add::<Self>(tensor, rows, values)
        }
    }

    fn row_indices<B: Backend>(rows: &[i32], device: &B::Device) -> burn::backend::tensor::IntTensor<B> {
        B::int_from_data(burn::tensor::TensorData::new(rows.to_vec(), [rows.len()]), device)
    }

    /// Burn's own `select`, for what the fast path does not cover.
    fn generic_gather<B: Backend>(tensor: FloatTensor<B>, rows: &[i32]) -> FloatTensor<B> {
        let device = tensor.device();
        B::float_select(tensor, 0, row_indices::<B>(rows, &device))
    }

    /// Burn's own `select_assign` with `Add`.
    fn generic_add<B: Backend>(tensor: FloatTensor<B>, rows: &[i32], values: FloatTensor<B>) -> FloatTensor<B> {
        let device = tensor.device();
        let op = burn::tensor::IndexingUpdateOp::Add;
        B::float_select_assign(tensor, 0, row_indices::<B>(rows, &device), values, op)
    }

    #[cfg(feature = "flex")]
    fn from_values<B: Backend>(values: Vec<f32>, shape: [usize; 2], device: &B::Device) -> FloatTensor<B> {
        B::float_from_data(burn::tensor::TensorData::new(values, shape), device)
    }
}

#[cfg(any(feature = "flex", feature = "ndarray"))]
pub use host_op::RowsBackend;

/// The loops on host slices.
mod kernel {
    use rayon::prelude::*;

    /// Rows per parallel piece of a gather (pieces write disjoint output rows).
    const GATHER_PIECE: usize = 4096;
    /// Pieces of the destination an add is split into: each scans every
    /// index and applies those in its own range of rows, so the pieces
    /// write disjoint memory, a repeated row gets its additions in order,
    /// and the result does not depend on the thread count.
    const ADD_PIECES: usize = 16;

    /// Rows `rows` of a `[n, cols]` slice.
    pub fn gather(source: &[f32], cols: usize, rows: &[i32]) -> Vec<f32> {
        let n = source.len() / cols.max(1);
        let mut out = vec![0.0f32; rows.len() * cols];
        out.par_chunks_mut(GATHER_PIECE * cols.max(1)).enumerate().for_each(|(p, piece)| {
            for (dst, &r) in piece.chunks_exact_mut(cols).zip(&rows[p * GATHER_PIECE..]) {
                let r = checked(r, n);
                dst.copy_from_slice(&source[r * cols..(r + 1) * cols]);
            }
        });
        out
    }

    /// Adds `values` (`[rows.len(), cols]`) to rows `rows` of `target` (`[n, cols]`).
    pub fn add(target: &mut [f32], cols: usize, rows: &[i32], values: &[f32]) {
        let n = target.len() / cols.max(1);
        assert_eq!(values.len(), rows.len() * cols, "one row of values per index");
        for &r in rows {
            checked(r, n);
        }
        let rows_per_piece = n.div_ceil(ADD_PIECES).max(1);
        target.par_chunks_mut(rows_per_piece * cols.max(1)).enumerate().for_each(|(p, piece)| {
            let first = p * rows_per_piece;
            let range = first..first + piece.len() / cols.max(1);
            for (k, &r) in rows.iter().enumerate() {
                let r = r as usize;
                if range.contains(&r) {
                    let at = (r - first) * cols;
                    let src = &values[k * cols..(k + 1) * cols];
                    piece[at..at + cols].iter_mut().zip(src).for_each(|(a, b)| *a += b);
                }
            }
        });
    }

    fn checked(r: i32, n: usize) -> usize {
        assert!(r >= 0 && (r as usize) < n, "row {r} out of range for {n} rows");
        r as usize
    }
}

/// Rows `rows` of `tensor`, in that order (`rows_t` holds the same indices
/// as a tensor, for the backends that gather through Burn's `select`).
pub fn gather_rows(tensor: &Tensor<2>, rows: &[i32], rows_t: &Tensor<1, Int>) -> Tensor<2> {
    #[cfg(any(feature = "flex", feature = "ndarray"))]
    if is_host_memory(&tensor.device()) {
        let out = <burn::backend::Dispatch as RowsBackend>::gather_rows(tensor.clone().into_dispatch(), rows);
        return Tensor::from_dispatch(out);
    }
    let _ = rows;
    select_rows(tensor.clone(), rows_t.clone())
}

/// [`gather_rows`] as host values (`[rows.len(), cols]`, row-major).
pub fn read_rows(tensor: &Tensor<2>, rows: &[i32], rows_t: &Tensor<1, Int>) -> Vec<f32> {
    to_vec(gather_rows(tensor, rows, rows_t))
}

/// `tensor` with `values` added to its rows `rows` (`rows_t` the same
/// indices as a tensor). In place when `tensor` is uniquely owned.
pub fn add_to_rows(tensor: Tensor<2>, rows: &[i32], rows_t: &Tensor<1, Int>, values: Tensor<2>) -> Tensor<2> {
    #[cfg(any(feature = "flex", feature = "ndarray"))]
    if is_host_memory(&tensor.device()) {
        let out =
            <burn::backend::Dispatch as RowsBackend>::add_to_rows(tensor.into_dispatch(), rows, values.into_dispatch());
        return Tensor::from_dispatch(out);
    }
    let _ = rows;
    assign_rows(tensor, rows_t.clone(), values, IndexingUpdateOp::Add)
}

#[cfg(test)]
mod tests {
    use super::kernel;

    #[test]
    fn gather_and_add_on_host_slices_match_the_definition() {
        let (n, cols) = (1000, 3);
        let source: Vec<f32> = (0..n * cols).map(|i| i as f32).collect();
        let rows: Vec<i32> = (0..9000).map(|i| ((i * 7919) % n) as i32).collect();
        let out = kernel::gather(&source, cols, &rows);
        for (k, &r) in rows.iter().enumerate() {
            assert_eq!(&out[k * cols..(k + 1) * cols], &source[r as usize * cols..(r as usize + 1) * cols]);
        }
        // Repeated rows (9000 indices into 1000 rows) get every addition.
        let values: Vec<f32> = (0..rows.len() * cols).map(|i| (i % 13) as f32 * 0.5).collect();
        let mut fast = source.clone();
        kernel::add(&mut fast, cols, &rows, &values);
        let mut slow = source;
        for (k, &r) in rows.iter().enumerate() {
            for c in 0..cols {
                slow[r as usize * cols + c] += values[k * cols + c];
            }
        }
        assert_eq!(fast, slow);
    }

    #[test]
    #[should_panic(expected = "out of range")]
    fn an_index_past_the_end_is_refused() {
        kernel::add(&mut [0.0; 6], 3, &[2], &[1.0; 3]);
    }
}
