//! `refnpr stylize`, from files to files: check the inputs and the memory
//! (`inputs`), tell a recolouring (`recolouring`),
//! register (or read `registration.bin`), read the style images, then the
//! loops - the refit, the guides, the image epochs and the smooth update,
//! each step a `StyleStep` call - with their resume points and phase
//! costs; save the stylized checkpoint, its reference renders,
//! `stylize.json` and the test views.

use std::collections::BTreeMap;
use std::time::Instant;

use anyhow::{Result, bail};
use rand::seq::SliceRandom;

use crate::field::checkpoint;
use crate::scene::data::Dataset;
use crate::stylize::budget::{self, MemoryPlan};
use crate::stylize::coarse::{self, FineStage};
use crate::stylize::colour_transfer::{ColourStats, ColourTransfer};
use crate::stylize::field;
use crate::stylize::guides::{self, ColourSource, Content};
use crate::stylize::inputs::{self, Inputs, keeps_content, registration, style_side};
use crate::stylize::outputs::{render_test_views, save_outputs};
use crate::stylize::recolouring::{FittedMap, explained_on_content, fit_colour_map, with_recolouring_schedule};
use crate::stylize::region::PixelRegion;
use crate::stylize::resume::{self, JobKey, ResumeState};
use crate::stylize::step::{Guidance, StyleStep, ViewGuide};
use crate::stylize::strokes;
use crate::stylize::styles::is_background;
use crate::stylize::tcm::Template;
use crate::stylize::{CurvePoint, HeldMemory, LocalEditReport, Method, StepKind, StylizeJob, StylizeReport};
use crate::util::costs::Work;
use crate::util::diverged;
use crate::util::files;
use crate::util::image::Image;
use crate::util::lock::OutputLock;
use crate::util::memory::peak_rss_mb;
use crate::util::metrics::psnr_from_mse;
use crate::util::profile::{self, PartTime};
use crate::util::progress::{Event, Phase, Progress, WarningLog};
use crate::util::rng::epoch_rng;
use crate::util::tensor::to_vec;
use crate::util::transfer::{self, PhaseLog, PhaseTransfers, Transfers};

