//! `refnpr train`: a training run in a folder - start or resume, drive the
//! steps, checkpoint, evaluate the test views, write `metrics.json`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Result, ensure};
use serde::{Deserialize, Serialize};

use crate::field::checkpoint;
use crate::field::grid::sh_bytes;
use crate::photo::config::TrainConfig;
use crate::photo::evaluate::evaluate;
use crate::photo::pose_refine::{self, RefineSettings, Refinement};
use crate::photo::trainer::{Trainer, far_decision};
use crate::scene::data::{Dataset, write_colmap};
use crate::util::backend::{BackendKind, max_buffer_bytes};
use crate::util::costs::Work;
use crate::util::lock::OutputLock;
use crate::util::memory::peak_rss_mb;
use crate::util::metrics;
use crate::util::profile::{self, PartTime};
use crate::util::progress::{Event, Phase, Progress};
use crate::util::transfer::{self, PhaseLog, PhaseTransfers, Transfers, human_bytes};
use crate::util::{diverged, files};

/// What `refnpr train` writes to `RUN/metrics.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrainMetrics {
    pub test_psnr: f32,
    pub test_ssim: f32,
    pub train_seconds: f64,
    pub steps: usize,
    pub backend: String,
    pub dataset: PathBuf,
    pub kind: String,
    pub grid_res: [usize; 3],
    pub active_voxels: usize,
    pub per_view_psnr: Vec<f32>,
    pub peak_rss_mb: Option<f64>,
    /// Host-device traffic (`util::transfer`) of this process's work:
    /// `fit` (all steps, upsampling included), `fit_final_resolution` (the
    /// steps after the last upsampling: the steady state), `evaluate`.
    #[serde(default)]
    pub transfers: BTreeMap<String, PhaseTransfers>,
    /// The training loss of every step this process ran (a resumed run
    /// starts its curve at the step it resumed from).
    #[serde(default)]
    pub loss_curve: Vec<FitPoint>,
    /// Wall seconds per part of a training step (march, rows, gradient,
    /// update), summed over the steps after the last upsampling that this
    /// process ran; `calls` is their number.
    #[serde(default)]
    pub step_profile: Vec<PartTime>,
}

/// One training step's loss.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct FitPoint {
    pub step: usize,
    /// Mean squared error of the batch's colours (the photo loss).
    pub mse: f32,
}

/// Trains (or, with `resume`, continues) a run in `out`: checkpoints, test
/// renders in `out/test`, `config.toml` and `metrics.json`.
pub fn run_training(
    dataset: &Dataset,
    config: TrainConfig,
    out: &Path,
    backend: BackendKind,
    resume: bool,
    progress: &dyn Progress,
) -> Result<TrainMetrics> {
    let _lock = OutputLock::acquire(out)?;
    let checkpoint = out.join(checkpoint::CHECKPOINT_FILE);
    let resume_from = (resume && checkpoint.exists()).then_some(checkpoint.as_path());
    let mut trainer = start(dataset, config, resume_from, backend, progress)?;
    progress.event(Event::JobStart(Work {
        job: "train".into(),
        backend: backend.to_string(),
        shape: dataset.shape_name().into(),
        units: (trainer.config.optim.steps * trainer.config.optim.batch_rays) as f64,
        pixels: dataset.train_pixels(),
        resumed: resume_from.is_some(),
    }));
    files::write_toml(&out.join("config.toml"), &trainer.config)?;
    let started = Instant::now();
    let (fit_transfers, loss_curve) = fit(&mut trainer, dataset, out, progress)?;
    progress.event(Event::PhaseDone { phase: Phase::Fit, seconds: started.elapsed().as_secs_f64() });
    progress.info(format!("evaluating {} test views, writing the checkpoint meanwhile", dataset.test.len()));
    // The final checkpoint and the test renders only read the field: the
    // write, which mostly waits on the disk (a fern checkpoint is 1.3 GB),
    // runs beside the renders.
    let mut phases = PhaseLog::default();
    let write_checkpoint = trainer.checkpoint_writer(dataset);
    let (saved, report) = std::thread::scope(|s| {
        let save = s.spawn(|| write_checkpoint(out));
        let test = Some(out.join("test"));
        let settings = trainer.config.render_settings();
        let report = phases.run("evaluate", dataset.test.len(), || {
            evaluate(&trainer.grid, dataset, &dataset.test, &settings, test.as_deref())
        });
        (save.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)), report)
    });
    saved?;
    let report = report?;
    progress.event(Event::PhaseDone { phase: Phase::Evaluate, seconds: phases.seconds["evaluate"] });
    let mut transfers = fit_transfers;
    transfers.append(&mut phases.transfers);
    for (phase, t) in &transfers {
        progress.event(Event::Detail(t.describe(phase)));
    }
    let step_profile = trainer.profile.parts();
    if !step_profile.is_empty() {
        progress.event(Event::Detail(format!("final-resolution steps: {}", profile::describe(&step_profile))));
    }
    let metrics = TrainMetrics {
        test_psnr: report.psnr,
        test_ssim: report.ssim,
        train_seconds: trainer.train_seconds,
        steps: trainer.step,
        backend: backend.to_string(),
        dataset: dataset.root.clone(),
        kind: dataset.kind.to_string(),
        grid_res: trainer.grid.geometry.res,
        active_voxels: trainer.grid.num_rows(),
        per_view_psnr: report.per_view_psnr,
        peak_rss_mb: peak_rss_mb(),
        transfers,
        loss_curve,
        step_profile,
    };
    files::write_json(&out.join("metrics.json"), &metrics)?;
    progress.event(Event::JobDone);
    Ok(metrics)
}

