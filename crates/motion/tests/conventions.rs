//! Skeletons of other tools, as their BVH files lay them out (rest layout, naming, helper
//! bones, units, up axis), get their joint roles without a `--joint-map`, and drive the
//! built-in human the way they move: Blender's Rigify (metarig names, the generated rig's
//! `DEF-` deform bones with their twist segments, and the plain `neck`/`head` variant),
//! Mixamo, Unreal's mannequin, CMU's ASF names, 3ds Max's Biped (Truebones' packs: names with
//! spaces, legs from the spine, arms from the neck), MotionBuilder's HumanIK (a `Reference`
//! root, roll leaves), LAFAN1's rest along +X, and skeletons whose names say nothing.
//!
//! Each layout is written here from the tool's conventions (the fixtures' provenance): Rigify's
//! from the human metarig's bone heads (Blender, Z up, facing −Y, metres), Mixamo's T-pose in
//! centimetres (Y up, facing +Z), Unreal's mannequin (Z up, facing +Y, centimetres, bones
//! `root` → `pelvis` …), CMU's ASF skeleton (Y up, facing +Z, centimetres). Face, finger and
//! foot-helper bones are placed roughly: they take no role, but they are where the old
//! inference went wrong (a face bone as the head) or must not be picked.

use std::fmt::Write as _;
use std::path::Path;

use f3g_motion::retarget::{RolesFrom, complete_by_topology};
use f3g_motion::{Motion, RestChoice, RetargetOptions, read, retarget};
use f3g_rig::{Rig, Role, Roles};
use glam::{EulerRot, Quat, Vec3};

fn builtin() -> Rig {
    f3g_rig::builtin::load().unwrap().rig
}

/// A bone of a layout: name, parent name, head position in the file's axes and units.
type Bone = (String, Option<String>, Vec3);

fn bone(name: &str, parent: &str, head: [f32; 3]) -> Bone {
    (
        name.to_string(),
        (!parent.is_empty()).then(|| parent.to_string()),
        Vec3::from_array(head),
    )
}

/// `bones` followed by their mirror images: every bone whose name holds the left marker `l`
/// again, across x = 0, named with the right marker `r`.
fn mirrored(bones: Vec<Bone>, l: &str, r: &str) -> Vec<Bone> {
    let mut out = bones.clone();
    for (name, parent, head) in &bones {
        if name.contains(l) {
            out.push((
                name.replace(l, r),
                parent.as_ref().map(|p| p.replace(l, r)),
                Vec3::new(-head.x, head.y, head.z),
            ));
        }
    }
    out
}

/// Orders `bones` depth first from the root, children in the order given (as exporters
/// write them).
fn depth_first(bones: &[Bone]) -> Vec<usize> {
    fn visit(bones: &[Bone], at: usize, out: &mut Vec<usize>) {
        out.push(at);
        for (c, b) in bones.iter().enumerate() {
            if b.1.as_deref() == Some(bones[at].0.as_str()) {
                visit(bones, c, out);
            }
        }
    }
    let mut out = Vec::new();
    let root = bones.iter().position(|b| b.1.is_none()).unwrap();
    visit(bones, root, &mut out);
    assert_eq!(out.len(), bones.len(), "a bone's parent is missing");
    out
}

/// BVH text of `bones` (rest offsets from the heads; each leaf gets an `End Site` along its
/// own offset) with `frames` of world rotations by bone name (BVH frames are
/// world-aligned: a bone's channels hold `parent_world⁻¹ · world`), rotation channels in
/// `order` (e.g. "ZXY": `Zrotation Xrotation Yrotation`).
fn bvh(bones: &[Bone], frames: &[Vec<(String, Quat)>], order: &str) -> String {
    bvh_turned(
        bones,
        frames,
        order,
        &vec![Quat::IDENTITY; bones.len()],
        &[],
    )
}

/// [`bvh`] with each bone's rest frame turned by `turned[bone]` against the world: its
/// children's offsets are written in the turned frame and its rotations carry the turn, so
/// the frames pose the same positions while the file's rest (every rotation zero) lies as the
/// turns make it (LAFAN1: every bone along +X). `moved[f]`, where given, moves the root from
/// its rest position in frame `f`.
fn bvh_turned(
    bones: &[Bone],
    frames: &[Vec<(String, Quat)>],
    order: &str,
    turned: &[Quat],
    moved: &[Vec3],
) -> String {
    let order_rot = match order {
        "ZXY" => EulerRot::ZXY,
        "XYZ" => EulerRot::XYZ,
        "ZYX" => EulerRot::ZYX,
        "YXZ" => EulerRot::YXZ,
        _ => unreachable!(),
    };
    let channels: Vec<String> = order.chars().map(|c| format!("{c}rotation")).collect();
    let channels = channels.join(" ");
    let seq = depth_first(bones);
    let index = |name: &str| bones.iter().position(|b| b.0 == name).unwrap();
    let mut out = String::from("HIERARCHY\n");
    // Written recursively for the braces.
    fn write(
        bones: &[Bone],
        turned: &[Quat],
        at: usize,
        depth: usize,
        channels: &str,
        out: &mut String,
    ) {
        let pad = "  ".repeat(depth);
        let (name, parent, head) = &bones[at];
        let offset = match parent {
            Some(p) => {
                let p = bones.iter().position(|b| &b.0 == p).unwrap();
                turned[p].inverse() * (*head - bones[p].2)
            }
            None => *head,
        };
        let kind = if parent.is_some() { "JOINT" } else { "ROOT" };
        let _ = writeln!(out, "{pad}{kind} {name}\n{pad}{{");
        let _ = writeln!(out, "{pad}  OFFSET {} {} {}", offset.x, offset.y, offset.z);
        if parent.is_some() {
            let _ = writeln!(out, "{pad}  CHANNELS 3 {channels}");
        } else {
            let _ = writeln!(
                out,
                "{pad}  CHANNELS 6 Xposition Yposition Zposition {channels}"
            );
        }
        let children: Vec<usize> = (0..bones.len())
            .filter(|&c| bones[c].1.as_deref() == Some(name.as_str()))
            .collect();
        for &c in &children {
            write(bones, turned, c, depth + 1, channels, out);
        }
        if children.is_empty() {
            let tip = offset.normalize_or_zero() * 0.3 * offset.length();
            let _ = writeln!(
                out,
                "{pad}  End Site\n{pad}  {{\n{pad}    OFFSET {} {} {}\n{pad}  }}",
                tip.x, tip.y, tip.z
            );
        }
        let _ = writeln!(out, "{pad}}}");
    }
    write(bones, turned, seq[0], 0, &channels, &mut out);
    let _ = writeln!(
        out,
        "MOTION\nFrames: {}\nFrame Time: 0.033333",
        frames.len()
    );
    for (f, frame) in frames.iter().enumerate() {
        let world = |j: usize| {
            frame
                .iter()
                .find(|(n, _)| *n == bones[j].0)
                .map(|(_, q)| *q)
        };
        // A bone without its own world rotation turns with its parent.
        let mut worlds = vec![Quat::IDENTITY; bones.len()];
        for &j in &seq {
            let parent = bones[j].1.as_deref().map(index);
            let inherited = parent.map_or(Quat::IDENTITY, |p| worlds[p]);
            worlds[j] = world(j).unwrap_or(inherited);
        }
        let mut values = Vec::new();
        for &j in &seq {
            let parent = bones[j].1.as_deref().map(index);
            if parent.is_none() {
                // Position channels are absolute.
                let at = bones[j].2 + moved.get(f).copied().unwrap_or_default();
                values.extend(at.to_array().map(|v| v.to_string()));
            }
            let world = |j: usize| worlds[j] * turned[j];
            let local = parent.map_or(Quat::IDENTITY, world).inverse() * world(j);
            let (a, b, c) = local.as_dquat().to_euler(order_rot);
            values.extend([a, b, c].map(|v| format!("{:.6}", v.to_degrees())));
        }
        let _ = writeln!(out, "{}", values.join(" "));
    }
    out
}

