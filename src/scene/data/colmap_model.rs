//! COLMAP sparse models, binary and text: `cameras`, `images`, `points3D`
//! as COLMAP's `mapper` and `image_undistorter` write them (the formats of
//! COLMAP's `src/colmap/scene/reconstruction_io.cc`, read from their
//! documented layout). Parsing only: turning a model into a dataset is
//! `data::colmap`.
//!
//! Every count read from a binary file is checked against the bytes left
//! before anything is allocated for it, so a corrupt file is refused with
//! a message instead of exhausting memory.

use anyhow::{Result, bail};
use glam::{DMat3, DQuat, DVec3};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use super::undistort::Lens;
use crate::util::input::InputError;

/// The camera models refnpr reads (COLMAP's model ids 0-4).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CameraModel {
    /// f, cx, cy
    SimplePinhole,
    /// fx, fy, cx, cy
    Pinhole,
    /// f, cx, cy, k
    SimpleRadial,
    /// f, cx, cy, k1, k2
    Radial,
    /// fx, fy, cx, cy, k1, k2, p1, p2
    Opencv,
}

/// COLMAP's names of its models, by id (ids 5-10 are refused).
const MODEL_NAMES: [&str; 11] = [
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
    "OPENCV_FISHEYE",
    "FULL_OPENCV",
    "FOV",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "THIN_PRISM_FISHEYE",
];

impl CameraModel {
    fn from_id(id: i32) -> std::result::Result<Self, String> {
        match id {
            0 => Ok(Self::SimplePinhole),
            1 => Ok(Self::Pinhole),
            2 => Ok(Self::SimpleRadial),
            3 => Ok(Self::Radial),
            4 => Ok(Self::Opencv),
            _ => Err(usize::try_from(id)
                .ok()
                .and_then(|i| MODEL_NAMES.get(i))
                .map_or(format!("id {id}"), |n| n.to_string())),
        }
    }

    fn from_name(name: &str) -> std::result::Result<Self, String> {
        match MODEL_NAMES.iter().position(|n| *n == name) {
            Some(i) => Self::from_id(i as i32),
            None => Err(name.to_string()),
        }
    }

    /// How many parameters the model has.
    pub fn num_params(self) -> usize {
        match self {
            Self::SimplePinhole => 3,
            Self::Pinhole | Self::SimpleRadial => 4,
            Self::Radial => 5,
            Self::Opencv => 8,
        }
    }
}

/// A COLMAP camera: its model, image size and parameters (in COLMAP's order).
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapCamera {
    pub model: CameraModel,
    pub width: u32,
    pub height: u32,
    pub params: Vec<f64>,
}

impl ColmapCamera {
    /// Its pinhole part and distortion.
    pub fn lens(&self) -> Lens {
        let p = &self.params;
        match self.model {
            CameraModel::SimplePinhole => Lens::pinhole(p[0], p[0], p[1], p[2]),
            CameraModel::Pinhole => Lens::pinhole(p[0], p[1], p[2], p[3]),
            CameraModel::SimpleRadial => Lens { k1: p[3], ..Lens::pinhole(p[0], p[0], p[1], p[2]) },
            CameraModel::Radial => Lens { k1: p[3], k2: p[4], ..Lens::pinhole(p[0], p[0], p[1], p[2]) },
            CameraModel::Opencv => {
                Lens { k1: p[4], k2: p[5], p1: p[6], p2: p[7], ..Lens::pinhole(p[0], p[1], p[2], p[3]) }
            }
        }
    }
}

/// A registered image: its world-to-camera pose (COLMAP / OpenCV camera
/// axes: x right, y down, z forward) and the 3D points it sees.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapImage {
    pub camera_id: u32,
    pub name: String,
    /// Rotation quaternion (w, x, y, z), world to camera.
    pub qvec: [f64; 4],
    pub tvec: [f64; 3],
    /// The ids of the 3D points it observes (unmatched keypoints left out).
    pub point_ids: Vec<u64>,
}

impl ColmapImage {
    /// World-to-camera rotation.
    pub fn rotation(&self) -> DMat3 {
        let [w, x, y, z] = self.qvec;
        DMat3::from_quat(DQuat::from_xyzw(x, y, z, w).normalize())
    }

