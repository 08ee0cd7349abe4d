//! A rig as one `.npz` file, so that what was built on a body model travels without the
//! model's asset files (a trained avatar's run folder keeps its rig in `body_model.npz`).
//!
//! Arrays (f32 unless noted): `meta_json` (UTF-8 bytes as i64: name, joint names, parameter
//! names, blend-shape names, roles, the corrective kind), `parents (J)` i64 (−1 for a root),
//! `offsets (J,3)`, `pre_rotations (J,4)` (x, y, z, w), `vertices (V,3)`, `triangles (F,3)`
//! i64, `identity (I,V,3)`, `expression (E,V,3)`, `skin_joints (V,8)` i64, `skin_weights
//! (V,8)`, `surface (V)` i64 (1 = skin); a Momentum parameterisation adds
//! `transform_entries (K,2)` i64 (row, column), `transform_weights (K)`, `transform_offsets
//! (7J)`; linear correctives `posedirs`, MLP correctives `sparse_entries (K,2)` i64,
//! `sparse_weights (K)`, `dense`; a joint model `joint_base (J,3)`, `joint_identity (I,J,3)`,
//! `joint_expression (E,J,3)`; inverse bind matrices `inverse_bind (J,12)` (the 3×3 matrix
//! column-major, then the translation). Reading checks every size and index and validates the
//! rig, so a damaged file is an error naming it.

use std::collections::BTreeMap;
use std::path::Path;

use glam::{Affine3A, Mat3A, Quat, Vec3, Vec3A};
use serde::{Deserialize, Serialize};

use crate::correctives::PoseCorrectives;
use crate::params::ParameterTransform;
use crate::rig::{JointModel, Mesh, Parameterization, Rig};
use crate::roles::{Role, Roles};
use crate::skeleton::{Joint, PARAMS_PER_JOINT, Skeleton};
use crate::skin::MAX_INFLUENCES;
use crate::{BlendShapes, RigError, SkinWeights};
use f3g_io::NpyValues::{F32, I64};

/// The format's name and version in `meta_json`.
const FORMAT: &str = "f3g-rig 1";

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Meta {
    format: String,
    name: String,
    joints: Vec<String>,
    /// `None` for the axis-angle parameterisation.
    momentum_parameters: Option<Vec<String>>,
    identity: Vec<String>,
    expression: Vec<String>,
    roles: BTreeMap<Role, usize>,
    correctives: Option<CorrectiveKind>,
}

#[derive(Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
enum CorrectiveKind {
    Linear {
        first_joint: usize,
    },
    Mlp {
        first_joint: usize,
        joints: usize,
        hidden: usize,
    },
}

fn flat(points: &[Vec3]) -> Vec<f32> {
    points.iter().flat_map(|p| p.to_array()).collect()
}

fn io(e: f3g_io::IoError) -> RigError {
    RigError::File {
        file: e.path,
        reason: e.reason,
    }
}

/// Writes `rig` to `path` (atomically).
pub fn write(rig: &Rig, path: &Path) -> Result<(), RigError> {
    let bytes = to_bytes(rig, f3g_io::NpzEntries::Stored).map_err(|e| RigError::file(path, e))?;
    f3g_io::write_atomic(path, &bytes).map_err(io)
}

