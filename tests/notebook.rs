//! The notebook API (`refnpr::notebook`): what a cell shows, and the
//! pipeline's stages called the way the notebooks call them.

mod common;

use common::TempDir;
use refnpr::BackendKind;
use refnpr::notebook::display::{content_block, png_bytes};
use refnpr::notebook::*;
use refnpr::reference::r3::RegisterParams;
use refnpr::scene::data::{LoadOptions, Split};
use refnpr::util::image::Image;

fn ramp(w: usize, h: usize, level: f32) -> Image {
    let rgb = (0..w * h).flat_map(|i| [level, i as f32 / (w * h) as f32, 0.5]).collect();
    Image::new(w, h, rgb)
}

#[test]
fn what_a_cell_shows_is_an_evcxr_content_block() {
    let block = content_block("image/png", "QUJD");
    assert_eq!(block, "EVCXR_BEGIN_CONTENT image/png\nQUJD\nEVCXR_END_CONTENT\n");

    let img = ramp(5, 3, 0.25);
    let decoded = image::load_from_memory(&png_bytes(&img)).unwrap().to_rgb8();
    assert_eq!((decoded.width(), decoded.height()), (5, 3));
    assert_eq!(decoded.get_pixel(4, 2).0, img.to_rgb8().get_pixel(4, 2).0);

    let big = img.enlarged(3);
    assert_eq!((big.width, big.height), (15, 9));
    assert_eq!(&big.rgb[(8 * 15 + 14) * 3..(8 * 15 + 14) * 3 + 3], &img.rgb[(2 * 5 + 4) * 3..(2 * 5 + 4) * 3 + 3]);
}

#[test]
fn a_gallery_lays_its_images_out_row_by_row_with_captions() {
    let items =
        vec![("a".to_string(), ramp(4, 2, 0.0)), ("b".to_string(), ramp(3, 5, 0.5)), ("c".into(), ramp(2, 2, 1.0))];
    let g = Gallery::new(items).with_columns(2);
    let sheet = g.sheet();
    // Row 1: 4 + gap + 3 wide, 5 tall; row 2: the third image; 4-pixel gaps.
    assert_eq!((sheet.width, sheet.height), (4 + 4 + 3, 5 + 4 + 2));
    let at = |x: usize, y: usize| &sheet.rgb[(y * sheet.width + x) * 3..(y * sheet.width + x) * 3 + 3];
    assert_eq!(at(0, 0)[0], 0.0, "the first image at the top left");
    assert_eq!(at(8, 0)[0], 0.5, "the second after the gap");
    assert_eq!(at(5, 0), &[1.0, 1.0, 1.0], "the gap is white");
    assert_eq!(at(0, 9)[0], 1.0, "the third starts the second row");
    assert_eq!(g.captions(), "a | b\nc");
}

#[test]
fn plots_are_svg_with_their_series_and_tables_escape_html() {
    let series =
        [Series::new("loss <a>", vec![(0.0, 1.0), (1.0, 0.1), (2.0, 0.01)]), Series::new("other", vec![(0.0, 0.5)])];
    let plot = Plot::lines("curve", "step", "MSE", &series, true).unwrap();
    assert!(plot.svg.starts_with("<svg"), "{}", &plot.svg[..40.min(plot.svg.len())]);
    assert!(plot.svg.contains("curve") && plot.svg.contains("other"));
    assert!(plot.svg.contains("<polyline") || plot.svg.contains("<path"), "the lines are drawn");
    // A log plot of nothing positive has nothing to draw: an error, not an empty picture.
    assert!(Plot::lines("empty", "x", "y", &[Series::new("zeros", vec![(0.0, 0.0)])], true).is_err());

    let t = Table::new(&["run", "dB"]).row(vec!["<b>".into(), "17.5".into()]);
    assert!(t.html().contains("<td>&lt;b&gt;</td><td>17.5</td>"));
    assert_eq!(t.to_string(), "run  dB\n<b>  17.5\n");
}

