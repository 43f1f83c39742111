//! Small conversions between plain Rust buffers and Burn tensors.

use burn::tensor::{Device, Int, Tensor, TensorData};

/// A float tensor of the given shape from a flat row-major buffer.
pub fn floats<const D: usize>(values: Vec<f32>, shape: [usize; D], device: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(values, shape), device)
}

/// A 1-D index tensor.
pub fn indices(values: Vec<i32>, device: &Device) -> Tensor<1, Int> {
    let n = values.len();
    Tensor::from_data(TensorData::new(values, [n]), device)
}

/// The tensor's values as a flat `Vec<f32>` (row-major).
pub fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_into_vec::<f32>()
        .expect("float tensor data converts to f32")
}

/// A scalar float tensor's value.
pub fn scalar(t: Tensor<1>) -> f32 {
    to_vec(t)[0]
}
