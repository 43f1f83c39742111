//! The painting's strokes at another scale (`[controls] stroke_scale`,
//! `--stroke-scale`), made on the painting itself before any work on the
//! field.
//!
//! Changing the scale at which the losses match features does not move the
//! pattern (docs/local_edits.md: measured and taken out): R³ registers most
//! surfaces a view shows to the painting's own pixels, and L_ref holds them
//! at the painting's scale. So the painting is rescaled instead, and every
//! term (R³'s colours, TCM's template, L_color's patches) carries the new
//! pattern. Only the strokes move: the part of the painting that follows
//! the content render's structure (its colours, the objects' outlines) stays
//! where it is, and the texture left over (the strokes) is magnified.
//! Strokes are made larger only: shrinking the texture repeats its shapes
//! (the painting's texture is not a stationary pattern), and the tiles show.

use anyhow::Result;

use crate::field::checkpoint;
use crate::reference::case::{ReferenceCase, read_style};
use crate::scene::data::Dataset;
use crate::stylize::StylizeJob;
use crate::stylize::region::PixelRegion;
use crate::stylize::styles::is_background;
use crate::util::image::Image;
use crate::util::progress::Progress;

/// The guided filter's window radius, as a fraction of the image's shorter
/// side times the scale: the painting's colours are explained by the
/// content's local structure over windows larger than a stroke, so that
/// what is left over (the texture) holds the strokes at the new size too.
const GUIDE_RADIUS: f32 = 0.03;
/// The guided filter's regulariser (a variance of the content's luminance):
/// where the content varies less than this over a window the painting is
/// not taken to follow it (a painted-over region's texture is the strokes,
/// not the photo's detail subtracted).
const GUIDE_EPS: f32 = 0.05;
/// The tiles the texture is magnified in, as a fraction of the shorter side
/// times the scale: each tile enlarges the texture about its own centre, so
/// a stroke stays near the surface it was painted on.
const TILE: f32 = 0.25;

/// The case with each painting's strokes rescaled by `[controls]
/// stroke_scale` (unchanged at 1): the rescaled paintings are written to
/// the run folder as `strokes_N.png` (what every loss then sees) and the
/// case points at them. `regions` (a local edit's, found on the paintings
/// as given) limit the change to the painted pixels.
pub(crate) fn scaled_case(
    job: &StylizeJob,
    case: ReferenceCase,
    dataset: &Dataset,
    regions: Option<&[PixelRegion]>,
    progress: &dyn Progress,
) -> Result<ReferenceCase> {
    let scale = job.config.controls.stroke_scale;
    if scale == 1.0 {
        return Ok(case);
    }
    // The render each painting was made over: the photoreal field with its
    // view-dependent bands, as `refnpr reference` wrote content.png.
    let photo = checkpoint::load_with(&job.photo, &job.backend.open(progress)?, false)?;
    let background = photo.meta.background;
    let mut scaled = case.clone();
    for (r, (spec, camera)) in scaled.references.iter_mut().zip(case.cameras(dataset)?).enumerate() {
        let (w, h) = (camera.intrinsics.width, camera.intrinsics.height);
        let style = Image::new(w as usize, h as usize, read_style(&spec.style, w, h, background)?.0);
        let content = photo.render_view(&camera).image;
        let region = regions.map(|regions| &regions[r]);
        let out = rescale_strokes(&content, &style, scale, region, background);
        let path = job.out.join(format!("strokes_{r}.png"));
        out.save_png(&path)?;
        spec.style = path;
    }
    progress.info(format!(
        "the paintings' strokes {scale} times their size: the losses see {}",
        job.out.join("strokes_N.png").display()
    ));
    Ok(scaled)
}

/// `style` with its strokes `scale` times larger. `content` is the render
/// the painting was made over, at its camera. The painting is split, with
/// a guided filter on the content's luminance, into what follows the
/// content's structure and the texture left over; the texture is magnified
/// in overlapping tiles and added back. Background pixels (of the content)
/// and, with a `region` (a local edit), pixels outside it stay as painted.
pub fn rescale_strokes(
    content: &Image,
    style: &Image,
    scale: f32,
    region: Option<&PixelRegion>,
    background: [f32; 3],
) -> Image {
    if scale == 1.0 {
        return style.clone();
    }
    let (w, h) = (style.width, style.height);
    let side = w.min(h) as f32 * scale;
    let radius = ((GUIDE_RADIUS * side).round() as usize).max(2);
    let follows = guided_filter(content, style, radius, GUIDE_EPS);
    let texture: Vec<f32> = style.rgb.iter().zip(&follows).map(|(s, f)| s - f).collect();
    let moved = magnified_in_tiles(&texture, w, h, scale, TILE * side);
    let mut rgb = style.rgb.clone();
    for (i, px) in rgb.chunks_exact_mut(3).enumerate() {
        let c = &content.rgb[i * 3..][..3];
        if region.is_some_and(|r| !r.inside[i]) || is_background(&[c[0], c[1], c[2]], background) {
            continue;
        }
        (0..3).for_each(|k| px[k] = (follows[i * 3 + k] + moved[i * 3 + k]).clamp(0.0, 1.0));
    }
    Image::new(w, h, rgb)
}

