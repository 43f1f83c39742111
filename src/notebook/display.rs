//! What a notebook cell shows. evcxr (the Rust Jupyter kernel) calls a
//! value's inherent `evcxr_display` method when the value ends a cell; the
//! method prints a block `EVCXR_BEGIN_CONTENT <mime>` ... `EVCXR_END_CONTENT`
//! that the kernel turns into a rich output. Pictures travel as base64 PNG,
//! plots as SVG (text drawn by the viewer: no font files), tables as HTML.

use std::fmt::Write as _;

use anyhow::{Context, Result, ensure};
use base64::Engine;
use base64::engine::general_purpose::STANDARD as BASE64;
use image::ImageEncoder;
use image::codecs::png::PngEncoder;
use plotters::prelude::*;

use crate::util::image::Image;

/// The block evcxr turns into an output of `mime` type.
pub fn content_block(mime: &str, body: &str) -> String {
    format!("EVCXR_BEGIN_CONTENT {mime}\n{body}\nEVCXR_END_CONTENT\n")
}

#[allow(clippy::print_stdout)] // evcxr reads displays from stdout
fn emit(text: &str) {
    print!("{text}");
}

/// The image as PNG bytes.
pub fn png_bytes(image: &Image) -> Vec<u8> {
    let mut bytes = Vec::new();
    PngEncoder::new(&mut bytes)
        .write_image(image.to_rgb8().as_raw(), image.width as u32, image.height as u32, image::ExtendedColorType::Rgb8)
        .expect("encoding a PNG in memory cannot fail");
    bytes
}

impl Image {
    /// Shows the image in a notebook cell (PNG).
    pub fn evcxr_display(&self) {
        emit(&content_block("image/png", &BASE64.encode(png_bytes(self))));
    }

    /// The image scaled by a whole factor (nearest neighbour), so a small
    /// render is not a thumbnail on screen.
    pub fn enlarged(&self, factor: usize) -> Image {
        let factor = factor.max(1);
        let (w, h) = (self.width * factor, self.height * factor);
        let mut rgb = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                let i = ((y / factor) * self.width + x / factor) * 3;
                rgb.extend_from_slice(&self.rgb[i..i + 3]);
            }
        }
        Image::new(w, h, rgb)
    }
}

/// Images side by side, captions on a line above them.
#[derive(Debug, Clone)]
pub struct Gallery {
    pub items: Vec<(String, Image)>,
    /// Images per row.
    pub columns: usize,
}

/// Gap between the images of a gallery, in pixels (white).
const GAP: usize = 4;

impl Gallery {
    pub fn new(items: Vec<(String, Image)>) -> Self {
        let columns = items.len().clamp(1, 6);
        Self { items, columns }
    }

    pub fn with_columns(mut self, columns: usize) -> Self {
        self.columns = columns.max(1);
        self
    }

    /// One picture: the images on a white sheet, row by row, each row as
    /// tall as its tallest image.
    pub fn sheet(&self) -> Image {
        let rows: Vec<&[(String, Image)]> = self.items.chunks(self.columns).collect();
        let row_height = |row: &[(String, Image)]| row.iter().map(|(_, i)| i.height).max().unwrap_or(0);
        let row_width = |row: &[(String, Image)]| row.iter().map(|(_, i)| i.width + GAP).sum::<usize>();
        let width = rows.iter().map(|r| row_width(r)).max().unwrap_or(GAP).saturating_sub(GAP).max(1);
        let height = (rows.iter().map(|r| row_height(r) + GAP).sum::<usize>()).saturating_sub(GAP).max(1);
        let mut rgb = vec![1.0; width * height * 3];
        let mut top = 0;
        for row in &rows {
            let mut left = 0;
            for (_, img) in row.iter() {
                for y in 0..img.height {
                    let dst = ((top + y) * width + left) * 3;
                    rgb[dst..dst + img.width * 3].copy_from_slice(&img.rgb[y * img.width * 3..(y + 1) * img.width * 3]);
                }
                left += img.width + GAP;
            }
            top += row_height(row) + GAP;
        }
        Image::new(width, height, rgb)
    }

