//! VGG16's 2x2, stride 2 max-pool (floor: an odd last row or column is
//! dropped) and its gradient, on host `[N, C, H, W]` slices; `vgg::cpu_ops`
//! makes it a Burn operation. burn-flex's pool with indices and its
//! scatter-add backward were 9 % of VGG16's forward+backward once the
//! convolutions ran on `vgg::conv3x3`.
//!
//! A window's maximum is its first largest value in row-major order; a NaN
//! wins (as the max of anything with NaN), so a diverged input stays
//! visible.

use rayon::prelude::*;

use crate::vgg::conv3x3::Dims;

/// The index within `window` (4 values, row-major) of its maximum.
fn argmax(window: [f32; 4]) -> usize {
    let mut best = 0;
    for (i, &v) in window.iter().enumerate().skip(1) {
        let m = window[best];
        if !m.is_nan() && (v.is_nan() || v > m) {
            best = i;
        }
    }
    best
}

/// The 2x2 window of output `(oy, ox)` in plane `plane` (`w` wide).
fn window(plane: &[f32], w: usize, oy: usize, ox: usize) -> [f32; 4] {
    let (top, bottom) = (2 * oy * w + 2 * ox, (2 * oy + 1) * w + 2 * ox);
    [plane[top], plane[top + 1], plane[bottom], plane[bottom + 1]]
}

/// The pooled `[N, C, H/2, W/2]`.
pub fn forward(x: &[f32], dims: Dims) -> Vec<f32> {
    assert_eq!(x.len(), dims.len(), "input of shape {dims:?}");
    let (h, w, oh, ow) = (dims.h, dims.w, dims.h / 2, dims.w / 2);
    let mut y = vec![0.0f32; dims.n * dims.c * oh * ow];
    if oh * ow == 0 {
        return y;
    }
    y.par_chunks_mut(oh * ow).zip(x.par_chunks(h * w)).for_each(|(out, plane)| {
        for oy in 0..oh {
            for ox in 0..ow {
                let win = window(plane, w, oy, ox);
                out[oy * ow + ox] = win[argmax(win)];
            }
        }
    });
    y
}

/// `x`'s gradient given the output gradient `dy` (`[N, C, H/2, W/2]`): each
/// output's gradient goes to its window's maximum.
pub fn input_grad(x: &[f32], dims: Dims, dy: &[f32]) -> Vec<f32> {
    assert_eq!(x.len(), dims.len(), "input of shape {dims:?}");
    let (h, w, oh, ow) = (dims.h, dims.w, dims.h / 2, dims.w / 2);
    assert_eq!(dy.len(), dims.n * dims.c * oh * ow, "output gradient of the pooled shape");
    let mut dx = vec![0.0f32; x.len()];
    if oh * ow == 0 {
        return dx;
    }
    dx.par_chunks_mut(h * w).zip(x.par_chunks(h * w)).zip(dy.par_chunks(oh * ow)).for_each(|((grad, plane), up)| {
        for oy in 0..oh {
            for ox in 0..ow {
                let i = argmax(window(plane, w, oy, ox));
                grad[(2 * oy + i / 2) * w + 2 * ox + i % 2] = up[oy * ow + ox];
            }
        }
    });
    dx
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pools_floor_odd_sides_and_routes_gradients_to_the_maximum() {
        // One 3x5 plane: the last row and column are dropped.
        let x = [1.0, 5.0, 2.0, 2.0, 9.0, 3.0, 4.0, 8.0, 1.0, 9.0, 7.0, 7.0, 7.0, 7.0, 9.0];
        let dims = Dims { n: 1, c: 1, h: 3, w: 5 };
        assert_eq!(forward(&x, dims), vec![5.0, 8.0]);
        assert_eq!(input_grad(&x, dims, &[10.0, 20.0]), {
            let mut g = vec![0.0; 15];
            g[1] = 10.0;
            g[7] = 20.0;
            g
        });
        // Ties go to the first; NaN wins.
        assert_eq!(argmax([2.0, 2.0, 1.0, 2.0]), 0);
        assert_eq!(argmax([2.0, f32::NAN, 3.0, 1.0]), 1);
        assert!(forward(&[1.0, f32::NAN, 0.0, 0.0], Dims { n: 1, c: 1, h: 2, w: 2 })[0].is_nan());
    }
}
