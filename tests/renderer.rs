//! The volume renderer against closed-form cases, and its gradients against
//! finite differences. Runs on the backend named by REFNPR_BACKEND.

mod common;

use burn::tensor::Tensor;
use glam::{Mat4, Vec3};
use refnpr::field::composite::{self as render, BatchTensors};
use refnpr::field::grid::{GridGeometry, RadianceGrid};
use refnpr::field::march::{self, MarchParams};
use refnpr::field::view::{self, RenderSettings};
use refnpr::scene::camera::{Camera, Intrinsics, Ray};
use refnpr::scene::sh;
use refnpr::util::tensor::{floats, to_vec};

fn params(step: f32) -> MarchParams {
    MarchParams { step, sigma_threshold: 0.0, stop_threshold: 1e-7, ..MarchParams::default() }
}

/// A box [-1,1]^3 at resolution r, every row holding density `sigma` and flat colour `c`.
fn uniform_grid(r: usize, sigma: f32, c: [f32; 3], degree: u32) -> RadianceGrid {
    let geo = GridGeometry::new([r; 3], Vec3::splat(-1.0), Vec3::splat(1.0));
    let n = geo.num_points();
    let nb = sh::num_basis(degree);
    let mut shd = vec![0.0; n * 3 * nb];
    for row in 0..n {
        for ch in 0..3 {
            shd[row * 3 * nb + ch * nb] = sh::dc_for_colour(c[ch]);
        }
    }
    RadianceGrid::from_rows(geo, degree, (0..n as u32).collect(), vec![sigma; n], shd, &common::device())
}

fn axis_ray(o: Vec3, d: Vec3) -> Ray {
    Ray { origin: o, dir: d.normalize(), view_dir: d.normalize() }
}

#[test]
fn homogeneous_slab_matches_beer_lambert() {
    // 16 voxels of 0.125; step 0.5 voxel -> exactly 32 samples of 0.0625 across the 2-unit box.
    let (sigma, c, bg) = (0.8f32, [0.9f32, 0.3, 0.1], [0.2f32, 0.4, 1.0]);
    let grid = uniform_grid(16, sigma, c, 0);
    let rays = vec![axis_ray(Vec3::new(0.1, -0.2, 5.0), -Vec3::Z), axis_ray(Vec3::new(-3.0, 0.3, 0.05), Vec3::X)];
    let view::RaysRender { rgb, expected_depth: depth, threshold_depth: tdepth, opacity } =
        view::render_rays(&grid, &rays, &RenderSettings { march: params(0.5), chunk: 1024 }, bg);
    let t_final = (-sigma * 2.0f32).exp();
    for r in 0..2 {
        for ch in 0..3 {
            let want = c[ch] * (1.0 - t_final) + bg[ch] * t_final;
            assert!(
                (rgb[r * 3 + ch] - want).abs() < common::tol(1e-5),
                "ray {r} ch {ch}: {} vs {want}",
                rgb[r * 3 + ch]
            );
        }
        assert!((opacity[r] - (1.0 - t_final)).abs() < common::tol(1e-5));
        // Expected depth of a homogeneous slab (discrete sum over the 32 samples).
        let (t0, step) = (if r == 0 { 4.0 } else { 2.0 }, 0.0625f32);
        let mut want_d = 0.0;
        let mut acc = 0.0f32;
        for i in 0..32 {
            let t = t0 + step * (i as f32 + 0.5);
            want_d += (-acc).exp() * (1.0 - (-sigma * step).exp()) * t;
            acc += sigma * step;
        }
        assert!((depth[r] - want_d).abs() < common::tol(1e-4), "depth {} vs {want_d}", depth[r]);
        // Equation 4: where the optical depth reaches ln 2, exactly t0 + ln2 / sigma
        // in a homogeneous slab (located inside the sample's segment).
        let want_t = t0 + std::f32::consts::LN_2 / sigma;
        assert!((tdepth[r].unwrap() - want_t).abs() < 1e-4, "{:?} vs {want_t}", tdepth[r]);
    }
    // The depth-only march (R³'s) gives the same answer.
    assert_eq!(march::threshold_depths(&grid, &rays, &params(0.5)), tdepth);
}

