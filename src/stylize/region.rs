//! Local edits: a painting that changes part of a view changes only the
//! surfaces it paints, from every side, and the rest of the scene keeps the
//! photoreal field.
//!
//! 1. Each reference with a `region` (`reference.toml`) gets its edited
//!    pixels (`reference_regions`): where the style image differs from the
//!    photoreal render by more than `region_threshold` in some channel
//!    (closed by a few pixels, so a recolouring that leaves a grey stroke
//!    grey keeps no hole), or the white of a mask image. A reference
//!    without `region` edits all of its pixels.
//! 2. With several references, each one's unpainted pixels whose surface
//!    another reference paints are set aside (`mark_painted_elsewhere`):
//!    they show another's object as a photo, not a wish to keep it.
//!    R³ registers training rays to the regions' pixels only, and the
//!    colour map is fitted on them.
//! 3. The pixels become voxels (`edit_region`). A voxel a reference sees
//!    is edited when more of its compositing weight, over that reference's
//!    rays, comes from edited pixels than from kept ones (for some
//!    reference: what one leaves unpainted does not veto another's edit).
//!    A voxel no reference sees is decided by TCM: every training pixel takes the label
//!    of the reference position its content features match (relu3, the
//!    finer block; `Template::edit_votes`), and the voxel takes the label
//!    with more weight, so the far side of a painted object follows the
//!    object, and the far side of a kept one stays.
//! 4. The optimiser changes only edited voxels (`StyleStep::image_step`'s
//!    gradient is masked), L_ref's reference pixels are the edited ones,
//!    TCM's template and L_color's reference patches are the regions' only
//!    (`Template::build`: a reference's unpainted pixels are the photo, and
//!    would pull a surface another reference paints back to it), and the
//!    saved field (`compose`) is the photoreal checkpoint, every SH band and
//!    the far background included, with the edited voxels' colour
//!    replaced: a ray that crosses no edited voxel renders exactly as the
//!    photoreal field renders it.

use std::borrow::Cow;
use std::path::Path;

use anyhow::{Context, Result, bail, ensure};
use burn::tensor::Tensor;

use crate::field::checkpoint::Checkpoint;
use crate::field::frozen::FrozenSamples;
use crate::field::grid::RadianceGrid;
use crate::reference::case::{ReferenceCase, RegionSpec, read_style};
use crate::reference::registration::field_surface;
use crate::scene::camera::Camera;
use crate::scene::data::Dataset;
use crate::stylize::tcm::{FEATURE_BLOCKS, PairRegion, block_size, relu3_position_of};
use crate::util::image::Image;
use crate::util::input::InputError;
use crate::util::tensor::{floats, to_vec};

/// How far (pixels) a difference region is closed: holes and gaps up to
/// twice this wide inside a painted area join it.
const CLOSE_RADIUS: usize = 2;

/// The least compositing weight (summed over a voxel's corners) that counts as seen.
const MIN_WEIGHT: f32 = 1e-3;

/// The edited pixels of one reference view.
#[derive(Debug, Clone, PartialEq)]
pub struct PixelRegion {
    pub width: usize,
    pub height: usize,
    /// Row-major, true where edited.
    pub inside: Vec<bool>,
    /// Row-major, true where the pixel is outside the region but its
    /// surface is edited by another reference (`mark_painted_elsewhere`):
    /// such a pixel says nothing, neither edit nor keep.
    pub elsewhere: Vec<bool>,
}

impl PixelRegion {
    pub fn new(width: usize, height: usize, inside: Vec<bool>) -> Self {
        Self { width, height, elsewhere: vec![false; inside.len()], inside }
    }

    pub fn everywhere(width: usize, height: usize) -> Self {
        Self::new(width, height, vec![true; width * height])
    }

    /// What the template takes of this region: its edited pixels, and the
    /// kept ones (neither inside nor painted elsewhere).
    pub fn pair_region(&self) -> PairRegion {
        let kept = self.inside.iter().zip(&self.elsewhere).map(|(i, e)| !i && !e).collect();
        PairRegion { edited: self.inside.clone(), kept }
    }

    /// The label of pixel `i` in a vote: edit, keep, or none (painted elsewhere).
    fn label(&self, i: usize) -> Option<bool> {
        match (self.inside[i], self.elsewhere[i]) {
            (true, _) => Some(true),
            (false, true) => None,
            (false, false) => Some(false),
        }
    }

    pub fn count(&self) -> usize {
        self.inside.iter().filter(|&&i| i).count()
    }

    /// `image` with every pixel outside the region set to `fill`.
    pub fn outside_filled(&self, image: &Image, fill: [f32; 3]) -> Image {
        let rgb = image
            .rgb
            .chunks_exact(3)
            .zip(&self.inside)
            .flat_map(|(p, &inside)| if inside { [p[0], p[1], p[2]] } else { fill });
        Image::new(self.width, self.height, rgb.collect())
    }

