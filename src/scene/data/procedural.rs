//! The built-in procedural scene: a few textured objects on a ground disc,
//! ray-traced analytically and written in the Blender layout with
//! per-view ground-truth depth (`*_depth.npy`, distance along the unit ray,
//! 0 = miss) and object ids (`*_id.png`), plus a "stylized" variant (every
//! object re-textured) from the same cameras under `stylized/`.
//!
//! Shading is Lambertian under a fixed light, so colours do not depend on
//! the view: the stylized renders are an exact target for stylization tests.
//!
//! With [`SceneOptions::environment`] the scene stands in a textured far
//! environment (a skybox: floor tiles below the horizon, walls with windows
//! and a sky above) instead of an empty background: the 360° capture of an
//! object in a room, with ground truth. Its colour depends on the ray's
//! direction only (no parallax), so a direction-indexed background model can
//! represent it exactly up to its resolution; the stylized twin repaints it.

use crate::scene::camera::{Camera, Intrinsics, look_at};
use crate::util::image::write_png;
use crate::util::{files, npy};
use anyhow::{Context, Result};
use glam::{Vec3, Vec4};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde_json::json;
use std::path::Path;

/// Options of the generator.
#[derive(Debug, Clone, Copy)]
pub struct SceneOptions {
    pub seed: u64,
    /// Square image size in pixels.
    pub size: u32,
    pub num_train: usize,
    pub num_val: usize,
    pub num_test: usize,
    /// A textured far environment around the scene instead of an empty (transparent) background.
    pub environment: bool,
}

impl Default for SceneOptions {
    fn default() -> Self {
        Self { seed: 0, size: 96, num_train: 48, num_val: 4, num_test: 8, environment: false }
    }
}

/// Object ids written to the id maps.
pub const ID_BACKGROUND: u8 = 0;
pub const ID_GROUND: u8 = 1;
pub const ID_SPHERE: u8 = 2;
pub const ID_BOX: u8 = 3;
pub const ID_CYLINDER: u8 = 4;

/// The scene box written into the transforms files.
pub const SCENE_BBOX: [[f32; 3]; 2] = [[-1.4, -1.4, -1.4], [1.4, 1.4, 1.4]];

#[derive(Clone, Copy)]
enum Pattern {
    Checker(f32),
    StripesZ(f32),
    StripesX(f32),
    Rings(f32),
    Dots(f32),
}

#[derive(Clone, Copy)]
struct Texture {
    a: Vec3,
    b: Vec3,
    pattern: Pattern,
}

impl Texture {
    fn at(&self, p: Vec3) -> Vec3 {
        let pick = match self.pattern {
            Pattern::Checker(s) => ((p.x / s).floor() + (p.y / s).floor() + (p.z / s).floor()) as i64 % 2 == 0,
            Pattern::StripesZ(s) => ((p.z / s).floor() as i64).rem_euclid(2) == 0,
            Pattern::StripesX(s) => ((p.x / s).floor() as i64).rem_euclid(2) == 0,
            Pattern::Rings(s) => (((p.x * p.x + p.y * p.y).sqrt() / s).floor() as i64).rem_euclid(2) == 0,
            Pattern::Dots(s) => {
                let q = (p / s).fract() - Vec3::splat(0.5);
                q.length() < 0.35
            }
        };
        if pick { self.a } else { self.b }
    }
}

#[derive(Clone, Copy)]
enum Shape {
    Disc { z: f32, radius: f32 },
    Sphere { centre: Vec3, radius: f32 },
    Box { lo: Vec3, hi: Vec3 },
    Cylinder { centre: Vec3, radius: f32, height: f32 },
}

#[derive(Clone, Copy)]
struct Object {
    id: u8,
    shape: Shape,
}

/// The objects of a seeded scene and their two texture sets.
pub struct Scene {
    objects: Vec<Object>,
    photo: Vec<Texture>,
    stylized: Vec<Texture>,
    environment: bool,
}

