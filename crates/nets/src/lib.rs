//! The networks and image metrics of F3G-Avatar, as Burn modules that run on every backend: the
//! CPU (Flex), and wgpu or CUDA with the `gpu` and `cuda` features.
//!
//! - [`styleunet`]: the DualStyleUNet (one encoder, front/back StyleGAN2 decoders, Haar output,
//!   optional view branch) of the body and face branches, with the paper's and CPU presets.
//! - [`discriminator`]: the StyleGAN2 residual discriminator, non-saturating losses, R1.
//! - [`lpips`]: LPIPS v0.1 (AlexNet, VGG16), differentiable.
//! - [`metrics`]: SSIM (the paper's evaluation and 3DGS's training convention), PSNR, D-SSIM
//!   and L1 losses.
//! - [`layers`]: the equalised-learning-rate network modules; [`init`] draws their weights.
//! - [`conv`]: the 2-D convolution every network uses, a backend op (im2col + GEMM on the CPU,
//!   Burn's kernels with a chosen algorithm on a GPU).
//! - [`fused`]: StyleGAN2's element-wise chains (bias + leaky ReLU, ×2 up- and down-sampling,
//!   blur, Haar) and modulated weights, each one pass (a loop on the CPU, a kernel on a GPU)
//!   where it can run, else Burn's tensor ops ([`fused::portable`]).
//! - [`resample`]: bilinear resizing to any size.
//! - [`adam`]: Adam with each parameter's update as one pass (on a GPU, one kernel for up to 32
//!   parameters).
//! - [`checkpoint`]: saving and loading modules atomically, with shape checks.
//! - [`host`]: CPU tensors as host slices and back, for the CPU implementations of backend ops.
//!
//! Conventions: tensors `[B, C, H, W]`, images in `[0, 1]`; weights are initialised on the host
//! from a seed, so the same seed gives the same network on every backend.

pub mod adam;
pub mod checkpoint;
pub mod conv;
#[cfg(any(feature = "gpu", feature = "cuda"))]
pub mod cube_grid;
#[cfg(any(feature = "gpu", feature = "cuda"))]
mod cube_layout;
pub mod discriminator;
mod error;
pub mod fused;
mod gate;
pub mod host;
pub mod init;
pub mod layers;
pub mod lpips;
pub mod metrics;
pub mod resample;
pub mod styleunet;

pub use discriminator::{Discriminator, DiscriminatorConfig};
pub use error::NetsError;
pub use lpips::{Lpips, LpipsNet};
pub use styleunet::{DualOutput, DualStyleUNet, StyleUNetConfig};
