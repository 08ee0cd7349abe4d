//! glTF animations (`.glb`, `.gltf`): read from a skin's joints, written with one.
//!
//! Reading: the first skin is the skeleton (its joints' rest transforms from their nodes,
//! [`f3g_rig::gltf::skin_joints`]); the first animation (or the one named) drives it. Each
//! joint's rotation channel is sampled at the frame times — step, linear (spherical) or cubic
//! spline (its values, without the tangents) — and the root's translation channel likewise;
//! other joints' translations and all scales are ignored. glTF stores key times, not a frame
//! rate: the frames are at the rate the smallest key interval gives (rounded, at most 240).
//! glTF is +Y up, in metres.
//!
//! Checked before the `gltf` crate reads them (it unwraps or assumes what it does not
//! validate): every channel's target node, path and sampler; the read channels' accessor
//! types, counts and byte ranges; key times finite and strictly increasing; rotation keys
//! unit quaternions, root translations within [`crate::MAX_TRANSLATION_METRES`]. Buffers
//! are read by [`f3g_rig::gltf::import`]: files beside the `.gltf` only.
//!
//! Writing: the skeleton as nodes under one skin (inverse bind matrices of the rest pose, no
//! mesh), one animation with a rotation channel per joint and a translation channel for the
//! root, linear, at the motion's frame times.

use std::path::Path;

use glam::{Mat4, Quat, Vec3};
use gltf::json::validation::Checked;
use serde_json::json;

use f3g_rig::glb::GlbBuffer;

use crate::{MAX_FRAMES, MAX_TRANSLATION_METRES, Motion, MotionError, Up};

/// Key times and values of one channel.
struct Track<T> {
    times: Vec<f32>,
    values: Vec<T>,
    step: bool,
}

impl<T: Copy> Track<T> {
    /// The value at `t` (clamped to the keys), blending neighbours with `mix`.
    fn at(&self, t: f32, mix: impl Fn(T, T, f32) -> T) -> T {
        let k = self.times.partition_point(|&x| x <= t);
        if k == 0 {
            return self.values[0];
        }
        if k >= self.times.len() || self.step {
            return self.values[k.min(self.times.len()) - 1];
        }
        let (t0, t1) = (self.times[k - 1], self.times[k]);
        let u = if t1 > t0 { (t - t0) / (t1 - t0) } else { 0.0 };
        mix(self.values[k - 1], self.values[k], u)
    }
}

