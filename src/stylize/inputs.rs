//! What a stylization starts from, read and checked before any work: the
//! photoreal run, its dataset and the reference case (`Inputs`), the views'
//! size against VGG16 and the feature caches against memory
//! (`preflight`), the pseudo-rays (R³, or a given `registration.bin`) and
//! the style side (the style images, ARF's colour statistics and photo
//! recolouring).

use anyhow::{Result, bail, ensure};

use crate::field::checkpoint::{self, Checkpoint};
use crate::field::march::Marcher;
use crate::reference::case::ReferenceCase;
use crate::reference::registration::{PhotoRun, RegistrationFile, lift_references, register_case};
use crate::scene::data::Dataset;
use crate::stylize::colour_transfer::{ColourStats, ColourTransfer};
use crate::stylize::region::{PixelRegion, reference_regions};
use crate::stylize::styles::{arf_colour_transfer, read_styles, style_colour_stats};
use crate::stylize::{Method, StylizeJob};
use crate::util::image::Image;
use crate::util::progress::{Progress, WarningLog};
use crate::util::transfer;
use crate::vgg;

/// What a stylization starts from: the photoreal run, its dataset and the reference case.
pub(crate) struct Inputs {
    pub ck: Checkpoint,
    pub dataset: Dataset,
    pub case: ReferenceCase,
    /// The training views' size `[width, height]`.
    pub image_size: [usize; 2],
    /// A local edit's painted pixels per reference (`stylize::region`).
    pub regions: Option<Vec<PixelRegion>>,
}

impl Inputs {
    /// Reads and checks them (`preflight`) before any work.
    pub fn load(job: &StylizeJob, progress: &dyn Progress) -> Result<Self> {
        job.config.validate()?;
        let device = job.backend.open(progress)?;
        // The stylized field is view-independent: only the DC band is read.
        let (ck, dataset) = checkpoint::load_run_view_independent(&job.photo, job.data.as_deref(), &device)?;
        // The stylization's steps mix the field's tensors with VGG16's: one device.
        ensure!(
            ck.grid.device() == device,
            "{}: the field's {} voxels of colour do not fit in one of the wgpu adapter's buffers ({}): stylize \
             with --backend flex",
            job.photo.display(),
            ck.grid.num_rows(),
            crate::util::backend::max_buffer_bytes(&device).map(transfer::human_bytes).unwrap_or_default()
        );
        let case = ReferenceCase::load(&job.case)?;
        if let Some(m) = case.scene_mismatch(&dataset) {
            bail!(
                "{m}: the reference case does not belong to the photoreal run {} (fix `scene_name` in the case if it does)",
                job.photo.display()
            );
        }
        let image_size = preflight(job, &dataset)?;
        ensure!(
            !case.is_local() || job.config.colour_grid_scale == 1,
            "{}: a local edit is composed into the photo's own lattice; colour_grid_scale must be 1, got {}",
            job.case.display(),
            job.config.colour_grid_scale
        );
        // A local edit's regions, against the render the painting was made
        // over: the photoreal field with its view-dependent bands.
        let regions = match case.is_local() {
            true => reference_regions(&case, &checkpoint::load_with(&job.photo, &device, false)?, &dataset)?,
            false => None,
        };
        Ok(Inputs { ck, dataset, case, image_size, regions })
    }
}

/// Whether the content features of every view are kept (λ' > 0).
pub(crate) fn keeps_content(job: &StylizeJob) -> bool {
    let cfg = &job.config;
    match job.method {
        Method::RefNpr => cfg.loss.content > 0.0 && cfg.ablation.use_feature_loss,
        Method::Arf => cfg.arf.content > 0.0,
    }
}

/// Refuses, before any work, views too small for VGG16 (memory is planned
/// once the inputs are loaded: `stylize::budget`). Returns the views' size
/// `[width, height]`.
fn preflight(job: &StylizeJob, dataset: &Dataset) -> Result<[usize; 2]> {
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
    Ok([width, height])
}

/// The pseudo-rays: R³ on the photoreal field (a local edit's: its regions
/// only), or the `registration.bin` of `job.registration` after checking it
/// belongs to this run and case; a warning when Ref-NPR gets no registered pixel.
pub(crate) fn registration(
    job: &StylizeJob,
    ck: &Checkpoint,
    dataset: &Dataset,
    case: &ReferenceCase,
    regions: Option<&[PixelRegion]>,
    warnings: &mut WarningLog,
) -> Result<RegistrationFile> {
    let file = match &job.registration {
        None => {
            let edited: Option<Vec<Vec<bool>>> =
                regions.map(|r| r.iter().map(|region| region.inside.clone()).collect());
            let params = &job.config.register;
            let (file, report) = register_case(ck, dataset, case, params, edited.as_deref(), warnings.progress())?;
            warnings.extend_reported(report.warnings);
            file
        }
        Some(given) => {
            let path = &RegistrationFile::resolve(given);
            let file = RegistrationFile::load(path)?;
            // The case's references as they are now, to compare with the file's.
            let (_, references) = lift_references(ck, &Marcher::new(&ck.grid), dataset, case, warnings)?;
            file.check_matches(&PhotoRun::of(ck), dataset, &references, path)?;
            if regions.is_some() {
                warnings.push(format!(
                    "{} was registered with every reference pixel: in this local edit, training rays registered \
                     to unpainted pixels keep pulling toward the photo (without --registration, only the regions register)",
                    path.display()
                ));
            }
            if file.params != job.config.register {
                warnings.push(format!(
                    "{} was registered with {:?}, not this config's [register] {:?}: using the file",
                    path.display(),
                    file.params,
                    job.config.register
                ));
            }
            file
        }
    };
    if job.method == Method::RefNpr && file.views.iter().all(|v| v.registration.pixels.is_empty()) {
        warnings.push(
            "R³ registered no training pixel: L_ref uses the reference view only, the rest comes from TCM".into(),
        );
    }
    Ok(file)
}

/// The style images and, for ARF with either colour transfer on, the style's
/// colour statistics (both transfers aim at them) and the photos'
/// recolouring (`--style` is ARF's alone).
pub(crate) fn style_side(
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
