//! The body-model contract: everything the avatar pipeline asks of a body model, and nothing
//! else. A loader that fills these fields of a [`Rig`] adds a body model:
//!
//! - the skinned model itself (skeleton, pose parameterisation with named parameters,
//!   identity and expression blend shapes with names, skin weights, optional correctives);
//! - [`Rig::roles`]: the joint of each [`Role`] ([`crate::roles`]), resolved once when the model
//!   loads; [`Role::REQUIRED`] must all be there ([`Rig::check_body_model`], which
//!   [`crate::ModelSpec::load`] runs, names the first role missing);
//! - [`Rig::surface`]: which vertices are skin (the canonical template is made of them;
//!   helpers such as teeth are not).
//!
//! Everything else the pipeline needs is derived here from them: the head region
//! ([`Rig::head_joints`], [`Rig::head_vertices`]), the canonical pose
//! ([`Rig::canonical_params`]: legs apart, arms raised, by rotating the hip and shoulder joints
//! about their forward axis), the finger parameters ([`Rig::finger_params`]) and those a
//! silhouette sees ([`Rig::posture_params`]). No code
//! outside this crate looks a joint up by name.

use glam::{EulerRot, Quat, Vec3};
use serde::{Deserialize, Serialize};

use crate::RigError;
use crate::rig::{Parameterization, Rig, RigParams};
use crate::roles::{Role, RoleMap};
use crate::skeleton::{PARAMS_PER_JOINT, Similarity};

/// Angles of the canonical pose.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CanonicalPose {
    /// Rotation of each hip away from the body, degrees.
    pub leg_spread_deg: f32,
    /// Rotation of each upper arm upwards from the model's rest pose, degrees.
    pub arm_raise_deg: f32,
}

impl Default for CanonicalPose {
    /// Legs apart by ±25° about the forward axis, as Animatable Gaussians' canonical pose, so
    /// that the front and back maps see the inner legs; arms as the model rests.
    fn default() -> Self {
        Self {
            leg_spread_deg: 25.0,
            arm_raise_deg: 0.0,
        }
    }
}

/// The rotation channel about a joint's forward (z) axis at rest.
const RZ: usize = 5;

impl Rig {
    /// The joint of `role`; an error naming the role and how to name its joint otherwise.
    pub fn role(&self, role: Role) -> Result<usize, RigError> {
        self.roles.get(role).ok_or_else(|| {
            RigError::Model(format!(
                "the body model `{}` has no joint in the role `{}`: name it in a role map \
                 (a JSON file `{{\"{}\": \"JOINT\"}}` saved as MODEL.roles.json beside a glTF \
                 model, e.g. {})",
                self.name,
                role.name(),
                role.name(),
                RoleMap::beside(std::path::Path::new("body.glb")).display()
            ))
        })
    }

    /// Checks that the model has every role the avatar pipeline needs.
    pub fn check_body_model(&self) -> Result<(), RigError> {
        for role in Role::REQUIRED {
            self.role(role)?;
        }
        Ok(())
    }

    /// The head joint and all its descendants (jaw, eyes, face joints).
    pub fn head_joints(&self) -> Result<Vec<usize>, RigError> {
        let head = self.role(Role::Head)?;
        Ok((0..self.skeleton.len())
            .filter(|&j| self.skeleton.is_ancestor_or_self(head, j))
            .collect())
    }

    /// Vertices skinned mostly (weight ≥ 0.5) to the head joints: the head region of the mesh.
    pub fn head_vertices(&self) -> Result<Vec<usize>, RigError> {
        let head = self.head_joints()?;
        Ok((0..self.skin.len())
            .filter(|&v| {
                self.skin
                    .influences(v)
                    .filter(|(j, _)| head.contains(j))
                    .map(|(_, w)| w)
                    .sum::<f32>()
                    >= 0.5
            })
            .collect())
    }

    /// The Momentum parameter that drives exactly one channel of `joint` with weight 1 and
    /// nothing else, if the model has one.
    fn channel_parameter(&self, joint: usize, channel: usize) -> Option<usize> {
        let Parameterization::Momentum(t) = &self.parameterization else {
            return None;
        };
        let row = (joint * PARAMS_PER_JOINT + channel) as u32;
        t.entries
            .iter()
            .find(|e| {
                e.0 == row && e.2 == 1.0 && t.entries.iter().filter(|o| o.1 == e.1).count() == 1
            })
            .map(|e| e.1 as usize)
    }

