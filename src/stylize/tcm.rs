//! TCM, the template-based correspondence (paper eqs. 6-7), and the colour
//! matching of eq. 9. The reference side (content render I_R and style S_R
//! of every reference) becomes a `Template`: per feature block, the
//! normalised content descriptors (search keys) and the style features at
//! the same positions (the guidance). A training view's content render is
//! matched once against it (exact cosine nearest neighbour, chunked) and the
//! indices are kept: the guidance F_G is then a row gather per step.
//! Several references are searched as one union (their keys concatenated).

use anyhow::Result;
use burn::tensor::{Device, Int, Tensor};
use half::f16;
use half::slice::HalfFloatSliceExt;
use serde::Serialize;

use crate::stylize::losses::patch_means;
use crate::util::image::Image;
use crate::util::tensor::{floats, indices, select_rows, tensor_bytes, to_vec};
use crate::vgg::features::{block_descriptors, block_matrix, nearest_by_dot};
use crate::vgg::{FeatureMaps, Vgg16, VggLayer};

pub const RELU3: [VggLayer; 3] = [VggLayer::Relu3_1, VggLayer::Relu3_2, VggLayer::Relu3_3];
pub const RELU4: [VggLayer; 3] = [VggLayer::Relu4_1, VggLayer::Relu4_2, VggLayer::Relu4_3];
pub const RELU5: [VggLayer; 3] = [VggLayer::Relu5_1, VggLayer::Relu5_2, VggLayer::Relu5_3];
/// The feature loss's blocks (relu3_x: 768 channels at 1/4, relu4_x: 1536 at 1/8), summed.
pub const FEATURE_BLOCKS: [&[VggLayer]; 2] = [&RELU3, &RELU4];
/// Pixels per relu5 position: the colour loss's patch size.
pub const COLOUR_PATCH: usize = 16;

/// The grid of a block: that of its first layer.
pub fn block_size(block: &[VggLayer], height: usize, width: usize) -> [usize; 2] {
    block[0].map_size(height, width)
}

/// The relu3 position (row-major in its `block_size` grid) whose receptive
/// centre is nearest pixel `(x, y)` of a `width` x `height` view: the pixel
/// divided by the block's stride, the last row and column taking the
/// pixels a pooling dropped. One mapping for every per-position vote.
pub fn relu3_position_of(x: usize, y: usize, width: usize, height: usize) -> usize {
    let [rows, cols] = block_size(FEATURE_BLOCKS[0], height, width);
    let stride = FEATURE_BLOCKS[0][0].stride();
    (y / stride).min(rows - 1) * cols + (x / stride).min(cols - 1)
}

/// Features of `image` for `blocks` (raw, `[positions, channels]` each) and,
/// when `colour` is set, the normalised relu5 descriptors. No gradient.
pub fn image_features(
    vgg: &Vgg16,
    image: &Image,
    device: &Device,
    blocks: &[&[VggLayer]],
    colour: bool,
) -> Result<(Vec<Tensor<2>>, Option<Tensor<2>>)> {
    let mut layers: Vec<VggLayer> = blocks.iter().flat_map(|b| b.iter().copied()).collect();
    if colour {
        layers.extend(RELU5);
    }
    let maps = vgg.features(image.tensor(device), &layers)?;
    let raw =
        blocks.iter().map(|b| block_matrix(&maps, b, 0, block_size(b, image.height, image.width)).inner()).collect();
    let c = colour.then(|| block_descriptors(&maps, &RELU5, 0, block_size(&RELU5, image.height, image.width)).inner());
    Ok((raw, c))
}

/// Fixed features kept for the whole run (the content term's, one matrix
/// per block and view). On the CPU backends they are kept as f16 numbers
/// when every value fits (issue 19: lego's 100 views held 1.15 GB of them
/// as f32, fern's 17 views 0.9 GB) and widened to f32 when used: a
/// rounding of at most 2^-11 of each value (below f16's smallest normal
/// number, 6.1e-5, at most 3e-8 absolute) on a target of the content term
/// (a 5e-3 share of the feature loss). On a GPU they stay f32 tensors on the
/// device (no per-step upload).
pub enum StoredFeatures {
    /// (Boxed: a tensor handle is several times the size of the other variant.)
    Tensor(Box<Tensor<2>>),
    Half {
        values: Vec<f16>,
        shape: [usize; 2],
        device: Device,
    },
}

