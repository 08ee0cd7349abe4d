//! The training configuration: one typed struct that is the config-file format (JSON), with
//! the `cpu` and `paper` presets, overrides by dotted key, and validation naming the key.
//!
//! A config file holds any subset of the keys; it is merged over the preset it names
//! (`"preset": "cpu"`, the default) and then checked: unknown keys and out-of-range values are
//! errors. Overrides use the same dotted keys (`--set steps.joint=500`, values in JSON).

use std::path::Path;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::AvatarError;
use f3g_nets::{DiscriminatorConfig, LpipsNet, StyleUNetConfig};

/// Largest position-map side (2·R² texels, one Gaussian each; the paper uses 1024).
pub const MAX_MAP_RESOLUTION: usize = 2048;
/// Largest side of a rendered face crop or LPIPS crop (the paper's: 512).
pub const MAX_CROP: usize = 2048;
/// Largest step count of one training stage.
pub const MAX_STAGE_STEPS: u64 = 1_000_000_000;
/// Largest `batch`: every sample of a step holds its graph in memory until the backward.
pub const MAX_BATCH: usize = 64;

fn one_sample() -> usize {
    1
}

/// The face density of configurations written before it was a key.
fn reference_face_density() -> usize {
    f3g_template::head::DENSIFY
}

/// Which canonical template the avatar is built on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TemplateChoice {
    /// The body model's surface alone.
    Body,
    /// The body plus the capture's garment: the built-in human's skirt for the built-in body,
    /// otherwise the mesh in `garment`.
    Clothed,
}

/// The names of the configuration file (`body`, `clothed`), for `f3g train --template`.
impl std::str::FromStr for TemplateChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "body" => Ok(Self::Body),
            "clothed" => Ok(Self::Clothed),
            _ => Err(format!("unknown template `{s}`: expected body or clothed")),
        }
    }
}

/// How the body branch's outputs are split between networks.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BodyLayout {
    /// One view-conditioned network predicts all 14 channels (so the camera also moves the
    /// geometry; kept for comparison).
    Single,
    /// A geometry network (position offset, opacity, scale, rotation: 11 channels) and a
    /// view-conditioned colour network (3): the camera changes colours only.
    Split,
    /// Animatable Gaussians' three networks: position (3), view-conditioned colour (3) and
    /// other (opacity, scale, rotation: 8).
    Three,
}

/// How the colour channels of the networks become colours.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ColourActivation {
    /// `0.5 + o` (Animatable Gaussians: the raw output, unbounded).
    Linear,
    /// `sigmoid(o)`: colours stay in [0, 1].
    Sigmoid,
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

/// The avatar itself: what inference needs to rebuild and run it (template, maps, networks,
/// the face branch, the head crops it is seen through, the pose PCA), apart from how it is
/// trained. In a configuration file its keys sit beside the training keys (one flat JSON
/// object), so `--set map_resolution=512` names a model key as it always has.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelConfig {
    pub template: TemplateChoice,
    /// Garment mesh for `template = clothed` with a body model other than the built-in one.
    pub garment: Option<String>,
    /// Side of each canonical position map (front and back), R.
    pub map_resolution: usize,
    /// The body StyleUNets: input the posed front and back maps (6 channels) at `input_size`,
    /// output per side at `output_size` (the paper: `R/2 → R`; a smaller output is upsampled
    /// bilinearly to `R`, the per-texel detail then coming from the learnable canonical
    /// attributes); their `out_channels` and `view_conditioned` are set per network by
    /// `body_layout`.
    pub body_net: StyleUNetConfig,
    pub body_layout: BodyLayout,
    /// Whether the face branch exists: the three face StyleUNets and their Gaussians
    /// (`--no-face-branch` and `--no-face-networks` turn it off).
    pub face_branch: bool,
    /// The three face StyleUNets (their `out_channels` are set per network: 3, 3, 8).
    pub face_net: StyleUNetConfig,
    /// Side of the rendered face crops.
    pub face_crop_size: usize,
    /// Face crop box enlargement around the projected head.
    pub face_padding: f32,
    /// Face Gaussians per head texel of the body maps, along each axis (the reference: 2).
    /// 4 (four times the face Gaussians) measured no better on the demo's 230-pixel heads
    /// at its 730 steps (BENCHMARKS, "The face at real resolution").
    #[serde(default = "reference_face_density")]
    pub face_density: usize,
    /// Initial thickness of the Gaussians: the scale along the surface normal relative to the
    /// tangent scale (1: isotropic, as Animatable Gaussians; below 1: discs on the surface).
    pub initial_thickness: f32,
    /// Initial opacity of every Gaussian (Animatable Gaussians: 0.1).
    pub initial_opacity: f32,
    pub colour_activation: ColourActivation,
    /// Learnable per-Gaussian canonical attributes added to the networks' outputs.
    pub learn_canonical: bool,
    /// Step-size multiplier of the canonical attributes relative to `lr`.
    pub canonical_lr_scale: f32,
    /// Pose PCA components and clamp (in standard deviations) for unseen poses.
    pub pca_components: usize,
    pub pca_sigma: f32,
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