/// Blender's Rigify human metarig: bone heads (Z up, facing −Y, metres; the torso, limbs and
/// feet as the metarig places them, a few face and finger bones roughly), parents before
/// children.
fn rigify_metarig() -> Vec<Bone> {
    let left = vec![
        bone("spine", "", [0.0, 0.0552, 1.0099]),
        bone("spine.001", "spine", [0.0, 0.0172, 1.1573]),
        bone("pelvis.L", "spine", [0.0, 0.0552, 1.0099]),
        bone("thigh.L", "spine", [0.0980, 0.0124, 1.0720]),
        bone("spine.002", "spine.001", [0.0, 0.0004, 1.2929]),
        bone("shin.L", "thigh.L", [0.0980, -0.0286, 0.5372]),
        bone("spine.003", "spine.002", [0.0, 0.0059, 1.4657]),
        bone("foot.L", "shin.L", [0.0980, 0.0162, 0.0852]),
        bone("spine.004", "spine.003", [0.0, 0.0114, 1.6582]),
        bone("shoulder.L", "spine.003", [0.0183, -0.0684, 1.6051]),
        bone("breast.L", "spine.003", [0.1184, 0.0485, 1.4596]),
        bone("toe.L", "foot.L", [0.0985, -0.0950, 0.0198]),
        bone("heel.02.L", "foot.L", [0.0600, 0.0459, 0.0]),
        bone("spine.005", "spine.004", [0.0, -0.0067, 1.7197]),
        bone("upper_arm.L", "shoulder.L", [0.1953, 0.0267, 1.5846]),
        bone("spine.006", "spine.005", [0.0, -0.0247, 1.7813]),
        bone("forearm.L", "upper_arm.L", [0.4424, 0.0676, 1.3329]),
        bone("face", "spine.006", [0.0, -0.0247, 1.7813]),
        bone("hand.L", "forearm.L", [0.6594, 0.0442, 1.1388]),
        bone("jaw", "face", [0.0, 0.0, 1.75]),
        bone("eye.L", "face", [0.03, -0.09, 1.83]),
        bone("ear.L", "face", [0.07, 0.0, 1.82]),
        bone("palm.01.L", "hand.L", [0.6734, 0.0330, 1.1215]),
        bone("thumb.01.L", "palm.01.L", [0.6700, 0.0100, 1.1100]),
        bone("f_index.01.L", "palm.01.L", [0.7234, 0.0068, 1.0648]),
        bone("f_index.02.L", "f_index.01.L", [0.7500, 0.0000, 1.0350]),
        bone("palm.02.L", "hand.L", [0.6734, 0.0440, 1.1215]),
        bone("f_middle.01.L", "palm.02.L", [0.7300, 0.0300, 1.0600]),
    ];
    // The metarig interleaves the sides (`thigh.L`, `thigh.R`, …); here the right side
    // follows the left. Either way `pelvis.L` comes before `thigh.L` under `spine`, as
    // Blender's exporter writes it.
    mirrored(left, ".L", ".R")
}

/// The generated rig's deform bones (`DEF-…`): the metarig's bones with the limbs split into
/// twist segments (`DEF-upper_arm.L.001` …), as a BVH export of a Rigify rig's deform layer
/// holds them.
fn rigify_deform() -> Vec<Bone> {
    let metarig = rigify_metarig();
    let head = |n: &str| metarig.iter().find(|b| b.0 == n).unwrap().2;
    let mut out: Vec<Bone> = Vec::new();
    for (name, parent, at) in &metarig {
        let no_deform = ["heel", "face", "ear", "eye"];
        if no_deform.iter().any(|n| name.starts_with(n)) {
            continue;
        }
        let parent = parent.as_ref().map(|p| {
            let p = if p == "face" { "spine.006" } else { p };
            // The second segment of a split parent carries the child.
            let split = ["upper_arm", "forearm", "thigh", "shin"]
                .iter()
                .any(|s| p.starts_with(s));
            if split {
                format!("DEF-{p}.001")
            } else {
                format!("DEF-{p}")
            }
        });
        out.push((format!("DEF-{name}"), parent, *at));
        for (split, next) in [
            ("upper_arm", "forearm"),
            ("forearm", "hand"),
            ("thigh", "shin"),
            ("shin", "foot"),
        ] {
            if let Some(side) = name.strip_prefix(split).filter(|s| s.len() == 2) {
                let middle = (*at + head(&format!("{next}{side}"))) / 2.0;
                out.push((
                    format!("DEF-{name}.001"),
                    Some(format!("DEF-{name}")),
                    middle,
                ));
            }
        }
    }
    out
}

/// World rotations (file axes) that make `bone` point along `direction` from its rest
/// direction toward `end`.
fn aim(bones: &[Bone], bone: &str, end: &str, direction: Vec3) -> (String, Quat) {
    let at = |n: &str| bones.iter().find(|b| b.0 == n).unwrap().2;
    let rest = (at(end) - at(bone)).normalize();
    (
        bone.to_string(),
        Quat::from_rotation_arc(rest, direction.normalize()),
    )
}

/// Unit vector of the bone `from` → `to` at frame `f` of `motion`, in +Y-up axes.
fn source_direction(motion: &Motion, f: usize, from: &str, to: &str) -> Vec3 {
    let p = motion.positions(f);
    let j = |n: &str| motion.skeleton.index_of(n).unwrap();
    (p[j(to)] - p[j(from)]).normalize()
}

/// Unit vector of the target's bone `from` → `to` (roles) at frame `f`.
fn target_direction(
    rig: &Rig,
    frames: &[f3g_rig::RigParams],
    f: usize,
    from: Role,
    to: Role,
) -> Vec3 {
    let w = rig.joint_world(&frames[f]).unwrap();
    let j = |r: Role| rig.roles.get(r).unwrap();
    (w[j(to)].translation - w[j(from)].translation).normalize()
}

fn degrees(a: Vec3, b: Vec3) -> f32 {
    a.dot(b).clamp(-1.0, 1.0).acos().to_degrees()
}

/// Roles inferred (and completed from the shape) for `motion`'s skeleton, by joint name.
fn roles_by_name(motion: &Motion) -> Vec<(Role, String)> {
    let s = &motion.skeleton;
    complete_by_topology(s, Roles::infer(s))
        .iter()
        .map(|(r, j)| (r, s.joints()[j].name.clone()))
        .collect()
}

/// Writes a fixture and reads it back; with `F3G_CORPUS_DIR` set, also keeps a copy there
/// (the README's contact sheet of the corpus is drawn from those files: docs/motions.md).
fn write_read(dir: &Path, name: &str, text: &str) -> Motion {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    if let Some(keep) = std::env::var_os("F3G_CORPUS_DIR") {
        std::fs::create_dir_all(&keep).unwrap();
        std::fs::write(Path::new(&keep).join(name), text).unwrap();
    }
    read(&path).unwrap()
}

/// Mixamo's rig (a Y Bot export): Y up, facing +Z, left +X, centimetres, T-pose, with the
/// `mixamorig:` namespace, fingers and the `_End` joints.
fn mixamo() -> Vec<Bone> {
    let left = vec![
        bone("Hips", "", [0.0, 104.0, 1.0]),
        bone("Spine", "Hips", [0.0, 114.0, 0.0]),
        bone("Spine1", "Spine", [0.0, 126.0, -1.0]),
        bone("Spine2", "Spine1", [0.0, 139.0, -1.5]),
        bone("Neck", "Spine2", [0.0, 155.0, -1.0]),
        bone("Head", "Neck", [0.0, 165.0, 1.0]),
        bone("HeadTop_End", "Head", [0.0, 184.0, 3.0]),
        bone("LeftShoulder", "Spine2", [6.0, 148.0, -1.0]),
        bone("LeftArm", "LeftShoulder", [18.0, 147.0, -2.0]),
        bone("LeftForeArm", "LeftArm", [45.0, 147.0, -3.0]),
        bone("LeftHand", "LeftForeArm", [71.0, 147.0, -2.0]),
        bone("LeftHandThumb1", "LeftHand", [74.0, 145.0, 2.0]),
        bone("LeftHandThumb2", "LeftHandThumb1", [76.0, 144.0, 5.0]),
        bone("LeftHandIndex1", "LeftHand", [80.0, 147.0, 1.0]),
        bone("LeftHandIndex2", "LeftHandIndex1", [84.0, 147.0, 1.0]),
        bone("LeftHandMiddle1", "LeftHand", [81.0, 147.0, -1.0]),
        bone("LeftUpLeg", "Hips", [9.0, 97.0, 0.0]),
        bone("LeftLeg", "LeftUpLeg", [9.0, 54.0, 1.0]),
        bone("LeftFoot", "LeftLeg", [9.0, 9.0, -3.0]),
        bone("LeftToeBase", "LeftFoot", [9.0, 1.0, 10.0]),
        bone("LeftToe_End", "LeftToeBase", [9.0, 1.0, 19.0]),
    ];
    mirrored(left, "Left", "Right")
        .into_iter()
        .map(|(n, p, h)| {
            (
                format!("mixamorig:{n}"),
                p.map(|p| format!("mixamorig:{p}")),
                h,
            )
        })
        .collect()
}