    /// The captions, row by row, left to right.
    pub fn captions(&self) -> String {
        let rows: Vec<String> = self
            .items
            .chunks(self.columns)
            .map(|row| row.iter().map(|(c, _)| c.as_str()).collect::<Vec<_>>().join(" | "))
            .collect();
        rows.join("\n")
    }

    /// Shows the captions, then the sheet.
    pub fn evcxr_display(&self) {
        emit(&format!("{}\n", self.captions()));
        self.sheet().evcxr_display();
    }
}

/// Pixels differing by more than this are marked in [`difference`].
pub const DIFFERENCE_MARK: f32 = 1.0 / 255.0;

/// How two renders of the same view differ: the largest and mean absolute
/// channel difference, and a picture of `|a - b|` amplified `gain` times.
#[derive(Debug, Clone)]
pub struct Difference {
    pub max_abs: f32,
    pub mean_abs: f32,
    /// Pixels whose largest channel difference exceeds one 8-bit level.
    pub pixels_over_one_level: usize,
    pub picture: Image,
    pub gain: f32,
}

/// `|a - b|` of two images of one size.
pub fn difference(a: &Image, b: &Image, gain: f32) -> Result<Difference> {
    ensure!(
        (a.width, a.height) == (b.width, b.height),
        "the images differ in size: {}x{} and {}x{}",
        a.width,
        a.height,
        b.width,
        b.height
    );
    let diffs: Vec<f32> = a.rgb.iter().zip(&b.rgb).map(|(x, y)| (x - y).abs()).collect();
    let max_abs = diffs.iter().copied().fold(0.0, f32::max);
    let mean_abs = diffs.iter().sum::<f32>() / diffs.len().max(1) as f32;
    let pixels_over_one_level = diffs.chunks(3).filter(|p| p.iter().any(|&d| d > DIFFERENCE_MARK)).count();
    let picture = Image::new(a.width, a.height, diffs.iter().map(|d| (d * gain).min(1.0)).collect());
    Ok(Difference { max_abs, mean_abs, pixels_over_one_level, picture, gain })
}

impl Difference {
    pub fn summary(&self) -> String {
        format!(
            "largest channel difference {:.2e}, mean {:.2e}; {} pixels differ by more than one 8-bit level (picture: |a - b| x {})",
            self.max_abs, self.mean_abs, self.pixels_over_one_level, self.gain
        )
    }

    pub fn evcxr_display(&self) {
        emit(&format!("{}\n", self.summary()));
        self.picture.evcxr_display();
    }
}

/// A line plot, kept as SVG text.
#[derive(Debug, Clone)]
pub struct Plot {
    pub svg: String,
}

/// One named line of a plot.
#[derive(Debug, Clone)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f32, f32)>,
}

impl Series {
    pub fn new(name: impl Into<String>, points: Vec<(f32, f32)>) -> Self {
        Self { name: name.into(), points }
    }
}

/// Distinct line colours (Tableau 10's first six).
const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