/// The colours of the far environment: floor tiles, walls, windows, sky.
struct EnvironmentPalette {
    floor: [Vec3; 2],
    walls: [Vec3; 2],
    window: Vec3,
    horizon: Vec3,
    zenith: Vec3,
}

const PHOTO_ENVIRONMENT: EnvironmentPalette = EnvironmentPalette {
    floor: [Vec3::new(0.55, 0.45, 0.35), Vec3::new(0.3, 0.22, 0.16)],
    walls: [Vec3::new(0.8, 0.78, 0.7), Vec3::new(0.6, 0.62, 0.66)],
    window: Vec3::new(0.2, 0.3, 0.45),
    horizon: Vec3::new(0.8, 0.88, 0.95),
    zenith: Vec3::new(0.3, 0.5, 0.85),
};

const STYLIZED_ENVIRONMENT: EnvironmentPalette = EnvironmentPalette {
    floor: [Vec3::new(0.15, 0.5, 0.45), Vec3::new(0.05, 0.2, 0.25)],
    walls: [Vec3::new(0.85, 0.35, 0.55), Vec3::new(0.45, 0.2, 0.5)],
    window: Vec3::new(1.0, 0.85, 0.3),
    horizon: Vec3::new(1.0, 0.6, 0.3),
    zenith: Vec3::new(0.35, 0.15, 0.45),
};

/// The far environment's colour in direction `d` (unit, z up).
fn environment_colour(d: Vec3, palette: &EnvironmentPalette) -> Vec3 {
    use std::f32::consts::{FRAC_PI_2, TAU};
    let azimuth = (d.y.atan2(d.x) / TAU + 0.5).fract();
    let elevation = d.z.clamp(-1.0, 1.0).asin();
    if elevation < 0.0 {
        // Tiles 15 degrees of azimuth by 10 of elevation.
        let tile = (azimuth * 24.0).floor() as i64 + (elevation.to_degrees() / 10.0).floor() as i64;
        return palette.floor[tile.rem_euclid(2) as usize];
    }
    let sector = (azimuth * 16.0).floor() as i64;
    let wall_top = (8.0 + 4.0 * (sector * 7).rem_euclid(5) as f32).to_radians();
    if elevation < wall_top {
        let (u, v) = ((azimuth * 64.0).fract(), (elevation.to_degrees() / 3.0).fract());
        let window = (0.3..0.7).contains(&u) && (0.3..0.7).contains(&v);
        return if window { palette.window } else { palette.walls[sector.rem_euclid(2) as usize] };
    }
    palette.horizon.lerp(palette.zenith, (elevation / FRAC_PI_2).sqrt())
}

fn hit(shape: &Shape, o: Vec3, d: Vec3) -> Option<(f32, Vec3)> {
    match *shape {
        Shape::Disc { z, radius } => {
            if d.z.abs() < 1e-8 {
                return None;
            }
            let t = (z - o.z) / d.z;
            let p = o + t * d;
            (t > 1e-4 && p.truncate().length() <= radius).then_some((t, Vec3::Z))
        }
        Shape::Sphere { centre, radius } => {
            let oc = o - centre;
            let b = oc.dot(d);
            let c = oc.length_squared() - radius * radius;
            let disc = b * b - c;
            if disc < 0.0 {
                return None;
            }
            let t = -b - disc.sqrt();
            (t > 1e-4).then(|| (t, (o + t * d - centre).normalize()))
        }
        Shape::Box { lo, hi } => {
            let inv = Vec3::ONE / d;
            let t0 = (lo - o) * inv;
            let t1 = (hi - o) * inv;
            let tmin = t0.min(t1);
            let tmax = t0.max(t1);
            let tn = tmin.max_element();
            let tf = tmax.min_element();
            if tf < tn || tn <= 1e-4 {
                return None;
            }
            let axis = if tn == tmin.x {
                0
            } else if tn == tmin.y {
                1
            } else {
                2
            };
            let mut n = Vec3::ZERO;
            n[axis] = -d[axis].signum();
            Some((tn, n))
        }
        Shape::Cylinder { centre, radius, height } => {
            // Side wall (vertical axis) and the top cap.
            let mut best: Option<(f32, Vec3)> = None;
            let (ox, oy) = (o.x - centre.x, o.y - centre.y);
            let a = d.x * d.x + d.y * d.y;
            if a > 1e-10 {
                let b = ox * d.x + oy * d.y;
                let c = ox * ox + oy * oy - radius * radius;
                let disc = b * b - a * c;
                if disc >= 0.0 {
                    let t = (-b - disc.sqrt()) / a;
                    let z = o.z + t * d.z;
                    if t > 1e-4 && z >= centre.z && z <= centre.z + height {
                        let p = o + t * d;
                        best = Some((t, Vec3::new(p.x - centre.x, p.y - centre.y, 0.0).normalize()));
                    }
                }
            }
            if d.z.abs() > 1e-8 {
                let t = (centre.z + height - o.z) / d.z;
                let p = o + t * d;
                let r2 = (p.x - centre.x).powi(2) + (p.y - centre.y).powi(2);
                if t > 1e-4 && r2 <= radius * radius && best.is_none_or(|b| t < b.0) {
                    best = Some((t, Vec3::Z));
                }
            }
            best
        }
    }
}