    /// The camera centre in world coordinates.
    pub fn centre(&self) -> DVec3 {
        -(self.rotation().transpose() * DVec3::from(self.tvec))
    }
}

/// A sparse model: cameras by id, images sorted by name, points by id.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Model {
    pub cameras: HashMap<u32, ColmapCamera>,
    pub images: Vec<ColmapImage>,
    pub points: HashMap<u64, [f64; 3]>,
}

impl Model {
    /// A model from the texts of its three files.
    pub fn from_text(cameras: &str, images: &str, points: &str) -> std::result::Result<Model, String> {
        let mut images = images_txt(images)?;
        images.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(Model { cameras: cameras_txt(cameras)?, images, points: points_txt(points)? })
    }
}

/// Which of the two forms a model folder holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Form {
    Binary,
    Text,
}

/// The folder of a sparse model inside a dataset folder: `sparse/0/`,
/// `sparse/` (what `image_undistorter` writes) or the folder itself.
pub fn find_model(dir: &Path) -> Option<(PathBuf, Form)> {
    for d in [dir.join("sparse").join("0"), dir.join("sparse"), dir.to_path_buf()] {
        if d.join("cameras.bin").is_file() {
            return Some((d, Form::Binary));
        }
        if d.join("cameras.txt").is_file() {
            return Some((d, Form::Text));
        }
    }
    None
}

/// Reads the model in `dir` (binary when `cameras.bin` is there, else text)
/// and checks that every image's camera and every point id it names exist.
pub fn read(dir: &Path, form: Form) -> Result<Model> {
    let ext = if form == Form::Binary { "bin" } else { "txt" };
    let file = |name: &str| dir.join(format!("{name}.{ext}"));
    let load = |name: &str| -> Result<Vec<u8>> {
        let path = file(name);
        std::fs::read(&path).map_err(|e| {
            let message = format!("cannot read the COLMAP model file {}: {e}", path.display());
            InputError::Missing { path: path.clone(), message }.into()
        })
    };
    let refuse = |name: &str, message: String| -> anyhow::Error {
        let path = file(name);
        InputError::Malformed { message: format!("{}: {message}", path.display()), path }.into()
    };
    let (cameras, images, points) = match form {
        Form::Binary => (
            cameras_bin(&load("cameras")?).map_err(|m| refuse("cameras", m))?,
            images_bin(&load("images")?).map_err(|m| refuse("images", m))?,
            points_bin(&load("points3D")?).map_err(|m| refuse("points3D", m))?,
        ),
        Form::Text => (
            cameras_txt(&text(&load("cameras")?)).map_err(|m| refuse("cameras", m))?,
            images_txt(&text(&load("images")?)).map_err(|m| refuse("images", m))?,
            points_txt(&text(&load("points3D")?)).map_err(|m| refuse("points3D", m))?,
        ),
    };
    let mut model = Model { cameras, images, points };
    model.images.sort_by(|a, b| a.name.cmp(&b.name));
    for im in &model.images {
        if !model.cameras.contains_key(&im.camera_id) {
            bail!(refuse(
                "images",
                format!("image {} names camera {}, which cameras.{ext} lacks", im.name, im.camera_id)
            ));
        }
    }
    Ok(model)
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// A cursor over a binary model file (little-endian, as COLMAP writes).
struct Bytes<'a> {
    data: &'a [u8],
    at: usize,
}

type Parse<T> = std::result::Result<T, String>;