impl StoredFeatures {
    /// Stores `features` as f16 when `half` is asked and every value is
    /// finite and within f16's range; as the tensor otherwise.
    pub fn store(features: Tensor<2>, half: bool) -> Self {
        if !half {
            return Self::Tensor(Box::new(features));
        }
        let [rows, cols] = features.dims();
        let device = features.device();
        let values = to_vec(features.clone());
        let fits = values.iter().all(|v| v.is_finite() && v.abs() <= f16::MAX.to_f32());
        if !fits {
            return Self::Tensor(Box::new(features));
        }
        let mut half = vec![f16::ZERO; values.len()];
        half.convert_from_f32_slice(&values);
        Self::Half { values: half, shape: [rows, cols], device }
    }

    /// The features as an f32 tensor.
    pub fn tensor(&self) -> Tensor<2> {
        match self {
            Self::Tensor(t) => (**t).clone(),
            Self::Half { values, shape, device } => {
                let mut wide = vec![0.0f32; values.len()];
                values.convert_to_f32_slice(&mut wide);
                floats(wide, *shape, device)
            }
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        match self {
            Self::Tensor(t) => t.shape().num_elements() * 4,
            Self::Half { values, .. } => values.len() * 2,
        }
    }
}

/// The features of a stylized render used by the losses (with gradient when `maps` carry one).
pub fn render_blocks(maps: &FeatureMaps, blocks: &[&[VggLayer]], height: usize, width: usize) -> Vec<Tensor<2>> {
    blocks.iter().map(|b| block_matrix(maps, b, 0, block_size(b, height, width))).collect()
}

/// The reference side of TCM.
pub struct Template {
    /// Per block: normalised content descriptors of every reference position
    /// (in a local edit, of the edited positions only).
    pub keys: Vec<Tensor<2>>,
    /// Per block: the style image's raw features at the same positions.
    pub values: Vec<Tensor<2>>,
    /// Normalised relu5 descriptors of the references' content renders.
    pub colour_keys: Tensor<2>,
    /// The style images' patch mean colours at the same positions (in a
    /// local edit, the mean over the patch's edited pixels).
    pub colour_values: Tensor<2>,
    /// Whether the references carry regions (a local edit).
    pub local: bool,
    /// A local edit: the normalised relu3 content descriptors of the
    /// reference positions at least half kept (`PairRegion::kept`; None when
    /// there are none).
    pub kept_keys: Option<Tensor<2>>,
    /// Each reference's content render size, `[height, width]`: where its
    /// positions lie in the keys (`matches_at_full_size`).
    pub sizes: Vec<[usize; 2]>,
}

/// A (content, style) pair of one reference view and, in a local edit, its region.
pub struct ReferencePair {
    pub content: Image,
    pub style: Image,
    pub region: Option<PairRegion>,
}

/// A reference's pixels in a local edit (row-major, the view's size): those
/// it edits, and those it keeps (neither: unpainted here but painted by
/// another reference, which say nothing).
#[derive(Debug, Clone, PartialEq)]
pub struct PairRegion {
    pub edited: Vec<bool>,
    pub kept: Vec<bool>,
}

/// Per cell of a `[rows, cols]` feature grid of `stride` pixels per cell
/// over an image `width` pixels wide, the fraction of the pixels under it
/// that `edited` (row-major) marks.
pub fn cell_fractions(edited: &[bool], width: usize, [rows, cols]: [usize; 2], stride: usize) -> Vec<f32> {
    (0..rows * cols)
        .map(|cell| {
            let (y0, x0) = (cell / cols * stride, cell % cols * stride);
            let pixels = (y0..y0 + stride).flat_map(|y| (x0..x0 + stride).map(move |x| y * width + x));
            pixels.filter(|&i| edited[i]).count() as f32 / (stride * stride) as f32
        })
        .collect()
}

/// The cells a region's template keeps: those at least half edited or,
/// where none is (a region smaller than one cell), every cell it touches.
pub fn edited_cells(fractions: &[f32]) -> Vec<usize> {
    let half: Vec<usize> = (0..fractions.len()).filter(|&c| fractions[c] >= 0.5).collect();
    match half.is_empty() {
        true => (0..fractions.len()).filter(|&c| fractions[c] > 0.0).collect(),
        false => half,
    }
}

/// Per `patch` x `patch` block of `image` (the grid `patch_means` pools),
/// the mean colour of the pixels `edited` marks, for the blocks in `cells`.
fn edited_patch_means(image: &Image, edited: &[bool], patch: usize, cells: &[usize]) -> Vec<f32> {
    let cols = image.width / patch;
    let mut out = Vec::with_capacity(cells.len() * 3);
    for &cell in cells {
        let (y0, x0) = (cell / cols * patch, cell % cols * patch);
        let (mut sum, mut n) = ([0.0f32; 3], 0usize);
        for i in (y0..y0 + patch).flat_map(|y| (x0..x0 + patch).map(move |x| y * image.width + x)) {
            if edited[i] {
                (0..3).for_each(|c| sum[c] += image.rgb[i * 3 + c]);
                n += 1;
            }
        }
        out.extend(sum.map(|s| s / n.max(1) as f32));
    }
    out
}

/// `rows` of `x` (all of them when `rows` is None).
fn keep_rows(x: Tensor<2>, rows: Option<&[usize]>) -> Tensor<2> {
    match rows {
        None => x,
        Some(r) => {
            let device = x.device();
            select_rows(x, indices(r.iter().map(|&i| i as i32).collect(), &device))
        }
    }
}

impl Template {
    /// Bytes of its keys and values.
    pub fn bytes(&self) -> usize {
        let blocks: usize = self.keys.iter().chain(&self.values).map(tensor_bytes).sum();
        blocks
            + tensor_bytes(&self.colour_keys)
            + tensor_bytes(&self.colour_values)
            + self.kept_keys.as_ref().map_or(0, tensor_bytes)
    }

