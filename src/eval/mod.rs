//! Measuring and showing results: image metrics (`metrics`: PSNR, SSIM),
//! how well a field reproduces photos (`photoreal`), the stylization
//! metrics (`stylization`: Ref-LPIPS, ground-truth PSNR, warp stability,
//! robustness) and camera-path renders (`render_path`).

pub mod metrics;
pub mod photoreal;
pub mod render_path;
pub mod stylization;
