//! Stylization metrics against hand-computed values on tiny inputs. Runs on
//! the backend named by REFNPR_BACKEND.

mod common;

use glam::{Mat4, Vec3};
use refnpr::eval::lpips::{Lpips, LpipsNet};
use refnpr::eval::stylization::{self as evaluation, SurfaceRender, Tolerance};
use refnpr::scene::camera::{Camera, Intrinsics, look_at};
use refnpr::util::image::Image;
use refnpr::util::tensor::floats;
use refnpr::vgg::{FeatureMaps, Vgg16, VggLayer};

#[test]
fn masked_psnr_matches_hand_value() {
    // Two pixels differ by 0.1 in every channel, one by 0.5 but masked out.
    let a = vec![0.2, 0.2, 0.2, 0.5, 0.5, 0.5, 0.0, 0.0, 0.0];
    let b = vec![0.3, 0.3, 0.3, 0.4, 0.4, 0.4, 0.5, 0.5, 0.5];
    let (sum, n) = evaluation::psnr_masked(&a, &b, &[true, true, false]).expect("masked pixels");
    assert_eq!(n, 6);
    let psnr = refnpr::util::metrics::psnr_from_mse((sum / n as f64) as f32);
    assert!((psnr - 20.0).abs() < 1e-3, "{psnr}");
    assert!(evaluation::psnr_masked(&a, &b, &[false; 3]).is_none());
}

#[test]
fn normalised_feature_distance_matches_hand_value() {
    let d = common::device();
    // One layer, 2 channels, 1x2 positions: a = (1,0), (0,2); b = (0,1), (0,3).
    // Unit vectors: a = (1,0), (0,1); b = (0,1), (0,1): squared distances 2 and 0, mean 1.
    let a = floats(vec![1.0, 0.0, 0.0, 2.0], [1, 2, 1, 2], &d);
    let b = floats(vec![0.0, 0.0, 1.0, 3.0], [1, 2, 1, 2], &d);
    let fa = FeatureMaps::from_maps([(VggLayer::Relu1_2, a.clone())]);
    let fb = FeatureMaps::from_maps([(VggLayer::Relu1_2, b)]);
    let v = evaluation::normalised_feature_distance(&fa, &fb, &[VggLayer::Relu1_2]);
    assert!((v - 1.0).abs() < 1e-5, "{v}");
    let same = evaluation::normalised_feature_distance(
        &fa,
        &FeatureMaps::from_maps([(VggLayer::Relu1_2, a)]),
        &[VggLayer::Relu1_2],
    );
    assert!(same.abs() < 1e-6, "{same}");
}

#[test]
fn perceptual_distance_is_zero_for_the_same_image_and_grows_with_change() {
    let d = common::device();
    let vgg = Vgg16::load(&d);
    let (w, h) = (40, 36);
    let img = |shift: f32| Image {
        width: w,
        height: h,
        rgb: (0..w * h * 3).map(|i| (((i / 3) % w) as f32 / w as f32 + shift * ((i % 3) as f32)).fract()).collect(),
    };
    let a = img(0.0);
    let zero = evaluation::perceptual_distance(&vgg, &a, &a, &d).unwrap();
    let small = evaluation::perceptual_distance(&vgg, &a, &img(0.05), &d).unwrap();
    let large = evaluation::perceptual_distance(&vgg, &a, &img(0.4), &d).unwrap();
    assert!(zero.abs() < 1e-5, "{zero}");
    assert!(small > 1e-3 && large > small, "{small} {large}");
}

/// A square camera at `eye` looking at the origin.
fn camera(eye: Vec3, size: u32) -> Camera {
    Camera::new(Intrinsics::from_fov_x(size, size, 0.9), look_at(eye, Vec3::ZERO, Vec3::Y))
}

/// What `camera` sees of the plane z = 0 (the scene), coloured by `colour(point)`.
fn plane_view(camera: Camera, colour: &dyn Fn(Vec3) -> [f32; 3]) -> SurfaceRender {
    let rays = camera.rays(None);
    let points: Vec<Option<Vec3>> = rays
        .iter()
        .map(|r| {
            let t = -r.origin.z / r.dir.z;
            (t > 0.0).then(|| r.origin + t * r.dir)
        })
        .collect();
    let rgb = points.iter().flat_map(|p| p.map(colour).unwrap_or([1.0; 3])).collect();
    SurfaceRender { camera, image: camera.image_of(rgb), points }
}

const TOL: Tolerance = Tolerance { absolute: 0.05, relative: 0.0 };