    /// The template of `pairs`. A pair with a region contributes only the
    /// positions its edited pixels cover (`edited_cells`), so that TCM and
    /// L_color carry only what was painted: in a local edit a reference's
    /// unpainted pixels are the photo, and matching them would pull a
    /// surface another reference paints back to its photo colours.
    pub fn build(vgg: &Vgg16, pairs: &[ReferencePair], device: &Device) -> Result<Self> {
        let nb = FEATURE_BLOCKS.len();
        let (mut keys, mut values) = (vec![Vec::new(); nb], vec![Vec::new(); nb]);
        let (mut ckeys, mut cvalues, mut kept) = (Vec::new(), Vec::new(), Vec::new());
        for p in pairs {
            let (w, h) = (p.content.width, p.content.height);
            let (content, colour) = image_features(vgg, &p.content, device, &FEATURE_BLOCKS, true)?;
            let (style, _) = image_features(vgg, &p.style, device, &FEATURE_BLOCKS, false)?;
            for b in 0..nb {
                let key = crate::vgg::features::normalise_rows(content[b].clone());
                let (grid, stride) = (block_size(FEATURE_BLOCKS[b], h, w), FEATURE_BLOCKS[b][0].stride());
                let cells = p.region.as_ref().map(|r| edited_cells(&cell_fractions(&r.edited, w, grid, stride)));
                if let (0, Some(region), Some(cells)) = (b, &p.region, &cells) {
                    let fractions = cell_fractions(&region.kept, w, grid, stride);
                    let kept_cells: Vec<usize> =
                        (0..fractions.len()).filter(|c| fractions[*c] >= 0.5 && !cells.contains(c)).collect();
                    if !kept_cells.is_empty() {
                        kept.push(keep_rows(key.clone(), Some(&kept_cells)));
                    }
                }
                keys[b].push(keep_rows(key, cells.as_deref()));
                values[b].push(keep_rows(style[b].clone(), cells.as_deref()));
            }
            let colour = colour.expect("colour descriptors requested");
            match p.region.as_ref().map(|r| &r.edited) {
                None => {
                    ckeys.push(colour);
                    cvalues.push(patch_means(p.style.tensor(device), COLOUR_PATCH));
                }
                Some(edited) => {
                    let grid = [h / COLOUR_PATCH, w / COLOUR_PATCH];
                    let cells = edited_cells(&cell_fractions(edited, w, grid, COLOUR_PATCH));
                    let means = edited_patch_means(&p.style, edited, COLOUR_PATCH, &cells);
                    ckeys.push(keep_rows(colour, Some(&cells)));
                    cvalues.push(floats(means, [cells.len(), 3], device));
                }
            }
        }
        Ok(Self {
            keys: keys.into_iter().map(|k| Tensor::cat(k, 0)).collect(),
            values: values.into_iter().map(|v| Tensor::cat(v, 0)).collect(),
            colour_keys: Tensor::cat(ckeys, 0),
            colour_values: Tensor::cat(cvalues, 0),
            local: pairs.iter().any(|p| p.region.is_some()),
            kept_keys: (!kept.is_empty()).then(|| Tensor::cat(kept, 0)),
            sizes: pairs.iter().map(|p| [p.content.height, p.content.width]).collect(),
        })
    }

