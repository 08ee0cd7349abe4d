//! FBX animation stacks (`.fbx`, binary or ASCII: Mixamo, Blender, MotionBuilder), read with
//! ufbx.
//!
//! The skeleton is every bone node (LimbNode/Root), parents first; rest frames are the bind
//! pose's where the file has one for the bone (a skinned character's rest: a bone's own
//! transform is whatever pose the exporter stood at — Blender writes its current frame's),
//! else the nodes' transforms as the file stores them (pre- and post-rotations folded in by
//! ufbx), the root's including its non-bone ancestors' (an `Armature` node). The first animation stack
//! drives it, evaluated at the file's frame rate (`frames_per_second`, 30 when unset) from the
//! stack's start to its end. Units and up axis are the file's (`UnitScaleFactor`, `UpAxis`);
//! only uniform scales are read. Every key of a bone's rotation and translation curves must be
//! finite and plausible ([`crate::MAX_ANGLE_DEGREES`], [`crate::MAX_TRANSLATION_METRES`]).
//!
//! Writing: an ASCII FBX 7.4 file, Y up, the motion's unit: a bone per joint (`Model` with a
//! `LimbNode` attribute, its rest transform as `Lcl Translation`/`Lcl Rotation`) and one
//! animation stack with a rotation curve node per joint (Euler `XYZ`, degrees) and a
//! translation curve node on the root, a key per frame.

use std::path::Path;

use glam::{Affine3A, Mat3, Quat, Vec3};

use f3g_rig::{Joint, Skeleton};

use crate::{
    MAX_ANGLE_DEGREES, MAX_FRAMES, MAX_JOINTS, MAX_TRANSLATION_METRES, Motion, MotionError, Up,
};

fn vec3(v: ufbx::Vec3) -> Vec3 {
    Vec3::new(v.x as f32, v.y as f32, v.z as f32)
}

fn quat(q: ufbx::Quat) -> Quat {
    Quat::from_xyzw(q.x as f32, q.y as f32, q.z as f32, q.w as f32).normalize()
}

fn affine(m: &ufbx::Matrix) -> Affine3A {
    Affine3A::from_mat3_translation(
        Mat3::from_cols(
            Vec3::new(m.m00 as f32, m.m10 as f32, m.m20 as f32),
            Vec3::new(m.m01 as f32, m.m11 as f32, m.m21 as f32),
            Vec3::new(m.m02 as f32, m.m12 as f32, m.m22 as f32),
        ),
        Vec3::new(m.m03 as f32, m.m13 as f32, m.m23 as f32),
    )
}