/// Where `train --refine-poses` keeps its first fit and the refined capture, inside the run folder.
pub const FIRST_FIT: &str = "first_fit";
pub const REFINED_SCENE: &str = "scene_refined";

/// `refnpr train --refine-poses`: fits `dataset` (a COLMAP capture around
/// the scene) in `out/first_fit`, aligns its cameras to that field
/// (`pose_refine`), writes the capture with them to `out/scene_refined`, and
/// fits that in `out`: the run, and every stage after it, sees the refined
/// cameras. Returns both fits' metrics and the refinement.
pub fn run_training_with_refined_poses(
    dataset: &Dataset,
    config: TrainConfig,
    out: &Path,
    backend: BackendKind,
    progress: &dyn Progress,
) -> Result<(TrainMetrics, Refinement, TrainMetrics)> {
    let scene = out.join(REFINED_SCENE);
    crate::scene::data::check_writable(dataset, &scene)?;
    let first_dir = out.join(FIRST_FIT);
    let first = run_training(dataset, config.clone(), &first_dir, backend, false, progress)?;
    let ck = checkpoint::load(&first_dir, &pose_refine::render_device(backend))?;
    let refinement =
        pose_refine::refine_dataset(&ck.grid, dataset, &ck.meta.render, &RefineSettings::default(), progress)?;
    progress.info(refinement.describe());
    write_colmap(dataset, &refinement.cameras, &scene)?;
    let refined = crate::scene::data::load(&scene, &config.data)?;
    let second = run_training(&refined, config, out, backend, false, progress)?;
    Ok((first, refinement, second))
}

/// A fresh trainer, or the one a checkpoint holds.
fn start(
    dataset: &Dataset,
    config: TrainConfig,
    resume_from: Option<&Path>,
    backend: BackendKind,
    progress: &dyn Progress,
) -> Result<Trainer> {
    let device = backend.open(progress)?;
    let followed = config.for_views(dataset);
    match resume_from {
        Some(ckpt) => {
            let mut t = Trainer::resume(dataset, ckpt, &device)?;
            progress.info(format!("resuming {} at step {}", ckpt.display(), t.step));
            // The command's step count wins (the same command resumes where it
            // stopped; a larger count extends a finished run), grown as the
            // grid followed the images if the checkpoint's did (a run made
            // with the schedule as written keeps its count); every other
            // setting is the checkpoint's, which its grid was made with.
            let grew = t.config.grid.final_res() == followed.grid.final_res();
            let wanted = if grew { followed.optim.steps } else { config.optim.steps };
            if wanted != t.config.optim.steps {
                ensure!(
                    wanted >= t.step,
                    "{} is already at step {}: it cannot end at step {wanted} (ask for {} steps or more)",
                    ckpt.display(),
                    t.step,
                    t.step
                );
                progress.info(format!(
                    "extending the run from {} to {wanted} steps (its other settings are the checkpoint's)",
                    t.config.optim.steps
                ));
                t.config.optim.steps = wanted;
            }
            Ok(t)
        }
        None => {
            let (_, why) = far_decision(dataset, &config.grid)?;
            progress.info(format!("far background: {why}"));
            if followed != config {
                progress.info(format!(
                    "the grid follows the images: {:?} at the end instead of {:?}, {} steps instead of {} \
                     ([grid] voxels_per_pixel = {}; 0 keeps the schedule as written)",
                    followed.grid.final_res(),
                    config.grid.final_res(),
                    followed.optim.steps,
                    config.optim.steps,
                    config.grid.voxels_per_pixel
                ));
            }
            Trainer::new(dataset, followed, &device)
        }
    }
}

