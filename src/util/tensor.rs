//! Small conversions between plain Rust buffers and Burn tensors: the one
//! place the library moves values between host and device (each move is
//! counted by `util::transfer`).

use burn::tensor::kind::Basic;
use burn::tensor::{Device, IndexingUpdateOp, Int, Tensor, TensorData};

use crate::util::transfer;

/// Bytes a tensor's values take (its element count times its element size).
pub fn tensor_bytes<const D: usize, K: Basic>(t: &Tensor<D, K>) -> usize {
    t.shape().num_elements() * t.dtype().size()
}

/// A float tensor of the given shape from a flat row-major buffer.
pub fn floats<const D: usize>(values: Vec<f32>, shape: [usize; D], device: &Device) -> Tensor<D> {
    transfer::record_upload(values.len() * 4);
    Tensor::from_data(TensorData::new(values, shape), device)
}

/// A 1-D index tensor.
pub fn indices(values: Vec<i32>, device: &Device) -> Tensor<1, Int> {
    let n = values.len();
    transfer::record_upload(n * 4);
    Tensor::from_data(TensorData::new(values, [n]), device)
}

/// The tensor's values as a flat `Vec<f32>` (row-major).
pub fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    transfer::record_read(t.shape().num_elements() * 4);
    t.into_data().convert::<f32>().try_into_vec::<f32>().expect("float tensor data converts to f32")
}

/// A scalar float tensor's value.
pub fn scalar(t: Tensor<1>) -> f32 {
    to_vec(t)[0]
}

/// The most indices one `select_assign` is given. Burn 0.22.1's wgpu
/// `select_assign` applies only the first 65535 indices and drops the rest
/// (measured: a gradient of 140000 gathered rows sums to 65535 of them), and
/// it is also the backward of `select`; pieces below that are exact everywhere.
pub const INDEX_PIECE: usize = 1 << 15;

/// Whether long index lists must be cut into pieces on this device: the
/// bug is in the cubecl (GPU) kernels; the CPU backends (which report no
/// device identity) take any length in one call, which on a large grid
/// saves one full-size gradient buffer per piece.
fn needs_pieces(device: &Device) -> bool {
    !is_host_memory(device)
}

/// Whether the device's tensors live in host memory (the CPU backends,
/// which report no device identity): a copy "on the device" is then a
/// second copy in RAM.
pub fn is_host_memory(device: &Device) -> bool {
    // `Device::identity` exists only in builds with a cubecl (GPU) backend;
    // without one every device is a CPU backend's.
    #[cfg(feature = "wgpu")]
    return device.identity().is_none();
    #[cfg(not(feature = "wgpu"))]
    {
        let _ = device;
        true
    }
}

/// `x.select(0, idx)` whose backward stays exact on wgpu: long index lists
/// are gathered in pieces and concatenated (each piece's backward is a
/// `select_assign` of at most `INDEX_PIECE` indices). Index tensors are
/// gathered in the same pieces (burn-cubecl 0.22.1 has two kernels known
/// to stop at 65535 elements, `select_assign` and `cumsum`; `select` is
/// not shown to, and is kept within the bound all the same).
pub fn select_rows<const D: usize, K: Basic>(x: Tensor<D, K>, idx: Tensor<1, Int>) -> Tensor<D, K> {
    let n = idx.dims()[0];
    if n <= INDEX_PIECE || !needs_pieces(&x.device()) {
        return x.select(0, idx);
    }
    let pieces = (0..n)
        .step_by(INDEX_PIECE)
        .map(|s| x.clone().select(0, idx.clone().narrow(0, s, INDEX_PIECE.min(n - s))))
        .collect();
    Tensor::cat(pieces, 0)
}

/// `x.cumsum(0)` of a column `[n, 1]`, exact on wgpu: burn-cubecl 0.22.1's
/// cumsum stops at 65535 elements there (measured on lavapipe: a cumsum of
/// 70,000 ones ends at 65535), so it runs in pieces, each carrying the
/// previous piece's last sum.
pub fn cumsum_rows(x: Tensor<2>) -> Tensor<2> {
    let n = x.dims()[0];
    if n <= INDEX_PIECE || !needs_pieces(&x.device()) {
        return x.cumsum(0);
    }
    let mut pieces: Vec<Tensor<2>> = Vec::new();
    for s in (0..n).step_by(INDEX_PIECE) {
        let mut piece = x.clone().narrow(0, s, INDEX_PIECE.min(n - s)).cumsum(0);
        if let Some(previous) = pieces.last() {
            let len = previous.dims()[0];
            piece = piece + previous.clone().narrow(0, len - 1, 1);
        }
        pieces.push(piece);
    }
    Tensor::cat(pieces, 0)
}

/// `target.select_assign(0, idx, values, op)` in pieces of at most `INDEX_PIECE` indices (see there).
pub fn assign_rows<const D: usize>(
    target: Tensor<D>,
    idx: Tensor<1, Int>,
    values: Tensor<D>,
    op: IndexingUpdateOp,
) -> Tensor<D> {
    let n = idx.dims()[0];
    if n <= INDEX_PIECE || !needs_pieces(&target.device()) {
        return target.select_assign(0, idx, values, op);
    }
    let mut t = target;
    for s in (0..n).step_by(INDEX_PIECE) {
        let len = INDEX_PIECE.min(n - s);
        t = t.select_assign(0, idx.clone().narrow(0, s, len), values.clone().narrow(0, s, len), op);
    }
    t
}

/// An interleaved RGB buffer (`height * width * 3`, row-major) as a planar `[1, 3, H, W]` tensor.
pub fn image_tensor(rgb: &[f32], width: usize, height: usize, device: &Device) -> Tensor<4> {
    assert_eq!(rgb.len(), width * height * 3, "image buffer is {width}x{height}x3");
    let mut planar = vec![0.0f32; rgb.len()];
    let plane = width * height;
    for (p, px) in rgb.chunks_exact(3).enumerate() {
        for c in 0..3 {
            planar[c * plane + p] = px[c];
        }
    }
    floats(planar, [1, 3, height, width], device)
}