/// `refnpr stylize`.
pub fn run_stylize(job: &StylizeJob, progress: &dyn Progress) -> Result<StylizeReport> {
    let started = Instant::now();
    let Inputs { ck, dataset, case, image_size, regions } = Inputs::load(job, progress)?;
    let explained_on_content = explained_on_content(job, &case, &dataset, ck.meta.background);
    let job = &with_recolouring_schedule(job, explained_on_content);
    let _lock = OutputLock::acquire(&job.out)?;
    let case = strokes::scaled_case(job, case, &dataset, regions.as_deref(), progress)?;
    let resumed = if job.resume { ResumeState::load(job)? } else { None };
    announce_start(job, &dataset, resumed.is_some(), progress);
    let mut phases = PhaseLog::default();
    let mut warnings = WarningLog::new(progress);
    let coarse = coarse::coarse_dataset(job, &dataset, &case)?;
    let registration =
        phases.run("registration", 0, || registration(job, &ck, &dataset, &case, regions.as_deref(), &mut warnings))?;
    let registered_fraction = registration.fraction_overall();
    let (styles, style_colours, colour_transfer) =
        style_side(job, &case, &dataset, &registration, ck.meta.background, &mut warnings)?;
    let register_coarse = |small: &Dataset| {
        progress.info(coarse::announce(job, small, &dataset));
        phases.run("registration_coarse", 0, || inputs::registration(job, &ck, small, &case, None, &mut warnings))
    };
    let (work, registration, styles, fine) =
        coarse::stages(coarse.as_ref(), &dataset, registration, styles, register_coarse)?;
    let image_size = coarse::view_size(work).unwrap_or(image_size);
    // The field's meta (its march) as the stylized grid has it.
    let (grid, meta) = field::colour_grid(ck.grid, &ck.meta, job.config.colour_grid_scale, &job.backend.device())?;
    let mut st = Stylization::new(job, StyleStep::new(job, work, grid, &meta, registration), colour_transfer, fine);
    let start = st.refit_or_resume(resumed.as_ref(), &mut phases, progress)?;
    st.step.set_regions(regions);
    if job.method == Method::RefNpr && st.step.regions.is_none() {
        st.step.stylize_far(progress);
    }
    let colour = job.method == Method::RefNpr && job.config.ablation.use_colour_loss && case.color_pre;
    st.colour_map = fit_colour_map(job, &st.step, &styles, explained_on_content, progress);
    let (guidance, colour_matched) = st.content_phase(&styles, colour, image_size, &mut phases, progress)?;
    let local_edit = st.local_edit(&guidance, progress)?;
    st.recolour_field();
    if let Some(state) = resumed {
        st.restore(state);
    }
    st.image_epochs(&styles, guidance, start, &mut phases, progress)?;
    let sample_cache = st.step.samples.report(st.step.sample_cache_mb);
    st.apply_controls();
    let post_colour_transfer = st.post_colour_transfer(style_colours, progress)?;
    let steps = st.curve.iter().filter(|p| p.phase != StepKind::Refit).count();
    save_outputs(&st.step, steps, &meta, job, started)?;
    let report = StylizeReport {
        method: job.method,
        backend: job.backend.to_string(),
        photo: job.photo.clone(),
        case: job.case.clone(),
        config: job.config.clone(),
        registration: job.registration.clone(),
        views: dataset.train.len(),
        image_size: coarse::view_size(&dataset).unwrap_or(image_size),
        registered_pixels: st.step.samples.registered.len(),
        registered_fraction,
        colour_matched_fraction: colour_matched,
        colour_map: st.colour_map.as_ref().map(|f| f.report),
        colour_transfer: st.colour_transfer,
        post_colour_transfer,
        total_seconds: started.elapsed().as_secs_f64(),
        seconds: phases.seconds,
        transfers: phases.transfers,
        step_profiles: std::mem::take(&mut st.step_profiles),
        peak_rss_mb: peak_rss_mb(),
        memory: phases.memory,
        memory_plan: st.memory_plan,
        held: std::mem::take(&mut st.held),
        sample_cache,
        local_edit,
        final_losses: st.curve.iter().rev().find(|p| p.phase != StepKind::Refit).cloned(),
        curve: std::mem::take(&mut st.curve),
        warnings: warnings.into_vec(),
    };
    files::write_json(&job.out.join("stylize.json"), &report)?;
    ResumeState::remove(&job.out);
    render_test_views(job, &dataset, progress)?;
    progress.event(Event::JobDone);
    Ok(report)
}

/// The event a run starts with: its name, backend and work in pixels.
fn announce_start(job: &StylizeJob, dataset: &Dataset, resumed: bool, progress: &dyn Progress) {
    progress.event(Event::JobStart(Work {
        job: job_name(job.method),
        backend: job.backend.to_string(),
        shape: dataset.shape_name().into(),
        units: job.work_units(dataset.train_pixels()),
        pixels: dataset.train_pixels(),
        resumed,
    }));
}

/// A stylization in progress: its step, the loss curve so far, and what
/// its resume points hold.
struct Stylization<'a> {
    job: &'a StylizeJob,
    step: StyleStep<'a>,
    /// ARF: the photos are recoloured with this before the refit.
    colour_transfer: Option<ColourTransfer>,
    /// Ref-NPR with `[colour_map]` on: the references' colour mapping.
    colour_map: Option<FittedMap>,
    curve: Vec<CurvePoint>,
    /// The field after the refit and when the smooth update began: the
    /// guides were built from them, so a resumed run rebuilds them from these.
    refit_sh: Vec<f32>,
    smooth_sh: Option<Vec<f32>>,
    /// The image step of the last `resume.bin` written by this run.
    saved_at: Option<usize>,
    /// Each finished phase's step profile (`refit`, `image_epochs`, `smooth_update`).
    step_profiles: BTreeMap<String, Vec<PartTime>>,
    /// Coarse epochs (`schedule.coarse_scale`): the views at full size, for the smooth update.
    fine: Option<FineStage<'a>>,
    /// What the run held when each phase ended.
    held: BTreeMap<String, HeldMemory>,
    /// The memory budget's plan.
    memory_plan: Option<MemoryPlan>,
}