impl Plot {
    /// Lines on shared axes; `log_y` plots the y values on a log scale
    /// (non-positive values are left out).
    pub fn lines(title: &str, x_label: &str, y_label: &str, series: &[Series], log_y: bool) -> Result<Plot> {
        let keep = |y: f32| y.is_finite() && (!log_y || y > 0.0);
        let points = || series.iter().flat_map(|s| s.points.iter().filter(|p| p.0.is_finite() && keep(p.1)));
        ensure!(points().next().is_some(), "nothing to plot for {title:?}: every series is empty");
        let (mut x0, mut x1, mut y0, mut y1) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
        for &(x, y) in points() {
            (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
        }
        if x1 <= x0 {
            x1 = x0 + 1.0;
        }
        if y1 <= y0 {
            y1 = y0 * 1.5 + 1e-6;
        }
        let mut svg = String::new();
        {
            let root = SVGBackend::with_string(&mut svg, (640, 360)).into_drawing_area();
            root.fill(&WHITE).context("drawing the plot")?;
            let mut chart = ChartBuilder::on(&root);
            chart.caption(title, ("sans-serif", 18)).margin(10).x_label_area_size(36).y_label_area_size(64);
            if log_y {
                let mut c = chart.build_cartesian_2d(x0..x1, (y0..y1).log_scale()).context("plot axes")?;
                c.configure_mesh().x_desc(x_label).y_desc(y_label).draw().context("plot grid")?;
                draw_series(&mut c, series, keep)?;
            } else {
                let mut c = chart.build_cartesian_2d(x0..x1, y0..y1).context("plot axes")?;
                c.configure_mesh().x_desc(x_label).y_desc(y_label).draw().context("plot grid")?;
                draw_series(&mut c, series, keep)?;
            }
            root.present().context("finishing the plot")?;
        }
        Ok(Plot { svg })
    }

    pub fn evcxr_display(&self) {
        emit(&content_block("image/svg+xml", &self.svg));
    }
}

fn draw_series<'a, C>(
    chart: &mut ChartContext<'a, SVGBackend<'a>, C>,
    series: &[Series],
    keep: impl Fn(f32) -> bool,
) -> Result<()>
where
    C: CoordTranslate<From = (f32, f32)>,
{
    for (k, s) in series.iter().enumerate() {
        let colour = PALETTE[k % PALETTE.len()];
        let pts: Vec<(f32, f32)> = s.points.iter().copied().filter(|p| p.0.is_finite() && keep(p.1)).collect();
        chart
            .draw_series(LineSeries::new(pts, colour.stroke_width(2)))
            .context("drawing a line")?
            .label(s.name.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK.mix(0.3))
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .context("drawing the legend")?;
    Ok(())
}

/// A table of figures (HTML in a notebook, aligned text elsewhere).
#[derive(Debug, Clone, Default)]
pub struct Table {
    pub headers: Vec<String>,
    pub rows: Vec<Vec<String>>,
}

impl Table {
    pub fn new(headers: &[&str]) -> Self {
        Self { headers: headers.iter().map(|s| s.to_string()).collect(), rows: Vec::new() }
    }

    pub fn row(mut self, cells: Vec<String>) -> Self {
        self.rows.push(cells);
        self
    }

    pub fn html(&self) -> String {
        let esc = |s: &str| s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;");
        let mut h = String::from("<table>\n<tr>");
        for c in &self.headers {
            let _ = write!(h, "<th>{}</th>", esc(c));
        }
        h.push_str("</tr>\n");
        for r in &self.rows {
            h.push_str("<tr>");
            for c in r {
                let _ = write!(h, "<td>{}</td>", esc(c));
            }
            h.push_str("</tr>\n");
        }
        h.push_str("</table>");
        h
    }

    pub fn evcxr_display(&self) {
        emit(&content_block("text/html", &self.html()));
    }
}

impl std::fmt::Display for Table {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let columns = self.headers.len().max(self.rows.iter().map(Vec::len).max().unwrap_or(0));
        let width = |c: usize| {
            std::iter::once(&self.headers)
                .chain(&self.rows)
                .filter_map(|r| r.get(c))
                .map(|s| s.chars().count())
                .max()
                .unwrap_or(0)
        };
        let widths: Vec<usize> = (0..columns).map(width).collect();
        for r in std::iter::once(&self.headers).chain(&self.rows) {
            let cells: Vec<String> =
                widths.iter().enumerate().map(|(c, w)| format!("{:<w$}", r.get(c).map_or("", |s| s))).collect();
            writeln!(f, "{}", cells.join("  ").trim_end())?;
        }
        Ok(())
    }
}
