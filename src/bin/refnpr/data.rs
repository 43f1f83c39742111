//! Data in: `refnpr scene` (the built-in procedural scene) and `refnpr
//! capture` (photos to a dataset through COLMAP).

use std::path::PathBuf;

use anyhow::Result;
use refnpr::Console;
use refnpr::scene::data::procedural;
use refnpr::tools::capture;

// `refnpr scene`'s arguments.
#[derive(clap::Args)]
pub struct SceneArgs {
    /// The folder to write (train it with `refnpr train --data OUT`).
    #[arg(long)]
    pub out: PathBuf,
    /// Seed of the scene's random layout and textures.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Square image size in pixels.
    #[arg(long, default_value_t = 96)]
    pub size: u32,
    /// Surround the scene with a textured far environment (a 360° capture of an object in a room)
    /// instead of an empty background; fit it with a far background: `refnpr train --config
    /// configs/far_background.toml` (`[grid] far_background = "on"`).
    #[arg(long)]
    pub environment: bool,
}

/// `refnpr scene`.
pub fn scene(args: SceneArgs) -> Result<()> {
    let SceneArgs { out, seed, size, environment } = args;
    procedural::write_scene(&out, &procedural::SceneOptions { seed, size, environment, ..Default::default() })?;
    println!("wrote the procedural scene to {}", out.display());
    Ok(())
}

// `refnpr capture`'s arguments.
#[derive(clap::Args)]
pub struct CaptureArgs {
    /// The folder of photos (PNG or JPEG, 20-100 of one scene).
    pub photos: PathBuf,
    /// The dataset folder to write (COLMAP's log: OUT/colmap.log).
    #[arg(long)]
    pub out: PathBuf,
    /// Photos are downsized to this long side first (pixels; a 12-megapixel phone photo,
    /// 4032x3024, becomes 800x600).
    #[arg(long, alias = "max-size", default_value_t = capture::DEFAULT_MAX_SIDE)]
    pub max_side: u32,
    /// COLMAP's camera model (SIMPLE_RADIAL, RADIAL, OPENCV, PINHOLE, ...).
    #[arg(long, default_value = "SIMPLE_RADIAL")]
    pub camera_model: String,
    /// The photos come from several cameras or zoom settings (one camera each).
    #[arg(long)]
    pub several_cameras: bool,
    /// The COLMAP executable.
    #[arg(long, default_value = "colmap")]
    pub colmap: PathBuf,
    /// A dataset of the same photos with known poses: print the recovered
    /// poses' error against it (views matched by file name).
    #[arg(long)]
    pub truth: Option<PathBuf>,
}

/// `refnpr capture`: the dataset, then what COLMAP recovered (and with
/// `--truth`, the poses' error against known ones).
pub fn capture(args: CaptureArgs, progress: &Console) -> Result<()> {
    let CaptureArgs { photos, out, max_side, camera_model, several_cameras, colmap, truth } = args;
    let opts = capture::CaptureOptions { max_side, camera_model, single_camera: !several_cameras, colmap };
    let r = capture::capture(&photos, &out, &opts, progress)?;
    println!(
        "registered {} of {} photos ({} points, {}x{}) in {:.0} s; wrote {} (train it: refnpr train --data {} --out RUN)",
        r.registered,
        r.photos,
        r.points,
        r.size.0,
        r.size.1,
        r.seconds,
        out.display(),
        out.display()
    );
    if let Some(truth) = truth {
        let e = capture::compare_poses(&out, &truth)?;
        println!("{}", serde_json::to_string(&e)?);
    }
    Ok(())
}