impl<'a> Stylization<'a> {
    fn new(
        job: &'a StylizeJob,
        mut step: StyleStep<'a>,
        colour_transfer: Option<ColourTransfer>,
        fine: Option<FineStage<'a>>,
    ) -> Self {
        if let (true, Some(tf)) = (job.method == Method::Arf && job.config.arf.transfer_grid, colour_transfer) {
            step.field.apply_colour_transfer(&tf);
        }
        Stylization {
            job,
            step,
            colour_transfer,
            colour_map: None,
            curve: Vec::new(),
            refit_sh: Vec::new(),
            smooth_sh: None,
            saved_at: None,
            step_profiles: BTreeMap::new(),
            fine,
            held: BTreeMap::new(),
            memory_plan: None,
        }
    }

    /// The refit and the first resume point; or, resuming, the field as the
    /// refit left it. Returns the image steps already done.
    fn refit_or_resume(
        &mut self,
        resumed: Option<&ResumeState>,
        phases: &mut PhaseLog,
        progress: &dyn Progress,
    ) -> Result<usize> {
        self.plan_memory(progress)?;
        match resumed {
            None => {
                let m = transfer::measure(|| self.refit(progress));
                m.value?;
                self.finish_refit()?;
                let steps = self.curve.iter().filter(|p| p.phase == StepKind::Refit).count();
                phases.record("refit", m.seconds, PhaseTransfers::new(m.moved, steps));
                self.held.insert("refit".into(), self.step.held(None));
                Ok(0)
            }
            Some(state) => {
                progress.info(format!(
                    "resuming {} after image step {} (the refit is done)",
                    resume::path(&self.job.out).display(),
                    state.image_steps
                ));
                self.start_from_refit(state)?;
                Ok(state.image_steps)
            }
        }
    }

    /// The memory budget's plan, before the sample cache is filled: the
    /// cache's size and the views whose content features are kept.
    fn plan_memory(&mut self, progress: &dyn Progress) -> Result<()> {
        let fine = self.fine.as_ref().map(|f| f.dataset);
        let references = self.step.samples.registration.references.len();
        let per_ray = self.step.samples.reference_list_bytes_per_ray();
        if let Some(plan) = budget::plan(self.job, self.step.dataset(), fine, references, per_ray)? {
            progress.info(plan.describe());
            self.step.sample_cache_mb = plan.sample_cache_mb;
            self.step.content_views_kept = plan.content_views_kept;
            self.memory_plan = Some(plan);
        }
        Ok(())
    }

    /// Ray epochs: refit the degree-0 colour to the photos (MSE, SH TV);
    /// ARF: to the recoloured photos.
    fn refit(&mut self, progress: &dyn Progress) -> Result<()> {
        let (job, dataset, background) = (self.job, self.step.dataset(), self.step.background());
        let mut colours: Vec<[f32; 3]> =
            dataset.train.iter().flat_map(|v| crate::util::image::pixels(&v.rgb)).collect();
        if let Some(tf) = &self.colour_transfer {
            // Background pixels stay: rays that miss the scene render the
            // fixed background colour, and a recoloured target there could
            // never be fitted (lego: 70 % of the pixels).
            colours.iter_mut().filter(|c| !is_background(c, background)).for_each(|c| *c = tf.apply(*c));
        }
        // The refit's rays are training pixels: with the views' lists cached
        // first, a step copies its rays' lists instead of marching them.
        self.step.cache_samples();
        let s = &job.config.schedule;
        let steps = (s.ray_epochs as f64 * colours.len() as f64 / s.ray_batch as f64).ceil() as usize;
        progress.event(Event::Start { phase: Phase::Refit, done: 0, total: steps });
        if !job.config.optim.keep_state {
            self.step.field.reset_optimiser();
        }
        for step in 0..steps {
            let started = Instant::now();
            let point = self.step.refit_step(step, &colours);
            let mse = point.total;
            diverged::check_loss(mse, Phase::Refit, step + 1, || self.what_is_kept())?;
            let message = format!("mse {mse:.5} psnr {:.2}", psnr_from_mse(mse));
            progress.event(Event::Step { phase: Phase::Refit, done: step + 1, total: steps, message });
            self.curve.push(CurvePoint { seconds: started.elapsed().as_secs_f32(), ..point });
        }
        self.finish_profile("refit");
        Ok(())
    }

    /// `colour_map.init_field`: the refit field's colours through the map
    /// (after the first guides, whose content renders stay the photos'); a
    /// local edit's voxels only.
    fn recolour_field(&mut self) {
        if let (true, Some(fitted)) = (self.job.config.colour_map.init_field, &self.colour_map) {
            let only = self.step.edit.as_ref().map(|e| &e.rows[..]);
            self.step.field.apply_colour_map(&fitted.map, only);
        }
    }

