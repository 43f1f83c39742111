//! A camera path as an MP4 (H.264, yuv420p: what players, browsers and
//! video sites accept) through `ffmpeg`, fed raw frames on its stdin.

use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};

use anyhow::{Context, Result, bail};

use crate::util::image::Image;

/// How `ffmpeg` is installed, for the error when it is missing.
pub const FFMPEG_INSTALL: &str = "install ffmpeg (Debian/Ubuntu: `sudo apt install ffmpeg`; macOS: `brew install ffmpeg`; Windows: `winget install ffmpeg`)";

/// Whether `exe` runs (`ffmpeg -version`).
pub fn ffmpeg_available(exe: &str) -> bool {
    Command::new(exe).arg("-version").stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok_and(|s| s.success())
}

/// Encodes `frames` (all one size) at `fps` into `out`, atomically: ffmpeg
/// writes a temporary file beside it, renamed over `out` once complete.
/// Odd sizes are padded by one pixel (yuv420p needs even sides).
pub fn write_mp4(frames: &[Image], fps: u32, out: &Path, exe: &str) -> Result<()> {
    let Some(first) = frames.first() else { bail!("no frames to encode") };
    if frames.iter().any(|f| (f.width, f.height) != (first.width, first.height)) {
        bail!("the frames differ in size; a video needs one size");
    }
    if !ffmpeg_available(exe) {
        bail!(
            "`{exe}` is not available to encode {}: {FFMPEG_INSTALL}; or use the PNG frames of `refnpr render`",
            out.display()
        );
    }
    let dir = out.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    crate::util::files::create_dir(dir)?;
    let name = out.file_name().context("the output names no file")?.to_string_lossy();
    let tmp = dir.join(format!(".{name}.partial"));
    let mut child = Command::new(exe)
        .args(["-hide_banner", "-loglevel", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s"])
        .arg(format!("{}x{}", first.width, first.height))
        .args(["-r", &fps.to_string(), "-i", "-", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2"])
        .args(["-c:v", "libx264", "-pix_fmt", "yuv420p", "-crf", "18", "-movflags", "+faststart", "-f", "mp4"])
        .arg(&tmp)
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .with_context(|| format!("starting `{exe}`"))?;
    let fed = (|| -> std::io::Result<()> {
        let mut stdin = child.stdin.take().expect("piped stdin");
        for f in frames {
            stdin.write_all(&f.to_rgb8())?;
        }
        Ok(())
    })();
    let output = child.wait_with_output()?;
    if fed.is_err() || !output.status.success() {
        let _ = std::fs::remove_file(&tmp);
        bail!("ffmpeg failed to encode {}: {}", out.display(), String::from_utf8_lossy(&output.stderr).trim());
    }
    std::fs::rename(&tmp, out).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        crate::util::files::io_error(e, out)
    })
}
