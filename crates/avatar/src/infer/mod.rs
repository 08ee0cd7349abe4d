//! Inference: a trained avatar loaded from its run folder and what it is used for. Nothing
//! here imports `crate::train`: a run folder holds everything inference needs (the model
//! configuration, the stored setup, the training poses, the pose PCA, checkpoints), so a run
//! needs neither the body model's files nor the capture.
//!
//! - [`run`]: the run folder's layout, format version and readers.
//! - `trained.rs`: [`TrainedAvatar`], a run's networks on a device, rendering poses and views.
//! - [`eval`]: body and head metrics on held-out views or poses; [`animate`]: pose sequences
//!   to frames, GIF, MP4 and `.ply`; [`export`]: a posed avatar as a 3DGS `.ply` with SH fitted to
//!   its view-dependent colour; [`video`]: frames as H.264 MP4.
//! - [`bake`]: the networks baked into a linear avatar; [`avatar_file`]: it as one `.glb`.
//! - `report.rs`: comparison grids and loss curves (also training's validation images).

pub mod animate;
pub mod avatar_file;
pub mod bake;
pub mod eval;
pub mod export;
pub(crate) mod report;
pub(crate) mod run;
mod trained;
pub mod video;

pub(crate) use run::evenly;
pub use run::{RUN_FORMAT, Run, RunInfo, TrainState, load_face_base, read_state};
pub use trained::TrainedAvatar;