    /// Sets a rotation channel (`3..6`: rx, ry, rz) of `joint` in `params`: the joint's own
    /// axis-angle component, or the Momentum parameter that drives exactly that channel with
    /// weight 1 and nothing else. A model without such a parameter cannot take the rotation:
    /// an error naming the joint.
    pub fn set_rotation(
        &self,
        params: &mut RigParams,
        joint: usize,
        channel: usize,
        radians: f32,
    ) -> Result<(), RigError> {
        let name = &self.skeleton.joints()[joint].name;
        match &self.parameterization {
            Parameterization::AxisAngle => {
                // One axis of the joint's axis-angle vector (exact for a single axis).
                params.pose[3 * joint + channel - 3] = radians;
                Ok(())
            }
            Parameterization::Momentum(_) => match self.channel_parameter(joint, channel) {
                Some(p) => {
                    params.pose[p] = radians;
                    Ok(())
                }
                None => Err(RigError::Model(format!(
                    "{}: no pose parameter turns the joint `{name}` alone about its axis {}",
                    self.name,
                    crate::params::CHANNELS[channel]
                ))),
            },
        }
    }

    /// Sets the whole pose rotation of `joint` (applied after its rest rotation): its
    /// axis-angle vector, or its Momentum `rx, ry, rz` parameters (`R = Rz·Ry·Rx`). Channels
    /// the model cannot move are left out; returns the rotation set (`rotation` itself when
    /// every channel is there).
    pub fn set_joint_rotation(&self, params: &mut RigParams, joint: usize, rotation: Quat) -> Quat {
        let rotation = rotation.normalize();
        match &self.parameterization {
            Parameterization::AxisAngle => {
                let q = if rotation.w < 0.0 {
                    -rotation
                } else {
                    rotation
                };
                let (axis, angle) = q.to_axis_angle();
                params.pose[3 * joint..3 * joint + 3].copy_from_slice(&(axis * angle).to_array());
                q
            }
            Parameterization::Momentum(_) => {
                // In f64: near ±90° about y, f32's asin loses half its digits.
                let (z, y, x) = rotation.as_dquat().to_euler(EulerRot::ZYX);
                let (z, y, x) = (z as f32, y as f32, x as f32);
                let mut applied = [0.0f32; 3];
                for (k, angle) in [x, y, z].into_iter().enumerate() {
                    if let Some(p) = self.channel_parameter(joint, 3 + k) {
                        params.pose[p] = angle;
                        applied[k] = angle;
                    }
                }
                crate::skeleton::euler_xyz(applied[0], applied[1], applied[2])
            }
        }
    }

    /// Sets the translation of the root joint (world frame, added to its rest position):
    /// SMPL's `transl`, or the root's Momentum `tx, ty, tz` parameters.
    pub fn set_root_translation(
        &self,
        params: &mut RigParams,
        translation: Vec3,
    ) -> Result<(), RigError> {
        match &self.parameterization {
            Parameterization::AxisAngle => {
                let n = params.pose.len();
                params.pose[n - 3..].copy_from_slice(&translation.to_array());
                Ok(())
            }
            Parameterization::Momentum(_) => {
                for k in 0..3 {
                    let p = self.channel_parameter(0, k).ok_or_else(|| {
                        RigError::Model(format!(
                            "{}: no pose parameter moves the root joint `{}` along {}",
                            self.name,
                            self.skeleton.joints()[0].name,
                            crate::params::CHANNELS[k]
                        ))
                    })?;
                    params.pose[p] = translation[k];
                }
                Ok(())
            }
        }
    }

    /// The translation of the root joint that [`Rig::set_root_translation`] sets.
    pub fn root_translation(&self, params: &RigParams) -> Vec3 {
        let mut t = Vec3::ZERO;
        match &self.parameterization {
            Parameterization::AxisAngle => {
                let n = params.pose.len();
                t = Vec3::from_slice(&params.pose[n - 3..]);
            }
            Parameterization::Momentum(_) => {
                for k in 0..3 {
                    // A channel the model lacks stays at zero, as setting it would fail.
                    if let Some(p) = self.channel_parameter(0, k) {
                        t[k] = params.pose[p];
                    }
                }
            }
        }
        t
    }

    /// World transforms of the joints for parameters: forward kinematics without the mesh.
    pub fn joint_world(&self, params: &RigParams) -> Result<Vec<Similarity>, RigError> {
        let poses = self.joint_poses(&params.pose)?;
        let offsets = self.shaped_offsets(&params.identity, &params.expression);
        Ok(self.skeleton.forward(&poses, offsets.as_deref()))
    }