    /// `[controls]`: `preserve_colour` (the refit photo's chroma under the
    /// stylized luminance), then `style_strength` (the blend with the refit photo).
    fn apply_controls(&mut self) {
        let controls = &self.job.config.controls;
        if controls.preserve_colour {
            self.step.field.keep_chroma_of(&self.refit_sh);
        }
        if controls.style_strength != 1.0 {
            self.step.field.blend_with(&self.refit_sh, controls.style_strength);
        }
    }

    /// A local edit: its voxels (from then on the only ones the optimiser
    /// changes), and each reference's region drawn over its render as
    /// `region_R.png`.
    fn local_edit(&mut self, guidance: &Guidance, progress: &dyn Progress) -> Result<Option<LocalEditReport>> {
        let Some(regions) = self.step.regions.take() else {
            return Ok(None);
        };
        let edit = self.step.edit_region(&regions, &guidance.guides)?;
        self.step.samples.keep_reference_pixels(|r, i| regions[r].inside[i]);
        for (r, region) in regions.iter().enumerate() {
            region.overlay(&self.step.render_reference(r)).save_png(&self.job.out.join(format!("region_{r}.png")))?;
        }
        let report = LocalEditReport {
            painted_pixels: regions.iter().map(PixelRegion::count).collect(),
            seen_voxels: edit.seen,
            matched_voxels: edit.matched,
            voxels: edit.rows.len(),
        };
        progress.info(format!(
            "local edit: {} voxels a reference sees and {} matched by TCM (of {}); the rest keeps the photoreal field",
            report.seen_voxels, report.matched_voxels, report.voxels
        ));
        (self.step.edit, self.step.regions) = (Some(edit), Some(regions));
        Ok(Some(report))
    }

    /// The content phase: the sample cache, then the first guides; writes
    /// `colour_targets.json` when L_color is on. Returns the guidance and
    /// the fraction of relu5 positions the colour loss supervises.
    fn content_phase(
        &mut self,
        styles: &[Image],
        colour: bool,
        [w, h]: [usize; 2],
        phases: &mut PhaseLog,
        progress: &dyn Progress,
    ) -> Result<(Guidance, f32)> {
        let views = self.step.dataset().train.len();
        let keep =
            keeps_content(self.job).then_some(match (&self.colour_map, self.job.config.colour_map.mapped_content) {
                (Some(fitted), true) => Content::Mapped(&fitted.map),
                _ => Content::Render,
            });
        let source = colour.then_some(match (&self.colour_map, self.job.config.colour_map.colour_targets) {
            (Some(fitted), true) => fitted.targets(&self.job.config),
            _ => ColourSource::Matched,
        });
        let (guidance, matched) =
            phases.run("content", views, || guides::guidance(&mut self.step, styles, keep, source, progress))?;
        let held = self.step.held(Some(&guidance));
        progress.event(Event::Detail(held.describe()));
        self.held.insert("content".into(), held);
        let cache = self.step.samples.report(self.step.sample_cache_mb);
        progress.event(Event::Detail(format!(
            "sample cache: {} of {} views{}, {:.0} MB of {} ({} samples in {} cells)",
            cache.views_cached,
            cache.views,
            if cache.registered_cached { " and the registered pixels" } else { "" },
            cache.mb,
            cache.budget_mb,
            cache.samples,
            cache.cells
        )));
        if colour {
            // What L_color pulls each view towards, for inspection (small: one entry per target patch).
            let records: Vec<_> = guidance
                .guides
                .iter()
                .enumerate()
                .filter_map(|(v, g)| g.colour().map(|c| c.to_record(v, w, h)))
                .collect();
            files::write_json(&self.job.out.join("colour_targets.json"), &records)?;
        }
        Ok((guidance, matched))
    }

