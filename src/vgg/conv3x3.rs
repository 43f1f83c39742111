//! The 3x3 convolution (stride 1, zero padding 1: every convolution of
//! VGG16) on host memory, with both of its gradients. Plain Rust over
//! row-major `[N, C, H, W]` slices; `vgg::conv_op` makes it a Burn
//! operation.
//!
//! Why it exists (issue 19): burn-flex runs a convolution as im2col + gemm
//! and its backward as the generic transposed / weight convolutions, 4.6x
//! (forward) and 9.6x (forward + backward) slower than onnxruntime's forward
//! on VGG16 at 504x378. This kernel uses Winograd's minimal filtering
//! F(2x2, 3x3) (Lavin & Gray, "Fast Algorithms for Convolutional Neural
//! Networks", 2016): each 2x2 block of outputs of a channel pair costs 16
//! multiplies instead of 36, so the convolution becomes 16 independent
//! matrix products `M[xi] = U[xi] . V[xi]` (U: transformed weights `K x C`,
//! V: transformed input tiles `C x P`) plus cheap linear transforms around
//! them. The products run on the `gemm` crate (the one burn-flex uses).
//!
//! The input gradient is the same convolution of the output gradient with
//! the weights flipped in space and their in/out channels swapped. The
//! weight gradient is 9 matrix products (one per kernel tap) over a
//! zero-padded copy of the input; it is exact (no Winograd), as VGG's
//! weights are frozen here and only the tests need it.
//!
//! Work is split into bands of tile rows per image, run in parallel with
//! rayon; each output value is computed by exactly one band with a fixed
//! order of operations, so results do not depend on the thread count.

use gemm::Parallelism;
use rayon::prelude::*;

/// The shape of a `[N, C, H, W]` tensor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Dims {
    pub n: usize,
    pub c: usize,
    pub h: usize,
    pub w: usize,
}