impl TrainConfig {
    /// Small enough to train on two CPU cores in minutes (what `f3g demo` uses).
    pub fn cpu() -> Self {
        let mut body = StyleUNetConfig::cpu_body(14, true);
        body.in_channels = 6;
        let mut face = StyleUNetConfig::cpu_face(3, false);
        face.in_channels = 6;
        Self {
            preset: "cpu".into(),
            seed: 0,
            model: ModelConfig {
                template: TemplateChoice::Clothed,
                garment: None,
                map_resolution: 256,
                body_net: body,
                body_layout: BodyLayout::Split,
                face_branch: true,
                face_net: face,
                // 256², the evaluation's size: on the demo's 1536 × 2048 capture this beats
                // 128² by +0.9 dB and −0.032 head LPIPS (two seeds) for +9 % step time.
                face_crop_size: 256,
                face_padding: 1.3,
                face_density: f3g_template::head::DENSIFY,
                initial_thickness: 0.3,
                initial_opacity: 0.5,
                colour_activation: ColourActivation::Linear,
                learn_canonical: true,
                canonical_lr_scale: 8.0,
                pca_components: 20,
                pca_sigma: 2.0,
            },
            face_losses: true,
            body_scale: 1.0,
            lpips_net: LpipsNet::Alex,
            lpips_size: 128,
            losses: LossWeights {
                l1: 1.0,
                lpips: 0.1,
                offset: 5e-3,
                face_l1: 1.0,
                face_lpips: 0.1,
                adversarial: 5e-3,
                r1_gamma: 1.0,
                r1_interval: 16,
            },
            adversarial: true,
            discriminator: DiscriminatorConfig::cpu(256),
            discriminator_weights: None,
            // 730 steps: about 8.5 minutes on 2 cores, so that `f3g demo` stays within 10.
            steps: Stages {
                pretrain: 100,
                body: 250,
                face_pretrain: 30,
                joint: 250,
                face_finetune: 100,
            },
            face_init_frames: 8,
            lr: 1e-3,
            adam_epsilon: 1e-8,
            batch: 1,
            band_radius: None,
            lr_discriminator: 2e-3,
            view_noise: 0.1,
            checkpoint_every: 100,
            validate_every: 100,
            cache_bytes: 1 << 30,
        }
    }

    /// The `cpu` preset trained longer, for `f3g demo --quality` (about 40 minutes of training
    /// on two CPU cores at the measured 0.5 s per body step and 1.1 s per joint step): 3.5× the
    /// rendering steps, most of them in the body and joint stages, whose losses are still
    /// falling when the demo stops.
    pub fn cpu_long() -> Self {
        Self {
            preset: "cpu-long".into(),
            steps: Stages {
                pretrain: 100,
                body: 1100,
                face_pretrain: 50,
                joint: 1400,
                face_finetune: 300,
            },
            checkpoint_every: 250,
            validate_every: 250,
            ..Self::cpu()
        }
    }