impl<'a> Bytes<'a> {
    fn take(&mut self, n: usize) -> Parse<&'a [u8]> {
        if self.data.len() - self.at < n {
            return Err(format!("cut short at byte {} (needed {n} more)", self.at));
        }
        let s = &self.data[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }
    fn u64(&mut self) -> Parse<u64> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes")))
    }
    fn i64(&mut self) -> Parse<i64> {
        Ok(i64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes")))
    }
    fn i32(&mut self) -> Parse<i32> {
        Ok(i32::from_le_bytes(self.take(4)?.try_into().expect("4 bytes")))
    }
    fn f64(&mut self) -> Parse<f64> {
        let v = f64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes"));
        if !v.is_finite() {
            return Err(format!("a NaN or infinite number at byte {}", self.at - 8));
        }
        Ok(v)
    }
    /// A count of records of at least `record` bytes each, checked against the bytes left.
    fn count(&mut self, record: usize, what: &str) -> Parse<usize> {
        let n = self.u64()?;
        let left = (self.data.len() - self.at) as u64;
        if n.saturating_mul(record as u64) > left {
            return Err(format!("claims {n} {what}, more than its remaining {left} bytes hold"));
        }
        Ok(n as usize)
    }
    fn done(&self) -> Parse<()> {
        if self.at != self.data.len() {
            return Err(format!("{} bytes left over after the last record", self.data.len() - self.at));
        }
        Ok(())
    }
}

fn camera_of(model: Parse<CameraModel>, width: u64, height: u64, params: Vec<f64>) -> Parse<ColmapCamera> {
    let model = model.map_err(|name| {
        format!(
            "camera model {name} is not supported (refnpr reads SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, \
             OPENCV); undistort the model first: colmap image_undistorter --image_path IMAGES --input_path MODEL \
             --output_path OUT --output_type COLMAP"
        )
    })?;
    let (width, height) = match (u32::try_from(width), u32::try_from(height)) {
        (Ok(w), Ok(h)) if (1..=65536).contains(&w) && (1..=65536).contains(&h) => (w, h),
        _ => return Err(format!("image size {width}x{height} is out of range")),
    };
    if params.len() != model.num_params() {
        return Err(format!("a {model:?} camera has {} parameters, found {}", model.num_params(), params.len()));
    }
    let cam = ColmapCamera { model, width, height, params };
    let lens = cam.lens();
    if !(lens.fx > 0.0 && lens.fy > 0.0) {
        return Err(format!("focal length {} x {} is not positive", lens.fx, lens.fy));
    }
    Ok(cam)
}

fn cameras_bin(data: &[u8]) -> Parse<HashMap<u32, ColmapCamera>> {
    let mut b = Bytes { data, at: 0 };
    let n = b.count(24, "cameras")?;
    let mut cameras = HashMap::with_capacity(n);
    for _ in 0..n {
        let id = b.i32()?;
        let model_id = b.i32()?;
        let (width, height) = (b.u64()?, b.u64()?);
        let model = CameraModel::from_id(model_id);
        // An unsupported model's parameter count is unknown to us: refuse it here.
        let num = model.clone().map_or(0, CameraModel::num_params);
        let params = (0..num).map(|_| b.f64()).collect::<Parse<Vec<f64>>>()?;
        let cam = camera_of(model, width, height, params).map_err(|m| format!("camera {id}: {m}"))?;
        cameras.insert(id as u32, cam);
    }
    b.done()?;
    Ok(cameras)
}

fn pose_checked(qvec: [f64; 4], name: &str) -> Parse<[f64; 4]> {
    let norm = qvec.iter().map(|v| v * v).sum::<f64>().sqrt();
    if norm.is_nan() || norm <= 1e-6 {
        return Err(format!("image {name}: its rotation quaternion is zero"));
    }
    Ok(qvec)
}

fn images_bin(data: &[u8]) -> Parse<Vec<ColmapImage>> {
    let mut b = Bytes { data, at: 0 };
    // id, qvec, tvec, camera id, a name of at least its NUL, the point count.
    let n = b.count(4 + 56 + 4 + 1 + 8, "images")?;
    let mut images = Vec::with_capacity(n);
    for _ in 0..n {
        let _id = b.i32()?;
        let qvec = [b.f64()?, b.f64()?, b.f64()?, b.f64()?];
        let tvec = [b.f64()?, b.f64()?, b.f64()?];
        let camera_id = b.i32()? as u32;
        let rest = &b.data[b.at..];
        let len = rest.iter().position(|&c| c == 0).ok_or("an image name without its terminating NUL")?;
        let name = String::from_utf8_lossy(b.take(len)?).into_owned();
        b.take(1)?;
        let num = b.count(24, "keypoints")?;
        let mut point_ids = Vec::new();
        for _ in 0..num {
            let (_x, _y) = (b.take(8)?, b.take(8)?);
            let id = b.i64()?;
            if id >= 0 {
                point_ids.push(id as u64);
            }
        }
        images.push(ColmapImage { camera_id, qvec: pose_checked(qvec, &name)?, tvec, name, point_ids });
    }
    b.done()?;
    Ok(images)
}