#[test]
fn a_difference_measures_and_pictures_two_renders() {
    let a = ramp(4, 4, 0.2);
    let mut b = a.clone();
    b.rgb[0] += 0.1;
    let d = difference(&a, &b, 5.0).unwrap();
    assert!((d.max_abs - 0.1).abs() < 1e-6);
    assert_eq!(d.pixels_over_one_level, 1);
    assert!((d.picture.rgb[0] - 0.5).abs() < 1e-6, "the picture is |a - b| times the gain");
    assert_eq!(difference(&a, &a, 5.0).unwrap().max_abs, 0.0);
    let err = difference(&a, &ramp(3, 4, 0.2), 1.0).unwrap_err().to_string();
    assert!(err.contains("4x4 and 3x4"), "{err}");
}

/// A typo in a notebook gets the CLI's message, causes included.
#[test]
fn notebook_errors_name_the_file_and_the_key() {
    let err = Scene::load("no/such/scene").err().expect("a missing folder is an error").to_string();
    assert!(err.starts_with("error: ") && err.contains("no/such/scene"), "{err}");
    assert_eq!(error_text(Scene::load("no/such/scene")).0, Some(err));
    assert_eq!(error_text(Ok(1)).0, None);

    let t = TempDir::new("nb-typo");
    let scene = Scene::procedural(t.path().join("scene"), 16).unwrap();
    let err = train_config(&scene.default_config(), "[optim]\nstepz = 10\n").err().unwrap().to_string();
    assert!(err.contains("stepz") && err.contains("the notebook's config"), "{err}");
    let (_, style) = demo_configs().unwrap();
    let err = stylize_config(&style, "[schedule]\nimage_epoch = 1\n").err().unwrap().to_string();
    assert!(err.contains("image_epoch"), "{err}");
    let err = scene.camera("train:99").err().unwrap().to_string();
    assert!(err.contains("train:99") && err.contains("48 train views"), "{err}");
    let err = scene.photos(Split::Test, &[0, 8]).err().unwrap().to_string();
    assert!(err.contains("8 is out of range"), "{err}");
}

