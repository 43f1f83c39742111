//! refnpr: reference-based non-photorealistic radiance fields (Ref-NPR, CVPR
//! 2023) on Burn. The folders are the pipeline, in order:
//!
//! | module | stage |
//! | --- | --- |
//! | `util` | backend choice, tensor helpers, the one `Image` type and its files, the image metrics (PSNR, SSIM, speckle), file writes (safetensors: checkpoints' layout, arrays with JSON), progress events, per-step RNG, memory readings, phase costs |
//! | `scene` | cameras, rays, NDC, camera paths, the SH basis; dataset loaders (Blender, LLFF, NSVF, COLMAP models, `transforms.json`, the procedural scene) |
//! | `kernels` | our fused kernels as Burn operations with their backward and graph oracles: the GPU row gathers (CubeCL), the GPU compositing, colour pass and optimiser kernels, flex's parallel row updates, the CPU 3x3 convolution (Winograd) |
//! | `vgg` | the feature networks: the ONNX-imported VGG16 with Oxford's or torchvision's weights, AlexNet, the embedded LPIPS weights, block descriptors and nearest neighbours |
//! | `field` | the radiance grid, ray marching (plain Rust), compositing (Burn graph), the view renderer (kernel chosen once), camera-path renders, the frozen-density colour renderer, what the optimisers share (RMSprop, TV, row subsets), checkpoints |
//! | `photo` | stage 1: fitting the photorealistic field (config, `Trainer::step_once`, the training run, its test-view evaluation) |
//! | `reference` | stage 2: reference cases and style images, R³ (plain Rust), the `reference` / `register` commands |
//! | `stylize` | stage 3: Ref-NPR (R³ + TCM + colour matching) and the ARF baseline: config, losses, TCM, the style field, the sample cache, the step (`StyleStep`), the guides, the run (the loops) |
//! | `eval` | LPIPS as the `lpips` package computes it, and the stylization metrics (Ref-LPIPS, ground-truth PSNR, warp stability, speckle) |
//! | `export` | results out: Gaussian splats (3DGS PLY), the iso-surface as a coloured mesh (glb, PLY), MP4 through ffmpeg, surface points |
//! | `view` | the browser viewer: the field packed as WebGL2 textures, the page (HTML, JavaScript, GLSL), the local server, the static copy |
//! | `tools` | `capture` (photos to a dataset through COLMAP), the benchmarks, the one-command demo, the robustness study, the fuzzer, the painterly repaint filter |
//! | `notebook` | the front API: one type per stage whose values display in a Jupyter cell (evcxr) |
//!
//! The table is the stage order: a module imports only its own stage and
//! the ones above it (`scripts/check_layers.py`, run by the test command,
//! reads this table and fails on an import that points down the table, or
//! on files of one stage importing each other in a cycle). The `refnpr`
//! binary and the examples sit above every stage.
//!
//! The front API, re-exported here: the stage types [`Scene`] (a dataset),
//! [`Photo`] (a photoreal run), [`Reference`] (a reference case),
//! [`Registered`] (R³'s registration) and [`Stylized`] (a stylized run),
//! their configs, the backend choice and the progress sinks
//! (`examples/orbit.rs` goes from the procedural scene to a stylized
//! orbit through them alone).
//!
//! Every stage reads and writes files (dataset folder -> `RUN/checkpoint.bin`
//! -> `CASE/` -> `registration.bin` -> `STYLE/checkpoint.bin` -> renders), so
//! the `refnpr` binary is a thin layer of one call per subcommand. Library
//! code never prints: long work reports to a `util::progress::Progress` sink.

// Library code reports through `util::progress`; only the `Console` sink prints.
#![warn(clippy::print_stdout, clippy::print_stderr)]
// The docs' links must resolve (`cargo doc` in the test command, warnings denied).
#![deny(rustdoc::broken_intra_doc_links)]

pub mod eval;
pub mod export;
pub mod field;
pub mod kernels;
pub mod notebook;
pub mod photo;
pub mod reference;
pub mod scene;
pub mod stylize;
pub mod tools;
pub mod util;
pub mod vgg;
pub mod view;

#[cfg(test)]
mod test_support;

// The README's Rust example, compiled by `cargo test --doc` (the test command) so it cannot drift from the API.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeExamples;

pub use notebook::{
    Error, Gallery, Photo, Plot, Reference, Registered, Scene, Stylized, Table, demo_configs, stylize_config,
    train_config,
};
pub use photo::config::TrainConfig;
pub use reference::r3::RegisterParams;
pub use scene::camera::Camera;
pub use stylize::Method;
pub use stylize::config::StylizeConfig;
pub use util::backend::BackendKind;
pub use util::image::Image;
pub use util::progress::{Console, Event, Progress, Quiet};
