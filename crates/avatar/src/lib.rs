//! F3G-Avatar: the avatar model, its training, evaluation and animation.
//!
//! - [`config`]: the training configuration (presets `cpu` and `paper`, JSON files, overrides).
//! - [`setup`]: what a run derives from the body model: template, position and head maps,
//!   initial attributes, a frame's joint transforms; [`inputs`]: the networks' inputs for a
//!   frame and a camera, on the device; [`posing`]: linear blend skinning as tensor ops.
//! - [`model`]: body and face networks, canonical face model, fusion, LBS, rendering.
//! - [`train`]: region-aware training with stages, checkpoints and exact resume.
//! - [`run`]: the run folder (config, checkpoints, PCA, logs).
//! - [`report`]: comparison grids, loss curves.
//! - [`trained`]: a trained avatar for inference; [`eval`]: body and head metrics on held-out
//!   views or poses; [`animate`]: pose sequences to frames, GIF and `.ply`; [`export`]: a
//!   posed avatar as a 3DGS `.ply` with SH fitted to its view-dependent colour.
//!
//! Data flow per step: body parameters → joint transforms (`setup`, on the host) → posed maps
//! and skinning (`inputs`, `posing`, on the device) → networks (`model`) → canonical Gaussians
//! (body ++ face) → LBS → splatting → losses against the capture.

pub mod animate;
pub mod avatar_file;
pub mod bake;
pub mod config;
mod error;
pub mod eval;
pub mod export;
pub mod inputs;
pub mod model;
pub mod posing;
pub mod report;
pub mod run;
pub mod setup;
pub mod setup_file;
pub mod train;
pub mod trained;

pub use config::{ModelConfig, TrainConfig};
pub use error::AvatarError;
pub use train::{Outcome, StepReport, Trainer};