/// Reads a glTF animation (module docs); `animation` picks one by name.
pub fn read_gltf(path: &Path, animation: Option<&str>) -> Result<Motion, MotionError> {
    let (doc, buffers) = f3g_rig::gltf::import(path)?;
    let skin = doc
        .skins()
        .next()
        .ok_or_else(|| MotionError::file(path, "a glTF motion needs a skin (its skeleton)"))?;
    let joints = f3g_rig::gltf::skin_joints(&doc, &skin, path)?;
    let names: Vec<String> = doc
        .animations()
        .map(|a| a.name().unwrap_or("").to_string())
        .collect();
    let anim = match animation {
        Some(name) => doc
            .animations()
            .find(|a| a.name() == Some(name))
            .ok_or_else(|| {
                MotionError::file(
                    path,
                    format!("no animation `{name}` (it has: {})", names.join(", ")),
                )
            })?,
        None => doc
            .animations()
            .next()
            .ok_or_else(|| MotionError::file(path, "holds no animation"))?,
    };
    check_targets(&doc, anim.index(), path)?;
    let n = joints.skeleton.len();
    let mut rotations: Vec<Option<Track<Quat>>> = (0..n).map(|_| None).collect();
    let mut root: Option<Track<Vec3>> = None;
    let data = |b: gltf::Buffer| buffers.get(b.index()).map(|d| &d.0[..]);
    use gltf::animation::{Interpolation, Property, util::ReadOutputs};
    for (c, channel) in anim.channels().enumerate() {
        let node = channel.target().node().index();
        let Some(j) = joints.nodes.iter().position(|&x| x == node) else {
            continue;
        };
        let property = channel.target().property();
        let is_root = joints.skeleton.joints()[j].parent.is_none();
        if !(property == Property::Rotation || (property == Property::Translation && is_root)) {
            continue;
        }
        let sampler = channel.sampler();
        let interpolation = sampler.interpolation();
        check_sampler(c, &sampler, property, &buffers, path)?;
        let reader = channel.reader(data);
        let error =
            |reason: String| MotionError::file(path, format!("animation channel {c}: {reason}"));
        let times: Vec<f32> = reader
            .read_inputs()
            .ok_or_else(|| error("its key times cannot be read".into()))?
            .collect();
        check_times(&times).map_err(error)?;
        // Cubic splines store (in-tangent, value, out-tangent) per key.
        let keep = |k: usize| interpolation != Interpolation::CubicSpline || k % 3 == 1;
        let step = interpolation == Interpolation::Step;
        match reader.read_outputs() {
            Some(ReadOutputs::Rotations(r)) => {
                let values: Vec<Quat> = r
                    .into_f32()
                    .enumerate()
                    .filter(|(k, _)| keep(*k))
                    .map(|(_, q)| Quat::from_array(q))
                    .collect();
                if let Some((k, q)) = values
                    .iter()
                    .enumerate()
                    .find(|(_, q)| !QUATERNION_NORM.contains(&q.length()))
                {
                    return Err(error(format!(
                        "rotation key {k} {q} is not a unit quaternion (norm {})",
                        q.length()
                    )));
                }
                rotations[j] = Some(Track {
                    times,
                    values,
                    step,
                });
            }
            Some(ReadOutputs::Translations(t)) => {
                let values: Vec<Vec3> = t
                    .enumerate()
                    .filter(|(k, _)| keep(*k))
                    .map(|(_, v)| Vec3::from_array(v))
                    .collect();
                if let Some((k, v)) = values
                    .iter()
                    .enumerate()
                    .find(|(_, v)| !v.is_finite() || v.length() > MAX_TRANSLATION_METRES)
                {
                    return Err(error(format!(
                        "translation key {k} {v} m is not within {} km of the origin",
                        MAX_TRANSLATION_METRES / 1000.0
                    )));
                }
                root = Some(Track {
                    times,
                    values,
                    step,
                });
            }
            _ => return Err(error("its values cannot be read".into())),
        }
    }
    let tracks: Vec<&[f32]> = rotations
        .iter()
        .flatten()
        .map(|t| t.times.as_slice())
        .chain(root.iter().map(|t| t.times.as_slice()))
        .collect();
    if tracks.is_empty() {
        return Err(MotionError::file(
            path,
            "the animation moves none of the skin's joints",
        ));
    }
    let all = tracks.iter().flat_map(|t| t.iter().copied());
    let start = all.clone().fold(f32::MAX, f32::min);
    let end = all.fold(f32::MIN, f32::max);
    let shortest = tracks
        .iter()
        .flat_map(|t| t.windows(2).map(|w| w[1] - w[0]))
        .filter(|d| *d > 1e-4)
        .fold(f32::MAX, f32::min);
    let fps = if shortest == f32::MAX {
        30.0
    } else {
        (1.0 / shortest).round().clamp(1.0, 240.0)
    };
    let frames = ((end - start) * fps).round() as f64 + 1.0;
    if !(frames >= 1.0 && frames <= MAX_FRAMES as f64) {
        return Err(MotionError::file(
            path,
            format!(
                "the animation lasts {} s: more frames than f3g reads",
                end - start
            ),
        ));
    }
    let frames = frames as usize;
    crate::ensure_memory(frames, n, path)?;
    let rest = joints.skeleton.joints();
    // The root joint's non-joint ancestors: its offset and rest rotation include them, its
    // keys do not.
    let root_node = doc
        .nodes()
        .nth(joints.nodes[0])
        .expect("a skin joint is a node");
    let (t, r, _) = root_node.transform().decomposed();
    let ancestors = joints.world[0]
        * Mat4::from_rotation_translation(Quat::from_array(r).normalize(), Vec3::from(t)).inverse();
    let (_, ancestors_rotation, _) = ancestors.to_scale_rotation_translation();
    let mut out_rotations = Vec::with_capacity(frames * n);
    let mut root_translation = Vec::with_capacity(frames);
    for f in 0..frames {
        let t = start + f as f32 / fps;
        for (j, track) in rotations.iter().enumerate() {
            let local = match track {
                Some(tr) => tr.at(t, |a, b, u| a.slerp(b, u)).normalize(),
                None => {
                    out_rotations.push(Quat::IDENTITY);
                    continue;
                }
            };
            // The node's rotation is the rest rotation times the pose.
            let rest_local = if j == 0 {
                ancestors_rotation * local
            } else {
                local
            };
            out_rotations.push((rest[j].pre_rotation.conjugate() * rest_local).normalize());
        }
        root_translation.push(match &root {
            Some(tr) => {
                ancestors.transform_point3(tr.at(t, |a, b, u| a.lerp(b, u))) - rest[0].offset
            }
            None => Vec3::ZERO,
        });
    }
    let motion = Motion {
        skeleton: joints.skeleton.clone(),
        rotations: out_rotations,
        root_translation,
        fps,
        metres_per_unit: 1.0,
        up: Up::Y,
        smpl: None,
    };
    crate::check_values(&motion, path)?;
    Ok(motion)
}

