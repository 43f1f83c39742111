//! The 3x3 convolution (stride 1, zero padding 1: every convolution of
//! VGG16) on host memory, with both of its gradients. Plain Rust over
//! row-major `[N, C, H, W]` slices; `kernels::conv_op` makes it a Burn
//! operation.
//!
//! Why it exists (issue 19): burn-flex runs a convolution as im2col + gemm
//! and its backward as the generic transposed / weight convolutions, 4.6x
//! (forward) and 9.6x (forward + backward) slower than onnxruntime's forward
//! on VGG16 at 504x378. This kernel uses Winograd's minimal filtering
//! F(4x4, 3x3) (Lavin & Gray, "Fast Algorithms for Convolutional Neural
//! Networks", 2016): each 4x4 block of outputs of a channel pair costs 36
//! multiplies instead of 144, so the convolution becomes 36 independent
//! matrix products `M[xi] = U[xi] . V[xi]` (U: transformed weights `K x C`,
//! V: transformed input tiles `C x P`) plus cheap linear transforms around
//! them. The products run on the `gemm` crate (the one burn-flex uses).
//! F(2x2, 3x3) was measured first: 779 against 535 ms for VGG16's forward
//! at 504x378; F(4x4)'s larger transform constants cost accuracy (errors
//! about 5e-6 of a layer's largest value against 1e-6), well inside the
//! 1e-4 the tests hold the model to.
//!
//! The input gradient is the same convolution of the output gradient with
//! the weights flipped in space and their in/out channels swapped. The
//! weight gradient is 9 matrix products (one per kernel tap) over a
//! zero-padded copy of the input; it is exact (no Winograd), as VGG's
//! weights are frozen here and only the tests need it.
//!
//! Work is split into bands of tile rows per image (their size fixed by
//! the layer's shape, never by the thread count), one after another; inside
//! a band each step runs in parallel with rayon over independent pieces
//! (input channels, the 36 products, output channels), each computed by
//! one thread with a fixed order of operations, so results do not depend
//! on the thread count.

use gemm::Parallelism;
use rayon::prelude::*;

use crate::util::pool::BufferPool;

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

/// Output tile side: each tile computes 4x4 outputs of a channel pair.
const TILE: usize = 4;
/// Input tile side (TILE + 2).
const ALPHA: usize = 6;
/// Positions of an input tile, each one matrix product.
const XI: usize = ALPHA * ALPHA;

