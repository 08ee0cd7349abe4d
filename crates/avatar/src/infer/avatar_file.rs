//! The portable avatar file: a [`BakedAvatar`] as one glTF 2.0 binary (`.glb`).
//!
//! - **Gaussians**: one `POINTS` primitive with the `KHR_gaussian_splatting` extension
//!   (as ratified; kernel `ellipse`, colour space `srgb_rec709_display`): `POSITION`
//!   (the canonical means), `KHR_gaussian_splatting:ROTATION` (unit quaternions, glTF's x, y,
//!   z, w order), `:SCALE` (linear), `:OPACITY` (linear, in [0, 1]) and
//!   `:SH_DEGREE_l_COEF_n` (3DGS's coefficients, `0.5 + C0·f_dc` for degree 0).
//! - **Skinning**: the skeleton as nodes in the canonical pose (local translation, rotation,
//!   uniform scale), a standard `skin` whose inverse bind matrices are the canonical pose's
//!   inverse, and per Gaussian `JOINTS_0`/`WEIGHTS_0` (four influences); so `Σ w S_j` with
//!   `S_j = W_j · IBM_j` poses a Gaussian exactly as f3g does.
//! - **Morph targets**: the `K` pose correctives' position offsets first, then the body
//!   model's `E` expressions, named in the mesh's `extras.targetNames` (`corrective_0`, …,
//!   `expression:mouth-open`, …). Their weights are computed, not animated: expressions come
//!   from the body parameters, correctives from the pose.
//! - **`F3G_pose_correctives`** (on the primitive): what glTF morph targets cannot carry —
//!   per corrective the colour (`colour`, VEC3, added to the degree-0 colour), log-scale
//!   (`logScale`, VEC3) and opacity-logit (`opacityLogit`, SCALAR) offsets — and the map from
//!   the pose to the corrective weights: `featureJoints` (joint indices), `featureUsed` (which
//!   of the `9·J` values of `R_root⁻¹ R_j − I`, row-major per joint, are used), `featureMean`
//!   and `featureMap` (`[K, F]`, row-major): `w = featureMap · (f − featureMean)`.
//! - **`F3G_world_shading`** (on the primitive, only for an avatar trained with
//!   `world_shading`): the light fixed in the world — `coefficients` (27 numbers, `[9, 3]`
//!   row-major: SH basis function of degree ≤ 2, channel) and `normal` (VEC3 accessor, each
//!   Gaussian's canonical unit normal). A player turns the normal by the Gaussian's skinning
//!   rotation and multiplies the degree-0 colour by `Σ_k Y_k(n) a_kc`; the stored colours are
//!   the albedo, so viewers that know no f3g extension show the avatar unshaded.
//! - **`F3G_avatar`** (top level): the body model as an f3g rig file in a buffer view
//!   (`bodyModel`), its parameter names (`parameters.pose|identity|expression`, so motions can
//!   be mapped onto it), the canonical pose's parameters, the head's vertices and the head
//!   crops' padding (for evaluation), the training step, the format version.
//!
//! A renderer that knows neither extension still shows a skinned point cloud.
//!
//! **Compressed files** ([`Encoding::Compressed`], `export-avatar --compress`) keep this
//! structure with three changes. The Gaussians are an SPZ payload
//! (`KHR_gaussian_splatting_compression_spz_2`, Khronos's draft, in `extensionsRequired`; the
//! attributes are accessors without buffer views, as the draft specifies; [`f3g_splat::spz`]).
//! `JOINTS_0` and `WEIGHTS_0` are unsigned bytes (weights `normalized`, summing to 255; joints
//! 16-bit when the skeleton has more than 256). The correctives, the expressions and the
//! shading normals are not morph targets and accessors but **`F3G_packed_arrays`** (on the
//! primitive): one zlib-compressed buffer view of quantised arrays, each per Gaussian, stored
//! component by component as little-endian signed integers of `bits` bits times `scale`
//! (`arrays`: `name`, `width`, `bits`, `scale`, in the buffer's order; names `corrective_c:position`,
//! `corrective_c:colour`, `corrective_c:logScale`, `corrective_c:opacityLogit`,
//! `expression:NAME`, `shading:normal`). No other glTF viewer animates the avatar's correctives
//! or expressions, so nothing is lost to them that they used.

use std::io::Write;
use std::path::Path;

use glam::Mat4;
use serde_json::{Value, json};

use super::bake::{BakedAvatar, BakedShading, CORRECTIVE_VALUES};
use crate::AvatarError;
use crate::model::logit;
use f3g_rig::glb::{GlbBuffer, GlbFile};
use f3g_rig::{RigParams, Similarity};

/// The version of the `F3G_avatar` extension this module writes and reads.
pub const VERSION: u64 = 1;
const SPLATS: &str = "KHR_gaussian_splatting";
const SPZ: &str = "KHR_gaussian_splatting_compression_spz_2";
const PACKED: &str = "F3G_packed_arrays";

/// How an avatar file stores its numbers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Encoding {
    /// Every value a 32-bit float in a standard accessor: any `KHR_gaussian_splatting` loader
    /// reads the Gaussians.
    #[default]
    Float,
    /// SPZ Gaussians, byte skin weights, and the correctives, expressions and normals quantised
    /// and deflated (module docs): about a seventh of the size.
    Compressed,
}

/// Bits of the quantised arrays of compressed files, per kind (the size and quality this
/// costs is measured in BENCHMARKS.md, "Compressed avatars").
const POSITION_BITS: u32 = 16;
const APPEARANCE_BITS: u32 = 8;
const NORMAL_BITS: u32 = 8;

/// A corrective's parts in a compressed file: the packed array's name suffix, the columns of
/// [`CORRECTIVE_VALUES`] it holds (first, width) and its bits.
const CORRECTIVE_PARTS: [(&str, usize, usize, u32); 4] = [
    ("position", 0, 3, POSITION_BITS),
    ("colour", 3, 3, APPEARANCE_BITS),
    ("logScale", 6, 3, APPEARANCE_BITS),
    ("opacityLogit", 9, 1, APPEARANCE_BITS),
];

