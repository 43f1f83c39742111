//! Views and rays rendered without autodiff (evaluation, path renders,
//! test views, R³'s depths): the kernel is chosen once, when the renderer
//! is built - the fused plain-Rust pass of `host_render` on the CPU
//! backends, the Burn graph of `composite` in chunks of rays on a GPU - so
//! no caller branches on it.

use crate::field::composite::{BatchTensors, composite, max_samples_per_call};
use crate::field::grid::RadianceGrid;
use crate::field::host_render;
/// Rays rendered without autodiff, in plain buffers (defined beside the host kernel that fills it).
pub use crate::field::host_render::RaysRender;
use crate::field::march::{MarchParams, Marcher};
use crate::scene::camera::{Camera, NdcParams, Ray};
use crate::util::image::Image;
use crate::util::tensor::{is_host_memory, to_vec};
use serde::{Deserialize, Serialize};

/// How a field is rendered: its march settings and the rays per chunk of
/// whole-image renders. A checkpoint stores them with its field, so
/// whatever renders it needs nothing of the run that fitted it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RenderSettings {
    pub march: MarchParams,
    /// Rays per chunk when rendering whole images on a GPU.
    pub chunk: usize,
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
/// (O(active rows): millions on real scenes) and the kernel with what it
/// reads. An evaluation renders 120 path frames from one renderer.
pub struct ViewRenderer<'a> {
    grid: &'a RadianceGrid,
    /// The warp of forward-facing scenes (None: rays in world space).
    ndc: Option<NdcParams>,
    marcher: Marcher<'a>,
    kernel: ViewKernel,
    params: MarchParams,
    background: [f32; 3],
}

/// What renders a view's rays, chosen when the renderer is built.
enum ViewKernel {
    /// The fused pass of `host_render` over the SH rows as host numbers
    /// (CPU backends; fern at SH degree 2: 27 floats a row).
    Host { sh: Vec<f32> },
    /// The Burn graph in chunks of `chunk` rays (GPU: bounded memory at any resolution).
    Graph { chunk: usize },
}

impl<'a> ViewRenderer<'a> {
    pub fn new(
        grid: &'a RadianceGrid,
        ndc: Option<&NdcParams>,
        settings: &RenderSettings,
        background: [f32; 3],
    ) -> Self {
        let kernel = match is_host_memory(&grid.device()) {
            true => ViewKernel::Host { sh: to_vec(grid.sh.clone().inner()) },
            false => ViewKernel::Graph { chunk: settings.chunk.max(1) },
        };
        Self { grid, ndc: ndc.copied(), marcher: Marcher::new(grid), kernel, params: settings.march, background }
    }

    /// The warp of forward-facing scenes the views are marched in.
    pub fn ndc(&self) -> Option<&NdcParams> {
        self.ndc.as_ref()
    }

    /// Renders rays (on a GPU in chunks: bounded memory at any resolution).
    pub fn rays(&self, rays: &[Ray]) -> RaysRender {
        let chunk = match &self.kernel {
            ViewKernel::Host { sh } => {
                return host_render::render_rays(&self.marcher, sh, rays, &self.params, self.background);
            }
            ViewKernel::Graph { chunk } => *chunk,
        };
        let device = self.grid.device();
        let (dens, sh) = (self.grid.density.clone().inner(), self.grid.sh.clone().inner());
        let mut out = RaysRender::default();
        // A chunk whose samples would not fit in one of the device's buffers goes in runs of rays.
        let most = max_samples_per_call(&device, sh.dims()[1]);
        for part in rays.chunks(chunk) {
            let batch = self.marcher.samples(part, &self.params);
            for (first, count) in batch.ray_runs(most) {
                let bt = BatchTensors::new(&batch.sub_batch(first, count), None, &device);
                let rendered = composite(dens.clone(), sh.clone(), &bt, self.background);
                out.rgb.extend(to_vec(rendered.rgb));
                out.expected_depth.extend(to_vec(rendered.depth));
                out.opacity.extend(to_vec(rendered.opacity));
            }
            out.threshold_depth.extend(batch.threshold_depth);
        }
        out
    }

