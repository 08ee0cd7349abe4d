//! Differentiable 3D Gaussian splatting.
//!
//! project (cull, EWA covariance, SH colour) → bin into 16×16 tiles (stable depth order) →
//! composite front to back → backward from the final transmittance, back to front.
//!
//! - [`reference`]: the readable renderer (gsplat 1.5.3's semantics, every Gaussian at every
//!   pixel) that every fast path is tested against.
//! - [`semantics`]: what every path computes (footprint, cut-offs, outputs, layouts), its
//!   constants and input checks, shared by the CPU renderer and the GPU kernels.
//! - [`cpu`]: the fast multi-threaded CPU renderer (generic over `f32`/`f64`).
//! - [`op`]: the same renderer as a Burn operation with a hand-written backward
//!   ([`render`] is the entry point for tensors that need gradients).
//! - [`ply`]: the standard 3DGS `.ply` layout, read and write.
//!
//! Conventions: metres, OpenCV cameras (`x_cam = R x + t`, +Z forward, pixel centres at
//! `i + 0.5`), quaternions (w, x, y, z), natural-log scales, opacity logits, SH colour with
//! `0.5 + C0 · f_dc` for degree 0. Images are `[H, W, C]` row-major.

mod cloud;
pub mod cpu;
#[cfg(any(feature = "gpu", feature = "cuda"))]
pub mod cube;
mod error;
pub mod op;
pub mod ply;
mod real;
pub mod reference;
pub mod semantics;
pub mod sh;
pub mod spz;

pub use cloud::GaussianCloud;
pub use error::SplatError;
pub use f3g_camera::{
    Camera, CameraError, DEFAULT_FAR, DEFAULT_NEAR, MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE,
};
pub use op::{Gaussians, Rendered, SplatBackend, render};
pub use real::Real;
pub use semantics::RenderOptions;
