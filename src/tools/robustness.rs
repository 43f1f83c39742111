//! The robustness study (paper section 4.3): the stylized field's own
//! renders at N path views used as new references, stylized again with the
//! run's method; PSNR between the two fields' renders along the path,
//! averaged. An experiment, not a metric: it runs whole stylizations, so it
//! sits above both the stylization and its metrics (`eval::stylization`).
//!
//! Two protocols over the same restylizations, each reported:
//! - refnpr's (`robustness_psnr`): one PSNR over all the path frames' pixels
//!   at the render size, averaged over the restylizations;
//! - the authors' (`robustness_psnr_authors`, as their maintainer described
//!   it in their tracker, dvlab-research/Ref-NPR issue 9): each frame in 8
//!   bits resized to 400x400, a PSNR per frame, the mean of the best 100
//!   frames (all of them when the path has fewer), averaged over the
//!   restylizations. Our resize is bilinear (a triangle filter, which widens
//!   when shrinking), theirs OpenCV's `INTER_LINEAR`.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use crate::eval::stylization::{
    EvalJob, RobustnessViews, StylizationEval, SurfaceRender, evaluate_run, nearest_cameras,
};
use crate::field::checkpoint::{self, Checkpoint};
use crate::reference::case;
use crate::scene::camera::Camera;
use crate::stylize::config::StylizeConfig;
use crate::stylize::resume;
use crate::stylize::run::run_stylize;
use crate::stylize::{Method, StylizeJob};
use crate::util::files;
use crate::util::image::Image;
use crate::util::metrics;
use crate::util::progress::{Event, Phase, Progress};

/// `refnpr eval --run STYLE_RUN --reference CASE [--robustness N]`: the
/// stylization metrics, then the robustness study when `job.robustness` > 0.
pub fn evaluate(job: &EvalJob, progress: &dyn Progress) -> Result<StylizationEval> {
    let run = evaluate_run(job, progress)?;
    let mut report = run.report;
    let frames = &run.frames;
    report.robustness_frames = match job.robustness_views {
        _ if job.robustness == 0 => Vec::new(),
        RobustnessViews::Spread => (0..job.robustness).map(|k| k * frames.len() / job.robustness).collect(),
        RobustnessViews::Near => {
            let reference = run.case.cameras(&run.dataset)?[0];
            let path: Vec<Camera> = frames.iter().map(|f| f.camera).collect();
            nearest_cameras(&path, &reference, job.robustness)
        }
    };
    if !report.robustness_frames.is_empty() {
        let (ours, authors) =
            robustness(job, &run.ck, frames, &report.robustness_frames, run.case.path_frames, progress)?;
        report.robustness_psnr = Some(ours);
        report.robustness_psnr_authors = Some(authors);
    }
    Ok(report)
}

/// Whether `out` holds a finished stylization (a checkpoint, no resume
/// file left) made with `method` and `config`.
fn finished_restylization(out: &Path, method: Method, config: &StylizeConfig) -> bool {
    let finished = out.join(checkpoint::CHECKPOINT_FILE).exists() && !resume::path(out).exists();
    let report: Option<serde_json::Value> = files::read_json(&out.join("stylize.json")).ok();
    let same = report.is_some_and(|r| {
        serde_json::from_value::<Method>(r["method"].clone()).is_ok_and(|m| m == method)
            && serde_json::from_value::<StylizeConfig>(r["config"].clone()).is_ok_and(|c| &c == config)
    });
    finished && same
}

/// The side the authors' protocol resizes each frame to.
pub const AUTHORS_SIDE: usize = 400;
/// The frames the authors' protocol averages (the best ones).
pub const AUTHORS_BEST_FRAMES: usize = 100;

/// A frame as the authors' protocol reads it: 8 bits (a PNG), resized to
/// 400x400, 8 bits again.
pub fn authors_frame(image: &Image) -> Vec<f32> {
    let quantised = |rgb: &[f32]| rgb.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() / 255.0).collect::<Vec<_>>();
    let eight_bit = Image::new(image.width, image.height, quantised(&image.rgb));
    quantised(&eight_bit.resized(AUTHORS_SIDE, AUTHORS_SIDE).rgb)
}

/// The authors' robustness figure of one restylization: the mean of the
/// best [`AUTHORS_BEST_FRAMES`] per-frame PSNRs.
pub fn best_frames_psnr(mut psnrs: Vec<f32>) -> f32 {
    psnrs.sort_by(|a, b| b.total_cmp(a));
    psnrs.truncate(AUTHORS_BEST_FRAMES);
    psnrs.iter().sum::<f32>() / psnrs.len().max(1) as f32
}

