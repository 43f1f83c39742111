//! Whether a reference is a recolouring, told before any work on the field:
//! what a one-reference case's colour map explains of its painting on the
//! image it was painted over (content.png), and the schedule such a case
//! runs with (`[colour_map] recolour_lr_schedule`), and the colour map
//! fitted on the refit field's renders of the references.

use crate::reference::case::ReferenceCase;
use crate::scene::data::Dataset;
use crate::stylize::colour_map::ColourMap;
use crate::stylize::config::StylizeConfig;
use crate::stylize::guides::ColourSource;
use crate::stylize::step::StyleStep;
use crate::stylize::styles::painted_over;
use crate::stylize::{ColourMapReport, Method, StylizeJob};
use crate::util::image::Image;
use crate::util::progress::Progress;

/// What a one-reference case's colour map explains of its painting,
/// measured on the image it was painted over (`painted_over`: content.png),
/// before any work on the field. None for ARF, with the colour map off, or
/// for a case without content.png (then measured on the refit render,
/// after the refit).
pub(crate) fn explained_on_content(
    job: &StylizeJob,
    case: &ReferenceCase,
    dataset: &Dataset,
    background: [f32; 3],
) -> Option<f32> {
    if job.method != Method::RefNpr || !job.config.colour_map.is_on() {
        return None;
    }
    let (content, style) = painted_over(case, dataset, background)?;
    let pair = [(&content, &style)];
    Some(ColourMap::fit(&pair, &job.config.colour_map, background).explained(&pair))
}

/// The job as it runs: a recolouring recognised on content.png takes
/// `[colour_map] recolour_lr_schedule` for the whole stylization, the
/// refit included (it must be known before the refit's first step). The
/// run's stylize.json and resume key carry the schedule it ran with.
pub(crate) fn with_recolouring_schedule(job: &StylizeJob, explained_on_content: Option<f32>) -> StylizeJob {
    let mut job = job.clone();
    let cm = &job.config.colour_map;
    if explained_on_content.is_some_and(|e| e >= cm.recolour_explained) {
        job.config.schedule.lr_schedule = cm.recolour_lr_schedule;
    }
    job
}

/// The references' colour map and what its fit says of the case.
pub(crate) struct FittedMap {
    pub map: ColourMap,
    pub report: ColourMapReport,
}

impl FittedMap {
    /// L_color's targets through the map: a recolouring's weight and
    /// patches, or `[loss] colour` over `target_patch`-pixel patches.
    pub fn targets(&self, cfg: &StylizeConfig) -> ColourSource<'_> {
        let c = &cfg.colour_map;
        let (patch, weight) = match self.report.recolouring {
            true => (c.recolour_patch, c.recolour_weight),
            false => (c.target_patch, cfg.loss.colour),
        };
        ColourSource::Mapped { map: &self.map, patch, weight }
    }
}

