//! SMPL-X: the official model `.npz` and `smpl_params.npz` sequences.
//!
//! The model file (which users supply; it cannot be redistributed) holds `v_template (V,3)`,
//! `shapedirs (V,3,S)` (shape directions, then expression directions: S = 400 in v1.1 with
//! expressions from column 300, S = 20 in v1.0 with expressions from column 10), `posedirs
//! (V,3,486)`, `J_regressor (55,V)`, `weights (V,55)`, `kintree_table (2,55)` and `f (F,3)`.
//!
//! It loads into a [`Rig`] with the axis-angle parameterisation: pose = 55 axis-angle vectors
//! (global orientation, 21 body joints, jaw, left eye, right eye, 15 + 15 finger joints) then
//! the translation; identity = betas; expression = expression coefficients; the rest skeleton is
//! regressed from the shaped template; pose correctives are `posedirs · vec(R − I)` over joints
//! 1..54. Hand poses are absolute (`flat_hand_mean=True`, as AvatarReX and THuman4.0 use).

use std::path::Path;

use glam::{Quat, Vec3};

use crate::correctives::PoseCorrectives;
use crate::rig::{JointModel, Mesh, Parameterization, Rig, RigParams};
use crate::roles::{Role, Roles};
use crate::skeleton::{Joint, Skeleton};
use crate::{BlendShapes, RigError, SkinWeights};

/// SMPL-X joint names in model order.
pub const JOINT_NAMES: [&str; 55] = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "jaw",
    "left_eye",
    "right_eye",
    "left_index1",
    "left_index2",
    "left_index3",
    "left_middle1",
    "left_middle2",
    "left_middle3",
    "left_pinky1",
    "left_pinky2",
    "left_pinky3",
    "left_ring1",
    "left_ring2",
    "left_ring3",
    "left_thumb1",
    "left_thumb2",
    "left_thumb3",
    "right_index1",
    "right_index2",
    "right_index3",
    "right_middle1",
    "right_middle2",
    "right_middle3",
    "right_pinky1",
    "right_pinky2",
    "right_pinky3",
    "right_ring1",
    "right_ring2",
    "right_ring3",
    "right_thumb1",
    "right_thumb2",
    "right_thumb3",
];

const JOINTS: usize = 55;

/// The joints of the body-model roles.
const ROLES: [(Role, &str); 22] = [
    (Role::Pelvis, "pelvis"),
    (Role::Spine, "spine1"),
    (Role::Chest, "spine3"),
    (Role::Neck, "neck"),
    (Role::Head, "head"),
    (Role::Jaw, "jaw"),
    (Role::LeftEye, "left_eye"),
    (Role::RightEye, "right_eye"),
    (Role::LeftClavicle, "left_collar"),
    (Role::RightClavicle, "right_collar"),
    (Role::LeftShoulder, "left_shoulder"),
    (Role::RightShoulder, "right_shoulder"),
    (Role::LeftElbow, "left_elbow"),
    (Role::RightElbow, "right_elbow"),
    (Role::LeftWrist, "left_wrist"),
    (Role::RightWrist, "right_wrist"),
    (Role::LeftHip, "left_hip"),
    (Role::RightHip, "right_hip"),
    (Role::LeftKnee, "left_knee"),
    (Role::RightKnee, "right_knee"),
    (Role::LeftAnkle, "left_ankle"),
    (Role::RightAnkle, "right_ankle"),
];

fn io(e: f3g_io::IoError) -> RigError {
    RigError::File {
        file: e.path,
        reason: e.reason,
    }
}

fn expect_shape(
    file: &Path,
    field: &str,
    got: &[usize],
    expected: &[Option<usize>],
) -> Result<(), RigError> {
    let ok = got.len() == expected.len()
        && got
            .iter()
            .zip(expected)
            .all(|(g, e)| e.is_none_or(|e| e == *g));
    if ok {
        return Ok(());
    }
    let text: Vec<String> = expected
        .iter()
        .map(|e| e.map_or("*".into(), |v| v.to_string()))
        .collect();
    Err(RigError::field(
        file,
        field,
        format!("has shape {got:?}, expected ({})", text.join(", ")),
    ))
}

fn finite(file: &Path, field: &str, values: &[f32]) -> Result<(), RigError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(RigError::field(
            file,
            field,
            format!("non-finite value at flat index {i}"),
        )),
        None => Ok(()),
    }
}

