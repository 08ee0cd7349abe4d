//! MHR (Momentum Human Rig) from its official asset folder:
//! `lod{N}.fbx` (skeleton, mesh, skin, 45 identity + 72 expression blend shapes),
//! `compact_v6_1.model` (the 204-parameter transform: pose and scales),
//! `corrective_activation.npz` (`0.sparse_indices (2,K)`: output and input index of each weight,
//! `0.sparse_weight (K)`) and `corrective_blendshapes_lod{N}.npz`
//! (`corrective_blendshapes (H,V,3)`).
//!
//! The FBX is read with ufbx. Momentum works in centimetres; everything is converted to metres
//! (vertices, offsets, blend shapes, correctives, and the transform's translation rows). Each
//! skeleton node's full rest local rotation (FBX pre-rotation, rotation and post-rotation)
//! becomes the joint's pre-rotation. The first [`IDENTITY_SHAPES`] blend channels are identity,
//! the rest expression. Pose correctives use the 6-D features of joints 2.. (see
//! [`PoseCorrectives::Mlp`]).

use std::path::Path;

use glam::{Affine3A, Mat3, Quat, Vec3};

use crate::correctives::PoseCorrectives;
use crate::gltf::momentum_to_metres;
use crate::params::read_model_file;
use crate::rig::{Mesh, Parameterization, Rig};
use crate::roles::Roles;
use crate::skeleton::{Joint, Skeleton};
use crate::{BlendShapes, RigError, SkinWeights};

/// Number of identity blend shapes in MHR (20 body, 20 head, 5 hands).
pub const IDENTITY_SHAPES: usize = 45;
/// The first joint whose rotation drives the pose correctives.
pub const CORRECTIVE_FIRST_JOINT: usize = 2;
/// File name of the parameter transform in the asset folder.
pub const MODEL_FILE: &str = "compact_v6_1.model";

fn io(e: f3g_io::IoError) -> RigError {
    RigError::File {
        file: e.path,
        reason: e.reason,
    }
}

fn vec3(v: ufbx::Vec3, unit: f32) -> Vec3 {
    Vec3::new(v.x as f32, v.y as f32, v.z as f32) * unit
}

fn affine(m: &ufbx::Matrix, unit: f32) -> Affine3A {
    let linear = Mat3::from_cols(
        Vec3::new(m.m00 as f32, m.m10 as f32, m.m20 as f32),
        Vec3::new(m.m01 as f32, m.m11 as f32, m.m21 as f32),
        Vec3::new(m.m02 as f32, m.m12 as f32, m.m22 as f32),
    );
    Affine3A::from_mat3_translation(
        linear,
        Vec3::new(m.m03 as f32, m.m13 as f32, m.m23 as f32) * unit,
    )
}