/// The stages as the notebooks chain them: scene, fit (loaded, not fitted,
/// the second time), renders, the twin and painted references, R³.
#[test]
fn the_notebook_stages_chain_like_the_cli() {
    let t = TempDir::new("nb-stages");
    let backend = common::backend();
    let scene = Scene::procedural(t.path().join("scene"), 24).unwrap();
    assert_eq!(scene.summary().rows[0][4], "24x24");

    // The procedural truth of a camera is the photo of that camera.
    let cam = scene.camera("train:3").unwrap();
    let truth = scene.truth(&cam, false).unwrap();
    let photo_rgb = &scene.dataset.train[3].rgb;
    let psnr = refnpr::util::metrics::psnr(&truth.rgb, photo_rgb);
    assert!(psnr > 40.0, "truth vs the written photo: {psnr:.1} dB (8-bit rounding only)");
    assert!(
        scene.stylized_twin().unwrap().truth(&cam, true).is_err(),
        "the twin folder alone is not the procedural scene"
    );

    let config = train_config(&common::quick_blender_config(16, 24, 20, 40, 1024), "").unwrap();
    let out = t.path().join("photo");
    let photo = Photo::fit(&scene, config.clone(), &out, backend).unwrap();
    let metrics = photo.metrics.as_ref().expect("metrics.json was read");
    assert_eq!(metrics.loss_curve.len(), 40);
    assert!(metrics.loss_curve.iter().all(|p| p.mse.is_finite()));
    assert!(photo.loss_curve().unwrap().svg.contains("training batch"));
    let again = Photo::fit_or_load(&scene, config.clone(), &out, backend).unwrap();
    assert_eq!(again.metrics.as_ref().unwrap().train_seconds, metrics.train_seconds, "loaded, not fitted again");
    let mut other = config.clone();
    other.optim.steps = 30;
    let refit = Photo::fit_or_load(&scene, other, t.path().join("photo30"), backend).unwrap();
    assert_eq!(refit.metrics.as_ref().unwrap().steps, 30);
    // A run whose grid followed the images (more steps than written) is loaded again too.
    let mut follows = train_config(&common::quick_blender_config(8, 12, 10, 20, 1024), "").unwrap();
    follows.grid.voxels_per_pixel = 0.9;
    let grown = Photo::fit_or_load(&scene, follows.clone(), t.path().join("grown"), backend).unwrap();
    let grown_metrics = grown.metrics.as_ref().unwrap();
    assert!(grown_metrics.steps > 20, "{} steps: the grid did not follow the images", grown_metrics.steps);
    let again = Photo::fit_or_load(&scene, follows, t.path().join("grown"), backend).unwrap();
    assert_eq!(again.metrics.as_ref().unwrap().train_seconds, grown_metrics.train_seconds, "loaded, not fitted again");

    // A scene loaded at half size is fitted, and reloaded, at half size.
    let half = Scene::load_with(&scene.dir, &LoadOptions { downscale: 2, ..LoadOptions::default() }).unwrap();
    let small = Photo::fit(&half, config.clone(), t.path().join("half"), backend).unwrap();
    assert_eq!(small.dataset.test[0].camera.intrinsics.width, 12);
    assert_eq!(small.render_view("test:0").unwrap().width, 12);

    let render = photo.render_view("test:1").unwrap();
    assert_eq!((render.width, render.height), (24, 24));
    let views = photo.test_views(&[0, 1]).unwrap();
    assert_eq!(views.items.len(), 4);
    let path = photo.render_path(6, t.path().join("orbit")).unwrap();
    assert_eq!(path.items.len(), 6);
    assert!(t.path().join("orbit/path.gif").exists());

    let twin = Reference::twin(&scene, 0, t.path().join("case")).unwrap();
    assert_eq!(twin.beside_content(&photo).unwrap().items.len(), 2);
    let painted = Reference::painted(&photo, "train:0", t.path().join("painted"), 3).unwrap();
    let style = &painted.styles().unwrap().items[0].1;
    assert_eq!((style.width, style.height), (24, 24));

    let reg = Registered::run(&photo, &twin, &RegisterParams::default(), t.path().join("r3")).unwrap();
    assert!(reg.report.registered_pixels > 0);
    assert_eq!(reg.overlays(&photo, &[0, 5]).unwrap().items.len(), 2);
    let best = reg.most_covered(3);
    let shares = &reg.report.fraction_per_view;
    assert_eq!(best.len(), 3);
    assert!(shares[best[0]] >= shares[best[1]] && shares[best[1]] >= shares[best[2]], "{best:?} {shares:?}");
    assert!(shares.iter().enumerate().all(|(i, s)| best.contains(&i) || s <= &shares[best[2]]), "{best:?} {shares:?}");
    assert!(reg.coverage().unwrap().svg.contains("registered"));
    assert_eq!(reg.figures().rows.len(), 1);
}