/// The rig file's bytes (to embed it in another file), its arrays stored or deflated.
pub fn to_bytes(rig: &Rig, storage: f3g_io::NpzEntries) -> Result<Vec<u8>, String> {
    let skeleton = rig.skeleton.joints();
    let (j, v) = (skeleton.len(), rig.mesh.vertices.len());
    let meta = Meta {
        format: FORMAT.into(),
        name: rig.name.clone(),
        joints: skeleton.iter().map(|j| j.name.clone()).collect(),
        momentum_parameters: match &rig.parameterization {
            Parameterization::Momentum(t) => Some(t.names.clone()),
            Parameterization::AxisAngle => None,
        },
        identity: rig.identity.names.clone(),
        expression: rig.expression.names.clone(),
        roles: rig.roles.iter().collect(),
        correctives: rig.correctives.as_ref().map(|c| match c {
            PoseCorrectives::Linear { first_joint, .. } => CorrectiveKind::Linear {
                first_joint: *first_joint,
            },
            PoseCorrectives::Mlp {
                first_joint,
                joints,
                hidden,
                ..
            } => CorrectiveKind::Mlp {
                first_joint: *first_joint,
                joints: *joints,
                hidden: *hidden,
            },
        }),
    };
    let meta: Vec<i64> = serde_json::to_vec(&meta)
        .expect("serialisable")
        .into_iter()
        .map(i64::from)
        .collect();
    let parents: Vec<i64> = skeleton
        .iter()
        .map(|j| j.parent.map_or(-1, |p| p as i64))
        .collect();
    let offsets: Vec<f32> = skeleton.iter().flat_map(|j| j.offset.to_array()).collect();
    let pre: Vec<f32> = skeleton
        .iter()
        .flat_map(|j| j.pre_rotation.to_array())
        .collect();
    let vertices = flat(&rig.mesh.vertices);
    let triangles: Vec<i64> = rig
        .mesh
        .triangles
        .iter()
        .flatten()
        .map(|&i| i64::from(i))
        .collect();
    let identity = flat(&rig.identity.deltas);
    let expression = flat(&rig.expression.deltas);
    let skin_joints: Vec<i64> = rig
        .skin
        .joints
        .iter()
        .flatten()
        .map(|&i| i64::from(i))
        .collect();
    let skin_weights: Vec<f32> = rig.skin.weights.iter().flatten().copied().collect();
    let surface: Vec<i64> = rig.surface.iter().map(|&s| i64::from(s)).collect();
    let (ni, ne) = (rig.identity.len(), rig.expression.len());
    let mut arrays = vec![
        ("meta_json", vec![meta.len()], I64(&meta)),
        ("parents", vec![j], I64(&parents)),
        ("offsets", vec![j, 3], F32(&offsets)),
        ("pre_rotations", vec![j, 4], F32(&pre)),
        ("vertices", vec![v, 3], F32(&vertices)),
        (
            "triangles",
            vec![rig.mesh.triangles.len(), 3],
            I64(&triangles),
        ),
        ("identity", vec![ni, v, 3], F32(&identity)),
        ("expression", vec![ne, v, 3], F32(&expression)),
        ("skin_joints", vec![v, MAX_INFLUENCES], I64(&skin_joints)),
        ("skin_weights", vec![v, MAX_INFLUENCES], F32(&skin_weights)),
        ("surface", vec![v], I64(&surface)),
    ];
    let (entries, weights);
    if let Parameterization::Momentum(t) = &rig.parameterization {
        entries = t
            .entries
            .iter()
            .flat_map(|e| [i64::from(e.0), i64::from(e.1)])
            .collect::<Vec<i64>>();
        weights = t.entries.iter().map(|e| e.2).collect::<Vec<f32>>();
        arrays.push(("transform_entries", vec![t.entries.len(), 2], I64(&entries)));
        arrays.push(("transform_weights", vec![t.entries.len()], F32(&weights)));
        arrays.push(("transform_offsets", vec![t.offsets.len()], F32(&t.offsets)));
    }
    let (sparse_entries, sparse_weights);
    match &rig.correctives {
        Some(PoseCorrectives::Linear { posedirs, .. }) => {
            arrays.push(("posedirs", vec![posedirs.len()], F32(posedirs)));
        }
        Some(PoseCorrectives::Mlp { sparse, dense, .. }) => {
            sparse_entries = sparse
                .iter()
                .flat_map(|e| [i64::from(e.0), i64::from(e.1)])
                .collect::<Vec<i64>>();
            sparse_weights = sparse.iter().map(|e| e.2).collect::<Vec<f32>>();
            arrays.push((
                "sparse_entries",
                vec![sparse.len(), 2],
                I64(&sparse_entries),
            ));
            arrays.push(("sparse_weights", vec![sparse.len()], F32(&sparse_weights)));
            arrays.push(("dense", vec![dense.len()], F32(dense)));
        }
        None => {}
    }
    let (base, joint_identity, joint_expression);
    if let Some(m) = &rig.joint_model {
        base = flat(&m.base);
        joint_identity = flat(&m.identity);
        joint_expression = flat(&m.expression);
        arrays.push(("joint_base", vec![j, 3], F32(&base)));
        arrays.push(("joint_identity", vec![ni, j, 3], F32(&joint_identity)));
        arrays.push(("joint_expression", vec![ne, j, 3], F32(&joint_expression)));
    }
    let inverse_bind: Vec<f32>;
    if let Some(ibm) = &rig.inverse_bind {
        inverse_bind = ibm
            .iter()
            .flat_map(|a| {
                let mut m = a.matrix3.to_cols_array().to_vec();
                m.extend(a.translation.to_array());
                m
            })
            .collect();
        arrays.push(("inverse_bind", vec![j, 12], F32(&inverse_bind)));
    }
    let arrays: Vec<(&str, &[usize], f3g_io::NpyValues)> = arrays
        .iter()
        .map(|(n, s, a)| (*n, s.as_slice(), *a))
        .collect();
    f3g_io::encode_npz(&arrays, storage)
}

/// Reads a rig written by [`write`]: every size and index is checked against the description
/// and the rig validated, so a damaged file is an error naming it (and the array).
pub fn read(path: &Path) -> Result<Rig, RigError> {
    read_from(f3g_io::Npz::open(path).map_err(io)?)
}