/// Unreal's UE4 mannequin (`SK_Mannequin`): Z up, centimetres, facing +Y (its left side at
/// −X), A-pose, `root` on the floor above `pelvis`, twist bones and the IK bones.
fn unreal() -> Vec<Bone> {
    let arm = |from: [f32; 3], length: f32| -> [f32; 3] {
        // 40° below the horizontal, outward (−X on the left).
        let a = 40f32.to_radians();
        [
            from[0] - length * a.cos(),
            from[1],
            from[2] - length * a.sin(),
        ]
    };
    let shoulder = [-16.0, -2.0, 148.0];
    let elbow = arm(shoulder, 28.0);
    let wrist = arm(elbow, 26.0);
    let hand_end = arm(wrist, 8.0);
    let mid = |a: [f32; 3], b: [f32; 3]| {
        [
            (a[0] + b[0]) / 2.0,
            (a[1] + b[1]) / 2.0,
            (a[2] + b[2]) / 2.0,
        ]
    };
    let (hip, knee, ankle) = ([-9.0, 1.0, 92.0], [-10.0, 0.0, 50.0], [-11.0, -3.0, 8.0]);
    let left = vec![
        bone("root", "", [0.0, 0.0, 0.0]),
        bone("pelvis", "root", [0.0, 1.0, 97.0]),
        bone("spine_01", "pelvis", [0.0, 2.0, 108.0]),
        bone("spine_02", "spine_01", [0.0, 0.0, 126.0]),
        bone("spine_03", "spine_02", [0.0, -2.0, 139.0]),
        bone("clavicle_l", "spine_03", [-4.0, -2.0, 150.0]),
        bone("upperarm_l", "clavicle_l", shoulder),
        bone("upperarm_twist_01_l", "upperarm_l", mid(shoulder, elbow)),
        bone("lowerarm_l", "upperarm_l", elbow),
        bone("lowerarm_twist_01_l", "lowerarm_l", mid(elbow, wrist)),
        bone("hand_l", "lowerarm_l", wrist),
        bone("index_01_l", "hand_l", hand_end),
        bone(
            "thumb_01_l",
            "hand_l",
            [wrist[0] - 2.0, wrist[1] + 3.0, wrist[2] - 1.0],
        ),
        bone("neck_01", "spine_03", [0.0, -1.0, 155.0]),
        bone("head", "neck_01", [0.0, 1.0, 164.0]),
        bone("thigh_l", "pelvis", hip),
        bone("thigh_twist_01_l", "thigh_l", mid(hip, knee)),
        bone("calf_l", "thigh_l", knee),
        bone("calf_twist_01_l", "calf_l", mid(knee, ankle)),
        bone("foot_l", "calf_l", ankle),
        bone("ball_l", "foot_l", [-12.0, 12.0, 2.0]),
        bone("ik_foot_root", "root", [0.0, 0.0, 0.0]),
        bone("ik_foot_l", "ik_foot_root", ankle),
        bone("ik_hand_root", "root", [0.0, 0.0, 0.0]),
        bone(
            "ik_hand_gun",
            "ik_hand_root",
            [-wrist[0], wrist[1], wrist[2]],
        ),
        bone("ik_hand_l", "ik_hand_gun", wrist),
    ];
    mirrored(left, "_l", "_r")
}

/// 3ds Max's Biped as Truebones' BVH packs name it (`Bip01 …`): Z up, facing −Y (the body's
/// left at +X), inches; the legs hang from `Bip01 Spine` (not the pelvis) and the clavicles and
/// head from `Bip01 Neck`, with `Nub` end joints.
fn biped() -> Vec<Bone> {
    // `(" L Thigh", " Spine")` is `Bip01 L Thigh` under `Bip01 Spine`; `None` for the root.
    let b = |name: &str, parent: Option<&str>, at: [f32; 3]| {
        let parent = parent.map_or(String::new(), |p| format!("Bip01{p}"));
        bone(&format!("Bip01{name}"), &parent, at)
    };
    let left = vec![
        b("", None, [0.0, 0.0, 40.0]),
        b(" Pelvis", Some(""), [0.0, 0.0, 40.0]),
        b(" Spine", Some(" Pelvis"), [0.0, 0.3, 42.0]),
        b(" L Thigh", Some(" Spine"), [3.6, 0.0, 37.5]),
        b(" L Calf", Some(" L Thigh"), [3.6, -0.3, 20.5]),
        b(" L Foot", Some(" L Calf"), [3.6, 0.7, 3.3]),
        b(" L Toe0", Some(" L Foot"), [3.6, -3.5, 0.6]),
        b(" L Toe0Nub", Some(" L Toe0"), [3.6, -6.5, 0.6]),
        b(" Spine1", Some(" Spine"), [0.0, 0.4, 47.0]),
        b(" Spine2", Some(" Spine1"), [0.0, 0.5, 52.0]),
        b(" Neck", Some(" Spine2"), [0.0, 0.4, 58.5]),
        b(" Head", Some(" Neck"), [0.0, -0.2, 62.0]),
        b(" HeadNub", Some(" Head"), [0.0, -0.2, 70.0]),
        b(" L Clavicle", Some(" Neck"), [0.8, 0.2, 58.0]),
        b(" L UpperArm", Some(" L Clavicle"), [6.5, 0.6, 57.8]),
        b(" L Forearm", Some(" L UpperArm"), [17.5, 0.9, 57.8]),
        b(" L Hand", Some(" L Forearm"), [27.5, 0.6, 57.8]),
        b(" L Finger0", Some(" L Hand"), [28.3, -1.0, 57.4]),
        b(" L Finger0Nub", Some(" L Finger0"), [29.5, -2.3, 57.2]),
        b(" L Finger1", Some(" L Hand"), [30.5, -0.6, 57.8]),
        b(" L Finger1Nub", Some(" L Finger1"), [33.0, -0.6, 57.8]),
    ];
    mirrored(left, " L ", " R ")
}

/// MotionBuilder's HumanIK character as its BVH exports name it: Y up, facing +Z, left +X,
/// centimetres, T-pose, a `Reference` root on the floor above `Hips`, roll bones as leaves
/// (`LeafLeftUpLegRoll1` …) and `Spine1` to `Spine3`.
fn humanik() -> Vec<Bone> {
    let left = vec![
        bone("Reference", "", [0.0, 0.0, 0.0]),
        bone("Hips", "Reference", [0.0, 100.0, 0.0]),
        bone("LeftUpLeg", "Hips", [9.0, 93.0, 0.0]),
        bone("LeafLeftUpLegRoll1", "LeftUpLeg", [9.0, 72.0, 0.0]),
        bone("LeftLeg", "LeftUpLeg", [9.0, 51.0, 1.0]),
        bone("LeafLeftLegRoll1", "LeftLeg", [9.0, 30.0, 0.0]),
        bone("LeftFoot", "LeftLeg", [9.0, 8.0, -2.0]),
        bone("LeftToeBase", "LeftFoot", [9.0, 1.0, 10.0]),
        bone("Spine", "Hips", [0.0, 110.0, 0.0]),
        bone("Spine1", "Spine", [0.0, 120.0, -1.0]),
        bone("Spine2", "Spine1", [0.0, 130.0, -1.0]),
        bone("Spine3", "Spine2", [0.0, 140.0, -1.0]),
        bone("Neck", "Spine3", [0.0, 153.0, -1.0]),
        bone("Head", "Neck", [0.0, 162.0, 1.0]),
        bone("LeftShoulder", "Spine3", [4.0, 147.0, -1.0]),
        bone("LeftArm", "LeftShoulder", [17.0, 147.0, -2.0]),
        bone("LeafLeftArmRoll1", "LeftArm", [31.0, 147.0, -2.0]),
        bone("LeftForeArm", "LeftArm", [45.0, 147.0, -3.0]),
        bone("LeafLeftForeArmRoll1", "LeftForeArm", [58.0, 147.0, -3.0]),
        bone("LeftHand", "LeftForeArm", [70.0, 147.0, -2.0]),
        bone("LeftHandThumb1", "LeftHand", [73.0, 145.0, 2.0]),
        bone("LeftHandThumb2", "LeftHandThumb1", [75.0, 144.0, 5.0]),
        bone("LeftHandIndex1", "LeftHand", [79.0, 147.0, 1.0]),
        bone("LeftHandIndex2", "LeftHandIndex1", [83.0, 147.0, 1.0]),
    ];
    mirrored(left, "Left", "Right")
}