    /// AvatarReX scale as the paper trains it: 1024² maps, 512 → 1024 body network, 256² face
    /// networks, 512² face crops, VGG LPIPS on 512² crops, 5k pretraining, 400k rendering
    /// iterations (split into a body-only and a joint half, so the canonical face model is
    /// averaged from a trained body branch) and a 5k face-only fine-tune.
    pub fn paper() -> Self {
        let mut body = StyleUNetConfig::paper_body(14, true);
        body.in_channels = 6;
        let mut face = StyleUNetConfig::paper_face(3, false);
        face.in_channels = 6;
        let cpu = Self::cpu();
        Self {
            preset: "paper".into(),
            model: ModelConfig {
                map_resolution: 1024,
                body_net: body,
                face_net: face,
                body_layout: BodyLayout::Three,
                face_crop_size: 512,
                initial_opacity: 0.1,
                initial_thickness: 1.0,
                learn_canonical: false,
                ..cpu.model.clone()
            },
            body_scale: 1.0,
            lpips_net: LpipsNet::Vgg,
            lpips_size: 512,
            losses: LossWeights {
                r1_gamma: 10.0,
                ..cpu.losses.clone()
            },
            discriminator: DiscriminatorConfig::paper(512),
            steps: Stages {
                pretrain: 5000,
                body: 200_000,
                face_pretrain: 1000,
                joint: 200_000,
                face_finetune: 5000,
            },
            face_init_frames: 200,
            lr: 5e-4,
            checkpoint_every: 5000,
            validate_every: 5000,
            cache_bytes: 8 << 30,
            ..cpu
        }
    }

    /// A preset by name.
    pub fn preset(name: &str) -> Result<Self, AvatarError> {
        match name {
            "cpu" => Ok(Self::cpu()),
            "cpu-long" => Ok(Self::cpu_long()),
            "paper" => Ok(Self::paper()),
            _ => Err(AvatarError::config(
                "preset",
                format!("unknown preset `{name}`: expected cpu, cpu-long or paper"),
            )),
        }
    }

    /// Reads a JSON config file: its keys over the preset it names. A key the configuration
    /// does not have is an error naming it.
    pub fn from_file(path: &Path) -> Result<Self, AvatarError> {
        let text = std::fs::read_to_string(path).map_err(|e| AvatarError::file(path, e))?;
        let value: Value = serde_json::from_str(&text)
            .map_err(|e| AvatarError::file(path, format!("not valid JSON: {e}")))?;
        let preset = value
            .get("preset")
            .and_then(Value::as_str)
            .unwrap_or("cpu")
            .to_string();
        let preset = Self::preset(&preset).map_err(|e| AvatarError::file(path, e))?;
        let mut base = serde_json::to_value(preset).expect("serialisable");
        if let Some(key) = unknown_key(&base, &value, "") {
            return Err(AvatarError::file(
                path,
                format!("unknown configuration key `{key}`"),
            ));
        }
        merge(&mut base, &value);
        let config: Self = serde_json::from_value(base)
            .map_err(|e| AvatarError::file(path, format!("bad configuration: {e}")))?;
        config.validate().map_err(|e| AvatarError::file(path, e))?;
        Ok(config)
    }

    /// Applies `key=value` overrides (dotted keys, JSON values; bare words are strings).
    pub fn with_overrides(self, overrides: &[String]) -> Result<Self, AvatarError> {
        let mut value = serde_json::to_value(&self).expect("serialisable");
        for item in overrides {
            let (key, text) = item.split_once('=').ok_or_else(|| {
                AvatarError::config(item, "expected key=value, e.g. steps.joint=500")
            })?;
            let parsed: Value =
                serde_json::from_str(text).unwrap_or_else(|_| Value::String(text.to_string()));
            let mut slot = &mut value;
            for part in key.split('.') {
                slot = slot
                    .as_object_mut()
                    .and_then(|o| o.get_mut(part))
                    .ok_or_else(|| AvatarError::config(key, "no such key"))?;
            }
            *slot = parsed;
        }
        let config: Self = serde_json::from_value(value)
            .map_err(|e| AvatarError::config("--set", format!("{e}")))?;
        config.validate()?;
        Ok(config)
    }