/// Quantised per-Gaussian arrays, stored component by component, then deflated as one.
#[derive(Default)]
struct Packer {
    raw: Vec<u8>,
    arrays: Vec<Value>,
}

impl Packer {
    /// Appends `values` (`[N, width]`) as `bits`-bit integers times the scale that maps the
    /// largest magnitude onto the largest integer.
    fn push(&mut self, name: String, values: &[f32], width: usize, bits: u32) {
        let top = ((1i32 << (bits - 1)) - 1) as f32;
        let largest = values.iter().fold(0f32, |m, v| m.max(v.abs()));
        let scale = if largest > 0.0 { largest / top } else { 0.0 };
        for c in 0..width {
            for row in values.chunks_exact(width) {
                let q = if scale > 0.0 {
                    (row[c] / scale).round().clamp(-top, top) as i32
                } else {
                    0
                };
                self.raw
                    .extend_from_slice(&q.to_le_bytes()[..(bits / 8) as usize]);
            }
        }
        self.arrays.push(json!({
            "name": name,
            "width": width,
            "bits": bits,
            "scale": scale,
        }));
    }

    /// The extension object, its deflated bytes appended to `buffer`.
    fn finish(self, buffer: &mut GlbBuffer) -> Result<Value, AvatarError> {
        let mut zlib = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::best());
        zlib.write_all(&self.raw)
            .map_err(|e| AvatarError::Invalid(format!("deflating the packed arrays: {e}")))?;
        let deflated = zlib
            .finish()
            .map_err(|e| AvatarError::Invalid(format!("deflating the packed arrays: {e}")))?;
        Ok(json!({
            "bufferView": buffer.view(&deflated),
            "arrays": self.arrays,
        }))
    }
}

/// The packed arrays of a compressed file, dequantised, by name.
struct Packed {
    names: Vec<String>,
    arrays: std::collections::HashMap<String, Vec<f32>>,
}

impl Packed {
    /// Inflates and dequantises `F3G_packed_arrays` for `n` Gaussians; sizes are checked
    /// against the declared ones before anything large is allocated.
    fn read(file: &GlbFile, ext: &Value, n: usize) -> Result<Self, String> {
        let view = file.view(index(&ext["bufferView"], &format!("{PACKED}.bufferView"))?)?;
        let list = ext["arrays"]
            .as_array()
            .ok_or_else(|| format!("{PACKED}.arrays is not a list"))?;
        let mut layout = Vec::with_capacity(list.len());
        let mut total = 0usize;
        for a in list {
            let name = a["name"]
                .as_str()
                .ok_or_else(|| format!("{PACKED}: an array without a name"))?;
            let width = a["width"].as_u64().filter(|w| (1..=4).contains(w));
            let bits = a["bits"].as_u64().filter(|b| [8, 16].contains(b));
            let scale = a["scale"].as_f64().filter(|s| s.is_finite() && *s >= 0.0);
            let (Some(width), Some(bits), Some(scale)) = (width, bits, scale) else {
                return Err(format!(
                    "{PACKED}: array `{name}` needs a width 1–4, bits 8 or 16 and a finite scale ≥ 0"
                ));
            };
            let bytes = n * width as usize * bits as usize / 8;
            total = total
                .checked_add(bytes)
                .filter(|&t| t <= 1 << 31)
                .ok_or_else(|| format!("{PACKED}: the arrays declare more than 2 GiB"))?;
            layout.push((
                name.to_string(),
                width as usize,
                bits as usize / 8,
                scale as f32,
            ));
        }
        let raw = f3g_io::read_at_most(flate2::read::ZlibDecoder::new(view), total)
            .map_err(|e| format!("{PACKED}: inflating: {e}"))?;
        if raw.len() != total {
            return Err(format!(
                "{PACKED}: the buffer inflates to {} bytes, its arrays take {total}",
                raw.len()
            ));
        }
        let mut arrays = std::collections::HashMap::new();
        let names = layout.iter().map(|(name, ..)| name.clone()).collect();
        let mut at = 0;
        for (name, width, size, scale) in layout {
            let mut values = vec![0f32; n * width];
            for c in 0..width {
                for g in 0..n {
                    let b = &raw[at..at + size];
                    let q = if size == 1 {
                        b[0] as i8 as f32
                    } else {
                        i16::from_le_bytes([b[0], b[1]]) as f32
                    };
                    values[g * width + c] = q * scale;
                    at += size;
                }
            }
            if arrays.insert(name.clone(), values).is_some() {
                return Err(format!("{PACKED} names the array `{name}` twice"));
            }
        }
        Ok(Self { names, arrays })
    }

    /// The array `name`, `[N, width]` row-major.
    fn take(&mut self, name: &str) -> Result<Vec<f32>, String> {
        self.arrays
            .remove(name)
            .ok_or_else(|| format!("{PACKED} has no array `{name}`"))
    }
}

/// Writes `[N, width]` `values` into the `[·, N, CORRECTIVE_VALUES]` correctives at Gaussian
/// `first` onwards, columns `offset..offset + width`.
fn scatter(correctives: &mut [f32], values: &[f32], first: usize, offset: usize, width: usize) {
    for (g, row) in values.chunks_exact(width).enumerate() {
        let at = (first + g) * CORRECTIVE_VALUES + offset;
        correctives[at..at + width].copy_from_slice(row);
    }
}