    /// `content` with the edited pixels tinted and the rest greyed, for a person to check.
    pub fn overlay(&self, content: &Image) -> Image {
        let rgb = content
            .rgb
            .chunks_exact(3)
            .zip(&self.inside)
            .flat_map(|(p, &inside)| {
                let grey = (p[0] + p[1] + p[2]) / 3.0;
                match inside {
                    true => [0.5 * p[0] + 0.5, 0.5 * p[1] + 0.2, 0.5 * p[2]],
                    false => [0.3 * grey + 0.35; 3],
                }
            })
            .collect();
        Image::new(self.width, self.height, rgb)
    }

    /// Dilation (`grow`) or erosion of the region by a square of `radius`.
    fn morph(&self, radius: usize, grow: bool) -> Self {
        let (w, h) = (self.width, self.height);
        let inside = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let ys = y.saturating_sub(radius)..(y + radius + 1).min(h);
                let mut window =
                    ys.flat_map(|yy| (x.saturating_sub(radius)..(x + radius + 1).min(w)).map(move |xx| (xx, yy)));
                match grow {
                    true => window.any(|(xx, yy)| self.inside[yy * w + xx]),
                    false => window.all(|(xx, yy)| self.inside[yy * w + xx]),
                }
            })
            .collect();
        Self::new(w, h, inside)
    }

    /// Closing: dilation, then erosion (fills holes, keeps the outline).
    fn closed(&self, radius: usize) -> Self {
        self.morph(radius, true).morph(radius, false)
    }
}

/// The pixels where `style` differs from `content` by more than `threshold` in some channel, closed.
pub fn difference_region(content: &Image, style: &Image, threshold: f32) -> PixelRegion {
    let inside = content
        .rgb
        .chunks_exact(3)
        .zip(style.rgb.chunks_exact(3))
        .map(|(c, s)| (0..3).any(|k| (c[k] - s[k]).abs() > threshold))
        .collect();
    PixelRegion::new(content.width, content.height, inside).closed(CLOSE_RADIUS)
}

/// A mask image's white pixels (luminance above one half); it must be the view's size.
pub fn mask_region(path: &Path, width: usize, height: usize) -> Result<PixelRegion> {
    let img = image::open(path).with_context(|| format!("cannot read region mask {}", path.display()))?.to_luma32f();
    if (img.width() as usize, img.height() as usize) != (width, height) {
        let message = format!(
            "region mask {} is {}x{}, the reference view is {width}x{height}: the mask must be the view's size",
            path.display(),
            img.width(),
            img.height()
        );
        return Err(InputError::Malformed { path: path.into(), message }.into());
    }
    Ok(PixelRegion::new(width, height, img.pixels().map(|p| p[0] > 0.5).collect()))
}

/// The edited pixels of every reference of a local-edit case (None when
/// no reference has a `region`), checked before any work: a mask of the
/// wrong size, an empty region, or one that covers no surface of the
/// photoreal field is refused, naming the file. `photo` is the photoreal
/// checkpoint with every SH band (the render the painting was made over).
pub fn reference_regions(
    case: &ReferenceCase,
    photo: &Checkpoint,
    dataset: &Dataset,
) -> Result<Option<Vec<PixelRegion>>> {
    if !case.is_local() {
        return Ok(None);
    }
    let cameras = case.cameras(dataset)?;
    let mut regions = Vec::with_capacity(cameras.len());
    for (spec, camera) in case.references.iter().zip(&cameras) {
        let (w, h) = (camera.intrinsics.width as usize, camera.intrinsics.height as usize);
        let (region, named) = match &spec.region {
            None => (PixelRegion::everywhere(w, h), &spec.style),
            Some(RegionSpec::Mask(path)) => (mask_region(path, w, h)?, path),
            Some(RegionSpec::Difference) => {
                let (style, _) = read_style(&spec.style, w as u32, h as u32, photo.meta.background)?;
                let content = photo.render_view(camera).image;
                (difference_region(&content, &Image::new(w, h, style), case.region_threshold), &spec.style)
            }
        };
        check_region(&region, named, photo, camera, case.region_threshold, spec.region.as_ref())?;
        regions.push(region);
    }
    Ok(Some(regions))
}