#[test]
fn single_opaque_voxel_blocks_only_the_rays_through_it() {
    // One active lattice point at the centre of an 8^3 grid, very dense.
    let geo = GridGeometry::new([8; 3], Vec3::splat(-1.0), Vec3::splat(1.0));
    let centre = geo.flat(4, 4, 4) as u32;
    let c = [0.1f32, 0.8, 0.3];
    let shd: Vec<f32> = c.iter().map(|&v| sh::dc_for_colour(v)).collect();
    let grid = RadianceGrid::from_rows(geo, 0, vec![centre], vec![5000.0], shd, &common::device());
    let p = geo.grid_to_world(Vec3::splat(4.0));
    let hit = axis_ray(Vec3::new(p.x, p.y, 3.0), -Vec3::Z);
    let miss = axis_ray(Vec3::new(p.x + 0.6, p.y, 3.0), -Vec3::Z);
    let bg = [1.0, 1.0, 1.0];
    let view::RaysRender { rgb, threshold_depth: tdepth, opacity, .. } =
        view::render_rays(&grid, &[hit, miss], &RenderSettings { march: params(0.25), chunk: 64 }, bg);
    for ch in 0..3 {
        assert!((rgb[ch] - c[ch]).abs() < 1e-3, "hit colour {:?}", &rgb[..3]);
        assert!((rgb[3 + ch] - 1.0).abs() < 1e-6, "miss colour {:?}", &rgb[3..]);
    }
    assert!(opacity[0] > 0.999 && opacity[1] == 0.0);
    // The surface is found within one voxel of the lattice point, and the miss has no depth.
    let d = tdepth[0].expect("a hit has a depth");
    assert!((d - (3.0 - p.z)).abs() < geo.voxel_size().x, "depth {d}");
    assert!(tdepth[1].is_none());
}

#[test]
fn full_image_render_is_chunk_independent() {
    let grid = uniform_grid(8, 1.5, [0.5, 0.6, 0.7], 1);
    let cam = Camera::new(
        Intrinsics::from_fov_x(24, 18, 0.9),
        refnpr::scene::camera::look_at(Vec3::new(2.5, 2.0, 1.5), Vec3::ZERO, Vec3::Z),
    );
    let a = view::render_view(&grid, &cam, None, &RenderSettings { march: params(0.5), chunk: 7 }, [1.0; 3]);
    let b = view::render_view(&grid, &cam, None, &RenderSettings { march: params(0.5), chunk: 100_000 }, [1.0; 3]);
    assert_eq!(a.image.rgb.len(), 24 * 18 * 3);
    for (x, y) in a.image.rgb.iter().zip(&b.image.rgb) {
        assert!((x - y).abs() < 1e-5);
    }
    let _ = Mat4::IDENTITY;
}