    /// The canonical parameters: zero parameters with the hips turned ±`leg_spread` and the
    /// shoulders ±`arm_raise` about their forward axes (left positive).
    pub fn canonical_params(&self, pose: &CanonicalPose) -> Result<RigParams, RigError> {
        let mut params = self.zero_params();
        for (left, right, degrees) in [
            (Role::LeftHip, Role::RightHip, pose.leg_spread_deg),
            (Role::LeftShoulder, Role::RightShoulder, pose.arm_raise_deg),
        ] {
            if degrees != 0.0 {
                let radians = degrees.to_radians();
                self.set_rotation(&mut params, self.role(left)?, RZ, radians)?;
                self.set_rotation(&mut params, self.role(right)?, RZ, -radians)?;
            }
        }
        Ok(params)
    }

    /// Indices of the pose parameters that move the root joint(s): the global rotation and
    /// translation (they drive no other joint).
    pub fn root_params(&self) -> Vec<usize> {
        let joints = self.skeleton.joints();
        let is_root = |j: usize| joints[j].parent.is_none();
        match &self.parameterization {
            Parameterization::AxisAngle => {
                let n = self.num_pose_params();
                (0..joints.len())
                    .filter(|&j| is_root(j))
                    .flat_map(|j| 3 * j..3 * j + 3)
                    .chain(n - 3..n)
                    .collect()
            }
            Parameterization::Momentum(t) => {
                let mut drives_root = vec![false; t.len()];
                let mut drives_other = vec![false; t.len()];
                for &(row, col, w) in &t.entries {
                    if w != 0.0 {
                        if is_root(row as usize / PARAMS_PER_JOINT) {
                            drives_root[col as usize] = true;
                        } else {
                            drives_other[col as usize] = true;
                        }
                    }
                }
                (0..t.len())
                    .filter(|&c| drives_root[c] && !drives_other[c])
                    .collect()
            }
        }
    }

    /// Indices of the pose parameters that articulate the fingers: those that drive only
    /// joints below a wrist (the wrists' roles).
    pub fn finger_params(&self) -> Result<Vec<usize>, RigError> {
        let in_hand = self.below(&[Role::LeftWrist, Role::RightWrist])?;
        Ok(self.params_driving_only(&in_hand))
    }

    /// Indices of the pose parameters a silhouette sees: every one but those that drive only
    /// joints below a wrist or below the head (fingers, jaw, eyes), which the masks of a
    /// full-body capture cannot resolve.
    pub fn posture_params(&self) -> Result<Vec<usize>, RigError> {
        let hidden = self.below(&[Role::LeftWrist, Role::RightWrist, Role::Head])?;
        let hidden = self.params_driving_only(&hidden);
        Ok((0..self.num_pose_params())
            .filter(|p| !hidden.contains(p))
            .collect())
    }

    /// Per joint: whether it lies strictly below the joint of one of `roles`.
    fn below(&self, roles: &[Role]) -> Result<Vec<bool>, RigError> {
        let tops = roles
            .iter()
            .map(|&r| self.role(r))
            .collect::<Result<Vec<_>, _>>()?;
        Ok((0..self.skeleton.len())
            .map(|j| {
                tops.iter()
                    .any(|&t| t != j && self.skeleton.is_ancestor_or_self(t, j))
            })
            .collect())
    }

    /// The pose parameters that drive joints in `region` and no joint outside it.
    fn params_driving_only(&self, region: &[bool]) -> Vec<usize> {
        match &self.parameterization {
            Parameterization::AxisAngle => (0..region.len())
                .filter(|&j| region[j])
                .flat_map(|j| 3 * j..3 * j + 3)
                .collect(),
            Parameterization::Momentum(t) => {
                let mut drives_inside = vec![false; t.len()];
                let mut drives_other = vec![false; t.len()];
                for &(row, col, w) in &t.entries {
                    if w != 0.0 {
                        let joint = row as usize / PARAMS_PER_JOINT;
                        if region[joint] {
                            drives_inside[col as usize] = true;
                        } else {
                            drives_other[col as usize] = true;
                        }
                    }
                }
                (0..t.len())
                    .filter(|&c| drives_inside[c] && !drives_other[c])
                    .collect()
            }
        }
    }
}