fn check_region(
    region: &PixelRegion,
    named: &Path,
    photo: &Checkpoint,
    camera: &Camera,
    threshold: f32,
    spec: Option<&RegionSpec>,
) -> Result<()> {
    let empty = |message: String| -> Result<()> { Err(InputError::Malformed { path: named.into(), message }.into()) };
    if region.count() == 0 {
        return match spec {
            Some(RegionSpec::Difference) => empty(format!(
                "{}: the region is empty: no pixel differs from the photoreal render by more than \
                 region_threshold = {threshold} (paint over content.png, or lower region_threshold)",
                named.display()
            )),
            _ => empty(format!("region mask {}: no pixel is white (white marks the edited pixels)", named.display())),
        };
    }
    let surface = field_surface(photo, camera);
    let on_surface = region.inside.iter().zip(&surface.points).filter(|(i, p)| **i && p.is_some()).count();
    if on_surface == 0 {
        return empty(format!(
            "{}: the region's {} pixels cover no surface of the photoreal field (they see only background): \
             nothing there could be edited",
            named.display(),
            region.count()
        ));
    }
    Ok(())
}

/// Which voxels a local edit changes, and how they were decided.
#[derive(Debug, Clone)]
pub struct EditRegion {
    /// Per SH row: whether the stylization may change it.
    pub rows: Vec<bool>,
    /// Edited voxels a reference sees, and those decided by TCM.
    pub seen: usize,
    pub matched: usize,
}

/// Compositing weight per row of `samples`' rays, added to `edit` or
/// `keep` by the ray's label (None: the ray votes for neither).
fn vote(samples: &FrozenSamples, label: impl Fn(usize) -> Option<bool>, edit: &mut [f32], keep: &mut [f32]) {
    for ray in 0..samples.num_rays {
        let Some(edited) = label(ray) else { continue };
        let into = if edited { &mut *edit } else { &mut *keep };
        for s in samples.ray_samples(ray) {
            let w = samples.weight[s.index];
            for (row, cw) in s.rows.iter().zip(s.colour_weights) {
                if *row >= 0 && cw > 0.0 {
                    into[*row as usize] += w * cw;
                }
            }
        }
    }
}

/// Per row, one reference's verdict over its rays (`samples`, labelled by
/// `label`): None where they give the row too little weight to decide,
/// else whether more of it comes from edited pixels than from kept ones.
fn reference_verdict(
    num_rows: usize,
    samples: &FrozenSamples,
    label: impl Fn(usize) -> Option<bool>,
) -> Vec<Option<bool>> {
    let (mut edit, mut keep) = (vec![0.0f32; num_rows], vec![0.0f32; num_rows]);
    vote(samples, label, &mut edit, &mut keep);
    edit.iter().zip(&keep).map(|(e, k)| (e + k > MIN_WEIGHT).then_some(e > k)).collect()
}

/// Per row, whether `region` wins its vote over `samples` (the reference's rays).
fn edited_rows(num_rows: usize, samples: &FrozenSamples, region: &PixelRegion) -> Vec<bool> {
    let verdict = reference_verdict(num_rows, samples, |ray| Some(region.inside[ray]));
    verdict.into_iter().map(|v| v == Some(true)).collect()
}

/// Marks, in each reference, the pixels outside its region whose surface
/// another reference paints (more than half of the ray's compositing weight
/// on voxels that reference's region wins). With several references each
/// painting its own object, a reference's unpainted pixels show the other
/// objects as photos; they are not a wish to keep those surfaces.
pub fn mark_painted_elsewhere(num_rows: usize, references: &[FrozenSamples], regions: &mut [PixelRegion]) {
    let edited: Vec<Vec<bool>> = references.iter().zip(&*regions).map(|(s, r)| edited_rows(num_rows, s, r)).collect();
    for (r, (samples, region)) in references.iter().zip(regions.iter_mut()).enumerate() {
        let by_others = |row: usize| edited.iter().enumerate().any(|(o, e)| o != r && e[row]);
        for ray in 0..samples.num_rays {
            if region.inside[ray] {
                continue;
            }
            let (mut others, mut all) = (0.0f32, 0.0f32);
            for s in samples.ray_samples(ray) {
                for (row, cw) in s.rows.iter().zip(s.colour_weights).filter(|(row, cw)| **row >= 0 && *cw > 0.0) {
                    let w = samples.weight[s.index] * cw;
                    all += w;
                    others += if by_others(*row as usize) { w } else { 0.0 };
                }
            }
            region.elsewhere[ray] = all > MIN_WEIGHT && others > 0.5 * all;
        }
    }
}

