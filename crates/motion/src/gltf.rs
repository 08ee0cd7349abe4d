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
//! Writing: the skeleton as nodes under one skin (inverse bind matrices of the rest pose, no
//! mesh), one animation with a rotation channel per joint and a translation channel for the
//! root, linear, at the motion's frame times.

use std::path::Path;

use glam::{Mat4, Quat, Vec3};
use serde_json::json;

use f3g_rig::glb::GlbBuffer;

use crate::{MAX_FRAMES, Motion, MotionError, Up};

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
    let n = joints.skeleton.len();
    let mut rotations: Vec<Option<Track<Quat>>> = (0..n).map(|_| None).collect();
    let mut root: Option<Track<Vec3>> = None;
    let data = |b: gltf::Buffer| buffers.get(b.index()).map(|d| &d.0[..]);
    for channel in anim.channels() {
        let node = channel.target().node().index();
        let Some(j) = joints.nodes.iter().position(|&x| x == node) else {
            continue;
        };
        let sampler = channel.sampler();
        for a in [sampler.input(), sampler.output()] {
            if a.count() > MAX_FRAMES * 3 {
                return Err(MotionError::file(
                    path,
                    format!(
                        "accessor {} has {} keys, more than f3g reads",
                        a.index(),
                        a.count()
                    ),
                ));
            }
        }
        let reader = channel.reader(data);
        let times: Vec<f32> = reader
            .read_inputs()
            .ok_or_else(|| MotionError::file(path, "an animation channel without key times"))?
            .collect();
        let interpolation = sampler.interpolation();
        // Cubic splines store (in-tangent, value, out-tangent) per key.
        let keep =
            |k: usize| interpolation != gltf::animation::Interpolation::CubicSpline || k % 3 == 1;
        let step = interpolation == gltf::animation::Interpolation::Step;
        use gltf::animation::util::ReadOutputs;
        match reader.read_outputs() {
            Some(ReadOutputs::Rotations(r)) => {
                let values: Vec<Quat> = r
                    .into_f32()
                    .enumerate()
                    .filter(|(k, _)| keep(*k))
                    .map(|(_, q)| Quat::from_array(q))
                    .collect();
                rotations[j] = Some(Track {
                    times,
                    values,
                    step,
                });
            }
            Some(ReadOutputs::Translations(t)) if joints.skeleton.joints()[j].parent.is_none() => {
                let values: Vec<Vec3> = t
                    .enumerate()
                    .filter(|(k, _)| keep(*k))
                    .map(|(_, v)| Vec3::from_array(v))
                    .collect();
                root = Some(Track {
                    times,
                    values,
                    step,
                });
            }
            _ => {}
        }
    }
    let tracks: Vec<&[f32]> = rotations
        .iter()
        .flatten()
        .map(|t| t.times.as_slice())
        .chain(root.iter().map(|t| t.times.as_slice()))
        .collect();
    for (k, t) in rotations
        .iter()
        .flatten()
        .map(|t| (t.times.len(), t.values.len()))
        .chain(root.iter().map(|t| (t.times.len(), t.values.len())))
        .enumerate()
    {
        if t.0 != t.1 || t.0 == 0 {
            return Err(MotionError::file(
                path,
                format!(
                    "animation channel {k} has {} key times for {} values",
                    t.0, t.1
                ),
            ));
        }
    }
    if tracks.is_empty() {
        return Err(MotionError::file(
            path,
            "the animation moves none of the skin's joints",
        ));
    }
    let all = tracks.iter().flat_map(|t| t.iter().copied());
    if all.clone().any(|t| !t.is_finite()) {
        return Err(MotionError::file(
            path,
            "an animation key time is not finite",
        ));
    }
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
    crate::check_finite(&motion, path)?;
    Ok(motion)
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