fn points_bin(data: &[u8]) -> Parse<HashMap<u64, [f64; 3]>> {
    let mut b = Bytes { data, at: 0 };
    let n = b.count(8 + 24 + 3 + 8 + 8, "points")?;
    let mut points = HashMap::with_capacity(n);
    for _ in 0..n {
        let id = b.u64()?;
        let xyz = [b.f64()?, b.f64()?, b.f64()?];
        let _rgb = b.take(3)?;
        let _error = b.take(8)?;
        let track = b.count(8, "track entries")?;
        b.take(track * 8)?;
        points.insert(id, xyz);
    }
    b.done()?;
    Ok(points)
}

/// The lines of a text model that are not comments, with their line numbers.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())).filter(|(_, l)| !l.starts_with('#'))
}

fn number<T: std::str::FromStr>(tok: Option<&str>, line: usize, what: &str) -> Parse<T> {
    let tok = tok.ok_or_else(|| format!("line {line}: {what} is missing"))?;
    tok.parse().map_err(|_| format!("line {line}: {what} '{tok}' is not a number of the right kind"))
}

fn finite(v: f64, line: usize) -> Parse<f64> {
    if v.is_finite() { Ok(v) } else { Err(format!("line {line}: a NaN or infinite number")) }
}

fn cameras_txt(text: &str) -> Parse<HashMap<u32, ColmapCamera>> {
    let mut cameras = HashMap::new();
    for (line, l) in data_lines(text).filter(|(_, l)| !l.is_empty()) {
        let mut t = l.split_whitespace();
        let id: u32 = number(t.next(), line, "the camera id")?;
        let model = CameraModel::from_name(t.next().ok_or(format!("line {line}: the camera model is missing"))?);
        let width: u64 = number(t.next(), line, "the width")?;
        let height: u64 = number(t.next(), line, "the height")?;
        let params = t
            .map(|p| number::<f64>(Some(p), line, "a parameter").and_then(|v| finite(v, line)))
            .collect::<Parse<_>>()?;
        cameras.insert(id, camera_of(model, width, height, params).map_err(|m| format!("line {line}: {m}"))?);
    }
    Ok(cameras)
}

fn images_txt(text: &str) -> Parse<Vec<ColmapImage>> {
    let mut images = Vec::new();
    // Two lines per image; the second (its keypoints) may be empty.
    let mut lines = data_lines(text);
    while let Some((line, l)) = lines.next() {
        if l.is_empty() {
            continue;
        }
        let mut t = l.split_whitespace();
        let _id: u32 = number(t.next(), line, "the image id")?;
        let mut f = || number::<f64>(t.next(), line, "a pose value").and_then(|v| finite(v, line));
        let qvec = [f()?, f()?, f()?, f()?];
        let tvec = [f()?, f()?, f()?];
        let camera_id: u32 = number(t.next(), line, "the camera id")?;
        let name = t.collect::<Vec<_>>().join(" ");
        if name.is_empty() {
            return Err(format!("line {line}: the image name is missing"));
        }
        let mut point_ids = Vec::new();
        if let Some((line2, keypoints)) = lines.next() {
            let toks: Vec<&str> = keypoints.split_whitespace().collect();
            if !toks.len().is_multiple_of(3) {
                return Err(format!("line {line2}: keypoints come as X Y POINT3D_ID triples"));
            }
            for tri in toks.chunks(3) {
                let id: i64 = number(Some(tri[2]), line2, "a point id")?;
                if id >= 0 {
                    point_ids.push(id as u64);
                }
            }
        }
        images.push(ColmapImage { camera_id, qvec: pose_checked(qvec, &name)?, tvec, name, point_ids });
    }
    Ok(images)
}