/// Reads the first animation stack of an FBX file's bytes (module docs).
pub fn parse_fbx(bytes: &[u8], path: &Path) -> Result<Motion, MotionError> {
    let scene = ufbx::load_memory(bytes, ufbx::LoadOpts::default()).map_err(|e| {
        MotionError::file(path, format!("not a readable FBX file: {}", e.description))
    })?;
    let bones: Vec<&ufbx::Node> = scene
        .nodes
        .iter()
        .filter(|n| n.bone.is_some())
        .map(|n| &**n)
        .collect();
    if bones.is_empty() {
        return Err(MotionError::file(path, "no skeleton (no bone nodes)"));
    }
    if bones.len() > MAX_JOINTS {
        return Err(MotionError::file(
            path,
            format!("{} bones: more than f3g reads ({MAX_JOINTS})", bones.len()),
        ));
    }
    let index = |node: &ufbx::Node| {
        bones
            .iter()
            .position(|b| b.element.element_id == node.element.element_id)
    };
    let uniform = |s: Vec3, what: &str| -> Result<f32, MotionError> {
        if (s - Vec3::splat(s.x)).abs().max_element() > 1e-4 * s.x.abs().max(1.0) || s.x <= 0.0 {
            return Err(MotionError::file(
                path,
                format!("{what} has scale {s}: only uniform positive scales are read"),
            ));
        }
        Ok(s.x)
    };
    // The root's non-bone ancestors: their transform places it, their scale every offset.
    let root = bones[0];
    let ancestors = match root.parent.as_ref() {
        Some(p) => affine(&p.node_to_world),
        None => Affine3A::IDENTITY,
    };
    let (scale, ancestors_rotation, _) = ancestors.to_scale_rotation_translation();
    let scale = uniform(
        scale,
        &format!("the parent of the root bone `{}`", root.element.name),
    )?;
    // The rest: a skinned character's bind pose where the file has one for the bone, since a
    // bone's own transform is whatever pose the exporter stood at (Blender writes the current
    // frame's); else the bone's own transform.
    let bind = |b: &ufbx::Node| {
        scene
            .poses
            .iter()
            .filter(|p| p.is_bind_pose)
            .flat_map(|p| p.bone_poses.iter())
            .find(|bp| bp.bone_node.element.element_id == b.element.element_id)
            .map(|bp| (affine(&bp.bone_to_parent), affine(&bp.bone_to_world)))
    };
    let mut joints = Vec::with_capacity(bones.len());
    for b in &bones {
        let name = b.element.name.to_string();
        let t = &b.local_transform;
        uniform(vec3(t.scale), &format!("bone `{name}`"))?;
        let parent = b.parent.as_ref().and_then(|p| index(p));
        if parent.is_none() && !joints.is_empty() {
            return Err(MotionError::file(
                path,
                format!("bone `{name}` is a second root: f3g reads one skeleton"),
            ));
        }
        let (offset, pre_rotation) = match (parent, bind(b)) {
            (Some(_), Some((local, _))) => {
                let (_, rotation, translation) = local.to_scale_rotation_translation();
                (translation * scale, rotation)
            }
            (None, Some((_, world))) => {
                let (_, rotation, translation) = world.to_scale_rotation_translation();
                (translation, rotation)
            }
            (Some(_), None) => (vec3(t.translation) * scale, quat(t.rotation)),
            (None, None) => (
                ancestors.transform_point3(vec3(t.translation)),
                ancestors_rotation * quat(t.rotation),
            ),
        };
        joints.push(Joint {
            name,
            parent,
            offset,
            pre_rotation: pre_rotation.normalize(),
        });
    }
    let skeleton = Skeleton::new(joints).map_err(|e| MotionError::file(path, e))?;

    let stack = scene
        .anim_stacks
        .iter()
        .next()
        .ok_or_else(|| MotionError::file(path, "holds no animation stack"))?;
    let unit = scene.settings.unit_meters as f32;
    let metres_per_unit = if unit.is_finite() && unit > 0.0 {
        unit
    } else {
        0.01
    };
    check_keys(stack, &bones, metres_per_unit, path)?;
    let fps = match scene.settings.frames_per_second {
        f if f.is_finite() && f > 0.0 && f <= 10_000.0 => f,
        _ => 30.0,
    };
    let duration = stack.time_end - stack.time_begin;
    let frames = (duration * fps).round() + 1.0;
    if !(duration.is_finite() && duration >= 0.0 && frames <= MAX_FRAMES as f64) {
        return Err(MotionError::file(
            path,
            format!("the animation stack lasts {duration} s: more frames than f3g reads"),
        ));
    }
    let frames = frames as usize;
    crate::ensure_memory(frames, bones.len(), path)?;
    let rest = skeleton.joints();
    let mut rotations = Vec::with_capacity(frames * bones.len());
    let mut root_translation = Vec::with_capacity(frames);
    for f in 0..frames {
        let time = stack.time_begin + f as f64 / fps;
        for (j, b) in bones.iter().enumerate() {
            let t = ufbx::evaluate_transform(&stack.anim, b, time);
            let local = match j {
                0 => ancestors_rotation * quat(t.rotation),
                _ => quat(t.rotation),
            };
            rotations.push((rest[j].pre_rotation.conjugate() * local).normalize());
            if j == 0 {
                root_translation
                    .push(ancestors.transform_point3(vec3(t.translation)) - rest[0].offset);
            }
        }
    }
    let up = match scene.settings.axes.up {
        ufbx::CoordinateAxis::PositiveZ => Up::Z,
        _ => Up::Y,
    };
    let motion = Motion {
        skeleton,
        rotations,
        root_translation,
        fps: fps as f32,
        metres_per_unit,
        up,
        smpl: None,
    };
    crate::check_values(&motion, path)?;
    Ok(motion)
}