/// CMU's motion-capture skeleton under its ASF bone names (as `amc2bvh` writes them): Y up,
/// facing +Z, left +X, T-pose; each joint at the start of its ASF bone (`lhipjoint` at the
/// root, `lfemur` at the hip, `lradius` at the elbow, `lwrist` at the wrist).
fn cmu() -> Vec<Bone> {
    let left = vec![
        bone("root", "", [0.0, 100.0, 0.0]),
        bone("lhipjoint", "root", [0.0, 100.0, 0.0]),
        bone("lfemur", "lhipjoint", [9.0, 93.0, 1.0]),
        bone("ltibia", "lfemur", [9.0, 51.0, 0.0]),
        bone("lfoot", "ltibia", [9.0, 8.0, -2.0]),
        bone("ltoes", "lfoot", [9.0, 2.0, 10.0]),
        bone("lowerback", "root", [0.0, 100.0, 0.0]),
        bone("upperback", "lowerback", [0.0, 112.0, -1.0]),
        bone("thorax", "upperback", [0.0, 124.0, -1.0]),
        bone("lowerneck", "thorax", [0.0, 143.0, -1.0]),
        bone("upperneck", "lowerneck", [0.0, 150.0, 0.0]),
        bone("head", "upperneck", [0.0, 157.0, 1.0]),
        bone("lclavicle", "thorax", [0.0, 143.0, -1.0]),
        bone("lhumerus", "lclavicle", [17.0, 145.0, -2.0]),
        bone("lradius", "lhumerus", [45.0, 145.0, -2.0]),
        bone("lwrist", "lradius", [69.0, 145.0, -2.0]),
        bone("lhand", "lwrist", [72.0, 145.0, -2.0]),
        bone("lfingers", "lhand", [78.0, 145.0, -2.0]),
        bone("lthumb", "lhand", [71.0, 145.0, 2.0]),
    ];
    // ASF's sides are one glued letter: `l…` and `r…` (only the sided bones hold `l`
    // first, so the mirror renames by the first letter).
    let mut out = left.clone();
    for (name, parent, head) in &left {
        if let Some(rest) = name.strip_prefix('l') {
            let parent = parent.as_ref().map(|p| match p.strip_prefix('l') {
                Some(r) if p != "lowerback" && p != "lowerneck" => format!("r{r}"),
                _ => p.clone(),
            });
            if name != "lowerback" && name != "lowerneck" {
                out.push((
                    format!("r{rest}"),
                    parent,
                    Vec3::new(-head.x, head.y, head.z),
                ));
            }
        }
    }
    out
}

/// Source joint names and target roles of the bones compared: (from, to) each.
type Compared<'a> = [(&'a str, &'a str, Role, Role)];

/// The largest angle (degrees) between each compared source bone (in the target's axes: its
/// up axis to +Y, turned about +Y so that its rest hips face the target's) and the target's
/// bone, over the frames.
fn worst_angle(motion: &Motion, rig: &Rig, r: &f3g_motion::Retargeted, bones: &Compared) -> f32 {
    let (worst, at) = largest_angle(motion, rig, r, bones);
    assert!(worst < 20.0, "{at}");
    worst
}

/// The largest angle between a source bone's direction and its target's over the frames, and
/// where it is.
fn largest_angle(
    motion: &Motion,
    rig: &Rig,
    r: &f3g_motion::Retargeted,
    bones: &Compared,
) -> (f32, String) {
    let frames = &r.frames;
    let rest = rig.joint_world(&rig.zero_params()).unwrap();
    let at = |r: Role| rest[rig.roles.get(r).unwrap()].translation;
    let names = &r.source_roles.0;
    let source_rest = motion.positions(0);
    let s = |r: Role| source_rest[motion.skeleton.index_of(&names[&r]).unwrap()];
    let flat = |v: Vec3| Vec3::new(v.x, 0.0, v.z).normalize();
    let turn = Quat::from_rotation_arc(
        flat(s(Role::LeftHip) - s(Role::RightHip)),
        flat(at(Role::LeftHip) - at(Role::RightHip)),
    );
    let mut worst = (0.0f32, String::new());
    for f in 0..motion.frames() {
        for (from, to, role_from, role_to) in bones {
            let source = turn * source_direction(motion, f, from, to);
            let target = target_direction(rig, frames, f, *role_from, *role_to);
            let angle = degrees(source, target);
            if angle > worst.0 {
                worst = (
                    angle,
                    format!(
                        "frame {f}: the source's {from} → {to} points {source}, the target's \
                         {role_from:?} → {role_to:?} {target} ({angle}°)"
                    ),
                );
            }
        }
    }
    worst
}

/// The roles of the limbs and torso, `(role, joint)`, for left and right names made by
/// `side` from the bone words `[clavicle, upper arm, forearm, hand, thigh, shin, foot]`.
fn expected(
    torso: [&str; 5],
    limbs: [&str; 7],
    side: impl Fn(&str, bool) -> String,
) -> Vec<(Role, String)> {
    use Role::*;
    let mut out: Vec<(Role, String)> = [Pelvis, Spine, Chest, Neck, Head]
        .into_iter()
        .zip(torso.map(String::from))
        .collect();
    let left = [
        LeftClavicle,
        LeftShoulder,
        LeftElbow,
        LeftWrist,
        LeftHip,
        LeftKnee,
        LeftAnkle,
    ];
    let right = [
        RightClavicle,
        RightShoulder,
        RightElbow,
        RightWrist,
        RightHip,
        RightKnee,
        RightAnkle,
    ];
    for (i, word) in limbs.iter().enumerate() {
        out.push((left[i], side(word, true)));
        out.push((right[i], side(word, false)));
    }
    out
}

/// Checks the roles inferred for `motion`, then retargets it onto the built-in human without
/// a joint map: the correspondence takes each role's joint, and the compared bones point the
/// same way in every frame.
fn converts(motion: &Motion, family: &str, roles: &[(Role, String)], bones: &Compared) -> f32 {
    let inferred = roles_by_name(motion);
    for (role, name) in roles {
        let got = inferred
            .iter()
            .find(|(r, _)| r == role)
            .map(|(_, n)| n.as_str());
        assert_eq!(
            got,
            Some(name.as_str()),
            "{family}: {role:?} (inferred: {inferred:?})"
        );
    }
    let rig = builtin();
    let path = format!("{family}.bvh");
    let r = retarget(motion, &rig, &RetargetOptions::default(), Path::new(&path))
        .unwrap_or_else(|e| panic!("{family}: {e}"));
    for (role, name) in roles {
        let target = &rig.skeleton.joints()[rig.roles.get(*role).unwrap()].name;
        let c = r.correspondence.iter().find(|c| &c.target == target);
        assert_eq!(
            c.map(|c| c.source.as_str()),
            Some(name.as_str()),
            "{family}: the target's {role:?} joint `{target}` ({:?})",
            c.map(|c| c.by)
        );
        assert_eq!(
            r.source_roles.0.get(role),
            Some(name),
            "{family}: saved map, {role:?}"
        );
    }
    on_the_floor(&rig, &r, family);
    let warnings = &r.plausibility.as_ref().unwrap().warnings;
    assert!(warnings.is_empty(), "{family}: {warnings:?}");
    worst_angle(motion, &rig, &r, bones)
}

/// The human's mesh's lowest height at `p`.
fn lowest_vertex(rig: &Rig, p: &f3g_rig::RigParams) -> f32 {
    rig.pose(p).unwrap().bounds().0.y
}

/// The frames of [`poses`] whose legs stand as at rest (0, 1 and 4) have the human's soles on
/// its floor (its lowest point at rest) within 1 cm, whatever the source's proportions; those
/// with a thigh swung forward (2 and 3, the feet lifted) are not pushed through it.
fn on_the_floor(rig: &Rig, r: &f3g_motion::Retargeted, family: &str) {
    let floor = lowest_vertex(rig, &rig.zero_params());
    let report = r.floor.as_ref().expect("a floor report");
    assert_eq!(report.contact_frames, 3, "{family}: {report:?}");
    for (f, p) in r.frames.iter().enumerate() {
        let above = lowest_vertex(rig, p) - floor;
        if [0, 1, 4].contains(&f) {
            assert!(
                above.abs() < 0.01,
                "{family} frame {f}: the feet {:.1} cm above the floor",
                100.0 * above
            );
        } else {
            assert!(
                above > -0.005,
                "{family} frame {f}: {:.1} cm below the floor",
                -100.0 * above
            );
        }
    }
}

/// The arm and leg bones of both sides, compared source against target, for joint names made
/// by `side` from `[upper arm, forearm, hand, thigh, shin, foot]`.
fn limb_bones(
    words: [&str; 6],
    side: impl Fn(&str, bool) -> String,
) -> Vec<(String, String, Role, Role)> {
    use Role::*;
    let mut out = Vec::new();
    for left in [true, false] {
        let n = |i: usize| side(words[i], left);
        let (s, e, w, h, k, a) = if left {
            (
                LeftShoulder,
                LeftElbow,
                LeftWrist,
                LeftHip,
                LeftKnee,
                LeftAnkle,
            )
        } else {
            (
                RightShoulder,
                RightElbow,
                RightWrist,
                RightHip,
                RightKnee,
                RightAnkle,
            )
        };
        out.push((n(0), n(1), s, e));
        out.push((n(1), n(2), e, w));
        out.push((n(3), n(4), h, k));
        out.push((n(4), n(5), k, a));
    }
    out
}

