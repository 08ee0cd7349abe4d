//! The training configuration: one typed struct that is the config-file format (JSON) — the
//! model's keys ([`ModelConfig`]) and the training keys side by side in one flat object.
//!
//! - `presets.rs`: the presets `cpu`, `cpu-long` and `paper`.
//! - `json.rs`: config files merged over the preset they name (`"preset": "cpu"`, the
//!   default) and overrides by dotted key (`--set steps.joint=500`, values in JSON); unknown
//!   keys are errors naming them.
//! - `validate.rs`: ranges and consistency, naming the first bad key.

mod json;
mod presets;
mod validate;

use serde::{Deserialize, Serialize};

use crate::model::ModelConfig;
use f3g_nets::{DiscriminatorConfig, LpipsNet};

/// Largest step count of one training stage.
const MAX_STAGE_STEPS: u64 = 1_000_000_000;
/// Largest `batch`: every sample of a step holds its graph in memory until the backward.
const MAX_BATCH: usize = 64;

fn one_sample() -> usize {
    1
}

/// Loss weights (the paper's λ values in the `paper` preset).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LossWeights {
    pub l1: f32,
    pub lpips: f32,
    /// Mean offset length (metres) of the predicted positions from the canonical ones.
    pub offset: f32,
    pub face_l1: f32,
    pub face_lpips: f32,
    /// Non-saturating generator loss on face crops.
    pub adversarial: f32,
    /// R1 weight γ of the discriminator.
    pub r1_gamma: f32,
    /// R1 is applied every this many discriminator steps (lazy regularisation).
    pub r1_interval: u64,
}

/// Steps of each training stage.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Stages {
    /// Body network reconstructs the canonical attributes (no rendering).
    pub pretrain: u64,
    /// Body-only rendering (the pretrained body branch the face model is taken from).
    pub body: u64,
    /// Face networks learn zero residuals on the averaged canonical face model.
    pub face_pretrain: u64,
    /// Body and face branches with body and face losses.
    pub joint: u64,
    /// Face networks only.
    pub face_finetune: u64,
}

impl Stages {
    pub fn total(&self) -> u64 {
        self.pretrain + self.body + self.face_pretrain + self.joint + self.face_finetune
    }
}

/// Everything a training run needs besides the capture: the model ([`ModelConfig`]) and how
/// it is trained.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// The preset these values started from (informative).
    pub preset: String,
    pub seed: u64,
    #[serde(flatten)]
    pub model: ModelConfig,
    /// Whether head crops are rendered and supervised (L1, LPIPS, adversarial) in the joint
    /// and fine-tuning stages; without the face branch they train the body Gaussians
    /// (`--no-face-networks`: the face-crop losses alone). `--no-face-branch` turns both off.
    pub face_losses: bool,
    /// Scale of the body views relative to the capture's images.
    pub body_scale: f32,
    pub lpips_net: LpipsNet,
    /// Side the body's mask-bounding-box crop is resized to for LPIPS.
    pub lpips_size: usize,
    pub losses: LossWeights,
    /// Whether the face adversarial loss is used with the face losses (`--no-adversarial`
    /// turns it off).
    pub adversarial: bool,
    pub discriminator: DiscriminatorConfig,
    /// Pretrained discriminator weights (a module file saved by f3g, e.g. the `disc.bpk` of
    /// another run's checkpoint) to start from instead of training it from scratch.
    pub discriminator_weights: Option<String>,
    pub steps: Stages,
    /// Training frames whose body-branch outputs are averaged into the canonical face model.
    pub face_init_frames: usize,
    /// Samples per device per step: the step applies the gradient of their mean loss (with
    /// `--devices`, of the mean over every device's samples). 1 in the paper.
    #[serde(default = "one_sample")]
    pub batch: usize,
    /// Adam learning rate of the body and face networks (cosine schedule over the rendering
    /// stages, as Animatable Gaussians).
    pub lr: f64,
    /// Radius (capture pixels) of the boundary band left out of the losses; `null`: 0 for
    /// synthetic captures (their masks are exact), 2 otherwise (Animatable Gaussians, for
    /// matted masks).
    pub band_radius: Option<f32>,
    /// Adam's ε of the avatar networks (PyTorch's default 1e-8, as Animatable Gaussians runs
    /// it; Burn's default 1e-5 swamps the small gradients of the per-texel outputs).
    pub adam_epsilon: f32,
    /// Adam learning rate of the discriminator (β = (0, 0.99), StyleGAN2).
    pub lr_discriminator: f64,
    /// Standard deviation of the noise added to view directions during training.
    pub view_noise: f32,
    pub checkpoint_every: u64,
    pub validate_every: u64,
    /// Decoded-image cache of the loader, bytes.
    pub cache_bytes: usize,
}