/// Rotation keys are unit quaternions (glTF 2.0); writers' rounding and normalized integer
/// components stay within a few percent of norm 1, a key outside this range is damage.
const QUATERNION_NORM: std::ops::RangeInclusive<f32> = 0.5..=2.0;

/// The most elements a sampler's accessor may have: a key per frame, three for cubic splines.
const MAX_KEYS: usize = MAX_FRAMES * 3;

/// Refuses what the `gltf` crate unwraps without checking (gltf 1.4.1 validates neither a
/// channel's target node nor its path): every channel of animation `anim` must name an
/// existing node, one of glTF's target paths, and a sampler of the animation.
fn check_targets(doc: &gltf::Document, anim: usize, path: &Path) -> Result<(), MotionError> {
    let json = &doc.as_json().animations[anim];
    let nodes = doc.nodes().len();
    for (c, channel) in json.channels.iter().enumerate() {
        let error =
            |reason: String| MotionError::file(path, format!("animation channel {c}: {reason}"));
        let node = channel.target.node.value();
        if node >= nodes {
            return Err(error(format!(
                "target.node is node {node}, but the file has {nodes} nodes"
            )));
        }
        if matches!(channel.target.path, Checked::Invalid) {
            return Err(error(
                "target.path is not one of glTF's: translation, rotation, scale, weights".into(),
            ));
        }
        let sampler = channel.sampler.value();
        if sampler >= json.samplers.len() {
            return Err(error(format!(
                "uses sampler {sampler}, but the animation has {} samplers",
                json.samplers.len()
            )));
        }
    }
    Ok(())
}

