//! `refnpr stylize`, from files to files: check the inputs and the memory,
//! register (or read `registration.bin`), read the style images, refit,
//! build the guides, run the image epochs, save the stylized checkpoint,
//! its reference renders, `stylize.json` and the test views.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

use anyhow::{Result, bail};
use burn::tensor::Tensor;

use crate::eval::render_path::render_frames;
use crate::field::checkpoint::{self, Checkpoint};
use crate::field::march::Marcher;
use crate::reference::case::ReferenceCase;
use crate::reference::registration::{PhotoRun, RegistrationFile, lift_references, register_case};
use crate::scene::camera::Camera;
use crate::scene::data::Dataset;
use crate::stylize::colour_transfer::{ColourStats, ColourTransfer};
use crate::stylize::resume::{self, ResumeState};
use crate::stylize::styles::{arf_colour_transfer, read_styles, style_colour_stats};
use crate::stylize::stylizer::Stylizer;
use crate::stylize::tcm::{self, FEATURE_BLOCKS, RELU3};
use crate::stylize::{Method, StepKind, StylizeJob, StylizeReport};
use crate::util::files;
use crate::util::image::Image;
use crate::util::lock::OutputLock;
use crate::util::memory::{MemoryNow, available_memory_bytes, peak_rss_mb};
use crate::util::profile;
use crate::util::progress::{Event, Phase, Progress, WarningLog};
use crate::util::transfer::{self, PhaseTransfers};
use crate::vgg::{self, VggLayer};

/// `refnpr stylize`.
pub fn run_stylize(job: &StylizeJob, progress: &dyn Progress) -> Result<StylizeReport> {
    let started = Instant::now();
    let cfg = &job.config;
    cfg.validate()?;
    let (ck, dataset) = checkpoint::load_run(&job.photo, job.data.as_deref(), &job.backend.open(progress)?)?;
    let case = ReferenceCase::load(&job.case)?;
    if let Some(m) = case.scene_mismatch(&dataset) {
        bail!(
            "{m}: the reference case does not belong to the photoreal run {} (fix `scene_name` in the case if it does)",
            job.photo.display()
        );
    }
    let image_size = preflight(job, &ck, &dataset)?;
    let _lock = OutputLock::acquire(&job.out)?;
    let resumed = match job.resume {
        true => ResumeState::load(job)?,
        false => None,
    };
    let mut seconds = BTreeMap::new();
    let mut moved = BTreeMap::new();
    let mut memory = BTreeMap::new();
    let mut warnings = WarningLog::new(progress);

    let m = transfer::measure(|| registration(job, &ck, &dataset, &case, &mut warnings));
    let registration = m.value?;
    seconds.insert("registration".to_string(), m.seconds);
    memory.insert("registration".to_string(), MemoryNow::read());
    moved.insert("registration".to_string(), PhaseTransfers::new(m.moved, 0));
    let registered_fraction = registration.fraction_overall();
    if job.method == Method::RefNpr && registration.views.iter().all(|v| v.registration.pixels.is_empty()) {
        warnings.push(
            "R³ registered no training pixel: L_ref uses the reference view only, the rest comes from TCM".into(),
        );
    }

    let (styles, style_colours, colour_transfer) =
        style_side(job, &case, &dataset, &registration, ck.meta.background, &mut warnings)?;
    let photo_meta = ck.meta.clone();
    let mut st = Stylizer::new(job, &dataset, ck.grid, &photo_meta, registration, colour_transfer);
    if let (true, Some(tf)) = (job.method == Method::Arf && cfg.arf.transfer_grid, colour_transfer) {
        st.field.apply_colour_transfer(&tf);
    }
    match &resumed {
        None => {
            let m = transfer::measure(|| st.refit(progress));
            m.value?;
            seconds.insert("refit".to_string(), m.seconds);
            let refit_steps = st.curve.iter().filter(|p| p.phase == StepKind::Refit).count();
            moved.insert("refit".to_string(), PhaseTransfers::new(m.moved, refit_steps));
            st.finish_refit()?;
            memory.insert("refit".to_string(), MemoryNow::read());
        }
        Some(state) => {
            progress.info(format!(
                "resuming {} after image step {} (the refit is done)",
                resume::path(&job.out).display(),
                state.image_steps
            ));
            st.start_from_refit(state)?;
        }
    }

    let colour = job.method == Method::RefNpr && cfg.ablation.use_colour_loss && case.color_pre;
    let m = transfer::measure(|| st.guidance(&styles, keeps_content(job), colour, progress));
    let (guidance, colour_matched) = m.value?;
    let sample_cache = st.sample_cache_report();
    progress.event(Event::Detail(format!(
        "sample cache: {} of {} views{}, {:.0} MB of {} ({} samples in {} cells)",
        sample_cache.views_cached,
        sample_cache.views,
        if sample_cache.registered_cached { " and the registered pixels" } else { "" },
        sample_cache.mb,
        sample_cache.budget_mb,
        sample_cache.samples,
        sample_cache.cells
    )));
    seconds.insert("content".to_string(), m.seconds);
    memory.insert("content".to_string(), MemoryNow::read());
    moved.insert("content".to_string(), PhaseTransfers::new(m.moved, dataset.train.len()));
    if colour {
        // What L_color pulls each view towards, for inspection (small: one entry per 16x16 pixels).
        let [w, h] = image_size;
        let records: Vec<_> =
            guidance.guides.iter().enumerate().filter_map(|(v, g)| g.colour().map(|c| c.to_record(v, w, h))).collect();
        files::write_json(&job.out.join("colour_targets.json"), &records)?;
    }

    let start = resumed.as_ref().map_or(0, |s| s.image_steps);
    if let Some(state) = resumed {
        st.restore(state);
    }
    let epochs = st.image_epochs(&styles, guidance, start, progress)?;
    seconds.insert("image_epochs".to_string(), epochs.image_seconds);
    seconds.insert("smooth_update".to_string(), epochs.smooth_seconds);
    memory.insert("image_epochs".to_string(), MemoryNow::read());
    moved.insert("image_epochs".to_string(), epochs.image_steps);
    moved.insert("smooth_update".to_string(), epochs.smooth_steps);
    moved.insert("smooth_update_guides".to_string(), epochs.smooth_guides);
    progress
        .event(Event::PhaseDone { phase: Phase::ImageEpochs, seconds: epochs.image_seconds + epochs.smooth_seconds });
    for (phase, t) in &moved {
        progress.event(Event::Detail(t.describe(phase)));
    }
    for (phase, parts) in &st.step_profiles {
        progress.event(Event::Detail(format!("{phase} steps: {}", profile::describe(parts))));
    }

    let post_colour_transfer = match style_colours.filter(|_| cfg.arf.post_transfer) {
        Some(style) => {
            let tf = st.post_colour_transfer(&style, cfg.arf.transfer_pixels)?;
            progress.info(format!("ARF colour transfer after stylizing: {:?} + {:?}", tf.matrix, tf.offset));
            Some(tf)
        }
        None => None,
    };

    save_outputs(&st, &photo_meta, started, &job.out)?;
    let report = StylizeReport {
        method: job.method,
        backend: job.backend.to_string(),
        photo: job.photo.clone(),
        case: job.case.clone(),
        config: cfg.clone(),
        registration: job.registration.clone(),
        views: dataset.train.len(),
        image_size,
        registered_pixels: st.registered.len(),
        registered_fraction,
        colour_matched_fraction: colour_matched,
        colour_transfer: st.colour_transfer,
        post_colour_transfer,
        total_seconds: started.elapsed().as_secs_f64(),
        seconds,
        transfers: moved,
        step_profiles: std::mem::take(&mut st.step_profiles),
        peak_rss_mb: peak_rss_mb(),
        memory,
        sample_cache,
        final_losses: st.curve.iter().rev().find(|p| p.phase != StepKind::Refit).cloned(),
        curve: std::mem::take(&mut st.curve),
        warnings: warnings.into_vec(),
    };
    files::write_json(&job.out.join("stylize.json"), &report)?;
    ResumeState::remove(&job.out);
    if job.render_test && !dataset.test.is_empty() {
        let style_ck = checkpoint::load_with(&job.out, &job.backend.device(), false)?;
        let cams: Vec<Camera> = dataset.test.iter().map(|v| v.camera).collect();
        render_frames(&style_ck, &cams, &job.out.join("test"), progress)?;
    }
    Ok(report)
}

