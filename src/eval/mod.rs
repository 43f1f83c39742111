//! LPIPS as the `lpips` package computes it (`lpips`), and the stylization
//! metrics (`stylization`: Ref-LPIPS, ground-truth PSNR,
//! warp stability, speckle), computed from a stylized run and its reference
//! case. The image metrics every stage uses are `util::metrics`; how well a
//! field reproduces photos is `photo::evaluate`; the robustness study (an
//! experiment that restylizes) is `tools::robustness`.

pub mod lpips;
pub mod stylization;
pub mod texture;
