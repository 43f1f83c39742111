//! The reference's colour mapping, carried to surfaces it never sees.
//!
//! A painted reference S_R and the content render I_R of the same camera are
//! pixel-aligned: each scene pixel says "this photo colour became that
//! painted colour". [`ColourMap::fit`] turns those pairs into a smooth map
//! over colour space: the painted-minus-photo offsets are binned by photo
//! colour, and the map at any colour is a Gaussian-weighted mean of the
//! bins' offsets near it, shrunk towards no change where few pixels are near
//! (a colour the reference never shows keeps its photo colour). Applied to
//! the refit field's per-voxel colours it recolours every surface of the
//! same material the same way, consistent across views by construction;
//! applied to each view's content render it gives L_color targets that do
//! not depend on which reference patch a view happens to match.

use crate::stylize::config::{ColourMapConfig, MapPrior};
use crate::stylize::styles::is_background;
use crate::util::image::Image;

/// A map from photo colour to painted colour, tabulated at bin centres and
/// interpolated trilinearly between them.
#[derive(Debug, Clone)]
pub struct ColourMap {
    bins: usize,
    /// Offset (painted - photo) at each bin centre, `[r][g][b]` row-major.
    offsets: Vec<[f32; 3]>,
    /// Pixels of this colour (`styles::is_background`) are not the scene:
    /// neither fitted nor mapped.
    background: [f32; 3],
    /// Reference pixels the map was fitted on.
    pub pixels: usize,
}

/// The least-squares affine colour transform of the pairs' scene pixels:
/// per painted channel `k`, the coefficients of (photo r, g, b, 1). None
/// when the photo colours do not span colour space (a single colour, or
/// colours along one line), where the fit would be arbitrary.
fn affine_fit(pairs: &[(&Image, &Image)], background: [f32; 3]) -> Option<[[f64; 4]; 3]> {
    let (mut xtx, mut xts, mut n) = ([[0.0f64; 4]; 4], [[0.0f64; 4]; 3], 0usize);
    for (c, s) in scene_pixels(pairs, background) {
        let x = [f64::from(c[0]), f64::from(c[1]), f64::from(c[2]), 1.0];
        for i in 0..4 {
            (0..4).for_each(|j| xtx[i][j] += x[i] * x[j]);
            (0..3).for_each(|k| xts[k][i] += x[i] * f64::from(s[k]));
        }
        n += 1;
    }
    let m = glam::DMat4::from_cols_array_2d(&xtx);
    // Relative to the pixel count: the determinant of a well-spread set grows as n^4.
    if n == 0 || m.determinant().abs() <= 1e-10 * (n as f64).powi(4) {
        return None;
    }
    let inv = m.inverse();
    Some(std::array::from_fn(|k| inv.mul_vec4(glam::DVec4::from_array(xts[k])).to_array()))
}

/// The (content, painted) colour pairs of `pairs`' pixels whose content
/// colour is not the `background`: what the map is fitted on and scored on.
fn scene_pixels<'a>(
    pairs: &'a [(&Image, &Image)],
    background: [f32; 3],
) -> impl Iterator<Item = ([f32; 3], [f32; 3])> + 'a {
    pairs.iter().flat_map(move |(content, style)| {
        assert_eq!(content.rgb.len(), style.rgb.len(), "a reference and its content render differ in size");
        content
            .rgb
            .chunks_exact(3)
            .zip(style.rgb.chunks_exact(3))
            .map(|(c, s)| ([c[0], c[1], c[2]], [s[0], s[1], s[2]]))
            .filter(move |(c, _)| !is_background(c, background))
    })
}

fn bin_of(c: f32, bins: usize) -> usize {
    ((c.clamp(0.0, 1.0) * bins as f32) as usize).min(bins - 1)
}

