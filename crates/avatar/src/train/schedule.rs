//! The schedule: which stage a step belongs to, which networks it trains and its learning rate.
//!
//! Stages run in the order of [`Stage`]; without the face branch stages 3–5 are body steps (or
//! joint steps when the face-crop losses train the body alone), so both variants take the same
//! number of steps. The learning rate is constant in pretraining, then follows
//! `lr·((cos(π t/T) + 1)/2 · 0.95 + 0.05)` over the `T` rendering steps.

use serde::Serialize;

use super::config::{Stages, TrainConfig};

/// A training stage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    Pretrain,
    Body,
    FacePretrain,
    Joint,
    FaceFinetune,
}

impl Stage {
    /// Whether the body networks are updated in this stage.
    pub fn trains_body(self) -> bool {
        matches!(self, Self::Pretrain | Self::Body | Self::Joint)
    }

    /// Whether the face networks are updated in this stage (when they exist).
    pub fn trains_face(self) -> bool {
        matches!(self, Self::FacePretrain | Self::Joint | Self::FaceFinetune)
    }
}

/// The stages and learning rates of a configuration.
#[derive(Clone, Debug)]
pub struct Schedule {
    steps: Stages,
    lr: f64,
    face_branch: bool,
    face_losses: bool,
}

impl Schedule {
    pub fn new(config: &TrainConfig) -> Self {
        Self {
            steps: config.steps.clone(),
            lr: config.lr,
            face_branch: config.model.face_branch,
            face_losses: config.face_losses,
        }
    }

    /// Total steps.
    pub fn total(&self) -> u64 {
        self.steps.total()
    }

    /// The stage of step `s`.
    pub fn stage(&self, s: u64) -> Stage {
        let st = &self.steps;
        let mut end = st.pretrain;
        if s < end {
            return Stage::Pretrain;
        }
        end += st.body;
        if s < end || !(self.face_branch || self.face_losses) {
            return Stage::Body;
        }
        if !self.face_branch {
            // Face-crop losses without face networks: nothing to pretrain or fine-tune alone.
            return Stage::Joint;
        }
        end += st.face_pretrain;
        if s < end {
            return Stage::FacePretrain;
        }
        end += st.joint;
        if s < end {
            return Stage::Joint;
        }
        Stage::FaceFinetune
    }

    /// The learning rate of step `s`.
    pub fn lr(&self, s: u64) -> f64 {
        let pre = self.steps.pretrain;
        if s < pre {
            return self.lr;
        }
        let t = (s - pre) as f64;
        let total = (self.total() - pre).max(1) as f64;
        self.lr * (((std::f64::consts::PI * t / total).cos() + 1.0) / 2.0 * 0.95 + 0.05)
    }

    /// Whether the body optimiser starts afresh at step `s` (Animatable Gaussians resets Adam
    /// after pretraining).
    pub fn resets_body_optimiser(&self, s: u64) -> bool {
        s == self.steps.pretrain && s > 0
    }

    /// Whether step `s` needs the canonical face model (built once, on first need).
    pub fn needs_face_model(&self, s: u64) -> bool {
        self.face_branch && self.stage(s).trains_face()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn schedule(face_branch: bool, face_losses: bool) -> Schedule {
        Schedule {
            steps: Stages {
                pretrain: 2,
                body: 3,
                face_pretrain: 1,
                joint: 4,
                face_finetune: 2,
            },
            lr: 1e-3,
            face_branch,
            face_losses,
        }
    }

    #[test]
    fn stages_follow_the_configured_lengths_in_order() {
        let s = schedule(true, true);
        let stages: Vec<_> = (0..12).map(|i| s.stage(i)).collect();
        use Stage::*;
        assert_eq!(
            stages,
            [
                Pretrain,
                Pretrain,
                Body,
                Body,
                Body,
                FacePretrain,
                Joint,
                Joint,
                Joint,
                Joint,
                FaceFinetune,
                FaceFinetune
            ]
        );
        assert!(s.resets_body_optimiser(2) && !s.resets_body_optimiser(3));
        assert!(!s.needs_face_model(4) && s.needs_face_model(5));
    }

    #[test]
    fn ablations_keep_the_step_count_and_train_the_body() {
        let body_only = schedule(false, false);
        assert!((2..12).all(|i| body_only.stage(i) == Stage::Body));
        let losses_only = schedule(false, true);
        assert!((5..12).all(|i| losses_only.stage(i) == Stage::Joint));
        assert!(!(0..12).any(|i| losses_only.needs_face_model(i)));
    }

    #[test]
    fn the_learning_rate_is_constant_then_cosine_to_five_percent() {
        let s = schedule(true, true);
        assert_eq!(s.lr(0), 1e-3);
        assert_eq!(s.lr(1), 1e-3);
        assert_eq!(s.lr(2), 1e-3);
        let last = s.lr(11);
        let expected =
            1e-3 * (((std::f64::consts::PI * 9.0 / 10.0).cos() + 1.0) / 2.0 * 0.95 + 0.05);
        assert!((last - expected).abs() < 1e-15);
        assert!((3..12).all(|i| s.lr(i) < s.lr(i - 1)));
    }
}
