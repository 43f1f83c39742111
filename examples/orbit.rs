//! From nothing to a stylized orbit through refnpr's front API alone: the
//! built-in procedural scene, a photoreal fit, the scene's stylized twin as
//! the painted reference, a Ref-NPR stylization, and an orbit GIF of the
//! result.
//!
//!     cargo run --example orbit -- OUT [SIZE]
//!
//! SIZE is the views' side in pixels (default 64: about a minute on two
//! CPU cores; the demo's schedule and 128 pixels give a sharper result).
//! The test command builds and runs it.

use std::path::PathBuf;

use refnpr::{BackendKind, Method, Photo, Reference, Scene, Stylized};

fn main() -> Result<(), refnpr::Error> {
    let mut args = std::env::args().skip(1);
    let out = PathBuf::from(args.next().unwrap_or_else(|| "orbit-out".into()));
    let size: u32 = match args.next() {
        Some(s) => s.parse().map_err(|e| anyhow::anyhow!("SIZE must be a whole number of pixels, not {s:?}: {e}"))?,
        None => 64,
    };
    let backend = BackendKind::from_env()?;

    let scene = Scene::procedural(out.join("scene"), size)?;
    println!("scene: {} training views of {size}x{size}", scene.dataset.train.len());

    // The demo's configs, on a shorter schedule.
    let (mut fit, mut style) = refnpr::demo_configs()?;
    fit.optim.steps = 300;
    fit.grid.upsample_steps = vec![150];
    fit.checkpoint_every = fit.optim.steps;
    let photo = Photo::fit(&scene, fit, out.join("photo"), backend)?;
    let psnr = photo.metrics.as_ref().map_or(f32::NAN, |m| m.test_psnr);
    println!("photoreal fit: {psnr:.2} dB on the test views");

    let reference = Reference::twin(&scene, 0, out.join("case"))?;
    style.schedule.image_epochs = 2;
    let stylized = Stylized::run(&photo, &reference, Method::RefNpr, style, out.join("stylized"))?;
    println!(
        "stylized: {} views, {:.0} % of their pixels registered by R³, {:.0} s",
        stylized.report.views,
        100.0 * stylized.report.registered_fraction,
        stylized.report.total_seconds
    );

    let (orbit, frames) = (out.join("orbit"), 24);
    stylized.render_path(frames, &orbit)?;
    println!("orbit: {frames} frames in {}", orbit.join("path.gif").display());
    let eval = stylized.evaluate(&reference, Some(&scene))?;
    println!(
        "against the stylized twin: {:.2} dB over all pixels, {:.2} dB where the reference does not see",
        eval.gt_psnr.unwrap_or(f32::NAN),
        eval.gt_psnr_occluded.unwrap_or(f32::NAN)
    );
    Ok(())
}