/// Ref-NPR with `[colour_map]` on: fits the references' colour mapping
/// on their content renders from the refit field. Whether it is a
/// recolouring is measured on content.png where the case keeps it
/// (`explained_on_content`): the refit render differs from the photo
/// render by the refit's own error, which can outweigh a mild grade's
/// whole change (lego teal-orange: 45 % explained on the refit render).
pub(crate) fn fit_colour_map(
    job: &StylizeJob,
    step: &StyleStep,
    styles: &[Image],
    explained_on_content: Option<f32>,
    progress: &dyn Progress,
) -> Option<FittedMap> {
    let cfg = &job.config.colour_map;
    if job.method != Method::RefNpr || !cfg.is_on() {
        return None;
    }
    // A local edit's map is fitted on its regions: the content outside them
    // is set to the background, which the fit skips (a reference's unpainted
    // pixels are the photo, and would pull the map towards no change).
    let contents: Vec<Image> = (0..styles.len())
        .map(|r| match &step.regions {
            Some(regions) => regions[r].outside_filled(&step.render_reference(r), step.background()),
            None => step.render_reference(r),
        })
        .collect();
    let pairs: Vec<(&Image, &Image)> = contents.iter().zip(styles).collect();
    let map = ColourMap::fit(&pairs, cfg, step.background());
    let (explained, explained_on) = match explained_on_content {
        Some(e) => (e, "content.png"),
        None => (map.explained(&pairs), "the refit render"),
    };
    let recolouring = explained >= cfg.recolour_explained;
    let report = ColourMapReport { pixels: map.pixels, explained, explained_on, recolouring };
    let map = match report.recolouring {
        true => ColourMap::fit(&pairs, &cfg.recolouring(), step.background()),
        false => map,
    };
    progress.info(format!(
        "colour map fitted on {} reference pixels; it explains {:.0} % of the painting's change (measured on {explained_on}){}",
        map.pixels,
        100.0 * explained,
        match report.recolouring {
            true => format!(
                ": a recolouring (the map fitted again sharper, L_color {} over {}-pixel patches, the {} learning-rate schedule)",
                cfg.recolour_weight,
                cfg.recolour_patch,
                job.config.schedule.lr_schedule.name()
            ),
            false => String::new(),
        }
    ));
    Some(FittedMap { map, report })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A recolouring told by content.png runs with `[colour_map]
    /// recolour_lr_schedule` from the refit's first step on; painted
    /// strokes, ARF, the colour map off and a case without content.png
    /// keep `[schedule] lr_schedule`.
    #[test]
    fn a_recolouring_on_content_png_takes_its_own_schedule() {
        use crate::scene::data::{self, procedural};
        use crate::stylize::config::LrSchedule;
        let dir = crate::test_support::temp_dir("recolour-schedule");
        let opts =
            procedural::SceneOptions { seed: 2, size: 48, num_train: 1, num_val: 1, num_test: 1, environment: false };
        procedural::write_scene(&dir.join("scene"), &opts).unwrap();
        let dataset = data::load(&dir.join("scene"), &Default::default()).unwrap();
        let view = &dataset.train[0];
        let (w, h) = (view.camera.intrinsics.width as usize, view.camera.intrinsics.height as usize);
        let case_dir = dir.join("case");
        std::fs::create_dir_all(&case_dir).unwrap();
        std::fs::write(case_dir.join("reference.toml"), "[[reference]]\nstyle = \"style.png\"\nview = \"train:0\"\n")
            .unwrap();
        Image::new(w, h, view.rgb.clone()).save_png(&case_dir.join("content.png")).unwrap();
        // A function of colour alone (channels swapped), and yellow stripes
        // painted over every other 4-pixel column (a function of position).
        let swapped: Vec<f32> = view.rgb.chunks_exact(3).flat_map(|c| [c[1], c[2], c[0]]).collect();
        let striped: Vec<f32> = (0..w * h)
            .flat_map(|i| match (i % w / 4) % 2 {
                0 => [1.0, 0.9, 0.1],
                _ => [view.rgb[3 * i], view.rgb[3 * i + 1], view.rgb[3 * i + 2]],
            })
            .collect();
        let schedule = |style: &[f32], method: Method, config: StylizeConfig| {
            Image::new(w, h, style.to_vec()).save_png(&case_dir.join("style.png")).unwrap();
            let case = ReferenceCase::load(&case_dir).unwrap();
            let job = StylizeJob {
                photo: dir.join("photo"),
                case: case_dir.clone(),
                out: dir.join("out"),
                config,
                method,
                backend: Default::default(),
                style: None,
                data: None,
                registration: None,
                render_test: false,
                resume: false,
            };
            let explained = explained_on_content(&job, &case, &dataset, dataset.background);
            with_recolouring_schedule(&job, explained).config.schedule.lr_schedule
        };
        let defaults = StylizeConfig::default();
        assert_eq!(defaults.schedule.lr_schedule, LrSchedule::Shared);
        assert_eq!(schedule(&swapped, Method::RefNpr, defaults.clone()), LrSchedule::PerPhase, "a recolouring");
        assert_eq!(schedule(&striped, Method::RefNpr, defaults.clone()), LrSchedule::Shared, "painted stripes");
        assert_eq!(schedule(&swapped, Method::Arf, defaults.clone()), LrSchedule::Shared, "ARF");
        let mut off = defaults.clone();
        (off.colour_map.init_field, off.colour_map.colour_targets) = (false, false);
        assert_eq!(schedule(&swapped, Method::RefNpr, off), LrSchedule::Shared, "the colour map off");
        let mut shared = defaults.clone();
        shared.colour_map.recolour_lr_schedule = LrSchedule::Shared;
        assert_eq!(schedule(&swapped, Method::RefNpr, shared), LrSchedule::Shared, "recolour_lr_schedule = shared");
        std::fs::remove_file(case_dir.join("content.png")).unwrap();
        assert_eq!(schedule(&swapped, Method::RefNpr, defaults), LrSchedule::Shared, "no content.png");
    }
}