fn vec3s(v: &[f32]) -> Vec<Vec3> {
    v.chunks_exact(3)
        .map(|c| Vec3::new(c[0], c[1], c[2]))
        .collect()
}

/// Loads an SMPL-X model file with `num_betas` identity and `num_expression` expression shapes.
pub fn load(path: &Path, num_betas: usize, num_expression: usize) -> Result<Rig, RigError> {
    let mut npz = f3g_io::Npz::open(path).map_err(io)?;
    let mut get = |name: &str| -> Result<(Vec<usize>, Vec<f32>), RigError> {
        let (shape, values) = npz.f32(name).map_err(io)?;
        finite(path, name, &values)?;
        Ok((shape, values))
    };
    let (shape, template) = get("v_template")?;
    expect_shape(path, "v_template", &shape, &[None, Some(3)])?;
    let v = shape[0];
    let (shape, shapedirs) = get("shapedirs")?;
    expect_shape(path, "shapedirs", &shape, &[Some(v), Some(3), None])?;
    let columns = shape[2];
    let expression_start = if columns >= 400 { 300 } else { 10 };
    if num_betas > expression_start || expression_start + num_expression > columns {
        return Err(RigError::field(
            path,
            "shapedirs",
            format!(
                "{columns} shape columns cannot hold {num_betas} betas (before column {expression_start}) and {num_expression} expressions"
            ),
        ));
    }
    let (shape, posedirs) = get("posedirs")?;
    expect_shape(
        path,
        "posedirs",
        &shape,
        &[Some(v), Some(3), Some(9 * (JOINTS - 1))],
    )?;
    let (shape, regressor) = get("J_regressor")?;
    expect_shape(path, "J_regressor", &shape, &[Some(JOINTS), Some(v)])?;
    let (shape, weights) = get("weights")?;
    expect_shape(path, "weights", &shape, &[Some(v), Some(JOINTS)])?;
    let (shape, kintree) = npz.i64("kintree_table").map_err(io)?;
    expect_shape(path, "kintree_table", &shape, &[Some(2), Some(JOINTS)])?;
    let (shape, faces) = npz.i64("f").map_err(io)?;
    expect_shape(path, "f", &shape, &[None, Some(3)])?;
    if let Some(i) = faces.iter().position(|&x| x < 0 || x as usize >= v) {
        return Err(RigError::field(
            path,
            "f",
            format!(
                "vertex index {} at flat index {i} is outside 0..{v}",
                faces[i]
            ),
        ));
    }

    // Columns `[start, start + count)` of shapedirs as blend shapes.
    let directions = |start: usize, count: usize| -> Vec<Vec3> {
        let at = |i: usize, c: usize, s: usize| shapedirs[(i * 3 + c) * columns + s];
        (start..start + count)
            .flat_map(|s| (0..v).map(move |i| Vec3::new(at(i, 0, s), at(i, 1, s), at(i, 2, s))))
            .collect()
    };
    let betas = directions(0, num_betas);
    let expressions = directions(expression_start, num_expression);
    let regress = |points: &[Vec3]| -> Vec<Vec3> {
        (0..JOINTS)
            .map(|j| (0..v).fold(Vec3::ZERO, |acc, i| acc + points[i] * regressor[j * v + i]))
            .collect()
    };
    let template = vec3s(&template);
    let base = regress(&template);
    let joint_deltas = |shapes: &[Vec3], count: usize| -> Vec<Vec3> {
        (0..count)
            .flat_map(|s| regress(&shapes[s * v..(s + 1) * v]))
            .collect()
    };
    let joint_model = JointModel {
        base: base.clone(),
        identity: joint_deltas(&betas, num_betas),
        expression: joint_deltas(&expressions, num_expression),
    };

    let mut joints = Vec::with_capacity(JOINTS);
    for (j, name) in JOINT_NAMES.iter().enumerate() {
        let parent = kintree[j];
        let parent = if j == 0 {
            None
        } else if parent >= 0 && (parent as usize) < j {
            Some(parent as usize)
        } else {
            return Err(RigError::field(
                path,
                "kintree_table",
                format!("joint {j} has parent {parent}; parents must precede children"),
            ));
        };
        joints.push(Joint {
            name: name.to_string(),
            parent,
            offset: base[j] - parent.map_or(Vec3::ZERO, |p| base[p]),
            pre_rotation: Quat::IDENTITY,
        });
    }

    let lists: Vec<Vec<(usize, f32)>> = (0..v)
        .map(|i| (0..JOINTS).map(|j| (j, weights[i * JOINTS + j])).collect())
        .collect();
    let skin =
        SkinWeights::from_lists(&lists, JOINTS).map_err(|e| RigError::field(path, "weights", e))?;
    // posedirs (V, 3, F) → [F, V·3].
    let features = 9 * (JOINTS - 1);
    let mut correctives = vec![0.0f32; features * v * 3];
    for (k, chunk) in posedirs.chunks_exact(features).enumerate() {
        for (f, &w) in chunk.iter().enumerate() {
            correctives[f * v * 3 + k] = w;
        }
    }
    let skeleton = Skeleton::new(joints)?;
    let rig = Rig {
        name: format!("smplx:{}", path.display()),
        parameterization: Parameterization::AxisAngle,
        mesh: Mesh {
            vertices: template,
            triangles: faces
                .chunks_exact(3)
                .map(|t| [t[0] as u32, t[1] as u32, t[2] as u32])
                .collect(),
        },
        identity: BlendShapes::new(
            (0..num_betas).map(|i| format!("beta{i}")).collect(),
            betas,
            v,
        )?,
        expression: BlendShapes::new(
            (0..num_expression)
                .map(|i| format!("expression{i}"))
                .collect(),
            expressions,
            v,
        )?,
        skin,
        correctives: Some(PoseCorrectives::Linear {
            first_joint: 1,
            posedirs: correctives,
        }),
        joint_model: Some(joint_model),
        inverse_bind: None,
        roles: Roles::from_names(&skeleton, &ROLES),
        surface: vec![true; v],
        skeleton,
    };
    rig.validate()?;
    Ok(rig)
}

