//! The robustness study (paper section 4.3): the stylized field's own
//! renders at N path views used as new references, stylized again with the
//! run's method; PSNR between the two fields' renders along the path,
//! averaged. An experiment, not a metric: it runs whole stylizations, so it
//! sits above both the stylization and its metrics (`eval::stylization`).

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
        let psnr = robustness(job, &run.ck, frames, &report.robustness_frames, run.case.path_frames, progress)?;
        report.robustness_psnr = Some(psnr);
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

/// Restylizes from the run's own renders at path frames `chosen` and
/// compares the path renders of each result with the run's.
fn robustness(
    job: &EvalJob,
    ck: &Checkpoint,
    frames: &[SurfaceRender],
    chosen: &[usize],
    path_frames: usize,
    progress: &dyn Progress,
) -> Result<f32> {
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
    let mut psnrs = Vec::new();
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
        let renderer = again.renderer();
        for f in frames {
            let r = renderer.view(&f.camera);
            sum += metrics::squared_error(&r.image.rgb, &f.image.rgb);
            n += r.image.rgb.len();
        }
        psnrs.push(metrics::psnr_from_mse((sum / n as f64) as f32));
    }
    Ok(psnrs.iter().sum::<f32>() / psnrs.len() as f32)
}
