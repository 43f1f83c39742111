//! The stylization's memory budget (`memory_gb`, `refnpr stylize
//! --memory-gb`).
//!
//! Once the photos, the field and R³'s registration are loaded, before the
//! refit, the run's peak is predicted: the process's resident memory then,
//! the guides every view will hold (content features, TCM matches, colour
//! targets, the template), the image steps' working set (VGG16's forward
//! and backward and the renders, with what the allocator keeps of freed
//! buffers) and the sample cache, the views' sample lists sized from the
//! reference's (marched by then). The budget goes to the
//! content features first and to the cache (`sample_cache_mb`) with what
//! is left: views whose features are not kept have them taken again at
//! each of their steps, views beyond the cache are marched again, which
//! costs time, not memory. A run that would pass the budget even so is
//! refused there, naming each part and what to change. Without
//! `memory_gb` the budget is most of what the machine has free.
//!
//! The budget counts host memory (on wgpu the device's pools are reported
//! in `stylize.json` beside it, not planned).

use anyhow::{Result, bail};
use serde::Serialize;

use crate::scene::data::Dataset;
use crate::stylize::inputs::keeps_content;
use crate::stylize::tcm::{self, FEATURE_BLOCKS, RELU3};
use crate::stylize::{Method, StylizeJob};
use crate::vgg::VggLayer;

const MB: f64 = 1024.0 * 1024.0;

/// What the image steps add to the process besides the guides and the
/// cache, whatever the views' size: the content phase's and the steps'
/// freed buffers the allocator keeps, VGG16's activations and gradients
/// (`docs/performance.md`, "Memory budget": measured on lego at 200 and
/// 400 px and fern; the same at both lego sizes).
pub const STEP_BASE_MB: f64 = 704.0;

/// And per MB of the largest view's sample lists: a view beyond the cache
/// marched for its step, the render's and the re-render's per-sample
/// buffers (fern, with 7 times lego 400's samples a view, adds 1.3 GB).
pub const STEP_PER_LIST_MB: f64 = 7.0;

/// A view's sample lists against the reference view's, per pixel: views
/// differ in how much of them the scene covers (lego: the mean view's
/// lists are 1.16 times `train:0`'s).
pub const LIST_MARGIN: f64 = 1.25;

/// The share of the machine's free memory a budget takes when none is set.
pub const FREE_SHARE: f64 = 0.9;

/// Where the budget came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum BudgetSource {
    /// `memory_gb` / `--memory-gb`.
    Set,
    /// [`FREE_SHARE`] of the memory the machine had free at the plan.
    FreeMemory,
}

/// What the budget decided, in `stylize.json` (MB throughout).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MemoryPlan {
    pub budget_mb: f64,
    pub source: BudgetSource,
    /// The process's resident memory at the plan (photos, field, registration, VGG16).
    pub resident_mb: f64,
    /// Every view's guides but the content features: TCM matches, colour targets.
    pub guides_mb: f64,
    /// The image steps' working set at the largest views, with what the
    /// allocator keeps of freed buffers.
    pub step_mb: f64,
    /// The content term's features: views kept, of how many, and their MB
    /// (with the images the others' are taken again from).
    pub content_views_kept: usize,
    pub content_views: usize,
    pub content_mb: f64,
    /// The sample cache the budget leaves, at most `sample_cache_mb`.
    pub sample_cache_mb: usize,
    /// What the cache is predicted to fill: the views' lists, at most `sample_cache_mb`.
    pub cache_fill_mb: f64,
    /// `sample_cache_mb` as configured.
    pub configured_cache_mb: usize,
    /// The sum of the parts above.
    pub predicted_peak_mb: f64,
}

/// The sizes a plan is made from (MB).
#[derive(Debug, Clone, Copy)]
pub struct PlanInputs {
    pub resident_mb: f64,
    /// Matches and colour targets of every view.
    pub guides_mb: f64,
    /// Views with a content term (0: none) and, per view, its kept
    /// features and the image they are taken again from.
    pub content_views: usize,
    pub content_features_mb: f64,
    pub content_image_mb: f64,
    /// `keep_content_features`: false keeps none.
    pub keep_content_features: bool,
    pub step_mb: f64,
    pub configured_cache_mb: usize,
    /// The training views' sample lists, all of them (estimated).
    pub lists_mb: f64,
}