/// A sequence of SMPL-X parameters in the `smpl_params.npz` layout (all axis-angle).
#[derive(Clone, Debug, PartialEq)]
pub struct SmplParams {
    pub frames: usize,
    /// `[betas]`, shared by all frames (row 0 of the file).
    pub betas: Vec<f32>,
    /// `[frames, 3]` each.
    pub global_orient: Vec<f32>,
    pub transl: Vec<f32>,
    pub jaw_pose: Vec<f32>,
    pub leye_pose: Vec<f32>,
    pub reye_pose: Vec<f32>,
    /// `[frames, 63]`
    pub body_pose: Vec<f32>,
    /// `[frames, 45]` each.
    pub left_hand_pose: Vec<f32>,
    pub right_hand_pose: Vec<f32>,
    /// `[frames, E]`
    pub expression: Vec<f32>,
}

impl SmplParams {
    /// Number of expression coefficients per frame.
    pub fn num_expression(&self) -> usize {
        self.expression.len().checked_div(self.frames).unwrap_or(0)
    }

    /// The pose vector of frame `i` in the [`Parameterization::AxisAngle`] layout.
    pub fn pose(&self, i: usize) -> Vec<f32> {
        let row = |v: &[f32], width: usize| v[i * width..(i + 1) * width].to_vec();
        [
            row(&self.global_orient, 3),
            row(&self.body_pose, 63),
            row(&self.jaw_pose, 3),
            row(&self.leye_pose, 3),
            row(&self.reye_pose, 3),
            row(&self.left_hand_pose, 45),
            row(&self.right_hand_pose, 45),
            row(&self.transl, 3),
        ]
        .concat()
    }

    /// Every frame's parameters for `rig`, which must have SMPL-X's joints and axis-angle
    /// parameterisation (an SMPL-X model file of any version); otherwise an error that says how
    /// to convert the parameters.
    pub fn frames_for(&self, rig: &Rig) -> Result<Vec<RigParams>, RigError> {
        let names: Vec<&str> = rig
            .skeleton
            .joints()
            .iter()
            .map(|j| j.name.as_str())
            .collect();
        if rig.parameterization != Parameterization::AxisAngle || names != JOINT_NAMES {
            return Err(RigError::Params(format!(
                "SMPL-X parameters do not match the body model `{}` (not an SMPL-X model): \
                 convert them with `f3g rig fit`",
                rig.name
            )));
        }
        Ok((0..self.frames).map(|i| self.frame(i, rig)).collect())
    }

