//! Lens distortion (OpenCV's radial-tangential model, which COLMAP's
//! SIMPLE_RADIAL, RADIAL and OPENCV cameras and nerfstudio's `k1 k2 k3 p1
//! p2` are cases of) removed once, when a dataset is loaded: every later
//! stage sees a pinhole camera.

/// A camera's pinhole part and its distortion, in pixels of its image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lens {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub k1: f64,
    pub k2: f64,
    pub k3: f64,
    pub p1: f64,
    pub p2: f64,
}

impl Lens {
    pub fn pinhole(fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Self { fx, fy, cx, cy, k1: 0.0, k2: 0.0, k3: 0.0, p1: 0.0, p2: 0.0 }
    }

    pub fn is_distorted(&self) -> bool {
        [self.k1, self.k2, self.k3, self.p1, self.p2].iter().any(|&k| k != 0.0)
    }

    /// The same lens for an image scaled by (sx, sy).
    pub fn scaled(&self, sx: f64, sy: f64) -> Self {
        Self { fx: self.fx * sx, fy: self.fy * sy, cx: self.cx * sx, cy: self.cy * sy, ..*self }
    }

    /// Where the distorted image holds the point at normalised pinhole coordinates (u, v).
    fn distort(&self, u: f64, v: f64) -> (f64, f64) {
        let r2 = u * u + v * v;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let du = u * radial + 2.0 * self.p1 * u * v + self.p2 * (r2 + 2.0 * u * u);
        let dv = v * radial + self.p1 * (r2 + 2.0 * v * v) + 2.0 * self.p2 * u * v;
        (du, dv)
    }
}

/// The pinhole image (same size and intrinsics as the lens's pinhole part)
/// of an interleaved RGB image taken through `lens`: each output pixel
/// centre is distorted into the input and sampled bilinearly (clamped at
/// the border, where a barrel lens leaves no data).
pub fn undistort(rgb: &[f32], width: u32, height: u32, lens: &Lens) -> Vec<f32> {
    let (w, h) = (width as usize, height as usize);
    let mut out = vec![0.0f32; w * h * 3];
    let at = |x: usize, y: usize, c: usize| rgb[(y * w + x) * 3 + c];
    for y in 0..h {
        for x in 0..w {
            // Pixel centres at +0.5, as COLMAP and `Camera::ray` place them.
            let u = (x as f64 + 0.5 - lens.cx) / lens.fx;
            let v = (y as f64 + 0.5 - lens.cy) / lens.fy;
            let (du, dv) = lens.distort(u, v);
            let sx = (du * lens.fx + lens.cx - 0.5).clamp(0.0, (w - 1) as f64);
            let sy = (dv * lens.fy + lens.cy - 0.5).clamp(0.0, (h - 1) as f64);
            let (x0, y0) = (sx.floor() as usize, sy.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
            let (ax, ay) = ((sx - x0 as f64) as f32, (sy - y0 as f64) as f32);
            for c in 0..3 {
                let top = at(x0, y0, c) * (1.0 - ax) + at(x1, y0, c) * ax;
                let bottom = at(x0, y1, c) * (1.0 - ax) + at(x1, y1, c) * ax;
                out[(y * w + x) * 3 + c] = top * (1.0 - ay) + bottom * ay;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_straight_line_bent_by_the_lens_comes_out_straight() {
        // Draw, through a barrel lens, the vertical line x = 30 of the pinhole
        // image; undistorting must put it back in column 30 on every row.
        let (w, h) = (64u32, 48u32);
        let lens = Lens { k1: -0.2, k2: 0.05, p1: 0.001, ..Lens::pinhole(50.0, 50.0, 32.0, 24.0) };
        let mut rgb = vec![0.0f32; (w * h * 3) as usize];
        for y in 0..h as usize {
            let v = (y as f64 + 0.5 - lens.cy) / lens.fy;
            let u = (30.5 - lens.cx) / lens.fx;
            let (du, _) = lens.distort(u, v);
            let xd = (du * lens.fx + lens.cx - 0.5).round() as usize;
            rgb[(y * w as usize + xd) * 3] = 1.0;
        }
        let out = undistort(&rgb, w, h, &lens);
        for y in 4..h as usize - 4 {
            let row: Vec<f32> = (0..w as usize).map(|x| out[(y * w as usize + x) * 3]).collect();
            let peak = row.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map(|p| p.0).unwrap();
            assert!((peak as i32 - 30).abs() <= 1, "row {y}: the line is at column {peak}");
        }
        // Without distortion the image is returned as it is.
        let same = undistort(&rgb, w, h, &Lens::pinhole(50.0, 50.0, 32.0, 24.0));
        assert_eq!(same, rgb);
    }
}