/// Skin weights as bytes summing to 255 (glTF's normalised `WEIGHTS_0`): each rounded, the
/// rounding's remainder given to the largest.
fn weight_bytes(weights: &[f32; 4]) -> [u8; 4] {
    let sum: f32 = weights.iter().sum::<f32>().max(1e-12);
    let mut q = weights.map(|w| (w / sum * 255.0).round().clamp(0.0, 255.0) as i32);
    let largest = (0..4).max_by(|&a, &b| q[a].cmp(&q[b])).unwrap_or(0);
    q[largest] += 255 - q.iter().sum::<i32>();
    q.map(|v| v.clamp(0, 255) as u8)
}
const CORRECTIVES: &str = "F3G_pose_correctives";
const AVATAR: &str = "F3G_avatar";
const SHADING: &str = "F3G_world_shading";

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// How far a stored opacity is kept from 0 and 1 before its logit: a file may hold exactly 0
/// or 1 (a sigmoid rounds to them in f32), whose logits would be infinite.
const OPACITY_MARGIN: f32 = 1e-7;

/// Column `c` of a `[rows, width]` array as `[rows, 3]` (the `c`-th VEC3 of each row).
fn vec3_column(values: &[f32], width: usize, c: usize) -> Vec<f32> {
    values
        .chunks_exact(width)
        .flat_map(|row| row[3 * c..3 * c + 3].to_vec())
        .collect()
}

/// The canonical pose's world transform of every joint.
fn canonical_world(avatar: &BakedAvatar) -> Result<Vec<Similarity>, AvatarError> {
    Ok(avatar
        .rig
        .pose(&f3g_template::without_root(&avatar.rig, &avatar.canonical))?
        .joints)
}

/// Writes `avatar` to `path` as `.glb` (atomically); returns the file's size in bytes.
pub fn write(avatar: &BakedAvatar, path: &Path, encoding: Encoding) -> Result<u64, AvatarError> {
    let bytes = to_bytes(avatar, encoding)?;
    f3g_io::write_atomic(path, &bytes)?;
    Ok(bytes.len() as u64)
}

/// The Gaussians' attributes of a compressed file: accessors without data and the SPZ payload
/// they come from; returns the attributes and the `KHR_gaussian_splatting` object.
fn spz_gaussians(
    avatar: &BakedAvatar,
    buffer: &mut GlbBuffer,
) -> Result<(Value, Value), AvatarError> {
    let cloud = f3g_splat::GaussianCloud {
        means: avatar.means.clone(),
        log_scales: avatar.log_scales.clone(),
        quats: avatar.quats.clone(),
        opacity_logits: avatar.opacity_logits.clone(),
        sh: avatar.sh.clone(),
        sh_degree: avatar.sh_degree,
    };
    let spz = f3g_splat::spz::encode(&cloud).map_err(|e| AvatarError::Invalid(e.to_string()))?;
    // POSITION's bounds are those of the positions as stored.
    let stored: Vec<f32> = avatar
        .means
        .iter()
        .enumerate()
        .map(|(i, &x)| f3g_splat::spz::stored_position(x, i % 3))
        .collect();
    let n = avatar.len();
    let mut attributes = json!({
        "POSITION": buffer.placeholder(n, "VEC3", Some(&stored)),
        format!("{SPLATS}:ROTATION"): buffer.placeholder(n, "VEC4", None),
        format!("{SPLATS}:SCALE"): buffer.placeholder(n, "VEC3", None),
        format!("{SPLATS}:OPACITY"): buffer.placeholder(n, "SCALAR", None),
    });
    for c in 0..f3g_splat::sh::num_coeffs(avatar.sh_degree) {
        let l = (c as f64).sqrt() as usize;
        attributes[format!("{SPLATS}:SH_DEGREE_{l}_COEF_{}", c - l * l)] =
            json!(buffer.placeholder(n, "VEC3", None));
    }
    let splats = json!({
        "kernel": "ellipse",
        "colorSpace": "srgb_rec709_display",
        "extensions": { SPZ: { "bufferView": buffer.view(&spz) } },
    });
    Ok((attributes, splats))
}

