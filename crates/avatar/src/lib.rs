//! F3G-Avatar: the avatar model, its training, evaluation and animation.
//!
//! Three folders, named by who may use what:
//!
//! - [`model`]: the avatar itself — its configuration ([`model::ModelConfig`]), the setup a
//!   run derives from the body model and stores, the networks' inputs for a frame and a camera,
//!   linear blend skinning as tensor ops, the body and face networks and their fusion into
//!   canonical Gaussians. Imports neither `infer` nor `train`.
//! - [`infer`]: a trained avatar and what it is used for — the run folder's readers, loading,
//!   evaluation, animation, `.ply` export, baking into a portable avatar file, report images.
//!   Imports `model`, never `train` (`crates/cli/tests/tidy.rs` checks both rules).
//! - [`train`]: the training configuration (presets `cpu`, `cpu-long` and `paper`, JSON
//!   files, overrides), the run folder's writing side, checkpoints, the region-aware training
//!   loop with exact resume, and `f3g bench train`'s phase timer.
//!
//! Data flow per step: body parameters → joint transforms (the setup, on the host) → posed
//! maps and skinning (the networks' inputs, on the device) → networks → canonical Gaussians
//! (body ++ face) → LBS → splatting → losses against the capture.

mod error;
pub mod infer;
pub mod model;
pub mod train;

pub use error::AvatarError;
