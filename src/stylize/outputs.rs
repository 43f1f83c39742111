//! What a stylization writes at its end: the stylized checkpoint (a local
//! edit's composed with the photoreal field), the reference renders and
//! the test views.

use std::time::Instant;

use anyhow::Result;
use burn::tensor::Tensor;

use crate::field::checkpoint::{self, CheckpointMeta};
use crate::field::render_path::render_frames;
use crate::scene::camera::Camera;
use crate::scene::data::Dataset;
use crate::stylize::StylizeJob;
use crate::stylize::step::StyleStep;
use crate::util::progress::Progress;

/// The stylized checkpoint (a local edit's: the photoreal field with the
/// edited voxels' colour, at the photo's SH degree and march, so that the
/// rest renders as the photo did) and the reference renders.
pub(crate) fn save_outputs(
    step: &StyleStep,
    image_steps: usize,
    field_meta: &CheckpointMeta,
    job: &StylizeJob,
    started: Instant,
) -> Result<()> {
    let (config, out) = (&job.config, &job.out);
    let mut meta = field_meta.clone();
    meta.run_config = serde_json::to_value(config).expect("a config is plain data");
    meta.step = image_steps;
    meta.train_seconds = started.elapsed().as_secs_f64();
    let composed;
    let grid = match &step.edit {
        None => {
            meta.sh_degree = 0;
            meta.render.march = step.march();
            &step.field.grid
        }
        Some(edit) => {
            let mut photo = checkpoint::load_with(&job.photo, &step.field.grid.device(), false)?;
            edit.compose(&mut photo.grid, &step.field.grid);
            composed = photo.grid;
            &composed
        }
    };
    let (rows, device) = (grid.num_rows(), grid.device());
    let zeros = (Tensor::zeros([rows, 1], &device), Tensor::zeros([rows, 3 * grid.num_basis()], &device));
    checkpoint::save(&out.join(checkpoint::CHECKPOINT_FILE), &meta, grid, &zeros.0, &zeros.1, &[])?;
    // A local edit's reference renders come from the saved field (every SH
    // band outside the edit), as `refnpr render` would draw them; the
    // stylized field alone is what was saved otherwise.
    let saved = match step.edit {
        Some(_) => Some(checkpoint::load_with(&out.join(checkpoint::CHECKPOINT_FILE), &device, false)?),
        None => None,
    };
    for r in 0..step.num_references() {
        let render = match &saved {
            Some(ck) => ck.render_view(&step.samples.registration.references[r].camera).image,
            None => step.render_reference(r),
        };
        render.save_png(&out.join(format!("reference_{r}.png")))?;
    }
    Ok(())
}

/// The stylized test views (`job.render_test`), from the saved checkpoint.
pub(crate) fn render_test_views(job: &StylizeJob, dataset: &Dataset, progress: &dyn Progress) -> Result<()> {
    if job.render_test && !dataset.test.is_empty() {
        let style_ck = checkpoint::load_with(&job.out, &job.backend.device(), false)?;
        let cams: Vec<Camera> = dataset.test.iter().map(|v| v.camera).collect();
        render_frames(&style_ck, &cams, &job.out.join("test"), progress)?;
    }
    Ok(())
}
