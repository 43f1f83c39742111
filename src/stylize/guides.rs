//! What the image epochs are guided by, built from the field as it is:
//! the content renders of every training view, their VGG16 features, the
//! TCM template of the references and each view's matches and colour
//! targets (Ref-NPR), or the style features (ARF).

use anyhow::Result;
use burn::tensor::Tensor;

use crate::scene::camera::Camera;
use crate::scene::data::View;
use crate::stylize::Method;
use crate::stylize::colour_map::ColourMap;
use crate::stylize::config::WhiteOn;
use crate::stylize::step::{ContentFeatures, Guidance, StyleStep, ViewGuide};
use crate::stylize::tcm::{self, ColourTargets, RELU3, ReferencePair, StoredFeatures, Template};
use crate::util::image::Image;
use crate::util::progress::{Event, Phase, Progress};

/// Caches the sample lists, then builds the template (Ref-NPR) or the
/// style features (ARF) and every view's guide; also the fraction of
/// relu5 positions the colour loss supervises.
pub(crate) fn guidance(
    st: &mut StyleStep,
    styles: &[Image],
    keep_content: Option<Content>,
    colour: Option<ColourSource>,
    progress: &dyn Progress,
) -> Result<(Guidance, f32)> {
    st.cache_samples();
    let (template, style_bank) = match st.method() {
        Method::RefNpr => (Some(template(st, styles)?), None),
        Method::Arf => {
            let style = match st.cfg().arf.half_resolution {
                true => arf_style_at_half_resolution(&styles[0], &st.dataset().train[0].camera),
                false => styles[0].clone(),
            };
            let (raw, _) = tcm::image_features(&st.vgg, &style, &st.ad, &[&RELU3], false)?;
            (None, Some(raw.into_iter().next().expect("one block")))
        }
    };
    let (guides, matched) = guides(st, template.as_ref(), keep_content, colour, progress)?;
    Ok((Guidance { template, style_bank, guides }, matched))
}

/// Where L_color's targets come from.
#[derive(Clone, Copy)]
pub(crate) enum ColourSource<'m> {
    /// The TCM-matched reference patches (the paper).
    Matched,
    /// The colour map over the view's own content render, compared in
    /// `patch`-pixel patch means with weight `weight`.
    Mapped { map: &'m ColourMap, patch: usize, weight: f32 },
}

/// What the content term's fixed features are taken of.
#[derive(Clone, Copy)]
pub(crate) enum Content<'m> {
    /// The content render (the paper).
    Render,
    /// The content render through the colour map: the content's structure
    /// in the reference's colours, so the term no longer pulls them back.
    Mapped(&'m ColourMap),
}

/// Content renders, features, TCM matches and colour targets of every view.
pub(crate) fn guides(
    st: &StyleStep,
    template: Option<&Template>,
    keep_content: Option<Content>,
    colour: Option<ColourSource>,
    progress: &dyn Progress,
) -> Result<(Vec<ViewGuide>, f32)> {
    let blocks = st.method().feature_blocks();
    let n = st.dataset().train.len();
    progress.event(Event::Start { phase: Phase::Guides, done: 0, total: n });
    let mut out = Vec::with_capacity(n);
    let mut matched = 0.0;
    let half = st.method() == Method::Arf && st.cfg().arf.half_resolution;
    let half_content = st.half_content_features();
    for v in 0..n {
        let content = st.render_view(v);
        let halved;
        let vgg_input = if half {
            halved = content.half();
            &halved
        } else {
            &content
        };
        let matched_colour = matches!(colour, Some(ColourSource::Matched));
        let (raw, colour_desc) = tcm::image_features(&st.vgg, vgg_input, &st.ad, &blocks, matched_colour)?;
        let matches = template.map(|t| t.matches(&raw, st.cfg().search_chunk)).unwrap_or_default();
        let edit_votes =
            template.filter(|t| t.local).map(|t| t.edit_votes(&raw[0], st.cfg().search_chunk)).unwrap_or_default();
        // The content render through the colour map, once, for whichever of the two uses it.
        let mapped = match (keep_content, colour) {
            (Some(Content::Mapped(map)), _) | (_, Some(ColourSource::Mapped { map, .. })) => {
                Some(map.apply_image(&content))
            }
            _ => None,
        };
        let l = &st.cfg().loss;
        let white = (l.colour_white_on == WhiteOn::Content).then_some(l.colour_white);
        let colour = match (template, colour_desc, colour) {
            (Some(t), Some(d), _) => Some(ColourTargets {
                weight: l.colour,
                ..t.colour_targets(d, &content, l.colour_max_distance, white, st.cfg().search_chunk)
            }),
            (Some(_), None, Some(ColourSource::Mapped { patch, weight, .. })) => mapped
                .as_ref()
                .map(|m| ColourTargets { weight, ..ColourTargets::from_mapped(&content, m, white, patch, &st.device) }),
            _ => None,
        };
        let colour = match edit_votes.is_empty() {
            true => colour,
            false => colour.map(|c| c.only_edited(&edit_votes, content.width, content.height)),
        };
        matched += colour.as_ref().map_or(0.0, |c| c.matched_fraction / n as f32);
        let keep = v < st.content_views_kept;
        let content = match keep_content {
            None => ContentFeatures::Unused,
            Some(Content::Render) if keep => ContentFeatures::Kept(store(raw, half_content)),
            Some(Content::Render) => ContentFeatures::Recomputed(vgg_input.clone()),
            Some(Content::Mapped(_)) => {
                let mapped = mapped.expect("mapped above for Content::Mapped");
                match keep {
                    true => ContentFeatures::Kept(store(
                        tcm::image_features(&st.vgg, &mapped, &st.ad, &blocks, false)?.0,
                        half_content,
                    )),
                    false => ContentFeatures::Recomputed(mapped),
                }
            }
        };
        out.push(ViewGuide { content, matches, edit_votes, colour });
        progress.event(Event::Step { phase: Phase::Guides, done: v + 1, total: n, message: String::new() });
    }
    Ok((out, matched))
}

