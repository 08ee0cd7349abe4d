//! The compiler and the device-feature narrowing the GPU runtimes call.

mod base;
#[cfg(any(feature = "amdgpu", feature = "nvptx"))]
pub mod lowered_features;

pub use base::*;