/// What a run says when its grid outgrows the device's buffers and moves to host memory.
fn host_grid_warning(trainer: &Trainer) -> String {
    let bytes = sh_bytes(trainer.grid.num_rows(), trainer.grid.num_basis());
    let limit = max_buffer_bytes(&trainer.compute_device()).map(human_bytes).unwrap_or_default();
    format!(
        "at step {} the field ({} voxels, {} of SH colour) outgrew the wgpu adapter's largest buffer ({limit}): \
         it is kept in host memory from here on, each step's rows travel to the adapter and back, and views \
         render on the CPU",
        // The step that upsampled; `step` already counts it.
        trainer.step - 1,
        trainer.grid.num_rows(),
        human_bytes(bytes)
    )
}

/// Runs the remaining steps, checkpointing every `checkpoint_every`.
/// `train_seconds` counts the time since the last checkpoint, so a resumed
/// run adds only what it did itself. Returns the steps' host-device traffic
/// (checkpoint writes apart): `fit` and `fit_final_resolution`, and the
/// loss of every step.
fn fit(
    trainer: &mut Trainer,
    dataset: &Dataset,
    out: &Path,
    progress: &dyn Progress,
) -> Result<(BTreeMap<String, PhaseTransfers>, Vec<FitPoint>)> {
    let total = trainer.config.optim.steps;
    // Steps after this one run on the final grid (the upsampling step itself rebuilds it).
    let last_upsample = trainer.config.grid.upsample_steps.iter().copied().max();
    let (mut all, mut steady) = ((Transfers::default(), 0), (Transfers::default(), 0));
    progress.event(Event::Start { phase: Phase::Fit, done: trainer.step, total });
    let mut segment = Instant::now();
    let mut rays_done = 0usize;
    let checkpoint = out.join(checkpoint::CHECKPOINT_FILE);
    // The step of this run's last checkpoint: a resumed run starts from one.
    let mut saved_at = (trainer.step > 0).then_some(trainer.step);
    let mut curve = Vec::with_capacity(total.saturating_sub(trainer.step));
    while trainer.step < total {
        let steady_step = last_upsample.is_none_or(|s| trainer.step > s);
        if Some(trainer.step) == last_upsample.map(|s| s + 1) {
            trainer.profile.clear();
        }
        let on_host = trainer.grid_kept_on_host();
        let m = transfer::measure(|| trainer.step_once());
        let (st, moved) = (m.value?, m.moved);
        if !on_host && trainer.grid_kept_on_host() {
            progress.warning(host_grid_warning(trainer));
        }
        diverged::check_loss(st.mse, Phase::Fit, trainer.step, || match saved_at {
            Some(k) => format!("the last good checkpoint, {} (step {k}), is kept", checkpoint.display()),
            None => "no checkpoint of this run was written yet".to_string(),
        })?;
        curve.push(FitPoint { step: trainer.step, mse: st.mse });
        all = (all.0.plus(moved), all.1 + 1);
        if steady_step {
            steady = (steady.0.plus(moved), steady.1 + 1);
        }
        rays_done += trainer.config.optim.batch_rays;
        let rays_s = rays_done as f64 / segment.elapsed().as_secs_f64().max(1e-9);
        let message = format!(
            "loss {:.5} psnr {:.2} | {:.0} rays/s | {} samples | {} voxels",
            st.mse,
            metrics::psnr_from_mse(st.mse),
            rays_s,
            st.samples,
            trainer.grid.num_rows()
        );
        progress.event(Event::Step { phase: Phase::Fit, done: trainer.step, total, message });
        if trainer.step.is_multiple_of(trainer.config.checkpoint_every) && trainer.step < total {
            trainer.train_seconds += segment.elapsed().as_secs_f64();
            segment = Instant::now();
            rays_done = 0;
            trainer.save(dataset, out)?;
            saved_at = Some(trainer.step);
        }
    }
    trainer.train_seconds += segment.elapsed().as_secs_f64();
    let transfers = BTreeMap::from([
        ("fit".to_string(), PhaseTransfers::new(all.0, all.1)),
        ("fit_final_resolution".to_string(), PhaseTransfers::new(steady.0, steady.1)),
    ]);
    Ok((transfers, curve))
}
