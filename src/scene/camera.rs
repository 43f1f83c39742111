//! Pinhole cameras, per-pixel rays, NDC rays and render paths.
//!
//! Conventions: camera-to-world matrices in the OpenGL / Blender convention
//! (x right, y up, the camera looks down -z). Every loader converts to this.

use glam::{Mat3, Mat4, Vec3, Vec4};
use serde::{Deserialize, Serialize};

use crate::util::image::Image;

/// Pinhole intrinsics in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
}

impl Intrinsics {
    /// Intrinsics from a horizontal field of view (Blender's `camera_angle_x`).
    pub fn from_fov_x(width: u32, height: u32, fov_x: f32) -> Self {
        let f = 0.5 * width as f32 / (0.5 * fov_x).tan();
        Self { width, height, fx: f, fy: f, cx: width as f32 * 0.5, cy: height as f32 * 0.5 }
    }

    /// The same camera at another resolution (focal and centre scale with it).
    pub fn resized(&self, width: u32, height: u32) -> Self {
        let sx = width as f32 / self.width as f32;
        let sy = height as f32 / self.height as f32;
        Self { width, height, fx: self.fx * sx, fy: self.fy * sy, cx: self.cx * sx, cy: self.cy * sy }
    }

    /// The camera whose pixels are `n` x `n` blocks of this one's (an odd
    /// last row or column dropped): focal and centre divided by `n`, so a
    /// pixel's ray passes through its block's centre.
    pub fn downscaled(&self, n: u32) -> Self {
        let s = n as f32;
        Self {
            width: self.width / n,
            height: self.height / n,
            fx: self.fx / s,
            fy: self.fy / s,
            cx: self.cx / s,
            cy: self.cy / s,
        }
    }

    pub fn num_pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// A posed camera.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub intrinsics: Intrinsics,
    /// Camera-to-world, OpenGL convention.
    pub c2w: Mat4,
}

/// One ray: origin and unit direction, plus the view direction used for
/// spherical harmonics (the world direction even when rays are in NDC space).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
    pub view_dir: Vec3,
}

/// Parameters of the normalised-device-coordinate warp used for
/// forward-facing (LLFF) scenes, as in the NeRF code (near plane at 1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NdcParams {
    pub width: f32,
    pub height: f32,
    pub focal: f32,
    pub near: f32,
}

impl Camera {
    /// An image the size of this camera's view.
    pub fn image_of(&self, rgb: Vec<f32>) -> Image {
        Image::new(self.intrinsics.width as usize, self.intrinsics.height as usize, rgb)
    }

    pub fn new(intrinsics: Intrinsics, c2w: Mat4) -> Self {
        Self { intrinsics, c2w }
    }

    pub fn position(&self) -> Vec3 {
        self.c2w.w_axis.truncate()
    }

    /// Unit-length viewing direction (the camera's -z axis).
    pub fn forward(&self) -> Vec3 {
        (-self.c2w.z_axis.truncate()).normalize()
    }

    /// The world-space ray through the centre of pixel (x, y).
    pub fn ray(&self, x: f32, y: f32) -> Ray {
        let k = &self.intrinsics;
        let d_cam = Vec3::new((x + 0.5 - k.cx) / k.fx, -(y + 0.5 - k.cy) / k.fy, -1.0);
        let rot = Mat3::from_mat4(self.c2w);
        let dir = (rot * d_cam).normalize();
        Ray { origin: self.position(), dir, view_dir: dir }
    }

    /// Rays for every pixel, row-major.
    pub fn rays(&self, ndc: Option<&NdcParams>) -> Vec<Ray> {
        let (w, h) = (self.intrinsics.width, self.intrinsics.height);
        let mut out = Vec::with_capacity(w as usize * h as usize);
        for y in 0..h {
            for x in 0..w {
                let r = self.ray(x as f32, y as f32);
                out.push(match ndc {
                    Some(p) => to_ndc(r, p),
                    None => r,
                });
            }
        }
        out
    }

