//! The radiance field: the sparse voxel grid (`grid`), ray marching in plain
//! Rust (`march`), the differentiable compositing graph (`composite`;
//! its GPU kernel is `kernels::composite_op`), the colour-only renderer over frozen
//! density (`frozen`; `kernels::frozen_op` on a GPU; `host_colour`, its fused
//! plain-Rust twin for the CPU backends), what the optimisers share (`optim`; `kernels::optim_op`, RMSprop's
//! GPU kernel), the far background behind the box (`environment`) and
//! single-file checkpoints (`checkpoint`).

pub mod checkpoint;
pub mod composite;
pub mod environment;
pub mod frozen;
pub mod grid;
pub(crate) mod host_colour;
pub(crate) mod host_fit;
pub(crate) mod host_render;
pub mod march;
pub mod optim;
pub mod render_path;
pub mod view;

/// What renders and differentiates the batches of rays: the photoreal
/// fit's step, the stylization's ray losses (L_ref, the refit's photo
/// loss) and its image renders.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RayKernel {
    /// `host` on the CPU backends, `graph` on a GPU.
    #[default]
    Auto,
    /// The Burn graph (`composite::composite`, `frozen::render_colour`) and
    /// autodiff; on a GPU the photoreal step's compositing and the
    /// stylization's colour pass are fused CubeCL kernels (`composite_op`,
    /// `frozen_op`) inside that graph.
    Graph,
    /// The Burn graph without the fused compositing kernel, on every device:
    /// each sample's 8 corners x SH coefficients as tensors. On a GPU it is
    /// the kernel's fallback and the "before" of its measurements
    /// (docs/performance.md); in the stylization it is `graph`, whose
    /// colour pass on a GPU is `frozen_op`'s kernel (its graph is the
    /// oracle of the test command's `graph_oracle` tests).
    Unfused,
    /// The fused plain-Rust passes (`host_fit`, `host_colour`), meant for
    /// the CPU backends (on a GPU they would read the grid back every step).
    Host,
}

impl RayKernel {
    /// Whether the plain-Rust passes run on `device`.
    pub fn is_host(self, device: &burn::tensor::Device) -> bool {
        match self {
            RayKernel::Auto => crate::util::tensor::is_host_memory(device),
            RayKernel::Host => true,
            RayKernel::Graph | RayKernel::Unfused => false,
        }
    }
}

/// `max(x, 0)` that keeps NaN, as Burn's `relu` does: `f32::max` returns 0
/// for NaN, which would hide a diverged field from the loss checks
/// (`util::diverged`) in the plain-Rust passes.
pub(crate) fn relu(x: f32) -> f32 {
    if x < 0.0 { 0.0 } else { x }
}