    /// Checks ranges and the consistency between sizes, naming the first bad key: the
    /// model's ([`ModelConfig::validate`]), then training's.
    pub fn validate(&self) -> Result<(), AvatarError> {
        self.model.validate()?;
        let bad = |k: &str, m: String| Err(AvatarError::config(k, m));
        let m = &self.model;
        for (key, value, limit) in [
            ("lpips_size", self.lpips_size, MAX_CROP),
            ("face_init_frames", self.face_init_frames, 100_000),
            ("batch", self.batch, MAX_BATCH),
        ] {
            if value > limit {
                return bad(key, format!("{value} is larger than the limit {limit}"));
            }
        }
        if self.batch == 0 {
            return bad("batch", "0 samples per step: expected at least 1".into());
        }
        // The paper trains 405k steps; a billion per stage keeps every step count summable.
        for (stage, steps) in [
            ("steps.pretrain", self.steps.pretrain),
            ("steps.body", self.steps.body),
            ("steps.face_pretrain", self.steps.face_pretrain),
            ("steps.joint", self.steps.joint),
            ("steps.face_finetune", self.steps.face_finetune),
        ] {
            if steps > MAX_STAGE_STEPS {
                return bad(
                    stage,
                    format!("{steps} is larger than the limit {MAX_STAGE_STEPS}"),
                );
            }
        }
        self.discriminator
            .validate()
            .map_err(|e| AvatarError::config("discriminator", e))?;
        if self.discriminator.resolution != m.face_crop_size {
            return bad(
                "discriminator.resolution",
                format!(
                    "must equal face_crop_size ({}); got {}",
                    m.face_crop_size, self.discriminator.resolution
                ),
            );
        }
        let min_crop = match self.lpips_net {
            LpipsNet::Alex => 32,
            LpipsNet::Vgg => 16,
        };
        if m.face_crop_size < min_crop || self.lpips_size < min_crop {
            return bad(
                "face_crop_size",
                format!("face_crop_size and lpips_size must be at least {min_crop} for LPIPS"),
            );
        }
        if !(self.body_scale > 0.0 && self.body_scale <= 1.0) {
            return bad(
                "body_scale",
                format!("{} is not in (0, 1]", self.body_scale),
            );
        }
        for (k, v) in [("lr", self.lr), ("lr_discriminator", self.lr_discriminator)] {
            if !(v > 0.0 && v < 1.0) {
                return bad(k, format!("{v} is not in (0, 1)"));
            }
        }
        let l = &self.losses;
        for (k, v) in [
            ("losses.l1", l.l1),
            ("losses.lpips", l.lpips),
            ("losses.offset", l.offset),
            ("losses.face_l1", l.face_l1),
            ("losses.face_lpips", l.face_lpips),
            ("losses.adversarial", l.adversarial),
            ("losses.r1_gamma", l.r1_gamma),
            ("view_noise", self.view_noise),
            ("band_radius", self.band_radius.unwrap_or(0.0)),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(k, format!("{v} must be finite and ≥ 0"));
            }
        }
        if !(self.adam_epsilon.is_finite() && self.adam_epsilon > 0.0) {
            return bad(
                "adam_epsilon",
                format!("{} must be finite and > 0", self.adam_epsilon),
            );
        }
        if l.r1_interval == 0 {
            return bad("losses.r1_interval", "must be at least 1".into());
        }
        if self.steps.total() == 0 {
            return bad("steps", "all stages have zero steps".into());
        }
        if m.face_branch && !self.face_losses {
            return bad(
                "face_losses",
                "the face branch trains on the face-crop losses: must be true with face_branch"
                    .into(),
            );
        }
        if m.face_branch && self.face_init_frames == 0 {
            return bad(
                "face_init_frames",
                "must be at least 1 with the face branch".into(),
            );
        }
        if self.checkpoint_every == 0 || self.validate_every == 0 {
            return bad(
                "checkpoint_every",
                "checkpoint_every and validate_every must be ≥ 1".into(),
            );
        }
        Ok(())
    }
}

impl ModelConfig {
    /// The model part of a run's `config.json` (its training keys are ignored), checked.
    pub fn from_file(path: &Path) -> Result<Self, AvatarError> {
        let text = std::fs::read_to_string(path).map_err(|e| AvatarError::file(path, e))?;
        let model: Self = serde_json::from_str(&text)
            .map_err(|e| AvatarError::file(path, format!("bad model configuration: {e}")))?;
        model.validate().map_err(|e| AvatarError::file(path, e))?;
        Ok(model)
    }