    /// Projects a world point to continuous pixel coordinates and its depth
    /// along the viewing axis (None when behind the camera).
    pub fn project(&self, p: Vec3) -> Option<(f32, f32, f32)> {
        let w2c = self.c2w.inverse();
        let q = w2c.transform_point3(p);
        if q.z >= -1e-6 {
            return None;
        }
        let k = &self.intrinsics;
        let x = k.fx * (q.x / -q.z) + k.cx - 0.5;
        let y = -k.fy * (q.y / -q.z) + k.cy - 0.5;
        Some((x, y, -q.z))
    }
}

/// Warps a world ray into NDC space (NeRF's `ndc_rays`), the direction
/// normalised so that marching steps are lengths in NDC units.
pub fn to_ndc(r: Ray, p: &NdcParams) -> Ray {
    let (o, d) = (r.origin, r.dir);
    let t = -(p.near + o.z) / d.z;
    let o = o + t * d;
    let ax = -2.0 * p.focal / p.width;
    let ay = -2.0 * p.focal / p.height;
    let o_ndc = Vec3::new(ax * o.x / o.z, ay * o.y / o.z, 1.0 + 2.0 * p.near / o.z);
    let d_ndc = Vec3::new(ax * (d.x / d.z - o.x / o.z), ay * (d.y / d.z - o.y / o.z), -2.0 * p.near / o.z);
    Ray { origin: o_ndc, dir: d_ndc.normalize(), view_dir: r.dir }
}

/// The world point of an NDC point (the inverse of the warp `to_ndc`
/// applies to points); None at or beyond the far end (z_ndc -> 1 is infinity).
pub fn from_ndc(q: Vec3, p: &NdcParams) -> Option<Vec3> {
    if q.z >= 1.0 - 1e-4 {
        return None;
    }
    let z = 2.0 * p.near / (q.z - 1.0);
    let ax = -2.0 * p.focal / p.width;
    let ay = -2.0 * p.focal / p.height;
    Some(Vec3::new(q.x * z / ax, q.y * z / ay, z))
}

/// NeRF's `viewmatrix`: a camera-to-world frame looking along `z` (the
/// camera's +z is the backwards axis) with `up` as the approximate up vector.
pub fn view_matrix(z: Vec3, up: Vec3, pos: Vec3) -> Mat4 {
    let z = z.normalize();
    let x = up.cross(z).normalize();
    let y = z.cross(x).normalize();
    Mat4::from_cols(x.extend(0.0), y.extend(0.0), z.extend(0.0), pos.extend(1.0))
}

/// NeRF's `poses_avg`: the mean camera (centre = mean position, back axis =
/// summed back axes, up = summed up axes).
pub fn average_pose(poses: &[Mat4]) -> Mat4 {
    let n = poses.len().max(1) as f32;
    let center = poses.iter().map(|p| p.w_axis.truncate()).sum::<Vec3>() / n;
    let z = poses.iter().map(|p| p.z_axis.truncate()).sum::<Vec3>();
    let up = poses.iter().map(|p| p.y_axis.truncate()).sum::<Vec3>();
    view_matrix(z, up, center)
}

/// The standard LLFF spiral render path of the NeRF / Plenoxels code:
/// `n` poses, `rots` rotations, `zrate` 0.5, radii from the 90th percentile
/// of |camera positions| and the focus depth from the scene bounds.
pub fn llff_spiral(poses: &[Mat4], near: f32, far: f32, n: usize, rots: f32, zrate: f32) -> Vec<Mat4> {
    let c2w = average_pose(poses);
    let up = poses.iter().map(|p| p.y_axis.truncate()).sum::<Vec3>().normalize();
    let close_depth = near * 0.9;
    let inf_depth = far * 5.0;
    let dt = 0.75;
    let focal = 1.0 / ((1.0 - dt) / close_depth + dt / inf_depth);
    let mut rads = [0.0f32; 3];
    for (axis, rad) in rads.iter_mut().enumerate() {
        let mut v: Vec<f32> = poses.iter().map(|p| p.w_axis[axis].abs()).collect();
        *rad = percentile(&mut v, 90.0);
    }
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let theta = 2.0 * std::f32::consts::PI * rots * i as f32 / n as f32;
        let local = Vec4::new(theta.cos() * rads[0], -theta.sin() * rads[1], -(theta * zrate).sin() * rads[2], 1.0);
        let c = (c2w * local).truncate();
        let look = (c2w * Vec4::new(0.0, 0.0, -focal, 1.0)).truncate();
        out.push(view_matrix(c - look, up, c));
    }
    out
}

