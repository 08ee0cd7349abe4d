//! Rigged characters from glTF 2.0 (`.gltf` or `.glb`).
//!
//! The first node with a skinned mesh defines the character: the skin's joints become the
//! skeleton (each joint's parent is its nearest ancestor among the joints; transforms of
//! non-joint ancestors are folded into the root), node rotations become pre-rotations and node
//! translations rest offsets (unit scales only), the skin's inverse bind matrices are kept, all
//! triangle primitives are concatenated, `JOINTS_0/1` and `WEIGHTS_0/1` give up to eight
//! influences, and morph targets become the expression block (names from `extras.targetNames`).
//!
//! Pose parameters come from, in order of preference: a Momentum `.model` file passed by the
//! caller; the `FB_momentum` extension that Momentum writes into glTF files; otherwise `rx, ry,
//! rz` for every joint plus `tx, ty, tz` for the root. Momentum works in centimetres, so the
//! translation rows of a Momentum transform are scaled by 0.01 to stay in metres.
//!
//! Buffers come from the GLB's binary chunk, `data:` URIs, or regular files beside the `.gltf`
//! named by relative URIs (no absolute path, no `..`), each read up to its `byteLength`.

use std::collections::HashMap;
use std::path::Path;

use glam::{Affine3A, Mat4, Quat, Vec3};

use crate::params::{CHANNELS, ParameterTransform, parse_model};
use crate::rig::{Mesh, Parameterization, Rig};
use crate::roles::{RoleMap, Roles};
use crate::skeleton::{Joint, PARAMS_PER_JOINT, Skeleton};
use crate::skin::MAX_INFLUENCES;
use crate::{BlendShapes, RigError, SkinWeights};

/// Momentum's length unit (centimetres) in metres.
pub const MOMENTUM_UNIT: f32 = 0.01;

/// Parses glTF/GLB bytes. The `gltf` crate's validation indexes a primitive's POSITION
/// accessor before checking that it exists (gltf-json 1.4.1, `primitive_validate_hook`), so a
/// damaged file can panic inside it; that panic becomes an error naming the file (the panic
/// message is still printed).
fn parse(bytes: &[u8], path: &Path) -> Result<gltf::Gltf, RigError> {
    std::panic::catch_unwind(|| gltf::Gltf::from_slice(bytes))
        .map_err(|_| {
            RigError::file(
                path,
                "not a valid glTF file: the glTF reader failed on it (an index out of range)",
            )
        })?
        .map_err(|e| RigError::file(path, format!("not a valid glTF file: {e}")))
}

/// The largest buffer f3g reads (2 GiB): far above any body model or motion (a 10-minute,
/// 120 fps capture of 100 joints is 0.1 GiB of rotations), far below what a lying
/// `byteLength` can ask for.
pub const MAX_BUFFER_BYTES: u64 = 1 << 31;

/// The file's buffers: the GLB's binary chunk, `data:` URIs, and files beside the `.gltf`
/// ([`external`]) — each at least its `byteLength` (at most [`MAX_BUFFER_BYTES`]), so that
/// accessor reads stay inside it. Not `gltf::import_buffers`: it reads any path a URI names
/// (absolute, `..`, a FIFO, a device) to its end, and panics on a percent escape that decodes
/// to invalid UTF-8.
fn buffers(gltf: &gltf::Gltf, path: &Path) -> Result<Vec<gltf::buffer::Data>, RigError> {
    let base = path.parent().unwrap_or(Path::new("."));
    let mut blob = gltf.blob.clone();
    let mut out = Vec::new();
    for buffer in gltf.document.buffers() {
        let (index, length) = (buffer.index(), buffer.length() as u64);
        let error = |reason: String| RigError::file(path, format!("buffer {index}: {reason}"));
        if length > MAX_BUFFER_BYTES {
            return Err(error(format!(
                "byteLength {length} is more than the {MAX_BUFFER_BYTES} bytes f3g reads"
            )));
        }
        f3g_io::memory::ensure_available(length, &format!("buffer {index} (byteLength {length})"))
            .map_err(|e| error(e.to_string()))?;
        let data = match buffer.source() {
            gltf::buffer::Source::Bin => blob.take().ok_or_else(|| {
                error("refers to a GLB binary chunk that the file does not have".into())
            })?,
            gltf::buffer::Source::Uri(uri) if uri.starts_with("data:") => {
                gltf::buffer::Data::from_source(buffer.source(), None)
                    .map_err(|e| error(format!("cannot decode its data: URI: {e}")))?
                    .0
            }
            gltf::buffer::Source::Uri(uri) => external(base, uri, length).map_err(error)?,
        };
        if (data.len() as u64) < length {
            return Err(error(format!(
                "holds {} bytes, fewer than its byteLength {length}",
                data.len()
            )));
        }
        out.push(gltf::buffer::Data(data));
    }
    Ok(out)
}