/// Weights in the Winograd domain: `u[xi][k][c]` for the 36 positions xi of
/// a 6x6 tile, `k` output and `c` input channels.
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
        Self::build(k, c, |ko, ci| &weights[(ko * c + ci) * 9..][..9], false)
    }

    /// The weights of the input gradient: `W'[c][k][a][b] = W[k][c][2-a][2-b]`
    /// for weights `W` `[K, C, 3, 3]`, so `K' = C` and `C' = K`.
    pub fn flipped_transposed(weights: &[f32], k: usize, c: usize) -> Self {
        assert_eq!(weights.len(), k * c * 9, "3x3 weights [{k}, {c}, 3, 3]");
        Self::build(c, k, |ci, ko| &weights[(ko * c + ci) * 9..][..9], true)
    }

    /// `U = G g G^T` for every channel pair, `kernel(ko, ci)` the 9 taps of
    /// output `ko` and input `ci` (row-major; read in reverse order, that
    /// is rotated by 180 degrees, when `flip`). Per output channel, all
    /// input channels at once (contiguous rows of `u`), in parallel.
    fn build<'w>(k: usize, c: usize, kernel: impl Fn(usize, usize) -> &'w [f32] + Sync, flip: bool) -> Self {
        // Every value is written below.
        let mut u = WEIGHT_BUFFERS.take(XI * k * c);
        let out = SharedOut(u.as_mut_ptr());
        (0..k).into_par_iter().for_each_init(
            || (vec![0.0f32; 9 * c], vec![0.0f32; 18 * c]),
            |(g, t), ko| {
                for ci in 0..c {
                    let taps = kernel(ko, ci);
                    for tap in 0..9 {
                        g[tap * c + ci] = taps[if flip { 8 - tap } else { tap }];
                    }
                }
                // t[i][b] = (G g)[i][b]: column b of every kernel.
                for b in 0..3 {
                    let input = [&g[b * c..(b + 1) * c], &g[(3 + b) * c..(4 + b) * c], &g[(6 + b) * c..(7 + b) * c]];
                    let mut rows = t.chunks_mut(c).skip(b).step_by(3);
                    weight_transform(std::array::from_fn(|_| rows.next().expect("six rows")), input);
                }
                // u[i][j] = (t G^T)[i][j], straight into u[6 i + j][ko][..].
                for i in 0..ALPHA {
                    let input = [
                        &t[3 * i * c..(3 * i + 1) * c],
                        &t[(3 * i + 1) * c..(3 * i + 2) * c],
                        &t[(3 * i + 2) * c..(3 * i + 3) * c],
                    ];
                    // SAFETY: rows (6 i + j, ko) of u belong to this output
                    // channel only, and u outlives the loop.
                    let rows = std::array::from_fn(|j| unsafe {
                        std::slice::from_raw_parts_mut(out.ptr().add(((i * ALPHA + j) * k + ko) * c), c)
                    });
                    weight_transform(rows, input);
                }
            },
        );
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

/// A frozen layer's weights prepared once for [`forward`] and
/// [`input_grad`]: the Winograd-domain weights of the forward, and those of
/// the input gradient, built on first use (forward-only callers never pay
/// for them). Preparing them on every call cost VGG16 as much as its
/// matrix products on the deeper layers (issue 19).
pub struct PreparedWeights {
    /// `[K, C, 3, 3]`, kept for the input gradient's weights.
    weights: Vec<f32>,
    forward: WinogradWeights,
    flipped: std::sync::OnceLock<WinogradWeights>,
}

impl PreparedWeights {
    /// From weights `[K, C, 3, 3]` (row-major, as `conv2d`'s).
    pub fn new(weights: Vec<f32>, k: usize, c: usize) -> Self {
        let forward = WinogradWeights::new(&weights, k, c);
        Self { weights, forward, flipped: std::sync::OnceLock::new() }
    }

    /// The forward's weights.
    pub fn forward(&self) -> &WinogradWeights {
        &self.forward
    }

    /// The input gradient's weights (see [`WinogradWeights::flipped_transposed`]).
    pub fn flipped(&self) -> &WinogradWeights {
        self.flipped.get_or_init(|| WinogradWeights::flipped_transposed(&self.weights, self.forward.k, self.forward.c))
    }
}

impl std::fmt::Debug for PreparedWeights {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PreparedWeights")
            .field("out_channels", &self.forward.k)
            .field("in_channels", &self.forward.c)
            .field("flipped", &self.flipped.get().is_some())
            .finish()
    }
}

impl Drop for WinogradWeights {
    fn drop(&mut self) {
        WEIGHT_BUFFERS.give_back(std::mem::take(&mut self.u));
    }
}

/// The buffers of dropped `WinogradWeights`, for the next ones: a 512x512
/// layer's 38 MB fresh from the system cost more in page faults than its
/// transform (measured: 10-15 ms against 3). Two cover a forward and a
/// backward step.
static WEIGHT_BUFFERS: BufferPool = BufferPool::new(2);

/// A pointer shared by the bands of one call, each writing its own
/// elements.
#[derive(Clone, Copy)]
struct SharedOut(*mut f32);
// SAFETY: the bands write disjoint elements (see each use), and the buffer
// outlives the parallel loop that uses the pointer.
unsafe impl Send for SharedOut {}
unsafe impl Sync for SharedOut {}

impl SharedOut {
    /// The pointer (a method, so that closures capture the whole `Sync`
    /// value rather than its raw-pointer field).
    fn ptr(&self) -> *mut f32 {
        self.0
    }
}

