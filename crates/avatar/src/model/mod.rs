//! The avatar model: what inference and training share. Nothing here imports `crate::infer`
//! or `crate::train`.
//!
//! - `config/`: [`ModelConfig`] (template, maps, networks, layout, face branch and crops, pose
//!   PCA) and its validation.
//! - `setup.rs`: [`Setup`], what a run derives from its body model — template, position and
//!   head maps, initial attributes — and a frame's host share ([`FramePose`]); `setup_file.rs`:
//!   the setup stored in the run folder, so inference needs no body-model files.
//! - `inputs.rs`: the networks' inputs for a frame's pose and a camera, on the device
//!   ([`NetInputs`]), and the pose PCA on the device ([`PcaTensors`]).
//! - [`posing`]: linear blend skinning as tensor operations.
//! - `nets.rs`: the body and face networks ([`AvatarNets`]), the canonical face model
//!   ([`FaceBase`]), the setup's tensors ([`Constants`]), fusion into canonical Gaussians
//!   ([`canonical`]; a pose seen from several views runs the networks that do not see the
//!   camera once, [`view_free`]), posing and rendering them ([`render_posed`]).
//! - [`shading`]: the light fixed in the world (`world_shading`).
//!
//! Conventions: metres, +Y up, the body facing +Z; Gaussian order body then face.

mod config;
mod inputs;
mod nets;
pub mod posing;
mod setup;
mod setup_file;
pub mod shading;

pub(crate) use config::MAX_CROP;
pub use config::{BodyLayout, ColourActivation, ModelConfig, TemplateChoice};
pub(crate) use inputs::GaussianTables;
pub use inputs::{NetInputs, PcaTensors, PoseTensors};
pub use nets::{
    AvatarNets, BodyNets, Canonical, Constants, FaceBase, FaceNets, ViewFree, canonical,
    canonical_seen, render_posed, view_free,
};
pub(crate) use nets::{
    DISCRIMINATOR_PARAM_IDS, body_attributes_host, body_outputs, logit, nchw, pose,
};
pub use setup::{FramePose, Setup};
pub use setup_file::STORED_SETUP;

use burn::tensor::{Tensor, TensorData};

/// A float tensor's values on the host as `f32`, whatever its element type on the device: the
/// crate's one way out of a tensor, so every reader sees the same conversion.
pub(crate) fn host_values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    host_data(t.into_data())
}

/// [`host_values`] for data already read back.
pub(crate) fn host_data(data: TensorData) -> Vec<f32> {
    data.convert::<f32>()
        .try_into_vec::<f32>()
        .expect("a float tensor converts to f32")
}