impl ColourMap {
    /// Fits the map on pixel-aligned (content render, painted reference)
    /// pairs, over the pixels whose content colour is not the `background`.
    pub fn fit(pairs: &[(&Image, &Image)], cfg: &ColourMapConfig, background: [f32; 3]) -> Self {
        let b = cfg.bins;
        // Per bin: summed offsets and pixel count.
        let mut sums = vec![[0.0f64; 3]; b * b * b];
        let mut counts = vec![0.0f64; b * b * b];
        let mut pixels = 0;
        for (c, s) in scene_pixels(pairs, background) {
            let i = (bin_of(c[0], b) * b + bin_of(c[1], b)) * b + bin_of(c[2], b);
            (0..3).for_each(|k| sums[i][k] += f64::from(s[k] - c[k]));
            counts[i] += 1.0;
            pixels += 1;
        }
        let filled: Vec<usize> = (0..counts.len()).filter(|&i| counts[i] > 0.0).collect();
        let centre = |i: usize| {
            let (r, g, bl) = (i / (b * b), (i / b) % b, i % b);
            [r, g, bl].map(|x| (x as f32 + 0.5) / b as f32)
        };
        let affine = match cfg.prior {
            MapPrior::Unchanged => None,
            MapPrior::Affine => affine_fit(pairs, background),
        };
        // The prior's offset at a colour: none, or the affine transform's (clamped as any painted colour).
        let prior_offset = |p: [f32; 3]| -> [f64; 3] {
            let Some(a) = &affine else { return [0.0; 3] };
            let x = [f64::from(p[0]), f64::from(p[1]), f64::from(p[2]), 1.0];
            std::array::from_fn(|k| (0..4).map(|j| a[k][j] * x[j]).sum::<f64>().clamp(0.0, 1.0) - x[k])
        };
        let two_var = 2.0 * cfg.sigma * cfg.sigma;
        let prior = f64::from(cfg.prior_pixels);
        let offsets = (0..b * b * b)
            .map(|at| {
                let p = centre(at);
                let (mut sum, mut weight) = (prior_offset(p).map(|o| o * prior), prior);
                for &i in &filled {
                    let q = centre(i);
                    let d2: f32 = (0..3).map(|k| (p[k] - q[k]).powi(2)).sum();
                    let w = f64::from((-d2 / two_var).exp());
                    (0..3).for_each(|k| sum[k] += w * sums[i][k]);
                    weight += w * counts[i];
                }
                match weight > 0.0 {
                    true => sum.map(|s| (s / weight) as f32),
                    false => [0.0; 3],
                }
            })
            .collect();
        ColourMap { bins: b, offsets, background, pixels }
    }

    /// The painted colour of photo colour `c` (clamped to [0, 1]).
    pub fn apply(&self, c: [f32; 3]) -> [f32; 3] {
        let b = self.bins;
        // Trilinear between bin centres (clamped at the outer half bins).
        let pos = c.map(|x| (x.clamp(0.0, 1.0) * b as f32 - 0.5).clamp(0.0, (b - 1) as f32));
        let lo = pos.map(|x| (x.floor() as usize).min(b - 2));
        let t: [f32; 3] = std::array::from_fn(|k| pos[k] - lo[k] as f32);
        let mut off = [0.0f32; 3];
        for corner in 0..8 {
            let idx: [usize; 3] = std::array::from_fn(|k| lo[k] + ((corner >> (2 - k)) & 1));
            let w: f32 = (0..3).map(|k| if (corner >> (2 - k)) & 1 == 1 { t[k] } else { 1.0 - t[k] }).product();
            let o = self.offsets[(idx[0] * b + idx[1]) * b + idx[2]];
            (0..3).for_each(|k| off[k] += w * o[k]);
        }
        std::array::from_fn(|k| (c[k] + off[k]).clamp(0.0, 1.0))
    }

    /// How much of the painting's change the map accounts for over the scene
    /// pixels of `pairs` (content render, painted reference):
    /// `1 - sum |S - map(C)|^2 / sum |S - C|^2`. A recolouring (every photo
    /// colour painted one way) is explained almost whole; painted strokes,
    /// which put many colours over one photo colour, are not. 1 when the
    /// painting changes nothing; below 0 when the map makes it worse.
    pub fn explained(&self, pairs: &[(&Image, &Image)]) -> f32 {
        let (mut change, mut left) = (0.0f64, 0.0f64);
        for (c, s) in scene_pixels(pairs, self.background) {
            let m = self.apply(c);
            change += (0..3).map(|k| f64::from(s[k] - c[k]).powi(2)).sum::<f64>();
            left += (0..3).map(|k| f64::from(s[k] - m[k]).powi(2)).sum::<f64>();
        }
        if change <= 0.0 { 1.0 } else { (1.0 - left / change) as f32 }
    }