/// The `.glb` bytes of `avatar`.
pub fn to_bytes(avatar: &BakedAvatar, encoding: Encoding) -> Result<Vec<u8>, AvatarError> {
    let compressed = encoding == Encoding::Compressed;
    let n = avatar.len();
    let k = avatar.corrective_count();
    let e = avatar.expression_names.len();
    let mut buffer = GlbBuffer::default();
    let mut packer = Packer::default();
    let mut used_extensions = vec![SPLATS, CORRECTIVES, AVATAR];
    let mut required_extensions = Vec::new();
    const VERTEX: Option<u32> = Some(34962);

    // Gaussians.
    let (mut attributes, splats) = if compressed {
        used_extensions.push(SPZ);
        required_extensions.push(SPZ);
        spz_gaussians(avatar, &mut buffer)?
    } else {
        (
            float_gaussians(avatar, &mut buffer),
            json!({ "kernel": "ellipse", "colorSpace": "srgb_rec709_display" }),
        )
    };
    let joints: Vec<u16> = avatar.skin_joints.iter().flatten().copied().collect();
    if compressed {
        attributes["JOINTS_0"] = if avatar.rig.skeleton.len() <= 256 {
            let bytes: Vec<u8> = joints.iter().map(|&j| j as u8).collect();
            json!(buffer.accessor(&bytes, "VEC4", false, VERTEX))
        } else {
            json!(buffer.accessor(&joints, "VEC4", false, VERTEX))
        };
        let weights: Vec<u8> = avatar.skin_weights.iter().flat_map(weight_bytes).collect();
        attributes["WEIGHTS_0"] = json!(buffer.normalized_bytes(&weights, "VEC4", VERTEX));
    } else {
        let weights: Vec<f32> = avatar.skin_weights.iter().flatten().copied().collect();
        attributes["JOINTS_0"] = json!(buffer.accessor(&joints, "VEC4", false, VERTEX));
        attributes["WEIGHTS_0"] = json!(buffer.accessor(&weights, "VEC4", false, VERTEX));
    }

    // Correctives, then expressions: morph targets, or packed arrays.
    let stride = CORRECTIVE_VALUES * n;
    let mut targets = Vec::new();
    let mut names = Vec::new();
    let (mut colour, mut log_scale, mut opacity_logit) = (Vec::new(), Vec::new(), Vec::new());
    for c in 0..k {
        let basis = &avatar.correctives[c * stride..(c + 1) * stride];
        let column = |range: std::ops::Range<usize>| -> Vec<f32> {
            basis
                .chunks_exact(CORRECTIVE_VALUES)
                .flat_map(|g| g[range.clone()].to_vec())
                .collect()
        };
        if compressed {
            for (part, offset, width, bits) in CORRECTIVE_PARTS {
                let name = format!("corrective_{c}:{part}");
                packer.push(name, &column(offset..offset + width), width, bits);
            }
            continue;
        }
        targets.push(json!({ "POSITION": buffer.accessor(&column(0..3), "VEC3", true, VERTEX) }));
        colour.push(buffer.accessor(&column(3..6), "VEC3", false, None));
        log_scale.push(buffer.accessor(&column(6..9), "VEC3", false, None));
        opacity_logit.push(buffer.accessor(&column(9..10), "SCALAR", false, None));
        names.push(format!("corrective_{c}"));
    }
    for (i, name) in avatar.expression_names.iter().enumerate() {
        let d = &avatar.expressions[i * 3 * n..(i + 1) * 3 * n];
        if compressed {
            packer.push(format!("expression:{name}"), d, 3, POSITION_BITS);
            continue;
        }
        targets.push(json!({ "POSITION": buffer.accessor(d, "VEC3", true, VERTEX) }));
        names.push(format!("expression:{name}"));
    }
    let used: Vec<u32> = avatar.feature_used.iter().map(|&u| u as u32).collect();
    let mut correctives = json!({
        "count": k,
        "featureJoints": avatar.feature_joints,
        "expressions": e,
    });
    if !compressed {
        correctives["colour"] = json!(colour);
        correctives["logScale"] = json!(log_scale);
        correctives["opacityLogit"] = json!(opacity_logit);
    }
    if !used.is_empty() {
        correctives["featureUsed"] = json!(buffer.accessor(&used, "SCALAR", false, None));
        correctives["featureMean"] =
            json!(buffer.accessor(&avatar.feature_mean, "SCALAR", false, None));
    }
    if !avatar.feature_map.is_empty() {
        correctives["featureMap"] =
            json!(buffer.accessor(&avatar.feature_map, "SCALAR", false, None));
    }
    let mut primitive = json!({
        "attributes": attributes,
        "mode": 0,
        "extensions": {
            SPLATS: splats,
            CORRECTIVES: correctives,
        },
    });
    if !targets.is_empty() {
        primitive["targets"] = Value::Array(targets);
    }
    if let Some(light) = &avatar.shading {
        let mut shading = json!({ "coefficients": light.coefficients });
        if compressed {
            packer.push("shading:normal".into(), &light.normals, 3, NORMAL_BITS);
        } else {
            shading["normal"] = json!(buffer.accessor(&light.normals, "VEC3", false, None));
        }
        primitive["extensions"][SHADING] = shading;
        used_extensions.push(SHADING);
    }
    if compressed {
        primitive["extensions"][PACKED] = packer.finish(&mut buffer)?;
        used_extensions.push(PACKED);
        // Without its arrays no reader can pose the avatar as it was trained.
        required_extensions.push(PACKED);
    }
    let mut mesh = json!({ "name": "avatar", "primitives": [primitive] });
    if !names.is_empty() {
        mesh["weights"] = json!(vec![0.0; names.len()]);
        mesh["extras"] = json!({ "targetNames": names });
    }

    // Skeleton in the canonical pose.
    let world = canonical_world(avatar)?;
    let skeleton = avatar.rig.skeleton.joints();
    let (nodes, roots) = f3g_rig::glb::skinned_nodes(
        &avatar.rig.skeleton,
        |j| {
            let local = match skeleton[j].parent {
                Some(p) => world[p].inverse().compose(&world[j]),
                None => world[j],
            };
            json!({
                "translation": local.translation.to_array(),
                "rotation": local.rotation.normalize().to_array(),
                "scale": [local.scale, local.scale, local.scale],
            })
        },
        "avatar",
    );
    let inverse_bind: Vec<f32> = world
        .iter()
        .flat_map(|w| Mat4::from(w.inverse().to_affine()).to_cols_array())
        .collect();
    let inverse_bind = buffer.accessor(&inverse_bind, "MAT4", false, None);

    // The body model and what evaluation needs.
    // Deflated in compressed files: the body model is most of a float file's non-Gaussian
    // bytes (the built-in human's 34 expressions are 5.8 of its 9.2 MB, and deflate to 0.07).
    let entries = match encoding {
        Encoding::Float => f3g_io::NpzEntries::Stored,
        Encoding::Compressed => f3g_io::NpzEntries::Deflated,
    };
    let rig_bytes = f3g_rig::file::to_bytes(&avatar.rig, entries).map_err(AvatarError::Invalid)?;
    let body_model = buffer.view(&rig_bytes);
    let head: Vec<u32> = avatar.head_vertices.iter().map(|&v| v as u32).collect();
    let mut extension = json!({
        "version": VERSION,
        "bodyModel": { "bufferView": body_model, "name": avatar.rig.name },
        "parameters": {
            "pose": avatar.rig.pose_param_names(),
            "identity": avatar.rig.identity.names,
            "expression": avatar.rig.expression.names,
        },
        "canonicalPose": buffer.accessor(&avatar.canonical.pose, "SCALAR", false, None),
        "facePadding": avatar.face_padding,
        "faceCropSize": avatar.face_crop_size,
        "step": avatar.step,
    });
    if !avatar.canonical.identity.is_empty() {
        extension["canonicalIdentity"] =
            json!(buffer.accessor(&avatar.canonical.identity, "SCALAR", false, None));
    }
    if !head.is_empty() {
        extension["headVertices"] = json!(buffer.accessor(&head, "SCALAR", false, None));
    }
    let mut document = json!({
        "asset": { "version": "2.0", "generator": "f3g-avatar export-avatar" },
        "extensionsUsed": used_extensions,
        "extensions": { AVATAR: extension },
        "scene": 0,
        "scenes": [{ "nodes": roots }],
        "nodes": nodes,
        "meshes": [mesh],
        "skins": [{
            "joints": (0..skeleton.len()).collect::<Vec<_>>(),
            "inverseBindMatrices": inverse_bind,
        }],
    });
    if !required_extensions.is_empty() {
        document["extensionsRequired"] = json!(required_extensions);
    }
    Ok(buffer.finish(document))
}

