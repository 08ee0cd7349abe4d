//! The model's configuration: what inference needs to rebuild and run an avatar (template,
//! maps, networks, layout, face branch and crops, pose PCA), apart from how it is trained
//! (`crate::train::TrainConfig` holds a `ModelConfig` and the training keys beside it).
//!
//! In a run's `config.json` the model's keys sit beside the training keys in one flat JSON
//! object; [`ModelConfig::from_file`] reads its part and ignores the rest. Validation
//! ([`ModelConfig::validate`], `validate.rs`) names the first bad key.

mod validate;

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::AvatarError;
use f3g_nets::StyleUNetConfig;

/// Largest position-map side (2·R² texels, one Gaussian each; the paper uses 1024).
const MAX_MAP_RESOLUTION: usize = 2048;
/// Largest side of a rendered face crop or LPIPS crop (the paper's: 512).
pub(crate) const MAX_CROP: usize = 2048;

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
    /// Face Gaussians per head texel of the body maps, along each axis (the reference and the
    /// `paper` preset: 2; the `cpu` presets: 4, see there).
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
    /// Light fixed in the world: each colour is the networks' albedo times a learnt smooth
    /// function of the Gaussian's posed normal (`model/shading.rs`), so shading follows a limb
    /// into poses training never showed. Not in the paper; off in configurations written
    /// before it was a key.
    #[serde(default)]
    pub world_shading: bool,
    /// Pose PCA components and clamp (in standard deviations) for unseen poses.
    pub pca_components: usize,
    pub pca_sigma: f32,
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
}
