//! The model configuration's ranges and sizes, checked before anything is allocated.

use super::{MAX_CROP, MAX_MAP_RESOLUTION, ModelConfig};
use crate::AvatarError;

impl ModelConfig {
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
}