/// Refuses a bone's rotation key (degrees) beyond [`MAX_ANGLE_DEGREES`] or translation key
/// beyond [`MAX_TRANSLATION_METRES`], or one that is not finite, before any is evaluated: ufbx
/// turns any finite angle into a rotation, and keys between or outside the frames are never
/// sampled.
fn check_keys(
    stack: &ufbx::AnimStack,
    bones: &[&ufbx::Node],
    metres_per_unit: f32,
    path: &Path,
) -> Result<(), MotionError> {
    for layer in stack.layers.iter() {
        for prop in layer.anim_props.iter() {
            let Some(bone) = bones
                .iter()
                .find(|b| b.element.element_id == prop.element.element_id)
            else {
                continue;
            };
            let (limit, unit) = match prop.prop_name.as_ref() {
                "Lcl Rotation" => (f64::from(MAX_ANGLE_DEGREES), "°"),
                "Lcl Translation" => (
                    f64::from(MAX_TRANSLATION_METRES / metres_per_unit),
                    " file units (1 km)",
                ),
                _ => continue,
            };
            for (axis, curve) in ["X", "Y", "Z"].iter().zip(&prop.anim_value.curves) {
                let Some(curve) = curve else { continue };
                if let Some((k, key)) = curve
                    .keyframes
                    .iter()
                    .enumerate()
                    .find(|(_, key)| !key.value.is_finite() || key.value.abs() > limit)
                {
                    return Err(MotionError::file(
                        path,
                        format!(
                            "bone `{}`: `{}` {axis} key {k} is {}: expected a finite value within ±{limit}{unit}",
                            bone.element.name, prop.prop_name, key.value
                        ),
                    ));
                }
            }
        }
    }
    Ok(())
}

/// FBX's time unit: ticks per second.
const KTIME: i64 = 46_186_158_000;

