//! The general skinned rig every body model loads into, and its evaluation.
//!
//! Evaluation order: pose parameters → joint poses; rest mesh = template + identity and
//! expression blend shapes + pose correctives; rest skeleton (fixed, or regressed from the
//! identity/expression when the model has a joint model); forward kinematics at the pose and
//! at rest; skinning transforms `world · rest⁻¹` (or the file's inverse bind matrices);
//! linear blend skinning.

use glam::{Affine3A, Quat, Vec3};

use crate::RigError;
use crate::blend::BlendShapes;
use crate::correctives::PoseCorrectives;
use crate::params::ParameterTransform;
use crate::roles::Roles;
use crate::skeleton::{JointPose, Similarity, Skeleton};
use crate::skin::{SkinWeights, skin_points};

/// How a model's pose parameter vector maps to joint poses.
#[derive(Clone, Debug, PartialEq)]
pub enum Parameterization {
    /// Momentum: a linear parameter transform to `[tx, ty, tz, rx, ry, rz, sc]` per joint.
    Momentum(ParameterTransform),
    /// SMPL family: an axis-angle vector per joint (in joint order), then the root translation.
    AxisAngle,
}

/// Rest joint positions as a linear function of the shape coefficients (SMPL-X's
/// `J_regressor · v_shaped`, the built-in human's joint-cube centres). Requires rest frames
/// aligned with the world (no pre-rotations).
#[derive(Clone, Debug, PartialEq)]
pub struct JointModel {
    /// World rest positions at zero coefficients, one per joint.
    pub base: Vec<Vec3>,
    /// `[identity shapes · joints]` position offsets.
    pub identity: Vec<Vec3>,
    /// `[expression shapes · joints]` position offsets.
    pub expression: Vec<Vec3>,
}

/// A triangle mesh.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
}

/// A skinned body model.
#[derive(Clone, Debug)]
pub struct Rig {
    pub name: String,
    pub skeleton: Skeleton,
    pub parameterization: Parameterization,
    /// Template mesh at zero parameters.
    pub mesh: Mesh,
    pub identity: BlendShapes,
    pub expression: BlendShapes,
    pub skin: SkinWeights,
    pub correctives: Option<PoseCorrectives>,
    pub joint_model: Option<JointModel>,
    /// Inverse bind matrices from a file; when absent, the inverse of the rest pose.
    pub inverse_bind: Option<Vec<Affine3A>>,
    /// The joint of each role the model has (the body-model contract, [`crate::body`]).
    pub roles: Roles,
    /// Per vertex: whether it is skin, part of the canonical template (not teeth, say).
    pub surface: Vec<bool>,
}

/// Parameters of a rig: pose, identity and expression blocks.
#[derive(Clone, Debug, PartialEq)]
pub struct RigParams {
    pub pose: Vec<f32>,
    pub identity: Vec<f32>,
    pub expression: Vec<f32>,
}

/// A posed rig.
#[derive(Clone, Debug)]
pub struct Posed {
    /// Rest mesh with blend shapes and correctives, before skinning.
    pub rest_vertices: Vec<Vec3>,
    /// Posed mesh.
    pub vertices: Vec<Vec3>,
    /// World transforms of the joints.
    pub joints: Vec<Similarity>,
    /// Rest-to-posed transform of each joint, `world · inverse_bind`.
    pub skinning: Vec<Affine3A>,
}

impl Posed {
    /// The posed mesh's axis-aligned bounds, `(min, max)`: its lowest point (`min.y`) is where
    /// it stands.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.vertices
            .iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), v| {
                (lo.min(*v), hi.max(*v))
            })
    }
}

impl Rig {
    /// Number of pose parameters.
    pub fn num_pose_params(&self) -> usize {
        match &self.parameterization {
            Parameterization::Momentum(t) => t.len(),
            Parameterization::AxisAngle => 3 * self.skeleton.len() + 3,
        }
    }

    /// Names of the pose parameters.
    pub fn pose_param_names(&self) -> Vec<String> {
        match &self.parameterization {
            Parameterization::Momentum(t) => t.names.clone(),
            Parameterization::AxisAngle => self
                .skeleton
                .joints()
                .iter()
                .flat_map(|j| ["x", "y", "z"].map(|a| format!("{}_{a}", j.name)))
                .chain(["transl_x", "transl_y", "transl_z"].map(String::from))
                .collect(),
        }
    }

