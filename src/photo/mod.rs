//! Stage 1, the photorealistic field: the training config (`config`), the
//! trainer and its optimisation step (`trainer`), the training run that
//! drives it (`run`), how well a field reproduces photos (`evaluate`), and
//! cameras aligned to a fitted field (`pose_refine`).

pub mod config;
pub mod evaluate;
pub mod pose_refine;
pub mod run;
pub mod trainer;
