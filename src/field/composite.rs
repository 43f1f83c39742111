//! The differentiable half of volume rendering (paper eqs. 1-2): a Burn
//! graph over the packed samples of `march` - gather the 8 corner rows,
//! weight, sum; ReLU density; SH colour; per-ray transmittance in a padded
//! `[rays, K]` layout; weights and sums - so autodiff reaches the grid rows.
//! Whole images are rendered in chunks of rays (bounded memory).

use burn::tensor::{Device, Int, Tensor, activation::relu};

use crate::field::grid::RadianceGrid;
use crate::field::host_render;
use crate::field::march::{MarchParams, Marcher, SampleBatch};
use crate::scene::camera::{Camera, NdcParams, Ray};
use crate::util::image::Image;
use crate::util::tensor::{floats, indices, is_host_memory, select_rows, to_vec};

/// A sample batch uploaded to a device, ready for `composite`.
pub struct BatchTensors {
    pub num_rays: usize,
    pub num_samples: usize,
    /// Samples per ray in the padded [rays, K] layout.
    pub k: usize,
    pub corners: Tensor<1, Int>,
    pub corner_weights: Tensor<2>,
    pub colour_weights: Tensor<2>,
    pub basis: Tensor<3>,
    pub delta: Tensor<1>,
    pub t: Tensor<1>,
    /// For each padded slot, the packed sample index, or `num_samples` for padding.
    pub pad_map: Tensor<1, Int>,
}

impl BatchTensors {
    /// Uploads a batch. `remap` replaces each corner's grid row (e.g. by a
    /// local row of a training step's parameter subset).
    pub fn new(b: &SampleBatch, remap: Option<&dyn Fn(i32) -> i32>, device: &Device) -> Self {
        let s = b.num_samples();
        let nb = b.basis.len().checked_div(s).unwrap_or(1);
        let k = b.max_samples_per_ray().max(1);
        let mut pad = vec![s as i32; b.num_rays * k];
        for r in 0..b.num_rays {
            let (lo, hi) = (b.ray_offsets[r] as usize, b.ray_offsets[r + 1] as usize);
            for (j, i) in (lo..hi).enumerate() {
                pad[r * k + j] = i as i32;
            }
        }
        let corners: Vec<i32> = match remap {
            Some(f) => b.corner_rows.iter().map(|&r| f(r)).collect(),
            None => b.corner_rows.clone(),
        };
        Self {
            num_rays: b.num_rays,
            num_samples: s,
            k,
            corners: indices(corners, device),
            corner_weights: floats(b.corner_weights.clone(), [s * 8, 1], device),
            colour_weights: floats(b.colour_weights.clone(), [s * 8, 1], device),
            basis: floats(b.basis.clone(), [s, 1, nb], device),
            delta: floats(b.delta.clone(), [s], device),
            t: floats(b.t.clone(), [s], device),
            pad_map: indices(pad, device),
        }
    }
}

/// What the differentiable renderer returns per ray.
pub struct Rendered {
    /// [rays, 3]
    pub rgb: Tensor<2>,
    /// Expected depth sum(w_i t_i), [rays]
    pub depth: Tensor<1>,
    /// Accumulated opacity 1 - T_final, [rays]
    pub opacity: Tensor<1>,
}

/// Trilinear interpolation at `s` samples: gathers the 8 corner rows of each
/// (`corners`, `[s * 8]`), weights them (`weights`, `[s * 8, 1]`) and sums,
/// giving `[s, columns]`.
pub fn interpolate_corners(rows: Tensor<2>, corners: &Tensor<1, Int>, weights: Tensor<2>) -> Tensor<2> {
    let columns = rows.dims()[1];
    let s = corners.dims()[0] / 8;
    (select_rows(rows, corners.clone()) * weights).reshape([s, 8, columns]).sum_dim(1).reshape([s, columns])
}

/// Moves packed per-sample values into the padded [rays, K] layout (zero padding).
fn to_padded<const D: usize>(packed: Tensor<D>, bt: &BatchTensors, tail: [usize; D]) -> Tensor<D> {
    let mut zshape = tail;
    zshape[0] = 1;
    let zero = Tensor::zeros(zshape, &packed.device());
    select_rows(Tensor::cat(vec![packed, zero], 0), bt.pad_map.clone())
}

