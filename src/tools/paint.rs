//! A quick painterly repaint of a content view, for trying stylization
//! without painting by hand (`refnpr paint`) and for the demo's second
//! reference case: a warm-shifted, posterized base overlaid with short
//! brush strokes that follow the image's edges. Deterministic under a seed.
//! Also colour grades (`Grade`): recolourings that are a function of the
//! pixel's colour alone, so a graded dataset is the exact intended result of
//! a graded reference at every view (`recolour_dataset`), the measure of how
//! far a reference's colours reach surfaces it never sees.

use std::path::Path;

use anyhow::{Context, Result, ensure};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Pixels brighter than this in every channel are background: left as they are.
const BACKGROUND: f32 = 0.97;

/// Hue rotation (degrees), saturation gain and posterization levels of the base.
const HUE_SHIFT: f32 = 35.0;
const SATURATION_GAIN: f32 = 1.6;
const LEVELS: f32 = 5.0;

fn rgb_to_hsv([r, g, b]: [f32; 3]) -> [f32; 3] {
    let max = r.max(g).max(b);
    let min = r.min(g).min(b);
    let d = max - min;
    let h = if d <= 0.0 {
        0.0
    } else if max == r {
        60.0 * ((g - b) / d).rem_euclid(6.0)
    } else if max == g {
        60.0 * ((b - r) / d + 2.0)
    } else {
        60.0 * ((r - g) / d + 4.0)
    };
    [h, if max > 0.0 { d / max } else { 0.0 }, max]
}

fn hsv_to_rgb([h, s, v]: [f32; 3]) -> [f32; 3] {
    let c = v * s;
    let hp = h.rem_euclid(360.0) / 60.0;
    let x = c * (1.0 - (hp % 2.0 - 1.0).abs());
    let (r, g, b) = match hp as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [r + m, g + m, b + m]
}

/// The base colour of a pixel: hue rotated, saturation raised, value posterized.
fn recolour(p: [f32; 3]) -> [f32; 3] {
    let [h, s, v] = rgb_to_hsv(p);
    let v = ((v * LEVELS).round() / LEVELS).clamp(0.08, 1.0);
    hsv_to_rgb([h + HUE_SHIFT, (s * SATURATION_GAIN + 0.15).min(1.0), v])
}

fn luminance(p: &[f32]) -> f32 {
    0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2]
}

/// Repaints an interleaved RGB image (`width * height * 3`, values in [0, 1]).
pub fn painterly(rgb: &[f32], width: usize, height: usize, seed: u64) -> Vec<f32> {
    assert_eq!(rgb.len(), width * height * 3, "image buffer is {width}x{height}x3");
    let px = |x: usize, y: usize| -> [f32; 3] {
        let i = (y * width + x) * 3;
        [rgb[i], rgb[i + 1], rgb[i + 2]]
    };
    let is_background = |p: [f32; 3]| p.iter().all(|&c| c > BACKGROUND);
    let mut out: Vec<f32> = (0..width * height)
        .flat_map(|i| {
            let p = px(i % width, i / width);
            if is_background(p) { p } else { recolour(p) }
        })
        .collect();
    // Brush strokes: short segments across the luminance gradient (along edges),
    // coloured from the recoloured source with a little jitter.
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let strokes = width * height / 5;
    let scale = (width.min(height) as f32 / 96.0).max(0.5);
    for _ in 0..strokes {
        let (x, y) = (rng.random_range(0..width), rng.random_range(0..height));
        let src = px(x, y);
        if is_background(src) {
            continue;
        }
        let (xl, xr) = (x.saturating_sub(1), (x + 1).min(width - 1));
        let (yu, yd) = (y.saturating_sub(1), (y + 1).min(height - 1));
        let gx = luminance(&px(xr, y)) - luminance(&px(xl, y));
        let gy = luminance(&px(x, yd)) - luminance(&px(x, yu));
        let angle = if gx.abs() + gy.abs() > 1e-3 {
            gy.atan2(gx) + std::f32::consts::FRAC_PI_2
        } else {
            rng.random_range(0.0..std::f32::consts::PI)
        };
        let (dx, dy) = (angle.cos(), angle.sin());
        let length = rng.random_range(3.0..7.0) * scale;
        let jitter = rng.random_range(-0.06f32..0.06);
        let colour = recolour(src).map(|c| (c + jitter).clamp(0.0, 1.0));
        let mut t = -length / 2.0;
        while t <= length / 2.0 {
            for w in [-0.5f32, 0.5] {
                let sx = (x as f32 + t * dx - w * dy * scale).round();
                let sy = (y as f32 + t * dy + w * dx * scale).round();
                if sx < 0.0 || sy < 0.0 || sx >= width as f32 || sy >= height as f32 {
                    continue;
                }
                let (sx, sy) = (sx as usize, sy as usize);
                if is_background(px(sx, sy)) {
                    continue;
                }
                let i = (sy * width + sx) * 3;
                for c in 0..3 {
                    out[i + c] = 0.2 * out[i + c] + 0.8 * colour[c];
                }
            }
            t += 0.5;
        }
    }
    out
}

