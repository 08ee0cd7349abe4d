//! The built-in human: the MakeHuman base mesh (CC0) with its default rig, skin weights and
//! expression/identity targets, converted by `tools/convert_makehuman.py` into
//! `assets/builtin_human.npz` and compiled into the binary, so it works offline everywhere.
//!
//! Frame: metres, +Y up, the body faces +Z, its left side is +X; the pelvis is near the origin.
//! Rest frames are world-aligned (no pre-rotations, as in SMPL), so a joint's `rx` bends about
//! the world X axis at rest. The rest skeleton follows the identity and expression shapes
//! (each joint is the centre of a MakeHuman joint cube or vertex set).
//!
//! Parts (see [`BuiltinHuman::vertex_part`]): `body`, `eye_l`, `eye_r`, `teeth_upper`,
//! `teeth_lower`, `tongue`, `skirt` (a garment helper that does not hug the body). Joint cubes,
//! tights, eyelashes, the genital helper and the long-hair helper (it hangs over the face) are
//! dropped.
//!
//! Pose parameters (`{joint}_{channel}`):
//! - `root_tx, root_ty, root_tz, root_rx, root_ry, root_rz`: global translation and rotation;
//! - `rx, ry, rz` for the spine, neck, head, clavicles, shoulders, arms, wrists, fingers,
//!   pelvis, legs and feet (not breasts, metacarpals or toes, which follow their parents);
//! - face joints: `jaw_rx` (positive opens the mouth), `jaw_ry`, `jaw_rz`; `eye.L_rx`,
//!   `eye.L_ry` (and `.R`) turn the eyeballs; `orbicularis03.L_rx` closes the upper eyelid and
//!   `orbicularis04.L_rx` (negative) raises the lower one (and `.R`).
//!
//! Identity shapes (coefficient 0 = MakeHuman's default human): `gender` (+1 male, −1 female),
//! `weight`, `muscle`, `age` (1 = old) and `height` (1 = MakeHuman's maximum, +0.69 m).
//! Expression shapes: the 34 MakeHuman expression units (`eye-left-closure` blinks,
//! `mouth-open`, `mouth-corner-puller` smiles, `eyebrows-left-up`, ...); see
//! [`BuiltinHuman::rig`]`.expression.names`.

use glam::{Quat, Vec3};

use crate::params::ParameterTransform;
use crate::rig::{JointModel, Mesh, Parameterization, Rig};
use crate::roles::{Role, Roles};
use crate::skeleton::{Joint, Skeleton};
use crate::{BlendShapes, RigError, SkinWeights};

const ASSET: &[u8] = include_bytes!("../../../assets/builtin_human.npz");
const LABEL: &str = "assets/builtin_human.npz";

/// Joints without pose parameters outside the head: they follow their parents.
fn is_fixed_body_joint(name: &str) -> bool {
    name.starts_with("breast") || name.starts_with("toe") || name.starts_with("metacarpal")
}

/// Rotation channels of face joints that are posable.
const FACE_DOFS: [(&str, &[usize]); 9] = [
    ("jaw", &[3, 4, 5]),
    ("eye.L", &[3, 4]),
    ("eye.R", &[3, 4]),
    ("orbicularis03.L", &[3]),
    ("orbicularis03.R", &[3]),
    ("orbicularis04.L", &[3]),
    ("orbicularis04.R", &[3]),
    ("head", &[3, 4, 5]),
    ("root", &[0, 1, 2, 3, 4, 5]),
];

/// The parts whose vertices are skin (the template's surface): teeth, tongue and the skirt
/// helper are not.
const SKIN_PARTS: [&str; 3] = ["body", "eye_l", "eye_r"];

/// The joints of the body-model roles (MakeHuman's default rig).
const ROLES: [(Role, &str); 22] = [
    (Role::Pelvis, "root"),
    (Role::Spine, "spine03"),
    (Role::Chest, "spine01"),
    (Role::Neck, "neck01"),
    (Role::Head, "head"),
    (Role::Jaw, "jaw"),
    (Role::LeftEye, "eye.L"),
    (Role::RightEye, "eye.R"),
    (Role::LeftClavicle, "clavicle.L"),
    (Role::RightClavicle, "clavicle.R"),
    (Role::LeftShoulder, "upperarm01.L"),
    (Role::RightShoulder, "upperarm01.R"),
    (Role::LeftElbow, "lowerarm01.L"),
    (Role::RightElbow, "lowerarm01.R"),
    (Role::LeftWrist, "wrist.L"),
    (Role::RightWrist, "wrist.R"),
    (Role::LeftHip, "upperleg01.L"),
    (Role::RightHip, "upperleg01.R"),
    (Role::LeftKnee, "lowerleg01.L"),
    (Role::RightKnee, "lowerleg01.R"),
    (Role::LeftAnkle, "foot.L"),
    (Role::RightAnkle, "foot.R"),
];