#[test]
fn autodiff_gradients_match_finite_differences() {
    // A 4^3 grid with smooth positive density and SH degree 1, a few oblique rays.
    let geo = GridGeometry::new([4; 3], Vec3::splat(-1.0), Vec3::splat(1.0));
    let n = geo.num_points();
    let nb = sh::num_basis(1);
    let dens: Vec<f32> = (0..n).map(|i| 0.6 + 0.5 * ((i * 7919) % 13) as f32 / 13.0).collect();
    let shd: Vec<f32> = (0..n * 3 * nb).map(|i| 0.15 * ((((i * 104_729) % 17) as f32 / 17.0) - 0.5)).collect();
    let dev = common::device();
    let grid = RadianceGrid::from_rows(geo, 1, (0..n as u32).collect(), dens.clone(), shd.clone(), &dev);
    let rays: Vec<Ray> = (0..6)
        .map(|i| {
            let o = Vec3::new(-2.0, -1.5 + 0.5 * i as f32, 2.0 - 0.3 * i as f32);
            axis_ray(o, Vec3::new(1.0, 0.35, -0.55 + 0.1 * i as f32))
        })
        .collect();
    let p = params(0.5);
    let batch = march::generate_samples(&grid, &rays, &p);
    assert!(batch.num_samples() > 20);
    let bt = BatchTensors::new(&batch, None, &dev);
    let weights: Vec<f32> = (0..rays.len() * 3).map(|i| 0.3 + ((i * 31) % 7) as f32 / 7.0).collect();
    let loss_of = |d: &[f32], s: &[f32]| -> f32 {
        let out = render::composite(
            floats(d.to_vec(), [n, 1], &dev),
            floats(s.to_vec(), [n, 3 * nb], &dev),
            &bt,
            [0.5, 0.5, 0.5],
        );
        let l = (out.rgb * floats(weights.clone(), [rays.len(), 3], &dev)).sum();
        to_vec(l)[0]
    };
    let ld = floats(dens.clone(), [n, 1], &dev).autodiff().require_grad();
    let ls = floats(shd.clone(), [n, 3 * nb], &dev).autodiff().require_grad();
    let out = render::composite(ld.clone(), ls.clone(), &bt, [0.5, 0.5, 0.5]);
    let loss = (out.rgb * floats(weights.clone(), [rays.len(), 3], &dev)).sum();
    let grads = loss.backward();
    let gd = to_vec(ld.grad(&grads).unwrap());
    let gs = to_vec(ls.grad(&grads).unwrap());
    // Check the largest gradients (where finite differences are meaningful in f32).
    let mut checked = 0;
    let h = 1e-2f32;
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| gd[b].abs().total_cmp(&gd[a].abs()));
    for &i in order.iter().take(8) {
        let fd = common::central_difference(&dens, i, h, |d| loss_of(d, &shd) as f64) as f32;
        assert!((fd - gd[i]).abs() < 2e-2 * gd[i].abs().max(1e-2), "density {i}: autodiff {} fd {fd}", gd[i]);
        checked += 1;
    }
    let mut order: Vec<usize> = (0..gs.len()).collect();
    order.sort_by(|&a, &b| gs[b].abs().total_cmp(&gs[a].abs()));
    for &i in order.iter().take(8) {
        let fd = common::central_difference(&shd, i, h, |s| loss_of(&dens, s) as f64) as f32;
        assert!((fd - gs[i]).abs() < 2e-2 * gs[i].abs().max(1e-2), "sh {i}: autodiff {} fd {fd}", gs[i]);
        checked += 1;
    }
    assert_eq!(checked, 16);
}

/// R³'s depth-only march (with empty-block skipping) gives exactly the
/// renderer's equation-4 depth on a sparse grid, hits and misses alike.
#[test]
fn depth_march_with_block_skipping_equals_the_renderer() {
    let grid = refnpr::field::grid::sphere_grid(64, &common::device());
    let cam = Camera::new(
        Intrinsics::from_fov_x(40, 40, 0.9),
        refnpr::scene::camera::look_at(Vec3::new(2.2, 1.0, 0.8), Vec3::ZERO, Vec3::Z),
    );
    let rays = cam.rays(None);
    let p = MarchParams::default();
    let tdepth = view::render_rays(&grid, &rays, &RenderSettings { march: p, chunk: 4096 }, [1.0; 3]).threshold_depth;
    let fast = march::threshold_depths(&grid, &rays, &p);
    let hits = tdepth.iter().filter(|d| d.is_some()).count();
    assert!(hits > 200 && hits < rays.len(), "the sphere covers part of the view: {hits}");
    assert_eq!(fast, tdepth);
}