/// The convolution of `x` (`[N, C, H, W]`) with `weights` (`K x C`), plus
/// `bias` (`K` values) when given, through a ReLU when `relu`:
/// `[N, K, H, W]`.
pub fn forward(x: &[f32], dims: Dims, weights: &WinogradWeights, bias: Option<&[f32]>, relu: bool) -> Vec<f32> {
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
    let (tiles_h, tiles_w) = (dims.h.div_ceil(TILE), dims.w.div_ceil(TILE));
    let band_rows = band_rows(tiles_w, dims.c + k);
    let tiles_max = band_rows.min(tiles_h) * tiles_w;
    // Every value of a band's V and M is written before it is read.
    let mut v = BAND_BUFFERS.take(XI * dims.c * tiles_max);
    let mut m = BAND_BUFFERS.take(XI * k * tiles_max);
    let (image_in, image_out) = (dims.c * dims.h * dims.w, k * dims.h * dims.w);
    for (image, image_y) in x.chunks_exact(image_in).zip(y.chunks_exact_mut(image_out)) {
        for t0 in (0..tiles_h).step_by(band_rows) {
            let rows = t0..(t0 + band_rows).min(tiles_h);
            band(image, dims, weights, bias, relu, rows, &mut v, &mut m, image_y);
        }
    }
    BAND_BUFFERS.give_back(v);
    BAND_BUFFERS.give_back(m);
    y
}