    /// All-zero parameters (the rest pose, the template identity, a neutral face).
    pub fn zero_params(&self) -> RigParams {
        RigParams {
            pose: vec![0.0; self.num_pose_params()],
            identity: vec![0.0; self.identity.len()],
            expression: vec![0.0; self.expression.len()],
        }
    }

    /// Checks internal consistency; loaders call it before returning a rig.
    pub fn validate(&self) -> Result<(), RigError> {
        let (v, j) = (self.mesh.vertices.len(), self.skeleton.len());
        let bad = |m: String| Err(RigError::Model(format!("{}: {m}", self.name)));
        if self.skin.len() != v {
            return bad(format!(
                "{} skin-weight rows for {v} vertices",
                self.skin.len()
            ));
        }
        if let Some(row) = self
            .skin
            .joints
            .iter()
            .position(|js| js.iter().any(|&x| x as usize >= j))
        {
            return bad(format!("vertex {row} is skinned to a joint index ≥ {j}"));
        }
        if let Some(t) = self
            .mesh
            .triangles
            .iter()
            .position(|t| t.iter().any(|&x| x as usize >= v))
        {
            return bad(format!("triangle {t} references a vertex index ≥ {v}"));
        }
        if self.mesh.vertices.iter().any(|p| !p.is_finite()) {
            return bad("non-finite template vertex".into());
        }
        for (block, shapes) in [
            ("identity", &self.identity),
            ("expression", &self.expression),
        ] {
            if shapes.deltas.len() != shapes.len() * v {
                return bad(format!(
                    "{block} blend shapes do not match the vertex count"
                ));
            }
        }
        if let Parameterization::Momentum(t) = &self.parameterization
            && t.offsets.len() != j * crate::skeleton::PARAMS_PER_JOINT
        {
            return bad(format!(
                "parameter transform has {} rows for {j} joints",
                t.offsets.len()
            ));
        }
        if let Some(m) = &self.joint_model {
            if m.base.len() != j
                || m.identity.len() != self.identity.len() * j
                || m.expression.len() != self.expression.len() * j
            {
                return bad("joint model sizes do not match the joints and blend shapes".into());
            }
            if self
                .skeleton
                .joints()
                .iter()
                .any(|jt| jt.pre_rotation != Quat::IDENTITY)
            {
                return bad(
                    "a joint model needs world-aligned rest frames (identity pre-rotations)".into(),
                );
            }
        }
        if self.surface.len() != v {
            return bad(format!(
                "{} surface flags for {v} vertices",
                self.surface.len()
            ));
        }
        if let Err(e) = self.roles.validate(j) {
            return bad(e);
        }
        if let Some(ibm) = &self.inverse_bind
            && ibm.len() != j
        {
            return bad(format!(
                "{} inverse bind matrices for {j} joints",
                ibm.len()
            ));
        }
        if let Some(c) = &self.correctives {
            let rows = c.features(j);
            let (weights, expected) = match c {
                PoseCorrectives::Linear { posedirs, .. } => (posedirs.len(), rows * 3 * v),
                PoseCorrectives::Mlp { dense, hidden, .. } => (dense.len(), hidden * 3 * v),
            };
            if weights != expected {
                return bad(format!(
                    "pose correctives have {weights} weights, expected {expected}"
                ));
            }
        }
        Ok(())
    }

    fn check_params(&self, p: &RigParams) -> Result<(), RigError> {
        for (block, got, expected) in [
            ("pose", &p.pose, self.num_pose_params()),
            ("identity", &p.identity, self.identity.len()),
            ("expression", &p.expression, self.expression.len()),
        ] {
            if got.len() != expected {
                return Err(RigError::Params(format!(
                    "{} has {} {block} parameters, {} given",
                    self.name,
                    expected,
                    got.len()
                )));
            }
            if let Some(i) = got.iter().position(|v| !v.is_finite()) {
                return Err(RigError::Params(format!(
                    "{block} parameter {i} is not finite"
                )));
            }
        }
        Ok(())
    }

    /// Joint poses for a pose parameter vector.
    pub fn joint_poses(&self, pose: &[f32]) -> Result<Vec<JointPose>, RigError> {
        match &self.parameterization {
            Parameterization::Momentum(t) => Ok(t
                .apply(pose)?
                .iter()
                .map(JointPose::from_momentum)
                .collect()),
            Parameterization::AxisAngle => {
                let j = self.skeleton.len();
                if pose.len() != 3 * j + 3 {
                    return Err(RigError::Params(format!(
                        "{} pose parameters given, expected {}",
                        pose.len(),
                        3 * j + 3
                    )));
                }
                let mut poses: Vec<JointPose> = pose[..3 * j]
                    .chunks_exact(3)
                    .map(|a| JointPose {
                        rotation: axis_angle(Vec3::new(a[0], a[1], a[2])),
                        ..JointPose::REST
                    })
                    .collect();
                poses[0].translation = Vec3::new(pose[3 * j], pose[3 * j + 1], pose[3 * j + 2]);
                Ok(poses)
            }
        }
    }