    /// A local edit's vote of each relu3 position of a view (its raw
    /// content features): whether the nearest reference position (cosine)
    /// is an edited one rather than a kept one.
    pub fn edit_votes(&self, relu3: &Tensor<2>, chunk: usize) -> Vec<bool> {
        let query = crate::vgg::features::normalise_rows(relu3.clone());
        let Some(kept) = &self.kept_keys else {
            return vec![true; query.dims()[0]];
        };
        let (_, edited) = nearest_by_dot(query.clone(), self.keys[0].clone(), chunk);
        let (_, kept) = nearest_by_dot(query, kept.clone(), chunk);
        edited.iter().zip(&kept).map(|(e, k)| e >= k).collect()
    }

    /// Eq. 7 for every position of each block: the index of the nearest
    /// template position (cosine), from a view's raw content features.
    pub fn matches(&self, content: &[Tensor<2>], chunk: usize) -> Vec<Tensor<1, Int>> {
        let device = self.keys[0].device();
        let to_tensor = |idx: Vec<usize>| indices(idx.into_iter().map(|i| i as i32).collect(), &device);
        self.match_indices(content, chunk).into_iter().map(to_tensor).collect()
    }

    /// `matches` as indices on the host.
    pub fn match_indices(&self, content: &[Tensor<2>], chunk: usize) -> Vec<Vec<usize>> {
        content
            .iter()
            .zip(&self.keys)
            .map(|(c, k)| nearest_by_dot(crate::vgg::features::normalise_rows(c.clone()), k.clone(), chunk).0)
            .collect()
    }

    /// Matches found between a view and the references `n` times smaller
    /// (`coarse`: per block, the indices into `self_coarse`'s keys, from a
    /// `view_coarse` = `[height, width]` render) carried to this template,
    /// the references at full size, for the view at `view_fine`: each
    /// full-size position takes the match of the coarse position it lies
    /// in, offset by its place within its n x n block, so the 2-D layout of
    /// the matched reference patch is kept. A local edit's template keeps
    /// only its edited cells, not a grid: not carried (None).
    pub fn matches_at_full_size(
        &self,
        self_coarse: &Template,
        coarse: &[Vec<usize>],
        view_coarse: [usize; 2],
        view_fine: [usize; 2],
        n: usize,
    ) -> Option<Vec<Tensor<1, Int>>> {
        if self.local || self_coarse.local || self.sizes.len() != self_coarse.sizes.len() {
            return None;
        }
        let device = self.keys[0].device();
        let blocks = FEATURE_BLOCKS.iter().zip(coarse);
        let carried = blocks.map(|(block, idx)| {
            let grids = |sizes: &[[usize; 2]]| sizes.iter().map(|&[h, w]| block_size(block, h, w)).collect::<Vec<_>>();
            let views = [view_coarse, view_fine].map(|[h, w]| block_size(block, h, w));
            let refs = [grids(&self_coarse.sizes), grids(&self.sizes)];
            let carried = carry_matches(idx, views, &refs, n);
            indices(carried.into_iter().map(|i| i as i32).collect(), &device)
        });
        Some(carried.collect())
    }

    /// Eq. 6: the guidance features of block `b` for matched indices.
    pub fn guidance(&self, b: usize, matches: &Tensor<1, Int>) -> Tensor<2> {
        self.values[b].clone().select(0, matches.clone())
    }