    /// The image epochs, one `image_step` per training view in a seeded
    /// order; the last `smooth_fraction` of them (Ref-NPR) are the smooth
    /// content update, where the stylized field becomes the content
    /// generator. A resumed run passes the image steps already done as
    /// `start`. Records the phases `image_epochs`, `smooth_update` and
    /// `smooth_update_guides` (the content renders of the new guides).
    fn image_epochs(
        &mut self,
        styles: &[Image],
        mut guidance: Guidance,
        start: usize,
        phases: &mut PhaseLog,
        progress: &dyn Progress,
    ) -> Result<()> {
        let job = self.job;
        let s = &job.config.schedule;
        let views = self.step.dataset().train.len();
        let total_steps = s.image_epochs * views;
        let smooth_start = s.image_epochs - self.job.smooth_epochs().min(s.image_epochs);
        if !job.config.optim.keep_state && start == 0 {
            self.step.field.reset_optimiser();
        }
        let started = Instant::now();
        let mut smooth_started = None;
        // Per-step traffic, the smooth update's guides (content renders) apart.
        let (mut image_moved, mut smooth_moved, mut guides_moved) = Default::default();
        progress.event(Event::Start { phase: Phase::ImageEpochs, done: start, total: total_steps });
        let mut step = 0;
        for epoch in 0..s.image_epochs {
            let smooth = epoch >= smooth_start;
            if smooth && smooth_started.is_none() {
                smooth_started = Some(Instant::now());
                self.finish_profile("image_epochs");
                self.held.insert("image_epochs".into(), self.step.held(Some(&guidance)));
                guides_moved = self.start_smooth_update(styles, &mut guidance, step < start, progress)?;
            }
            let mut order: Vec<usize> = (0..views).collect();
            order.shuffle(&mut epoch_rng(job.config.seed, epoch));
            for v in order {
                if step < start {
                    step += 1;
                    continue;
                }
                let moved = self.one_image_step(v, step, (epoch, total_steps), &guidance, smooth, progress)?;
                let sum: &mut Transfers = if smooth { &mut smooth_moved } else { &mut image_moved };
                *sum = sum.plus(moved);
                step += 1;
                let every = s.checkpoint_every;
                if every > 0 && step.is_multiple_of(every) && step < total_steps {
                    self.save_resume_point(step)?;
                }
            }
        }
        let smooth_secs = smooth_started.map(|t| t.elapsed().as_secs_f64()).unwrap_or(0.0);
        let last = if smooth_started.is_some() { "smooth_update" } else { "image_epochs" };
        self.finish_profile(last);
        self.held.insert(last.into(), self.step.held(Some(&guidance)));
        let image_secs = started.elapsed().as_secs_f64() - smooth_secs;
        let smooth_steps = (s.image_epochs - smooth_start) * views;
        phases.record("image_epochs", image_secs, PhaseTransfers::new(image_moved, smooth_start * views));
        phases.record("smooth_update", smooth_secs, PhaseTransfers::new(smooth_moved, smooth_steps));
        phases.transfers.insert("smooth_update_guides".into(), PhaseTransfers::new(guides_moved, 0));
        progress.event(Event::PhaseDone { phase: Phase::ImageEpochs, seconds: image_secs + smooth_secs });
        for (phase, t) in &phases.transfers {
            progress.event(Event::Detail(t.describe(phase)));
        }
        for (phase, parts) in &self.step_profiles {
            progress.event(Event::Detail(format!("{phase} steps: {}", profile::describe(parts))));
        }
        Ok(())
    }

    /// One image step, checked, reported and added to the curve. Returns
    /// what it moved between host and device.
    fn one_image_step(
        &mut self,
        v: usize,
        step: usize,
        (epoch, total_steps): (usize, usize),
        guidance: &Guidance,
        smooth: bool,
        progress: &dyn Progress,
    ) -> Result<Transfers> {
        let m = transfer::measure(|| self.step.image_step(v, step, total_steps, guidance, smooth));
        let mut point = m.value?;
        point.seconds = m.seconds as f32;
        diverged::check_loss(point.total, Phase::ImageEpochs, step + 1, || self.what_is_kept())?;
        let message = format!(
            "epoch {}/{} {:?} | total {:.4} ref {:.4} feat {:.4} colour {:.4}",
            epoch + 1,
            self.job.config.schedule.image_epochs,
            point.phase,
            point.total,
            point.reference,
            point.feature,
            point.colour
        );
        progress.event(Event::Step { phase: Phase::ImageEpochs, done: step + 1, total: total_steps, message });
        self.curve.push(point);
        Ok(m.moved)
    }