fn compared(bones: &[(String, String, Role, Role)]) -> Vec<(&str, &str, Role, Role)> {
    bones
        .iter()
        .map(|(a, b, r, s)| (a.as_str(), b.as_str(), *r, *s))
        .collect()
}

/// A pose for the frames: the arms hanging (upper arms and forearms straight down), the
/// forearms bent forward, the upper arms out sideways with the forearms hanging, and the
/// torso turned 70° with the arms hanging; the thighs swing forward in the second and third.
/// `up`, `forward` and `left` are the file's axes; the names as `limb_bones`'s.
fn poses(
    bones: &[Bone],
    words: [&str; 6],
    side: impl Fn(&str, bool) -> String,
    torso: &str,
    (up, forward, left): (Vec3, Vec3, Vec3),
) -> Vec<Vec<(String, Quat)>> {
    let down = -up;
    let mut frames = vec![Vec::new(); 5];
    let turn = Quat::from_axis_angle(up, 70f32.to_radians());
    frames[4].push((torso.to_string(), turn));
    for is_left in [true, false] {
        let n = |i: usize| side(words[i], is_left);
        let out = if is_left { left } else { -left };
        let hang = [
            aim(bones, &n(0), &n(1), down),
            aim(bones, &n(1), &n(2), down),
        ];
        frames[1].extend(hang.iter().cloned());
        frames[2].push(aim(bones, &n(0), &n(1), down));
        frames[2].push(aim(bones, &n(1), &n(2), forward));
        frames[3].push(aim(bones, &n(0), &n(1), out));
        frames[3].push(aim(bones, &n(1), &n(2), down));
        frames[4].extend(hang.iter().map(|(b, q)| (b.clone(), turn * *q)));
        let thigh = (down * 0.8 + forward * 0.6).normalize();
        frames[2].push(aim(bones, &n(3), &n(4), thigh));
        frames[3].push(aim(bones, &n(3), &n(4), thigh));
        frames[3].push(aim(bones, &n(4), &n(5), down));
    }
    frames
}

/// Blender's axes: Z up, facing −Y, the body's left +X.
const BLENDER: (Vec3, Vec3, Vec3) = (Vec3::Z, Vec3::NEG_Y, Vec3::X);

fn rigify_side(prefix: &'static str) -> impl Fn(&str, bool) -> String {
    move |w: &str, left: bool| format!("{prefix}{w}.{}", if left { "L" } else { "R" })
}

const RIGIFY_LIMBS: [&str; 7] = [
    "shoulder",
    "upper_arm",
    "forearm",
    "hand",
    "thigh",
    "shin",
    "foot",
];
const RIGIFY_BONES: [&str; 6] = ["upper_arm", "forearm", "hand", "thigh", "shin", "foot"];

#[test]
fn rigify_skeletons_get_their_roles_and_convert() {
    let dir = tempfile::tempdir().unwrap();
    // The metarig's names, the generated rig's deform bones, and a rig whose neck and head
    // are named so.
    let renamed: Vec<Bone> = rigify_metarig()
        .into_iter()
        .map(|(n, p, h)| {
            let f = |n: &str| match n {
                "spine.004" => "neck".to_string(),
                "spine.005" => "neck.001".to_string(),
                "spine.006" => "head".to_string(),
                n => n.to_string(),
            };
            (f(&n), p.map(|p| f(&p)), h)
        })
        .collect();
    for (family, bones, prefix, torso) in [
        (
            "metarig",
            rigify_metarig(),
            "",
            ["spine", "spine.001", "spine.003", "spine.004", "spine.006"],
        ),
        (
            "DEF",
            rigify_deform(),
            "DEF-",
            [
                "DEF-spine",
                "DEF-spine.001",
                "DEF-spine.003",
                "DEF-spine.004",
                "DEF-spine.006",
            ],
        ),
        (
            "neck-head",
            renamed,
            "",
            ["spine", "spine.001", "spine.003", "neck", "head"],
        ),
    ] {
        let side = rigify_side(prefix);
        let frames = poses(
            &bones,
            RIGIFY_BONES,
            &side,
            &format!("{prefix}spine"),
            BLENDER,
        );
        let motion = write_read(
            dir.path(),
            &format!("{family}.bvh"),
            &bvh(&bones, &frames, "YXZ"),
        );
        let roles = expected(torso, RIGIFY_LIMBS, &side);
        let limbs = limb_bones(RIGIFY_BONES, &side);
        let worst = converts(&motion, family, &roles, &compared(&limbs));
        eprintln!("rigify {family}: limb bones within {worst:.2}°");
    }
}

/// The forearm bug: a Rigify source whose forearms hang down gives a built-in human whose
/// forearms hang down (elbow → wrist, world directions within 20°).
#[test]
fn rigify_forearms_that_hang_down_hang_down_on_the_human() {
    let dir = tempfile::tempdir().unwrap();
    let rig = builtin();
    for (family, bones, prefix) in [
        ("metarig", rigify_metarig(), ""),
        ("DEF", rigify_deform(), "DEF-"),
    ] {
        let side = rigify_side(prefix);
        let frames = poses(
            &bones,
            RIGIFY_BONES,
            &side,
            &format!("{prefix}spine"),
            BLENDER,
        );
        let motion = write_read(
            dir.path(),
            &format!("{family}.bvh"),
            &bvh(&bones, &frames, "YXZ"),
        );
        let r = retarget(
            &motion,
            &rig,
            &RetargetOptions::default(),
            Path::new("rigify.bvh"),
        )
        .unwrap_or_else(|e| panic!("{family}: {e}"));
        // Frames 1, 3 and 4 hang the forearms; frame 2 bends them forward.
        for (f, want) in [
            (1, Vec3::NEG_Y),
            (2, Vec3::Z),
            (3, Vec3::NEG_Y),
            (4, Vec3::NEG_Y),
        ] {
            for (elbow, wrist, left) in [
                (Role::LeftElbow, Role::LeftWrist, true),
                (Role::RightElbow, Role::RightWrist, false),
            ] {
                let source =
                    source_direction(&motion, f, &side("forearm", left), &side("hand", left));
                assert!(
                    degrees(source, want) < 1.0,
                    "{family} frame {f}: the source points {source}"
                );
                let target = target_direction(&rig, &r.frames, f, elbow, wrist);
                assert!(
                    degrees(source, target) < 20.0,
                    "{family} frame {f}: the source's forearm points {source}, the human's {target}"
                );
            }
        }
    }
}

/// Joints whose names say nothing (`Joint0`, …, in Mixamo's layout, Y up, and Unreal's, Z up
/// with its IK bones beside the pelvis): the roles come from the skeleton's shape, the same as
/// the names give, and the motion converts as well.
#[test]
fn anonymous_skeletons_get_their_roles_from_their_shape() {
    let mixamo_side =
        |w: &str, left: bool| format!("mixamorig:{}{w}", if left { "Left" } else { "Right" });
    let mixamo_words = ["Arm", "ForeArm", "Hand", "UpLeg", "Leg", "Foot"];
    let mixamo_axes = (Vec3::Y, Vec3::Z, Vec3::X);
    converts_anonymous(
        "mixamo",
        mixamo(),
        mixamo_words,
        mixamo_side,
        mixamo_axes,
        "mixamorig:Hips",
    );
    let unreal_side = |w: &str, left: bool| format!("{w}_{}", if left { "l" } else { "r" });
    let unreal_words = ["upperarm", "lowerarm", "hand", "thigh", "calf", "foot"];
    let unreal_axes = (Vec3::Z, Vec3::Y, Vec3::NEG_X);
    converts_anonymous(
        "unreal",
        unreal(),
        unreal_words,
        unreal_side,
        unreal_axes,
        "pelvis",
    );
}