/// Restylizes from the run's own renders at path frames `chosen` and
/// compares the path renders of each result with the run's: (refnpr's
/// protocol, the authors').
fn robustness(
    job: &EvalJob,
    ck: &Checkpoint,
    frames: &[SurfaceRender],
    chosen: &[usize],
    path_frames: usize,
    progress: &dyn Progress,
) -> Result<(f32, f32)> {
    let report_path = job.run.join("stylize.json");
    let report: serde_json::Value = files::read_json(&report_path)
        .with_context(|| format!("robustness needs the stylization's {}", report_path.display()))?;
    let photo = PathBuf::from(report["photo"].as_str().context("stylize.json names no photo run")?);
    let mut config: StylizeConfig =
        serde_json::from_value(report["config"].clone()).context("stylize.json's config")?;
    // The paper restylizes with the method under test: an ARF run is
    // restylized by ARF with its own render as the style image.
    let method: Method = serde_json::from_value(report["method"].clone()).context("stylize.json's method")?;
    if let Some(e) = job.robustness_epochs {
        config.schedule.image_epochs = e;
    }
    let work = job.run.join("robustness");
    let originals: Vec<Vec<f32>> = frames.iter().map(|f| authors_frame(&f.image)).collect();
    let (mut psnrs, mut authors) = (Vec::new(), Vec::new());
    for (k, &frame) in chosen.iter().enumerate() {
        let case_dir = work.join(format!("case_{frame}"));
        frames[frame].image.save_png(&case_dir.join("style.png"))?;
        files::write_text(
            &case_dir.join(case::CASE_TOML),
            &format!(
                "# the stylized field's own render at path frame {frame} (refnpr eval --robustness)\n\
                 path_frames = {path_frames}\n\n[[reference]]\nstyle = \"style.png\"\nview = \"path:{frame}\"\n"
            ),
        )?;
        let out = work.join(format!("stylized_{frame}"));
        progress.event(Event::Step {
            phase: Phase::Robustness,
            done: k,
            total: chosen.len(),
            message: format!("restylizing from path frame {frame}"),
        });
        let restyle = StylizeJob {
            resume: job.resume,
            photo: photo.clone(),
            case: case_dir,
            out: out.clone(),
            config: config.clone(),
            method,
            backend: job.backend,
            style: None,
            data: job.data.clone(),
            registration: None,
            render_test: false,
        };
        match job.resume && finished_restylization(&out, method, &config) {
            true => progress.info(format!("keeping the finished restylization {}", out.display())),
            false => drop(run_stylize(&restyle, progress)?),
        }
        let again = checkpoint::load_with(&out, &ck.grid.device(), false)?;
        // One PSNR over all the path frames' pixels, one render at a time.
        let (mut sum, mut n) = (0.0f64, 0usize);
        let mut per_frame = Vec::new();
        let renderer = again.renderer();
        for (f, original) in frames.iter().zip(&originals) {
            let r = renderer.view(&f.camera);
            sum += metrics::squared_error(&r.image.rgb, &f.image.rgb);
            n += r.image.rgb.len();
            per_frame.push(metrics::psnr(&authors_frame(&r.image), original));
        }
        psnrs.push(metrics::psnr_from_mse((sum / n as f64) as f32));
        authors.push(best_frames_psnr(per_frame));
    }
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
    Ok((mean(&psnrs), mean(&authors)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The authors' figure averages the best 100 frames, or all when fewer.
    #[test]
    fn best_frames_psnr_averages_the_best_hundred() {
        // 150 frames: 100 at 30 dB, 50 at 10 dB (in mixed order).
        let psnrs: Vec<f32> = (0..150).map(|i| if i % 3 == 0 { 10.0 } else { 30.0 }).collect();
        assert_eq!(best_frames_psnr(psnrs), 30.0);
        assert_eq!(best_frames_psnr(vec![20.0, 10.0, 30.0]), 20.0);
    }

    /// A frame as the authors read it: 400x400, 8-bit values.
    #[test]
    fn authors_frames_are_400_square_in_eight_bits() {
        let (w, h) = (64, 48);
        let rgb: Vec<f32> = (0..w * h * 3).map(|i| (i % 97) as f32 / 96.0).collect();
        let frame = authors_frame(&Image::new(w, h, rgb));
        assert_eq!(frame.len(), AUTHORS_SIDE * AUTHORS_SIDE * 3);
        assert!(frame.iter().all(|v| ((v * 255.0).round() - v * 255.0).abs() < 1e-3), "8-bit values");
        let flat = authors_frame(&Image::new(w, h, vec![0.5; w * h * 3]));
        let expected = (0.5f32 * 255.0).round() / 255.0;
        assert!(flat.iter().all(|v| (v - expected).abs() < 1e-6), "a flat frame stays flat");
    }
}