/// The guided filter (He et al.) of each channel of `style` with the
/// luminance of `content` as the guide: per window, the least-squares
/// `a * guide + b`, averaged over the windows covering each pixel.
fn guided_filter(content: &Image, style: &Image, radius: usize, eps: f32) -> Vec<f32> {
    let (w, h) = (style.width, style.height);
    let guide: Vec<f32> = content.rgb.chunks_exact(3).map(|p| (p[0] + p[1] + p[2]) / 3.0).collect();
    let mean = |x: &[f32]| box_filter(x, w, h, radius);
    let product = |a: &[f32], b: &[f32]| -> Vec<f32> { a.iter().zip(b).map(|(x, y)| x * y).collect() };
    let mean_g = mean(&guide);
    let var_g: Vec<f32> = mean(&product(&guide, &guide)).iter().zip(&mean_g).map(|(m2, m)| m2 - m * m).collect();
    let mut out = vec![0.0f32; style.rgb.len()];
    for c in 0..3 {
        let channel: Vec<f32> = style.rgb.iter().skip(c).step_by(3).copied().collect();
        let mean_s = mean(&channel);
        let mean_gs = mean(&product(&guide, &channel));
        let a: Vec<f32> = (0..w * h).map(|i| (mean_gs[i] - mean_g[i] * mean_s[i]) / (var_g[i] + eps)).collect();
        let b: Vec<f32> = (0..w * h).map(|i| mean_s[i] - a[i] * mean_g[i]).collect();
        let (a, b) = (mean(&a), mean(&b));
        (0..w * h).for_each(|i| out[i * 3 + c] = a[i] * guide[i] + b[i]);
    }
    out
}

/// The mean over the `(2 radius + 1)`-pixel square about each pixel of a
/// single-channel image (edges mirrored), by running sums.
fn box_filter(x: &[f32], w: usize, h: usize, radius: usize) -> Vec<f32> {
    let pass = |src: &[f32], len: usize, lines: usize, at: &dyn Fn(usize, usize) -> usize| -> Vec<f32> {
        let mut out = vec![0.0f32; src.len()];
        let n = (2 * radius + 1) as f32;
        for line in 0..lines {
            let value = |i: isize| src[at(line, mirror(i, len))];
            let mut sum: f32 = (-(radius as isize)..=radius as isize).map(value).sum();
            for i in 0..len {
                out[at(line, i)] = sum / n;
                sum += value(i as isize + radius as isize + 1) - value(i as isize - radius as isize);
            }
        }
        out
    };
    let rows = pass(x, w, h, &|y, x| y * w + x);
    pass(&rows, h, w, &|x, y| y * w + x)
}

/// The texture magnified `scale` times about the centre of each of a grid
/// of tiles `tile` pixels wide, the tiles overlapping by half and blended
/// with cos² weights; the blend is divided by the root of the squared
/// weights' sum, so that two unrelated textures averaged keep their
/// contrast.
fn magnified_in_tiles(texture: &[f32], w: usize, h: usize, scale: f32, tile: f32) -> Vec<f32> {
    let half = tile / 2.0;
    let weight = |d: f32| if d.abs() < half { (std::f32::consts::PI * d / tile).cos().powi(2) } else { 0.0 };
    let anchors = |n: usize| (0..).map(move |k| k as f32 * half).take_while(move |a| *a < n as f32 + half);
    let mut out = vec![0.0f32; texture.len()];
    for y in 0..h {
        for x in 0..w {
            let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
            let (mut acc, mut squares) = ([0.0f32; 3], 0.0f32);
            for ay in anchors(h).filter(|a| (py - a).abs() < half) {
                for ax in anchors(w).filter(|a| (px - a).abs() < half) {
                    let wt = weight(py - ay) * weight(px - ax);
                    let sx = ax + (px - ax) / scale - 0.5;
                    let sy = ay + (py - ay) / scale - 0.5;
                    let v = sample_mirrored(texture, w, h, sx, sy);
                    (0..3).for_each(|c| acc[c] += wt * v[c]);
                    squares += wt * wt;
                }
            }
            let norm = squares.sqrt().max(1e-6);
            (0..3).for_each(|c| out[(y * w + x) * 3 + c] = acc[c] / norm);
        }
    }
    out
}