/// [`poses`] of `bones` written with every joint renamed `Joint<i>` convert with the roles the
/// names give, found from the shape.
fn converts_anonymous(
    family: &str,
    bones: Vec<Bone>,
    words: [&str; 6],
    side: impl Fn(&str, bool) -> String + Copy,
    axes: (Vec3, Vec3, Vec3),
    torso: &str,
) {
    let dir = tempfile::tempdir().unwrap();
    let frames = poses(&bones, words, side, torso, axes);
    let anonymous = |n: &str| format!("Joint{}", bones.iter().position(|b| b.0 == n).unwrap());
    let renamed: Vec<Bone> = bones
        .iter()
        .map(|(n, p, h)| (anonymous(n), p.as_deref().map(anonymous), *h))
        .collect();
    let by_name = roles_by_name(&write_read(
        dir.path(),
        &format!("{family}-named.bvh"),
        &bvh(&bones, &frames, "ZXY"),
    ));
    let frames: Vec<Vec<(String, Quat)>> = frames
        .iter()
        .map(|f| f.iter().map(|(n, q)| (anonymous(n), *q)).collect())
        .collect();
    let motion = write_read(
        dir.path(),
        &format!("{family}-anonymous.bvh"),
        &bvh(&renamed, &frames, "ZXY"),
    );
    let rig = builtin();
    let r = retarget(
        &motion,
        &rig,
        &RetargetOptions::default(),
        Path::new(family),
    )
    .unwrap_or_else(|e| panic!("{family}: {e}"));
    assert_eq!(r.roles_from, RolesFrom::Shape, "{family}");
    for role in [
        Role::Pelvis,
        Role::LeftHip,
        Role::RightKnee,
        Role::LeftAnkle,
        Role::RightShoulder,
        Role::LeftElbow,
        Role::RightWrist,
        Role::Neck,
    ] {
        // (The head is the neck chain's last joint, Mixamo's `HeadTop_End`: it turns as the
        // head does, which is what retargeting takes from it.)
        let named = by_name.iter().find(|(r, _)| *r == role).map(|(_, n)| n);
        assert_eq!(
            r.source_roles.0.get(&role),
            named.map(|n| anonymous(n)).as_ref(),
            "{family}: {role:?}"
        );
    }
    on_the_floor(&rig, &r, family);
    let warnings = &r.plausibility.as_ref().unwrap().warnings;
    assert!(warnings.is_empty(), "{family}: {warnings:?}");
    let limbs: Vec<(String, String, Role, Role)> = limb_bones(words, side)
        .into_iter()
        .map(|(a, b, r, s)| (anonymous(&a), anonymous(&b), r, s))
        .collect();
    let worst = worst_angle(&motion, &rig, &r, &compared(&limbs));
    eprintln!("{family}, anonymous: limb bones within {worst:.2}°");
}

/// A skeleton layout as its tool writes BVH, and the joints its roles must find.
struct Layout<'a, S: Fn(&str, bool) -> String + Copy> {
    family: &'a str,
    bones: Vec<Bone>,
    /// A sided joint's name from its word and side.
    side: S,
    /// `[clavicle, upper arm, forearm, hand, thigh, shin, foot]` words for `side`.
    limbs: [&'a str; 7],
    /// The pelvis (which [`poses`] turns), spine, chest, neck and head joints.
    torso: [&'a str; 5],
    /// The file's (up, forward, left).
    axes: (Vec3, Vec3, Vec3),
    /// Rotation channel order written.
    order: &'a str,
}

impl<S: Fn(&str, bool) -> String + Copy> Layout<'_, S> {
    /// Writes [`poses`] of the layout as `<family>.bvh`, reads it back and checks it converts
    /// with its roles ([`converts`]), comparing its limb bones and `extra` ones; prints the
    /// worst angle.
    fn converts(&self, extra: &[(&str, &str, Role, Role)]) {
        let dir = tempfile::tempdir().unwrap();
        let [_, words @ ..] = self.limbs;
        let frames = poses(&self.bones, words, self.side, self.torso[0], self.axes);
        let motion = write_read(
            dir.path(),
            &format!("{}.bvh", self.family),
            &bvh(&self.bones, &frames, self.order),
        );
        let roles = expected(self.torso, self.limbs, self.side);
        let limbs = limb_bones(words, self.side);
        let mut bones = compared(&limbs);
        bones.extend_from_slice(extra);
        let worst = converts(&motion, self.family, &roles, &bones);
        eprintln!("{}: limb bones within {worst:.2}°", self.family);
    }
}

#[test]
fn mixamo_names_get_their_roles() {
    let torso = ["Hips", "Spine", "Spine2", "Neck", "Head"].map(|n| format!("mixamorig:{n}"));
    Layout {
        family: "mixamo",
        bones: mixamo(),
        side: |w: &str, left: bool| format!("mixamorig:{}{w}", if left { "Left" } else { "Right" }),
        limbs: ["Shoulder", "Arm", "ForeArm", "Hand", "UpLeg", "Leg", "Foot"],
        torso: torso.each_ref().map(String::as_str),
        axes: (Vec3::Y, Vec3::Z, Vec3::X),
        order: "ZXY",
    }
    .converts(&[]);
}

#[test]
fn unreal_names_get_their_roles_and_the_pelvis_drives_the_body() {
    // Z up, facing +Y, left −X. The pelvis (not the root on the floor) turns the body.
    Layout {
        family: "unreal",
        bones: unreal(),
        side: |w: &str, left: bool| format!("{w}_{}", if left { "l" } else { "r" }),
        limbs: [
            "clavicle", "upperarm", "lowerarm", "hand", "thigh", "calf", "foot",
        ],
        torso: ["pelvis", "spine_01", "spine_03", "neck_01", "head"],
        axes: (Vec3::Z, Vec3::Y, Vec3::NEG_X),
        order: "XYZ",
    }
    .converts(&[("thigh_r", "thigh_l", Role::RightHip, Role::LeftHip)]);
}

/// Truebones-style Biped names (`Bip01 L Thigh`), legs from the spine, arms from the neck, Z up
/// and inches (read as centimetres: a 70-unit body; retargeting scales by the legs' lengths, so
/// the result is the same).
#[test]
fn biped_names_get_their_roles() {
    Layout {
        family: "biped",
        bones: biped(),
        side: |w: &str, left: bool| format!("Bip01 {} {w}", if left { "L" } else { "R" }),
        limbs: [
            "Clavicle", "UpperArm", "Forearm", "Hand", "Thigh", "Calf", "Foot",
        ],
        torso: [
            "Bip01 Pelvis",
            "Bip01 Spine",
            "Bip01 Spine2",
            "Bip01 Neck",
            "Bip01 Head",
        ],
        axes: (Vec3::Z, Vec3::NEG_Y, Vec3::X),
        order: "ZXY",
    }
    .converts(&[]);
}

/// MotionBuilder / HumanIK names with their `Reference` root and roll leaves.
#[test]
fn humanik_names_get_their_roles() {
    Layout {
        family: "humanik",
        bones: humanik(),
        side: |w: &str, left: bool| format!("{}{w}", if left { "Left" } else { "Right" }),
        limbs: ["Shoulder", "Arm", "ForeArm", "Hand", "UpLeg", "Leg", "Foot"],
        torso: ["Hips", "Spine", "Spine3", "Neck", "Head"],
        axes: (Vec3::Y, Vec3::Z, Vec3::X),
        order: "ZXY",
    }
    .converts(&[]);
}

#[test]
fn cmu_asf_names_get_their_roles() {
    Layout {
        family: "cmu",
        bones: cmu(),
        side: |w: &str, left: bool| format!("{}{w}", if left { "l" } else { "r" }),
        limbs: [
            "clavicle", "humerus", "radius", "wrist", "femur", "tibia", "foot",
        ],
        torso: ["root", "lowerback", "thorax", "lowerneck", "head"],
        axes: (Vec3::Y, Vec3::Z, Vec3::X),
        order: "ZYX",
    }
    .converts(&[]);
}

/// LAFAN1's skeleton (module docs of the test below): Mixamo's without the namespace, and
/// each joint's frame turned so that X lies along its first child's bone and Z toward the
/// body's left (+X here; forward, +Z, for bones along it), as LAFAN1's offsets lie: its hips'
/// leg offsets are mostly along Z, so its rest is wider along Z than tall along Y.
fn lafan1() -> (Vec<Bone>, Vec<Quat>) {
    let bones: Vec<Bone> = mixamo()
        .into_iter()
        .map(|(n, p, h)| {
            let plain = |n: &str| n.trim_start_matches("mixamorig:").to_string();
            (plain(&n), p.as_deref().map(plain), h)
        })
        .collect();
    let turned: Vec<Quat> = bones
        .iter()
        .map(|(name, _, head)| {
            bones
                .iter()
                .find(|b| b.1.as_deref() == Some(name.as_str()))
                .map_or(Quat::IDENTITY, |child| {
                    let x = (child.2 - *head).normalize();
                    let side = if x.x.abs() > 0.9 { Vec3::Z } else { Vec3::X };
                    let z = (side - x * side.dot(x)).normalize();
                    Quat::from_mat3(&glam::Mat3::from_cols(x, z.cross(x), z))
                })
        })
        .collect();
    (bones, turned)
}

