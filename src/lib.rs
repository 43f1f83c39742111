//! refnpr: reference-based non-photorealistic radiance fields (Ref-NPR, CVPR
//! 2023) on Burn. The folders are the pipeline, in order:
//!
//! | module | stage |
//! | --- | --- |
//! | `scene` | cameras, rays, NDC, camera paths, the SH basis; dataset loaders (Blender, LLFF, NSVF, the procedural scene) |
//! | `field` | the radiance grid, ray marching (plain Rust), compositing (Burn graph), the frozen-density colour renderer, what the optimisers share (RMSprop, TV, row subsets), checkpoints |
//! | `photo` | stage 1: fitting the photorealistic field (config, `Trainer::step_once`, the training run) |
//! | `reference` | stage 2: reference cases and style images, R³ (plain Rust), the `reference` / `register` commands |
//! | `vgg` | the ONNX-imported VGG16, block descriptors and nearest neighbours |
//! | `stylize` | stage 3: Ref-NPR (R³ + TCM + colour matching) and the ARF baseline: config, losses, TCM, the style field, the `Stylizer` and its image step, the run |
//! | `eval` | image metrics, photoreal and stylization metrics, camera-path renders |
//! | `tools` | the benchmarks, the one-command demo, the painterly repaint filter |
//! | `notebook` | the library as a notebook uses it: one type per stage, values that display in a Jupyter cell (evcxr) |
//! | `util` | backend choice, tensor helpers, the one `Image` type and its files, file writes, progress events, per-step RNG, memory readings |
//!
//! Every stage reads and writes files (dataset folder -> `RUN/checkpoint.bin`
//! -> `CASE/` -> `registration.bin` -> `STYLE/checkpoint.bin` -> renders), so
//! the `refnpr` binary is a thin layer of one call per subcommand. Library
//! code never prints: long work reports to a `util::progress::Progress` sink.

// Library code reports through `util::progress`; only the `Console` sink prints.
#![warn(clippy::print_stdout, clippy::print_stderr)]

pub mod eval;
pub mod field;
pub mod notebook;
pub mod photo;
pub mod reference;
pub mod scene;
pub mod stylize;
pub mod tools;
pub mod util;
pub mod vgg;

pub use util::backend::BackendKind;
pub use util::progress::{Console, Progress, Quiet};
