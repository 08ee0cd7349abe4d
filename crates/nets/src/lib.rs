//! The networks and image metrics of F3G-Avatar, as Burn modules.
//!
//! - [`styleunet`]: the DualStyleUNet (one encoder, front/back StyleGAN2 decoders, Haar output,
//!   optional view branch) of the body and face branches, with the paper's and CPU presets.
//! - [`discriminator`]: the StyleGAN2 residual discriminator, non-saturating losses, R1.
//! - [`lpips`]: LPIPS v0.1 (AlexNet, VGG16), differentiable.
//! - [`metrics`]: SSIM (3DGS convention), PSNR, D-SSIM and L1 losses.
//! - [`layers`]: the equalised-learning-rate building blocks.
//! - [`conv`]: the 2-D convolution every network uses, a backend op whose weight gradient is one
//!   GEMM per tile on the CPU.
//! - [`fused`]: StyleGAN2's element-wise chains (bias + leaky ReLU, ×2 up-sampling, blur, Haar)
//!   as single passes on the CPU.
//! - [`adam`]: Adam with each parameter's update as one pass (one kernel on a GPU).
//! - [`checkpoint`]: saving and loading modules atomically, with shape checks.
//!
//! Conventions: tensors `[B, C, H, W]`, images in `[0, 1]`; weights are initialised on the host
//! from a seed, so the same seed gives the same network on every backend.

pub mod adam;
pub mod checkpoint;
pub mod conv;
#[cfg(all(any(feature = "gpu", feature = "cuda"), not(feature = "fusion")))]
mod cube_grid;
#[cfg(all(any(feature = "gpu", feature = "cuda"), not(feature = "fusion")))]
mod cube_layout;
pub mod discriminator;
mod error;
pub mod fused;
mod host;
pub mod layers;
pub mod lpips;
pub mod metrics;
pub mod styleunet;

pub use discriminator::{Discriminator, DiscriminatorConfig};
pub use error::NetsError;
pub use lpips::{Lpips, LpipsNet};
pub use styleunet::{DualOutput, DualStyleUNet, StyleUNetConfig};
