//! The style side of a stylization: the case's style images read at their
//! views' sizes (or ARF's `--style` image), warnings about images that will
//! not stylize well, and ARF's colour transfer between photos and style.

use std::path::Path;

use anyhow::{Context, Result, bail};

use crate::reference::case::{self, ReferenceCase};
use crate::reference::registration::RegistrationFile;
use crate::scene::camera::Camera;
use crate::scene::data::Dataset;
use crate::stylize::colour_transfer::{ColourStats, ColourTransfer};
use crate::stylize::config::TransferPixels;
use crate::util::image::{Image, pixels};
use crate::util::progress::WarningLog;

/// A pixel within this of the background colour in every channel is background
/// (for the colour-transfer statistics).
const BACKGROUND_TOLERANCE: f32 = 0.01;

/// Whether a photo pixel has the background colour (within `BACKGROUND_TOLERANCE`).
pub fn is_background(c: &[f32; 3], background: [f32; 3]) -> bool {
    c.iter().zip(background).all(|(a, b)| (a - b).abs() <= BACKGROUND_TOLERANCE)
}

/// Warnings about a style image that will not stylize well.
fn style_warnings(path: &Path, rgb: &[f32]) -> Result<Vec<String>> {
    let mut out = Vec::new();
    let img = image::open(path).with_context(|| format!("cannot read style image {}", path.display()))?.to_rgba32f();
    let n = (img.width() * img.height()) as f32;
    let transparent = img.pixels().filter(|p| p.0[3] < 0.5).count() as f32 / n;
    if transparent > 0.5 {
        out.push(format!(
            "style image {} is {:.0}% transparent: those pixels become the background colour",
            path.display(),
            transparent * 100.0
        ));
    }
    let mean: [f32; 3] = std::array::from_fn(|c| rgb.iter().skip(c).step_by(3).sum::<f32>() / (rgb.len() / 3) as f32);
    let spread = rgb
        .chunks_exact(3)
        .map(|p| (0..3).map(|c| (p[c] - mean[c]).abs()).fold(0.0f32, f32::max))
        .fold(0.0f32, f32::max);
    if spread < 1e-3 {
        out.push(format!("style image {} is a single colour: the stylized scene will be flat", path.display()));
    }
    Ok(out)
}

/// Reads a reference's style image; a different aspect ratio from the view
/// is an error (a case for another scene or resolution).
fn read_reference_style(
    path: &Path,
    camera: &Camera,
    background: [f32; 3],
    warnings: &mut WarningLog,
) -> Result<Image> {
    let (w, h) = (camera.intrinsics.width, camera.intrinsics.height);
    let (iw, ih) =
        image::image_dimensions(path).with_context(|| format!("cannot read style image {}", path.display()))?;
    let (a, b) = (iw as f32 / ih as f32, w as f32 / h as f32);
    if (a / b - 1.0).abs() > 0.02 {
        bail!(
            "style image {} is {iw}x{ih} but its reference view is {w}x{h} (another aspect ratio): \
             is the case for another scene or resolution?",
            path.display()
        );
    }
    let (rgb, note) = case::read_style(path, w, h, background)?;
    for w in note.into_iter().chain(style_warnings(path, &rgb)?) {
        warnings.push(w);
    }
    Ok(camera.image_of(rgb))
}

/// The style images: one per reference of the case, at its view's size; for
/// ARF with `style`, that image alone.
pub fn read_styles(
    case: &ReferenceCase,
    registration: &RegistrationFile,
    style: Option<&Path>,
    background: [f32; 3],
    warnings: &mut WarningLog,
) -> Result<Vec<Image>> {
    if let Some(path) = style {
        let img = image::open(path).with_context(|| format!("cannot read style image {}", path.display()))?;
        let (w, h) = (img.width() as usize, img.height() as usize);
        let rgb = crate::scene::data::composite_over(&img.to_rgba32f(), background);
        for w in style_warnings(path, &rgb)? {
            warnings.push(w);
        }
        return Ok(vec![Image::new(w, h, rgb)]);
    }
    case.references
        .iter()
        .zip(&registration.references)
        .map(|(spec, p)| read_reference_style(&spec.style, &p.camera, background, warnings))
        .collect()
}

/// A one-reference case's painting and the image it was painted over,
/// where the case keeps it: `refnpr reference` writes the view's photoreal
/// render as content.png beside reference.toml. Both at the reference
/// view's size, so this is known before any work on the field (a
/// recolouring's schedule is chosen from it before the refit). None for
/// other cases, or when content.png is missing, unreadable or not of the
/// view's size.
pub fn painted_over(case: &ReferenceCase, dataset: &Dataset, background: [f32; 3]) -> Option<(Image, Image)> {
    let [spec] = &case.references[..] else { return None };
    let camera = case.cameras(dataset).ok()?.into_iter().next()?;
    let (w, h) = (camera.intrinsics.width, camera.intrinsics.height);
    let path = case.dir.join("content.png");
    if image::image_dimensions(&path).ok()? != (w, h) {
        return None;
    }
    let (content, _) = case::read_style(&path, w, h, background).ok()?;
    let (style, _) = case::read_style(&spec.style, w, h, background).ok()?;
    Some((camera.image_of(content), camera.image_of(style)))
}

/// Mean and covariance of the colours of `images` (interleaved RGB
/// buffers): over every pixel, or over those not of the background colour
/// (every pixel when that leaves none).
pub fn colour_stats(images: &[&[f32]], background: [f32; 3], which: TransferPixels) -> Result<ColourStats> {
    let all = || images.iter().flat_map(|rgb| pixels(rgb));
    match which {
        TransferPixels::All => ColourStats::of(all()),
        TransferPixels::Scene => {
            ColourStats::of(all().filter(|c| !is_background(c, background))).or_else(|_| ColourStats::of(all()))
        }
    }
}

/// The style side of ARF's colour transfers: over every pixel, or over the
/// reference pixels that see the scene (a style image given with --style:
/// its non-background pixels; every pixel when the mask leaves none).
pub fn style_colour_stats(
    style: &Image,
    registration: &RegistrationFile,
    own_style_image: bool,
    background: [f32; 3],
    which: TransferPixels,
) -> Result<ColourStats> {
    let style_pixels: Vec<[f32; 3]> = pixels(&style.rgb).collect();
    if which == TransferPixels::All {
        return ColourStats::of(style_pixels);
    }
    let style_mask: Vec<bool> = match (own_style_image, registration.references.first()) {
        (false, Some(r)) if r.hits.len() == style_pixels.len() => r.hits.clone(),
        _ => style_pixels.iter().map(|c| !is_background(c, background)).collect(),
    };
    let masked = style_pixels.iter().zip(&style_mask).filter(|(_, m)| **m).map(|(c, _)| *c);
    ColourStats::of(masked).or_else(|_| ColourStats::of(style_pixels.iter().copied()))
}

/// ARF's colour transfer of the training photos to the style's statistics.
pub fn arf_colour_transfer(
    dataset: &Dataset,
    style: &ColourStats,
    background: [f32; 3],
    which: TransferPixels,
) -> Result<ColourTransfer> {
    let photos: Vec<&[f32]> = dataset.train.iter().map(|v| &v.rgb[..]).collect();
    Ok(ColourTransfer::between(&colour_stats(&photos, background, which)?, style))
}