/// The built-in human and the extra per-vertex data the synthetic capture uses.
#[derive(Clone, Debug)]
pub struct BuiltinHuman {
    pub rig: Rig,
    /// Part index of every vertex, into [`BuiltinHuman::part_names`].
    pub vertex_part: Vec<u8>,
    pub part_names: Vec<String>,
    /// Texture coordinates and, per triangle corner, the index into them.
    pub uvs: Vec<[f32; 2]>,
    pub triangle_uvs: Vec<[u32; 3]>,
}

impl BuiltinHuman {
    /// Index of the part called `name`.
    pub fn part(&self, name: &str) -> Option<u8> {
        self.part_names
            .iter()
            .position(|p| p == name)
            .map(|p| p as u8)
    }
}

#[derive(serde::Deserialize)]
struct Meta {
    parts: Vec<String>,
    joint_names: Vec<String>,
    identity_names: Vec<String>,
    expression_names: Vec<String>,
}

fn io(e: f3g_io::IoError) -> RigError {
    RigError::File {
        file: e.path,
        reason: e.reason,
    }
}

fn vec3s(v: &[f32]) -> Vec<Vec3> {
    v.chunks_exact(3)
        .map(|c| Vec3::new(c[0], c[1], c[2]))
        .collect()
}

/// Loads the built-in human.
pub fn load() -> Result<BuiltinHuman, RigError> {
    let mut npz = f3g_io::Npz::from_bytes(ASSET, LABEL).map_err(io)?;
    let (_, meta_bytes) = npz.i64("meta_json").map_err(io)?;
    let meta_bytes: Vec<u8> = meta_bytes.into_iter().map(|b| b as u8).collect();
    let meta: Meta = serde_json::from_slice(&meta_bytes)
        .map_err(|e| RigError::field(LABEL.as_ref(), "meta_json", e))?;

    let vertices = vec3s(&npz.f32("vertices").map_err(io)?.1);
    let triangles: Vec<[u32; 3]> = npz
        .i64("triangles")
        .map_err(io)?
        .1
        .chunks_exact(3)
        .map(|t| [t[0] as u32, t[1] as u32, t[2] as u32])
        .collect();
    let parents = npz.i64("joint_parents").map_err(io)?.1;
    let positions = vec3s(&npz.f32("joint_positions").map_err(io)?.1);
    let joints: Vec<Joint> = meta
        .joint_names
        .iter()
        .enumerate()
        .map(|(i, name)| {
            let parent = usize::try_from(parents[i]).ok();
            Joint {
                name: name.clone(),
                parent,
                offset: positions[i] - parent.map_or(Vec3::ZERO, |p| positions[p]),
                pre_rotation: Quat::IDENTITY,
            }
        })
        .collect();
    let skeleton = Skeleton::new(joints)?;

    let skin_joints = npz.i64("skin_joints").map_err(io)?.1;
    let skin_weights = npz.f32("skin_weights").map_err(io)?.1;
    let lists: Vec<Vec<(usize, f32)>> = skin_joints
        .chunks_exact(crate::MAX_INFLUENCES)
        .zip(skin_weights.chunks_exact(crate::MAX_INFLUENCES))
        .map(|(j, w)| j.iter().zip(w).map(|(&j, &w)| (j as usize, w)).collect())
        .collect();
    let skin = SkinWeights::from_lists(&lists, skeleton.len())?;

    let n = vertices.len();
    let identity = BlendShapes::new(
        meta.identity_names.clone(),
        vec3s(&npz.f32("identity_shapes").map_err(io)?.1),
        n,
    )?;
    let expression = BlendShapes::new(
        meta.expression_names.clone(),
        vec3s(&npz.f32("expression_shapes").map_err(io)?.1),
        n,
    )?;
    let joint_model = JointModel {
        base: positions,
        identity: vec3s(&npz.f32("identity_joint_deltas").map_err(io)?.1),
        expression: vec3s(&npz.f32("expression_joint_deltas").map_err(io)?.1),
    };

    let vertex_part: Vec<u8> = npz
        .i64("vertex_part")
        .map_err(io)?
        .1
        .into_iter()
        .map(|p| p as u8)
        .collect();
    let skin_parts: Vec<u8> = SKIN_PARTS
        .iter()
        .filter_map(|name| meta.parts.iter().position(|p| p == name))
        .map(|p| p as u8)
        .collect();
    let rig = Rig {
        name: "builtin".into(),
        parameterization: Parameterization::Momentum(parameter_transform(&skeleton)),
        roles: Roles::from_names(&skeleton, &ROLES),
        surface: vertex_part.iter().map(|p| skin_parts.contains(p)).collect(),
        skeleton,
        mesh: Mesh {
            vertices,
            triangles,
        },
        identity,
        expression,
        skin,
        correctives: None,
        joint_model: Some(joint_model),
        inverse_bind: None,
    };
    rig.validate()?;

    let uvs: Vec<[f32; 2]> = npz
        .f32("uvs")
        .map_err(io)?
        .1
        .chunks_exact(2)
        .map(|c| [c[0], c[1]])
        .collect();
    let triangle_uvs = npz
        .i64("triangle_uvs")
        .map_err(io)?
        .1
        .chunks_exact(3)
        .map(|t| [t[0] as u32, t[1] as u32, t[2] as u32])
        .collect();
    Ok(BuiltinHuman {
        rig,
        vertex_part,
        part_names: meta.parts,
        uvs,
        triangle_uvs,
    })
}

