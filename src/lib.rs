//! refnpr: reference-based non-photorealistic radiance fields (Ref-NPR) on Burn.
//!
//! Stages, each a module with one job: `data` (scenes), `grid` + `render`
//! (the radiance field and its differentiable volume renderer), `train`
//! (photorealistic fitting), `checkpoint`, `metrics`, `imageio`, `vgg`
//! (the ONNX-imported VGG16 feature extractor, generated code in `vgg_model`)
//! and `features` (cosine nearest-neighbour search over its feature maps).

pub mod backend;
pub mod bench;
pub mod binfile;
pub mod camera;
pub mod checkpoint;
pub mod colour_transfer;
pub mod config;
pub mod data;
pub mod demo;
pub mod evaluation;
pub mod features;
pub mod grid;
pub mod imageio;
pub mod metrics;
pub mod paint;
pub mod render;
pub mod reference;
pub mod register;
pub mod registration;
pub mod render_path;
pub mod sh;
pub mod stylize;
pub mod tensor_util;
pub mod train;
pub mod vgg;
pub mod vgg_model;

pub use backend::BackendKind;