/// A +Y-up motion as an ASCII FBX 7.4 file (module docs).
pub fn write_fbx(motion: &Motion) -> Result<String, String> {
    use std::fmt::Write as _;
    let joints = motion.skeleton.joints();
    if let Some(j) = joints.iter().find(|j| j.name.contains(['"', '\n', '\r'])) {
        return Err(format!("joint name `{}` cannot be written to FBX", j.name));
    }
    if joints.iter().skip(1).any(|j| j.parent.is_none()) {
        return Err("FBX export takes one skeleton; this one has several roots".into());
    }
    let frames = motion.frames();
    let times: Vec<String> = (0..frames)
        .map(|f| ((f as f64 / motion.fps as f64) * KTIME as f64).round() as i64)
        .map(|t| t.to_string())
        .collect();
    let mut objects = String::new();
    let mut connections = String::new();
    let mut id = 100_000i64;
    let mut next = || {
        id += 1;
        id
    };
    let stack = next();
    let layer = next();
    let _ = writeln!(
        objects,
        "\tAnimationStack: {stack}, \"AnimStack::Take 001\", \"\" {{\n\t\tProperties70:  {{\n\t\t\tP: \"LocalStart\", \"KTime\", \"Time\", \"\",0\n\t\t\tP: \"LocalStop\", \"KTime\", \"Time\", \"\",{stop}\n\t\t\tP: \"ReferenceStart\", \"KTime\", \"Time\", \"\",0\n\t\t\tP: \"ReferenceStop\", \"KTime\", \"Time\", \"\",{stop}\n\t\t}}\n\t}}\n\tAnimationLayer: {layer}, \"AnimLayer::BaseLayer\", \"\" {{\n\t}}",
        stop = (((frames - 1) as f64 / motion.fps as f64) * KTIME as f64).round() as i64
    );
    let _ = writeln!(connections, "\tC: \"OO\",{layer},{stack}");
    let mut model_ids = Vec::new();
    for (j, joint) in joints.iter().enumerate() {
        let model = next();
        let attribute = next();
        model_ids.push(model);
        let o = joint.offset;
        let [rx, ry, rz] = degrees_xyz(joint.pre_rotation);
        let _ = writeln!(
            objects,
            "\tNodeAttribute: {attribute}, \"NodeAttribute::\", \"LimbNode\" {{\n\t\tTypeFlags: \"Skeleton\"\n\t}}\n\tModel: {model}, \"Model::{}\", \"LimbNode\" {{\n\t\tVersion: 232\n\t\tProperties70:  {{\n\t\t\tP: \"Lcl Translation\", \"Lcl Translation\", \"\", \"A\",{},{},{}\n\t\t\tP: \"Lcl Rotation\", \"Lcl Rotation\", \"\", \"A\",{rx},{ry},{rz}\n\t\t}}\n\t}}",
            joint.name, o.x, o.y, o.z
        );
        let parent = joint.parent.map_or(0, |p| model_ids[p]);
        let _ = writeln!(
            connections,
            "\tC: \"OO\",{attribute},{model}\n\tC: \"OO\",{model},{parent}"
        );
        // Curves: rotation (all joints), translation (the root).
        let mut channels: Vec<(&str, [Vec<f64>; 3])> = Vec::new();
        let euler: Vec<[f64; 3]> = (0..frames)
            .map(|f| degrees_xyz(joint.pre_rotation * motion.frame(f)[j]))
            .collect();
        channels.push((
            "R",
            std::array::from_fn(|k| euler.iter().map(|e| e[k]).collect()),
        ));
        if joint.parent.is_none() {
            let t: Vec<Vec3> = (0..frames)
                .map(|f| o + motion.root_translation[f])
                .collect();
            channels.push((
                "T",
                std::array::from_fn(|k| t.iter().map(|v| f64::from(v[k])).collect()),
            ));
        }
        for (kind, values) in channels {
            let node = next();
            let property = if kind == "R" {
                "Lcl Rotation"
            } else {
                "Lcl Translation"
            };
            let _ = writeln!(
                objects,
                "\tAnimationCurveNode: {node}, \"AnimCurveNode::{kind}\", \"\" {{\n\t\tProperties70:  {{\n\t\t\tP: \"d|X\", \"Number\", \"\", \"A\",0\n\t\t\tP: \"d|Y\", \"Number\", \"\", \"A\",0\n\t\t\tP: \"d|Z\", \"Number\", \"\", \"A\",0\n\t\t}}\n\t}}"
            );
            let _ = writeln!(
                connections,
                "\tC: \"OO\",{node},{layer}\n\tC: \"OP\",{node},{model}, \"{property}\""
            );
            for (axis, v) in ["d|X", "d|Y", "d|Z"].iter().zip(values) {
                let curve = next();
                let keys: Vec<String> = v.iter().map(|x| format!("{x}")).collect();
                let _ = writeln!(
                    objects,
                    "\tAnimationCurve: {curve}, \"AnimCurve::\", \"\" {{\n\t\tDefault: 0\n\t\tKeyVer: 4009\n\t\tKeyTime: *{frames} {{\n\t\t\ta: {}\n\t\t}}\n\t\tKeyValueFloat: *{frames} {{\n\t\t\ta: {}\n\t\t}}\n\t\tKeyAttrFlags: *1 {{\n\t\t\ta: 24836\n\t\t}}\n\t\tKeyAttrDataFloat: *4 {{\n\t\t\ta: 0,0,0,0\n\t\t}}\n\t\tKeyAttrRefCount: *1 {{\n\t\t\ta: {frames}\n\t\t}}\n\t}}",
                    times.join(","),
                    keys.join(",")
                );
                let _ = writeln!(connections, "\tC: \"OP\",{curve},{node}, \"{axis}\"");
            }
        }
    }
    // FBX's unit is centimetres times UnitScaleFactor.
    let unit = 100.0 * motion.metres_per_unit;
    let fps = motion.fps;
    Ok(format!(
        "; FBX 7.4.0 project file\nFBXHeaderExtension:  {{\n\tFBXHeaderVersion: 1003\n\tFBXVersion: 7400\n}}\nGlobalSettings:  {{\n\tVersion: 1000\n\tProperties70:  {{\n\t\tP: \"UpAxis\", \"int\", \"Integer\", \"\",1\n\t\tP: \"UpAxisSign\", \"int\", \"Integer\", \"\",1\n\t\tP: \"FrontAxis\", \"int\", \"Integer\", \"\",2\n\t\tP: \"FrontAxisSign\", \"int\", \"Integer\", \"\",1\n\t\tP: \"CoordAxis\", \"int\", \"Integer\", \"\",0\n\t\tP: \"CoordAxisSign\", \"int\", \"Integer\", \"\",1\n\t\tP: \"UnitScaleFactor\", \"double\", \"Number\", \"\",{unit}\n\t\tP: \"TimeMode\", \"enum\", \"\", \"\",14\n\t\tP: \"CustomFrameRate\", \"double\", \"Number\", \"\",{fps}\n\t}}\n}}\nObjects:  {{\n{objects}}}\nConnections:  {{\n{connections}}}\n"
    ))
}

/// Euler angles (degrees) with `R = Rz·Ry·Rx` in FBX's default `XYZ` key order.
fn degrees_xyz(q: Quat) -> [f64; 3] {
    let (z, y, x) = crate::euler_zyx_degrees(q);
    [x, y, z]
}
