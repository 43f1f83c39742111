//! Coarse image epochs (`schedule.coarse_scale`): a Ref-NPR run whose
//! views are large does everything before the smooth update - R³, the
//! refit, the guides and the image epochs - on its training views made
//! `coarse_scale` times smaller, and the smooth update on the views at
//! their own size. An image step's cost follows its view's pixels (VGG16,
//! TCM, the sample lists); the grid is the same at both sizes, so the
//! coarse epochs' field is where the full-size epochs start.

use anyhow::{Result, ensure};

use crate::reference::case::ReferenceCase;
use crate::reference::registration::RegistrationFile;
use crate::scene::data::Dataset;
use crate::stylize::{Method, StylizeJob};
use crate::util::image::Image;
use crate::vgg;

/// What the smooth update switches to: the views at their own size, their
/// registration and the paintings at the references' own size.
pub(crate) struct FineStage<'d> {
    pub dataset: &'d Dataset,
    pub registration: RegistrationFile,
    pub styles: Vec<Image>,
}

/// The training views of the coarse epochs (None: `coarse_scale` 1);
/// refuses, before any work, what the coarse epochs cannot do.
pub(crate) fn coarse_dataset(job: &StylizeJob, dataset: &Dataset, case: &ReferenceCase) -> Result<Option<Dataset>> {
    let n = job.config.schedule.coarse_scale;
    if n == 1 {
        return Ok(None);
    }
    ensure!(
        job.method == Method::RefNpr,
        "schedule.coarse_scale = {n}: coarse epochs end in Ref-NPR's smooth update at full size, which ARF does not \
         have (ARF: set it to 1; arf.half_resolution halves what VGG16 sees)"
    );
    ensure!(
        !case.is_local(),
        "schedule.coarse_scale = {n}: a local edit (`region` in {}) runs at the views' full size: set coarse_scale = 1",
        case.dir.display()
    );
    ensure!(
        job.registration.is_none(),
        "schedule.coarse_scale = {n}: --registration was registered on the views at full size, and the coarse \
         views are registered here: leave out --registration, or set coarse_scale = 1"
    );
    let Some(k) = dataset.train.first().map(|v| v.camera.intrinsics) else { return Ok(None) };
    let (w, h) = (k.width / n, k.height / n);
    ensure!(
        w as usize >= vgg::MIN_SIDE && h as usize >= vgg::MIN_SIDE,
        "schedule.coarse_scale = {n} makes the {}x{} training views {w}x{h}, below the {2}x{2} VGG16 needs: \
         use a smaller coarse_scale",
        k.width,
        k.height,
        vgg::MIN_SIDE
    );
    Ok(Some(dataset.with_train_downscaled(n)))
}

/// The views, registration and paintings the run starts on, and what the
/// smooth update switches to: without coarse views, the full-size ones
/// throughout; with them, `register_coarse` registers the coarse views and
/// the paintings are brought to their references' coarse sizes.
pub(crate) fn stages<'d>(
    coarse: Option<&'d Dataset>,
    full: &'d Dataset,
    registration: RegistrationFile,
    styles: Vec<Image>,
    register_coarse: impl FnOnce(&Dataset) -> Result<RegistrationFile>,
) -> Result<(&'d Dataset, RegistrationFile, Vec<Image>, Option<FineStage<'d>>)> {
    let Some(small) = coarse else { return Ok((full, registration, styles, None)) };
    let coarse_registration = register_coarse(small)?;
    let small_styles = coarse_styles(&styles, &coarse_registration);
    Ok((small, coarse_registration, small_styles, Some(FineStage { dataset: full, registration, styles })))
}

/// The paintings at the coarse references' sizes: block means where a
/// reference is a whole number of times smaller (a training view), else
/// resized (a reference camera of its own stays at its size).
pub(crate) fn coarse_styles(styles: &[Image], coarse: &RegistrationFile) -> Vec<Image> {
    styles
        .iter()
        .zip(&coarse.references)
        .map(|(style, r)| {
            let (w, h) = (r.camera.intrinsics.width as usize, r.camera.intrinsics.height as usize);
            let n = style.width / w.max(1);
            match (style.width, style.height) {
                (sw, sh) if (sw, sh) == (w, h) => style.clone(),
                (sw, sh) if n > 1 && sw / n == w && sh / n == h => style.block_mean(n),
                _ => style.resized(w, h),
            }
        })
        .collect()
}

/// The size `[width, height]` of `dataset`'s training views (the first's).
pub(crate) fn view_size(dataset: &Dataset) -> Option<[usize; 2]> {
    dataset.train.first().map(|v| [v.camera.intrinsics.width as usize, v.camera.intrinsics.height as usize])
}

/// The line a coarse run starts with.
pub(crate) fn announce(job: &StylizeJob, coarse: &Dataset, full: &Dataset) -> String {
    let size = |d| view_size(d).map(|[w, h]| format!("{w}x{h}")).unwrap_or_default();
    format!(
        "coarse epochs (schedule.coarse_scale = {}): R³, the refit and the image epochs on the views at {}, the \
         smooth update at {}",
        job.config.schedule.coarse_scale,
        size(coarse),
        size(full)
    )
}
