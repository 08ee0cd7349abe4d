//! The splat op's GPU kernels (CubeCL; features `gpu` for wgpu and `cuda`): one `#[cube]`
//! source for every runtime, checked against the CPU path in `tests/gpu.rs` on a wgpu device
//! (Mesa lavapipe in CI). [`backend`] chains them into `SplatBackend for CubeBackend`, the
//! unfused backend (`crate::op::fusion` runs it for Burn's `fusion` feature).
//!
//! Forward: [`project`] (projection, culling, SH colour, radii, tiles touched) →
//! [`depth_order`] (a depth sort of the Gaussians and the [`exclusive_scan`] of their tile
//! counts) → the one readback of a render (the intersection count) → [`bin_tiles`] (the
//! Gaussian–tile list sorted stably by tile with [`sort_pairs`], tile ranges) →
//! [`rasterize`]. Backward: [`rasterize_backward`] (screen-space gradients, atomically summed
//! per Gaussian) → [`project_backward`]. Conventions are the CPU path's (`crate::cpu`):
//! tensors are f32 except counts, ids and radii (i32, the Int dtype of Cube devices).
//!
//! Layout: the kernels index every tensor row-major, so every tensor they read goes through
//! `into_contiguous` and every tensor they write is allocated contiguous
//! (`empty_device_contiguous_dtype`, or made flat and reshaped). Burn's ordinary allocation is
//! *pitched* on CUDA (rows padded to 16 bytes or more: a `[n, 2]` i32 tensor has rows of four);
//! wgpu never pads, so only a CUDA run shows a tensor that breaks this rule.

mod backend;
pub mod bin;
#[cfg(feature = "cuda-source")]
pub mod cuda_source;
pub mod project;
pub mod project_backward;
pub mod raster;
pub mod scan;
pub mod sort;

pub use bin::{DepthOrder, TileBins, bin_tiles, depth_order};
pub use project::{Projection, project};
pub use project_backward::project_backward;
pub use raster::{Accumulation, Raster, rasterize, rasterize_backward};
pub use scan::{exclusive_scan, exclusive_scan_in_rows};
pub use sort::{sort_pairs, sort_pairs_in_rows};

/// The CUDA C of every kernel the splat op launches on `target`, in every variant it launches
/// (tests only: feature `cuda-source`).
///
/// # Errors
/// The first kernel whose expansion or code generation failed, named.
#[cfg(feature = "cuda-source")]
pub fn kernel_sources(
    target: &cuda_source::CudaTarget,
) -> Result<Vec<cuda_source::KernelSource>, String> {
    let mut sources = Vec::new();
    sources.extend(backend::cuda_kernels(target)?);
    sources.extend(project::cuda_kernels(target)?);
    sources.extend(bin::cuda_kernels(target)?);
    sources.extend(sort::cuda_kernels(target)?);
    sources.extend(scan::cuda_kernels(target)?);
    sources.extend(raster::cuda_kernels(target)?);
    sources.extend(project_backward::cuda_kernels(target)?);
    Ok(sources)
}