    /// Checks the model's ranges and sizes, naming the first bad key.
    pub fn validate(&self) -> Result<(), AvatarError> {
        let bad = |k: &str, m: String| Err(AvatarError::config(k, m));
        let r = self.map_resolution;
        if r < 16 || !r.is_power_of_two() {
            return bad("map_resolution", format!("{r} is not a power of two ≥ 16"));
        }
        // Sizes are checked before anything is allocated (the paper's largest is 1024).
        for (key, value, limit) in [
            ("map_resolution", r, MAX_MAP_RESOLUTION),
            ("face_crop_size", self.face_crop_size, MAX_CROP),
            ("pca_components", self.pca_components, 512),
        ] {
            if value > limit {
                return bad(key, format!("{value} is larger than the limit {limit}"));
            }
        }
        self.body_net
            .validate()
            .map_err(|e| AvatarError::config("body_net", e))?;
        if self.body_net.output_size > r {
            return bad(
                "body_net.output_size",
                format!(
                    "{} exceeds map_resolution ({r}): the outputs are read at the map's texels",
                    self.body_net.output_size
                ),
            );
        }
        if self.body_net.in_channels != 6 {
            return bad(
                "body_net.in_channels",
                "must be 6 (front and back maps)".into(),
            );
        }
        self.face_net
            .validate()
            .map_err(|e| AvatarError::config("face_net", e))?;
        if self.face_net.in_channels != 6 || self.face_net.output_size != self.face_net.input_size {
            return bad(
                "face_net",
                "in_channels must be 6 and output_size equal to input_size".into(),
            );
        }
        if !(1..=4).contains(&self.face_density) {
            return bad(
                "face_density",
                format!("{} is not in 1..=4", self.face_density),
            );
        }
        if !(self.face_padding >= 1.0 && self.face_padding <= 4.0) {
            return bad(
                "face_padding",
                format!("{} is not in [1, 4]", self.face_padding),
            );
        }
        if !(self.initial_thickness > 0.0 && self.initial_thickness <= 1.0) {
            return bad(
                "initial_thickness",
                format!("{} is not in (0, 1]", self.initial_thickness),
            );
        }
        if !(self.initial_opacity > 0.0 && self.initial_opacity < 1.0) {
            return bad(
                "initial_opacity",
                format!("{} is not in (0, 1)", self.initial_opacity),
            );
        }
        if !(self.canonical_lr_scale.is_finite() && self.canonical_lr_scale >= 0.0) {
            return bad(
                "canonical_lr_scale",
                format!("{} must be finite and ≥ 0", self.canonical_lr_scale),
            );
        }
        if !(self.pca_sigma.is_finite() && self.pca_sigma > 0.0) {
            return bad(
                "pca_sigma",
                format!("{} must be finite and positive", self.pca_sigma),
            );
        }
        Ok(())
    }

    /// The body networks' configurations, in the order of `BodyNets` (`net`, then `colour`
    /// and `other` when the layout has them).
    pub fn body_nets(&self) -> Vec<StyleUNetConfig> {
        let with = |out: usize, view: bool| StyleUNetConfig {
            out_channels: out,
            view_conditioned: view,
            ..self.body_net.clone()
        };
        match self.body_layout {
            BodyLayout::Single => vec![with(14, true)],
            BodyLayout::Split => vec![with(11, false), with(3, true)],
            BodyLayout::Three => vec![with(3, false), with(3, true), with(8, false)],
        }
    }

    /// The face networks' configurations: position, colour (view-conditioned), auxiliary.
    pub fn face_nets(&self) -> [StyleUNetConfig; 3] {
        let with = |out: usize, view: bool| StyleUNetConfig {
            out_channels: out,
            view_conditioned: view,
            ..self.face_net.clone()
        };
        [with(3, false), with(3, true), with(8, false)]
    }
}

/// The first key of `patch` (as a dotted path) that `base`, a whole configuration, lacks.
fn unknown_key(base: &Value, patch: &Value, prefix: &str) -> Option<String> {
    let (Value::Object(b), Value::Object(p)) = (base, patch) else {
        return None;
    };
    p.iter().find_map(|(k, v)| {
        let path = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        match b.get(k) {
            None => Some(path),
            Some(inner) => unknown_key(inner, v, &path),
        }
    })
}