/// LAFAN1's layout (Ubisoft's animation dataset, from its BVH files): Y up, facing +Z,
/// centimetres, the CMU/HumanIK names without a namespace, and a rest pose whose bones all lie
/// along +X — each joint's frame turned so that its first child's offset is along its X, the
/// frames' rotations standing the body up. Taken as the reference (the file's rest), it
/// turned the human into a contorted body lying on its side; the first frame stands and is
/// the reference instead.
#[test]
fn lafan1_rest_along_x_takes_a_standing_frame_as_its_reference() {
    let dir = tempfile::tempdir().unwrap();
    let (bones, turned) = lafan1();
    let side = |w: &str, left: bool| format!("{}{w}", if left { "Left" } else { "Right" });
    let words = ["Arm", "ForeArm", "Hand", "UpLeg", "Leg", "Foot"];
    let frames = poses(&bones, words, side, "Hips", (Vec3::Y, Vec3::Z, Vec3::X));
    let text = bvh_turned(&bones, &frames, "ZYX", &turned, &[]);
    let mut motion = write_read(dir.path(), "lafan1.bvh", &text);
    // The file's rest lies along X: its bones' offsets say nothing of up.
    let rest = motion.skeleton.rest(None);
    let hips = motion.skeleton.index_of("Hips").unwrap();
    let head = motion.skeleton.index_of("Head").unwrap();
    let trunk = (rest[head].translation - rest[hips].translation).normalize();
    assert!(
        trunk.x > 0.9,
        "the fixture's rest trunk lies along X: {trunk}"
    );
    assert_eq!(
        motion.up,
        f3g_motion::Up::Z,
        "read as LAFAN1's was: Z up by its rest"
    );

    let rig = builtin();
    let on_file_rest = retarget(
        &motion,
        &rig,
        &RetargetOptions {
            rest: RestChoice::FileRest,
            ..Default::default()
        },
        Path::new("lafan1.bvh"),
    )
    .unwrap();
    let warnings = &on_file_rest.plausibility.as_ref().unwrap().warnings;
    assert!(
        warnings
            .iter()
            .any(|w| w.contains("upright") || w.contains("points")),
        "the file's rest as the reference is reported: {warnings:?}"
    );

    let r = retarget(
        &motion,
        &rig,
        &RetargetOptions::default(),
        Path::new("lafan1.bvh"),
    )
    .unwrap();
    let reference = r.reference.clone().unwrap();
    assert_eq!(
        (reference.frame, reference.up),
        (Some(0), f3g_motion::Up::Y)
    );
    // The test's own comparison reads the motion with the up axis found.
    motion.up = reference.up;
    let torso = ["Hips", "Spine", "Spine2", "Neck", "Head"];
    let roles = expected(
        torso,
        ["Shoulder", "Arm", "ForeArm", "Hand", "UpLeg", "Leg", "Foot"],
        side,
    );
    let worst = converts(
        &motion,
        "lafan1",
        &roles,
        &compared(&limb_bones(words, side)),
    );
    eprintln!("lafan1: limb bones within {worst:.2}°");
}

/// LAFAN1's layout (its rest along +X) in a clip that never stands — a crouch, trunk leaning
/// 50° forward, thighs forward, shins back, arms hanging, then with the forearms raised: no
/// frame can be the reference, so `auto` keeps the file's rest and the human lies contorted
/// (the checks report it); `--rest t-pose` builds a T from the file's rest and the human
/// crouches as the source does, every limb bone within 20° of the source's.
#[test]
fn a_clip_that_never_stands_takes_a_t_pose_built_from_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let (bones, turned) = lafan1();
    let (up, forward) = (Vec3::Y, Vec3::Z);
    let lean = Quat::from_axis_angle(Vec3::X, 50f32.to_radians());
    let mut crouch = vec![("Spine".to_string(), lean)];
    for side in ["Left", "Right"] {
        let n = |w: &str| format!("{side}{w}");
        crouch.push(aim(
            &bones,
            &n("UpLeg"),
            &n("Leg"),
            forward * 0.9 - up * 0.45,
        ));
        crouch.push(aim(&bones, &n("Leg"), &n("Foot"), -forward * 0.5 - up));
        crouch.push(aim(&bones, &n("Foot"), &n("ToeBase"), forward - up * 0.3));
        crouch.push(aim(&bones, &n("Arm"), &n("ForeArm"), -up));
        crouch.push(aim(&bones, &n("ForeArm"), &n("Hand"), -up));
    }
    let mut raised = crouch.clone();
    for side in ["Left", "Right"] {
        let n = |w: &str| format!("{side}{w}");
        raised.retain(|(b, _)| *b != n("ForeArm"));
        raised.push(aim(&bones, &n("ForeArm"), &n("Hand"), forward));
    }
    let text = bvh_turned(&bones, &[crouch, raised], "ZYX", &turned, &[]);
    let motion = write_read(dir.path(), "lafan1_crouch.bvh", &text);
    let rig = builtin();
    let convert = |motion: &Motion, rest: RestChoice| {
        retarget(
            motion,
            &rig,
            &RetargetOptions {
                rest,
                ..Default::default()
            },
            Path::new("lafan1_crouch.bvh"),
        )
        .unwrap()
    };
    let limb_warnings = |r: &f3g_motion::Retargeted| -> Vec<String> {
        let warnings = &r.plausibility.as_ref().unwrap().warnings;
        warnings
            .iter()
            .filter(|w| w.contains("points"))
            .cloned()
            .collect()
    };

    let auto = convert(&motion, RestChoice::Auto);
    let reference = auto.reference.clone().unwrap();
    assert_eq!((reference.frame, reference.t_pose), (None, false));
    assert!(
        reference
            .reason
            .is_some_and(|r| r.contains("no frame does")),
        "auto finds no standing frame"
    );
    assert_eq!(
        auto.reference.as_ref().unwrap().up,
        f3g_motion::Up::Z,
        "misread"
    );
    let side = |w: &str, left: bool| format!("{}{w}", if left { "Left" } else { "Right" });
    let limbs = limb_bones(["Arm", "ForeArm", "Hand", "UpLeg", "Leg", "Foot"], side);
    let mut as_stood = motion.clone();
    as_stood.up = f3g_motion::Up::Y;
    let (worst, at) = largest_angle(&as_stood, &rig, &auto, &compared(&limbs));
    assert!(worst > 30.0, "auto's body is turned off the source's: {at}");

    let r = convert(&motion, RestChoice::TPose);
    let reference = r.reference.clone().unwrap();
    assert_eq!(
        (reference.frame, reference.t_pose, reference.up),
        (None, true, f3g_motion::Up::Y)
    );
    assert_eq!(limb_warnings(&r), Vec::<String>::new());
    let worst = worst_angle(&as_stood, &rig, &r, &compared(&limbs));
    eprintln!("lafan1 crouch, --rest t-pose: limb bones within {worst:.2}°");
}

/// A squat with planted feet (Mixamo's skeleton with a cartoon's short thighs and long shins,
/// the knees 16 cm higher): the knees bend forward and the pelvis goes down and back, the
/// ankles still. The human's thigh and shin are proportioned unlike these, so the same angles
/// move its feet along the floor; `lock_feet` keeps them where they stand (each ankle within
/// 5 mm of where it was planted).
#[test]
fn locked_feet_stay_where_they_stand_in_a_squat() {
    let dir = tempfile::tempdir().unwrap();
    let bones: Vec<Bone> = mixamo()
        .into_iter()
        .map(
            |(n, p, h)| match n.ends_with("Leg") && !n.ends_with("UpLeg") {
                true => (n, p, h + Vec3::Y * 16.0),
                false => (n, p, h),
            },
        )
        .collect();
    let at = |n: &str| {
        bones
            .iter()
            .find(|b| b.0 == format!("mixamorig:{n}"))
            .unwrap()
            .2
    };
    let (thigh, shin) = (
        at("LeftUpLeg").distance(at("LeftLeg")),
        at("LeftLeg").distance(at("LeftFoot")),
    );
    let (mut frames, mut moved) = (Vec::new(), Vec::new());
    for f in 0..24 {
        // Down and up twice: thighs forward by `a`, shins back by `b`, ankles fixed.
        let a = 1.1 * (std::f32::consts::PI * f as f32 / 12.0).sin().abs();
        let b = 0.7 * a;
        let (knee, ankle) = (
            Vec3::new(0.0, -a.cos(), a.sin()),
            Vec3::new(0.0, -b.cos(), -b.sin()),
        );
        let drop = thigh + shin - (thigh * a.cos() + shin * b.cos());
        let back = thigh * a.sin() - shin * b.sin();
        moved.push(Vec3::new(0.0, -drop, -back));
        let mut pose = Vec::new();
        for side in ["Left", "Right"] {
            let n = |w: &str| format!("mixamorig:{side}{w}");
            pose.push(aim(&bones, &n("UpLeg"), &n("Leg"), knee));
            pose.push(aim(&bones, &n("Leg"), &n("Foot"), ankle));
            // The feet flat on the floor.
            pose.push(aim(
                &bones,
                &n("Foot"),
                &n("ToeBase"),
                at("LeftToeBase") - at("LeftFoot"),
            ));
        }
        frames.push(pose);
    }
    let none = vec![Quat::IDENTITY; bones.len()];
    let text = bvh_turned(&bones, &frames, "ZXY", &none, &moved);
    let motion = write_read(dir.path(), "squat.bvh", &text);
    // The source's ankles stay put: the fixture is right.
    let ankle = motion.skeleton.index_of("mixamorig:LeftFoot").unwrap();
    for f in 0..motion.frames() {
        let d = motion.positions(f)[ankle].distance(motion.positions(0)[ankle]);
        assert!(d < 0.05, "the source's ankle moved {d} cm in frame {f}");
    }
    let rig = builtin();
    let ankles = [Role::LeftAnkle, Role::RightAnkle].map(|r| rig.roles.get(r).unwrap());
    let slide = |lock_feet: bool| {
        let r = retarget(
            &motion,
            &rig,
            &RetargetOptions {
                lock_feet,
                ..Default::default()
            },
            Path::new("squat.bvh"),
        )
        .unwrap();
        let flat = |v: Vec3| Vec3::new(v.x, 0.0, v.z);
        let start = rig.joint_world(&r.frames[0]).unwrap();
        let mut worst = 0.0f32;
        for p in &r.frames {
            let w = rig.joint_world(p).unwrap();
            for &j in &ankles {
                worst = worst.max(flat(w[j].translation).distance(flat(start[j].translation)));
            }
        }
        (worst, r)
    };
    let (free, r) = slide(false);
    assert!(r.feet_locked.is_none());
    assert!(
        free > 0.02,
        "the unlocked feet slide {free} m (the case this is for)"
    );
    let (locked, r) = slide(true);
    let report = r.feet_locked.unwrap();
    assert_eq!(report.planted_frames, 24, "{report:?}");
    assert!(locked < 0.005, "locked feet slide {locked} m: {report:?}");
    assert!(
        (report.largest_slide_before_m - free).abs() < 0.005,
        "{report:?} vs {free}"
    );
    assert!(r.plausibility.unwrap().warnings.is_empty());
    eprintln!(
        "squat: feet slid {:.1} cm, locked {:.2} cm",
        100.0 * free,
        100.0 * locked
    );
}