/// `x`'s gradient for the convolution with weights `[K, C, 3, 3]`, given
/// the output gradient `dy` (`[N, K, H, W]`): `[N, C, H, W]`.
pub fn input_grad(dy: &[f32], dims: Dims, flipped: &WinogradWeights) -> Vec<f32> {
    forward(dy, dims, flipped, None, false)
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
            // SAFETY: tap `tap` writes grad[(ko c + ci) 9 + tap] only: the 9
            // taps write disjoint elements; reads stay inside x_pad (see its
            // two spare values) and dy_pad.
            unsafe {
                gemm::gemm(
                    k,
                    c,
                    positions,
                    out.ptr().add(tap),
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

/// Tile rows per band: as many as keep the band's transformed input and
/// products (36 (C+K) values per tile) near 32 MB, and at least 256 tiles.
/// On VGG16's deeper layers at the losses' sizes that is the whole image,
/// so each layer's transformed weights are read once per image. Fixed
/// numbers, not the thread count: the bands decide the matrix products'
/// shapes, which may decide gemm's blocking and so the rounding, and the
/// results must not depend on the machine's core count.
fn band_rows(tiles_w: usize, channels: usize) -> usize {
    let tiles = (8_388_608 / (XI * channels)).clamp(256, 8192);
    tiles.div_ceil(tiles_w).max(1)
}

/// The bands' transformed input `V[xi][c][p]` and products `M[xi][k][p]`,
/// kept between calls: allocating them afresh cost more in page faults
/// than the transforms themselves.
static BAND_BUFFERS: BufferPool = BufferPool::new(2);

/// B^T d for 6 vectors d (one 6-point input transform per index), B^T =
/// [[4,0,-5,0,1,0],[0,-4,-4,1,1,0],[0,4,-4,-1,1,0],[0,-2,-1,2,1,0],
/// [0,2,-1,-2,1,0],[0,4,0,-5,0,1]].
fn input_transform(out: [&mut [f32]; 6], d: [&[f32]; 6]) {
    let len = out[0].len();
    let [o0, o1, o2, o3, o4, o5] = out;
    let (o0, o1, o2, o3, o4, o5) =
        (&mut o0[..len], &mut o1[..len], &mut o2[..len], &mut o3[..len], &mut o4[..len], &mut o5[..len]);
    let (d0, d1, d2, d3, d4, d5) = (&d[0][..len], &d[1][..len], &d[2][..len], &d[3][..len], &d[4][..len], &d[5][..len]);
    for i in 0..len {
        let (a1_minus_a3, a4_minus_a2) = (d1[i] - d3[i], d4[i] - d2[i]);
        o0[i] = 4.0 * d0[i] - 5.0 * d2[i] + d4[i];
        o1[i] = -4.0 * (d1[i] + d2[i]) + d3[i] + d4[i];
        o2[i] = 4.0 * (d1[i] - d2[i]) - d3[i] + d4[i];
        o3[i] = -2.0 * a1_minus_a3 + a4_minus_a2;
        o4[i] = 2.0 * a1_minus_a3 + a4_minus_a2;
        o5[i] = 4.0 * d1[i] - 5.0 * d3[i] + d5[i];
    }
}

/// A^T m for 6 vectors m (one output transform per index), A^T =
/// [[1,1,1,1,1,0],[0,1,-1,2,-2,0],[0,1,1,4,4,0],[0,1,-1,8,-8,1]], plus `bias`,
/// clamped at 0 (`floor` = 0) or not (`floor` = -inf).
fn output_transform(out: [&mut [f32]; 4], m: [&[f32]; 6], bias: f32, floor: f32) {
    let len = out[0].len();
    let [o0, o1, o2, o3] = out;
    let (o0, o1, o2, o3) = (&mut o0[..len], &mut o1[..len], &mut o2[..len], &mut o3[..len]);
    let (m0, m1, m2, m3, m4, m5) = (&m[0][..len], &m[1][..len], &m[2][..len], &m[3][..len], &m[4][..len], &m[5][..len]);
    for i in 0..len {
        let (sum12, diff12, sum34, diff34) = (m1[i] + m2[i], m1[i] - m2[i], m3[i] + m4[i], m3[i] - m4[i]);
        o0[i] = (m0[i] + sum12 + sum34 + bias).max(floor);
        o1[i] = (diff12 + 2.0 * diff34 + bias).max(floor);
        o2[i] = (sum12 + 4.0 * sum34 + bias).max(floor);
        o3[i] = (diff12 + 8.0 * diff34 + m5[i] + bias).max(floor);
    }
}

/// G g for 3 vectors g (one kernel-column transform per index), G =
/// [[1/4,0,0],[-1/6,-1/6,-1/6],[-1/6,1/6,-1/6],[1/24,1/12,1/6],[1/24,-1/12,1/6],[0,0,1]].
fn weight_transform(out: [&mut [f32]; 6], g: [&[f32]; 3]) {
    let len = out[0].len();
    let [o0, o1, o2, o3, o4, o5] = out;
    let (o0, o1, o2, o3, o4, o5) =
        (&mut o0[..len], &mut o1[..len], &mut o2[..len], &mut o3[..len], &mut o4[..len], &mut o5[..len]);
    let (g0, g1, g2) = (&g[0][..len], &g[1][..len], &g[2][..len]);
    for i in 0..len {
        let (outer, middle) = (g0[i] + g2[i], g1[i]);
        o0[i] = g0[i] / 4.0;
        o1[i] = -(outer + middle) / 6.0;
        o2[i] = -(outer - middle) / 6.0;
        o3[i] = g0[i] / 24.0 + middle / 12.0 + g2[i] / 6.0;
        o4[i] = g0[i] / 24.0 - middle / 12.0 + g2[i] / 6.0;
        o5[i] = g2[i];
    }
}

/// Output tile rows `rows` of one image (`x`, written to `y`, the image's
/// output `[K, H, W]`): transform the input tiles, multiply, transform
/// back. Winograd F(4x4, 3x3) with the points 0, 1, -1, 2, -2 and infinity
/// (Lavin & Gray's matrices). Each step runs in parallel over independent
/// pieces, each piece computed by one thread with a fixed order of
/// operations: the input transform per input channel, the 36 matrix
/// products per position, the output transform per output channel (one
/// product per position over the whole band, rather than one per band and
/// thread, keeps gemm's tiles-long dimension filled on small layers and
/// reads the weights once per band).
///
/// The transforms run along whole tile rows so that they vectorise: the 6
/// input rows of a tile row are zero-padded (padded column q = input
/// column q - 1) and split into 4 column phases, R_r[t] = P[4t + r]; tile
/// tx reads P[4tx .. 4tx+6] = R_0[tx], R_1[tx], R_2[tx], R_3[tx],
/// R_0[tx+1], R_1[tx+1].
#[allow(clippy::too_many_arguments)]
// One pass of numeric kernel whose three stages share their tile buffers;
// split, each part would take the buffers and the index arithmetic apart.
#[allow(clippy::too_many_lines)]
fn band(
    x: &[f32],
    dims: Dims,
    weights: &WinogradWeights,
    bias: Option<&[f32]>,
    relu: bool,
    rows: std::ops::Range<usize>,
    v: &mut [f32],
    m: &mut [f32],
    y: &mut [f32],
) {
    let Dims { c, h, w, .. } = dims;
    let k = weights.k;
    let tw = w.div_ceil(TILE);
    let n1 = tw + 1;
    let row_len = TILE * n1;
    let (t0, t1) = (rows.start, rows.end);
    let tiles = (t1 - t0) * tw;
    assert!(v.len() >= XI * c * tiles && m.len() >= XI * k * tiles, "band buffers too short");

    // V: per input channel (its rows of V), in parallel.
    let v_out = SharedOut(v.as_mut_ptr());
    (0..c).into_par_iter().for_each_init(
        || (vec![0.0f32; ALPHA * row_len], vec![0.0f32; ALPHA * row_len]),
        |(padded, t), ci| {
            let plane = &x[ci * h * w..(ci + 1) * h * w];
            for ty in t0..t1 {
                for a in 0..ALPHA {
                    let row = &mut padded[a * row_len..(a + 1) * row_len];
                    row.fill(0.0);
                    let src_row = (TILE * ty + a).wrapping_sub(1);
                    if src_row < h {
                        // Input column col is padded column col + 1 = 4t + r:
                        // columns 4t .. 4t+3 go to R_1[t], R_2[t], R_3[t], R_0[t+1].
                        let (r0, rest) = row.split_at_mut(n1);
                        let (r1, rest) = rest.split_at_mut(n1);
                        let (r2, r3) = rest.split_at_mut(n1);
                        let src = &plane[src_row * w..(src_row + 1) * w];
                        let mut quads = src.chunks_exact(TILE);
                        for (t, quad) in quads.by_ref().enumerate() {
                            r1[t] = quad[0];
                            r2[t] = quad[1];
                            r3[t] = quad[2];
                            r0[t + 1] = quad[3];
                        }
                        let (t, rest) = (w / TILE, quads.remainder());
                        for (r, &value) in [r1, r2, r3].into_iter().zip(rest) {
                            r[t] = value;
                        }
                    }
                }
                // Columns: T = B^T [row 0; ...; row 5], all phases at once.
                let r: [&[f32]; 6] = std::array::from_fn(|a| &padded[a * row_len..(a + 1) * row_len]);
                let mut t_rows = t.chunks_mut(row_len);
                input_transform(std::array::from_fn(|_| t_rows.next().expect("six rows")), r);
                // Rows: V[6 i + j][ci] from row i of T.
                let at = ci * tiles + (ty - t0) * tw;
                for i in 0..ALPHA {
                    let ti = &t[i * row_len..(i + 1) * row_len];
                    let phase = |r: usize, shift: usize| &ti[r * n1 + shift..r * n1 + shift + tw];
                    let d = [phase(0, 0), phase(1, 0), phase(2, 0), phase(3, 0), phase(0, 1), phase(1, 1)];
                    // SAFETY: row ci of V[xi] belongs to this input channel
                    // only, and lies inside v (asserted above).
                    let dst = std::array::from_fn(|j| unsafe {
                        std::slice::from_raw_parts_mut(v_out.ptr().add((i * ALPHA + j) * c * tiles + at), tw)
                    });
                    input_transform(dst, d);
                }
            }
        },
    );

    // M[xi] (K x P) = U[xi] (K x C) . V[xi] (C x P), per position in parallel.
    let v: &[f32] = v;
    let m_out = SharedOut(m.as_mut_ptr());
    (0..XI).into_par_iter().for_each(|xi| {
        // SAFETY: the three matrices lie inside u, v and m with the strides
        // given (row-major, leading dimensions C, P and P); M[xi] is
        // written by this position only.
        unsafe {
            gemm::gemm(
                k,
                tiles,
                c,
                m_out.ptr().add(xi * k * tiles),
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
    });

    // Y = A^T M A per tile, plus the bias: down the columns into S (4 x 6
    // rows of tw), then along the rows into 4 output rows per tile row; per
    // output channel in parallel.
    let m: &[f32] = m;
    let floor = if relu { 0.0 } else { f32::NEG_INFINITY };
    let y_out = SharedOut(y.as_mut_ptr());
    (0..k).into_par_iter().for_each_init(
        || vec![0.0f32; (TILE * ALPHA + TILE) * tw],
        |s, ko| {
            let b = bias.map_or(0.0, |b| b[ko]);
            for ty in t0..t1 {
                let at = (ty - t0) * tw;
                let row = |xi: usize| &m[(xi * k + ko) * tiles + at..][..tw];
                let (s_cols, s_out) = s.split_at_mut(TILE * ALPHA * tw);
                for j in 0..ALPHA {
                    let col: [&[f32]; 6] = std::array::from_fn(|a| row(a * ALPHA + j));
                    let mut dst = s_cols.chunks_mut(tw).skip(j).step_by(ALPHA);
                    output_transform(
                        std::array::from_fn(|_| dst.next().expect("four rows")),
                        col,
                        0.0,
                        f32::NEG_INFINITY,
                    );
                }
                for i in 0..TILE {
                    let out_row = TILE * ty + i;
                    if out_row >= h {
                        break;
                    }
                    let si: [&[f32]; 6] = std::array::from_fn(|j| &s_cols[(i * ALPHA + j) * tw..][..tw]);
                    let mut y_parts = s_out.chunks_mut(tw);
                    output_transform(std::array::from_fn(|_| y_parts.next().expect("four rows")), si, b, floor);
                    // SAFETY: row out_row of channel ko lies in this image's
                    // output; only this output channel's piece writes it.
                    let dst = unsafe { std::slice::from_raw_parts_mut(y_out.ptr().add((ko * h + out_row) * w), w) };
                    let (y0, rest) = s_out.split_at(tw);
                    let (y1, rest) = rest.split_at(tw);
                    let (y2, y3) = rest.split_at(tw);
                    let mut quads = dst.chunks_exact_mut(TILE);
                    for (tx, out) in quads.by_ref().enumerate() {
                        out.copy_from_slice(&[y0[tx], y1[tx], y2[tx], y3[tx]]);
                    }
                    let tx = w / TILE;
                    for (value, phase) in quads.into_remainder().iter_mut().zip([y0, y1, y2]) {
                        *value = phase[tx];
                    }
                }
            }
        },
    );
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
        // Sides of every remainder modulo the 4x4 tile, and a single pixel.
        for (n, c, k, h, w) in
            [(1, 3, 4, 8, 8), (2, 5, 3, 7, 9), (1, 2, 2, 1, 1), (1, 4, 6, 5, 2), (1, 3, 5, 11, 7), (1, 6, 3, 6, 3)]
        {
            let dims = Dims { n, c, h, w };
            let (x, wt, b) = (values(dims.len(), 1), values(k * c * 9, 2), values(k, 3));
            let weights = WinogradWeights::new(&wt, k, c);
            let got = forward(&x, dims, &weights, Some(&b), false);
            let want = naive(&x, dims, &wt, k, &b);
            assert!(max_rel(&got, &want) < 1e-5, "{dims:?} k={k}: {}", max_rel(&got, &want));
            let relu: Vec<f32> = want.iter().map(|v| v.max(0.0)).collect();
            assert!(max_rel(&forward(&x, dims, &weights, Some(&b), true), &relu) < 1e-5, "{dims:?} k={k} with ReLU");
            assert!(relu.contains(&0.0) && relu.iter().any(|&v| v > 0.0));
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