/// Deep merge of JSON objects: `patch` wins.
fn merge(base: &mut Value, patch: &Value) {
    match (base, patch) {
        (Value::Object(b), Value::Object(p)) => {
            for (k, v) in p {
                match b.get_mut(k) {
                    Some(slot) if slot.is_object() && v.is_object() => merge(slot, v),
                    _ => {
                        b.insert(k.clone(), v.clone());
                    }
                }
            }
        }
        (b, p) => *b = p.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--template` takes the names the configuration file uses.
    #[test]
    fn template_names_are_the_config_files() {
        for template in [TemplateChoice::Body, TemplateChoice::Clothed] {
            let name = serde_json::to_value(&template).unwrap();
            let name = name.as_str().unwrap();
            assert_eq!(name.parse::<TemplateChoice>(), Ok(template));
        }
        assert_eq!(
            "skirt".parse::<TemplateChoice>().unwrap_err(),
            "unknown template `skirt`: expected body or clothed"
        );
    }

    #[test]
    fn presets_are_valid() {
        for name in ["cpu", "cpu-long", "paper"] {
            let c = TrainConfig::preset(name).unwrap();
            c.validate().unwrap();
            assert_eq!(c.preset, name);
        }
        // `cpu-long` is `cpu` trained longer: only the step counts (and the cadence of
        // checkpoints and validation) differ.
        let rendering = |c: &TrainConfig| c.steps.body + c.steps.joint + c.steps.face_finetune;
        let (long, cpu) = (TrainConfig::cpu_long(), TrainConfig::cpu());
        assert!(rendering(&long) >= 3 * rendering(&cpu));
        let same = TrainConfig {
            preset: cpu.preset.clone(),
            steps: cpu.steps.clone(),
            checkpoint_every: cpu.checkpoint_every,
            validate_every: cpu.validate_every,
            ..long
        };
        assert_eq!(same, cpu);
    }

    #[test]
    fn files_merge_over_the_preset_and_reject_unknown_keys_and_bad_values() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.json");
        std::fs::write(&path, r#"{"steps": {"joint": 7}, "lr": 0.002}"#).unwrap();
        let c = TrainConfig::from_file(&path).unwrap();
        assert_eq!((c.steps.joint, c.lr, c.steps.body), (7, 0.002, 250));
        std::fs::write(&path, r#"{"map_resolution": 1073741824}"#).unwrap();
        let e = TrainConfig::from_file(&path).unwrap_err().to_string();
        assert!(e.contains("c.json") && e.contains("map_resolution"), "{e}");
        std::fs::write(&path, r#"{"stepz": 3}"#).unwrap();
        let e = TrainConfig::from_file(&path).unwrap_err().to_string();
        assert!(e.contains("c.json") && e.contains("stepz"), "{e}");
        std::fs::write(&path, r#"{"steps": {"joint": 7, "warp": 1}}"#).unwrap();
        let e = TrainConfig::from_file(&path).unwrap_err().to_string();
        assert!(e.contains("warp"), "{e}");
        std::fs::write(&path, r#"{"body_scale": 3}"#).unwrap();
        let e = TrainConfig::from_file(&path).unwrap_err().to_string();
        assert!(e.contains("body_scale"), "{e}");
        std::fs::write(&path, r#"{"map_resolution": 100}"#).unwrap();
        let e = TrainConfig::from_file(&path).unwrap_err().to_string();
        assert!(e.contains("map_resolution"), "{e}");
    }

    #[test]
    fn absurd_sizes_are_errors_naming_the_key() {
        for key in [
            "map_resolution",
            "face_crop_size",
            "lpips_size",
            "pca_components",
            "face_init_frames",
            "body_net.input_size",
            "body_net.output_size",
            "body_net.max_channels",
            "body_net.style_dim",
            "body_net.channel_base",
            "face_net.max_channels",
            "discriminator.resolution",
            "discriminator.max_channels",
            "body_net.n_mlp",
            "body_net.middle_size",
            "body_net.channel_multiplier",
            "face_net.input_size",
            "steps.joint",
        ] {
            let e = TrainConfig::cpu()
                .with_overrides(&[format!("{key}=1073741824")])
                .unwrap_err()
                .to_string();
            let field = key.rsplit('.').next().unwrap();
            assert!(e.contains(field), "{key}: {e}");
        }
        // Within every per-field limit, a feature map that cannot fit is still refused.
        let e = TrainConfig::cpu()
            .with_overrides(&[
                "body_net.input_size=2048".into(),
                "body_net.output_size=2048".into(),
                "body_net.max_channels=4096".into(),
                "body_net.channel_base=16777216".into(),
                "map_resolution=2048".into(),
            ])
            .unwrap_err()
            .to_string();
        assert!(e.contains("GiB"), "{e}");
    }

    #[test]
    fn overrides_use_dotted_keys() {
        let c = TrainConfig::cpu()
            .with_overrides(&["steps.joint=3".into(), "lpips_net=vgg".into()])
            .unwrap();
        assert_eq!((c.steps.joint, c.lpips_net), (3, LpipsNet::Vgg));
        let e = TrainConfig::cpu()
            .with_overrides(&["steps.nope=3".into()])
            .unwrap_err()
            .to_string();
        assert!(e.contains("steps.nope"), "{e}");
        assert!(
            TrainConfig::cpu()
                .with_overrides(&["lr=-1".into()])
                .unwrap_err()
                .to_string()
                .contains("`lr`")
        );
    }
}
