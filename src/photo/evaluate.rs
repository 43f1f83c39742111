//! How well a field reproduces photos: PSNR and SSIM of rendered views.

use std::path::Path;

use anyhow::Result;
use serde::{Deserialize, Serialize};

use crate::field::grid::RadianceGrid;
use crate::field::view::{RenderSettings, ViewRenderer};
use crate::scene::data::{Dataset, View};
use crate::util::metrics;

/// Quality of a grid on a set of views.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct EvalReport {
    pub psnr: f32,
    pub ssim: f32,
    pub per_view_psnr: Vec<f32>,
}

/// Renders each view, compares with its photo, optionally writes PNGs to `out`.
pub fn evaluate(
    grid: &RadianceGrid,
    dataset: &Dataset,
    views: &[View],
    settings: &RenderSettings,
    out: Option<&Path>,
) -> Result<EvalReport> {
    let mut psnrs = Vec::new();
    let mut ssims = Vec::new();
    let renderer = ViewRenderer::new(grid, dataset.ndc.as_ref(), settings, dataset.background);
    for (i, v) in views.iter().enumerate() {
        let r = renderer.view(&v.camera);
        psnrs.push(metrics::psnr(&r.image.rgb, &v.rgb));
        ssims.push(metrics::ssim(&r.image.rgb, &v.rgb, r.image.width, r.image.height));
        if let Some(dir) = out {
            r.image.save_png(&dir.join(format!("{i:04}.png")))?;
        }
    }
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len().max(1) as f32;
    Ok(EvalReport { psnr: mean(&psnrs), ssim: mean(&ssims), per_view_psnr: psnrs })
}
