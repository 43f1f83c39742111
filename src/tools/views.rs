//! `refnpr views`: a contact sheet of a run's views, each labelled with the
//! name `refnpr reference --view` takes (`train:N`, `test:N`, `path:N`), so
//! that the reference view is chosen by looking, not guessed.

use anyhow::{Result, ensure};

use crate::field::checkpoint::Checkpoint;
use crate::reference::case::DEFAULT_PATH_FRAMES;
use crate::scene::camera::Camera;
use crate::scene::data::{Dataset, View};
use crate::util::image::Image;
use crate::util::label;
use crate::util::progress::{Event, Phase, Progress};

/// How the sheet is laid out.
#[derive(Debug, Clone, Copy)]
pub struct SheetOptions {
    /// The long side of each thumbnail, in pixels.
    pub thumb: usize,
    /// Thumbnails per row.
    pub columns: usize,
    /// Render every N-th frame of the standard render path (0: none).
    pub path_every: usize,
}

impl Default for SheetOptions {
    fn default() -> Self {
        Self { thumb: 128, columns: 8, path_every: 4 }
    }
}

/// One labelled picture of the sheet.
struct Tile {
    label: String,
    image: Image,
}

const LABEL_SCALE: usize = 2;
const GAP: usize = 4;
const BACKGROUND: [f32; 3] = [0.13; 3];
const INK: [f32; 3] = [1.0; 3];

/// The sheet: the training photos, the test photos, then renders of the
/// standard render path (`path:N`) from the run's field.
pub fn contact_sheet(
    ck: &Checkpoint,
    dataset: &Dataset,
    opts: &SheetOptions,
    progress: &dyn Progress,
) -> Result<Image> {
    ensure!(opts.thumb >= 16 && opts.thumb <= 1024, "--thumb {} is outside 16..=1024 pixels", opts.thumb);
    ensure!(opts.columns >= 1, "--columns must be at least 1");
    let mut tiles: Vec<Tile> = Vec::new();
    tiles.extend(photo_tiles(&dataset.train, "train", opts.thumb));
    tiles.extend(photo_tiles(&dataset.test, "test", opts.thumb));
    if opts.path_every > 0 {
        let path = dataset.render_path(DEFAULT_PATH_FRAMES);
        let picked: Vec<(usize, Camera)> = path.into_iter().enumerate().step_by(opts.path_every).collect();
        let renderer = ck.renderer();
        progress.event(Event::Start { phase: Phase::Render, done: 0, total: picked.len() });
        for (k, (i, cam)) in picked.iter().enumerate() {
            let (w, h) = thumb_size(cam.intrinsics.width as usize, cam.intrinsics.height as usize, opts.thumb);
            let small = Camera::new(cam.intrinsics.resized(w as u32, h as u32), cam.c2w);
            tiles.push(Tile { label: format!("path:{i}"), image: renderer.view(&small).image });
            let message = format!("path:{i}");
            progress.event(Event::Step { phase: Phase::Render, done: k + 1, total: picked.len(), message });
        }
    }
    ensure!(!tiles.is_empty(), "the run's dataset has no views to show");
    lay_out(&tiles, opts)
}

fn photo_tiles(views: &[View], kind: &str, thumb: usize) -> Vec<Tile> {
    views
        .iter()
        .enumerate()
        .map(|(i, v)| {
            let (w, h) = (v.camera.intrinsics.width as usize, v.camera.intrinsics.height as usize);
            let (tw, th) = thumb_size(w, h, thumb);
            Tile { label: format!("{kind}:{i}"), image: v.camera.image_of(v.rgb.clone()).resized(tw, th) }
        })
        .collect()
}

/// A size with the long side `thumb` and the aspect of `w` x `h`.
fn thumb_size(w: usize, h: usize, thumb: usize) -> (usize, usize) {
    let s = thumb as f64 / w.max(h).max(1) as f64;
    (((w as f64 * s).round() as usize).max(1), ((h as f64 * s).round() as usize).max(1))
}

/// Tiles in rows of `columns`, each with its label on a band below it.
fn lay_out(tiles: &[Tile], opts: &SheetOptions) -> Result<Image> {
    let cell_w = opts.thumb + GAP;
    let (_, text_h) = label::text_size("0", LABEL_SCALE);
    let cell_h = opts.thumb + text_h + 3 * GAP;
    let rows = tiles.len().div_ceil(opts.columns);
    let (width, height) = (opts.columns * cell_w + GAP, rows * cell_h + GAP);
    let mut sheet = Image::new(width, height, BACKGROUND.repeat(width * height));
    for (k, tile) in tiles.iter().enumerate() {
        let (x0, y0) = (GAP + (k % opts.columns) * cell_w, GAP + (k / opts.columns) * cell_h);
        let img = &tile.image;
        for y in 0..img.height {
            let dst = ((y0 + y) * width + x0) * 3;
            sheet.rgb[dst..dst + img.width * 3].copy_from_slice(&img.rgb[y * img.width * 3..(y + 1) * img.width * 3]);
        }
        label::draw_text(&mut sheet, &tile.label, x0, y0 + opts.thumb + GAP, LABEL_SCALE, INK)?;
    }
    Ok(sheet)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_go_in_rows_with_their_labels_below() {
        let red = Image::new(4, 2, [1.0, 0.0, 0.0].repeat(8));
        let tiles: Vec<Tile> = (0..3).map(|i| Tile { label: format!("train:{i}"), image: red.clone() }).collect();
        let opts = SheetOptions { thumb: 16, columns: 2, path_every: 0 };
        let sheet = lay_out(&tiles, &opts).unwrap();
        let cell_h = 16 + 14 + 3 * GAP;
        assert_eq!((sheet.width, sheet.height), (2 * (16 + GAP) + GAP, 2 * cell_h + GAP));
        let px = |x: usize, y: usize| &sheet.rgb[(y * sheet.width + x) * 3..(y * sheet.width + x) * 3 + 3];
        // The third tile starts the second row.
        assert_eq!(px(GAP, GAP + cell_h), &[1.0, 0.0, 0.0]);
        assert_eq!(px(GAP + 16 + GAP, GAP + cell_h), &BACKGROUND);
        // Some label ink lies below each tile of the first row.
        for x0 in [GAP, GAP + 16 + GAP] {
            let band = (GAP + 16 + GAP..GAP + 16 + GAP + 14).flat_map(|y| (x0..x0 + 16).map(move |x| (x, y)));
            assert!(band.into_iter().any(|(x, y)| px(x, y) == INK), "no label under the tile at x={x0}");
        }
        assert_eq!(thumb_size(504, 378, 128), (128, 96));
    }
}
