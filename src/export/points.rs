//! The surface the field shows, as a coloured point cloud: every
//! `stride`-th pixel of every training view, placed at its equation-4
//! depth (the surface R³ registers) and coloured by the render there.

use glam::Vec3;

use crate::eval::stylization::surface_of;
use crate::export::ply::{Ply, Scalar};
use crate::field::checkpoint::Checkpoint;
use crate::scene::camera::Camera;
use crate::util::progress::{Event, Phase, Progress};

/// Points and their colours (world space, sRGB in [0, 1]).
#[derive(Debug, Clone, Default)]
pub struct Points {
    pub positions: Vec<Vec3>,
    pub colours: Vec<[f32; 3]>,
}

/// The surface points of `cameras`' views, every `stride`-th pixel along
/// both axes (1: all).
pub fn points_of(ck: &Checkpoint, cameras: &[Camera], stride: usize, progress: &dyn Progress) -> Points {
    let started = std::time::Instant::now();
    let stride = stride.max(1);
    let renderer = ck.renderer();
    let mut out = Points::default();
    progress.event(Event::Start { phase: Phase::Render, done: 0, total: cameras.len() });
    for (i, cam) in cameras.iter().enumerate() {
        let s = surface_of(&renderer, cam);
        let width = s.image.width;
        for (pixel, point) in s.points.iter().enumerate() {
            let (x, y) = (pixel % width, pixel / width);
            if x % stride != 0 || y % stride != 0 {
                continue;
            }
            if let Some(p) = point {
                out.positions.push(*p);
                let rgb = &s.image.rgb[pixel * 3..pixel * 3 + 3];
                out.colours.push([rgb[0], rgb[1], rgb[2]]);
            }
        }
        let message = format!("{} points", out.positions.len());
        progress.event(Event::Step { phase: Phase::Render, done: i + 1, total: cameras.len(), message });
    }
    progress.event(Event::PhaseDone { phase: Phase::Render, seconds: started.elapsed().as_secs_f64() });
    out
}

/// The points as a PLY (positions, 8-bit colours).
pub fn to_ply(points: &Points, source: &str) -> Ply {
    let mut ply = Ply { comments: vec![format!("refnpr surface points of {source}")], ..Default::default() };
    for (a, name) in ["x", "y", "z"].iter().enumerate() {
        ply.add(name, Scalar::Float, points.positions.iter().map(|p| p[a]).collect());
    }
    for (ch, name) in ["red", "green", "blue"].iter().enumerate() {
        ply.add(name, Scalar::UChar, points.colours.iter().map(|c| c[ch] * 255.0).collect());
    }
    ply
}