/// The style images and, for ARF with either colour transfer on, the style's
/// colour statistics (both transfers aim at them) and the photos'
/// recolouring (`--style` is ARF's alone).
fn style_side(
    job: &StylizeJob,
    case: &ReferenceCase,
    dataset: &Dataset,
    registration: &RegistrationFile,
    background: [f32; 3],
    warnings: &mut WarningLog,
) -> Result<(Vec<Image>, Option<ColourStats>, Option<ColourTransfer>)> {
    let own_style = job.style.as_deref().filter(|_| job.method == Method::Arf);
    let styles = read_styles(case, registration, own_style, background, warnings)?;
    let arf = &job.config.arf;
    if job.method != Method::Arf || !(arf.colour_transfer || arf.post_transfer) {
        return Ok((styles, None, None));
    }
    let which = arf.transfer_pixels;
    let style = style_colour_stats(&styles[0], registration, own_style.is_some(), background, which)?;
    if !arf.colour_transfer {
        return Ok((styles, Some(style), None));
    }
    let tf = arf_colour_transfer(dataset, &style, background, which)?;
    warnings.progress().info(format!("ARF colour transfer: photos recoloured with {:?} + {:?}", tf.matrix, tf.offset));
    Ok((styles, Some(style), Some(tf)))
}

/// Whether the content features of every view are kept (λ' > 0).
fn keeps_content(job: &StylizeJob) -> bool {
    let cfg = &job.config;
    match job.method {
        Method::RefNpr => cfg.loss.content > 0.0 && cfg.ablation.use_feature_loss,
        Method::Arf => cfg.arf.content > 0.0,
    }
}