/// At most ~200 characters of `text`, for quoting a file's value in an error.
fn quoted(text: &str) -> String {
    match text.char_indices().nth(200) {
        Some((end, _)) => format!("{}…", &text[..end]),
        None => text.to_string(),
    }
}

/// The first `length` bytes of the file a buffer's `uri` names: a relative path
/// (percent-decoded) inside `base`, the `.gltf`'s folder — no scheme, no absolute path, no
/// `..` — and a regular file, checked before opening so that a FIFO or a device is never
/// opened. (A symbolic link placed in the folder is followed: the user put it there, the file
/// did not.)
fn external(base: &Path, uri: &str, length: u64) -> Result<Vec<u8>, String> {
    use std::io::Read;
    use std::path::Component;
    let shown = quoted(uri);
    let relative = percent_decoded(uri)
        .ok_or_else(|| format!("URI `{shown}` is not a valid percent-encoded UTF-8 path"))?;
    let inside = !uri.contains(':')
        && !relative.is_empty()
        && Path::new(&relative)
            .components()
            .all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
    if !inside {
        return Err(format!(
            "URI `{shown}` is not a relative path inside the .gltf's folder: f3g reads buffers \
             from data: URIs and from files beside the .gltf (no scheme, no absolute path, no `..`)"
        ));
    }
    let file = base.join(&relative);
    let metadata = std::fs::metadata(&file).map_err(|e| format!("`{shown}`: {e}"))?;
    if !metadata.is_file() {
        let kind = if metadata.is_dir() {
            "a directory"
        } else {
            "a FIFO, socket or device"
        };
        return Err(format!(
            "`{shown}` is not a regular file ({kind}); f3g reads buffers from regular files only"
        ));
    }
    if metadata.len() < length {
        return Err(format!(
            "`{shown}` holds {} bytes, fewer than the buffer's byteLength {length}",
            metadata.len()
        ));
    }
    let mut data = Vec::with_capacity(length as usize);
    std::fs::File::open(&file)
        .and_then(|f| f.take(length).read_to_end(&mut data))
        .map_err(|e| format!("`{shown}`: {e}"))?;
    Ok(data)
}