/// A view is rendered in square tiles on the CPU backends (cache reuse
/// between neighbouring rays); every ray is still rendered on its own, so
/// the view equals its rays rendered in pixel order, to the bit, with the
/// image's edges cutting tiles short.
#[test]
fn a_view_rendered_in_tiles_equals_its_rays_in_pixel_order() {
    for (w, h) in [(37, 21), (16, 16), (5, 40)] {
        let order = view::tile_order(w, h, 16);
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..w * h).collect::<Vec<_>>(), "{w}x{h}: a permutation of the pixels");
    }
    let grid = refnpr::field::grid::sphere_grid(32, &common::device());
    let cam = Camera::new(
        Intrinsics::from_fov_x(37, 21, 0.9),
        refnpr::scene::camera::look_at(Vec3::new(2.2, 1.0, 0.8), Vec3::ZERO, Vec3::Z),
    );
    let renderer = view::ViewRenderer::new(
        &grid,
        None,
        &RenderSettings { march: MarchParams::default(), chunk: 4096 },
        [0.2, 0.5, 0.9],
    );
    let view = renderer.view(&cam);
    let rays = renderer.rays(&cam.rays(None));
    let hits = rays.threshold_depth.iter().filter(|d| d.is_some()).count();
    assert!(hits > 50 && hits < 37 * 21, "the sphere covers part of the view: {hits}");
    let clamped: Vec<f32> = rays.rgb.iter().map(|v| v.clamp(0.0, 1.0)).collect();
    assert_eq!(view.image.rgb, clamped);
    assert_eq!(view.expected_depth, rays.expected_depth);
    assert_eq!(view.threshold_depth, rays.threshold_depth);
    assert_eq!(view.opacity, rays.opacity);
}

/// Gathers and scatters of more than 65535 rows (every renderer and
/// optimiser step has them) are exact: Burn 0.22.1's wgpu `select_assign`,
/// also `select`'s backward, drops indices beyond 65535, which
/// `tensor_util::{select_rows, assign_rows}` work around by splitting.
#[test]
fn long_gathers_and_scatters_are_exact() {
    use refnpr::util::tensor::{assign_rows, indices, select_rows};
    let d = common::device();
    for n in [1000usize, 70_000, 140_001] {
        let x = floats(vec![1.0; 30], [10, 3], &d).autodiff().require_grad();
        let idx: Vec<i32> = (0..n).map(|i| (i % 10) as i32).collect();
        let g = to_vec(x.grad(&select_rows(x.clone(), indices(idx.clone(), &d)).sum().backward()).unwrap());
        assert_eq!(g.iter().sum::<f32>(), (3 * n) as f32, "gather backward over {n} rows");
        let t = assign_rows(
            Tensor::<2>::zeros([10, 3], &d),
            indices(idx, &d),
            Tensor::ones([n, 3], &d),
            burn::tensor::IndexingUpdateOp::Add,
        );
        assert_eq!(to_vec(t).iter().sum::<f32>(), (3 * n) as f32, "scatter-add of {n} rows");
    }
}

/// Colour at voxels with empty corners: renormalised over the active corners
/// (the default) every sample's colour weights sum to 1; svox2's zero corners
/// use the plain trilinear weights, which sum to less at the surface's edge.
#[test]
fn colour_corners_renormalised_or_zero() {
    // Only the lattice points with x index <= 2 of a 6^3 grid are active.
    let geo = GridGeometry::new([6; 3], Vec3::splat(-1.0), Vec3::splat(1.0));
    let coords: Vec<u32> = (0..geo.num_points() as u32).filter(|&f| geo.unflat(f as usize)[0] <= 2).collect();
    let n = coords.len();
    let grid = RadianceGrid::from_rows(geo, 0, coords, vec![2.0; n], vec![0.3; n * 3], &common::device());
    let rays = [axis_ray(Vec3::new(-2.0, 0.1, 0.05), Vec3::X)];
    let renormalised = march::generate_samples(&grid, &rays, &params(0.5));
    let zero_params = MarchParams { colour_corners: march::ColourCorners::Zero, ..params(0.5) };
    let zero = march::generate_samples(&grid, &rays, &zero_params);
    assert_eq!(renormalised.corner_weights, zero.corner_weights, "density is interpolated the same way");
    assert_eq!(zero.colour_weights, zero.corner_weights);
    let sums = |w: &[f32]| w.chunks_exact(8).map(|c| c.iter().sum::<f32>()).collect::<Vec<_>>();
    assert!(sums(&renormalised.colour_weights).iter().all(|s| (s - 1.0).abs() < 1e-5));
    let edge = sums(&zero.colour_weights).into_iter().fold(1.0f32, f32::min);
    assert!(edge < 0.9, "a sample beyond the active half-space has empty corners (smallest weight sum {edge})");
}