impl MemoryPlan {
    /// What the budget gives, in this order: the guides and one step; the
    /// content features of as many views as fit (the others' taken again
    /// at each step: time, not memory); the sample cache, with what is
    /// left. An error naming the parts when even the first does not fit.
    pub fn new(inputs: PlanInputs, budget_mb: f64, source: BudgetSource) -> Result<Self> {
        let PlanInputs { resident_mb, guides_mb, step_mb, configured_cache_mb, content_views, .. } = inputs;
        let (features, image) = (inputs.content_features_mb, inputs.content_image_mb.min(inputs.content_features_mb));
        let fixed = resident_mb + guides_mb + step_mb;
        let least = fixed + content_views as f64 * image;
        if least > budget_mb {
            let budget = match source {
                BudgetSource::Set => "memory_gb / --memory-gb".to_string(),
                BudgetSource::FreeMemory => format!("{:.0} % of the memory this machine has free", FREE_SHARE * 100.0),
            };
            bail!(
                "this stylization needs at least {} (loaded now {}, guides of every view {}, the image steps {}, \
                 content images {}), over its budget of {} ({budget}): raise \
                 --memory-gb if the machine has it, or use --coarse-scale 2 (the image epochs on views half the \
                 size), or a photoreal run on smaller views",
                gb(least),
                gb(resident_mb),
                gb(guides_mb),
                gb(step_mb),
                gb(content_views as f64 * image),
                gb(budget_mb)
            );
        }
        let left = budget_mb - least;
        let extra = features - image;
        let content_views_kept = match (inputs.keep_content_features, extra > 0.0) {
            (false, _) => 0,
            (true, true) => ((left / extra).floor() as usize).min(content_views),
            (true, false) => content_views,
        };
        let content_mb = content_views_kept as f64 * features + (content_views - content_views_kept) as f64 * image;
        let sample_cache_mb = ((budget_mb - fixed - content_mb).floor().max(0.0) as usize).min(configured_cache_mb);
        let cache_fill_mb = inputs.lists_mb.min(sample_cache_mb as f64);
        Ok(Self {
            budget_mb,
            source,
            resident_mb,
            guides_mb,
            step_mb,
            content_views_kept,
            content_views,
            content_mb,
            sample_cache_mb,
            cache_fill_mb,
            configured_cache_mb,
            predicted_peak_mb: fixed + content_mb + cache_fill_mb,
        })
    }

    /// One line for the progress output.
    pub fn describe(&self) -> String {
        let cache = match self.sample_cache_mb < self.configured_cache_mb {
            true => format!(
                "the sample cache gets {} MB of its {} MB (views beyond it are marched again each step)",
                self.sample_cache_mb, self.configured_cache_mb
            ),
            false => format!("the sample cache keeps its {} MB", self.configured_cache_mb),
        };
        let content = match self.content_views_kept < self.content_views {
            true => format!(
                "; content features kept for {} of {} views (the others' taken again at each step)",
                self.content_views_kept, self.content_views
            ),
            false => String::new(),
        };
        let source = match self.source {
            BudgetSource::Set => "set",
            BudgetSource::FreeMemory => "from free memory",
        };
        format!(
            "memory: predicted peak {} of a {} budget ({source}); {cache}{content}",
            gb(self.predicted_peak_mb),
            gb(self.budget_mb)
        )
    }
}

fn gb(mb: f64) -> String {
    format!("{:.2} GB", mb / 1024.0)
}

/// The budget, MB: `memory_gb` when set (> 0), else [`FREE_SHARE`] of the
/// machine's free memory on top of what the process holds; None where the
/// OS does not say (no plan then: the cache keeps `sample_cache_mb`).
pub fn budget_mb(memory_gb: f32, resident_mb: f64) -> Option<(f64, BudgetSource)> {
    if memory_gb > 0.0 {
        return Some((memory_gb as f64 * 1024.0, BudgetSource::Set));
    }
    let free = crate::util::memory::available_memory_bytes()? as f64 / MB;
    Some((resident_mb + FREE_SHARE * free, BudgetSource::FreeMemory))
}

