//! The far background's stylization (Ref-NPR on a capture whose field
//! learned one, `field::environment`): painted where a reference sees it,
//! recoloured the way the reference recoloured it everywhere else, then
//! fixed for the rest of the stylization.
//!
//! Why fixed, not optimised with the grid: the far map has no parallax,
//! so a reference pixel that sees it says exactly what colour the map has
//! in that direction, for every view: registration needs no depth, and
//! the painted directions are carried whole, more exactly than R³ carries
//! surfaces. Where no reference looks, TCM's patches would have nothing of
//! the background to match but other background patches; the reference's
//! own photo-to-painted colour mapping, fitted on the pixels that do see
//! the background ([`ColourMap`]), recolours the rest the same way. A map
//! fixed before the loop is the same in every view, so the stylized
//! background is consistent across views by construction.

use crate::field::environment::Environment;
use crate::reference::registration::ReferencePixels;
use crate::stylize::colour_map::ColourMap;
use crate::stylize::config::ColourMapConfig;
use crate::util::image::Image;

/// A reference pixel paints the far map only where the field leaves at
/// least this much of its ray (the rest of its colour is the field's).
const SEES_FAR: f32 = 0.9;

/// How many pixels' worth of painted colour a texel needs to take it
/// over its recoloured photo colour half-way (`seen / (seen + this)`).
const PAINT_CONFIDENCE: f32 = 1.0;

/// No colour of a far map is "the background" the colour map skips.
const NO_BACKGROUND: [f32; 3] = [-1.0; 3];

/// The photoreal far map `photo` stylized by the references. `left` is
/// the transmittance the field leaves each reference pixel's ray (every
/// reference's pixels one after another, as the stylization's sample
/// lists marched them): it decides which pixels see the far background.
pub fn stylized_far(
    photo: &Environment,
    references: &[ReferencePixels],
    left: &[f32],
    cfg: &ColourMapConfig,
) -> Environment {
    let (mut painted, mut seen) = (vec![0.0f32; photo.rgb.len()], vec![0.0f32; photo.rgb.len() / 3]);
    let (mut photo_side, mut painted_side) = (Vec::new(), Vec::new());
    let rays = references.iter().flat_map(|r| r.camera.rays(None).into_iter().zip(&r.colours));
    assert_eq!(left.len(), references.iter().map(|r| r.colours.len()).sum::<usize>(), "one transmittance per pixel");
    for ((ray, colour), &t) in rays.zip(left) {
        if t < SEES_FAR {
            continue;
        }
        photo.splat(ray.view_dir, |texel, w| {
            seen[texel] += w;
            (0..3).for_each(|c| painted[texel * 3 + c] += w * colour[c]);
        });
        photo_side.extend(photo.colour(ray.view_dir));
        painted_side.extend(colour);
    }
    let n = photo_side.len() / 3;
    let (photo_img, painted_img) = (Image::new(n, 1, photo_side), Image::new(n, 1, painted_side));
    let map = ColourMap::fit(&[(&photo_img, &painted_img)], cfg, NO_BACKGROUND);
    let rgb = photo
        .rgb
        .chunks_exact(3)
        .enumerate()
        .flat_map(|(texel, c)| {
            let recoloured = map.apply([c[0], c[1], c[2]]);
            let (s, paint) = (seen[texel], &painted[texel * 3..texel * 3 + 3]);
            let a = s / (s + PAINT_CONFIDENCE);
            std::array::from_fn::<f32, 3, _>(|k| match s > 0.0 {
                true => a * paint[k] / s + (1.0 - a) * recoloured[k],
                false => recoloured[k],
            })
        })
        .collect();
    Environment { width: photo.width, height: photo.height, rgb }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::camera::{Camera, Intrinsics, look_at};
    use glam::Vec3;

    fn close(a: [f32; 3], b: [f32; 3], tol: f32) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
    }

    /// A reference looking along +x through empty space paints its left
    /// half one colour and its right half another: the far map takes each
    /// where the reference saw it, and the photo colour's mean repaint
    /// everywhere it did not; pixels the field covers paint nothing.
    #[test]
    fn seen_directions_take_the_paint_and_unseen_ones_the_references_recolouring() {
        let photo = Environment::uniform(32, 16, [0.7, 0.6, 0.2]);
        let (left, right) = ([0.1, 0.8, 0.2], [0.1, 0.4, 0.9]);
        let (w, h) = (40u32, 30u32);
        let camera = Camera::new(Intrinsics::from_fov_x(w, h, 1.2), look_at(Vec3::ZERO, Vec3::X, Vec3::Z));
        let colours = (0..h).flat_map(|_| (0..w).map(move |x| if x < w / 2 { left } else { right })).collect();
        let reference = ReferencePixels { camera, colours, hits: vec![false; (w * h) as usize] };
        let cfg = ColourMapConfig::default();
        let far = stylized_far(&photo, std::slice::from_ref(&reference), &vec![1.0; (w * h) as usize], &cfg);
        // Directions through the middle of each half of the reference.
        let through = |x: f32| camera.ray(x, h as f32 / 2.0).view_dir;
        assert!(close(far.colour(through(w as f32 * 0.2)), left, 0.05), "{:?}", far.colour(through(8.0)));
        assert!(close(far.colour(through(w as f32 * 0.8)), right, 0.05), "{:?}", far.colour(through(32.0)));
        // Behind the reference and straight up: the photo colour, repainted
        // as the reference repainted it on average.
        let mean: [f32; 3] = std::array::from_fn(|k| (left[k] + right[k]) / 2.0);
        for d in [-Vec3::X, Vec3::new(-0.3, 0.5, 0.8)] {
            assert!(close(far.colour(d), mean, 0.1), "{d}: {:?} vs {mean:?}", far.colour(d));
        }
        // A reference whose every ray the field stops leaves the map as it was.
        let covered = stylized_far(&photo, &[reference], &vec![0.0; (w * h) as usize], &cfg);
        assert!(close(covered.colour(through(8.0)), [0.7, 0.6, 0.2], 1e-5), "{:?}", covered.colour(through(8.0)));
    }
}