/// Loads MHR at level of detail `lod` from `dir`.
pub fn load(dir: &Path, lod: u32) -> Result<Rig, RigError> {
    let fbx_path = dir.join(format!("lod{lod}.fbx"));
    let path_text = fbx_path
        .to_str()
        .ok_or_else(|| RigError::file(&fbx_path, "path is not valid UTF-8"))?;
    if !fbx_path.exists() {
        return Err(RigError::file(
            &fbx_path,
            "missing: expected the MHR asset folder (lod{N}.fbx, compact_v6_1.model, corrective npz files)",
        ));
    }
    let scene = ufbx::load_file(path_text, ufbx::LoadOpts::default())
        .map_err(|e| RigError::file(&fbx_path, format!("cannot read FBX: {}", e.description)))?;
    let unit = if scene.settings.unit_meters > 0.0 {
        scene.settings.unit_meters as f32
    } else {
        0.01
    };

    // Skeleton: every bone node, parents first (ufbx lists nodes parents before children).
    let bones: Vec<&ufbx::Node> = scene
        .nodes
        .iter()
        .filter(|n| n.bone.is_some())
        .map(|n| &**n)
        .collect();
    if bones.is_empty() {
        return Err(RigError::file(
            &fbx_path,
            "no skeleton (no LimbNode/Root nodes)",
        ));
    }
    let bone_index = |node: &ufbx::Node| {
        bones
            .iter()
            .position(|b| b.element.element_id == node.element.element_id)
    };
    let mut joints = Vec::with_capacity(bones.len());
    for b in &bones {
        let name = b.element.name.to_string();
        let t = &b.local_transform;
        if (vec3(t.scale, 1.0) - Vec3::ONE).abs().max_element() > 1e-4 {
            return Err(RigError::file(
                &fbx_path,
                format!("bone `{name}` has a non-unit rest scale"),
            ));
        }
        let parent = b.parent.as_ref().and_then(|p| bone_index(p));
        let (mut offset, mut pre_rotation) = (
            vec3(t.translation, unit),
            Quat::from_xyzw(
                t.rotation.x as f32,
                t.rotation.y as f32,
                t.rotation.z as f32,
                t.rotation.w as f32,
            ),
        );
        if parent.is_none()
            && let Some(p) = b.parent.as_ref()
        {
            let world = affine(&p.node_to_world, unit);
            let (_, rotation, _) = world.to_scale_rotation_translation();
            offset = world.transform_point3(offset);
            pre_rotation = rotation * pre_rotation;
        }
        joints.push(Joint {
            name,
            parent,
            offset,
            pre_rotation: pre_rotation.normalize(),
        });
    }
    let skeleton = Skeleton::new(joints).map_err(|e| RigError::file(&fbx_path, e))?;

    // The skinned mesh.
    let mesh = scene
        .meshes
        .iter()
        .find(|m| !m.skin_deformers.is_empty())
        .ok_or_else(|| RigError::file(&fbx_path, "no skinned mesh"))?;
    let vertices: Vec<Vec3> = mesh.vertices.iter().map(|v| vec3(*v, unit)).collect();
    if let Some(i) = vertices.iter().position(|v| !v.is_finite()) {
        return Err(RigError::file(
            &fbx_path,
            format!("vertex {i} is not finite in metres (f32)"),
        ));
    }
    let mut triangles = Vec::with_capacity(mesh.num_triangles);
    let mut scratch = vec![0u32; mesh.max_face_triangles * 3];
    for face in mesh.faces.iter() {
        let n = mesh.triangulate_face(&mut scratch, *face) as usize;
        for t in scratch[..3 * n].chunks_exact(3) {
            triangles.push([
                mesh.vertex_indices[t[0] as usize],
                mesh.vertex_indices[t[1] as usize],
                mesh.vertex_indices[t[2] as usize],
            ]);
        }
    }
    let skin = &mesh.skin_deformers[0];
    let mut lists = vec![Vec::new(); vertices.len()];
    let mut inverse_bind = vec![None; skeleton.len()];
    for cluster in skin.clusters.iter() {
        let bone = cluster
            .bone_node
            .as_ref()
            .and_then(|b| bone_index(b))
            .ok_or_else(|| {
                RigError::file(
                    &fbx_path,
                    format!(
                        "skin cluster `{}` is not bound to a bone",
                        cluster.element.name
                    ),
                )
            })?;
        inverse_bind[bone] = Some(affine(&cluster.geometry_to_bone, unit));
        for (&v, &w) in cluster.vertices.iter().zip(cluster.weights.iter()) {
            lists
                .get_mut(v as usize)
                .ok_or_else(|| {
                    RigError::file(&fbx_path, format!("cluster vertex {v} out of range"))
                })?
                .push((bone, w as f32));
        }
    }
    // Bones without a cluster influence nothing; their rest pose is the bind pose.
    let rest = skeleton.rest(None);
    let inverse_bind: Vec<Affine3A> = inverse_bind
        .into_iter()
        .zip(&rest)
        .map(|(b, r)| b.unwrap_or_else(|| r.inverse().to_affine()))
        .collect();
    let skin_weights = SkinWeights::from_lists(&lists, skeleton.len())
        .map_err(|e| RigError::file(&fbx_path, e))?;

    let mut names = Vec::new();
    let mut deltas = Vec::new();
    for deformer in mesh.blend_deformers.iter() {
        for channel in deformer.channels.iter() {
            let mut d = vec![Vec3::ZERO; vertices.len()];
            if let Some(shape) = channel.target_shape.as_ref() {
                for (&v, o) in shape
                    .offset_vertices
                    .iter()
                    .zip(shape.position_offsets.iter())
                {
                    if let Some(slot) = d.get_mut(v as usize) {
                        *slot = vec3(*o, unit);
                    }
                }
            }
            names.push(channel.element.name.to_string());
            deltas.push(d);
        }
    }
    let split = names.len().min(IDENTITY_SHAPES);
    let n = vertices.len();
    let identity = BlendShapes::new(names[..split].to_vec(), deltas[..split].concat(), n)
        .map_err(|e| RigError::file(&fbx_path, e))?;
    let expression = BlendShapes::new(names[split..].to_vec(), deltas[split..].concat(), n)
        .map_err(|e| RigError::file(&fbx_path, e))?;

    let transform =
        momentum_to_metres(read_model_file(&dir.join(MODEL_FILE), &skeleton)?.transform);
    let correctives = read_correctives(dir, lod, skeleton.len(), n, unit)?;
    let rig = Rig {
        name: format!("mhr:{}", dir.display()),
        parameterization: Parameterization::Momentum(transform),
        mesh: Mesh {
            vertices,
            triangles,
        },
        identity,
        expression,
        skin: skin_weights,
        correctives,
        joint_model: None,
        inverse_bind: Some(inverse_bind),
        roles: Roles::infer(&skeleton),
        surface: vec![true; n],
        skeleton,
    };
    rig.validate()?;
    Ok(rig)
}

