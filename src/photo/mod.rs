//! Stage 1, the photorealistic field: the training config (`config`), the
//! trainer and its optimisation step (`trainer`), the training run that
//! drives it (`run`), and how well a field reproduces photos (`evaluate`).

pub mod config;
pub mod evaluate;
pub mod run;
pub mod trainer;