/// The Gaussians' attributes of a float file: every value in its own accessor.
fn float_gaussians(avatar: &BakedAvatar, buffer: &mut GlbBuffer) -> Value {
    const VERTEX: Option<u32> = Some(34962);
    let position = buffer.accessor(&avatar.means, "VEC3", true, VERTEX);
    let rotations: Vec<f32> = avatar
        .quats
        .chunks_exact(4)
        .flat_map(|q| {
            let length = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
            [q[1] / length, q[2] / length, q[3] / length, q[0] / length]
        })
        .collect();
    let rotation = buffer.accessor(&rotations, "VEC4", false, VERTEX);
    let scales: Vec<f32> = avatar.log_scales.iter().map(|s| s.exp()).collect();
    let scale = buffer.accessor(&scales, "VEC3", false, VERTEX);
    let opacities: Vec<f32> = avatar.opacity_logits.iter().map(|&o| sigmoid(o)).collect();
    let opacity = buffer.accessor(&opacities, "SCALAR", false, VERTEX);
    let mut attributes = json!({
        "POSITION": position,
        format!("{SPLATS}:ROTATION"): rotation,
        format!("{SPLATS}:SCALE"): scale,
        format!("{SPLATS}:OPACITY"): opacity,
    });
    let coeffs = f3g_splat::sh::num_coeffs(avatar.sh_degree);
    for c in 0..coeffs {
        let l = (c as f64).sqrt() as usize;
        let values = vec3_column(&avatar.sh, 3 * coeffs, c);
        attributes[format!("{SPLATS}:SH_DEGREE_{l}_COEF_{}", c - l * l)] =
            json!(buffer.accessor(&values, "VEC3", false, VERTEX));
    }
    attributes
}

/// Reads an avatar file written by [`write`]; every count and index is checked, so a
/// truncated, foreign or inconsistent file is an error naming it.
pub fn read(path: &Path) -> Result<BakedAvatar, AvatarError> {
    let bytes = std::fs::read(path).map_err(|e| AvatarError::file(path, e))?;
    from_bytes(&bytes).map_err(|e| AvatarError::file(path, e))
}

/// The glTF structure a player reads beyond what [`from_bytes`] takes: buffer sizes against
/// the file, buffer views inside their buffer, a node tree (children that exist, one parent
/// each, no cycle) and finite inverse-bind matrices.
fn check_structure(file: &GlbFile) -> Result<(), String> {
    let doc = &file.document;
    let array = |name: &str| doc[name].as_array().map_or(&[][..], Vec::as_slice);
    let buffers = array("buffers");
    for (i, b) in buffers.iter().enumerate() {
        let length = b["byteLength"].as_u64().unwrap_or(u64::MAX);
        if b.get("uri").is_some() || length > file.bin_len() as u64 {
            return Err(format!(
                "buffer {i} declares {} bytes{}, the file's binary chunk holds {}",
                b["byteLength"],
                if b.get("uri").is_some() {
                    " in another file"
                } else {
                    ""
                },
                file.bin_len()
            ));
        }
    }
    for (i, v) in array("bufferViews").iter().enumerate() {
        let buffer = v["buffer"].as_u64().and_then(|b| buffers.get(b as usize));
        let end = v["byteOffset"]
            .as_u64()
            .unwrap_or(0)
            .checked_add(v["byteLength"].as_u64().unwrap_or(u64::MAX));
        match (buffer, end) {
            (Some(b), Some(end)) if end <= b["byteLength"].as_u64().unwrap_or(0) => {}
            _ => return Err(format!("buffer view {i} lies outside its buffer")),
        }
    }
    let nodes = array("nodes");
    let mut parent = vec![None; nodes.len()];
    for (i, node) in nodes.iter().enumerate() {
        for c in node["children"].as_array().map_or(&[][..], Vec::as_slice) {
            let c = c
                .as_u64()
                .map(|c| c as usize)
                .filter(|&c| c < nodes.len())
                .ok_or_else(|| format!("node {i} has a child {c} that is not a node"))?;
            if parent[c].replace(i).is_some() {
                return Err(format!("node {c} is the child of two nodes"));
            }
        }
    }
    for start in 0..nodes.len() {
        let (mut at, mut steps) = (start, 0);
        while let Some(p) = parent[at] {
            at = p;
            steps += 1;
            if steps > nodes.len() {
                return Err(format!("node {start} lies on a cycle of nodes"));
            }
        }
    }
    for (i, skin) in array("skins").iter().enumerate() {
        let joints = skin["joints"].as_array().map_or(&[][..], Vec::as_slice);
        if joints
            .iter()
            .any(|j| j.as_u64().is_none_or(|j| j as usize >= nodes.len()))
        {
            return Err(format!("skin {i} names a joint that is not a node"));
        }
        if let Some(a) = skin["inverseBindMatrices"].as_u64() {
            let matrices = file.floats(a as usize, 16)?;
            if matrices.len() != 16 * joints.len() {
                return Err(format!(
                    "skin {i} has {} inverse-bind matrices for {} joints",
                    matrices.len() / 16,
                    joints.len()
                ));
            }
            if let Some(at) = matrices.iter().position(|x| !x.is_finite()) {
                return Err(format!(
                    "skin {i}'s inverse-bind matrix {} holds a non-finite value",
                    at / 16
                ));
            }
        }
    }
    Ok(())
}