#[test]
fn visibility_and_warping_follow_the_geometry() {
    let reference = plane_view(camera(Vec3::new(0.0, 0.0, 3.0), 24), &|_| [0.5; 3]);
    let on_plane = Some(Vec3::new(0.2, -0.1, 0.0));
    let behind_plane = Some(Vec3::new(0.2, -0.1, -0.5));
    let outside = Some(Vec3::new(30.0, 0.0, 0.0));
    let seen =
        evaluation::visible_from(&[on_plane, behind_plane, outside, None], std::slice::from_ref(&reference), TOL);
    assert_eq!(seen, vec![true, false, false, false]);

    // A view-independent texture warps without error between two views of the plane ...
    let texture = |p: Vec3| [(p.x * 3.0).sin() * 0.5 + 0.5, (p.y * 5.0).cos() * 0.5 + 0.5, 0.3];
    let a = plane_view(camera(Vec3::new(0.3, 0.1, 3.0), 32), &texture);
    let b = plane_view(camera(Vec3::new(-0.2, 0.3, 2.8), 32), &texture);
    let (sum, n) = evaluation::warp_error(&a, &b, TOL);
    assert!(n > 500, "{n}");
    // (nearest-pixel lookup: a small residual from rounding only)
    assert!(sum / (3 * n) as f64 <= 2e-3, "{}", sum / (3 * n) as f64);
    // ... and with a known error when one view's colours are offset by 0.2.
    let shifted = plane_view(b.camera, &|p| texture(p).map(|c| c + 0.2));
    let (sum2, n2) = evaluation::warp_error(&a, &shifted, TOL);
    assert_eq!(n, n2);
    let rmse = (sum2 / (3 * n2) as f64).sqrt();
    assert!((rmse - 0.2).abs() < 0.03, "{rmse}");
}

#[test]
fn nearest_cameras_are_sorted_by_distance() {
    let cams: Vec<Camera> = [5.0f32, 1.0, 3.0, 2.0]
        .iter()
        .map(|&x| Camera::new(Intrinsics::from_fov_x(8, 8, 0.9), Mat4::from_translation(Vec3::new(x, 0.0, 0.0))))
        .collect();
    let to = Camera::new(Intrinsics::from_fov_x(8, 8, 0.9), Mat4::from_translation(Vec3::new(0.0, 0.0, 0.0)));
    assert_eq!(evaluation::nearest_cameras(&cams, &to, 3), vec![1, 3, 2]);
}

#[test]
fn ndc_points_map_back_onto_their_world_ray() {
    use refnpr::scene::camera::{NdcParams, Ray, from_ndc, to_ndc};
    let p = NdcParams { width: 40.0, height: 30.0, focal: 35.0, near: 1.0 };
    let dir = Vec3::new(0.1, -0.05, -1.0).normalize();
    let ray = Ray { origin: Vec3::new(0.2, 0.1, 0.0), dir, view_dir: dir };
    let n = to_ndc(ray, &p);
    for t in [0.0f32, 0.3, 0.9, 1.5] {
        let w = from_ndc(n.origin + t * n.dir, &p).expect("in front of the far end");
        // On the world ray: w = origin + s * dir for some s >= 0.
        let s = (w - ray.origin).dot(dir);
        assert!((ray.origin + s * dir - w).length() < 1e-3 * (1.0 + s), "t {t}: {w:?} is off the ray");
        assert!(s > 0.0);
        // NDC z = -1 is the near plane z = -near.
        if t == 0.0 {
            assert!((w.z + p.near).abs() < 1e-4, "{w:?}");
        }
    }
}

/// The fixture pair (tests/fixtures/lpips, made by models/make_lpips_fixtures.py)
/// and the distances the numpy reference (scripts/lpips_reference.py) gives it.
fn lpips_fixture() -> (Image, Image, serde_json::Value) {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/lpips");
    let read = |name: &str| {
        let (w, h, rgb) = refnpr::scene::data::read_rgb(&dir.join(name), [1.0; 3], 1).expect("fixture image");
        Image::new(w as usize, h as usize, rgb)
    };
    let values = serde_json::from_str(&std::fs::read_to_string(dir.join("distances.json")).expect("fixture values"))
        .expect("fixture JSON");
    (read("a.png"), read("b.png"), values)
}

#[test]
fn lpips_matches_the_numpy_reference_and_is_zero_on_the_same_image() {
    let d = common::device();
    let (a, b, expected) = lpips_fixture();
    for (net, key) in [(LpipsNet::Vgg, "vgg"), (LpipsNet::Alex, "alex")] {
        let lpips = Lpips::load(net, &d);
        let got = lpips.distance(&a, &b).unwrap();
        let want = expected[key].as_f64().expect("a distance") as f32;
        assert!((got - want).abs() < common::tol(1e-4), "{key}: LPIPS {got} against the numpy reference's {want}");
        let same = lpips.distance(&a, &a).unwrap();
        assert!(same.abs() < 1e-6, "{key}: LPIPS of an image with itself {same}");
        // Symmetric, as LPIPS is.
        let back = lpips.distance(&b, &a).unwrap();
        assert!((back - got).abs() < 1e-5, "{key}: {back} against {got}");
    }
}

#[test]
fn lpips_refuses_images_of_different_or_too_small_sizes() {
    let d = common::device();
    let lpips = Lpips::load(LpipsNet::Alex, &d);
    let grey = |w: usize, h: usize| Image::new(w, h, vec![0.5; w * h * 3]);
    let err = lpips.distance(&grey(40, 40), &grey(40, 48)).unwrap_err().to_string();
    assert!(err.contains("40x40") && err.contains("40x48"), "{err}");
    let err = lpips.distance(&grey(16, 40), &grey(16, 40)).unwrap_err().to_string();
    assert!(err.contains("at least 32x32"), "{err}");
}