impl Scene {
    /// The scene for a seed (object placement and palettes vary a little).
    pub fn new(seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut jitter = |s: f32| (rng.random::<f32>() - 0.5) * s;
        let objects = vec![
            Object { id: ID_GROUND, shape: Shape::Disc { z: 0.0, radius: 1.25 } },
            Object {
                id: ID_SPHERE,
                shape: Shape::Sphere { centre: Vec3::new(0.45 + jitter(0.1), 0.05 + jitter(0.1), 0.36), radius: 0.36 },
            },
            Object {
                id: ID_BOX,
                shape: Shape::Box {
                    lo: Vec3::new(-0.75 + jitter(0.1), -0.65, 0.0),
                    hi: Vec3::new(-0.25, -0.15 + jitter(0.1), 0.5),
                },
            },
            Object {
                id: ID_CYLINDER,
                shape: Shape::Cylinder { centre: Vec3::new(-0.2 + jitter(0.1), 0.6, 0.0), radius: 0.22, height: 0.7 },
            },
        ];
        let mut colour =
            |base: Vec3| (base + Vec3::new(jitter(0.1), jitter(0.1), jitter(0.1))).clamp(Vec3::ZERO, Vec3::ONE);
        let photo = vec![
            Texture {
                a: colour(Vec3::new(0.85, 0.85, 0.8)),
                b: colour(Vec3::new(0.35, 0.35, 0.35)),
                pattern: Pattern::Checker(0.25),
            },
            Texture {
                a: colour(Vec3::new(0.9, 0.2, 0.15)),
                b: colour(Vec3::new(0.95, 0.85, 0.2)),
                pattern: Pattern::StripesZ(0.12),
            },
            Texture {
                a: colour(Vec3::new(0.15, 0.35, 0.85)),
                b: colour(Vec3::new(0.9, 0.9, 0.95)),
                pattern: Pattern::Checker(0.125),
            },
            Texture {
                a: colour(Vec3::new(0.2, 0.7, 0.3)),
                b: colour(Vec3::new(0.1, 0.3, 0.15)),
                pattern: Pattern::StripesZ(0.1),
            },
        ];
        let stylized = vec![
            Texture {
                a: colour(Vec3::new(0.95, 0.75, 0.55)),
                b: colour(Vec3::new(0.55, 0.3, 0.2)),
                pattern: Pattern::Rings(0.2),
            },
            Texture {
                a: colour(Vec3::new(0.3, 0.1, 0.5)),
                b: colour(Vec3::new(0.95, 0.6, 0.9)),
                pattern: Pattern::StripesX(0.1),
            },
            Texture {
                a: colour(Vec3::new(0.95, 0.55, 0.1)),
                b: colour(Vec3::new(0.2, 0.2, 0.2)),
                pattern: Pattern::Dots(0.15),
            },
            Texture {
                a: colour(Vec3::new(0.1, 0.75, 0.8)),
                b: colour(Vec3::new(0.95, 0.95, 0.6)),
                pattern: Pattern::Checker(0.1),
            },
        ];
        Self { objects, photo, stylized, environment: false }
    }