    /// Rest offsets of the skeleton for a shape, when the model has a joint model.
    pub fn shaped_offsets(&self, identity: &[f32], expression: &[f32]) -> Option<Vec<Vec3>> {
        let m = self.joint_model.as_ref()?;
        let j = self.skeleton.len();
        let mut positions = m.base.clone();
        for (coeffs, deltas) in [(identity, &m.identity), (expression, &m.expression)] {
            for (s, &c) in coeffs.iter().enumerate() {
                for (p, d) in positions.iter_mut().zip(&deltas[s * j..(s + 1) * j]) {
                    *p += *d * c;
                }
            }
        }
        Some(
            self.skeleton
                .joints()
                .iter()
                .enumerate()
                .map(|(i, joint)| positions[i] - joint.parent.map_or(Vec3::ZERO, |p| positions[p]))
                .collect(),
        )
    }

    /// The rest mesh for given parameters (blend shapes and pose correctives, no skinning).
    pub fn rest_vertices(&self, p: &RigParams, poses: &[JointPose]) -> Vec<Vec3> {
        let mut v = self.mesh.vertices.clone();
        self.identity.apply(&p.identity, &mut v);
        self.expression.apply(&p.expression, &mut v);
        if let Some(c) = &self.correctives {
            c.apply(poses, &mut v);
        }
        v
    }

    /// Skinning transforms (`world · inverse_bind`) and world joint transforms.
    pub fn skinning_transforms(
        &self,
        p: &RigParams,
        poses: &[JointPose],
    ) -> (Vec<Affine3A>, Vec<Similarity>) {
        let offsets = self.shaped_offsets(&p.identity, &p.expression);
        let world = self.skeleton.forward(poses, offsets.as_deref());
        let skinning = match &self.inverse_bind {
            Some(ibm) => world
                .iter()
                .zip(ibm)
                .map(|(w, b)| w.to_affine() * *b)
                .collect(),
            None => {
                let rest = self.skeleton.rest(offsets.as_deref());
                world
                    .iter()
                    .zip(&rest)
                    .map(|(w, r)| w.compose(&r.inverse()).to_affine())
                    .collect()
            }
        };
        (skinning, world)
    }

    /// Evaluates the model.
    pub fn pose(&self, p: &RigParams) -> Result<Posed, RigError> {
        self.check_params(p)?;
        let poses = self.joint_poses(&p.pose)?;
        let rest_vertices = self.rest_vertices(p, &poses);
        let (skinning, joints) = self.skinning_transforms(p, &poses);
        let vertices = skin_points(&skinning, &self.skin, &rest_vertices);
        Ok(Posed {
            rest_vertices,
            vertices,
            joints,
            skinning,
        })
    }

    /// Transforms taking points posed at `from` to the same points posed at `to`:
    /// `skin_to · skin_from⁻¹` per joint (e.g. canonical pose → a frame's pose).
    pub fn relative_transforms(from: &Posed, to: &Posed) -> Vec<Affine3A> {
        from.skinning
            .iter()
            .zip(&to.skinning)
            .map(|(f, t)| *t * f.inverse())
            .collect()
    }

    /// Vertex normals of a posed mesh (area-weighted).
    pub fn vertex_normals(&self, vertices: &[Vec3]) -> Vec<Vec3> {
        vertex_normals(vertices, &self.mesh.triangles)
    }
}

/// Area-weighted vertex normals of a triangle mesh.
pub fn vertex_normals(vertices: &[Vec3], triangles: &[[u32; 3]]) -> Vec<Vec3> {
    let mut n = vec![Vec3::ZERO; vertices.len()];
    for t in triangles {
        let [a, b, c] = t.map(|i| vertices[i as usize]);
        let face = (b - a).cross(c - a);
        for &i in t {
            n[i as usize] += face;
        }
    }
    n.iter().map(|v| v.normalize_or_zero()).collect()
}

/// Rotation from an axis-angle vector (angle = length).
pub fn axis_angle(v: Vec3) -> Quat {
    let angle = v.length();
    if angle < 1e-12 {
        Quat::IDENTITY
    } else {
        Quat::from_axis_angle(v / angle, angle)
    }
}