/// One view's TCM matches found on a coarse render (`coarse_matches`):
/// per block, indices into the coarse template's keys, and the render's
/// `[height, width]`.
pub(crate) struct CoarseMatches {
    indices: Vec<Vec<usize>>,
    size: [usize; 2],
}

/// `schedule.coarse_matches`, first half: TCM's matches between `st`'s
/// views as they are now (the coarse ones) and `template` (the references
/// at the coarse size). Rendering, VGG16 and the search run at the coarse
/// views' pixels: 1/n² of the renders and features, 1/n⁴ of the pairs.
pub(crate) fn coarse_matches(
    st: &StyleStep,
    template: &Template,
    progress: &dyn Progress,
) -> Result<Vec<CoarseMatches>> {
    let n = st.dataset().train.len();
    progress.event(Event::Start { phase: Phase::Guides, done: 0, total: n });
    let mut out = Vec::with_capacity(n);
    for v in 0..n {
        let content = st.render_view(v);
        let (raw, _) = tcm::image_features(&st.vgg, &content, &st.ad, &st.method().feature_blocks(), false)?;
        let indices = template.match_indices(&raw, st.cfg().search_chunk);
        out.push(CoarseMatches { indices, size: [content.height, content.width] });
        progress.event(Event::Step { phase: Phase::Guides, done: v + 1, total: n, message: String::new() });
    }
    Ok(out)
}

/// `schedule.coarse_matches`, second half: the smooth update's guides, the
/// coarse matches carried to `full` (the template at the references' own
/// size) and to `st`'s views, now the full-size ones
/// (`Template::matches_at_full_size`). None where they cannot be carried
/// (a local edit).
pub(crate) fn carried_guides(
    st: &StyleStep,
    coarse: &Template,
    matches: Vec<CoarseMatches>,
    full: &Template,
) -> Option<Vec<ViewGuide>> {
    let scale = st.cfg().schedule.coarse_scale as usize;
    let views = st.dataset().train.iter().zip(matches);
    let carry = |(view, m): (&View, CoarseMatches)| {
        let size = [view.camera.intrinsics.height as usize, view.camera.intrinsics.width as usize];
        let matches = full.matches_at_full_size(coarse, &m.indices, m.size, size, scale)?;
        Some(ViewGuide { content: ContentFeatures::Unused, matches, edit_votes: Vec::new(), colour: None })
    };
    views.map(carry).collect()
}

/// Features kept per block, as f16 when `half`.
fn store(blocks: Vec<Tensor<2>>, half: bool) -> Vec<StoredFeatures> {
    blocks.into_iter().map(|features| StoredFeatures::store(features, half)).collect()
}

/// The TCM template of the references, their content renders from the
/// field as it is now (a local edit's: their regions only).
pub(crate) fn template(st: &StyleStep, styles: &[Image]) -> Result<Template> {
    let pairs: Vec<ReferencePair> = styles
        .iter()
        .enumerate()
        .map(|(r, s)| {
            let region = st.regions.as_ref().map(|regions| regions[r].pair_region());
            ReferencePair { content: st.render_reference(r), style: s.clone(), region }
        })
        .collect();
    Template::build(&st.vgg, &pairs, &st.ad)
}

/// ARF's style image at the released code's scale: resized so its long side
/// is the views' long side, then halved (the renders VGG sees are halved too).
fn arf_style_at_half_resolution(style: &Image, view: &Camera) -> Image {
    let long_side = view.intrinsics.width.max(view.intrinsics.height) as f32;
    let scale = long_side / style.width.max(style.height) as f32;
    let (w, h) = ((style.width as f32 * scale).round() as usize, (style.height as f32 * scale).round() as usize);
    let sized = if (w, h) == (style.width, style.height) { style.clone() } else { style.resized(w, h) };
    sized.half()
}