/// Linear-interpolated percentile (numpy's default).
pub fn percentile(v: &mut [f32], q: f32) -> f32 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let pos = q / 100.0 * (v.len() - 1) as f32;
    let lo = pos.floor() as usize;
    let hi = pos.ceil() as usize;
    v[lo] + (v[hi] - v[lo]) * (pos - lo as f32)
}

/// A circular orbit around `target` for object scenes: `n` cameras at the
/// given radius and elevation (degrees), looking at the target, z up.
pub fn orbit(target: Vec3, radius: f32, elevation_deg: f32, n: usize) -> Vec<Mat4> {
    let el = elevation_deg.to_radians();
    (0..n)
        .map(|i| {
            let az = 2.0 * std::f32::consts::PI * i as f32 / n as f32;
            let pos = target + radius * Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
            look_at(pos, target, Vec3::Z)
        })
        .collect()
}

/// Camera-to-world for a camera at `eye` looking at `target` (OpenGL convention).
pub fn look_at(eye: Vec3, target: Vec3, up: Vec3) -> Mat4 {
    view_matrix(eye - target, up, eye)
}

/// True when every entry is finite and the rotation part is invertible.
pub fn pose_is_valid(m: &Mat4) -> bool {
    m.to_cols_array().iter().all(|v| v.is_finite()) && Mat3::from_mat4(*m).determinant().abs() > 1e-6
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A downscaled camera's pixel looks through the centre of its block.
    #[test]
    fn a_downscaled_pixel_looks_through_its_blocks_centre() {
        let k = Intrinsics::from_fov_x(64, 48, 0.8);
        let cam = Camera::new(k, look_at(Vec3::new(3.0, 1.0, 2.0), Vec3::ZERO, Vec3::Z));
        let small = Camera { intrinsics: k.downscaled(3), ..cam };
        assert_eq!((small.intrinsics.width, small.intrinsics.height), (21, 16));
        let (x, y) = (5.0, 9.0);
        let block_centre = cam.ray(x * 3.0 + 1.0, y * 3.0 + 1.0);
        assert!((small.ray(x, y).dir - block_centre.dir).length() < 1e-5);
    }

    #[test]
    fn centre_pixel_looks_forward_and_projects_back() {
        let k = Intrinsics::from_fov_x(64, 48, 0.8);
        let cam = Camera::new(k, look_at(Vec3::new(3.0, 1.0, 2.0), Vec3::ZERO, Vec3::Z));
        let r = cam.ray(31.5, 23.5);
        assert!((r.dir - cam.forward()).length() < 1e-5);
        let p = r.origin + 2.5 * cam.ray(10.0, 7.0).dir;
        let (x, y, _) = cam.project(p).unwrap();
        assert!((x - 10.0).abs() < 1e-3 && (y - 7.0).abs() < 1e-3, "{x} {y}");
    }

    #[test]
    fn ndc_maps_near_plane_to_minus_one_and_infinity_to_one() {
        let k = Intrinsics::from_fov_x(40, 30, 1.0);
        let cam = Camera::new(k, Mat4::from_translation(Vec3::new(0.0, 0.0, 0.0)));
        let p = NdcParams { width: 40.0, height: 30.0, focal: k.fx, near: 1.0 };
        let r = to_ndc(cam.ray(20.0, 15.0), &p);
        assert!((r.origin.z + 1.0).abs() < 1e-5);
        assert!(r.dir.z > 0.99);
    }

    #[test]
    fn spiral_has_requested_length_and_valid_poses() {
        let poses: Vec<Mat4> =
            (0..5).map(|i| Mat4::from_translation(Vec3::new(i as f32 * 0.1 - 0.2, 0.05 * i as f32, 0.0))).collect();
        let path = llff_spiral(&poses, 1.0, 10.0, 120, 2.0, 0.5);
        assert_eq!(path.len(), 120);
        assert!(path.iter().all(pose_is_valid));
    }
}
