//! Short labels drawn into images (a contact sheet's `train:12`), from a
//! built-in 5x7 pixel font: no font file, no text-rendering crate for the
//! twenty characters the labels use.

use anyhow::{Result, bail};

use crate::util::image::Image;

/// Glyph width and height in font pixels.
const GLYPH_W: usize = 5;
const GLYPH_H: usize = 7;

/// The rows of a character's glyph, top first, bit 4 = leftmost pixel.
fn glyph(c: char) -> Option<[u8; GLYPH_H]> {
    Some(match c {
        '0' => [0x0e, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0e],
        '1' => [0x04, 0x0c, 0x04, 0x04, 0x04, 0x04, 0x0e],
        '2' => [0x0e, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1f],
        '3' => [0x1e, 0x01, 0x01, 0x0e, 0x01, 0x01, 0x1e],
        '4' => [0x02, 0x06, 0x0a, 0x12, 0x1f, 0x02, 0x02],
        '5' => [0x1f, 0x10, 0x1e, 0x01, 0x01, 0x11, 0x0e],
        '6' => [0x06, 0x08, 0x10, 0x1e, 0x11, 0x11, 0x0e],
        '7' => [0x1f, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0e, 0x11, 0x11, 0x0e, 0x11, 0x11, 0x0e],
        '9' => [0x0e, 0x11, 0x11, 0x0f, 0x01, 0x02, 0x0c],
        ':' => [0x00, 0x0c, 0x0c, 0x00, 0x0c, 0x0c, 0x00],
        ' ' => [0x00; GLYPH_H],
        'a' => [0x00, 0x00, 0x0e, 0x01, 0x0f, 0x11, 0x0f],
        'e' => [0x00, 0x00, 0x0e, 0x11, 0x1f, 0x10, 0x0e],
        'h' => [0x10, 0x10, 0x16, 0x19, 0x11, 0x11, 0x11],
        'i' => [0x04, 0x00, 0x0c, 0x04, 0x04, 0x04, 0x0e],
        'n' => [0x00, 0x00, 0x16, 0x19, 0x11, 0x11, 0x11],
        'p' => [0x00, 0x1e, 0x11, 0x11, 0x1e, 0x10, 0x10],
        'r' => [0x00, 0x00, 0x16, 0x19, 0x10, 0x10, 0x10],
        's' => [0x00, 0x00, 0x0f, 0x10, 0x0e, 0x01, 0x1e],
        't' => [0x08, 0x08, 0x1c, 0x08, 0x08, 0x09, 0x06],
        _ => return None,
    })
}

/// The size in pixels of `text` drawn at `scale` (one font pixel = scale x
/// scale image pixels; one font pixel between characters).
pub fn text_size(text: &str, scale: usize) -> (usize, usize) {
    let n = text.chars().count();
    ((n * (GLYPH_W + 1)).saturating_sub(1) * scale, GLYPH_H * scale)
}

/// Draws `text` into `img` with its top-left corner at (x, y), clipped at
/// the image's edges. Refuses characters the font does not have.
pub fn draw_text(img: &mut Image, text: &str, x: usize, y: usize, scale: usize, colour: [f32; 3]) -> Result<()> {
    for (k, c) in text.chars().enumerate() {
        let Some(rows) = glyph(c) else {
            bail!("the label font has no {c:?} (labels use a-z of train/test/path, digits, ':')")
        };
        let left = x + k * (GLYPH_W + 1) * scale;
        for (gy, bits) in rows.iter().enumerate() {
            for gx in 0..GLYPH_W {
                if bits & (0x10 >> gx) == 0 {
                    continue;
                }
                for (py, px) in (0..scale * scale).map(|i| (y + gy * scale + i / scale, left + gx * scale + i % scale))
                {
                    if px < img.width && py < img.height {
                        let at = (py * img.width + px) * 3;
                        img.rgb[at..at + 3].copy_from_slice(&colour);
                    }
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_label_lights_exactly_its_glyphs_pixels() {
        let mut img = Image::new(20, 10, vec![0.0; 20 * 10 * 3]);
        draw_text(&mut img, "1:", 1, 1, 1, [1.0; 3]).unwrap();
        let lit = |x: usize, y: usize| img.rgb[(y * 20 + x) * 3] == 1.0;
        // '1': its top row is one pixel at glyph column 2, its bottom row three.
        assert!(lit(3, 1) && !lit(2, 1) && !lit(4, 1));
        assert!(lit(2, 7) && lit(3, 7) && lit(4, 7));
        // ':' starts six pixels later; its dots are at glyph columns 1-2.
        assert!(lit(8, 2) && lit(9, 2) && !lit(7, 2));
        let on = img.rgb.chunks(3).filter(|p| p[0] == 1.0).count();
        assert_eq!(on, 10 + 8, "the '1' has 10 pixels, the ':' 8");
        assert_eq!(text_size("1:", 2), (22, 14));
    }

    #[test]
    fn text_past_the_edge_is_clipped_and_unknown_characters_refused() {
        let mut img = Image::new(4, 4, vec![0.0; 4 * 4 * 3]);
        draw_text(&mut img, "train:99", 2, 2, 3, [1.0; 3]).unwrap();
        assert!(draw_text(&mut img, "X", 0, 0, 1, [1.0; 3]).is_err());
    }
}