    /// Parameters of frame `i` for an SMPL-X rig (betas and expression padded or cut to its sizes).
    fn frame(&self, i: usize, rig: &Rig) -> RigParams {
        let fit = |v: &[f32], n: usize| {
            (0..n)
                .map(|k| v.get(k).copied().unwrap_or(0.0))
                .collect::<Vec<_>>()
        };
        let e = self.num_expression();
        RigParams {
            pose: self.pose(i),
            identity: fit(&self.betas, rig.identity.len()),
            expression: fit(&self.expression[i * e..(i + 1) * e], rig.expression.len()),
        }
    }
}

/// Reads `smpl_params.npz`. `betas`, `global_orient`, `transl` and `body_pose` are required;
/// `jaw_pose`, `leye_pose`, `reye_pose`, hand poses and `expression` default to zeros.
pub fn read_params(path: &Path) -> Result<SmplParams, RigError> {
    let mut npz = f3g_io::Npz::open(path).map_err(io)?;
    let (shape, transl) = npz.f32("transl").map_err(io)?;
    expect_shape(path, "transl", &shape, &[None, Some(3)])?;
    let frames = shape[0];
    let mut read = |name: &str, width: usize, required: bool| -> Result<Vec<f32>, RigError> {
        if !required && !npz.contains(name) {
            return Ok(vec![0.0; frames * width]);
        }
        let (shape, values) = npz.f32(name).map_err(io)?;
        expect_shape(path, name, &shape, &[Some(frames), Some(width)])?;
        finite(path, name, &values)?;
        Ok(values)
    };
    let global_orient = read("global_orient", 3, true)?;
    let body_pose = read("body_pose", 63, true)?;
    let jaw_pose = read("jaw_pose", 3, false)?;
    let leye_pose = read("leye_pose", 3, false)?;
    let reye_pose = read("reye_pose", 3, false)?;
    let left_hand_pose = read("left_hand_pose", 45, false)?;
    let right_hand_pose = read("right_hand_pose", 45, false)?;
    finite(path, "transl", &transl)?;
    let expression = if npz.contains("expression") {
        let (shape, values) = npz.f32("expression").map_err(io)?;
        expect_shape(path, "expression", &shape, &[Some(frames), None])?;
        finite(path, "expression", &values)?;
        values
    } else {
        Vec::new()
    };
    let (shape, betas) = npz.f32("betas").map_err(io)?;
    let betas = match shape.as_slice() {
        [n] => betas[..*n].to_vec(),
        // Row 0 (fitters write one row per frame or a single row).
        [rows, n] if *rows > 0 => betas[..*n].to_vec(),
        _ => {
            return Err(RigError::field(
                path,
                "betas",
                format!("has shape {shape:?}, expected (B,) or (F, B) with F ≥ 1"),
            ));
        }
    };
    finite(path, "betas", &betas)?;
    Ok(SmplParams {
        frames,
        betas,
        global_orient,
        transl,
        jaw_pose,
        leye_pose,
        reye_pose,
        body_pose,
        left_hand_pose,
        right_hand_pose,
        expression,
    })
}

/// Writes parameters in the `smpl_params.npz` layout.
pub fn write_params(path: &Path, p: &SmplParams) -> Result<(), RigError> {
    use f3g_io::NpyValues::F32;
    let n = p.frames;
    let e = p.num_expression();
    let b = [1, p.betas.len()];
    f3g_io::write_npz(
        path,
        &[
            ("betas", &b, F32(&p.betas)),
            ("global_orient", &[n, 3], F32(&p.global_orient)),
            ("transl", &[n, 3], F32(&p.transl)),
            ("body_pose", &[n, 63], F32(&p.body_pose)),
            ("jaw_pose", &[n, 3], F32(&p.jaw_pose)),
            ("leye_pose", &[n, 3], F32(&p.leye_pose)),
            ("reye_pose", &[n, 3], F32(&p.reye_pose)),
            ("left_hand_pose", &[n, 45], F32(&p.left_hand_pose)),
            ("right_hand_pose", &[n, 45], F32(&p.right_hand_pose)),
            ("expression", &[n, e], F32(&p.expression)),
        ],
    )
    .map_err(io)
}

/// Parents of SMPL-X's joints.
const PARENTS: [i8; 55] = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15, 20, 25,
    26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38, 21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49,
    50, 21, 52, 53,
];