/// The whole pipeline - scene, fit, twin reference, R³, Ref-NPR for one
/// epoch, a render, the evaluation against the stylized twin - on this
/// backend and on a CPU one (flex; ndarray when this one is flex) with the
/// same configs. The test command runs it on wgpu too, whose steps go
/// through the Burn graph (cut into runs where a step's samples exceed one
/// of the adapter's buffers) while the CPU backends take the fused
/// plain-Rust kernels: both must land in the same place.
#[test]
fn the_whole_pipeline_on_this_backend_lands_where_a_cpu_backends_does() {
    let t = TempDir::new("nb-pipeline");
    let here = common::backend();
    let cpu = if here == BackendKind::Flex { BackendKind::Ndarray } else { BackendKind::Flex };
    let scene = Scene::procedural(t.path().join("scene"), 32).unwrap();
    let truth = scene.stylized_twin().unwrap();
    let twin = Reference::twin(&scene, 0, t.path().join("case")).unwrap();
    let train = train_config(&common::quick_blender_config(16, 24, 20, 80, 1024), "").unwrap();
    let style = stylize_config(
        &Default::default(),
        "[schedule]\nimage_epochs = 1\nray_epochs = 1.0\n[loss]\nreference_rays = 2048\nregistered_rays = 2048\n",
    )
    .unwrap();
    let run = |backend: BackendKind| {
        let out = t.path().join(backend.to_string());
        let started = std::time::Instant::now();
        let photo = Photo::fit(&scene, train.clone(), out.join("photo"), backend).unwrap();
        Registered::run(&photo, &twin, &RegisterParams::default(), out.join("r3")).unwrap();
        let stylized = Stylized::run(&photo, &twin, refnpr::Method::RefNpr, style.clone(), out.join("style")).unwrap();
        let eval = stylized.evaluate(&twin, Some(&truth)).unwrap();
        let camera = scene.camera("test:1").unwrap();
        let image = (stylized.render(&camera), photo.render(&camera));
        let psnr = photo.metrics.as_ref().unwrap().test_psnr;
        println!(
            "{backend}: photo {psnr:.2} dB, stylized vs truth {:.2} dB, Ref-LPIPS {:.4}, {:.0} s",
            eval.gt_psnr.unwrap(),
            eval.ref_lpips,
            started.elapsed().as_secs_f64()
        );
        (psnr, eval, image)
    };
    let ((psnr, eval, image), (cpu_psnr, cpu_eval, cpu_image)) = (run(here), run(cpu));
    assert!(cpu_psnr > 20.0 && cpu_eval.gt_psnr.unwrap() > 12.0, "the CPU's run itself: {cpu_psnr} dB");
    assert!((psnr - cpu_psnr).abs() <= 0.5, "photo: {psnr:.2} vs {cpu_psnr:.2} dB");
    let (gt, cpu_gt) = (eval.gt_psnr.unwrap(), cpu_eval.gt_psnr.unwrap());
    assert!((gt - cpu_gt).abs() <= 0.5, "stylized vs truth: {gt:.2} vs {cpu_gt:.2} dB");
    // Ref-LPIPS follows the run's path more than the two PSNRs above: three
    // wgpu variants differing only in the order of float sums (the TV
    // gradient in the graph or a kernel; picks gathered or rendered over the
    // whole lists) measured 2.56, 2.65 and 2.65 against flex's 2.42 in the
    // uncalibrated form, which the bound below was set on (the calibrated
    // metric itself is checked on every backend by tests/evaluation.rs).
    let (lpips, cpu_lpips) = (eval.ref_lpips_uncalibrated, cpu_eval.ref_lpips_uncalibrated);
    let lpips_gap = (lpips - cpu_lpips).abs() / cpu_lpips;
    assert!(lpips_gap <= 0.12, "uncalibrated Ref-LPIPS {lpips:.4} vs {cpu_lpips:.4}");
    // Pixel by pixel the two runs part (the graph sums in another order, and
    // RMSprop divides near-cancelled gradients by their own size: on wgpu
    // this render measured 21.8 dB from flex's, 19.5 dB from the photo), so
    // the runs are compared through the truth and the reference above; the
    // distance is printed.
    let psnr = refnpr::util::metrics::psnr;
    let (between, moved) = (psnr(&image.0.rgb, &cpu_image.0.rgb), psnr(&cpu_image.0.rgb, &cpu_image.1.rgb));
    println!(
        "stylized test:1, this backend vs the CPU's: {between:.1} dB; the CPU's stylized vs its photo: {moved:.1} dB"
    );
}

/// A backend left out of the build is refused, naming the feature.
#[test]
fn every_backend_of_this_build_opens_or_names_its_feature() {
    for b in BackendKind::ALL {
        if b.is_compiled() {
            continue;
        }
        let err = b.open(&refnpr::Quiet).unwrap_err().to_string();
        assert!(err.contains(&format!("feature `{b}`")), "{err}");
    }
    assert!(BackendKind::Flex.is_compiled() || BackendKind::Ndarray.is_compiled() || BackendKind::Wgpu.is_compiled());
}
