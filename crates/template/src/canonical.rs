//! The canonical pose: the body model's zero pose with the legs apart (hip rotations of
//! ±25° about the forward axis, as Animatable Gaussians uses) and a configurable arm angle,
//! so that the front and back orthographic maps see the inner legs and the arms.

use f3g_rig::{Parameterization, Rig, RigParams};

/// Angles of the canonical pose.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CanonicalPose {
    /// Rotation of each hip away from the body, degrees.
    pub leg_spread_deg: f32,
    /// Rotation of each upper arm upwards from the model's rest pose, degrees.
    pub arm_raise_deg: f32,
}

impl Default for CanonicalPose {
    fn default() -> Self {
        Self {
            leg_spread_deg: 25.0,
            arm_raise_deg: 0.0,
        }
    }
}

/// `(left joint, right joint)` names of the hips and shoulders per model family.
const HIPS: [(&str, &str); 2] = [("upperleg01.L", "upperleg01.R"), ("left_hip", "right_hip")];
const SHOULDERS: [(&str, &str); 2] = [
    ("upperarm01.L", "upperarm01.R"),
    ("left_shoulder", "right_shoulder"),
];

/// Sets a rotation about the joint's Z channel (the forward axis at rest), when the model has
/// such a parameter; returns whether it did.
fn set_z_rotation(rig: &Rig, params: &mut RigParams, joint: &str, radians: f32) -> bool {
    let Some(j) = rig.skeleton.index_of(joint) else {
        return false;
    };
    match &rig.parameterization {
        Parameterization::AxisAngle => {
            params.pose[3 * j + 2] = radians;
            true
        }
        Parameterization::Momentum(t) => {
            let row = (j * f3g_rig::PARAMS_PER_JOINT + 5) as u32;
            // A parameter that drives exactly this channel with weight 1.
            let candidate = t.entries.iter().find(|e| {
                e.0 == row && e.2 == 1.0 && t.entries.iter().filter(|o| o.1 == e.1).count() == 1
            });
            match candidate {
                Some(e) => {
                    params.pose[e.1 as usize] = radians;
                    true
                }
                None => false,
            }
        }
    }
}

/// Canonical parameters for `rig`. Models without recognised hip and shoulder joints keep
/// their rest pose; the returned flag says whether the legs were spread.
pub fn canonical_params(rig: &Rig, pose: &CanonicalPose) -> (RigParams, bool) {
    let mut params = rig.zero_params();
    let (legs, arms) = (
        pose.leg_spread_deg.to_radians(),
        pose.arm_raise_deg.to_radians(),
    );
    let mut spread = false;
    for (l, r) in HIPS {
        if set_z_rotation(rig, &mut params, l, legs) && set_z_rotation(rig, &mut params, r, -legs) {
            spread = true;
        }
    }
    for (l, r) in SHOULDERS {
        if set_z_rotation(rig, &mut params, l, arms) {
            set_z_rotation(rig, &mut params, r, -arms);
        }
    }
    (params, spread)
}

/// `params` with the root's global rotation and translation removed (posed maps are
/// root-relative, as in Animatable Gaussians).
pub fn without_root(rig: &Rig, params: &RigParams) -> RigParams {
    let mut p = params.clone();
    let roots: Vec<usize> = rig
        .skeleton
        .joints()
        .iter()
        .enumerate()
        .filter(|(_, j)| j.parent.is_none())
        .map(|(i, _)| i)
        .collect();
    match &rig.parameterization {
        Parameterization::AxisAngle => {
            for &r in &roots {
                p.pose[3 * r..3 * r + 3].fill(0.0);
            }
            let n = p.pose.len();
            p.pose[n - 3..].fill(0.0);
        }
        Parameterization::Momentum(t) => {
            for e in &t.entries {
                if roots.contains(&(e.0 as usize / f3g_rig::PARAMS_PER_JOINT)) {
                    p.pose[e.1 as usize] = 0.0;
                }
            }
        }
    }
    p
}