/// A recolouring an artist might make, as a function of the colour alone.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Grade {
    /// Every hue rotated by 150°, saturation raised a little (greys stay grey).
    Hue,
    /// Material repaints: yellows become blue, greys and darks a teal tint; other colours stay.
    Materials,
    /// A film grade: shadows towards teal, highlights towards orange, more contrast.
    TealOrange,
}

fn smoothstep(lo: f32, hi: f32, x: f32) -> f32 {
    let t = ((x - lo) / (hi - lo)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// The signed hue difference `to - from` in (-180, 180].
fn hue_delta(from: f32, to: f32) -> f32 {
    let d = (to - from).rem_euclid(360.0);
    if d > 180.0 { d - 360.0 } else { d }
}

impl Grade {
    /// The graded colour of one pixel; near-white background stays as it is.
    pub fn apply(self, p: [f32; 3]) -> [f32; 3] {
        if p.iter().all(|&c| c > BACKGROUND) {
            return p;
        }
        let out = match self {
            Grade::Hue => {
                let [h, s, v] = rgb_to_hsv(p);
                hsv_to_rgb([h + 150.0, (s * 1.15).min(1.0), v])
            }
            Grade::Materials => {
                let [h, s, v] = rgb_to_hsv(p);
                // Yellow (hue near 50°, saturated) -> blue; greys and darks -> a teal tint.
                let yellow = (1.0 - smoothstep(20.0, 35.0, hue_delta(50.0, h).abs())) * smoothstep(0.2, 0.4, s);
                let grey = 1.0 - smoothstep(0.1, 0.3, s);
                let hue = h + yellow * hue_delta(h, 215.0);
                let hue = hue + grey * hue_delta(hue, 175.0);
                hsv_to_rgb([hue, (s + grey * 0.45).min(1.0), v])
            }
            Grade::TealOrange => {
                let l = luminance(&p);
                let (teal, orange) = ([-0.10, 0.03, 0.10], [0.12, 0.03, -0.12]);
                std::array::from_fn(|c| 0.5 + 1.15 * (p[c] - 0.5) + (1.0 - l) * teal[c] + l * orange[c])
            }
        };
        out.map(|c| c.clamp(0.0, 1.0))
    }

    /// Grades an interleaved RGB image.
    pub fn image(self, rgb: &[f32]) -> Vec<f32> {
        rgb.chunks_exact(3).flat_map(|p| self.apply([p[0], p[1], p[2]])).collect()
    }
}

/// Which objects an edit changes: object ids of the procedural scene's
/// `*_id.png` maps (1 ground, 2 sphere, 3 box, 4 cylinder); None: everything.
pub type Objects<'a> = Option<&'a [u8]>;

/// Per pixel of the id map at `path`, whether its object is one of
/// `objects`; the map must be `width` x `height`.
pub fn object_mask(path: &Path, objects: &[u8], width: u32, height: u32) -> Result<Vec<bool>> {
    let ids = ::image::open(path).with_context(|| format!("cannot read object-id map {}", path.display()))?.to_luma8();
    ensure!(
        ids.dimensions() == (width, height),
        "object-id map {} is {}x{}, the image is {width}x{height}",
        path.display(),
        ids.width(),
        ids.height()
    );
    Ok(ids.pixels().map(|p| objects.contains(&p[0])).collect())
}

/// `edited` where `mask` is set, `original` elsewhere (interleaved RGB).
pub fn only_where(original: &[f32], edited: &[f32], mask: &[bool]) -> Vec<f32> {
    original
        .chunks_exact(3)
        .zip(edited.chunks_exact(3))
        .zip(mask)
        .flat_map(|((o, e), &m)| if m { e } else { o })
        .copied()
        .collect()
}

/// What `recolour_dataset` did: images graded, and (with objects) images
/// copied unchanged because they have no object-id map beside them.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Recoloured {
    pub graded: usize,
    pub without_ids: usize,
}

/// Copies the dataset folder `src` to `out` with every colour image graded
/// (alpha kept; depth and normal maps copied as they are): the intended
/// result of a reference graded the same way, at every view (`refnpr eval
/// --gt`). With `objects`, only those objects' pixels are graded (each
/// image's `NAME_id.png` beside it says which pixel is which): the intended
/// result of a local edit.
pub fn recolour_dataset(src: &Path, out: &Path, grade: Grade, objects: Objects) -> Result<Recoloured> {
    ensure!(src.is_dir(), "{}: not a dataset folder", src.display());
    ensure!(!out.exists(), "{} exists: choose a new folder", out.display());
    let mut done = Recoloured::default();
    copy_graded(src, out, grade, objects, &mut done)?;
    Ok(done)
}

fn copy_graded(src: &Path, out: &Path, grade: Grade, objects: Objects, done: &mut Recoloured) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    for entry in std::fs::read_dir(src).with_context(|| format!("cannot read {}", src.display()))? {
        let path = entry?.path();
        let to = out.join(path.file_name().expect("a directory entry has a name"));
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        let is_map = name.contains("_depth") || name.contains("_normal") || name.ends_with("_id.png");
        let ids = path.with_file_name(format!("{}_id.png", name.trim_end_matches(".png")));
        if path.is_dir() {
            copy_graded(&path, &to, grade, objects, done)?;
        } else if name.ends_with(".png") && !is_map && (objects.is_none() || ids.exists()) {
            let mut img =
                ::image::open(&path).with_context(|| format!("cannot read image {}", path.display()))?.to_rgba32f();
            let mask = match objects {
                Some(o) => object_mask(&ids, o, img.width(), img.height())?,
                None => vec![true; img.pixels().len()],
            };
            for (px, _) in img.pixels_mut().zip(&mask).filter(|(_, m)| **m) {
                let [r, g, b] = grade.apply([px[0], px[1], px[2]]);
                (px[0], px[1], px[2]) = (r, g, b);
            }
            let rgba = ::image::DynamicImage::ImageRgba32F(img).to_rgba8();
            rgba.save(&to).with_context(|| format!("cannot write {}", to.display()))?;
            done.graded += 1;
        } else {
            done.without_ids += usize::from(name.ends_with(".png") && !is_map);
            std::fs::copy(&path, &to).with_context(|| format!("cannot copy {} to {}", path.display(), to.display()))?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grades_keep_white_change_colours_and_greys_as_named() {
        for g in [Grade::Hue, Grade::Materials, Grade::TealOrange] {
            assert_eq!(g.apply([1.0, 1.0, 1.0]), [1.0, 1.0, 1.0], "{g:?} moved the background");
        }
        let yellow = [0.9, 0.75, 0.1];
        let blue = Grade::Materials.apply(yellow);
        assert!(blue[2] > blue[0] && blue[2] > 0.5, "materials: yellow -> {blue:?}");
        let red = [0.8, 0.1, 0.1];
        let kept = Grade::Materials.apply(red);
        assert!(kept.iter().zip(red).all(|(a, b)| (a - b).abs() < 1e-4), "materials moved red: {kept:?}");
        let grey = Grade::Hue.apply([0.4, 0.4, 0.4]);
        assert!(grey.iter().all(|c| (c - 0.4).abs() < 1e-5), "hue moved a grey: {grey:?}");
        assert_ne!(Grade::Hue.apply(yellow), yellow);
    }

    /// `recolour --objects`: only the listed objects' pixels are graded, by
    /// the id map beside each image; an image without one is copied as it is.
    #[test]
    fn recolouring_some_objects_grades_only_their_pixels() {
        let src = crate::test_support::temp_dir("recolour-objects");
        let (red, yellow) = ([200u8, 30, 30, 255], [230u8, 200, 30, 255]);
        let img = ::image::RgbaImage::from_fn(2, 1, |x, _| ::image::Rgba(if x == 0 { red } else { yellow }));
        img.save(src.join("r_0.png")).unwrap();
        img.save(src.join("other.png")).unwrap();
        ::image::GrayImage::from_fn(2, 1, |x, _| ::image::Luma([if x == 0 { 2 } else { 3 }]))
            .save(src.join("r_0_id.png"))
            .unwrap();
        let out = src.with_extension("out");
        let _ = std::fs::remove_dir_all(&out);
        let done = recolour_dataset(&src, &out, Grade::Hue, Some(&[2])).unwrap();
        assert_eq!(done, Recoloured { graded: 1, without_ids: 1 });
        let got = ::image::open(out.join("r_0.png")).unwrap().to_rgba8();
        assert_ne!(got.get_pixel(0, 0).0, red, "object 2 was not graded");
        assert_eq!(got.get_pixel(1, 0).0, yellow, "object 3 was graded");
        assert_eq!(::image::open(out.join("other.png")).unwrap().to_rgba8(), img, "no id map: copied");
    }

    #[test]
    fn hsv_round_trips() {
        for p in [[0.2, 0.5, 0.9], [0.9, 0.1, 0.3], [0.4, 0.4, 0.4], [0.0, 0.0, 0.0], [1.0, 0.8, 0.0]] {
            let q = hsv_to_rgb(rgb_to_hsv(p));
            assert!(p.iter().zip(q).all(|(a, b)| (a - b).abs() < 1e-5), "{p:?} -> {q:?}");
        }
    }

    #[test]
    fn painting_keeps_the_background_changes_the_rest_and_is_deterministic() {
        let (w, h) = (40, 30);
        let rgb: Vec<f32> = (0..w * h)
            .flat_map(|i| {
                let (x, y) = (i % w, i / w);
                if x < 10 {
                    [1.0, 1.0, 1.0]
                } else {
                    [0.2 + 0.5 * (x as f32 / w as f32), 0.4, 0.3 + 0.4 * (y as f32 / h as f32)]
                }
            })
            .collect();
        let a = painterly(&rgb, w, h, 1);
        assert_eq!(a, painterly(&rgb, w, h, 1));
        assert_ne!(a, painterly(&rgb, w, h, 2));
        for y in 0..h {
            for x in 0..8 {
                let i = (y * w + x) * 3;
                assert_eq!(&a[i..i + 3], &[1.0, 1.0, 1.0], "background pixel ({x}, {y}) changed");
            }
        }
        let changed = (0..w * h).filter(|&p| (0..3).any(|c| (a[p * 3 + c] - rgb[p * 3 + c]).abs() > 0.05)).count();
        assert!(changed > w * h / 2, "{changed} of {} pixels repainted", w * h);
    }
}