/// Refuses, before any work, views too small for VGG16 and feature caches
/// that would not fit in memory. Returns the views' size `[width, height]`.
fn preflight(job: &StylizeJob, ck: &Checkpoint, dataset: &Dataset) -> Result<[usize; 2]> {
    if dataset.train.is_empty() {
        bail!("the photoreal run's dataset {} has no training views", dataset.root.display());
    }
    let cam0 = dataset.train[0].camera.intrinsics;
    let (width, height) = (cam0.width as usize, cam0.height as usize);
    if width < vgg::MIN_SIDE || height < vgg::MIN_SIDE {
        bail!("training views are {width}x{height}: stylization needs at least {0}x{0} (VGG16)", vgg::MIN_SIDE);
    }
    let half = job.method == Method::Arf && job.config.arf.half_resolution;
    if half && (width < 2 * vgg::MIN_SIDE || height < 2 * vgg::MIN_SIDE) {
        bail!(
            "training views are {width}x{height}: arf.half_resolution needs at least {0}x{0} (VGG16 at half size)",
            2 * vgg::MIN_SIDE
        );
    }
    let grid_bytes = ck.grid.num_rows() as u64 * 3 * 4 * 6; // SH, RMSprop state, gradients
    // Bytes per kept content feature: f16 with `half_content_features` (on
    // the CPU backends, whose memory this checks).
    let content_bytes = match (keeps_content(job), job.config.half_content_features) {
        (false, _) => 0,
        (true, true) => 2,
        (true, false) => 4,
    };
    let per_view = feature_cache_bytes(job.method, 1, width, height, content_bytes);
    let need = per_view * dataset.train.len() as u64 + grid_bytes;
    if let Some(avail) = available_memory_bytes()
        && need > avail / 4 * 3
    {
        let fit = (avail / 4 * 3).saturating_sub(grid_bytes) / per_view.max(1);
        bail!(
            "stylizing {} views of {width}x{height} needs about {:.1} GB for feature caches and the grid, but {:.1} GB is available \
             (about {fit} views fit): use a lower-resolution photoreal run, or set loss.content = 0 (drops the cached content features)",
            dataset.train.len(),
            need as f64 / 1e9,
            avail as f64 / 1e9
        );
    }
    Ok([width, height])
}

/// The pseudo-rays: R³ on the photoreal field, or the `registration.bin`
/// of `job.registration` after checking it belongs to this run and case.
fn registration(
    job: &StylizeJob,
    ck: &Checkpoint,
    dataset: &Dataset,
    case: &ReferenceCase,
    warnings: &mut WarningLog,
) -> Result<RegistrationFile> {
    match &job.registration {
        None => {
            let (file, report) = register_case(ck, dataset, case, &job.config.register, warnings.progress())?;
            warnings.extend_reported(report.warnings);
            Ok(file)
        }
        Some(given) => {
            let path = &RegistrationFile::resolve(given);
            let file = RegistrationFile::load(path)?;
            // The case's references as they are now, to compare with the file's.
            let (_, references) = lift_references(ck, &Marcher::new(&ck.grid), dataset, case, warnings)?;
            file.check_matches(&PhotoRun::of(ck), dataset, &references, path)?;
            if file.params != job.config.register {
                warnings.push(format!(
                    "{} was registered with {:?}, not this config's [register] {:?}: using the file",
                    path.display(),
                    file.params,
                    job.config.register
                ));
            }
            Ok(file)
        }
    }
}

/// The stylized checkpoint (a normal grid with SH degree 0) and the
/// stylized renders of the reference views.
fn save_outputs(st: &Stylizer, photo_meta: &checkpoint::CheckpointMeta, started: Instant, out: &Path) -> Result<()> {
    let mut meta = photo_meta.clone();
    meta.sh_degree = 0;
    meta.config.grid.sh_degree = 0;
    meta.config.march = st.march();
    meta.step = st.curve.iter().filter(|p| p.phase != StepKind::Refit).count();
    meta.train_seconds = started.elapsed().as_secs_f64();
    let grid = &st.field.grid;
    let (rows, device) = (grid.num_rows(), grid.device());
    let zeros = (Tensor::zeros([rows, 1], &device), Tensor::zeros([rows, 3], &device));
    checkpoint::save(&out.join(checkpoint::CHECKPOINT_FILE), &meta, grid, &zeros.0, &zeros.1)?;
    for r in 0..st.num_references() {
        st.render_reference(r).save_png(&out.join(format!("reference_{r}.png")))?;
    }
    Ok(())
}

/// Bytes the per-view feature caches need (raw content features of the
/// feature blocks, `content_bytes` a number, plus match indices).
fn feature_cache_bytes(method: Method, views: usize, width: usize, height: usize, content_bytes: usize) -> u64 {
    let blocks: Vec<&[VggLayer]> = match method {
        Method::RefNpr => FEATURE_BLOCKS.to_vec(),
        Method::Arf => vec![&RELU3],
    };
    let per_view: usize = blocks
        .iter()
        .map(|b| {
            let [h, w] = tcm::block_size(b, height, width);
            let c: usize = b.iter().map(|l| l.channels()).sum();
            h * w * (c * content_bytes + 8)
        })
        .sum();
    (per_view * views) as u64
}
