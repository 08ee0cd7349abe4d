//! The splat op's GPU kernels (CubeCL; features `gpu` for wgpu and `cuda`): one `#[cube]`
//! source for every runtime, checked against the CPU path in `tests/gpu.rs` on a wgpu device
//! (Mesa lavapipe in CI).
//!
//! Built so far: [`project`] (projection, culling, SH colour, radii, tiles touched),
//! [`exclusive_scan`] and [`intersect`] (the unsorted Gaussian–tile list; the one readback of
//! a render, its length, happens there) and [`sort_pairs`] (a stable radix sort for the depth
//! and tile orders). Still to come before `impl SplatBackend for Cube` (issue "GPU
//! splatting"): sorting the intersections by depth then tile, tile ranges, rasterisation
//! forward and backward, and the projection backward — `crates/splat/GSPLAT.md` records the formulas. Conventions are the CPU path's
//! (`crate::cpu`): tensors are f32 except counts and radii (i32, the Int dtype of Cube devices).

pub mod intersect;
pub mod project;
pub mod scan;
pub mod sort;

pub use intersect::{Intersections, intersect};
pub use project::{Projection, project};
pub use scan::exclusive_scan;
pub use sort::sort_pairs;