/// Equations 1-2 on the packed samples: density and colour by trilinear
/// interpolation of the given rows (colour over the active corners only), then alpha compositing per ray, with
/// `background` weighted by the remaining transmittance.
pub fn composite(density_rows: Tensor<2>, sh_rows: Tensor<2>, bt: &BatchTensors, background: [f32; 3]) -> Rendered {
    let device = density_rows.device();
    let (r, s, k) = (bt.num_rays, bt.num_samples, bt.k);
    let bg = floats(background.to_vec(), [1, 3], &device);
    if s == 0 {
        return Rendered {
            rgb: bg.repeat_dim(0, r),
            depth: Tensor::zeros([r], &device),
            opacity: Tensor::zeros([r], &device),
        };
    }
    let nb = sh_rows.dims()[1] / 3;
    let sigma = relu(interpolate_corners(density_rows, &bt.corners, bt.corner_weights.clone()).reshape([s]));
    let coeffs = interpolate_corners(sh_rows, &bt.corners, bt.colour_weights.clone()).reshape([s, 3, nb]);
    let colour = relu((coeffs * bt.basis.clone()).sum_dim(2).reshape([s, 3]) + 0.5);

    let tau = to_padded(sigma * bt.delta.clone(), bt, [s]).reshape([r, k]);
    let optical = tau.clone().cumsum(1);
    let transmittance = (tau.clone() - optical.clone()).exp(); // T_i = exp(-sum_{j<i} tau_j)
    let weights = transmittance * (-(tau.neg().exp()) + 1.0);
    let final_t = optical.narrow(1, k - 1, 1).neg().exp(); // [r, 1]

    let colour = to_padded(colour, bt, [s, 3]).reshape([r, k, 3]);
    let rgb = (weights.clone().reshape([r, k, 1]) * colour).sum_dim(1).reshape([r, 3]) + final_t.clone() * bg;
    let t = to_padded(bt.t.clone(), bt, [s]).reshape([r, k]);
    let depth = (weights * t).sum_dim(1).reshape([r]);
    let opacity = (-final_t + 1.0).reshape([r]);
    Rendered { rgb, depth, opacity }
}

/// A rendered view in plain buffers.
pub struct ViewRender {
    /// Colours clamped to [0, 1].
    pub image: Image,
    /// Expected depth (0 where nothing was hit).
    pub expected_depth: Vec<f32>,
    /// Equation-4 depth, None = miss.
    pub threshold_depth: Vec<Option<f32>>,
    pub opacity: Vec<f32>,
}

/// Rays rendered without autodiff, in plain buffers (colours not clamped).
#[derive(Debug, Clone, Default)]
pub struct RaysRender {
    /// Interleaved RGB.
    pub rgb: Vec<f32>,
    pub expected_depth: Vec<f32>,
    pub threshold_depth: Vec<Option<f32>>,
    pub opacity: Vec<f32>,
}

/// Side of the square tiles a view's rays are rendered in on the CPU.
const VIEW_TILE: usize = 16;

/// The pixels of a `width` x `height` image in tiles of `tile` x `tile`
/// (row by row inside a tile, tiles row by row; partial tiles at the
/// right and bottom edges): a permutation of `0..width * height`.
pub fn tile_order(width: usize, height: usize, tile: usize) -> Vec<usize> {
    let tile = tile.max(1);
    let mut order = Vec::with_capacity(width * height);
    for top in (0..height).step_by(tile) {
        for left in (0..width).step_by(tile) {
            for y in top..(top + tile).min(height) {
                order.extend((left..(left + tile).min(width)).map(|x| y * width + x));
            }
        }
    }
    order
}

/// Puts the per-ray results of rays rendered in `order` (ray `i` was
/// pixel `order[i]`) back into pixel order.
fn unpermute(r: RaysRender, order: &[usize]) -> RaysRender {
    let n = order.len();
    let mut out = RaysRender {
        rgb: vec![0.0; 3 * n],
        expected_depth: vec![0.0; n],
        threshold_depth: vec![None; n],
        opacity: vec![0.0; n],
    };
    for (i, &pixel) in order.iter().enumerate() {
        out.rgb[3 * pixel..3 * pixel + 3].copy_from_slice(&r.rgb[3 * i..3 * i + 3]);
        out.expected_depth[pixel] = r.expected_depth[i];
        out.threshold_depth[pixel] = r.threshold_depth[i];
        out.opacity[pixel] = r.opacity[i];
    }
    out
}