/// The corrective MLP, when both corrective files are present.
fn read_correctives(
    dir: &Path,
    lod: u32,
    num_joints: usize,
    vertices: usize,
    unit: f32,
) -> Result<Option<PoseCorrectives>, RigError> {
    let activation = dir.join("corrective_activation.npz");
    let shapes = dir.join(format!("corrective_blendshapes_lod{lod}.npz"));
    if !activation.exists() && !shapes.exists() {
        return Ok(None);
    }
    let mut npz = f3g_io::Npz::open(&activation).map_err(io)?;
    let (ishape, indices) = npz.i64("0.sparse_indices").map_err(io)?;
    let (wshape, weights) = npz.f32("0.sparse_weight").map_err(io)?;
    if ishape.len() != 2 || ishape[0] != 2 || wshape != [ishape[1]] {
        return Err(RigError::field(
            &activation,
            "0.sparse_indices",
            format!(
                "shape {ishape:?} does not match 0.sparse_weight {wshape:?}: expected (2, K) and (K)"
            ),
        ));
    }
    let k = ishape[1];
    let joints = num_joints.saturating_sub(CORRECTIVE_FIRST_JOINT);
    let mut npz = f3g_io::Npz::open(&shapes).map_err(io)?;
    let (dshape, dense) = npz.f32("corrective_blendshapes").map_err(io)?;
    if dshape.len() != 3 || dshape[1] != vertices || dshape[2] != 3 {
        return Err(RigError::field(
            &shapes,
            "corrective_blendshapes",
            format!("shape {dshape:?}, expected (H, {vertices}, 3)"),
        ));
    }
    let hidden = dshape[0];
    let sparse: Vec<(u32, u32, f32)> = (0..k)
        .map(|i| (indices[i] as u32, indices[k + i] as u32, weights[i]))
        .collect();
    if let Some(&(o, i, _)) = sparse
        .iter()
        .find(|(o, i, _)| *o as usize >= hidden || *i as usize >= 6 * joints)
    {
        return Err(RigError::field(
            &activation,
            "0.sparse_indices",
            format!(
                "entry ({o}, {i}) outside {hidden} outputs × {} inputs",
                6 * joints
            ),
        ));
    }
    Ok(Some(PoseCorrectives::Mlp {
        first_joint: CORRECTIVE_FIRST_JOINT,
        joints,
        sparse,
        hidden,
        dense: dense.iter().map(|v| v * unit).collect(),
    }))
}