/// An index field of a JSON object.
fn index(v: &Value, what: &str) -> Result<usize, String> {
    v.as_u64()
        .map(|i| i as usize)
        .ok_or_else(|| format!("{what} is missing or not an index"))
}

/// Float accessor `v` (an index) with `width` components, every value finite.
fn finite(file: &GlbFile, v: &Value, width: usize, what: &str) -> Result<Vec<f32>, String> {
    let values = file.floats(index(v, what)?, width)?;
    match values.iter().position(|x| !x.is_finite()) {
        Some(i) => Err(format!("{what} holds a non-finite value at {i}")),
        None => Ok(values),
    }
}

/// `values` if they are `width` per Gaussian of `n`, else an error naming `what`.
fn per_gaussian(values: Vec<f32>, width: usize, n: usize, what: &str) -> Result<Vec<f32>, String> {
    if values.len() == width * n {
        Ok(values)
    } else {
        Err(format!(
            "{what} has {} values for {n} Gaussians",
            values.len()
        ))
    }
}

/// Values out of range are refused, not clamped: the player would draw them as they are.
fn in_range(
    values: &[f32],
    width: usize,
    what: &str,
    ok: &dyn Fn(&[f32]) -> bool,
    expected: &str,
) -> Result<(), String> {
    match values.chunks_exact(width).position(|v| !ok(v)) {
        Some(g) => Err(format!(
            "{what} of Gaussian {g} is {:?}, expected {expected}",
            &values[g * width..(g + 1) * width]
        )),
        None => Ok(()),
    }
}

/// The Gaussians of a float file, from their accessors.
fn float_gaussians_read(
    file: &GlbFile,
    attributes: &Value,
) -> Result<f3g_splat::GaussianCloud, String> {
    let means = finite(file, &attributes["POSITION"], 3, "POSITION")?;
    let n = means.len() / 3;
    let sized = |values, width, what: &str| per_gaussian(values, width, n, what);
    let rotation = format!("{SPLATS}:ROTATION");
    let rotations = sized(
        finite(file, &attributes[&rotation], 4, &rotation)?,
        4,
        &rotation,
    )?;
    in_range(
        &rotations,
        4,
        &rotation,
        &|q| q.iter().map(|x| x * x).sum::<f32>() > 1e-12,
        "a quaternion that is not zero",
    )?;
    let quats: Vec<f32> = rotations
        .chunks_exact(4)
        .flat_map(|q| [q[3], q[0], q[1], q[2]])
        .collect();
    let scale = format!("{SPLATS}:SCALE");
    let scales = sized(finite(file, &attributes[&scale], 3, &scale)?, 3, &scale)?;
    in_range(
        &scales,
        3,
        &scale,
        &|s| s.iter().all(|&x| x > 0.0),
        "three positive scales",
    )?;
    let log_scales: Vec<f32> = scales.iter().map(|s| s.ln()).collect();
    let opacity = format!("{SPLATS}:OPACITY");
    let opacities = sized(
        finite(file, &attributes[&opacity], 1, &opacity)?,
        1,
        &opacity,
    )?;
    in_range(
        &opacities,
        1,
        &opacity,
        &|o| (0.0..=1.0).contains(&o[0]),
        "an opacity in [0, 1]",
    )?;
    let opacity_logits: Vec<f32> = opacities
        .iter()
        .map(|&o| logit(o.clamp(OPACITY_MARGIN, 1.0 - OPACITY_MARGIN)))
        .collect();
    let mut degree = 0;
    while degree < 3
        && attributes
            .get(format!("{SPLATS}:SH_DEGREE_{}_COEF_0", degree + 1))
            .is_some()
    {
        degree += 1;
    }
    let coeffs = f3g_splat::sh::num_coeffs(degree);
    let mut sh = vec![0.0f32; n * coeffs * 3];
    for c in 0..coeffs {
        let l = (c as f64).sqrt() as usize;
        let name = format!("{SPLATS}:SH_DEGREE_{l}_COEF_{}", c - l * l);
        let values = sized(finite(file, &attributes[&name], 3, &name)?, 3, &name)?;
        for g in 0..n {
            sh[(g * coeffs + c) * 3..(g * coeffs + c) * 3 + 3]
                .copy_from_slice(&values[3 * g..3 * g + 3]);
        }
    }
    Ok(f3g_splat::GaussianCloud {
        means,
        log_scales,
        quats,
        opacity_logits,
        sh,
        sh_degree: degree,
    })
}