/// Rest positions of the left side and the centre of [`schematic_rest`]; the right side
/// mirrors the left.
const LEFT_AND_CENTRE: [(&str, [f32; 3]); 31] = [
    ("pelvis", [0.0, -0.35, 0.01]),
    ("left_hip", [0.06, -0.44, -0.01]),
    ("spine1", [0.0, -0.24, -0.02]),
    ("left_knee", [0.11, -0.82, 0.0]),
    ("spine2", [0.0, -0.11, 0.0]),
    ("left_ankle", [0.09, -1.22, -0.04]),
    ("spine3", [0.0, -0.05, 0.01]),
    ("left_foot", [0.12, -1.28, 0.08]),
    ("neck", [0.0, 0.17, -0.03]),
    ("left_collar", [0.08, 0.09, -0.01]),
    ("head", [0.0, 0.28, 0.01]),
    ("left_shoulder", [0.18, 0.12, -0.02]),
    ("left_elbow", [0.44, 0.10, -0.03]),
    ("left_wrist", [0.70, 0.10, -0.02]),
    ("jaw", [0.0, 0.22, 0.02]),
    ("left_eye", [0.03, 0.33, 0.08]),
    ("left_index1", [0.80, 0.09, 0.02]),
    ("left_index2", [0.84, 0.09, 0.02]),
    ("left_index3", [0.86, 0.09, 0.02]),
    ("left_middle1", [0.80, 0.09, 0.0]),
    ("left_middle2", [0.84, 0.09, 0.0]),
    ("left_middle3", [0.87, 0.09, 0.0]),
    ("left_pinky1", [0.77, 0.09, -0.04]),
    ("left_pinky2", [0.80, 0.09, -0.04]),
    ("left_pinky3", [0.82, 0.09, -0.04]),
    ("left_ring1", [0.79, 0.09, -0.02]),
    ("left_ring2", [0.83, 0.09, -0.02]),
    ("left_ring3", [0.85, 0.09, -0.02]),
    ("left_thumb1", [0.73, 0.08, 0.03]),
    ("left_thumb2", [0.76, 0.08, 0.06]),
    ("left_thumb3", [0.78, 0.08, 0.08]),
];

/// SMPL-X's rest skeleton, T-pose, world-aligned joint frames: human proportions typed in
/// here (metres, Y up, facing +Z, left +X; not SMPL-X's data, whose joints the model regresses
/// from the shape). What drives another body model with SMPL-family rotations needs only its
/// bone directions and leg length, for which it is within a few centimetres.
pub fn schematic_rest() -> Skeleton {
    let position = |name: &str| -> Vec3 {
        let (key, mirror) = match name.strip_prefix("right_") {
            Some(rest) => (format!("left_{rest}"), true),
            None => (name.to_string(), false),
        };
        let p = LEFT_AND_CENTRE
            .iter()
            .find(|(n, _)| *n == key)
            .map(|(_, p)| Vec3::from_array(*p))
            .expect("every SMPL-X joint has a schematic position");
        if mirror {
            p * Vec3::new(-1.0, 1.0, 1.0)
        } else {
            p
        }
    };
    let joints = JOINT_NAMES
        .iter()
        .enumerate()
        .map(|(j, name)| {
            let parent = usize::try_from(PARENTS[j]).ok();
            Joint {
                name: name.to_string(),
                parent,
                offset: position(name) - parent.map_or(Vec3::ZERO, |p| position(JOINT_NAMES[p])),
                pre_rotation: Quat::IDENTITY,
            }
        })
        .collect();
    Skeleton::new(joints).expect("the schematic SMPL-X skeleton is valid")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_schematic_skeleton_is_a_t_pose_of_human_proportions() {
        let s = schematic_rest();
        let rest = s.rest(None);
        let at = |n: &str| rest[s.index_of(n).unwrap()].translation;
        // Arms straight out sideways, legs down, the head above the neck.
        let arm = at("left_wrist") - at("left_shoulder");
        assert!(arm.x > 0.45 && arm.y.abs() < 0.05, "{arm}");
        let leg = at("left_ankle") - at("left_hip");
        assert!(leg.y < -0.7 && leg.x.abs() < 0.1, "{leg}");
        assert!(at("head").y > at("neck").y);
        assert_eq!(
            at("right_elbow"),
            at("left_elbow") * Vec3::new(-1.0, 1.0, 1.0)
        );
    }
}
