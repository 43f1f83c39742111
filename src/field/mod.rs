//! The radiance field: the sparse voxel grid (`grid`), ray marching in plain
//! Rust (`march`), the differentiable compositing graph (`composite`), the
//! colour-only renderer over frozen density (`frozen`; `host_colour`, its
//! fused plain-Rust twin for the CPU backends), what the optimisers
//! share (`optim`) and single-file checkpoints (`checkpoint`).

pub mod checkpoint;
pub mod composite;
pub mod frozen;
pub mod grid;
pub mod host_colour;
pub mod march;
pub mod optim;