/// Reflects a coordinate into `0..n` (mirror tiling: the texture carried
/// from beyond the image's edge is its mirror image, without seams).
fn mirror(i: isize, n: usize) -> usize {
    let period = 2 * n as isize;
    let m = i.rem_euclid(period);
    if m < n as isize { m as usize } else { (period - 1 - m) as usize }
}

/// Bilinear sample of an interleaved RGB buffer at pixel coordinates
/// (centres at integers), mirrored beyond the edges.
fn sample_mirrored(rgb: &[f32], w: usize, h: usize, x: f32, y: f32) -> [f32; 3] {
    let (x0, y0) = (x.floor(), y.floor());
    let (tx, ty) = (x - x0, y - y0);
    let mut out = [0.0f32; 3];
    for (dy, wy) in [(0, 1.0 - ty), (1, ty)] {
        for (dx, wx) in [(0, 1.0 - tx), (1, tx)] {
            let px = mirror(x0 as isize + dx, w);
            let py = mirror(y0 as isize + dy, h);
            let p = (py * w + px) * 3;
            (0..3).for_each(|c| out[c] += wx * wy * rgb[p + c]);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A content image of two flat colours and a painting that recolours
    /// them and lays stripes of period `period` over them.
    fn striped(w: usize, h: usize, period: f32) -> (Image, Image) {
        let mut content = Vec::new();
        let mut style = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let c = if x < w / 2 { [0.15, 0.2, 0.1] } else { [0.8, 0.9, 0.85] };
                let stripe = 0.08 * (std::f32::consts::TAU * (x + y) as f32 / period).sin();
                content.extend(c);
                style.extend(c.map(|v| (1.0 - v + stripe).clamp(0.0, 1.0)));
            }
        }
        (Image::new(w, h, content), Image::new(w, h, style))
    }

    /// The stripes' period along a row, within the left half (one colour):
    /// the lag of the first peak of the autocorrelation of the mean of R, G
    /// and B.
    fn stripe_period(img: &Image, row: usize) -> usize {
        let w = img.width / 2;
        let luma: Vec<f32> =
            (0..w).map(|x| img.rgb[(row * img.width + x) * 3..][..3].iter().sum::<f32>() / 3.0).collect();
        let mean = luma.iter().sum::<f32>() / w as f32;
        let ac = |lag: usize| -> f32 { (0..w - lag).map(|x| (luma[x] - mean) * (luma[x + lag] - mean)).sum() };
        (3..w / 2).find(|&lag| ac(lag) > ac(lag - 1) && ac(lag) >= ac(lag + 1) && ac(lag) > 0.0).unwrap()
    }

    /// Stripes of period 8 come out of period 16 at scale 2 and of period
    /// 24 at scale 3; the colours stay, and scale 1 gives the painting back.
    #[test]
    fn strokes_come_out_scaled_and_the_colours_stay() {
        let (content, style) = striped(128, 128, 8.0);
        let row = 40;
        assert_eq!(stripe_period(&style, row), 8);
        for (scale, want) in [(2.0, 16), (3.0, 24)] {
            let out = rescale_strokes(&content, &style, scale, None, [1.0; 3]);
            let got = stripe_period(&out, row);
            assert!(got.abs_diff(want) <= 1, "scale {scale}: period {got}, want {want}");
            // The mean colour of each half is still the painting's.
            for (x0, x1) in [(0, 64), (64, 128)] {
                let mean = |img: &Image| -> f32 {
                    let cols = (x0..x1).map(|x| (0..128).map(|y| img.rgb[(y * 128 + x) * 3]).sum::<f32>());
                    cols.sum::<f32>() / (128 * (x1 - x0)) as f32
                };
                assert!((mean(&out) - mean(&style)).abs() < 0.03, "scale {scale}: half {x0}..{x1}");
            }
        }
        assert_eq!(rescale_strokes(&content, &style, 1.0, None, [1.0; 3]), style);
    }

    /// A local edit's rescaled painting differs from the painting only
    /// inside the region.
    #[test]
    fn outside_the_region_the_painting_stays() {
        let (content, style) = striped(64, 64, 6.0);
        let inside: Vec<bool> = (0..64 * 64).map(|i| (i % 64) < 32).collect();
        let region = PixelRegion::new(64, 64, inside.clone());
        let out = rescale_strokes(&content, &style, 2.0, Some(&region), [1.0; 3]);
        for (i, _) in inside.iter().enumerate().filter(|(_, inside)| !**inside) {
            assert_eq!(out.rgb[i * 3..][..3], style.rgb[i * 3..][..3], "pixel {i} outside the region changed");
        }
        assert!(out.rgb != style.rgb, "nothing inside the region changed");
    }
}