/// Reads an avatar from `.glb` bytes; errors say what is wrong.
pub fn from_bytes(bytes: &[u8]) -> Result<BakedAvatar, String> {
    let file = GlbFile::parse(bytes)?;
    check_structure(&file)?;
    let doc = &file.document;
    let ext = doc
        .pointer(&format!("/extensions/{AVATAR}"))
        .ok_or_else(|| format!("not an f3g avatar: no `{AVATAR}` extension (a plain glTF?)"))?;
    if ext["version"].as_u64() != Some(VERSION) {
        return Err(format!(
            "`{AVATAR}` version {}, this f3g reads version {VERSION}",
            ext["version"]
        ));
    }
    let rig_view = index(&ext["bodyModel"]["bufferView"], "bodyModel.bufferView")?;
    let rig = f3g_rig::file::from_bytes(file.view(rig_view)?, "the embedded body model")
        .map_err(|e| e.to_string())?;
    let pose = finite(&file, &ext["canonicalPose"], 1, "canonicalPose")?;
    let identity = match ext.get("canonicalIdentity") {
        Some(v) => finite(&file, v, 1, "canonicalIdentity")?,
        None => Vec::new(),
    };
    let canonical = RigParams {
        pose,
        identity,
        expression: vec![0.0; rig.expression.len()],
    };
    if canonical.pose.len() != rig.num_pose_params()
        || canonical.identity.len() != rig.identity.len()
    {
        return Err("the canonical pose does not fit the embedded body model".into());
    }
    let head_vertices: Vec<usize> = match ext.get("headVertices") {
        Some(v) => file
            .ints(index(v, "headVertices")?, 1)?
            .into_iter()
            .map(|x| x as usize)
            .collect(),
        None => Vec::new(),
    };
    if head_vertices.iter().any(|&v| v >= rig.mesh.vertices.len()) {
        return Err("headVertices names a vertex the body model does not have".into());
    }
    // The training range of `face_padding`: anything else crops the head wrongly (≤ 0: a
    // four-pixel crop that scores as a perfect head; huge: an image-sized crop).
    let face_padding = match &ext["facePadding"] {
        Value::Null => 1.3,
        v => v
            .as_f64()
            .filter(|p| (1.0..=4.0).contains(p))
            .ok_or_else(|| format!("F3G_avatar.facePadding is {v}, expected a number in [1, 4]"))?
            as f32,
    };
    let face_crop_size = match &ext["faceCropSize"] {
        Value::Null => 128,
        v => v
            .as_u64()
            .filter(|s| (16..=2048).contains(s))
            .ok_or_else(|| {
                format!("F3G_avatar.faceCropSize is {v}, expected a whole number in [16, 2048]")
            })? as usize,
    };

    let primitive = doc
        .pointer("/meshes/0/primitives/0")
        .ok_or("the file has no mesh primitive")?;
    let attributes = &primitive["attributes"];
    let attribute = |name: &str| index(&attributes[name], &format!("attribute {name}"));
    if primitive
        .pointer(&format!("/extensions/{SPLATS}"))
        .is_none()
    {
        return Err(format!("the primitive has no `{SPLATS}` extension"));
    }
    let gaussians = match primitive.pointer(&format!("/extensions/{SPLATS}/extensions/{SPZ}")) {
        Some(spz) => {
            let view = index(&spz["bufferView"], &format!("{SPZ}.bufferView"))?;
            let cloud =
                f3g_splat::spz::decode(file.view(view)?).map_err(|e| format!("{SPZ}: {e}"))?;
            let declared = doc["accessors"][attribute("POSITION")?]["count"].as_u64();
            if declared != Some(cloud.len() as u64) {
                return Err(format!(
                    "POSITION declares {declared:?} Gaussians, the SPZ payload holds {}",
                    cloud.len()
                ));
            }
            cloud
        }
        None => float_gaussians_read(&file, attributes)?,
    };
    let n = gaussians.len();
    let sized = |values, width, what: &str| per_gaussian(values, width, n, what);
    let joints_accessor = attribute("JOINTS_0")?;
    let joints: Vec<u16> = match file.component_type(joints_accessor) {
        Some(f3g_rig::glb::UNSIGNED_BYTE) => file
            .bytes(joints_accessor, 4)?
            .0
            .into_iter()
            .map(u16::from)
            .collect(),
        _ => file.shorts(joints_accessor, 4)?,
    };
    let weights_accessor = attribute("WEIGHTS_0")?;
    let weights = match file.component_type(weights_accessor) {
        Some(f3g_rig::glb::UNSIGNED_BYTE) => match file.bytes(weights_accessor, 4)? {
            (bytes, true) => bytes.into_iter().map(|b| b as f32 / 255.0).collect(),
            (_, false) => return Err("WEIGHTS_0 holds unsigned bytes not marked normalized".into()),
        },
        _ => finite(&file, &attributes["WEIGHTS_0"], 4, "WEIGHTS_0")?,
    };
    let weights = sized(weights, 4, "WEIGHTS_0")?;
    if joints.len() != 4 * n || joints.iter().any(|&j| j as usize >= rig.skeleton.len()) {
        return Err("JOINTS_0 does not name four joints of the skeleton per Gaussian".into());
    }
    in_range(
        &weights,
        4,
        "WEIGHTS_0",
        &|w| w.iter().all(|&x| x >= 0.0) && w.iter().sum::<f32>() > 1e-6,
        "four weights ≥ 0 with a positive sum",
    )?;
    let correctives_ext = primitive
        .pointer(&format!("/extensions/{CORRECTIVES}"))
        .ok_or_else(|| format!("the primitive has no `{CORRECTIVES}`"))?;
    let k = index(&correctives_ext["count"], "count")?;
    let e = index(&correctives_ext["expressions"], "expressions")?;
    let mut packed = match primitive.pointer(&format!("/extensions/{PACKED}")) {
        Some(ext) => Some(Packed::read(&file, ext, n)?),
        None => None,
    };
    // Counts are checked against the arrays that hold them before anything is allocated.
    let mut correctives: Vec<f32>;
    let mut expression_names = Vec::new();
    let mut expressions = Vec::new();
    if let Some(packed) = &mut packed {
        // Compressed: the correctives and expressions are packed arrays, in the file's order.
        let names: Vec<String> = packed.names.clone();
        let stored = names.iter().filter(|n| n.ends_with(":position")).count();
        if stored != k {
            return Err(format!(
                "{PACKED} holds {stored} correctives, {CORRECTIVES}.count says {k}"
            ));
        }
        correctives = vec![0.0f32; k * n * CORRECTIVE_VALUES];
        for c in 0..k {
            for (part, offset, width, _) in CORRECTIVE_PARTS {
                let values = packed.take(&format!("corrective_{c}:{part}"))?;
                scatter(&mut correctives, &values, c * n, offset, width);
            }
        }
        for name in names.iter().filter_map(|n| n.strip_prefix("expression:")) {
            expressions.extend(packed.take(&format!("expression:{name}"))?);
            expression_names.push(name.to_string());
        }
        if expression_names.len() != e {
            return Err(format!(
                "{PACKED} holds {} expressions, {CORRECTIVES} says {e}",
                expression_names.len()
            ));
        }
    } else {
        let targets = primitive["targets"].as_array().cloned().unwrap_or_default();
        if targets.len() != k + e {
            return Err(format!(
                "{} morph targets, but {k} correctives and {e} expressions",
                targets.len()
            ));
        }
        let list = |name: &str| -> Result<Vec<Value>, String> {
            let v = correctives_ext[name]
                .as_array()
                .cloned()
                .unwrap_or_default();
            if v.len() == k {
                Ok(v)
            } else {
                Err(format!(
                    "`{name}` lists {} accessors for {k} correctives",
                    v.len()
                ))
            }
        };
        let (colour, log_scale, opacity_logit) =
            (list("colour")?, list("logScale")?, list("opacityLogit")?);
        correctives = vec![0.0f32; k * n * CORRECTIVE_VALUES];
        for c in 0..k {
            let parts = [
                (&targets[c]["POSITION"], "a corrective's POSITION", 0, 3),
                (&colour[c], "colour", 3, 3),
                (&log_scale[c], "logScale", 6, 3),
                (&opacity_logit[c], "opacityLogit", 9, 1),
            ];
            for (accessor, what, offset, width) in parts {
                let values = sized(finite(&file, accessor, width, what)?, width, what)?;
                scatter(&mut correctives, &values, c * n, offset, width);
            }
        }
        let names: Vec<String> = doc
            .pointer("/meshes/0/extras/targetNames")
            .and_then(|v| serde_json::from_value(v.clone()).ok())
            .unwrap_or_default();
        for i in 0..e {
            let name = names
                .get(k + i)
                .and_then(|n| n.strip_prefix("expression:"))
                .ok_or_else(|| format!("morph target {} is not named `expression:…`", k + i))?;
            expression_names.push(name.to_string());
            expressions.extend(sized(
                finite(
                    &file,
                    &targets[k + i]["POSITION"],
                    3,
                    "an expression's POSITION",
                )?,
                3,
                name,
            )?);
        }
    }
    let feature_joints: Vec<usize> =
        serde_json::from_value(correctives_ext["featureJoints"].clone())
            .map_err(|e| format!("featureJoints: {e}"))?;
    if feature_joints.iter().any(|&j| j >= rig.skeleton.len()) {
        return Err("featureJoints names a joint the skeleton does not have".into());
    }
    let (feature_used, feature_mean) = match correctives_ext.get("featureUsed") {
        Some(v) => {
            let used: Vec<usize> = file
                .ints(index(v, "featureUsed")?, 1)?
                .into_iter()
                .map(|u| u as usize)
                .collect();
            if used.iter().any(|&u| u >= 9 * feature_joints.len()) {
                return Err("featureUsed names a feature beyond the feature joints'".into());
            }
            let mean = finite(&file, &correctives_ext["featureMean"], 1, "featureMean")?;
            if mean.len() != used.len() {
                return Err("featureMean and featureUsed differ in length".into());
            }
            (used, mean)
        }
        None => (Vec::new(), Vec::new()),
    };
    let feature_map = match correctives_ext.get("featureMap") {
        Some(v) => finite(&file, v, 1, "featureMap")?,
        None => Vec::new(),
    };
    if feature_map.len() != k * feature_used.len() {
        return Err(format!(
            "featureMap has {} values for {k} correctives × {} features",
            feature_map.len(),
            feature_used.len()
        ));
    }
    let shading = match primitive.pointer(&format!("/extensions/{SHADING}")) {
        None => None,
        Some(light) => {
            let coefficients: Vec<f32> = serde_json::from_value(light["coefficients"].clone())
                .ok()
                .filter(|c: &Vec<f32>| {
                    c.len() == 3 * crate::model::shading::SHADING_BASIS
                        && c.iter().all(|x| x.is_finite())
                })
                .ok_or_else(|| {
                    format!(
                        "{SHADING}.coefficients is {}, expected 27 finite numbers",
                        light["coefficients"]
                    )
                })?;
            let normals = match &mut packed {
                // Quantised normals are unit again once normalised.
                Some(packed) => packed
                    .take("shading:normal")?
                    .chunks_exact(3)
                    .flat_map(|v| {
                        let length = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
                        [v[0] / length, v[1] / length, v[2] / length]
                    })
                    .collect(),
                None => finite(&file, &light["normal"], 3, &format!("{SHADING}.normal"))?,
            };
            let normals = sized(normals, 3, &format!("{SHADING}.normal"))?;
            in_range(
                &normals,
                3,
                &format!("{SHADING}.normal"),
                &|n| (n.iter().map(|x| x * x).sum::<f32>() - 1.0).abs() < 1e-3,
                "a unit vector",
            )?;
            Some(BakedShading {
                coefficients,
                normals,
            })
        }
    };
    Ok(BakedAvatar {
        shading,
        rig,
        canonical,
        means: gaussians.means,
        quats: gaussians.quats,
        log_scales: gaussians.log_scales,
        opacity_logits: gaussians.opacity_logits,
        sh: gaussians.sh,
        sh_degree: gaussians.sh_degree,
        skin_joints: joints
            .chunks_exact(4)
            .map(|c| [c[0], c[1], c[2], c[3]])
            .collect(),
        skin_weights: weights
            .chunks_exact(4)
            .map(|c| [c[0], c[1], c[2], c[3]])
            .collect(),
        correctives,
        feature_joints,
        feature_used,
        feature_mean,
        feature_map,
        expression_names,
        expressions,
        head_vertices,
        face_padding,
        face_crop_size,
        step: ext["step"].as_u64().unwrap_or(0),
    })
}