    /// Eq. 9's targets for a view: for each relu5 position, the matched
    /// reference patch's style colour, and a mask that is 0 where the match's
    /// cosine distance exceeds `max_distance` or, when `white` is given, the
    /// view's own content patch is near white (> `white` in every channel:
    /// background).
    pub fn colour_targets(
        &self,
        colour_descriptors: Tensor<2>,
        content: &Image,
        max_distance: f32,
        white: Option<f32>,
        chunk: usize,
    ) -> ColourTargets {
        let device = colour_descriptors.device();
        let (idx, sim) = nearest_by_dot(colour_descriptors, self.colour_keys.clone(), chunk);
        let background = white_patches(content, white, COLOUR_PATCH, &device);
        let mask: Vec<f32> = sim
            .iter()
            .zip(&background)
            .map(|(&s, &background)| if 1.0 - s <= max_distance && !background { 1.0 } else { 0.0 })
            .collect();
        let n = mask.len();
        let matched = mask.iter().filter(|&&m| m > 0.0).count();
        let target = self.colour_values.clone().select(0, indices(idx.iter().map(|&i| i as i32).collect(), &device));
        ColourTargets {
            target,
            source: idx,
            mask: floats(mask, [n, 1], &device),
            matched_fraction: matched as f32 / n.max(1) as f32,
            patch: COLOUR_PATCH,
            weight: 1.0,
        }
    }
}

/// One block's matches carried from a coarse grid to the full-size one
/// (`Template::matches_at_full_size`): `idx` indexes the coarse references'
/// positions (`refs[0]`: each reference's `[rows, cols]`, concatenated
/// row-major one after another) for every position of the coarse view's
/// grid `views[0]`; the result, the full-size references' positions
/// (`refs[1]`) for every position of `views[1]`.
fn carry_matches(idx: &[usize], views: [[usize; 2]; 2], refs: &[Vec<[usize; 2]>; 2], n: usize) -> Vec<usize> {
    let [[crows, ccols], [frows, fcols]] = views;
    let offsets = |grids: &[[usize; 2]]| {
        grids
            .iter()
            .scan(0, |at, &[r, c]| {
                let start = *at;
                *at += r * c;
                Some(start)
            })
            .collect::<Vec<_>>()
    };
    let (coarse_at, fine_at) = (offsets(&refs[0]), offsets(&refs[1]));
    // A full-size row or column: the coarse one it lies in, and its place there.
    let split = |p: usize, coarse_len: usize| {
        let c = (p / n).min(coarse_len - 1);
        (c, (p - c * n).min(n - 1))
    };
    let mut out = Vec::with_capacity(frows * fcols);
    for y in 0..frows {
        let (cy, dy) = split(y, crows);
        for x in 0..fcols {
            let (cx, dx) = split(x, ccols);
            let i = idx[cy * ccols + cx];
            let r = coarse_at.partition_point(|&start| start <= i) - 1;
            let [_, rc] = refs[0][r];
            let (ty, tx) = ((i - coarse_at[r]) / rc, (i - coarse_at[r]) % rc);
            let [fr, fc] = refs[1][r];
            out.push(fine_at[r] + (ty * n + dy).min(fr - 1) * fc + (tx * n + dx).min(fc - 1));
        }
    }
    out
}

/// Colour-loss targets of one view.
pub struct ColourTargets {
    /// `[relu5 positions, 3]`
    pub target: Tensor<2>,
    /// `[relu5 positions, 1]`, 1 = supervised.
    pub mask: Tensor<2>,
    /// Per position, the template position its target comes from (the
    /// references' relu5 positions, row-major, one reference after another).
    pub source: Vec<usize>,
    pub matched_fraction: f32,
    /// Pixels per target patch side: `COLOUR_PATCH` (relu5) for matched
    /// targets, `[colour_map] target_patch` for the colour map's.
    pub patch: usize,
    /// λ_c, the weight of L_color on these targets (set by the guides:
    /// `[loss] colour`, or the colour map's weight for a recolouring).
    pub weight: f32,
}

/// Per `patch`-sized block of `content`: whether its mean is near white
/// (above `white` in every channel: background, no colour loss there).
fn white_patches(content: &Image, white: Option<f32>, patch: usize, device: &Device) -> Vec<bool> {
    let own = to_vec(patch_means(content.tensor(device), patch));
    own.chunks_exact(3).map(|p| white.is_some_and(|w| p.iter().all(|&v| v > w))).collect()
}

/// One view's colour targets as written to `colour_targets.json`: row-major
/// over the grid of target patches (`patch` x `patch` pixels each; 16, the
/// relu5 grid, for matched targets), `null` where the position is not
/// supervised.
#[derive(Debug, Clone, Serialize)]
pub struct ViewColourTargets {
    pub view: usize,
    /// Pixels per patch side.
    pub patch: usize,
    /// `[columns, rows]` of the patch grid.
    pub positions: [usize; 2],
    pub matched_fraction: f32,
    pub targets: Vec<Option<[f32; 3]>>,
    /// The template position each supervised target comes from.
    pub sources: Vec<Option<usize>>,
}

impl ColourTargets {
    /// Bytes of its targets, mask and sources.
    pub fn bytes(&self) -> usize {
        tensor_bytes(&self.target) + tensor_bytes(&self.mask) + self.source.len() * 8
    }