    /// The map applied to every pixel of an image but the background's.
    pub fn apply_image(&self, img: &Image) -> Image {
        let rgb = img
            .rgb
            .chunks_exact(3)
            .flat_map(|p| {
                let c = [p[0], p[1], p[2]];
                if is_background(&c, self.background) { c } else { self.apply(c) }
            })
            .collect();
        Image::new(img.width, img.height, rgb)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(colours: &[[f32; 3]]) -> Image {
        Image::new(colours.len(), 1, colours.iter().flatten().copied().collect())
    }

    #[test]
    fn a_recolouring_is_carried_to_the_same_colours_and_unseen_colours_stay() {
        // Yellow became blue, grey became teal, 50 pixels each.
        let (yellow, grey, red) = ([0.9, 0.75, 0.1], [0.4, 0.4, 0.4], [0.8, 0.1, 0.1]);
        let (blue, teal) = ([0.1, 0.3, 0.9], [0.2, 0.5, 0.5]);
        let content = image(&[&[yellow; 50][..], &[grey; 50], &[[1.0; 3]; 20]].concat());
        let style = image(&[&[blue; 50][..], &[teal; 50], &[[1.0; 3]; 20]].concat());
        let cfg = ColourMapConfig::default();
        let map = ColourMap::fit(&[(&content, &style)], &cfg, [1.0; 3]);
        assert_eq!(map.pixels, 100);
        let close = |a: [f32; 3], b: [f32; 3], tol: f32| a.iter().zip(b).all(|(x, y)| (x - y).abs() < tol);
        assert!(close(map.apply(yellow), blue, 0.1), "yellow -> {:?}", map.apply(yellow));
        assert!(close(map.apply(grey), teal, 0.1), "grey -> {:?}", map.apply(grey));
        // A slightly different yellow goes the same way; red was never painted and stays.
        assert!(close(map.apply([0.85, 0.72, 0.15]), blue, 0.15), "{:?}", map.apply([0.85, 0.72, 0.15]));
        assert!(close(map.apply(red), red, 0.02), "red -> {:?}", map.apply(red));
    }

    /// A recolouring is explained almost whole; strokes of two colours
    /// painted over one photo colour are not (the map can only give their
    /// mean); a reference that changes nothing is explained whole.
    #[test]
    fn a_recolouring_is_explained_and_strokes_are_not() {
        let (yellow, grey) = ([0.9, 0.75, 0.1], [0.4, 0.4, 0.4]);
        let (blue, teal, red) = ([0.1, 0.3, 0.9], [0.2, 0.5, 0.5], [0.8, 0.1, 0.1]);
        let cfg = ColourMapConfig::default();
        let content = image(&[&[yellow; 60][..], &[grey; 60]].concat());
        let recoloured = image(&[&[blue; 60][..], &[teal; 60]].concat());
        let map = ColourMap::fit(&[(&content, &recoloured)], &cfg, [1.0; 3]);
        let explained = map.explained(&[(&content, &recoloured)]);
        assert!(explained > 0.95, "a recolouring: {explained}");
        // Every other pixel of each material painted red instead: strokes.
        let strokes: Vec<[f32; 3]> = (0..120)
            .map(|i| {
                if i % 2 == 0 {
                    red
                } else if i < 60 {
                    blue
                } else {
                    teal
                }
            })
            .collect();
        let stroked = image(&strokes);
        let map = ColourMap::fit(&[(&content, &stroked)], &cfg, [1.0; 3]);
        let explained = map.explained(&[(&content, &stroked)]);
        assert!((0.0..0.7).contains(&explained), "strokes: {explained}");
        let same = ColourMap::fit(&[(&content, &content)], &cfg, [1.0; 3]);
        assert_eq!(same.explained(&[(&content, &content)]), 1.0);
    }

    /// A colour the reference never shows keeps its photo colour with the
    /// "unchanged" prior, and takes the painting's affine transform with
    /// the "affine" one (here red and blue swapped, exactly affine).
    #[test]
    fn the_affine_prior_carries_a_grade_to_colours_never_shown() {
        let shown: Vec<[f32; 3]> =
            (0..64).map(|i| [(i % 4) as f32 / 8.0, ((i / 4) % 4) as f32 / 8.0, (i / 16) as f32 / 8.0]).collect();
        let swapped: Vec<[f32; 3]> = shown.iter().map(|c| [c[2], c[1], c[0]]).collect();
        let content = image(&shown.iter().flat_map(|c| [*c; 10]).collect::<Vec<_>>());
        let style = image(&swapped.iter().flat_map(|c| [*c; 10]).collect::<Vec<_>>());
        let never = [0.9, 0.6, 0.75];
        let fitted = |prior| {
            let cfg = ColourMapConfig { sigma: 0.03, prior, ..ColourMapConfig::default() };
            ColourMap::fit(&[(&content, &style)], &cfg, [1.0; 3]).apply(never)
        };
        let (kept, carried) = (fitted(MapPrior::Unchanged), fitted(MapPrior::Affine));
        let close = |a: [f32; 3], b: [f32; 3]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 0.01);
        assert!(close(kept, never), "unchanged prior: {kept:?}");
        assert!(close(carried, [0.75, 0.6, 0.9]), "affine prior: {carried:?}");
        // Colours the reference shows are its own either way.
        let cfg = ColourMapConfig { sigma: 0.03, prior: MapPrior::Affine, ..ColourMapConfig::default() };
        let map = ColourMap::fit(&[(&content, &style)], &cfg, [1.0; 3]);
        assert!(close(map.apply(shown[21]), swapped[21]), "{:?}", map.apply(shown[21]));
    }

    #[test]
    fn an_identity_reference_maps_every_colour_to_itself() {
        let colours: Vec<[f32; 3]> = (0..200).map(|i| [(i % 7) as f32 / 7.0, (i % 11) as f32 / 11.0, 0.3]).collect();
        let img = image(&colours);
        let map = ColourMap::fit(&[(&img, &img)], &ColourMapConfig::default(), [1.0; 3]);
        for c in &colours {
            assert_eq!(map.apply(*c), *c);
        }
    }
}