/// The adapter line names the adapter, its kind and API; a CPU adapter gets
/// a warning that says how much slower it is and how to pick flex, a GPU
/// none. On the wgpu backend, the real adapter is reported through the
/// progress sink (lavapipe in CI: a CPU, so the warning comes too).
#[test]
fn wgpu_names_its_adapter_and_warns_on_a_cpu() {
    use refnpr::BackendKind;
    use refnpr::util::backend::{AdapterSummary, SOFTWARE_ADAPTER_SLOWDOWN, announce_wgpu};
    use refnpr::util::progress::{Event, Progress};
    let gpu = AdapterSummary {
        name: "NVIDIA H100".into(),
        kind: "discrete GPU".into(),
        api: "Vulkan".into(),
        driver: "NVIDIA 560".into(),
        software: false,
        max_buffer_bytes: 2_147_483_648,
    };
    assert_eq!(
        gpu.line(),
        "wgpu adapter: NVIDIA H100 (discrete GPU, Vulkan; driver NVIDIA 560; buffers up to 2.15 GB)"
    );
    assert!(gpu.software_warning().is_none());
    let cpu = AdapterSummary { name: "llvmpipe".into(), kind: "CPU".into(), software: true, ..gpu };
    let w = cpu.software_warning().expect("a CPU adapter is warned about");
    assert!(w.contains("llvmpipe") && w.contains(SOFTWARE_ADAPTER_SLOWDOWN) && w.contains("--backend flex"), "{w}");

    if common::backend() != BackendKind::Wgpu {
        return;
    }
    struct Recorder(std::sync::Mutex<Vec<Event>>);
    impl Progress for Recorder {
        fn event(&self, e: Event) {
            self.0.lock().unwrap().push(e);
        }
    }
    let rec = Recorder(Default::default());
    let adapter = announce_wgpu(&rec).expect("the wgpu tests run where wgpu has an adapter");
    let events = rec.0.into_inner().unwrap();
    assert_eq!(events[0], Event::Info(adapter.line()));
    assert!(adapter.line().starts_with("wgpu adapter: ") && !adapter.name.is_empty(), "{}", adapter.line());
    assert_eq!(events.len(), if adapter.software { 2 } else { 1 }, "{events:?}");
    assert!(adapter.max_buffer_bytes >= 1 << 27, "{}", adapter.line());
    if adapter.software {
        assert!(matches!(&events[1], Event::Warning(w) if w.contains("--backend flex")), "{events:?}");
    }
}

/// `neighbour_rows` gives, for every row, the rows of the lattice points
/// one step along +x, +y and +z: None past the lattice's end and at empty
/// points; `neighbour_row` gives the same axis by axis.
#[test]
fn neighbour_rows_are_the_rows_of_the_next_lattice_points() {
    let geo = GridGeometry::new([3, 4, 5], Vec3::splat(-1.0), Vec3::splat(1.0));
    // Every third point empty; rows in reverse lattice order.
    let coords: Vec<u32> = (0..60u32).filter(|p| p % 3 != 1).rev().collect();
    let n = coords.len();
    let grid = RadianceGrid::from_rows(geo, 0, coords.clone(), vec![0.1; n], vec![0.0; n * 3], &common::device());
    let row_of = |point: usize| coords.iter().position(|&c| c as usize == point).map(|r| r as i32);
    let (mut inside, mut empty) = (0, 0);
    for (row, &point) in coords.iter().enumerate() {
        let ijk = geo.unflat(point as usize);
        let want: [Option<i32>; 3] = std::array::from_fn(|axis| {
            let mut next = ijk;
            next[axis] += 1;
            (next[axis] < geo.res[axis]).then(|| row_of(geo.flat(next[0], next[1], next[2]))).flatten()
        });
        inside += want.iter().flatten().count();
        empty += (0..3).filter(|&a| ijk[a] + 1 < geo.res[a] && want[a].is_none()).count();
        assert_eq!(grid.neighbour_rows(row), want, "row {row} at {ijk:?}");
        assert!((0..3).all(|axis| grid.neighbour_row(row, axis) == want[axis]), "row {row}");
    }
    assert!(inside > 20 && empty > 20, "the grid has both kinds: {inside} neighbours, {empty} empty");
}
