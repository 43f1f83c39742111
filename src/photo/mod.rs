//! Stage 1, the photorealistic field: the training config (`config`), the
//! trainer and its optimisation step (`trainer`), and the training run that
//! drives it (`run`).

pub mod config;
pub mod run;
pub mod trainer;