fn points_txt(text: &str) -> Parse<HashMap<u64, [f64; 3]>> {
    let mut points = HashMap::new();
    for (line, l) in data_lines(text).filter(|(_, l)| !l.is_empty()) {
        let mut t = l.split_whitespace();
        let id: u64 = number(t.next(), line, "the point id")?;
        let mut f = || number::<f64>(t.next(), line, "a coordinate").and_then(|v| finite(v, line));
        points.insert(id, [f()?, f()?, f()?]);
    }
    Ok(points)
}

/// Parses the bytes of one model file by its name (`cameras.bin`,
/// `images.txt`, ...): what the fuzzer drives.
pub fn parse_file(name: &str, bytes: &[u8]) -> Parse<usize> {
    Ok(match name {
        "cameras.bin" => cameras_bin(bytes)?.len(),
        "images.bin" => images_bin(bytes)?.len(),
        "points3D.bin" => points_bin(bytes)?.len(),
        "cameras.txt" => cameras_txt(&text(bytes))?.len(),
        "images.txt" => images_txt(&text(bytes))?.len(),
        "points3D.txt" => points_txt(&text(bytes))?.len(),
        _ => return Err(format!("{name} is not a COLMAP model file")),
    })
}

/// Writes a model in the binary form (tests and fixtures; `capture` leaves
/// COLMAP's own files alone).
pub fn write_binary(model: &Model, dir: &Path) -> Result<()> {
    let mut cams = Vec::new();
    cams.extend((model.cameras.len() as u64).to_le_bytes());
    let mut ids: Vec<_> = model.cameras.keys().copied().collect();
    ids.sort();
    for id in ids {
        let c = &model.cameras[&id];
        let model_id = MODEL_NAMES.iter().position(|n| CameraModel::from_name(n) == Ok(c.model)).expect("known");
        cams.extend((id as i32).to_le_bytes());
        cams.extend((model_id as i32).to_le_bytes());
        cams.extend((c.width as u64).to_le_bytes());
        cams.extend((c.height as u64).to_le_bytes());
        c.params.iter().for_each(|p| cams.extend(p.to_le_bytes()));
    }
    let mut imgs = Vec::new();
    imgs.extend((model.images.len() as u64).to_le_bytes());
    for (i, im) in model.images.iter().enumerate() {
        imgs.extend((i as i32 + 1).to_le_bytes());
        im.qvec.iter().chain(&im.tvec).for_each(|v| imgs.extend(v.to_le_bytes()));
        imgs.extend((im.camera_id as i32).to_le_bytes());
        imgs.extend(im.name.as_bytes());
        imgs.push(0);
        imgs.extend((im.point_ids.len() as u64).to_le_bytes());
        for &p in &im.point_ids {
            imgs.extend(0f64.to_le_bytes());
            imgs.extend(0f64.to_le_bytes());
            imgs.extend((p as i64).to_le_bytes());
        }
    }
    let mut pts = Vec::new();
    pts.extend((model.points.len() as u64).to_le_bytes());
    let mut ids: Vec<_> = model.points.keys().copied().collect();
    ids.sort();
    for id in ids {
        pts.extend(id.to_le_bytes());
        model.points[&id].iter().for_each(|v| pts.extend(v.to_le_bytes()));
        pts.extend([128u8; 3]);
        pts.extend(0f64.to_le_bytes());
        pts.extend(0u64.to_le_bytes());
    }
    std::fs::create_dir_all(dir)?;
    std::fs::write(dir.join("cameras.bin"), cams)?;
    std::fs::write(dir.join("images.bin"), imgs)?;
    std::fs::write(dir.join("points3D.bin"), pts)?;
    Ok(())
}