/// Refuses a sampler whose accessors the `gltf` crate's readers would misread or panic on
/// (they assume the element type and index the buffer without checking): key times `SCALAR`
/// floats, rotations `VEC4` floats (or normalized integers), translations `VEC3` floats, as
/// many values as key times (three per key for cubic splines), and each accessor's
/// elements inside its buffer view and buffer ([`check_layout`]).
fn check_sampler(
    c: usize,
    sampler: &gltf::animation::Sampler,
    property: gltf::animation::Property,
    buffers: &[gltf::buffer::Data],
    path: &Path,
) -> Result<(), MotionError> {
    use gltf::accessor::{DataType, Dimensions};
    let (input, output) = (sampler.input(), sampler.output());
    let error =
        |reason: String| MotionError::file(path, format!("animation channel {c}: {reason}"));
    if (input.dimensions(), input.data_type()) != (Dimensions::Scalar, DataType::F32) {
        return Err(error(format!(
            "key times (accessor {}) are {:?} {:?}: expected SCALAR FLOAT",
            input.index(),
            input.dimensions(),
            input.data_type()
        )));
    }
    let fits = match property {
        gltf::animation::Property::Rotation => {
            output.dimensions() == Dimensions::Vec4
                && (output.data_type() == DataType::F32
                    || (output.normalized()
                        && matches!(
                            output.data_type(),
                            DataType::I8 | DataType::U8 | DataType::I16 | DataType::U16
                        )))
        }
        _ => (output.dimensions(), output.data_type()) == (Dimensions::Vec3, DataType::F32),
    };
    if !fits {
        return Err(error(format!(
            "values (accessor {}) are {:?} {:?}{}: expected {}",
            output.index(),
            output.dimensions(),
            output.data_type(),
            if output.normalized() {
                " normalized"
            } else {
                ""
            },
            match property {
                gltf::animation::Property::Rotation => {
                    "VEC4 FLOAT (or normalized BYTE, UNSIGNED_BYTE, SHORT, UNSIGNED_SHORT)"
                }
                _ => "VEC3 FLOAT",
            }
        )));
    }
    check_layout(&input, buffers)
        .map_err(|e| error(format!("key times (accessor {}) {e}", input.index())))?;
    check_layout(&output, buffers)
        .map_err(|e| error(format!("values (accessor {}) {e}", output.index())))?;
    let per_key = match sampler.interpolation() {
        gltf::animation::Interpolation::CubicSpline => 3,
        _ => 1,
    };
    if output.count() != input.count() * per_key {
        return Err(error(format!(
            "{} key times but {} values (expected {})",
            input.count(),
            output.count(),
            input.count() * per_key
        )));
    }
    Ok(())
}

/// Checks an accessor's layout: 1 to [`MAX_KEYS`] elements, in a buffer view or sparse, each
/// element (and a sparse accessor's indices and values) inside its view and buffer.
fn check_layout(a: &gltf::Accessor, buffers: &[gltf::buffer::Data]) -> Result<(), String> {
    let count = a.count();
    if count == 0 || count > MAX_KEYS {
        return Err(format!("has {count} elements: expected 1 to {MAX_KEYS}"));
    }
    match (a.view(), a.sparse()) {
        (None, None) => return Err("has neither a bufferView nor sparse values".into()),
        (Some(view), _) => span(&view, a.offset(), count, a.size(), buffers)?,
        (None, Some(_)) => {}
    }
    if let Some(sparse) = a.sparse() {
        let n = sparse.count();
        if n == 0 || n > count {
            return Err(format!("has {n} sparse elements: expected 1 to {count}"));
        }
        let indices = sparse.indices();
        span(
            &indices.view(),
            indices.offset(),
            n,
            indices.index_type().size(),
            buffers,
        )
        .map_err(|e| format!("sparse indices: {e}"))?;
        let values = sparse.values();
        span(&values.view(), values.offset(), n, a.size(), buffers)
            .map_err(|e| format!("sparse values: {e}"))?;
    }
    Ok(())
}

/// Checks that `count` elements of `size` bytes from `offset` in `view`, at its stride, lie
/// inside the view, and the view inside its buffer.
fn span(
    view: &gltf::buffer::View,
    offset: usize,
    count: usize,
    size: usize,
    buffers: &[gltf::buffer::Data],
) -> Result<(), String> {
    let stride = view.stride().unwrap_or(size);
    if stride < size {
        return Err(format!(
            "is read through bufferView {} with byteStride {stride}, shorter than its {size}-byte elements",
            view.index()
        ));
    }
    let end = (count - 1)
        .checked_mul(stride)
        .and_then(|x| x.checked_add(size))
        .and_then(|x| x.checked_add(offset));
    let view_end = view.offset().checked_add(view.length());
    let buffer = buffers.get(view.buffer().index()).map_or(0, |d| d.len());
    match (end, view_end) {
        (Some(end), Some(view_end)) if end <= view.length() && view_end <= buffer => Ok(()),
        _ => Err(format!(
            "reaches past the end of bufferView {} or of its buffer",
            view.index()
        )),
    }
}