/// Renders views of one grid state without autodiff. What every view of
/// that state shares is built once: the marcher's block occupancy
/// (O(active rows): millions on real scenes) and, on the CPU backends, the
/// SH rows as host numbers (fern at SH degree 2: 27 floats a row). An
/// evaluation renders 120 path frames from one renderer.
pub struct ViewRenderer<'a> {
    grid: &'a RadianceGrid,
    /// The warp of forward-facing scenes (None: rays in world space).
    ndc: Option<NdcParams>,
    marcher: Marcher<'a>,
    /// The SH rows as host numbers: the fused pass of `host_render` (CPU
    /// backends); None = the graph in chunks of `chunk` rays (GPU).
    sh_host: Option<Vec<f32>>,
    params: MarchParams,
    background: [f32; 3],
    chunk: usize,
}

impl<'a> ViewRenderer<'a> {
    pub fn new(
        grid: &'a RadianceGrid,
        ndc: Option<&NdcParams>,
        params: &MarchParams,
        background: [f32; 3],
        chunk: usize,
    ) -> Self {
        let sh_host = is_host_memory(&grid.device()).then(|| to_vec(grid.sh.clone().inner()));
        let (ndc, params, chunk) = (ndc.copied(), *params, chunk.max(1));
        Self { grid, ndc, marcher: Marcher::new(grid), sh_host, params, background, chunk }
    }

    /// The warp of forward-facing scenes the views are marched in.
    pub fn ndc(&self) -> Option<&NdcParams> {
        self.ndc.as_ref()
    }

    /// Renders rays (on a GPU in chunks: bounded memory at any resolution).
    pub fn rays(&self, rays: &[Ray]) -> RaysRender {
        if let Some(sh) = &self.sh_host {
            return host_render::render_rays(&self.marcher, sh, rays, &self.params, self.background);
        }
        let device = self.grid.device();
        let (dens, sh) = (self.grid.density.clone().inner(), self.grid.sh.clone().inner());
        let mut out = RaysRender::default();
        for part in rays.chunks(self.chunk) {
            let batch = self.marcher.samples(part, &self.params);
            let bt = BatchTensors::new(&batch, None, &device);
            let rendered = composite(dens.clone(), sh.clone(), &bt, self.background);
            out.rgb.extend(to_vec(rendered.rgb));
            out.expected_depth.extend(to_vec(rendered.depth));
            out.opacity.extend(to_vec(rendered.opacity));
            out.threshold_depth.extend(batch.threshold_depth);
        }
        out
    }

    /// Renders a full camera view. On the CPU backends the rays are
    /// rendered in square tiles (`VIEW_TILE`), not rows: neighbouring rays
    /// of a tile cross the same cells, which then are still in the cache
    /// (fern's path views: 15 % less time); every ray is rendered on its
    /// own, so the image is the same to the bit.
    pub fn view(&self, camera: &Camera) -> ViewRender {
        let rays = camera.rays(self.ndc.as_ref());
        let r = if self.sh_host.is_some() {
            let (width, height) = (camera.intrinsics.width as usize, camera.intrinsics.height as usize);
            let order = tile_order(width, height, VIEW_TILE);
            let tiled: Vec<Ray> = order.iter().map(|&i| rays[i]).collect();
            unpermute(self.rays(&tiled), &order)
        } else {
            self.rays(&rays)
        };
        ViewRender {
            image: Image::of_camera(camera, r.rgb.into_iter().map(|v| v.clamp(0.0, 1.0)).collect()),
            expected_depth: r.expected_depth,
            threshold_depth: r.threshold_depth,
            opacity: r.opacity,
        }
    }
}

/// Renders rays without autodiff (one-off: many views of one grid share a [`ViewRenderer`]).
pub fn render_rays(
    grid: &RadianceGrid,
    rays: &[Ray],
    params: &MarchParams,
    background: [f32; 3],
    chunk: usize,
) -> RaysRender {
    ViewRenderer::new(grid, None, params, background, chunk).rays(rays)
}

/// Renders a full camera view (`ndc`: the warp of forward-facing scenes;
/// many views of one grid share a [`ViewRenderer`]).
pub fn render_view(
    grid: &RadianceGrid,
    camera: &Camera,
    ndc: Option<&NdcParams>,
    params: &MarchParams,
    background: [f32; 3],
    chunk: usize,
) -> ViewRender {
    ViewRenderer::new(grid, ndc, params, background, chunk).view(camera)
}