    /// The same scene standing in the textured far environment (see the module's doc).
    pub fn with_environment(mut self, environment: bool) -> Self {
        self.environment = environment;
        self
    }

    /// What a ray that hits no object sees: the environment, or nothing (alpha 0).
    fn background(&self, d: Vec3, stylized: bool) -> Option<Vec3> {
        let palette = if stylized { &STYLIZED_ENVIRONMENT } else { &PHOTO_ENVIRONMENT };
        self.environment.then(|| environment_colour(d, palette))
    }

    /// Nearest hit: (distance, object index, normal).
    fn trace(&self, o: Vec3, d: Vec3) -> Option<(f32, usize, Vec3)> {
        let mut best: Option<(f32, usize, Vec3)> = None;
        for (i, ob) in self.objects.iter().enumerate() {
            if let Some((t, n)) = hit(&ob.shape, o, d)
                && best.is_none_or(|b| t < b.0)
            {
                best = Some((t, i, n));
            }
        }
        best
    }

    fn shade(&self, o: Vec3, d: Vec3, stylized: bool) -> Option<Vec3> {
        let (t, i, n) = self.trace(o, d)?;
        let p = o + t * d;
        let tex = if stylized { &self.stylized[i] } else { &self.photo[i] };
        let light = Vec3::new(0.4, 0.3, 0.85).normalize();
        Some(tex.at(p) * (0.4 + 0.6 * n.dot(light).max(0.0)))
    }

    /// Renders one camera: RGBA (2x2 supersampled), depth and object ids at pixel centres.
    pub fn render(&self, cam: &Camera, stylized: bool) -> (Vec<f32>, Vec<f32>, Vec<u8>) {
        let (w, h) = (cam.intrinsics.width, cam.intrinsics.height);
        let rows: Vec<(Vec<f32>, Vec<f32>, Vec<u8>)> = (0..h)
            .into_par_iter()
            .map(|y| {
                let mut rgba = Vec::with_capacity(w as usize * 4);
                let mut depth = Vec::with_capacity(w as usize);
                let mut ids = Vec::with_capacity(w as usize);
                for x in 0..w {
                    let mut acc = Vec4::ZERO;
                    for (sx, sy) in [(-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)] {
                        let r = cam.ray(x as f32 + sx, y as f32 + sy);
                        let seen = self.shade(r.origin, r.dir, stylized).or_else(|| self.background(r.dir, stylized));
                        if let Some(c) = seen {
                            acc += c.extend(1.0);
                        }
                    }
                    acc *= 0.25;
                    // Store un-premultiplied colour.
                    let col = if acc.w > 0.0 { acc.truncate() / acc.w } else { Vec3::ZERO };
                    rgba.extend([col.x, col.y, col.z, acc.w]);
                    let r = cam.ray(x as f32, y as f32);
                    match self.trace(r.origin, r.dir) {
                        Some((t, i, _)) => {
                            depth.push(t);
                            ids.push(self.objects[i].id);
                        }
                        None => {
                            depth.push(0.0);
                            ids.push(ID_BACKGROUND);
                        }
                    }
                }
                (rgba, depth, ids)
            })
            .collect();
        let mut rgba = Vec::new();
        let mut depth = Vec::new();
        let mut ids = Vec::new();
        for (a, b, c) in rows {
            rgba.extend(a);
            depth.extend(b);
            ids.extend(c);
        }
        (rgba, depth, ids)
    }
}

