//! What a scene is before any field: cameras, rays, the NDC warp and camera
//! paths (`camera`), the spherical-harmonic basis (`sh`), and posed-image
//! datasets with a loader per layout (`data`).

pub mod camera;
pub mod data;
pub mod sh;
