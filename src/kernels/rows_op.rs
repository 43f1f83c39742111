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
//! A backend extension trait (as `kernels::conv_op`): flex implements it on its
//! storage; ndarray implements it with Burn's own operations; wgpu (and any
//! other backend) never gets here, since the callers check
//! `is_host_memory` first and use `select` / `select_assign` otherwise.

// NdArray is deprecated upstream and stays a supported backend here; the
// code the extension macro generates names it too.
#![allow(deprecated)]

use burn::tensor::{IndexingUpdateOp, Int, Tensor};

use crate::kernels::gather_op::write_rows;
#[cfg(any(feature = "flex", feature = "ndarray"))]
use crate::util::tensor::is_host_memory;
use crate::util::tensor::{select_rows, to_vec};

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
        /// Writes `tensor`'s rows `rows`, in that order, into `out`
        /// (`[rows.len(), cols]`): a gather into a buffer the caller keeps.
        /// Returns the number of values written (extension operations
        /// return a value).
        fn read_rows_into(tensor: &FloatTensor<Self>, rows: &[i32], out: &mut [f32]) -> usize;
        /// Writes all of `tensor`'s values (row-major) into `out`, a buffer
        /// of exactly that length. Returns the number of values written.
        fn read_all_into(tensor: &FloatTensor<Self>, out: &mut [f32]) -> usize;
        /// `a` and `b` (two tensors of the same shape) after `update(k, a_row,
        /// b_row)` on their rows `rows[k]`, for every `k` (a repeated row
        /// gets each update, in order).
        fn update_row_pairs(
            a: FloatTensor<Self>,
            b: FloatTensor<Self>,
            rows: &[i32],
            update: &super::RowPairUpdate,
        ) -> (FloatTensor<Self>, FloatTensor<Self>);
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
            let in_place = writable_in_place(&tensor);
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

        fn read_rows_into(tensor: &FloatTensor<Self>, rows: &[i32], out: &mut [f32]) -> usize {
            if !(tensor.dtype() == DType::F32 && tensor.is_contiguous()) {
                return generic_read_into::<Self>(tensor, rows, out);
            }
            let cols = tensor.shape()[1];
            let (start, len) = (tensor.layout().start_offset(), tensor.layout().num_elements());
            super::kernel::gather_into(&tensor.storage::<f32>()[start..start + len], cols, rows, out);
            out.len()
        }

        fn read_all_into(tensor: &FloatTensor<Self>, out: &mut [f32]) -> usize {
            if !(tensor.dtype() == DType::F32 && tensor.is_contiguous()) {
                out.copy_from_slice(&host_values::<Self>(tensor.clone()));
                return out.len();
            }
            let start = tensor.layout().start_offset();
            out.copy_from_slice(&tensor.storage::<f32>()[start..start + out.len()]);
            out.len()
        }

        fn update_row_pairs(
            a: FloatTensor<Self>,
            b: FloatTensor<Self>,
            rows: &[i32],
            update: &super::RowPairUpdate,
        ) -> (FloatTensor<Self>, FloatTensor<Self>) {
            if !(writable_in_place(&a) && writable_in_place(&b) && a.shape() == b.shape()) {
                return generic_update_pairs::<Self>(a, b, rows, update);
            }
            let (mut a, mut b) = (a, b);
            let cols = a.shape()[1];
            let (start_a, len) = (a.layout().start_offset(), a.layout().num_elements());
            let start_b = b.layout().start_offset();
            super::kernel::update_pairs(
                &mut a.storage_mut::<f32>()[start_a..start_a + len],
                &mut b.storage_mut::<f32>()[start_b..start_b + len],
                cols,
                rows,
                update,
            );
            (a, b)
        }
    }

    /// Whether flex's tensor is f32 and its storage ours alone, so that its
    /// rows can be written in place.
    #[cfg(feature = "flex")]
    fn writable_in_place(t: &FloatTensor<Flex>) -> bool {
        t.dtype() == DType::F32 && t.is_unique() && t.layout().is_dense_unique_storage()
    }

    #[cfg(feature = "ndarray")]
    impl RowsBackend for NdArray {
        fn gather_rows(tensor: FloatTensor<Self>, rows: &[i32]) -> FloatTensor<Self> {
            generic_gather::<Self>(tensor, rows)
        }

        fn add_to_rows(tensor: FloatTensor<Self>, rows: &[i32], values: FloatTensor<Self>) -> FloatTensor<Self> {
            generic_add::<Self>(tensor, rows, values)
        }

        fn read_rows_into(tensor: &FloatTensor<Self>, rows: &[i32], out: &mut [f32]) -> usize {
            generic_read_into::<Self>(tensor, rows, out)
        }

        fn read_all_into(tensor: &FloatTensor<Self>, out: &mut [f32]) -> usize {
            out.copy_from_slice(&host_values::<Self>(tensor.clone()));
            out.len()
        }

        fn update_row_pairs(
            a: FloatTensor<Self>,
            b: FloatTensor<Self>,
            rows: &[i32],
            update: &super::RowPairUpdate,
        ) -> (FloatTensor<Self>, FloatTensor<Self>) {
            generic_update_pairs::<Self>(a, b, rows, update)
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

    /// A CPU backend's tensor as f32 values.
    fn host_values<B: Backend>(tensor: FloatTensor<B>) -> Vec<f32> {
        let data = burn::tensor::read_sync(B::float_into_data(tensor)).expect("reading a CPU backend's tensor");
        data.convert::<f32>().try_into_vec::<f32>().expect("f32 values after conversion")
    }

    /// Burn's own `select`, read into `out`.
    fn generic_read_into<B: Backend>(tensor: &FloatTensor<B>, rows: &[i32], out: &mut [f32]) -> usize {
        out.copy_from_slice(&host_values::<B>(generic_gather::<B>(tensor.clone(), rows)));
        out.len()
    }

    /// The rows read out, updated on the host and written back with Burn's
    /// `select_assign` (`Assign`).
    fn generic_update_pairs<B: Backend>(
        a: FloatTensor<B>,
        b: FloatTensor<B>,
        rows: &[i32],
        update: &super::RowPairUpdate,
    ) -> (FloatTensor<B>, FloatTensor<B>) {
        let device = a.device();
        let cols = a.shape()[1];
        assert_eq!(a.shape(), b.shape(), "row pairs of two tensors of one shape");
        let mut va = host_values::<B>(generic_gather::<B>(a.clone(), rows));
        let mut vb = host_values::<B>(generic_gather::<B>(b.clone(), rows));
        for (k, (ra, rb)) in va.chunks_exact_mut(cols.max(1)).zip(vb.chunks_exact_mut(cols.max(1))).enumerate() {
            update(k, ra, rb);
        }
        let assign = |t: FloatTensor<B>, values: Vec<f32>| {
            let values = B::float_from_data(burn::tensor::TensorData::new(values, [rows.len(), cols]), &device);
            B::float_select_assign(
                t,
                0,
                row_indices::<B>(rows, &device),
                values,
                burn::tensor::IndexingUpdateOp::Assign,
            )
        };
        (assign(a, va), assign(b, vb))
    }

    #[cfg(feature = "flex")]
    fn from_values<B: Backend>(values: Vec<f32>, shape: [usize; 2], device: &B::Device) -> FloatTensor<B> {
        B::float_from_data(burn::tensor::TensorData::new(values, shape), device)
    }
}

#[cfg(any(feature = "flex", feature = "ndarray"))]
pub use host_op::RowsBackend;
pub(crate) use kernel::{PREFETCH_AHEAD, prefetch_row};

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
        let mut out = vec![0.0f32; rows.len() * cols];
        gather_into(source, cols, rows, &mut out);
        out
    }

    /// Rows `rows` of a `[n, cols]` slice, written into `out` (`[rows.len(), cols]`).
    pub fn gather_into(source: &[f32], cols: usize, rows: &[i32], out: &mut [f32]) {
        let n = source.len() / cols.max(1);
        assert_eq!(out.len(), rows.len() * cols, "one output row per index");
        out.par_chunks_mut(GATHER_PIECE * cols.max(1)).enumerate().for_each(|(p, piece)| {
            let rows = &rows[p * GATHER_PIECE..];
            for (i, dst) in piece.chunks_exact_mut(cols).enumerate() {
                if let Some(&ahead) = rows.get(i + PREFETCH_AHEAD) {
                    prefetch_row(source, checked(ahead, n), cols);
                }
                let r = checked(rows[i], n);
                dst.copy_from_slice(&source[r * cols..(r + 1) * cols]);
            }
        });
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

    /// `update(k, a_row, b_row)` on rows `rows[k]` of `a` and `b` (both
    /// `[n, cols]`), in place. Split as [`add`]: each piece of rows gets the
    /// indices in its range, in their order (bucketed once, not scanned
    /// per piece). The bucketing runs in parallel too: each of
    /// `BUCKET_CHUNKS` chunks of the index list sorts its own indices into
    /// the pieces, and a piece takes the chunks' lists in chunk order, so
    /// it sees its indices in the order of a serial pass (on fern's
    /// density, one value a row, the serial pass was most of the update).
    pub fn update_pairs(a: &mut [f32], b: &mut [f32], cols: usize, rows: &[i32], update: &super::RowPairUpdate) {
        const BUCKET_CHUNKS: usize = 16;
        let n = a.len() / cols.max(1);
        assert_eq!(a.len(), b.len(), "row pairs of two tensors of one shape");
        let rows_per_piece = n.div_ceil(ADD_PIECES).max(1);
        let pieces = n.div_ceil(rows_per_piece);
        let chunk = rows.len().div_ceil(BUCKET_CHUNKS).max(1);
        let chunk_buckets: Vec<Vec<Vec<u32>>> = rows
            .par_chunks(chunk)
            .enumerate()
            .map(|(c, part)| {
                let mut buckets = vec![Vec::new(); pieces];
                for (i, &r) in part.iter().enumerate() {
                    buckets[checked(r, n) / rows_per_piece].push((c * chunk + i) as u32);
                }
                buckets
            })
            .collect();
        let piece = rows_per_piece * cols.max(1);
        a.par_chunks_mut(piece).zip(b.par_chunks_mut(piece)).enumerate().for_each(|(p, (pa, pb))| {
            let ks: Vec<u32> = chunk_buckets.iter().flat_map(|buckets| buckets[p].iter().copied()).collect();
            let first = p * rows_per_piece;
            for (i, &k) in ks.iter().enumerate() {
                if let Some(&ahead) = ks.get(i + PREFETCH_AHEAD) {
                    let row = rows[ahead as usize] as usize - first;
                    prefetch_row(pa, row, cols);
                    prefetch_row(pb, row, cols);
                }
                let at = (rows[k as usize] as usize - first) * cols;
                update(k as usize, &mut pa[at..at + cols], &mut pb[at..at + cols]);
            }
        });
    }

    /// How many rows ahead the loops above ask for a row: the step's rows
    /// are scattered over a tensor of hundreds of MB, each a cache miss,
    /// and a loop that reads one row at a time waits on each in turn.
    pub const PREFETCH_AHEAD: usize = 8;

    /// A hint to start loading row `row` (`cols` values) of `data` into
    /// the cache; changes no value. A row of 27 SH coefficients spans two
    /// or three cache lines.
    #[inline(always)]
    pub fn prefetch_row<T>(data: &[T], row: usize, cols: usize) {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
            let line = (64 / size_of::<T>()).max(1);
            let (start, end) = (row * cols, ((row + 1) * cols).min(data.len()));
            let mut at = start - start % line;
            while at < end {
                // SAFETY: SSE is part of x86_64's baseline, and a prefetch
                // of an address inside `data` only warms the cache.
                unsafe { _mm_prefetch::<_MM_HINT_T0>(data[at..].as_ptr().cast()) };
                at += line;
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = (data, row, cols);
    }

    fn checked(r: i32, n: usize) -> usize {
        assert!(r >= 0 && (r as usize) < n, "row {r} out of range for {n} rows");
        r as usize
    }
}

/// What [`update_row_pairs`] does to one row pair: `(k, a_row, b_row)`,
/// `k` the row's position in the index list.
pub type RowPairUpdate<'a> = dyn Fn(usize, &mut [f32], &mut [f32]) + Sync + 'a;

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

/// [`read_rows`] into `out` (resized to `[rows.len(), cols]`), a buffer the
/// caller keeps from step to step: on fern's fine grid a fresh one is tens
/// of MB of page faults a step. What `out` held is not zeroed first: every
/// value is overwritten, and zeroing it was a serial pass over as many
/// bytes as the gather writes (76 MB a fern step).
pub fn read_rows_into(tensor: &Tensor<2>, rows: &[i32], rows_t: &Tensor<1, Int>, out: &mut Vec<f32>) {
    let len = rows.len() * tensor.dims()[1];
    out.truncate(len);
    out.resize(len, 0.0);
    #[cfg(any(feature = "flex", feature = "ndarray"))]
    if is_host_memory(&tensor.device()) {
        let t = tensor.clone().into_dispatch();
        <burn::backend::Dispatch as RowsBackend>::read_rows_into(&t, rows, out);
        return;
    }
    out.copy_from_slice(&read_rows(tensor, rows, rows_t));
}

/// All of `tensor`'s values (row-major) into `out` (resized to fit), a
/// buffer the caller keeps from step to step: a fresh grid-sized copy each
/// step (the host ray passes read the whole SH grid) is tens of MB of page
/// faults on a 384³ field.
pub fn read_all_into(tensor: &Tensor<2>, out: &mut Vec<f32>) {
    let len = tensor.dims().iter().product();
    out.truncate(len);
    out.resize(len, 0.0);
    #[cfg(any(feature = "flex", feature = "ndarray"))]
    if is_host_memory(&tensor.device()) {
        let t = tensor.clone().into_dispatch();
        <burn::backend::Dispatch as RowsBackend>::read_all_into(&t, out);
        return;
    }
    out.copy_from_slice(&to_vec(tensor.clone()));
}

/// Calls `f` with `tensor`'s values (row-major) in blocks of whole rows,
/// about `block_values` values each, in order, through one buffer reused
/// from block to block: reading out a grid-sized tensor (a checkpoint save)
/// without a grid-sized copy. Stops at `f`'s first error.
pub fn for_each_row_block<E>(
    tensor: &Tensor<2>,
    block_values: usize,
    mut f: impl FnMut(&[f32]) -> Result<(), E>,
) -> Result<(), E> {
    let [num_rows, cols] = tensor.dims();
    let blocks = crate::util::chunk_ranges(num_rows, (block_values / cols.max(1)).max(1));
    #[cfg(any(feature = "flex", feature = "ndarray"))]
    if is_host_memory(&tensor.device()) {
        let t = tensor.clone().into_dispatch();
        let (mut rows, mut values) = (Vec::new(), Vec::new());
        for (start, len) in blocks {
            rows.clear();
            rows.extend(start as i32..(start + len) as i32);
            values.truncate(len * cols);
            values.resize(len * cols, 0.0);
            <burn::backend::Dispatch as RowsBackend>::read_rows_into(&t, &rows, &mut values);
            f(&values)?;
        }
        return Ok(());
    }
    for (start, len) in blocks {
        f(&to_vec(tensor.clone().narrow(0, start, len)))?;
    }
    Ok(())
}

/// Applies `update(k, a_row, b_row)` to rows `rows[k]` of `a` and `b` (two
/// tensors of one shape; `rows_t` the same indices as a tensor): in place
/// and in parallel on flex, by reading the rows out and writing them back
/// elsewhere (there the rows must be distinct). The optimisers' fused row
/// step: one pass over the rows of a parameter and its running average
/// instead of a gather and two row-adds.
pub fn update_row_pairs(
    a: &mut Tensor<2>,
    b: &mut Tensor<2>,
    rows: &[i32],
    rows_t: &Tensor<1, Int>,
    update: &RowPairUpdate,
) {
    let device = a.device();
    let placeholder = || Tensor::<2>::zeros([1, 1], &device);
    let (ta, tb) = (std::mem::replace(a, placeholder()), std::mem::replace(b, placeholder()));
    #[cfg(any(feature = "flex", feature = "ndarray"))]
    if is_host_memory(&device) {
        let (ra, rb) = <burn::backend::Dispatch as RowsBackend>::update_row_pairs(
            ta.into_dispatch(),
            tb.into_dispatch(),
            rows,
            update,
        );
        (*a, *b) = (Tensor::from_dispatch(ra), Tensor::from_dispatch(rb));
        return;
    }
    let cols = ta.dims()[1];
    let (mut va, mut vb) = (read_rows(&ta, rows, rows_t), read_rows(&tb, rows, rows_t));
    for (k, (ra, rb)) in va.chunks_exact_mut(cols.max(1)).zip(vb.chunks_exact_mut(cols.max(1))).enumerate() {
        update(k, ra, rb);
    }
    let values = |v: Vec<f32>| Tensor::<2>::from_data(burn::tensor::TensorData::new(v, [rows.len(), cols]), &device);
    *a = write_rows(ta, rows_t, values(va), IndexingUpdateOp::Assign);
    *b = write_rows(tb, rows_t, values(vb), IndexingUpdateOp::Assign);
}

/// `tensor` with `values` added to its rows `rows` (`rows_t` the same
/// indices as a tensor). In place when `tensor` is uniquely owned. On a GPU
/// the rows must be distinct (`kernels::gather_op::write_rows`), as an
/// optimiser step's are.
pub fn add_to_rows(tensor: Tensor<2>, rows: &[i32], rows_t: &Tensor<1, Int>, values: Tensor<2>) -> Tensor<2> {
    #[cfg(any(feature = "flex", feature = "ndarray"))]
    if is_host_memory(&tensor.device()) {
        let out =
            <burn::backend::Dispatch as RowsBackend>::add_to_rows(tensor.into_dispatch(), rows, values.into_dispatch());
        return Tensor::from_dispatch(out);
    }
    let _ = rows;
    write_rows(tensor, rows_t, values, IndexingUpdateOp::Add)
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
    fn row_pair_updates_on_host_slices_match_the_definition() {
        let (n, cols) = (1000, 3);
        let a0: Vec<f32> = (0..n * cols).map(|i| i as f32).collect();
        let b0: Vec<f32> = (0..n * cols).map(|i| (i % 17) as f32).collect();
        // Repeated rows (3000 indices into 1000 rows) get every update, in order.
        let rows: Vec<i32> = (0..3000).map(|i| ((i * 7919) % n) as i32).collect();
        let update = |k: usize, a: &mut [f32], b: &mut [f32]| {
            for (x, y) in a.iter_mut().zip(b.iter_mut()) {
                (*x, *y) = (*x * 0.5 + *y + k as f32, *y - 1.0);
            }
        };
        let (mut fast_a, mut fast_b) = (a0.clone(), b0.clone());
        kernel::update_pairs(&mut fast_a, &mut fast_b, cols, &rows, &update);
        let (mut slow_a, mut slow_b) = (a0, b0);
        for (k, &r) in rows.iter().enumerate() {
            let at = r as usize * cols..(r as usize + 1) * cols;
            update(k, &mut slow_a[at.clone()], &mut slow_b[at]);
        }
        assert_eq!((fast_a, fast_b), (slow_a, slow_b));
    }

    #[test]
    #[should_panic(expected = "out of range")]
    fn an_index_past_the_end_is_refused() {
        kernel::add(&mut [0.0; 6], 3, &[2], &[1.0; 3]);
    }
}

/// Checked against the Burn graph and autodiff, on every backend the test
/// command runs (`cargo test --lib graph_oracle`).
#[cfg(test)]
#[allow(clippy::print_stdout, clippy::print_stderr)] // the measured errors, shown with --nocapture
mod graph_oracle {
    use crate::test_support::device;
    use crate::util::tensor::{floats, to_vec};

    /// The optimisers' row gathers and row adds (`kernels::rows_op`: parallel and
    /// in place on flex, Burn's `select` / `select_assign` elsewhere) give what
    /// Burn's own operations give, repeated rows included (distinct rows for
    /// a GPU's add), on every backend.
    #[test]
    fn row_gathers_and_adds_match_select_and_select_assign() {
        use crate::kernels::rows_op::{add_to_rows, gather_rows, read_all_into, read_rows_into};
        use crate::util::tensor::{assign_rows, indices, select_rows};
        let d = device();
        let (n, cols) = (5000, 7);
        let grid = floats((0..n * cols).map(|i| (i % 97) as f32 * 0.25).collect(), [n, cols], &d);
        let rows: Vec<i32> = (0..12_000).map(|i| ((i * 7919) % n) as i32).collect();
        let rows_t = indices(rows.clone(), &d);
        let ours = to_vec(gather_rows(&grid, &rows, &rows_t));
        assert_eq!(ours, to_vec(select_rows(grid.clone(), rows_t.clone())), "gather");
        let mut kept = vec![9.0; 3];
        read_rows_into(&grid, &rows, &rows_t, &mut kept);
        assert_eq!(kept, ours, "gather into a kept buffer");
        // A view that starts inside its storage: the copy starts there too.
        let tail = grid.clone().slice([1..n, 0..cols]);
        read_all_into(&tail, &mut kept);
        assert_eq!(kept, to_vec(tail), "all values into a kept buffer");
        // Adds to repeated rows on the CPU backends; a GPU's add needs
        // distinct rows (`add_to_rows`; repeats would race), as an
        // optimiser step's are.
        let rows = match crate::util::tensor::is_host_memory(&d) {
            true => rows,
            false => (0..n as i32).rev().step_by(3).collect(),
        };
        let rows_t = indices(rows.clone(), &d);
        let values = floats((0..rows.len() * cols).map(|i| (i % 13) as f32 - 6.0).collect(), [rows.len(), cols], &d);
        let expected =
            to_vec(assign_rows(grid.clone(), rows_t.clone(), values.clone(), burn::tensor::IndexingUpdateOp::Add));
        // A copy of the grid, so the in-place add has it to itself.
        let own = floats(to_vec(grid), [n, cols], &d);
        assert_eq!(to_vec(add_to_rows(own, &rows, &rows_t, values)), expected, "add");
    }
}