    /// Targets from the colour map: the mean of `mapped` (the view's
    /// content render through `colour_map::ColourMap`) over each `patch` x
    /// `patch` block, supervised where the content's block is not
    /// background (`white`). No template position is their source (`source`
    /// is empty).
    pub fn from_mapped(
        content: &Image,
        mapped: &Image,
        white: Option<f32>,
        patch: usize,
        device: &Device,
    ) -> ColourTargets {
        let target = patch_means(mapped.tensor(device), patch);
        let mask: Vec<f32> =
            white_patches(content, white, patch, device).into_iter().map(|b| if b { 0.0 } else { 1.0 }).collect();
        let n = mask.len();
        let matched = mask.iter().filter(|&&m| m > 0.0).count();
        ColourTargets {
            target,
            source: Vec::new(),
            mask: floats(mask, [n, 1], device),
            matched_fraction: matched as f32 / n.max(1) as f32,
            patch,
            weight: 1.0,
        }
    }

    /// A local edit: supervises only the patches at least half of whose
    /// pixels TCM votes edited (`votes`, per relu3 position of a `width` x
    /// `height` view): a kept surface's patch target would push the edited
    /// voxels beside it to make up the difference.
    pub fn only_edited(mut self, votes: &[bool], width: usize, height: usize) -> Self {
        let edited: Vec<bool> =
            (0..width * height).map(|i| votes[relu3_position_of(i % width, i / width, width, height)]).collect();
        let grid = [height / self.patch, width / self.patch];
        let fractions = cell_fractions(&edited, width, grid, self.patch);
        let mut mask = to_vec(self.mask.clone());
        for (m, f) in mask.iter_mut().zip(&fractions) {
            *m *= if *f >= 0.5 { 1.0 } else { 0.0 };
        }
        let n = mask.len();
        self.matched_fraction = mask.iter().filter(|&&m| m > 0.0).count() as f32 / n.max(1) as f32;
        self.mask = floats(mask, [n, 1], &self.mask.device());
        self
    }

