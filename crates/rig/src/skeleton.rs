//! Joint hierarchies and forward kinematics (Momentum conventions).
//!
//! A joint's transform relative to its parent is `T(offset + t) · R_pre · R · S(2^s)`: the rest
//! offset plus a translation `t` (metres, parent frame), the rest pre-rotation, a pose rotation
//! `R`, and a uniform scale `2^s`. World transforms compose parent first, so a parent's scale
//! also scales its children's offsets. Joints are stored parents-first.
//!
//! Momentum's seven joint parameters are `[tx, ty, tz, rx, ry, rz, s]` with
//! `R = Rz(rz) · Ry(ry) · Rx(rx)` (x applied first); [`JointPose::from_momentum`] converts them.

use glam::{Affine3A, Mat3, Quat, Vec3};

use crate::RigError;

/// Parameters per joint in the Momentum convention.
pub const PARAMS_PER_JOINT: usize = 7;

/// A rotation, translation and uniform scale: `x ↦ R (s x) + t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Similarity {
    pub rotation: Quat,
    pub translation: Vec3,
    pub scale: f32,
}

impl Similarity {
    pub const IDENTITY: Self = Self {
        rotation: Quat::IDENTITY,
        translation: Vec3::ZERO,
        scale: 1.0,
    };

    /// `self ∘ other`.
    pub fn compose(&self, other: &Self) -> Self {
        Self {
            rotation: (self.rotation * other.rotation).normalize(),
            translation: self.translation + self.rotation * (self.scale * other.translation),
            scale: self.scale * other.scale,
        }
    }

    /// The inverse transform.
    pub fn inverse(&self) -> Self {
        let rotation = self.rotation.conjugate();
        Self {
            rotation,
            translation: -(rotation * self.translation) / self.scale,
            scale: 1.0 / self.scale,
        }
    }

    /// Applies the transform to a point.
    pub fn transform_point(&self, p: Vec3) -> Vec3 {
        self.rotation * (self.scale * p) + self.translation
    }

    /// As a general affine matrix.
    pub fn to_affine(&self) -> Affine3A {
        Affine3A::from_mat3_translation(
            Mat3::from_quat(self.rotation) * self.scale,
            self.translation,
        )
    }
}

/// One joint of a skeleton.
#[derive(Clone, Debug, PartialEq)]
pub struct Joint {
    pub name: String,
    /// Index of the parent, which always precedes the joint.
    pub parent: Option<usize>,
    /// Rest translation relative to the parent's frame (metres).
    pub offset: Vec3,
    /// Rest rotation relative to the parent's frame.
    pub pre_rotation: Quat,
}

/// A joint's pose on top of its rest transform.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointPose {
    /// Added to the rest offset (parent frame, metres).
    pub translation: Vec3,
    /// Applied after the pre-rotation.
    pub rotation: Quat,
    /// log₂ of the uniform scale.
    pub log2_scale: f32,
}

impl JointPose {
    pub const REST: Self = Self {
        translation: Vec3::ZERO,
        rotation: Quat::IDENTITY,
        log2_scale: 0.0,
    };

    /// From Momentum joint parameters `[tx, ty, tz, rx, ry, rz, s]`.
    pub fn from_momentum(p: &[f32; PARAMS_PER_JOINT]) -> Self {
        Self {
            translation: Vec3::new(p[0], p[1], p[2]),
            rotation: euler_xyz(p[3], p[4], p[5]),
            log2_scale: p[6],
        }
    }
}

/// `Rz(z) · Ry(y) · Rx(x)`: rotate about x first, then y, then z (Momentum's "XYZ" Euler order).
pub fn euler_xyz(x: f32, y: f32, z: f32) -> Quat {
    Quat::from_rotation_z(z) * Quat::from_rotation_y(y) * Quat::from_rotation_x(x)
}

/// A joint hierarchy.
#[derive(Clone, Debug, PartialEq)]
pub struct Skeleton {
    joints: Vec<Joint>,
}

impl Skeleton {
    /// Checks that parents precede children, names are unique and values are finite.
    pub fn new(joints: Vec<Joint>) -> Result<Self, RigError> {
        let mut names = std::collections::HashSet::new();
        for (i, j) in joints.iter().enumerate() {
            if !names.insert(j.name.as_str()) {
                return Err(RigError::Model(format!(
                    "joint name `{}` is used twice",
                    j.name
                )));
            }
            if let Some(p) = j.parent
                && p >= i
            {
                return Err(RigError::Model(format!(
                    "joint `{}` (index {i}) has parent index {p}: parents must come first",
                    j.name
                )));
            }
            if !j.offset.is_finite() || !j.pre_rotation.is_finite() {
                return Err(RigError::Model(format!(
                    "joint `{}` has a non-finite rest transform",
                    j.name
                )));
            }
        }
        Ok(Self { joints })
    }