/// Cameras of a split: on a hemisphere around the scene, looking at its centre.
pub fn cameras(opts: &SceneOptions, split: &str) -> Vec<Camera> {
    let (n, offset) = match split {
        "train" => (opts.num_train, 0.0),
        "val" => (opts.num_val, 0.37),
        _ => (opts.num_test, 0.61),
    };
    let intr = Intrinsics::from_fov_x(opts.size, opts.size, 0.75);
    let target = Vec3::new(0.0, 0.0, 0.25);
    (0..n)
        .map(|i| {
            let f = (i as f32 + offset) / n as f32;
            let az = 2.0 * std::f32::consts::PI * f * 1.0 + offset;
            // Elevations cycle through 15-60 degrees so every object is seen from above and the side.
            let el = (15.0 + 45.0 * ((i as f32 * 0.618_034 + offset).fract())).to_radians();
            let radius = 3.4;
            let eye = target + radius * Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
            Camera::new(intr, look_at(eye, target, Vec3::Z))
        })
        .collect()
}

fn save_rgba(path: &Path, w: u32, h: u32, rgba: &[f32]) -> Result<()> {
    let bytes: Vec<u8> = rgba.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
    write_png(path, image::RgbaImage::from_raw(w, h, bytes).context("image buffer size")?)
}

/// Writes the scene (photoreal and stylized) under `out`.
pub fn write_scene(out: &Path, opts: &SceneOptions) -> Result<()> {
    let scene = Scene::new(opts.seed).with_environment(opts.environment);
    for (root, stylized) in [(out.to_path_buf(), false), (out.join("stylized"), true)] {
        for split in ["train", "val", "test"] {
            let dir = root.join(split);
            files::create_dir(&dir)?;
            let cams = cameras(opts, split);
            let mut frames = Vec::new();
            for (i, cam) in cams.iter().enumerate() {
                let (rgba, depth, ids) = scene.render(cam, stylized);
                let (w, h) = (cam.intrinsics.width, cam.intrinsics.height);
                save_rgba(&dir.join(format!("r_{i}.png")), w, h, &rgba)?;
                if !stylized {
                    npy::write_f32(&dir.join(format!("r_{i}_depth.npy")), &[h as usize, w as usize], &depth)?;
                    let id_map = image::GrayImage::from_raw(w, h, ids).context("id buffer size")?;
                    write_png(&dir.join(format!("r_{i}_id.png")), id_map)?;
                }
                let m = cam.c2w.transpose().to_cols_array_2d();
                frames.push(json!({ "file_path": format!("./{split}/r_{i}"), "transform_matrix": m }));
            }
            let doc = json!({
                "camera_angle_x": 0.75,
                "bbox": SCENE_BBOX,
                "frames": frames,
            });
            files::write_json(&root.join(format!("transforms_{split}.json")), &doc)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_environment_fills_every_miss_and_its_stylized_twin_repaints_it() {
        let opts = SceneOptions { size: 24, ..Default::default() };
        let cam = cameras(&opts, "test")[0];
        let (empty, _, ids) = Scene::new(0).render(&cam, false);
        let around = Scene::new(0).with_environment(true);
        let (photo, _, same_ids) = around.render(&cam, false);
        let (stylized, _, _) = around.render(&cam, true);
        assert_eq!(ids, same_ids, "the environment is behind every object");
        let (mut misses, mut repainted) = (0, 0);
        for (i, id) in ids.iter().enumerate() {
            let px = |img: &[f32]| Vec4::from_slice(&img[i * 4..i * 4 + 4]);
            assert_eq!(px(&photo).w, 1.0, "pixel {i} is opaque");
            if px(&empty).w == 1.0 {
                assert_eq!(px(&photo), px(&empty), "pixel {i}: an object's pixel keeps its colour");
            }
            if *id == ID_BACKGROUND && px(&empty).w == 0.0 {
                misses += 1;
                repainted += usize::from((px(&photo) - px(&stylized)).truncate().length() > 0.1);
            }
        }
        assert!(misses > 24 * 24 / 10, "{misses} pixels see the environment");
        assert_eq!(repainted, misses, "the stylized environment differs everywhere");
    }
}