    pub fn to_record(&self, view: usize, width: usize, height: usize) -> ViewColourTargets {
        // The relu5 grid is floor(size / 16) per axis, as `patch_means` is for any patch.
        let [rows, cols] = [height / self.patch, width / self.patch];
        let target = to_vec(self.target.clone());
        let mask = to_vec(self.mask.clone());
        let targets = mask
            .iter()
            .enumerate()
            .map(|(i, &m)| (m > 0.0).then(|| [target[i * 3], target[i * 3 + 1], target[i * 3 + 2]]))
            .collect();
        let sources = mask.iter().zip(&self.source).map(|(&m, &s)| (m > 0.0).then_some(s)).collect();
        ViewColourTargets {
            view,
            patch: self.patch,
            positions: [cols, rows],
            matched_fraction: self.matched_fraction,
            targets,
            sources,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::device;

    /// An 8x8 view whose left three columns are edited, on a 2x2 grid of
    /// 4-pixel cells: the left cells three quarters edited, the right ones
    /// not; a region inside one cell keeps that cell.
    #[test]
    fn a_template_keeps_the_cells_its_region_covers() {
        let edited: Vec<bool> = (0..64).map(|i| i % 8 < 3).collect();
        assert_eq!(cell_fractions(&edited, 8, [2, 2], 4), vec![0.75, 0.0, 0.75, 0.0]);
        assert_eq!(edited_cells(&[0.75, 0.0, 0.75, 0.0]), vec![0, 2]);
        let speck: Vec<bool> = (0..64).map(|i| i == 8 * 5 + 6).collect();
        let fractions = cell_fractions(&speck, 8, [2, 2], 4);
        assert_eq!(fractions, vec![0.0, 0.0, 0.0, 1.0 / 16.0]);
        assert_eq!(edited_cells(&fractions), vec![3], "a region smaller than a cell keeps the cell it touches");
    }

    /// Coarse matches carried to full size at n = 2: the identity stays the
    /// identity (each full-size position matched to itself), a match into
    /// the second reference lands in the second reference's full-size grid
    /// with its 2x2 layout, and an odd full-size edge (5 rows over 2 coarse
    /// ones) takes the last coarse row, clamped to the reference's grid.
    #[test]
    fn coarse_matches_carry_to_full_size_keeping_the_patch_layout() {
        let identity: Vec<usize> = (0..4).collect();
        let refs = [vec![[2, 2]], vec![[4, 4]]];
        assert_eq!(carry_matches(&identity, [[2, 2], [4, 4]], &refs, 2), (0..16).collect::<Vec<_>>());

        // Two references of 2x2 coarse (4x4 full) positions; every coarse
        // view position matched to the second reference's position (1, 0).
        let refs = [vec![[2, 2], [2, 2]], vec![[4, 4], [4, 4]]];
        let carried = carry_matches(&[6; 4], [[2, 2], [4, 4]], &refs, 2);
        let want = |dy: usize, dx: usize| 16 + (2 + dy) * 4 + dx;
        assert_eq!(&carried[..4], &[want(0, 0), want(0, 1), want(0, 0), want(0, 1)]);
        assert_eq!(carried[4 + 1], want(1, 1), "row 1, column 1: the block's lower right");

        let refs = [vec![[2, 1]], vec![[5, 2]]];
        let carried = carry_matches(&[0, 1], [[2, 1], [5, 2]], &refs, 2);
        // Rows 0-1 from coarse row 0, rows 2-4 from coarse row 1 (row 4 a second "lower" row).
        assert_eq!(carried, vec![0, 1, 2, 3, 4, 5, 6, 7, 6, 7]);
    }

    /// The colour template of a region takes each patch's mean over its
    /// edited pixels only: the painted colour, not its mix with the photo.
    #[test]
    fn a_regions_patch_colour_is_the_mean_of_its_edited_pixels() {
        let rgb: Vec<f32> = (0..64).flat_map(|i| if i % 8 < 2 { [1.0, 0.0, 0.0] } else { [0.0, 0.0, 1.0] }).collect();
        let image = Image::new(8, 8, rgb);
        let edited: Vec<bool> = (0..64).map(|i| i % 8 < 2).collect();
        assert_eq!(edited_patch_means(&image, &edited, 4, &[0, 2]), vec![1.0, 0.0, 0.0, 1.0, 0.0, 0.0]);
    }

    /// The colour map's targets at `target_patch` 4 on an 8x8 view: four
    /// patches, each the mean of its block of the mapped render, the white
    /// block of the content unsupervised, and the record's grid 2x2.
    #[test]
    fn mapped_targets_are_block_means_at_the_configured_patch() {
        let d = device();
        let block = |x: usize, y: usize| (y / 4) * 2 + x / 4;
        let pixel = |img: &mut Vec<f32>, c: [f32; 3]| img.extend_from_slice(&c);
        let (mut content, mut mapped) = (Vec::new(), Vec::new());
        for y in 0..8 {
            for x in 0..8 {
                let b = block(x, y);
                pixel(&mut content, if b == 3 { [1.0; 3] } else { [0.2 * b as f32, 0.5, 0.1] });
                // Alternating columns around the block's colour: the mean is the colour.
                let s = if x % 2 == 0 { 0.05 } else { -0.05 };
                pixel(&mut mapped, [0.1 * b as f32 + 0.3 + s, 0.4, 0.6 - s]);
            }
        }
        let (content, mapped) = (Image::new(8, 8, content), Image::new(8, 8, mapped));
        let t = ColourTargets::from_mapped(&content, &mapped, Some(0.99), 4, &d);
        assert_eq!(t.target.dims(), [4, 3]);
        let target = to_vec(t.target.clone());
        for b in 0..4 {
            let want = [0.1 * b as f32 + 0.3, 0.4, 0.6];
            for c in 0..3 {
                assert!((target[b * 3 + c] - want[c]).abs() < 1e-5, "block {b}: {:?}", &target[b * 3..b * 3 + 3]);
            }
        }
        assert_eq!(to_vec(t.mask.clone()), vec![1.0, 1.0, 1.0, 0.0]);
        let record = t.to_record(0, 8, 8);
        assert_eq!((record.patch, record.positions), (4, [2, 2]));
        assert!(record.targets[3].is_none() && record.targets[0].is_some());
    }
}