    /// The joints, parents first.
    pub fn joints(&self) -> &[Joint] {
        &self.joints
    }

    /// Number of joints.
    pub fn len(&self) -> usize {
        self.joints.len()
    }

    /// True for a skeleton without joints.
    pub fn is_empty(&self) -> bool {
        self.joints.is_empty()
    }

    /// Index of the joint called `name`.
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.joints.iter().position(|j| j.name == name)
    }

    /// World transforms for `poses`, using `offsets` instead of the stored rest offsets when
    /// given (shape-dependent skeletons).
    pub fn forward(&self, poses: &[JointPose], offsets: Option<&[Vec3]>) -> Vec<Similarity> {
        let mut world: Vec<Similarity> = Vec::with_capacity(self.joints.len());
        for (i, (joint, pose)) in self.joints.iter().zip(poses).enumerate() {
            let offset = offsets.map_or(joint.offset, |o| o[i]);
            let local = Similarity {
                rotation: (joint.pre_rotation * pose.rotation).normalize(),
                translation: offset + pose.translation,
                scale: pose.log2_scale.exp2(),
            };
            let w = match joint.parent {
                Some(p) => world[p].compose(&local),
                None => local,
            };
            world.push(w);
        }
        world
    }

    /// World transforms at the rest pose.
    pub fn rest(&self, offsets: Option<&[Vec3]>) -> Vec<Similarity> {
        self.forward(&vec![JointPose::REST; self.joints.len()], offsets)
    }

    /// Whether joint `ancestor` is `joint` itself or one of its ancestors.
    pub fn is_ancestor_or_self(&self, ancestor: usize, joint: usize) -> bool {
        let mut j = Some(joint);
        while let Some(i) = j {
            if i == ancestor {
                return true;
            }
            j = self.joints[i].parent;
        }
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chain() -> Skeleton {
        Skeleton::new(vec![
            Joint {
                name: "root".into(),
                parent: None,
                offset: Vec3::new(0.0, 1.0, 0.0),
                pre_rotation: Quat::IDENTITY,
            },
            Joint {
                name: "a".into(),
                parent: Some(0),
                offset: Vec3::new(0.5, 0.0, 0.0),
                pre_rotation: Quat::from_rotation_y(0.3),
            },
            Joint {
                name: "b".into(),
                parent: Some(1),
                offset: Vec3::new(0.0, -0.4, 0.0),
                pre_rotation: Quat::IDENTITY,
            },
        ])
        .unwrap()
    }

    #[test]
    fn rest_pose_composes_offsets_and_pre_rotations() {
        let w = chain().rest(None);
        assert!((w[1].translation - Vec3::new(0.5, 1.0, 0.0)).length() < 1e-6);
        let expected_b =
            Vec3::new(0.5, 1.0, 0.0) + Quat::from_rotation_y(0.3) * Vec3::new(0.0, -0.4, 0.0);
        assert!((w[2].translation - expected_b).length() < 1e-6);
    }

    #[test]
    fn parent_scale_scales_child_offsets() {
        let s = chain();
        let mut poses = vec![JointPose::REST; 3];
        poses[1].log2_scale = 1.0;
        let w = s.forward(&poses, None);
        // b sits twice as far from a, and is itself scaled by 2.
        assert!(((w[2].translation - w[1].translation).length() - 0.8).abs() < 1e-6);
        assert!((w[2].scale - 2.0).abs() < 1e-6);
    }

    #[test]
    fn euler_order_is_x_then_y_then_z() {
        let q = euler_xyz(0.3, -0.2, 0.7);
        let v = Vec3::new(0.1, 0.2, 0.3);
        let manual = Quat::from_rotation_z(0.7)
            * (Quat::from_rotation_y(-0.2) * (Quat::from_rotation_x(0.3) * v));
        assert!((q * v - manual).length() < 1e-6);
    }

    #[test]
    fn similarity_inverse_and_affine_agree() {
        let s = Similarity {
            rotation: euler_xyz(0.1, 0.5, -0.3),
            translation: Vec3::new(1.0, 2.0, 3.0),
            scale: 1.7,
        };
        let p = Vec3::new(-0.3, 0.4, 0.9);
        assert!((s.inverse().transform_point(s.transform_point(p)) - p).length() < 1e-5);
        assert!((s.to_affine().transform_point3(p) - s.transform_point(p)).length() < 1e-5);
    }

    #[test]
    fn bad_hierarchies_are_rejected() {
        let mut joints = chain().joints().to_vec();
        joints[1].parent = Some(2);
        assert!(
            Skeleton::new(joints)
                .unwrap_err()
                .to_string()
                .contains("parents must come first")
        );
        let mut joints = chain().joints().to_vec();
        joints[2].name = "a".into();
        assert!(
            Skeleton::new(joints)
                .unwrap_err()
                .to_string()
                .contains("used twice")
        );
    }
}