/// Writes a model in the text form (Rust's shortest round-trip decimals,
/// so it reads back bit for bit; keypoint positions are written as 0).
pub fn write_text(model: &Model, dir: &Path) -> Result<()> {
    use std::fmt::Write;
    let mut cams = String::from("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    let mut ids: Vec<_> = model.cameras.keys().copied().collect();
    ids.sort();
    for id in ids {
        let c = &model.cameras[&id];
        let name = MODEL_NAMES.iter().find(|n| CameraModel::from_name(n) == Ok(c.model)).expect("known");
        let params: Vec<String> = c.params.iter().map(|p| p.to_string()).collect();
        writeln!(cams, "{id} {name} {} {} {}", c.width, c.height, params.join(" "))?;
    }
    let mut imgs =
        String::from("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n# POINTS2D[] as (X, Y, POINT3D_ID)\n");
    for (i, im) in model.images.iter().enumerate() {
        let pose: Vec<String> = im.qvec.iter().chain(&im.tvec).map(|v| v.to_string()).collect();
        writeln!(imgs, "{} {} {} {}", i + 1, pose.join(" "), im.camera_id, im.name)?;
        let points: Vec<String> = im.point_ids.iter().map(|p| format!("0 0 {p}")).collect();
        writeln!(imgs, "{}", points.join(" "))?;
    }
    let mut pts = String::from("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n");
    let mut ids: Vec<_> = model.points.keys().copied().collect();
    ids.sort();
    for id in ids {
        let [x, y, z] = model.points[&id];
        writeln!(pts, "{id} {x} {y} {z} 128 128 128 0")?;
    }
    std::fs::create_dir_all(dir)?;
    std::fs::write(dir.join("cameras.txt"), cams)?;
    std::fs::write(dir.join("images.txt"), imgs)?;
    std::fs::write(dir.join("points3D.txt"), pts)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_and_binary_forms_of_a_model_read_the_same() {
        let text_cams = "# comment\n1 OPENCV 40 30 50 51 20 15 0.01 -0.002 0.001 0.0005\n2 PINHOLE 40 30 45 45 20 15\n";
        let text_imgs = "# two lines each\n1 1 0 0 0 0.5 -0.25 2 1 a.png\n10 20 3 30 40 4 50 60 -1\n\
                         2 0.7071 0 0.7071 0 0 0 1 2 b c.png\n\n";
        let text_pts = "3 0.1 0.2 0.3 255 0 0 0.5 1 0 2 0\n4 -1 2 -3 0 0 0 0.1 1 1\n";
        let model = Model {
            cameras: cameras_txt(text_cams).unwrap(),
            images: images_txt(text_imgs).unwrap(),
            points: points_txt(text_pts).unwrap(),
        };
        assert_eq!(model.images.len(), 2);
        assert_eq!(model.images[0].point_ids, vec![3, 4]);
        assert_eq!(model.images[1].name, "b c.png");
        assert!(model.images[1].point_ids.is_empty());
        let dir = crate::test_support::temp_dir("colmap_forms");
        write_binary(&model, &dir).unwrap();
        let back = read(&dir, Form::Binary).unwrap();
        assert_eq!(back, model);
        write_text(&model, &dir).unwrap();
        assert_eq!(read(&dir, Form::Text).unwrap(), model);
    }

    #[test]
    fn a_camera_centre_follows_colmaps_world_to_camera_convention() {
        // A camera at (0, 0, -5) looking down +z: R = I, t = -R C = (0, 0, 5).
        let im = ColmapImage {
            camera_id: 1,
            name: "x".into(),
            qvec: [1.0, 0.0, 0.0, 0.0],
            tvec: [0.0, 0.0, 5.0],
            point_ids: vec![],
        };
        assert!((im.centre() - DVec3::new(0.0, 0.0, -5.0)).length() < 1e-12);
    }

    #[test]
    fn corrupt_files_are_refused_with_their_reason() {
        let err = cameras_txt("1 FULL_OPENCV 10 10 1 2 3 4 5 6 7 8 9 10 11 12\n").unwrap_err();
        assert!(err.contains("FULL_OPENCV") && err.contains("image_undistorter"), "{err}");
        assert!(cameras_txt("1 PINHOLE 10 10 1 2 3\n").unwrap_err().contains("4 parameters"));
        assert!(images_txt("1 0 0 0 0 1 2 3 1 a.png\n").unwrap_err().contains("quaternion is zero"));
        // A count far beyond the file's size is refused before any allocation.
        let mut huge = u64::MAX.to_le_bytes().to_vec();
        huge.extend([0u8; 16]);
        assert!(points_bin(&huge).unwrap_err().contains("claims"));
        assert!(cameras_bin(&[1, 0]).unwrap_err().contains("cut short"));
    }
}