/// `uri` with its `%XX` escapes decoded, if they are well formed and the result is UTF-8.
fn percent_decoded(uri: &str) -> Option<String> {
    let bytes = uri.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%' {
            let hex = bytes.get(i + 1..i + 3)?;
            if !hex.iter().all(u8::is_ascii_hexdigit) {
                return None;
            }
            out.push(u8::from_str_radix(std::str::from_utf8(hex).ok()?, 16).ok()?);
            i += 3;
        } else {
            out.push(bytes[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

/// The most elements f3g reads from one accessor: far above any body mesh (MHR's has 18 439
/// vertices, a dense scan a few million), far below what a lying `count` can ask for.
pub const MAX_ACCESSOR_COUNT: usize = 1 << 24;

/// Refuses an accessor whose `count` — for a sparse accessor without a buffer view, a number
/// the file can set freely, which the reader would turn into that many elements — is beyond
/// [`MAX_ACCESSOR_COUNT`] or the memory budget, before anything is read from it.
fn check_count(accessor: Option<gltf::Accessor>, what: &str, path: &Path) -> Result<(), RigError> {
    let Some(a) = accessor else {
        return Ok(());
    };
    let count = a.count();
    if count > MAX_ACCESSOR_COUNT {
        return Err(RigError::file(
            path,
            format!(
                "{what} (accessor {}) has count {count}, more than the {MAX_ACCESSOR_COUNT} elements f3g reads",
                a.index()
            ),
        ));
    }
    f3g_io::memory::ensure_available(
        count as u64 * a.size() as u64 * 2,
        &format!("{what} (accessor {}, count {count})", a.index()),
    )
    .map_err(|e| RigError::file(path, e))
}

/// Reads a `.gltf`/`.glb` file and its buffers (images are not decoded).
pub fn import(path: &Path) -> Result<(gltf::Document, Vec<gltf::buffer::Data>), RigError> {
    let bytes = std::fs::read(path).map_err(|e| RigError::file(path, e))?;
    let gltf = parse(&bytes, path)?;
    let buffers = buffers(&gltf, path)?;
    Ok((gltf.document, buffers))
}

/// A skin's joints as a skeleton.
pub struct SkinJoints {
    /// Parents first (the skin's order breaks ties); rest frames from the nodes, the root's
    /// including its non-joint ancestors' transforms.
    pub skeleton: Skeleton,
    /// The skin joint index of each skeleton joint, and the skeleton joint of each skin joint.
    pub order: Vec<usize>,
    pub of_skin: Vec<usize>,
    /// The node of each skeleton joint, and its scene (world) transform at rest.
    pub nodes: Vec<usize>,
    pub world: Vec<Mat4>,
}

/// A node on a cycle of `parent_of` links among `count` nodes, if there is one; each node is
/// walked once.
fn cycle(parent_of: &HashMap<usize, usize>, count: usize) -> Option<usize> {
    // 0: not seen, 1: on the current walk, 2: known to reach a root.
    let mut state = vec![0u8; count];
    for start in 0..count {
        let mut walk = Vec::new();
        let mut i = start;
        loop {
            match state[i] {
                1 => return Some(i),
                2 => break,
                _ => {}
            }
            state[i] = 1;
            walk.push(i);
            match parent_of.get(&i) {
                Some(&p) => i = p,
                None => break,
            }
        }
        for w in walk {
            state[w] = 2;
        }
    }
    None
}

/// The skeleton of `skin` (unit scales only: an error names a scaled joint).
pub fn skin_joints(
    doc: &gltf::Document,
    skin: &gltf::Skin,
    path: &Path,
) -> Result<SkinJoints, RigError> {
    // Node parents and world transforms of the whole scene graph.
    let mut parent_of: HashMap<usize, usize> = HashMap::new();
    for n in doc.nodes() {
        for c in n.children() {
            parent_of.insert(c.index(), n.index());
        }
    }
    // The walks up the hierarchy below would never end on a cycle (gltf does not check).
    if let Some(n) = cycle(&parent_of, doc.nodes().len()) {
        return Err(RigError::file(
            path,
            format!("node {n} is its own ancestor: glTF's nodes must form trees"),
        ));
    }
    let local = |i: usize| {
        Mat4::from_cols_array_2d(&doc.nodes().nth(i).expect("node index").transform().matrix())
    };
    let world = |mut i: usize| {
        let mut m = local(i);
        while let Some(&p) = parent_of.get(&i) {
            m = local(p) * m;
            i = p;
        }
        m
    };

    let skin_nodes: Vec<usize> = skin.joints().map(|j| j.index()).collect();
    let joint_parent = |node: usize| {
        let mut i = node;
        while let Some(&p) = parent_of.get(&i) {
            if let Some(k) = skin_nodes.iter().position(|&s| s == p) {
                return Some(k);
            }
            i = p;
        }
        None
    };
    let skin_parents: Vec<Option<usize>> = skin_nodes.iter().map(|&n| joint_parent(n)).collect();
    let mut order: Vec<usize> = Vec::with_capacity(skin_nodes.len());
    while order.len() < skin_nodes.len() {
        let before = order.len();
        for (k, parent) in skin_parents.iter().enumerate() {
            if !order.contains(&k) && parent.is_none_or(|p| order.contains(&p)) {
                order.push(k);
            }
        }
        if order.len() == before {
            return Err(RigError::file(path, "the skin's joints form a cycle"));
        }
    }
    let ours: Vec<usize> = (0..skin_nodes.len())
        .map(|k| {
            order
                .iter()
                .position(|&o| o == k)
                .expect("every joint ordered")
        })
        .collect();
    let mut joints = Vec::with_capacity(order.len());
    for &k in &order {
        let node = doc.nodes().nth(skin_nodes[k]).expect("joint node");
        let name = node
            .name()
            .map(String::from)
            .unwrap_or_else(|| format!("joint{k}"));
        let (t, r, s) = node.transform().decomposed();
        if s.iter().any(|v| (v - 1.0).abs() > 1e-4) {
            return Err(RigError::file(
                path,
                format!("joint `{name}` has scale {s:?}; only unit scales are supported"),
            ));
        }
        let (mut offset, mut pre_rotation) = (Vec3::from(t), Quat::from_array(r).normalize());
        if skin_parents[k].is_none()
            && let Some(&p) = parent_of.get(&skin_nodes[k])
        {
            let (scale, rotation, translation) = world(p).to_scale_rotation_translation();
            if (scale - Vec3::ONE).abs().max_element() > 1e-4 {
                return Err(RigError::file(
                    path,
                    format!(
                        "the ancestors of root joint `{name}` are scaled by {scale}; only unit scales are supported"
                    ),
                ));
            }
            offset = rotation * offset + translation;
            pre_rotation = rotation * pre_rotation;
        }
        joints.push(Joint {
            name,
            parent: skin_parents[k].map(|p| ours[p]),
            offset,
            pre_rotation,
        });
    }
    let skeleton = Skeleton::new(joints).map_err(|e| RigError::file(path, e))?;
    let world = order.iter().map(|&k| world(skin_nodes[k])).collect();
    let nodes = order.iter().map(|&k| skin_nodes[k]).collect();
    Ok(SkinJoints {
        skeleton,
        order,
        of_skin: ours,
        nodes,
        world,
    })
}

/// Loads a rigged character; `model` is an optional Momentum `.model` file for its parameters.
pub fn load(path: &Path, model: Option<&Path>) -> Result<Rig, RigError> {
    let bytes = std::fs::read(path).map_err(|e| RigError::file(path, e))?;
    let gltf = parse(&bytes, path)?;
    let buffers = buffers(&gltf, path)?;
    let doc = &gltf.document;
    let node = doc
        .nodes()
        .find(|n| n.mesh().is_some() && n.skin().is_some())
        .ok_or_else(|| RigError::file(path, "no node with a skinned mesh"))?;
    let skin = node.skin().expect("checked above");
    let mesh = node.mesh().expect("checked above");

    let SkinJoints {
        skeleton,
        order,
        of_skin: ours,
        world,
        ..
    } = skin_joints(doc, &skin, path)?;
    let skin_nodes: Vec<usize> = skin.joints().map(|j| j.index()).collect();

    check_count(
        skin.inverse_bind_matrices(),
        "the skin's inverse bind matrices",
        path,
    )?;
    let reader = skin.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
    let inverse_bind: Vec<Affine3A> = match reader.read_inverse_bind_matrices() {
        Some(m) => {
            let m: Vec<[[f32; 4]; 4]> = m.collect();
            if m.len() != skin_nodes.len() {
                return Err(RigError::file(
                    path,
                    format!(
                        "{} inverse bind matrices for {} joints",
                        m.len(),
                        skin_nodes.len()
                    ),
                ));
            }
            order
                .iter()
                .map(|&k| Affine3A::from_mat4(Mat4::from_cols_array_2d(&m[k])))
                .collect()
        }
        // glTF's default: the joints' scene transforms are the bind pose.
        None => world
            .iter()
            .map(|w| Affine3A::from_mat4(w.inverse()))
            .collect(),
    };

    // Mesh: every triangle primitive, concatenated.
    let mut vertices = Vec::new();
    let mut triangles = Vec::new();
    let mut lists: Vec<Vec<(usize, f32)>> = Vec::new();
    let mut targets: Vec<Vec<Vec3>> = Vec::new();
    for (pi, prim) in mesh.primitives().enumerate() {
        if prim.mode() != gltf::mesh::Mode::Triangles {
            continue;
        }
        use gltf::Semantic;
        let name = |what: &str| format!("{what} of primitive {pi}");
        check_count(prim.get(&Semantic::Positions), &name("POSITION"), path)?;
        check_count(prim.indices(), &name("the indices"), path)?;
        for set in 0..2 {
            check_count(prim.get(&Semantic::Joints(set)), &name("JOINTS"), path)?;
            check_count(prim.get(&Semantic::Weights(set)), &name("WEIGHTS"), path)?;
        }
        for (t, target) in prim.morph_targets().enumerate() {
            check_count(
                target.positions(),
                &name(&format!("morph target {t}")),
                path,
            )?;
        }
        let r = prim.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
        let start = vertices.len() as u32;
        let positions: Vec<Vec3> = r
            .read_positions()
            .ok_or_else(|| RigError::file(path, format!("primitive {pi} has no POSITION")))?
            .map(Vec3::from)
            .collect();
        let n = positions.len();
        match r.read_indices() {
            Some(ix) => {
                let ix: Vec<u32> = ix.into_u32().collect();
                triangles.extend(
                    ix.chunks_exact(3)
                        .map(|t| [t[0] + start, t[1] + start, t[2] + start]),
                );
            }
            None => triangles.extend(
                (0..n as u32 / 3).map(|t| [start + 3 * t, start + 3 * t + 1, start + 3 * t + 2]),
            ),
        }
        let mut prim_lists = vec![Vec::new(); n];
        for set in 0..2 {
            let (Some(js), Some(ws)) = (r.read_joints(set), r.read_weights(set)) else {
                continue;
            };
            for (v, (j, w)) in js.into_u16().zip(ws.into_f32()).enumerate().take(n) {
                for (jj, ww) in j.iter().zip(w) {
                    if ww != 0.0 {
                        let k = *jj as usize;
                        let joint = *ours.get(k).ok_or_else(|| {
                            RigError::file(
                                path,
                                format!(
                                    "vertex {v} of primitive {pi} uses joint {k} of {}",
                                    ours.len()
                                ),
                            )
                        })?;
                        prim_lists[v].push((joint, ww));
                    }
                }
            }
        }
        lists.extend(prim_lists);
        let prim_targets: Vec<Vec<Vec3>> = r
            .read_morph_targets()
            .map(|(p, _, _)| {
                p.map(|p| p.map(Vec3::from).collect())
                    .unwrap_or_else(|| vec![Vec3::ZERO; n])
            })
            .collect();
        if pi > 0 && prim_targets.len() != targets.len() {
            return Err(RigError::file(
                path,
                "primitives have different numbers of morph targets",
            ));
        }
        targets.resize(prim_targets.len(), Vec::new());
        for (all, t) in targets.iter_mut().zip(prim_targets) {
            all.extend(t);
        }
        vertices.extend(positions);
    }
    if vertices.is_empty() {
        return Err(RigError::file(
            path,
            "the skinned mesh has no triangle primitive",
        ));
    }
    let skin_weights =
        SkinWeights::from_lists(&lists, skeleton.len()).map_err(|e| RigError::file(path, e))?;
    let target_names: Vec<String> = mesh
        .extras()
        .as_ref()
        .and_then(|e| serde_json::from_str::<serde_json::Value>(e.get()).ok())
        .and_then(|v| v.get("targetNames").cloned())
        .and_then(|v| serde_json::from_value(v).ok())
        .unwrap_or_else(|| (0..targets.len()).map(|i| format!("target{i}")).collect());
    let expression = BlendShapes::new(target_names, targets.concat(), vertices.len())
        .map_err(|e| RigError::file(path, e))?;

    let transform = match model {
        Some(m) => {
            let text = std::fs::read_to_string(m).map_err(|e| RigError::file(m, e))?;
            momentum_to_metres(parse_model(&text, &skeleton, m)?.transform)
        }
        None => match momentum_extension(&bytes, &gltf, &skeleton, path)? {
            Some(t) => momentum_to_metres(t),
            None => default_transform(&skeleton),
        },
    };
    // Roles from the joint names, then the user's role map beside the file, if any.
    let map_path = RoleMap::beside(path);
    let mut roles = Roles::infer(&skeleton);
    if map_path.exists() {
        roles = roles
            .with_map(&skeleton, &RoleMap::read(&map_path)?)
            .map_err(|e| RigError::file(&map_path, e))?;
    }
    let count = vertices.len();
    let rig = Rig {
        name: format!("gltf:{}", path.display()),
        parameterization: Parameterization::Momentum(transform),
        mesh: Mesh {
            vertices,
            triangles,
        },
        identity: BlendShapes::default(),
        expression,
        skin: skin_weights,
        correctives: None,
        joint_model: None,
        inverse_bind: Some(inverse_bind),
        roles,
        surface: vec![true; count],
        skeleton,
    };
    rig.validate()?;
    Ok(rig)
}

/// Writes `rig` as a rigged glTF binary (`.glb`) that [`load`] reads back: the skeleton as
/// nodes (rest offsets as translations, pre-rotations as rotations) and a `skin` with inverse
/// bind matrices, the template mesh with `JOINTS_0/1` and `WEIGHTS_0/1` (all eight
/// influences), and the expression shapes as morph targets named in `extras.targetNames`.
/// What glTF cannot hold is left out: identity shapes and a shape-dependent skeleton (the
/// file is the model at zero identity), pose correctives, and a Momentum parameterisation
/// (the reader gives every joint `rx, ry, rz` and the root a translation).
pub fn write(rig: &Rig, path: &Path) -> Result<(), RigError> {
    use crate::glb::GlbBuffer;
    use serde_json::json;
    let joints = rig.skeleton.joints();
    let mut buffer = GlbBuffer::default();
    let positions: Vec<f32> = rig
        .mesh
        .vertices
        .iter()
        .flat_map(|v| v.to_array())
        .collect();
    let position = buffer.accessor(&positions, "VEC3", true, Some(34962));
    let indices: Vec<u32> = rig.mesh.triangles.iter().flatten().copied().collect();
    let indices = buffer.accessor(&indices, "SCALAR", false, Some(34963));
    let mut attributes = json!({ "POSITION": position });
    for set in 0..MAX_INFLUENCES / 4 {
        let ids: Vec<u16> = rig
            .skin
            .joints
            .iter()
            .flat_map(|j| j[4 * set..4 * set + 4].to_vec())
            .collect();
        let weights: Vec<f32> = rig
            .skin
            .weights
            .iter()
            .flat_map(|w| w[4 * set..4 * set + 4].to_vec())
            .collect();
        attributes[format!("JOINTS_{set}")] =
            json!(buffer.accessor(&ids, "VEC4", false, Some(34962)));
        attributes[format!("WEIGHTS_{set}")] =
            json!(buffer.accessor(&weights, "VEC4", false, Some(34962)));
    }
    let v = rig.mesh.vertices.len();
    let targets: Vec<serde_json::Value> = (0..rig.expression.len())
        .map(|s| {
            let deltas: Vec<f32> = rig.expression.deltas[s * v..(s + 1) * v]
                .iter()
                .flat_map(|d| d.to_array())
                .collect();
            json!({ "POSITION": buffer.accessor(&deltas, "VEC3", true, Some(34962)) })
        })
        .collect();
    let inverse_bind: Vec<Affine3A> = match &rig.inverse_bind {
        Some(ibm) => ibm.clone(),
        None => rig
            .skeleton
            .rest(None)
            .iter()
            .map(|r| r.inverse().to_affine())
            .collect(),
    };
    let matrices: Vec<f32> = inverse_bind
        .iter()
        .flat_map(|a| Mat4::from(*a).to_cols_array())
        .collect();
    let inverse_bind = buffer.accessor(&matrices, "MAT4", false, None);
    let (nodes, roots) = crate::glb::skinned_nodes(
        &rig.skeleton,
        |i| {
            json!({
                "translation": joints[i].offset.to_array(),
                "rotation": joints[i].pre_rotation.to_array(),
            })
        },
        &rig.name,
    );
    let document = json!({
        "asset": { "version": "2.0", "generator": "f3g-avatar" },
        "scene": 0,
        "scenes": [{ "nodes": roots }],
        "nodes": nodes,
        "meshes": [{
            "name": rig.name,
            "primitives": [{ "attributes": attributes, "indices": indices, "mode": 4,
                             "targets": targets }],
            "weights": vec![0.0; rig.expression.len()],
            "extras": { "targetNames": rig.expression.names },
        }],
        "skins": [{ "joints": (0..joints.len()).collect::<Vec<_>>(),
                    "inverseBindMatrices": inverse_bind }],
    });
    let mut document = document;
    if rig.expression.is_empty() {
        // glTF forbids empty `targets` and `weights` arrays.
        let mesh = &mut document["meshes"][0];
        mesh.as_object_mut().expect("object").remove("weights");
        mesh["primitives"][0]
            .as_object_mut()
            .expect("object")
            .remove("targets");
    }
    f3g_io::write_atomic(path, &buffer.finish(document)).map_err(|e| RigError::File {
        file: e.path,
        reason: e.reason,
    })
}

/// Scales the translation rows of a Momentum (centimetre) transform to metres.
pub fn momentum_to_metres(mut t: ParameterTransform) -> ParameterTransform {
    let is_translation = |row: usize| row % PARAMS_PER_JOINT < 3;
    for e in &mut t.entries {
        if is_translation(e.0 as usize) {
            e.2 *= MOMENTUM_UNIT;
        }
    }
    for (row, o) in t.offsets.iter_mut().enumerate() {
        if is_translation(row) {
            *o *= MOMENTUM_UNIT;
        }
    }
    t
}

/// `rx, ry, rz` for every joint and `tx, ty, tz` for roots.
pub fn default_transform(skeleton: &Skeleton) -> ParameterTransform {
    let mut t = ParameterTransform::empty(skeleton.len());
    for (j, joint) in skeleton.joints().iter().enumerate() {
        let channels: &[usize] = if joint.parent.is_none() {
            &[0, 1, 2, 3, 4, 5]
        } else {
            &[3, 4, 5]
        };
        for &c in channels {
            t.add_parameter(format!("{}_{}", joint.name, CHANNELS[c]), &[(j, c, 1.0)]);
        }
    }
    t
}

/// The parameter transform stored by Momentum in the `FB_momentum` extension, if any
/// (it keeps weights but not constant offsets).
fn momentum_extension(
    bytes: &[u8],
    gltf: &gltf::Gltf,
    skeleton: &Skeleton,
    path: &Path,
) -> Result<Option<ParameterTransform>, RigError> {
    let json: serde_json::Value = if gltf.blob.is_some() || bytes.starts_with(b"glTF") {
        let glb = gltf::binary::Glb::from_slice(bytes).map_err(|e| RigError::file(path, e))?;
        serde_json::from_slice(&glb.json).map_err(|e| RigError::file(path, e))?
    } else {
        serde_json::from_slice(bytes).map_err(|e| RigError::file(path, e))?
    };
    let Some(t) = json.pointer("/extensions/FB_momentum/transform") else {
        return Ok(None);
    };
    let field = |reason: String| RigError::field(path, "extensions.FB_momentum.transform", reason);
    let names: Vec<String> =
        serde_json::from_value(t.get("parameters").cloned().unwrap_or_default())
            .map_err(|e| field(e.to_string()))?;
    let mut transform = ParameterTransform {
        names,
        entries: Vec::new(),
        offsets: vec![0.0; skeleton.len() * PARAMS_PER_JOINT],
    };
    let joints = t
        .get("joints")
        .and_then(|j| j.as_object())
        .cloned()
        .unwrap_or_default();
    for (joint, channels) in joints {
        let j = skeleton
            .index_of(&joint)
            .ok_or_else(|| field(format!("unknown joint `{joint}`")))?;
        for (channel, params) in channels.as_object().cloned().unwrap_or_default() {
            let c = CHANNELS
                .iter()
                .position(|c| *c == channel)
                .ok_or_else(|| field(format!("unknown channel `{channel}`")))?;
            for (param, weight) in params.as_object().cloned().unwrap_or_default() {
                let col = transform
                    .index_of(&param)
                    .ok_or_else(|| field(format!("unknown parameter `{param}`")))?;
                let w = weight
                    .as_f64()
                    .ok_or_else(|| field(format!("weight of `{param}` is not a number")))?
                    as f32;
                transform
                    .entries
                    .push(((j * PARAMS_PER_JOINT + c) as u32, col as u32, w));
            }
        }
    }
    Ok(Some(transform))
}