/// The voxels of a local edit. `references` are the references' sample
/// lists and their regions; `views` are the training views' lists, each
/// with its relu3 positions' TCM votes (`Template::edit_votes`: whether the
/// position looks like an edited reference position) and its size.
pub fn edit_region(
    num_rows: usize,
    references: &[(FrozenSamples, &PixelRegion)],
    views: &mut dyn Iterator<Item = (Cow<'_, FrozenSamples>, &[bool], [usize; 2])>,
) -> Result<EditRegion> {
    // Per row: seen by some reference, and edited by one (each reference
    // decides for itself: what one leaves unpainted does not veto another's edit).
    let (mut seen_by_reference, mut edited) = (vec![false; num_rows], vec![false; num_rows]);
    for (samples, region) in references {
        let verdict = reference_verdict(num_rows, samples, |ray| region.label(ray));
        for (row, v) in verdict.into_iter().enumerate() {
            if let Some(edit) = v {
                seen_by_reference[row] = true;
                edited[row] |= edit;
            }
        }
    }
    let (mut tcm_edit, mut tcm_keep) = (vec![0.0f32; num_rows], vec![0.0f32; num_rows]);
    for (samples, votes, [w, h]) in views {
        let [bh, bw] = block_size(FEATURE_BLOCKS[0], h, w);
        ensure!(votes.len() == bh * bw, "TCM votes for {bh}x{bw} positions, got {}", votes.len());
        let label = |ray: usize| Some(votes[relu3_position_of(ray % w, ray / w, w, h)]);
        vote(&samples, label, &mut tcm_edit, &mut tcm_keep);
    }
    let (mut seen, mut matched) = (0, 0);
    let rows = (0..num_rows)
        .map(|row| match seen_by_reference[row] {
            true => {
                seen += usize::from(edited[row]);
                edited[row]
            }
            false => {
                let by_tcm = tcm_edit[row] > tcm_keep[row] && tcm_edit[row] > MIN_WEIGHT;
                matched += usize::from(by_tcm);
                by_tcm
            }
        })
        .collect();
    if seen + matched == 0 {
        bail!("the local edit's region covers no voxel of the field: nothing would change");
    }
    Ok(EditRegion { rows, seen, matched })
}

impl EditRegion {
    /// Per row of a step's gradient buffer (`grid_rows`: its grid rows in
    /// order), 1 where the row may change and 0 elsewhere, as a `[rows, 1]` factor.
    pub fn gradient_mask(
        &self,
        grid_rows: &mut dyn Iterator<Item = usize>,
        device: &burn::tensor::Device,
    ) -> Tensor<2> {
        let mask: Vec<f32> = grid_rows.map(|r| f32::from(u8::from(self.rows[r]))).collect();
        let n = mask.len();
        floats(mask, [n, 1], device)
    }

    /// The photoreal field (`photo`, every SH band) with the edited rows'
    /// colour taken from `style` (degree 0, the stylized field's): their
    /// DC band replaced and their higher bands zeroed. Every other row,
    /// the density and the far background stay the photo's, bit for bit.
    pub fn compose(&self, photo: &mut RadianceGrid, style: &RadianceGrid) {
        let nb = photo.num_basis();
        let style_sh = to_vec(style.sh.clone());
        let mut sh = to_vec(photo.sh.clone());
        for (row, _) in self.rows.iter().enumerate().filter(|(_, e)| **e) {
            for c in 0..3 {
                let band = &mut sh[row * 3 * nb + c * nb..row * 3 * nb + (c + 1) * nb];
                band.fill(0.0);
                band[0] = style_sh[row * 3 + c];
            }
        }
        let rows = photo.num_rows();
        photo.sh = floats(sh, [rows, 3 * nb], &photo.device());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn region(w: usize, h: usize, f: impl Fn(usize, usize) -> bool) -> PixelRegion {
        PixelRegion::new(w, h, (0..w * h).map(|i| f(i % w, i / w)).collect())
    }

    #[test]
    fn difference_is_thresholded_and_closed() {
        let (w, h) = (20, 12);
        let content = Image::new(w, h, vec![0.5; w * h * 3]);
        // A painted square with a one-pixel unchanged hole, and a change below the threshold elsewhere.
        let mut style = content.clone();
        for y in 3..9 {
            for x in 4..12 {
                if (x, y) != (7, 5) {
                    style.rgb[(y * w + x) * 3] = 0.9;
                }
            }
        }
        style.rgb[(10 * w + 17) * 3 + 1] = 0.55;
        let r = difference_region(&content, &style, 0.1);
        assert_eq!(r, region(w, h, |x, y| (4..12).contains(&x) && (3..9).contains(&y)), "square, hole filled");
        assert_eq!(difference_region(&content, &content, 0.1).count(), 0);
    }

    #[test]
    fn a_mask_of_the_wrong_size_is_refused_naming_the_file() {
        let dir = crate::test_support::temp_dir("region-mask");
        let path = dir.join("mask.png");
        image::GrayImage::from_pixel(10, 8, image::Luma([255])).save(&path).unwrap();
        let err = format!("{:#}", mask_region(&path, 12, 8).unwrap_err());
        assert!(err.contains("mask.png") && err.contains("10x8") && err.contains("12x8"), "{err}");
        assert_eq!(mask_region(&path, 10, 8).unwrap().count(), 80);
    }
}
