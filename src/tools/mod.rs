//! Around the pipeline: `capture` (a folder of photos to a dataset through COLMAP), benchmarks (`bench`), the one-command demo on the
//! procedural scene (`demo`), `info` (what the build runs on), `fuzz` (every parser of outside input fed mutated files), the robustness study (`robustness`: restylizations from the stylized
//! field's own renders), and a painterly repaint filter to try
//! stylization without painting by hand (`paint`), and the contact sheet of
//! a run's views to choose a reference view from (`views`).

pub mod bench;
pub mod capture;
pub mod demo;
pub mod fuzz;
pub mod info;
pub mod paint;
pub mod robustness;
pub mod views;