/// Key times must be finite and strictly increasing, as glTF 2.0 requires. Out-of-order times
/// are refused rather than sorted: they come from a damaged or wrongly assembled file, and
/// sorting would pair values with times in an order no tool wrote.
fn check_times(times: &[f32]) -> Result<(), String> {
    if let Some(k) = times.iter().position(|t| !t.is_finite()) {
        return Err(format!("key time {k} is not finite"));
    }
    match times.windows(2).position(|w| w[1] <= w[0]) {
        Some(k) => Err(format!(
            "key time {} ({} s) does not come after key time {k} ({} s): key times must increase",
            k + 1,
            times[k + 1],
            times[k]
        )),
        None => Ok(()),
    }
}

/// A +Y-up motion (as [`crate::from_rig`] makes) as a `.glb` animation (module docs).
pub fn write_gltf(motion: &Motion) -> Vec<u8> {
    let joints = motion.skeleton.joints();
    let rest = motion.skeleton.rest(None);
    let mut buffer = GlbBuffer::default();
    let (nodes, roots) = f3g_rig::glb::skinned_nodes(
        &motion.skeleton,
        |j| {
            json!({
                "translation": (joints[j].offset * motion.metres_per_unit).to_array(),
                "rotation": joints[j].pre_rotation.to_array(),
            })
        },
        "skeleton",
    );
    // No mesh: drop the mesh node skinned_nodes adds.
    let mesh_node = nodes.len() - 1;
    let nodes: Vec<_> = nodes.into_iter().take(mesh_node).collect();
    let roots: Vec<usize> = roots.into_iter().filter(|&r| r != mesh_node).collect();
    let inverse_bind: Vec<f32> = rest
        .iter()
        .flat_map(|w| {
            let m =
                Mat4::from_rotation_translation(w.rotation, w.translation * motion.metres_per_unit);
            m.inverse().to_cols_array()
        })
        .collect();
    let inverse_bind = buffer.accessor(&inverse_bind, "MAT4", false, None);
    let frames = motion.frames();
    let times: Vec<f32> = (0..frames).map(|f| f as f32 / motion.fps).collect();
    let input = buffer.accessor(&times, "SCALAR", true, None);
    let mut samplers = Vec::new();
    let mut channels = Vec::new();
    for (j, joint) in joints.iter().enumerate() {
        let values: Vec<f32> = (0..frames)
            .flat_map(|f| {
                (joint.pre_rotation * motion.frame(f)[j])
                    .normalize()
                    .to_array()
            })
            .collect();
        let output = buffer.accessor(&values, "VEC4", false, None);
        channels.push(
            json!({ "sampler": samplers.len(), "target": { "node": j, "path": "rotation" } }),
        );
        samplers.push(json!({ "input": input, "output": output, "interpolation": "LINEAR" }));
    }
    let root: Vec<f32> = (0..frames)
        .flat_map(|f| {
            ((joints[0].offset + motion.root_translation[f]) * motion.metres_per_unit).to_array()
        })
        .collect();
    let output = buffer.accessor(&root, "VEC3", false, None);
    channels
        .push(json!({ "sampler": samplers.len(), "target": { "node": 0, "path": "translation" } }));
    samplers.push(json!({ "input": input, "output": output, "interpolation": "LINEAR" }));
    let document = json!({
        "asset": { "version": "2.0", "generator": "f3g-avatar" },
        "scene": 0,
        "scenes": [{ "nodes": roots }],
        "nodes": nodes,
        "skins": [{ "joints": (0..joints.len()).collect::<Vec<_>>(), "inverseBindMatrices": inverse_bind }],
        "animations": [{ "name": "motion", "samplers": samplers, "channels": channels }],
    });
    buffer.finish(document)
}
