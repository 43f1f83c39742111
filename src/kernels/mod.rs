//! Our own fused kernels, each a Burn operation with its autodiff
//! plumbing and a graph oracle (a test holding it to the Burn graph it
//! replaces), in one place for whoever works on the GPU path:
//! - `gather_op`: a row gather whose backward is parallel on a GPU (CubeCL),
//!   with the row writes, run sums and each row's run it needs;
//! - `rows_op`: the lazy optimisers' row gathers and adds, in parallel and
//!   in place on flex;
//! - `composite_op`: equations 1-2 (compositing a ray's samples) as one GPU
//!   kernel per ray, forward and backward (`field::composite`'s GPU path);
//! - `frozen_op`: the stylization's colour pass over frozen density on a GPU
//!   (`field::frozen`'s);
//! - `optim_op`: RMSprop's lazy row step and the TV gradient on a GPU
//!   (`field::optim`'s);
//! - `conv3x3`, `conv_op`: VGG16's 3x3 convolutions on the CPU backends
//!   (Winograd F(4x4, 3x3), both gradients) as a Burn operation (`vgg`'s).
//!
//! A kernel is chosen where its caller checks the device (`is_host_memory`):
//! the CPU backends keep Burn's graph, or a plain-Rust kernel of their own,
//! bit for bit. The field's plain-Rust renderers (`field::host_fit`,
//! `host_render`, `host_colour`) stay with the field: they are its CPU path,
//! not a Burn operation.

pub mod composite_op;
pub(crate) mod conv3x3;
pub(crate) mod conv_op;
pub mod frozen_op;
pub mod gather_op;
pub mod optim_op;
pub(crate) mod rows_op;