/// The pose parameters listed in the module docs.
fn parameter_transform(skeleton: &Skeleton) -> ParameterTransform {
    let mut t = ParameterTransform::empty(skeleton.len());
    let head = skeleton.index_of("head");
    for (j, joint) in skeleton.joints().iter().enumerate() {
        let in_head = head.is_some_and(|h| h != j && skeleton.is_ancestor_or_self(h, j));
        let channels: &[usize] = match FACE_DOFS.iter().find(|(n, _)| *n == joint.name) {
            Some((_, c)) => c,
            None if in_head || is_fixed_body_joint(&joint.name) => &[],
            None => &[3, 4, 5],
        };
        for &c in channels {
            t.add_parameter(
                format!("{}_{}", joint.name, crate::params::CHANNELS[c]),
                &[(j, c, 1.0)],
            );
        }
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loads_with_the_documented_parts_and_controls() {
        let h = load().unwrap();
        let rig = &h.rig;
        assert_eq!(
            h.part_names,
            [
                "body",
                "eye_l",
                "eye_r",
                "teeth_upper",
                "teeth_lower",
                "tongue",
                "skirt"
            ]
        );
        assert_eq!(h.vertex_part.len(), rig.mesh.vertices.len());
        assert_eq!(rig.skeleton.len(), 163);
        let names = rig.pose_param_names();
        for p in [
            "root_tx",
            "jaw_rx",
            "eye.L_ry",
            "orbicularis03.R_rx",
            "upperleg01.L_rz",
            "finger2-1.R_rx",
        ] {
            assert!(names.iter().any(|n| n == p), "missing {p}");
        }
        assert!(
            !names
                .iter()
                .any(|n| n.starts_with("tongue") || n.starts_with("toe"))
        );
        assert!(rig.expression.names.iter().any(|n| n == "eye-left-closure"));
        assert_eq!(
            rig.identity.names,
            ["gender", "weight", "muscle", "age", "height"]
        );
        // About 1.7 m tall, facing +Z.
        let (lo, hi) = rig
            .mesh
            .vertices
            .iter()
            .fold((Vec3::MAX, Vec3::MIN), |(a, b), v| (a.min(*v), b.max(*v)));
        assert!((hi.y - lo.y - 1.66).abs() < 0.05, "height {}", hi.y - lo.y);
        let eye = rig.skeleton.index_of("eye.L").unwrap();
        let head = rig.skeleton.index_of("head").unwrap();
        let rest = rig.skeleton.rest(None);
        assert!(
            rest[eye].translation.z > rest[head].translation.z && rest[eye].translation.x > 0.0
        );
    }
}