    /// The smooth update begins: new guides from the stylized field (as it
    /// was at this point: a run `resumed_past` it rebuilds them from the
    /// kept `smooth_sh`). Returns what building them moved.
    fn start_smooth_update(
        &mut self,
        styles: &[Image],
        guidance: &mut Guidance,
        resumed_past: bool,
        progress: &dyn Progress,
    ) -> Result<Transfers> {
        let now = match (&self.smooth_sh, resumed_past) {
            (Some(then), true) => {
                let then = self.step.sh_tensor(then);
                Some(std::mem::replace(&mut self.step.field.grid.sh, then))
            }
            _ => None,
        };
        if !self.job.config.colour_map.in_smooth_update {
            // Nothing of the old guides is read again: freed before the new
            // ones are built, not held beside them (with coarse epochs they
            // were held beside the full-size sample cache: lego 400's peak).
            (guidance.guides, guidance.template) = (Vec::new(), None);
        }
        let m = transfer::measure(|| self.smooth_guides(styles, progress));
        let (mut guides, t) = m.value?;
        if self.job.config.colour_map.in_smooth_update {
            // L_color stays, with the first guides' targets (from the photo content renders).
            for (new, old) in guides.iter_mut().zip(&mut guidance.guides) {
                new.colour = old.colour.take();
            }
        }
        (guidance.guides, guidance.template) = (guides, Some(t));
        match now {
            Some(now) => self.step.field.grid.sh = now,
            None => self.smooth_sh = Some(to_vec(self.step.field.grid.sh.clone())),
        }
        Ok(m.moved)
    }

    /// The smooth update's template and guides from the field as it is,
    /// on the views at full size (coarse epochs switch to them here); with
    /// `schedule.coarse_matches`, TCM matched on the coarse views first and
    /// carried to full size.
    fn smooth_guides(&mut self, styles: &[Image], progress: &dyn Progress) -> Result<(Vec<ViewGuide>, Template)> {
        let Some(fine) = self.fine.take() else {
            let t = guides::template(&self.step, styles)?;
            return Ok((guides::guides(&self.step, Some(&t), None, None, progress)?.0, t));
        };
        let coarse = match self.job.config.schedule.coarse_matches {
            true => {
                let t = guides::template(&self.step, styles)?;
                let matches = guides::coarse_matches(&self.step, &t, progress)?;
                Some((t, matches))
            }
            false => None,
        };
        let size = coarse::view_size(fine.dataset).map(|[w, h]| format!("{w}x{h}")).unwrap_or_default();
        progress.info(format!("smooth update on the views at full size ({size} views)"));
        self.step.use_views(fine.dataset, fine.registration);
        let t = guides::template(&self.step, &fine.styles)?;
        if let Some(carried) = coarse.and_then(|(c, matches)| guides::carried_guides(&self.step, &c, matches, &t)) {
            return Ok((carried, t));
        }
        Ok((guides::guides(&self.step, Some(&t), None, None, progress)?.0, t))
    }

    /// Files the step profile of the phase that just ended under `phase`.
    fn finish_profile(&mut self, phase: &str) {
        let parts = self.step.take_profile();
        if !parts.is_empty() {
            self.step_profiles.insert(phase.to_string(), parts);
        }
    }

    /// What a diverged run leaves: its checkpoint is written only at its
    /// end; its last resume point, if any, is good.
    fn what_is_kept(&self) -> String {
        let out = &self.job.out;
        match self.saved_at {
            Some(k) => format!(
                "the last resume point, {} (image step {k}), is kept: `--resume` continues from it",
                resume::path(out).display()
            ),
            None => format!("nothing was written to {}", out.join(checkpoint::CHECKPOINT_FILE).display()),
        }
    }

    /// The refit is over: its field is kept (the guides are built from it)
    /// and the first resume point written.
    fn finish_refit(&mut self) -> Result<()> {
        self.refit_sh = to_vec(self.step.field.grid.sh.clone());
        self.save_resume_point(0)
    }

    /// Writes `OUT/resume.bin` after `image_steps` image steps; refuses a
    /// field that is not finite (a resume point must be good).
    fn save_resume_point(&mut self, image_steps: usize) -> Result<()> {
        let state = ResumeState {
            job: JobKey::of(self.job),
            refit_sh: self.refit_sh.clone(),
            smooth_sh: self.smooth_sh.clone(),
            sh: to_vec(self.step.field.grid.sh.clone()),
            rms: to_vec(self.step.field.rms()),
            image_steps,
            optimiser_steps: self.step.optimiser_steps,
            curve: self.curve.clone(),
        };
        if let Some(what) = diverged::first_non_finite(&[("SH colour", &state.sh), ("RMSprop state", &state.rms)]) {
            bail!(
                "the field's {what} holds NaN or infinite values after image step {image_steps}; {}",
                self.what_is_kept()
            );
        }
        state.save(&self.job.out)?;
        self.saved_at = Some(image_steps);
        Ok(())
    }