/// A kneel (Mixamo's skeleton, centimetres): standing, then on both knees — thighs down, shins
/// and feet back along the floor, the hips 49 cm lower. Rule 5 alone sank the human's knees
/// into the floor (its shins are shorter for its legs than Mixamo's); with the floor rule the
/// lowest point is on the floor in both frames, and no check complains.
#[test]
fn a_kneel_keeps_the_knees_on_the_floor() {
    let dir = tempfile::tempdir().unwrap();
    let bones = mixamo();
    let n = |w: &str, left: bool| format!("mixamorig:{}{w}", if left { "Left" } else { "Right" });
    let mut kneel = Vec::new();
    for left in [true, false] {
        kneel.push(aim(&bones, &n("Leg", left), &n("Foot", left), Vec3::NEG_Z));
        kneel.push(aim(
            &bones,
            &n("Foot", left),
            &n("ToeBase", left),
            Vec3::NEG_Z,
        ));
    }
    let frames = vec![Vec::new(), kneel];
    let moved = [Vec3::ZERO, Vec3::new(0.0, -49.0, 0.0)];
    let text = bvh_turned(
        &bones,
        &frames,
        "ZXY",
        &vec![Quat::IDENTITY; bones.len()],
        &moved,
    );
    let motion = write_read(dir.path(), "kneel.bvh", &text);
    let rig = builtin();
    let r = retarget(
        &motion,
        &rig,
        &RetargetOptions::default(),
        Path::new("kneel.bvh"),
    )
    .unwrap();
    let floor = lowest_vertex(&rig, &rig.zero_params());
    for (f, p) in r.frames.iter().enumerate() {
        let above = lowest_vertex(&rig, p) - floor;
        assert!(
            above.abs() < 0.01,
            "frame {f}: {:.1} cm above the floor",
            100.0 * above
        );
    }
    let knee = rig.roles.get(Role::LeftKnee).unwrap();
    let pelvis = rig.roles.get(Role::Pelvis).unwrap();
    let kneeling = rig.joint_world(&r.frames[1]).unwrap();
    assert!(
        kneeling[knee].translation.y - floor < 0.12
            && kneeling[pelvis].translation.y > kneeling[knee].translation.y + 0.3,
        "the human kneels upright: knee {} pelvis {}",
        kneeling[knee].translation,
        kneeling[pelvis].translation
    );
    let report = r.plausibility.unwrap();
    assert!(report.warnings.is_empty(), "{report:?}");
    assert_eq!(r.floor.unwrap().contact_frames, 2);
}

/// Files Blender itself exported (`tools/blender_corpus.py`: Rigify's basic human metarig
/// posed in four frames, written by Blender 4.5's FBX, glTF and BVH exporters) convert as
/// Blender poses them: every limb bone of the human within 20° of the metarig's in every
/// frame (Blender's directions in `expected.json`, Z up and facing −Y), the soles on the floor
/// in the standing frames, no warning. The FBX was written with the scene at its last frame,
/// so its bones' own transforms hold that pose and only its bind pose holds the rest.
#[test]
fn blender_exports_convert_as_blender_poses_them() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/blender");
    let expected: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("expected.json")).unwrap()).unwrap();
    let rig = builtin();
    let floor = lowest_vertex(&rig, &rig.zero_params());
    let mut bodies: Vec<(&str, Vec<Vec<f3g_rig::skeleton::Similarity>>)> = Vec::new();
    for file in ["metarig.fbx", "metarig.glb", "metarig.bvh"] {
        let motion = read(&dir.join(file)).unwrap_or_else(|e| panic!("{file}: {e}"));
        let r = retarget(&motion, &rig, &RetargetOptions::default(), Path::new(file))
            .unwrap_or_else(|e| panic!("{file}: {e}"));
        let warnings = &r.plausibility.as_ref().unwrap().warnings;
        assert!(warnings.is_empty(), "{file}: {warnings:?}");
        assert_eq!(r.frames.len(), 4, "{file}");
        let mut worst = 0.0f32;
        for (f, frame) in expected["directions"].as_object().unwrap() {
            let f: usize = f.parse().unwrap();
            for (bones, d) in frame.as_object().unwrap() {
                let d: Vec<f32> = d
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_f64().unwrap() as f32)
                    .collect();
                // Blender's Z up, −Y forward → +Y up, +Z forward.
                let source = Vec3::new(d[0], d[2], -d[1]);
                let (from, to) = bones.split_once('>').unwrap();
                let role = |bone: &str| {
                    let left = bone.ends_with(".L");
                    match bone.split('.').next().unwrap() {
                        "upper_arm" if left => Role::LeftShoulder,
                        "upper_arm" => Role::RightShoulder,
                        "forearm" if left => Role::LeftElbow,
                        "forearm" => Role::RightElbow,
                        "hand" if left => Role::LeftWrist,
                        "hand" => Role::RightWrist,
                        "thigh" if left => Role::LeftHip,
                        "thigh" => Role::RightHip,
                        "shin" if left => Role::LeftKnee,
                        "shin" => Role::RightKnee,
                        "foot" if left => Role::LeftAnkle,
                        _ => Role::RightAnkle,
                    }
                };
                let target = target_direction(&rig, &r.frames, f, role(from), role(to));
                let angle = degrees(source, target);
                assert!(
                    angle < 20.0,
                    "{file} frame {f}: Blender's {bones} points {source}, the human's {target} ({angle:.1}°)"
                );
                worst = worst.max(angle);
            }
        }
        // Frames 0, 1 and 3 stand (2 swings both thighs forward).
        for f in [0, 1, 3] {
            let above = lowest_vertex(&rig, &r.frames[f]) - floor;
            assert!(
                above.abs() < 0.01,
                "{file} frame {f}: the soles {:.1} cm above the floor",
                100.0 * above
            );
        }
        eprintln!("blender {file}: limb bones within {worst:.2}°");
        let joints = r.frames.iter().map(|p| rig.joint_world(p).unwrap());
        bodies.push((file, joints.collect()));
    }
    // The three exporters' files are one motion: every joint of the human (head, hands and
    // spine too, which the limb directions do not see) turns and sits alike.
    let (reference, first) = &bodies[1];
    for (file, body) in &bodies {
        for (f, (a, b)) in body.iter().zip(first).enumerate() {
            for (j, (a, b)) in a.iter().zip(b).enumerate() {
                let angle = a.rotation.angle_between(b.rotation).to_degrees();
                let gap = a.translation.distance(b.translation);
                assert!(
                    angle < 1.0 && gap < 0.01,
                    "frame {f}, joint `{}`: {file} turns it {angle:.1}° and moves it {:.1} cm \
                     from {reference}'s",
                    rig.skeleton.joints()[j].name,
                    100.0 * gap
                );
            }
        }
    }
}