    /// Renders a full camera view. The host kernel renders the rays in
    /// square tiles (`VIEW_TILE`), not rows: neighbouring rays of a tile
    /// cross the same cells, which then are still in the cache (fern's path
    /// views: 15 % less time); every ray is rendered on its own, so the
    /// image is the same to the bit.
    pub fn view(&self, camera: &Camera) -> ViewRender {
        let rays = camera.rays(self.ndc.as_ref());
        let r = match self.kernel {
            ViewKernel::Host { .. } => {
                let (width, height) = (camera.intrinsics.width as usize, camera.intrinsics.height as usize);
                let order = tile_order(width, height, VIEW_TILE);
                let tiled: Vec<Ray> = order.iter().map(|&i| rays[i]).collect();
                unpermute(self.rays(&tiled), &order)
            }
            ViewKernel::Graph { .. } => self.rays(&rays),
        };
        ViewRender {
            image: camera.image_of(r.rgb.into_iter().map(|v| v.clamp(0.0, 1.0)).collect()),
            expected_depth: r.expected_depth,
            threshold_depth: r.threshold_depth,
            opacity: r.opacity,
        }
    }
}

/// Renders rays without autodiff (one-off: many views of one grid share a [`ViewRenderer`]).
pub fn render_rays(grid: &RadianceGrid, rays: &[Ray], settings: &RenderSettings, background: [f32; 3]) -> RaysRender {
    ViewRenderer::new(grid, None, settings, background).rays(rays)
}

/// Renders a full camera view (`ndc`: the warp of forward-facing scenes;
/// many views of one grid share a [`ViewRenderer`]).
pub fn render_view(
    grid: &RadianceGrid,
    camera: &Camera,
    ndc: Option<&NdcParams>,
    settings: &RenderSettings,
    background: [f32; 3],
) -> ViewRender {
    ViewRenderer::new(grid, ndc, settings, background).view(camera)
}

/// Checked against the Burn graph and autodiff, on every backend the test
/// command runs (`cargo test --lib graph_oracle`).
#[cfg(test)]
#[allow(clippy::print_stdout, clippy::print_stderr)] // the measured errors, shown with --nocapture
mod graph_oracle {
    use super::{RenderSettings, render_rays};
    use crate::field::composite::{BatchTensors, composite};
    use crate::field::host_render;
    use crate::field::march;
    use crate::scene::sh;
    use crate::test_support::{device, params, sparse_degree2_grid, tol};
    use crate::util::tensor::{floats, to_vec};

    /// The plain-Rust renderer (`field::host_render`, what views rendered
    /// without autodiff use on the CPU backends) gives the Burn graph's
    /// colours, expected depths and opacities to 1e-5, on a sparse grid with
    /// varied density and SH degree 2, rays that hit, graze and miss.
    #[test]
    fn host_render_matches_the_graph() {
        let (grid, dens, shd, rays) = sparse_degree2_grid(12.0);
        let (n, nb, dev) = (dens.len(), sh::num_basis(2), device());
        let p = params(0.25);
        let batch = march::generate_samples(&grid, &rays, &p);
        assert!(batch.num_samples() > 200, "{} samples", batch.num_samples());
        let bt = BatchTensors::new(&batch, None, &dev);
        let graph =
            composite(floats(dens.clone(), [n, 1], &dev), floats(shd.clone(), [n, 3 * nb], &dev), &bt, [0.2, 0.5, 0.9]);
        let host = host_render::render_rays(&march::Marcher::new(&grid), &shd, &rays, &p, [0.2, 0.5, 0.9]);
        assert_eq!(host.threshold_depth, batch.threshold_depth, "the fused pass marches the same samples");
        for (name, host, graph) in [
            ("rgb", host.rgb, to_vec(graph.rgb)),
            ("depth", host.expected_depth, to_vec(graph.depth)),
            ("opacity", host.opacity, to_vec(graph.opacity)),
        ] {
            assert_eq!(host.len(), graph.len(), "{name}");
            let err = host.iter().zip(&graph).fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
            println!("{name}: max |host - graph| = {err:.2e}");
            assert!(err <= tol(1e-5) * graph.iter().fold(1.0f32, |m, v| m.max(v.abs())), "{name}: {err:.2e}");
        }
        let opacities = render_rays(&grid, &rays, &RenderSettings { march: p, chunk: 7 }, [0.2, 0.5, 0.9]).opacity;
        assert!(
            opacities.iter().any(|&o| o > 0.9) && opacities.iter().any(|&o| o < 0.1),
            "hits and misses: {opacities:?}"
        );
    }
}
