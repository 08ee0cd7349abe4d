//! The training configuration's checks, in the order they run: the model's
//! ([`crate::model::ModelConfig::validate`]), sizes, stage lengths, the face crops' consumers
//! (discriminator, LPIPS), rates and weights, then the keys that must agree with each other.
//! Each names the first bad key.

use super::{MAX_BATCH, MAX_STAGE_STEPS, TrainConfig};
use crate::AvatarError;
use crate::model::MAX_CROP;
use f3g_nets::LpipsNet;

fn bad(key: &str, reason: String) -> Result<(), AvatarError> {
    Err(AvatarError::config(key, reason))
}

impl TrainConfig {
    /// Checks ranges and the consistency between sizes, naming the first bad key: the
    /// model's, then training's.
    pub fn validate(&self) -> Result<(), AvatarError> {
        self.model.validate()?;
        self.check_sizes()?;
        self.check_stage_lengths()?;
        self.check_face_crops()?;
        self.check_rates_and_weights()?;
        self.check_agreement()
    }

    /// Sizes, before anything is allocated.
    fn check_sizes(&self) -> Result<(), AvatarError> {
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
        Ok(())
    }

    /// The paper trains 405k steps; a billion per stage keeps every step count summable.
    fn check_stage_lengths(&self) -> Result<(), AvatarError> {
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
        Ok(())
    }

    /// The discriminator sees the face crops at their size; LPIPS needs a least input size.
    fn check_face_crops(&self) -> Result<(), AvatarError> {
        let m = &self.model;
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
        Ok(())
    }

    /// Scales, learning rates, loss weights and Adam's ε.
    fn check_rates_and_weights(&self) -> Result<(), AvatarError> {
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
        Ok(())
    }

    /// Keys that only make sense together: something to train, the face branch with its
    /// losses and frames, the periodic outputs.
    fn check_agreement(&self) -> Result<(), AvatarError> {
        let m = &self.model;
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