/// The plan for a run whose image epochs see `work`'s training views and,
/// with coarse epochs, whose smooth update sees `fine`'s, and whose
/// references' sample lists take `list_bytes_per_ray` a ray; None where
/// the OS gives no memory figures (the cache keeps `sample_cache_mb`).
pub(crate) fn plan(
    job: &StylizeJob,
    work: &Dataset,
    fine: Option<&Dataset>,
    references: usize,
    list_bytes_per_ray: f64,
) -> Result<Option<MemoryPlan>> {
    let Some(resident_mb) = crate::util::memory::proc_status_mb("VmRSS:") else { return Ok(None) };
    let Some((budget_mb, source)) = budget_mb(job.config.memory_gb, resident_mb) else { return Ok(None) };
    let size = |d: &Dataset| {
        d.train.first().map_or([0, 0], |v| [v.camera.intrinsics.width, v.camera.intrinsics.height].map(|s| s as usize))
    };
    let (views, [w, h]) = (work.train.len(), size(work));
    let method = job.method;
    let guides = |d: &Dataset| {
        let [w, h] = size(d);
        mb(guide_bytes(method, d.train.len(), w, h, 0) + template_bytes(method, references, w, h))
    };
    let guides_mb = fine.map_or(0.0, guides).max(guides(work));
    // What VGG16 sees of a view: ARF's half-resolution renders are halved.
    let [vw, vh] = match method == Method::Arf && job.config.arf.half_resolution {
        true => [w / 2, h / 2],
        false => [w, h],
    };
    let content_bytes = if job.config.half_content_features { 2 } else { 4 };
    let content_views = if keeps_content(job) { views } else { 0 };
    let largest = fine.map_or(w * h, |d| {
        let [fw, fh] = size(d);
        fw * fh
    });
    let inputs = PlanInputs {
        resident_mb,
        guides_mb,
        content_views,
        content_features_mb: mb(guide_bytes(method, 1, vw, vh, content_bytes) - guide_bytes(method, 1, vw, vh, 0)),
        content_image_mb: mb((vw * vh * 3 * 4) as u64),
        keep_content_features: job.config.keep_content_features,
        step_mb: step_mb(view_lists_mb(list_bytes_per_ray, largest.max(w * h))),
        configured_cache_mb: job.config.sample_cache_mb,
        lists_mb: stage_lists_mb(list_bytes_per_ray, (views, w * h), fine.map(|d| (d.train.len(), largest))),
    };
    MemoryPlan::new(inputs, budget_mb, source).map(Some)
}

/// Bytes of `views` views' guides at `width` x `height`: per position of
/// each feature block its matches and, `content_bytes` per channel, the
/// content term's kept features; per relu5 position its colour target.
pub fn guide_bytes(method: Method, views: usize, width: usize, height: usize, content_bytes: usize) -> u64 {
    let features: usize = method
        .feature_blocks()
        .iter()
        .map(|b| {
            let [h, w] = tcm::block_size(b, height, width);
            let c: usize = b.iter().map(|l| l.channels()).sum();
            h * w * (c * content_bytes + 8)
        })
        .sum();
    let [h5, w5] = tcm::block_size(&tcm::RELU5, height, width);
    let colour = match method {
        Method::RefNpr => h5 * w5 * (12 + 4 + 8),
        Method::Arf => 0,
    };
    ((features + colour) * views) as u64
}

/// Bytes of the TCM template of `references` references at `width` x
/// `height` (f32 keys and values per feature block, relu5 colour keys);
/// ARF: its style features (relu3).
pub fn template_bytes(method: Method, references: usize, width: usize, height: usize) -> u64 {
    let features = |block: &[VggLayer]| {
        let [h, w] = tcm::block_size(block, height, width);
        h * w * block.iter().map(|l| l.channels()).sum::<usize>() * 4
    };
    let per_reference = match method {
        Method::RefNpr => FEATURE_BLOCKS.iter().map(|b| 2 * features(b)).sum::<usize>() + features(&tcm::RELU5),
        Method::Arf => features(&RELU3),
    };
    (per_reference * references) as u64
}

/// A view's sample lists at `pixels` pixels, MB, estimated from the
/// references' bytes a ray (with [`LIST_MARGIN`]).
pub fn view_lists_mb(list_bytes_per_ray: f64, pixels: usize) -> f64 {
    LIST_MARGIN * list_bytes_per_ray * pixels as f64 / MB
}

/// What the sample cache would fill, MB: every view's lists in the image
/// epochs (`work`: views, pixels a view) or, with coarse epochs, in the
/// smooth update at full size (`fine`), whichever is more: the cache is
/// emptied and filled again for the full-size views, up to the same size
/// (lego 400 with `--coarse-scale 2`: 1.2 GB of lists at 200 px, the
/// whole 2 GB cache at 400).
pub fn stage_lists_mb(list_bytes_per_ray: f64, work: (usize, usize), fine: Option<(usize, usize)>) -> f64 {
    let lists = |(views, pixels): (usize, usize)| views as f64 * view_lists_mb(list_bytes_per_ray, pixels);
    lists(work).max(fine.map_or(0.0, lists))
}

/// The image steps' working set where the largest view's sample lists take
/// `view_lists_mb`, MB.
pub fn step_mb(view_lists_mb: f64) -> f64 {
    STEP_BASE_MB + STEP_PER_LIST_MB * view_lists_mb
}

/// Bytes to MB.
pub fn mb(bytes: u64) -> f64 {
    bytes as f64 / MB
}

#[cfg(test)]
mod tests {
    use super::*;

    fn inputs(configured_cache_mb: usize) -> PlanInputs {
        PlanInputs {
            resident_mb: 1000.0,
            guides_mb: 200.0,
            content_views: 10,
            content_features_mb: 20.0,
            content_image_mb: 2.0,
            keep_content_features: true,
            step_mb: 600.0,
            configured_cache_mb,
            lists_mb: 10_000.0,
        }
    }

