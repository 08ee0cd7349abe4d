//! Motions f3g makes, for other tools: body-model parameters as a [`Motion`] on the body
//! model's own skeleton with world-aligned rest frames (as BVH holds them).

use glam::Quat;

use f3g_rig::{Joint, Rig, RigParams, Skeleton};

use crate::{Motion, MotionError, Up};

/// The joint motion of `frames` of `rig` at `fps`: each joint's rotation since rest in world
/// axes, re-expressed relative to its parent's, so that rest frames are world-aligned; the
/// rest skeleton is the body model's at the first frame's shape. Per-joint translations and
/// scales other than the root's are not kept (the built-in human and SMPL-X have none);
/// expressions are not joint motion and are not kept either.
pub fn from_rig(rig: &Rig, frames: &[RigParams], fps: f32) -> Result<Motion, MotionError> {
    let first = frames.first().ok_or_else(|| MotionError::Retarget {
        file: rig.name.clone().into(),
        reason: "no frames to export".into(),
    })?;
    let rest_params = RigParams {
        pose: vec![0.0; rig.num_pose_params()],
        identity: first.identity.clone(),
        expression: vec![0.0; rig.expression.len()],
    };
    let rest = rig.joint_world(&rest_params)?;
    let joints = rig.skeleton.joints();
    let skeleton = Skeleton::new(
        joints
            .iter()
            .enumerate()
            .map(|(j, joint)| Joint {
                name: joint.name.clone(),
                parent: joint.parent,
                offset: rest[j].translation
                    - joint
                        .parent
                        .map_or(glam::Vec3::ZERO, |p| rest[p].translation),
                pre_rotation: Quat::IDENTITY,
            })
            .collect(),
    )?;
    let mut rotations = Vec::with_capacity(frames.len() * joints.len());
    let mut root_translation = Vec::with_capacity(frames.len());
    let mut since_rest = vec![Quat::IDENTITY; joints.len()];
    for p in frames {
        let posed = rig.joint_world(p)?;
        for (j, joint) in joints.iter().enumerate() {
            since_rest[j] = (posed[j].rotation * rest[j].rotation.conjugate()).normalize();
            let parent = joint.parent.map_or(Quat::IDENTITY, |q| since_rest[q]);
            rotations.push((parent.conjugate() * since_rest[j]).normalize());
        }
        root_translation.push(posed[0].translation - rest[0].translation);
    }
    Ok(Motion {
        skeleton,
        rotations,
        root_translation,
        fps,
        metres_per_unit: 1.0,
        up: Up::Y,
        smpl: None,
    })
}