impl Dims {
    pub fn len(&self) -> usize {
        self.n * self.c * self.h * self.w
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Weights in the Winograd domain: `u[xi][k][c]` for the 16 positions xi of
/// a 4x4 tile, `k` output and `c` input channels.
#[derive(Debug, Clone)]
pub struct WinogradWeights {
    k: usize,
    c: usize,
    u: Vec<f32>,
}

impl WinogradWeights {
    /// From weights `[K, C, 3, 3]` (row-major, cross-correlation as in
    /// `conv2d`): `U = G g G^T` per channel pair.
    pub fn new(weights: &[f32], k: usize, c: usize) -> Self {
        assert_eq!(weights.len(), k * c * 9, "3x3 weights [{k}, {c}, 3, 3]");
        Self::build(k, c, |ko, ci, a, b| weights[((ko * c + ci) * 3 + a) * 3 + b])
    }

    /// The weights of the input gradient: `W'[c][k][a][b] = W[k][c][2-a][2-b]`
    /// for weights `W` `[K, C, 3, 3]`, so `K' = C` and `C' = K`.
    pub fn flipped_transposed(weights: &[f32], k: usize, c: usize) -> Self {
        assert_eq!(weights.len(), k * c * 9, "3x3 weights [{k}, {c}, 3, 3]");
        Self::build(c, k, |ci, ko, a, b| weights[((ko * c + ci) * 3 + (2 - a)) * 3 + (2 - b)])
    }

    fn build(k: usize, c: usize, g_at: impl Fn(usize, usize, usize, usize) -> f32) -> Self {
        let mut u = vec![0.0f32; 16 * k * c];
        for ko in 0..k {
            for ci in 0..c {
                let g = |a: usize, b: usize| g_at(ko, ci, a, b);
                // t = G g (4x3), G = [[1,0,0],[.5,.5,.5],[.5,-.5,.5],[0,0,1]].
                let mut t = [[0.0f32; 3]; 4];
                for b in 0..3 {
                    let (g0, g1, g2) = (g(0, b), g(1, b), g(2, b));
                    t[0][b] = g0;
                    t[1][b] = 0.5 * (g0 + g1 + g2);
                    t[2][b] = 0.5 * (g0 - g1 + g2);
                    t[3][b] = g2;
                }
                // u = t G^T (4x4).
                for (i, row) in t.iter().enumerate() {
                    let v = [row[0], 0.5 * (row[0] + row[1] + row[2]), 0.5 * (row[0] - row[1] + row[2]), row[2]];
                    for (j, value) in v.into_iter().enumerate() {
                        u[((i * 4 + j) * k + ko) * c + ci] = value;
                    }
                }
            }
        }
        Self { k, c, u }
    }

    /// Output channels.
    pub fn out_channels(&self) -> usize {
        self.k
    }

    /// Input channels.
    pub fn in_channels(&self) -> usize {
        self.c
    }
}

/// A pointer shared by the bands of one call, each writing its own
/// elements.
#[derive(Clone, Copy)]
struct SharedOut(*mut f32);
// SAFETY: the bands write disjoint elements (see each use), and the buffer
// outlives the parallel loop that uses the pointer.
unsafe impl Send for SharedOut {}
unsafe impl Sync for SharedOut {}

/// The convolution of `x` (`[N, C, H, W]`) with `weights` (`K x C`), plus
/// `bias` (`K` values) when given: `[N, K, H, W]`.
pub fn forward(x: &[f32], dims: Dims, weights: &WinogradWeights, bias: Option<&[f32]>) -> Vec<f32> {
    assert_eq!(x.len(), dims.len(), "input of shape {dims:?}");
    assert_eq!(dims.c, weights.c, "input channels vs weights");
    let k = weights.k;
    if let Some(b) = bias {
        assert_eq!(b.len(), k, "one bias per output channel");
    }
    let out_dims = Dims { c: k, ..dims };
    let mut y = vec![0.0f32; out_dims.len()];
    if dims.is_empty() || k == 0 {
        return y;
    }
    let (tiles_h, tiles_w) = (dims.h.div_ceil(2), dims.w.div_ceil(2));
    let band_rows = band_rows(tiles_h, tiles_w, dims.c + k);
    let bands: Vec<(usize, usize)> =
        (0..dims.n).flat_map(|n| (0..tiles_h).step_by(band_rows).map(move |t0| (n, t0))).collect();
    let out = SharedOut(y.as_mut_ptr());
    let tiles_max = band_rows * tiles_w;
    bands.into_par_iter().for_each_init(
        || Scratch::new(dims.c, k, tiles_max, dims.w),
        |scratch, (n, t0)| {
            let t1 = (t0 + band_rows).min(tiles_h);
            let image = &x[n * dims.c * dims.h * dims.w..(n + 1) * dims.c * dims.h * dims.w];
            let out = out;
            // SAFETY: the offset is image n's first output value.
            let image_out = SharedOut(unsafe { out.0.add(n * k * dims.h * dims.w) });
            band(image, dims, weights, bias, t0, t1, scratch, image_out);
        },
    );
    y
}

/// `x`'s gradient for the convolution with weights `[K, C, 3, 3]`, given
/// the output gradient `dy` (`[N, K, H, W]`): `[N, C, H, W]`.
pub fn input_grad(dy: &[f32], dims: Dims, flipped: &WinogradWeights) -> Vec<f32> {
    forward(dy, dims, flipped, None)
}

/// The weights' gradient `[K, C, 3, 3]` given the input `x` (`[N, C, H, W]`)
/// and the output gradient `dy` (`[N, K, H, W]`).
pub fn weight_grad(x: &[f32], x_dims: Dims, dy: &[f32], k: usize) -> Vec<f32> {
    let Dims { n, c, h, w } = x_dims;
    assert_eq!(x.len(), x_dims.len(), "input of shape {x_dims:?}");
    assert_eq!(dy.len(), n * k * h * w, "output gradient [{n}, {k}, {h}, {w}]");
    let mut grad = vec![0.0f32; k * c * 9];
    if x_dims.is_empty() || k == 0 {
        return grad;
    }
    // Positions run over rows of width w + 2 (the padded width): the input
    // at tap (a, b) is then the padded input read from offset a (w+2) + b,
    // one uniform stride per matrix, and the output gradient is zero in the
    // two extra columns.
    let (wp, hp) = (w + 2, h + 2);
    let positions = h * wp;
    // Two spare values at the end: tap (2, 2) of the last channel reads
    // past its plane at the two zero columns of the output gradient.
    let mut x_pad = vec![0.0f32; c * hp * wp + 2];
    let mut dy_pad = vec![0.0f32; k * positions];
    let out = SharedOut(grad.as_mut_ptr());
    for image in 0..n {
        for ci in 0..c {
            for row in 0..h {
                let src = &x[((image * c + ci) * h + row) * w..][..w];
                x_pad[(ci * hp + row + 1) * wp + 1..][..w].copy_from_slice(src);
            }
        }
        for ko in 0..k {
            for row in 0..h {
                let src = &dy[((image * k + ko) * h + row) * w..][..w];
                dy_pad[ko * positions + row * wp..][..w].copy_from_slice(src);
            }
        }
        (0..9usize).into_par_iter().for_each(|tap| {
            let (a, b) = (tap / 3, tap % 3);
            let out = out;
            // SAFETY: tap `tap` writes grad[(ko c + ci) 9 + tap] only: the 9
            // taps write disjoint elements; reads stay inside x_pad (see its
            // two spare values) and dy_pad.
            unsafe {
                gemm::gemm(
                    k,
                    c,
                    positions,
                    out.0.add(tap),
                    9,
                    (c * 9) as isize,
                    image > 0,
                    dy_pad.as_ptr(),
                    1,
                    positions as isize,
                    x_pad.as_ptr().add(a * wp + b),
                    (hp * wp) as isize,
                    1,
                    1.0,
                    1.0,
                    false,
                    false,
                    false,
                    Parallelism::None,
                );
            }
        });
    }
    grad
}

/// The bias gradient: `dy` (`[N, K, H, W]`) summed over images and pixels,
/// in a fixed order.
pub fn bias_grad(dy: &[f32], dims: Dims) -> Vec<f32> {
    let plane = dims.h * dims.w;
    (0..dims.c)
        .map(|ko| (0..dims.n).map(|image| dy[(image * dims.c + ko) * plane..][..plane].iter().sum::<f32>()).sum())
        .collect()
}

/// Tile rows per band: enough tiles for the matrix products to run at
/// speed, few enough that a band's transformed input and output (16 (C+K)
/// values per tile) stay near 16 MB, and at least two bands per thread
/// when the image allows, so both cores stay busy.
fn band_rows(tiles_h: usize, tiles_w: usize, channels: usize) -> usize {
    let tiles = (4_194_304 / (16 * channels)).clamp(64, 8192);
    let by_size = tiles.div_ceil(tiles_w).max(1);
    let by_threads = tiles_h.div_ceil(2 * rayon::current_num_threads()).max(1);
    by_size.min(by_threads)
}

/// One thread's buffers: the band's transformed input `V[xi][c][p]`, its
/// products `M[xi][k][p]`, and per-row work arrays.
struct Scratch {
    v: Vec<f32>,
    m: Vec<f32>,
    /// 4 zero-padded input rows split into even and odd padded columns
    /// (`tiles_w + 1` each), then their column transform.
    even: Vec<f32>,
    odd: Vec<f32>,
    t_even: Vec<f32>,
    t_odd: Vec<f32>,
    /// The output transform's 8 partial rows (`tiles_w` each).
    s: Vec<f32>,
}

impl Scratch {
    fn new(c: usize, k: usize, tiles: usize, w: usize) -> Self {
        let n1 = w.div_ceil(2) + 1;
        Self {
            v: vec![0.0; 16 * c * tiles],
            m: vec![0.0; 16 * k * tiles],
            even: vec![0.0; 4 * n1],
            odd: vec![0.0; 4 * n1],
            t_even: vec![0.0; 4 * n1],
            t_odd: vec![0.0; 4 * n1],
            s: vec![0.0; 8 * (n1 - 1)],
        }
    }
}

/// Output tile rows `[t0, t1)` of one image (`x`, written to `y`, the
/// image's output `[K, H, W]`): transform the input tiles, multiply,
/// transform back.
///
/// The transforms run along whole tile rows so that they vectorise: the 4
/// input rows of a tile row are zero-padded (padded column q = input column
/// q - 1) and split into even and odd padded columns, E[t] = P[2t] and
/// O[t] = P[2t+1]; tile tx reads P[2tx .. 2tx+4] = E[tx], O[tx], E[tx+1],
/// O[tx+1].
#[allow(clippy::too_many_arguments)]
fn band(
    x: &[f32],
    dims: Dims,
    weights: &WinogradWeights,
    bias: Option<&[f32]>,
    t0: usize,
    t1: usize,
    scratch: &mut Scratch,
    y: SharedOut,
) {
    let Dims { c, h, w, .. } = dims;
    let k = weights.k;
    let tw = w.div_ceil(2);
    let n1 = tw + 1;
    let tiles = (t1 - t0) * tw;
    let Scratch { v, m, even, odd, t_even, t_odd, s } = scratch;

    // V = B^T d B, B^T = [[1,0,-1,0],[0,1,1,0],[0,-1,1,0],[0,1,0,-1]].
    for ci in 0..c {
        let plane = &x[ci * h * w..(ci + 1) * h * w];
        for ty in t0..t1 {
            for r in 0..4 {
                let (e, o) = (&mut even[r * n1..(r + 1) * n1], &mut odd[r * n1..(r + 1) * n1]);
                e.fill(0.0);
                o.fill(0.0);
                let src_row = (2 * ty + r).wrapping_sub(1);
                if src_row < h {
                    // E[t] = x[2t - 1] (E[0] is padding), O[t] = x[2t].
                    let src = &plane[src_row * w..(src_row + 1) * w];
                    for (t, pair) in src.chunks(2).enumerate() {
                        o[t] = pair[0];
                        if let Some(&next) = pair.get(1) {
                            e[t + 1] = next;
                        }
                    }
                }
            }
            // Columns: T = B^T [row 0; row 1; row 2; row 3].
            for (rows, t) in [(&*even, &mut *t_even), (&*odd, &mut *t_odd)] {
                let (d0, rest) = rows.split_at(n1);
                let (d1, rest) = rest.split_at(n1);
                let (d2, d3) = rest.split_at(n1);
                let (t0_, rest) = t.split_at_mut(n1);
                let (t1_, rest) = rest.split_at_mut(n1);
                let (t2_, t3_) = rest.split_at_mut(n1);
                for i in 0..n1 {
                    t0_[i] = d0[i] - d2[i];
                    t1_[i] = d1[i] + d2[i];
                    t2_[i] = d2[i] - d1[i];
                    t3_[i] = d1[i] - d3[i];
                }
            }
            // Rows: V[4 i + j] from row i of T.
            let at = ci * tiles + (ty - t0) * tw;
            for i in 0..4 {
                let (e, o) = (&t_even[i * n1..(i + 1) * n1], &t_odd[i * n1..(i + 1) * n1]);
                let plane_of = |j: usize| (4 * i + j) * c * tiles + at;
                let out = &mut v[plane_of(0)..][..tw];
                for ((d, a), b) in out.iter_mut().zip(&e[..tw]).zip(&e[1..]) {
                    *d = a - b;
                }
                let out = &mut v[plane_of(1)..][..tw];
                for ((d, a), b) in out.iter_mut().zip(&o[..tw]).zip(&e[1..]) {
                    *d = a + b;
                }
                let out = &mut v[plane_of(2)..][..tw];
                for ((d, a), b) in out.iter_mut().zip(&e[1..]).zip(&o[..tw]) {
                    *d = a - b;
                }
                let out = &mut v[plane_of(3)..][..tw];
                for ((d, a), b) in out.iter_mut().zip(&o[..tw]).zip(&o[1..]) {
                    *d = a - b;
                }
            }
        }
    }

    // M[xi] (K x P) = U[xi] (K x C) . V[xi] (C x P).
    for xi in 0..16 {
        // SAFETY: the three matrices lie inside u, v and m with the strides
        // given (row-major, leading dimensions C, P and P).
        unsafe {
            gemm::gemm(
                k,
                tiles,
                c,
                m.as_mut_ptr().add(xi * k * tiles),
                1,
                tiles as isize,
                false,
                weights.u.as_ptr().add(xi * k * c),
                1,
                c as isize,
                v.as_ptr().add(xi * c * tiles),
                1,
                tiles as isize,
                0.0,
                1.0,
                false,
                false,
                false,
                Parallelism::None,
            );
        }
    }

    // Y = A^T M A per tile, A^T = [[1,1,1,0],[0,1,-1,-1]], plus the bias.
    for ko in 0..k {
        let b = bias.map_or(0.0, |b| b[ko]);
        for ty in t0..t1 {
            let at = (ty - t0) * tw;
            let row = |xi: usize| &m[(xi * k + ko) * tiles + at..][..tw];
            // Columns: S[i][j] = (A^T M)[i][j], 8 rows of tw.
            for j in 0..4 {
                let (m0, m1, m2, m3) = (row(j), row(4 + j), row(8 + j), row(12 + j));
                let (s0, s1) = s.split_at_mut(4 * tw);
                let (s0, s1) = (&mut s0[j * tw..(j + 1) * tw], &mut s1[j * tw..(j + 1) * tw]);
                for t in 0..tw {
                    s0[t] = m0[t] + m1[t] + m2[t];
                    s1[t] = m1[t] - m2[t] - m3[t];
                }
            }
            for i in 0..2 {
                let out_row = 2 * ty + i;
                if out_row >= h {
                    break;
                }
                let si = &s[4 * i * tw..4 * (i + 1) * tw];
                let (a0, rest) = si.split_at(tw);
                let (a1, rest) = rest.split_at(tw);
                let (a2, a3) = rest.split_at(tw);
                // SAFETY: row out_row of channel ko lies in this image's
                // output and in this band's rows [2 t0, 2 t1): no other band
                // touches it.
                let dst = unsafe { std::slice::from_raw_parts_mut(y.0.add((ko * h + out_row) * w), w) };
                for (t, pair) in dst.chunks_mut(2).enumerate() {
                    pair[0] = a0[t] + a1[t] + a2[t] + b;
                    if let Some(second) = pair.get_mut(1) {
                        *second = a1[t] - a2[t] - a3[t] + b;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The definition: `y[n][k][i][j] = b[k] + sum_{c,a,b} w[k][c][a][b] x[n][c][i+a-1][j+b-1]`.
    fn naive(x: &[f32], dims: Dims, w: &[f32], k: usize, bias: &[f32]) -> Vec<f32> {
        let Dims { n, c, h, w: wd } = dims;
        let mut y = vec![0.0f32; n * k * h * wd];
        for im in 0..n {
            for ko in 0..k {
                for i in 0..h {
                    for j in 0..wd {
                        let mut acc = bias[ko] as f64;
                        for ci in 0..c {
                            for a in 0..3 {
                                for b in 0..3 {
                                    let (yy, xx) = ((i + a).wrapping_sub(1), (j + b).wrapping_sub(1));
                                    if yy < h && xx < wd {
                                        acc += w[((ko * c + ci) * 3 + a) * 3 + b] as f64
                                            * x[((im * c + ci) * h + yy) * wd + xx] as f64;
                                    }
                                }
                            }
                        }
                        y[((im * k + ko) * h + i) * wd + j] = acc as f32;
                    }
                }
            }
        }
        y
    }

    fn values(len: usize, seed: u32) -> Vec<f32> {
        // A fixed, sign-mixed sequence (no RNG crate needed here).
        (0..len)
            .map(|i| (((i as u32).wrapping_mul(2_654_435_761).wrapping_add(seed) >> 8) % 2001) as f32 / 1000.0 - 1.0)
            .collect()
    }

    fn max_rel(a: &[f32], b: &[f32]) -> f32 {
        let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-6);
        a.iter().zip(b).fold(0.0f32, |m, (x, y)| m.max((x - y).abs())) / scale
    }

    #[test]
    fn forward_matches_the_definition_on_odd_and_even_sizes() {
        for (n, c, k, h, w) in [(1, 3, 4, 8, 8), (2, 5, 3, 7, 9), (1, 2, 2, 1, 1), (1, 4, 6, 5, 2)] {
            let dims = Dims { n, c, h, w };
            let (x, wt, b) = (values(dims.len(), 1), values(k * c * 9, 2), values(k, 3));
            let got = forward(&x, dims, &WinogradWeights::new(&wt, k, c), Some(&b));
            let want = naive(&x, dims, &wt, k, &b);
            assert!(max_rel(&got, &want) < 1e-5, "{dims:?} k={k}: {}", max_rel(&got, &want));
        }
    }

    #[test]
    fn gradients_match_finite_differences_of_the_definition() {
        let (n, c, k, h, w) = (2, 3, 4, 5, 6);
        let dims = Dims { n, c, h, w };
        let (x, wt, b) = (values(dims.len(), 4), values(k * c * 9, 5), values(k, 6));
        let dy = values(n * k * h * w, 7);
        // The loss sum(y . dy) is linear in each argument, so its
        // gradients are exact differences of the definition.
        let loss = |x: &[f32], wt: &[f32], b: &[f32]| -> f64 {
            naive(x, dims, wt, k, b).iter().zip(&dy).map(|(y, d)| (*y as f64) * (*d as f64)).sum()
        };
        let base = loss(&x, &wt, &b);
        let dx = input_grad(&dy, Dims { c: k, ..dims }, &WinogradWeights::flipped_transposed(&wt, k, c));
        for i in [0, 7, 31, dims.len() - 1] {
            let mut x2 = x.clone();
            x2[i] += 1.0;
            assert!(((loss(&x2, &wt, &b) - base) as f32 - dx[i]).abs() < 1e-4, "dx[{i}]");
        }
        let dw = weight_grad(&x, dims, &dy, k);
        for i in 0..k * c * 9 {
            let mut w2 = wt.clone();
            w2[i] += 1.0;
            assert!(((loss(&x, &w2, &b) - base) as f32 - dw[i]).abs() < 1e-4, "dw[{i}]");
        }
        let db = bias_grad(&dy, Dims { c: k, ..dims });
        for i in 0..k {
            let mut b2 = b.clone();
            b2[i] += 1.0;
            assert!(((loss(&x, &wt, &b2) - base) as f32 - db[i]).abs() < 1e-4, "db[{i}]");
        }
    }
}