    #[test]
    fn the_budget_goes_to_the_content_features_then_to_the_cache() {
        // Fixed: 1000 + 200 + 600 = 1800 MB; content 10 x 20 MB.
        let roomy = MemoryPlan::new(inputs(2048), 8000.0, BudgetSource::Set).unwrap();
        assert_eq!((roomy.content_views_kept, roomy.sample_cache_mb), (10, 2048));
        assert_eq!(roomy.predicted_peak_mb, 1800.0 + 200.0 + 2048.0);
        // Lists smaller than the cache fill only their own size.
        let small = MemoryPlan::new(PlanInputs { lists_mb: 500.0, ..inputs(2048) }, 8000.0, BudgetSource::Set).unwrap();
        assert_eq!((small.sample_cache_mb, small.cache_fill_mb), (2048, 500.0));
        assert_eq!(small.predicted_peak_mb, 1800.0 + 200.0 + 500.0);
        let tight = MemoryPlan::new(inputs(2048), 2500.0, BudgetSource::Set).unwrap();
        assert_eq!((tight.content_views_kept, tight.sample_cache_mb), (10, 500));
        assert!(tight.describe().contains("500 MB of its 2048 MB"), "{}", tight.describe());
        // 1800 + 10 x 2 = 1820 at least; 90 MB more keeps 5 views' features (18 MB each over the image).
        let tighter = MemoryPlan::new(inputs(2048), 1910.0, BudgetSource::Set).unwrap();
        assert_eq!(tighter.content_views_kept, 5);
        assert_eq!(tighter.content_mb, 5.0 * 20.0 + 5.0 * 2.0);
        assert_eq!(tighter.sample_cache_mb, 0);
        assert!(tighter.predicted_peak_mb <= 1910.0);
        assert!(tighter.describe().contains("kept for 5 of 10 views"), "{}", tighter.describe());
        let none =
            MemoryPlan::new(PlanInputs { keep_content_features: false, ..inputs(2048) }, 8000.0, BudgetSource::Set);
        let none = none.unwrap();
        assert_eq!((none.content_views_kept, none.content_mb, none.sample_cache_mb), (0, 20.0, 2048));
    }

    #[test]
    fn a_budget_below_the_parts_is_refused_naming_them() {
        let err = MemoryPlan::new(inputs(2048), 1800.0, BudgetSource::Set).unwrap_err().to_string();
        assert!(err.contains("needs at least 1.78 GB"), "{err}");
        assert!(err.contains("budget of 1.76 GB (memory_gb / --memory-gb)"), "{err}");
        assert!(err.contains("--coarse-scale 2"), "{err}");
        let bare = PlanInputs { content_views: 0, ..inputs(0) };
        assert!(MemoryPlan::new(bare, 1800.0, BudgetSource::Set).is_ok());
    }

    /// With coarse epochs the cache is filled again at full size: the plan
    /// counts the larger of the two fills (lego 400 at `--coarse-scale 2`
    /// was planned at 4.03 GB from its 200 px lists and peaked at 5.41).
    #[test]
    fn the_cache_fill_counts_the_full_size_stage_of_coarse_epochs() {
        let per_ray = 70.0;
        let coarse = stage_lists_mb(per_ray, (100, 200 * 200), None);
        assert_eq!(coarse, 100.0 * view_lists_mb(per_ray, 200 * 200));
        assert_eq!(stage_lists_mb(per_ray, (100, 200 * 200), Some((100, 400 * 400))), 4.0 * coarse);
        assert_eq!(stage_lists_mb(per_ray, (100, 200 * 200), Some((10, 400 * 400))), coarse);
    }

    #[test]
    fn guides_follow_the_views_pixels() {
        let at = |side| guide_bytes(Method::RefNpr, 100, side, side, 2);
        // relu3 at 1/4 and relu4 at 1/8, three layers each: 768 and 1536 channels, 2 bytes each, 8 for the match.
        let relu = 50 * 50 * (768 * 2 + 8) + 25 * 25 * (1536 * 2 + 8);
        assert_eq!(at(200), ((relu + 12 * 12 * 24) * 100) as u64);
        let ratio = at(400) as f64 / at(200) as f64;
        assert!((3.9..4.1).contains(&ratio), "{ratio}");
        assert_eq!(guide_bytes(Method::RefNpr, 1, 200, 200, 0), (50 * 50 * 8 + 25 * 25 * 8 + 12 * 12 * 24) as u64);
        // Lego at 400 px: 96 MB measured (`held.guides_mb` less the views' guides).
        let template = 2 * (100 * 100 * 768 * 4 + 50 * 50 * 1536 * 4) + 25 * 25 * 1536 * 4;
        assert_eq!(template_bytes(Method::RefNpr, 1, 400, 400), template as u64);
    }
}