    /// A resumed run: the field as the refit left it (to rebuild the first
    /// guides from).
    fn start_from_refit(&mut self, state: &ResumeState) -> Result<()> {
        let rows = self.step.field.grid.num_rows();
        if state.refit_sh.len() != rows * 3 || state.sh.len() != rows * 3 || state.rms.len() != rows * 3 {
            bail!("{} does not fit this photoreal run's grid", resume::path(&self.job.out).display());
        }
        self.refit_sh = state.refit_sh.clone();
        self.step.field.grid.sh = self.step.sh_tensor(&state.refit_sh);
        Ok(())
    }

    /// A resumed run, once its first guides are built: the field, optimiser
    /// state, step count and curve as the killed run left them.
    fn restore(&mut self, state: ResumeState) {
        self.step.field.grid.sh = self.step.sh_tensor(&state.sh);
        self.step.field.set_rms(self.step.sh_tensor(&state.rms));
        self.smooth_sh = state.smooth_sh;
        self.step.optimiser_steps = state.optimiser_steps;
        self.curve = state.curve;
        self.saved_at = Some(state.image_steps);
    }

    /// ARF's second colour transfer (`arf.post_transfer`), towards the style's colours.
    fn post_colour_transfer(
        &mut self,
        style_colours: Option<ColourStats>,
        progress: &dyn Progress,
    ) -> Result<Option<ColourTransfer>> {
        let cfg = &self.job.config;
        let Some(style) = style_colours.filter(|_| cfg.arf.post_transfer) else { return Ok(None) };
        let tf = self.step.post_colour_transfer(&style, cfg.arf.transfer_pixels)?;
        progress.info(format!("ARF colour transfer after stylizing: {:?} + {:?}", tf.matrix, tf.offset));
        Ok(Some(tf))
    }
}

/// The name a stylization carries in the cost ledger (`util::costs`).
fn job_name(method: Method) -> String {
    format!("stylize {method}")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stylize::config::StylizeConfig;
    use crate::util::costs::Ledger;

    /// Both methods find the reference machine's record before this machine has one.
    #[test]
    fn both_methods_are_estimated_before_their_first_run() {
        let ledger = Ledger::at(crate::test_support::temp_dir("stylize-costs").join("costs.jsonl"));
        for method in [Method::RefNpr, Method::Arf] {
            let work = Work {
                job: job_name(method),
                backend: "flex".into(),
                shape: "around".into(),
                units: 1e6,
                pixels: 1e5,
                resumed: false,
            };
            assert!(ledger.estimate(&work).is_some(), "no estimate for {}", work.job);
        }
    }

    /// Coarse epochs count at the coarse views' pixels, the smooth update
    /// at the views' own: the estimate of a `--coarse-scale 2` run is not
    /// the full-size run's (lego 400's was, at 1 h 30 min).
    #[test]
    fn coarse_epochs_count_at_their_pixels_in_the_estimate() {
        let job = |method, coarse_scale| {
            let mut config = StylizeConfig::default();
            config.schedule.coarse_scale = coarse_scale;
            StylizeJob {
                photo: "photo".into(),
                case: "case".into(),
                out: "out".into(),
                config,
                method,
                backend: Default::default(),
                style: None,
                data: None,
                registration: None,
                render_test: false,
                resume: false,
            }
        };
        // The default schedule: 2 refit epochs, 10 image epochs of which the last 3 smooth.
        let full = job(Method::RefNpr, 1);
        assert_eq!(full.smooth_epochs(), 3);
        assert_eq!(full.work_units(1000.0), 12_000.0);
        assert_eq!(job(Method::RefNpr, 2).work_units(1000.0), 1000.0 * (9.0 / 4.0 + 3.0));
        assert_eq!(job(Method::Arf, 1).smooth_epochs(), 0);
        assert_eq!(job(Method::Arf, 1).work_units(1000.0), 12_000.0);
    }
}