/// Reads a rig file held in memory (embedded in another file); `label` names it in errors.
pub fn from_bytes(bytes: &[u8], label: &str) -> Result<Rig, RigError> {
    read_from(f3g_io::Npz::from_bytes(bytes, label).map_err(io)?)
}

fn read_from<R: std::io::Read + std::io::Seek>(mut npz: f3g_io::Npz<R>) -> Result<Rig, RigError> {
    let path = &npz.path().to_path_buf();
    let bad = |field: &str, m: String| RigError::field(path, field, m);
    let bytes = npz.i64("meta_json").map_err(io)?.1;
    let bytes: Vec<u8> = bytes
        .into_iter()
        .map(|b| u8::try_from(b).unwrap_or(0))
        .collect();
    let meta: Meta = serde_json::from_slice(&bytes)
        .map_err(|e| bad("meta_json", format!("not an f3g rig description: {e}")))?;
    if meta.format != FORMAT {
        return Err(bad(
            "meta_json",
            format!("format `{}`, expected `{FORMAT}`", meta.format),
        ));
    }
    let (j, ni, ne) = (
        meta.joints.len(),
        meta.identity.len(),
        meta.expression.len(),
    );
    let (_, parents) = npz.i64("parents").map_err(io)?;
    if parents.len() != j {
        return Err(bad(
            "parents",
            format!("{} parents for {j} joints", parents.len()),
        ));
    }
    let offsets = npz.f32_exact("offsets", &[j, 3]).map_err(io)?;
    let pre = npz.f32_exact("pre_rotations", &[j, 4]).map_err(io)?;
    let mut joints = Vec::with_capacity(j);
    for (i, name) in meta.joints.iter().enumerate() {
        let parent = match parents[i] {
            -1 => None,
            p if p >= 0 && (p as usize) < i => Some(p as usize),
            p => {
                return Err(bad(
                    "parents",
                    format!("joint {i} has parent {p}: parents must come first"),
                ));
            }
        };
        joints.push(Joint {
            name: name.clone(),
            parent,
            offset: Vec3::from_slice(&offsets[3 * i..3 * i + 3]),
            pre_rotation: Quat::from_slice(&pre[4 * i..4 * i + 4]),
        });
    }
    let skeleton = Skeleton::new(joints).map_err(|e| RigError::file(path, e))?;
    let v = match npz.shape("vertices").map_err(io)?[..] {
        [v, 3] => v,
        ref other => {
            return Err(bad(
                "vertices",
                format!("has shape {other:?}, expected (V, 3)"),
            ));
        }
    };
    let vertices = vec3s(&npz.f32_exact("vertices", &[v, 3]).map_err(io)?);
    let f = match npz.shape("triangles").map_err(io)?[..] {
        [f, 3] => f,
        ref other => {
            return Err(bad(
                "triangles",
                format!("has shape {other:?}, expected (F, 3)"),
            ));
        }
    };
    let triangles = npz
        .indices("triangles", &[f, 3], v)
        .map_err(io)?
        .chunks_exact(3)
        .map(|t| [t[0] as u32, t[1] as u32, t[2] as u32])
        .collect();
    let identity = BlendShapes::new(
        meta.identity,
        vec3s(&npz.f32_exact("identity", &[ni, v, 3]).map_err(io)?),
        v,
    )
    .map_err(|e| RigError::file(path, e))?;
    let expression = BlendShapes::new(
        meta.expression,
        vec3s(&npz.f32_exact("expression", &[ne, v, 3]).map_err(io)?),
        v,
    )
    .map_err(|e| RigError::file(path, e))?;
    let skin_joints = npz
        .indices("skin_joints", &[v, MAX_INFLUENCES], j.max(1))
        .map_err(io)?;
    let skin_weights = npz
        .f32_exact("skin_weights", &[v, MAX_INFLUENCES])
        .map_err(io)?;
    let skin = SkinWeights {
        joints: skin_joints
            .chunks_exact(MAX_INFLUENCES)
            .map(|c| std::array::from_fn(|k| c[k] as u16))
            .collect(),
        weights: skin_weights
            .chunks_exact(MAX_INFLUENCES)
            .map(|c| std::array::from_fn(|k| c[k]))
            .collect(),
    };
    let surface = npz
        .indices("surface", &[v], 2)
        .map_err(io)?
        .into_iter()
        .map(|s| s == 1)
        .collect();
    let parameterization = match meta.momentum_parameters {
        None => Parameterization::AxisAngle,
        Some(names) => {
            let rows = j * PARAMS_PER_JOINT;
            let k = npz.shape("transform_weights").map_err(io)?;
            let [k] = k[..] else {
                return Err(bad(
                    "transform_weights",
                    format!("has shape {k:?}, expected (K,)"),
                ));
            };
            let entries = pairs(&mut npz, "transform_entries", k, rows, names.len())?;
            let weights = npz.f32_exact("transform_weights", &[k]).map_err(io)?;
            Parameterization::Momentum(ParameterTransform {
                entries: entries
                    .into_iter()
                    .zip(weights)
                    .map(|((r, c), w)| (r, c, w))
                    .collect(),
                offsets: npz.f32_exact("transform_offsets", &[rows]).map_err(io)?,
                names,
            })
        }
    };
    let correctives = match meta.correctives {
        None => None,
        Some(CorrectiveKind::Linear { first_joint }) => {
            let features = j.checked_sub(first_joint).ok_or_else(|| {
                bad(
                    "meta_json",
                    format!("correctives start at joint {first_joint} of {j}"),
                )
            })?;
            Some(PoseCorrectives::Linear {
                first_joint,
                posedirs: npz
                    .f32_exact("posedirs", &[9 * features * 3 * v])
                    .map_err(io)?,
            })
        }
        Some(CorrectiveKind::Mlp {
            first_joint,
            joints,
            hidden,
        }) => {
            if first_joint.checked_add(joints).is_none_or(|end| end > j) {
                return Err(bad(
                    "meta_json",
                    format!("correctives of joints {first_joint}..+{joints} of {j}"),
                ));
            }
            let k = npz.shape("sparse_weights").map_err(io)?;
            let [k] = k[..] else {
                return Err(bad(
                    "sparse_weights",
                    format!("has shape {k:?}, expected (K,)"),
                ));
            };
            let entries = pairs(&mut npz, "sparse_entries", k, hidden, 6 * joints)?;
            let weights = npz.f32_exact("sparse_weights", &[k]).map_err(io)?;
            let dense = hidden
                .checked_mul(3 * v)
                .ok_or_else(|| bad("dense", "its size overflows".into()))?;
            Some(PoseCorrectives::Mlp {
                first_joint,
                joints,
                sparse: entries
                    .into_iter()
                    .zip(weights)
                    .map(|((r, c), w)| (r, c, w))
                    .collect(),
                hidden,
                dense: npz.f32_exact("dense", &[dense]).map_err(io)?,
            })
        }
    };
    let joint_model = if npz.contains("joint_base") {
        Some(JointModel {
            base: vec3s(&npz.f32_exact("joint_base", &[j, 3]).map_err(io)?),
            identity: vec3s(&npz.f32_exact("joint_identity", &[ni, j, 3]).map_err(io)?),
            expression: vec3s(&npz.f32_exact("joint_expression", &[ne, j, 3]).map_err(io)?),
        })
    } else {
        None
    };
    let inverse_bind = if npz.contains("inverse_bind") {
        Some(
            npz.f32_exact("inverse_bind", &[j, 12])
                .map_err(io)?
                .chunks_exact(12)
                .map(|m| Affine3A {
                    matrix3: Mat3A::from_cols_slice(&m[..9]),
                    translation: Vec3A::from_slice(&m[9..]),
                })
                .collect(),
        )
    } else {
        None
    };
    let roles = Roles::from_pairs(meta.roles);
    roles.validate(j).map_err(|e| bad("meta_json", e))?;
    let rig = Rig {
        name: meta.name,
        skeleton,
        parameterization,
        mesh: Mesh {
            vertices,
            triangles,
        },
        identity,
        expression,
        skin,
        correctives,
        joint_model,
        inverse_bind,
        roles,
        surface,
    };
    rig.validate().map_err(|e| RigError::file(path, e))?;
    Ok(rig)
}

/// `(row, column)` pairs `(K, 2)` below `(rows, columns)`.
fn pairs<R: std::io::Read + std::io::Seek>(
    npz: &mut f3g_io::Npz<R>,
    name: &str,
    k: usize,
    rows: usize,
    columns: usize,
) -> Result<Vec<(u32, u32)>, RigError> {
    let values = npz.indices(name, &[k, 2], rows.max(columns)).map_err(io)?;
    let pairs: Vec<(u32, u32)> = values
        .chunks_exact(2)
        .map(|e| (e[0] as u32, e[1] as u32))
        .collect();
    match pairs
        .iter()
        .find(|(r, c)| *r as usize >= rows || *c as usize >= columns)
    {
        Some((r, c)) => Err(RigError::field(
            npz.path(),
            name,
            format!("({r}, {c}) is outside {rows} × {columns}"),
        )),
        None => Ok(pairs),
    }
}

fn vec3s(v: &[f32]) -> Vec<Vec3> {
    v.chunks_exact(3).map(Vec3::from_slice).collect()
}
