//! Retargeting: round trips through BVH, rest-pose alignment, naming families, units and
//! up axes, AMASS and `.smpl` layouts, and the errors a user meets.

mod common;

use std::path::Path;

use f3g_motion::retarget::{Matched, complete_by_topology};
use f3g_motion::{Motion, RetargetOptions, Up, from_rig, read, retarget};
use f3g_rig::{Rig, RigParams, Role, RoleMap, Roles};
use f3g_testkit::{Array, write_arrays};
use glam::{Quat, Vec3};

fn builtin() -> Rig {
    f3g_rig::builtin::load().unwrap().rig
}

/// World positions of `joints` of every frame.
fn positions(rig: &Rig, frames: &[RigParams], joints: &[usize]) -> Vec<Vec3> {
    frames
        .iter()
        .flat_map(|p| {
            let w = rig.joint_world(p).unwrap();
            joints
                .iter()
                .map(move |&j| w[j].translation)
                .collect::<Vec<_>>()
        })
        .collect()
}

fn largest_distance(a: &[Vec3], b: &[Vec3]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| x.distance(*y))
        .fold(0.0, f32::max)
}

fn without_expressions(mut frames: Vec<RigParams>) -> Vec<RigParams> {
    for p in &mut frames {
        p.expression.fill(0.0);
    }
    frames
}

fn role_joints(rig: &Rig) -> Vec<usize> {
    rig.roles.iter().map(|(_, j)| j).collect()
}

/// An f3g sequence of the built-in human written by `write` as `name` at `fps`, read back and
/// retargeted onto the same body model: every joint where it was, to 0.1 mm. Joint motion
/// only: expressions move the face's rest joints, which these formats cannot carry.
fn survives(name: &str, fps: f32, seed: u64, write: fn(&Motion) -> Vec<u8>) {
    let rig = builtin();
    let frames = without_expressions(f3g_rig::choreography::motion(&rig, 12, seed));
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    std::fs::write(&path, write(&from_rig(&rig, &frames, fps).unwrap())).unwrap();
    let back = read(&path).unwrap();
    assert_eq!((back.frames(), back.fps), (12, fps));
    let options = RetargetOptions {
        identity: frames[0].identity.clone(),
        ..Default::default()
    };
    let r = retarget(&back, &rig, &options, &path).unwrap();
    assert!(r.correspondence.iter().all(|c| c.by == Matched::Name));
    assert_eq!(r.correspondence.len(), rig.skeleton.len());
    let all: Vec<usize> = (0..rig.skeleton.len()).collect();
    let error = largest_distance(
        &positions(&rig, &frames, &all),
        &positions(&rig, &r.frames, &all),
    );
    assert!(error < 1e-4, "{name}: joints moved by up to {error} m");
}

#[test]
fn an_f3g_sequence_survives_bvh_gltf_and_fbx_joint_for_joint() {
    survives("seq.bvh", 15.0, 7, |m| {
        f3g_motion::write_bvh(m).unwrap().into_bytes()
    });
    survives("seq.glb", 15.0, 3, f3g_motion::write_gltf);
    survives("seq.fbx", 24.0, 5, |m| {
        f3g_motion::write_fbx(m).unwrap().into_bytes()
    });
}

#[test]
fn t_pose_and_a_pose_sources_drive_the_same_pose() {
    let rig = builtin();
    let t_pose = common::walk(0, 20);
    let a_pose = common::on_a_pose(&t_pose, 0);
    // The two sources agree joint for joint in every frame…
    for f in [0, 7, 19] {
        let (a, b) = (t_pose.world(f), a_pose.world(f));
        for (x, y) in a.iter().zip(&b) {
            assert!(x.translation.distance(y.translation) < 1e-3);
        }
    }
    // …and so do the poses they give the target, though their rest poses differ by 45°.
    let options = RetargetOptions::default();
    let from_t = retarget(&t_pose, &rig, &options, Path::new("t.bvh")).unwrap();
    let from_a = retarget(&a_pose, &rig, &options, Path::new("a.bvh")).unwrap();
    let joints = role_joints(&rig);
    let error = largest_distance(
        &positions(&rig, &from_t.frames, &joints),
        &positions(&rig, &from_a.frames, &joints),
    );
    assert!(error < 2e-3, "the role joints differ by up to {error} m");
    // At the T-pose source's rest the target's arms are raised into a T: wrist level with
    // the shoulder.
    let rest = Motion {
        rotations: vec![Quat::IDENTITY; t_pose.skeleton.len()],
        root_translation: vec![Vec3::new(0.0, 0.0, 0.0)],
        ..t_pose.clone()
    };
    let r = retarget(&rest, &rig, &options, Path::new("t.bvh")).unwrap();
    let w = rig.joint_world(&r.frames[0]).unwrap();
    let (shoulder, wrist) = (
        w[rig.roles.get(Role::LeftShoulder).unwrap()].translation,
        w[rig.roles.get(Role::LeftWrist).unwrap()].translation,
    );
    assert!(
        (wrist.y - shoulder.y).abs() < 0.03 && wrist.x - shoulder.x > 0.4,
        "shoulder {shoulder}, wrist {wrist}"
    );
}

#[test]
fn mixamo_cmu_and_blender_names_map_without_a_joint_map() {
    let expected = |key: &str, family: &str| -> Option<Role> {
        use Role::*;
        Some(match (key, family) {
            ("hips", _) => Pelvis,
            ("spine", "mixamo" | "blender") | ("spine1", "cmu") => Spine,
            ("chest", _) => Chest,
            ("neck", _) => Neck,
            ("head", _) => Head,
            ("l_clavicle", _) => LeftClavicle,
            ("r_clavicle", _) => RightClavicle,
            ("l_arm", _) => LeftShoulder,
            ("r_arm", _) => RightShoulder,
            ("l_forearm", _) => LeftElbow,
            ("r_forearm", _) => RightElbow,
            ("l_hand", _) => LeftWrist,
            ("r_hand", _) => RightWrist,
            ("l_upleg", _) => LeftHip,
            ("r_upleg", _) => RightHip,
            ("l_leg", _) => LeftKnee,
            ("r_leg", _) => RightKnee,
            ("l_foot", _) => LeftAnkle,
            ("r_foot", _) => RightAnkle,
            _ => return None,
        })
    };
    let rig = builtin();
    let dir = tempfile::tempdir().unwrap();
    let mut poses = Vec::new();
    for (f, family) in common::FAMILIES.iter().enumerate() {
        let skeleton = common::skeleton(f, 0.0);
        let roles = complete_by_topology(&skeleton, Roles::infer(&skeleton));
        for j in 0..skeleton.len() {
            let role = roles.iter().find(|(_, k)| *k == j).map(|(r, _)| r);
            assert_eq!(
                role,
                expected(common::key(j), family),
                "{family}: `{}`",
                skeleton.joints()[j].name
            );
        }
        // Through a BVH file, in centimetres: the same walk drives the same pose.
        let motion =
            common::through_bvh(&common::walk(f, 10), dir.path(), &format!("{family}.bvh"));
        assert_eq!((motion.metres_per_unit, motion.up), (0.01, Up::Y));
        let r = retarget(
            &motion,
            &rig,
            &RetargetOptions::default(),
            Path::new("w.bvh"),
        )
        .unwrap();
        assert!(
            r.unmatched_roles
                .iter()
                .all(|(r, _)| matches!(r, Role::Jaw | Role::LeftEye | Role::RightEye)),
            "{:?}",
            r.unmatched_roles
        );
        poses.push(positions(&rig, &r.frames, &role_joints(&rig)));
    }
    for p in &poses[1..] {
        let error = largest_distance(&poses[0], p);
        assert!(error < 1e-3, "families disagree by {error} m");
    }
}

#[test]
fn z_up_metres_and_y_up_centimetres_give_the_same_pose() {
    let rig = builtin();
    let y_up = common::walk(0, 10);
    // The same walk measured in metres in a Z-up world.
    let to_z = Quat::from_rotation_x(std::f32::consts::FRAC_PI_2);
    let joints = y_up
        .skeleton
        .joints()
        .iter()
        .map(|j| f3g_rig::Joint {
            offset: to_z * j.offset * 0.01,
            ..j.clone()
        })
        .collect();
    let z_up = Motion {
        skeleton: f3g_rig::Skeleton::new(joints).unwrap(),
        rotations: y_up
            .rotations
            .iter()
            .map(|q| to_z * *q * to_z.inverse())
            .collect(),
        root_translation: y_up
            .root_translation
            .iter()
            .map(|t| to_z * *t * 0.01)
            .collect(),
        metres_per_unit: 1.0,
        up: Up::Z,
        ..y_up.clone()
    };
    let options = RetargetOptions::default();
    let a = retarget(&y_up, &rig, &options, Path::new("y.bvh")).unwrap();
    let b = retarget(&z_up, &rig, &options, Path::new("z.bvh")).unwrap();
    let joints = role_joints(&rig);
    let error = largest_distance(
        &positions(&rig, &a.frames, &joints),
        &positions(&rig, &b.frames, &joints),
    );
    assert!(error < 1e-3, "{error} m");
    // The target stands: head above pelvis, feet near its own rest floor.
    let w = rig.joint_world(&b.frames[0]).unwrap();
    assert!(
        w[rig.roles.get(Role::Head).unwrap()].translation.y
            > w[rig.roles.get(Role::Pelvis).unwrap()].translation.y + 0.4
    );
}

#[test]
fn resampling_keeps_the_duration() {
    let walk = common::walk(0, 31); // one second at 30 fps
    let r = retarget(
        &walk,
        &builtin(),
        &RetargetOptions {
            fps: Some(10.0),
            ..Default::default()
        },
        Path::new("w.bvh"),
    )
    .unwrap();
    assert_eq!((r.frames.len(), r.fps), (11, 10.0));
}

/// An AMASS file of `frames` frames: standing (the Z-up root orientation AMASS stores),
/// the left knee bending.
fn amass(width: usize, frames: usize, rate_key: &str) -> Vec<Array> {
    let mut poses = vec![0.0f32; frames * width];
    for f in 0..frames {
        poses[f * width] = std::f32::consts::FRAC_PI_2; // root: +90° about X, Z up
        poses[f * width + 3 * 4] = 0.5 * f as f32 / frames as f32; // left knee
    }
    let trans: Vec<f32> = (0..frames)
        .flat_map(|f| [0.01 * f as f32, 0.0, 0.9])
        .collect();
    vec![
        Array::f32("poses", &[frames, width], &poses),
        Array::f32("trans", &[frames, 3], &trans),
        Array::f32("betas", &[16], &[0.1; 16]),
        Array::f32(rate_key, &[], &[120.0]),
    ]
}

#[test]
fn amass_layouts_and_key_variants_read_and_stand_upright() {
    let dir = tempfile::tempdir().unwrap();
    let rig = builtin();
    for (width, key, family) in [
        (156, "mocap_framerate", f3g_motion::SmplFamily::SmplH),
        (165, "mocap_frame_rate", f3g_motion::SmplFamily::SmplX),
        (72, "mocap_framerate", f3g_motion::SmplFamily::Smpl),
    ] {
        let path = dir.path().join(format!("amass{width}.npz"));
        write_arrays(&path, &amass(width, 24, key));
        let motion = read(&path).unwrap();
        assert_eq!((motion.frames(), motion.fps, motion.up), (24, 120.0, Up::Z));
        assert_eq!(motion.smpl.as_ref().unwrap().family, family);
        let r = retarget(
            &motion,
            &rig,
            &RetargetOptions {
                fps: Some(30.0),
                ..Default::default()
            },
            &path,
        )
        .unwrap();
        assert_eq!(r.frames.len(), 6);
        let w = rig.joint_world(&r.frames[0]).unwrap();
        let at = |role| w[rig.roles.get(role).unwrap()].translation;
        assert!(
            at(Role::Head).y > at(Role::Pelvis).y + 0.4,
            "{width}: the body lies down"
        );
        assert!(at(Role::LeftAnkle).y < at(Role::Pelvis).y - 0.6);
    }
    // Without a frame rate: the error names the keys it looks for.
    let path = dir.path().join("no_rate.npz");
    let mut arrays = amass(156, 4, "mocap_framerate");
    arrays.pop();
    write_arrays(&path, &arrays);
    let e = read(&path).unwrap_err().to_string();
    assert!(
        e.contains("no_rate.npz") && e.contains("mocap_frame_rate"),
        "{e}"
    );
}

#[test]
fn an_amass_rest_pose_raises_the_arms_without_twisting_them() {
    // AMASS's rest lies in its Z-up world (the root orientation stands it up): the whole body's
    // rest frame must be turned onto it first, or the arms come out twisted about themselves.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rest.npz");
    let mut arrays = amass(156, 1, "mocap_framerate");
    if let f3g_testkit::Values::F32(v) = &mut arrays[0].values {
        v[12] = 0.0; // knee straight
    }
    write_arrays(&path, &arrays);
    let rig = builtin();
    let r = retarget(
        &read(&path).unwrap(),
        &rig,
        &RetargetOptions::default(),
        &path,
    )
    .unwrap();
    let rest = rig.joint_world(&rig.zero_params()).unwrap();
    let posed = rig.joint_world(&r.frames[0]).unwrap();
    let (shoulder, elbow) = (
        rig.roles.get(Role::LeftShoulder).unwrap(),
        rig.roles.get(Role::LeftElbow).unwrap(),
    );
    let arm = (rest[elbow].translation - rest[shoulder].translation).normalize();
    // SMPL's rest is a T-pose: the arm straight out to the left, only raised, not turned.
    let raised = Quat::from_rotation_arc(arm, Vec3::X) * rest[shoulder].rotation;
    let off = 2.0
        * (posed[shoulder].rotation.conjugate() * raised)
            .xyz()
            .length()
            .asin();
    assert!(off < 0.35, "the upper arm is {off} rad off a plain raise");
    let pelvis = rig.roles.get(Role::Pelvis).unwrap();
    let turned = 2.0
        * (posed[pelvis].rotation.conjugate() * rest[pelvis].rotation)
            .xyz()
            .length()
            .asin();
    assert!(turned < 0.35, "the pelvis is turned by {turned} rad");
}

#[test]
fn amass_gender_as_a_string_array_is_accepted() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let plain = dir.path().join("plain.npz");
    write_arrays(&plain, &amass(156, 3, "mocap_framerate"));
    // Copy the archive and add `gender` as numpy writes it: a 0-d '<U6' array.
    let path = dir.path().join("gendered.npz");
    let mut archive = zip::ZipWriter::new(std::fs::File::create(&path).unwrap());
    let mut source = zip::ZipArchive::new(std::fs::File::open(&plain).unwrap()).unwrap();
    for i in 0..source.len() {
        let file = source.by_index(i).unwrap();
        archive.raw_copy_file(file).unwrap();
    }
    let mut header = b"{'descr': '<U6', 'fortran_order': False, 'shape': (), }".to_vec();
    while !(10 + header.len() + 1).is_multiple_of(64) {
        header.push(b' ');
    }
    header.push(b'\n');
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend((header.len() as u16).to_le_bytes());
    npy.extend(header);
    for c in "female".chars() {
        npy.extend((c as u32).to_le_bytes());
    }
    archive
        .start_file("gender.npy", zip::write::FileOptions::default())
        .unwrap();
    archive.write_all(&npy).unwrap();
    archive.finish().unwrap();
    assert_eq!(read(&path).unwrap().frames(), 3);
}

#[test]
fn smpl_codec_files_read() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("walk.smpl");
    let frames = 5;
    write_arrays(
        &path,
        &[
            Array::i64("codecVersion", &[], &[1]),
            Array::i64("smplVersion", &[], &[2]),
            Array::i64("frameCount", &[], &[frames as i64]),
            Array::f32("frameRate", &[], &[30.0]),
            Array::f32("shapeParameters", &[10], &[0.0; 10]),
            Array::f32("bodyTranslation", &[frames, 3], &vec![0.0; frames * 3]),
            Array::f32("bodyPose", &[frames, 22, 3], &vec![0.1; frames * 66]),
            Array::f32("headPose", &[frames, 3, 3], &vec![0.0; frames * 9]),
            Array::f32("leftHandPose", &[frames, 15, 3], &vec![0.0; frames * 45]),
            Array::f32("rightHandPose", &[frames, 15, 3], &vec![0.0; frames * 45]),
        ],
    );
    let motion = read(&path).unwrap();
    assert_eq!((motion.frames(), motion.fps, motion.up), (5, 30.0, Up::Y));
    assert_eq!(
        motion.smpl.as_ref().unwrap().family,
        f3g_motion::SmplFamily::SmplX
    );
    // The root's rotation is bodyPose's first joint.
    let expected = f3g_rig::rig::axis_angle(Vec3::splat(0.1));
    assert!((motion.frame(0)[0] - expected).length() < 1e-5);
    retarget(&motion, &builtin(), &RetargetOptions::default(), &path).unwrap();
}

/// `motion` without the joints named in `gone` (leaves), their rotations dropped.
fn without(motion: &Motion, gone: &[&str]) -> Motion {
    let old = motion.skeleton.joints();
    let kept: Vec<usize> = (0..old.len())
        .filter(|&j| !gone.contains(&old[j].name.as_str()))
        .collect();
    let joints = kept
        .iter()
        .map(|&j| f3g_rig::Joint {
            parent: old[j]
                .parent
                .map(|p| kept.iter().position(|&k| k == p).unwrap()),
            ..old[j].clone()
        })
        .collect();
    let rotations = (0..motion.frames())
        .flat_map(|f| kept.iter().map(move |&j| motion.frame(f)[j]))
        .collect();
    Motion {
        skeleton: f3g_rig::Skeleton::new(joints).unwrap(),
        rotations,
        ..motion.clone()
    }
}

#[test]
fn a_joint_map_names_what_the_names_do_not() {
    let rig = builtin();
    // Hips named so that nothing can read them: the roles come from the skeleton's shape.
    let walk = common::walk(0, 3);
    let joints = walk
        .skeleton
        .joints()
        .iter()
        .map(|j| f3g_rig::Joint {
            name: j
                .name
                .replace("mixamorig:Hips", "Bone_007")
                .replace("UpLeg", "Strut"),
            ..j.clone()
        })
        .collect();
    let odd = Motion {
        skeleton: f3g_rig::Skeleton::new(joints).unwrap(),
        ..walk
    };
    let r = retarget(
        &odd,
        &rig,
        &RetargetOptions::default(),
        Path::new("odd.bvh"),
    )
    .unwrap();
    assert_eq!(r.roles_from, f3g_motion::retarget::RolesFrom::Shape);
    assert_eq!(r.source_roles.0[&Role::Pelvis], "Bone_007");
    assert_eq!(r.source_roles.0[&Role::LeftHip], "mixamorig:LeftStrut");
    // Without toes the feet point nowhere: the walk's bending knees tell left from right.
    let toeless = without(&odd, &["mixamorig:LeftToeBase", "mixamorig:RightToeBase"]);
    let r = retarget(
        &toeless,
        &rig,
        &RetargetOptions::default(),
        Path::new("odd.bvh"),
    )
    .unwrap();
    assert_eq!(r.source_roles.0[&Role::LeftHip], "mixamorig:LeftStrut");
    assert_eq!(r.source_roles.0[&Role::RightWrist], "mixamorig:RightHand");
    // Standing still with straight legs nothing does: the error lists the joints that took no
    // role, says why the shape did not help and how to name them.
    let mut still = toeless.clone();
    let joints = still.skeleton.len();
    still.rotations.truncate(joints);
    still.rotations.fill(Quat::IDENTITY);
    still.root_translation.truncate(1);
    let straight: Vec<f3g_rig::Joint> = still
        .skeleton
        .joints()
        .iter()
        .map(|j| f3g_rig::Joint {
            // The knees on the hip–ankle lines.
            offset: if j.name.ends_with("Leg") || j.name.ends_with("Foot") {
                Vec3::new(0.0, j.offset.y, 0.0)
            } else {
                j.offset
            },
            ..j.clone()
        })
        .collect();
    still.skeleton = f3g_rig::Skeleton::new(straight).unwrap();
    let e = retarget(
        &still,
        &rig,
        &RetargetOptions::default(),
        Path::new("odd.bvh"),
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("odd.bvh")
            && e.contains("--joint-map")
            && e.contains("Bone_007")
            && e.contains("no toe joints")
            && e.contains("knees never bend"),
        "{e}"
    );
    let map: RoleMap = serde_json::from_str(
        r#"{"pelvis": "Bone_007", "left_hip": "mixamorig:LeftStrut", "right_hip": "mixamorig:RightStrut"}"#,
    )
    .unwrap();
    let options = RetargetOptions {
        joint_map: Some(map),
        ..Default::default()
    };
    let r = retarget(&odd, &rig, &options, Path::new("odd.bvh")).unwrap();
    assert!(
        r.correspondence
            .iter()
            .any(|c| c.source == "Bone_007" && c.by == Matched::Role(Role::Pelvis))
    );
    // A map naming a joint the skeleton lacks is refused, naming it.
    let map: RoleMap = serde_json::from_str(r#"{"pelvis": "Nope"}"#).unwrap();
    let e = retarget(
        &odd,
        &rig,
        &RetargetOptions {
            joint_map: Some(map),
            ..Default::default()
        },
        Path::new("odd.bvh"),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("Nope") && e.contains("--joint-map"), "{e}");
}

#[test]
fn unknown_and_missing_files_list_the_formats() {
    let dir = tempfile::tempdir().unwrap();
    let missing = read(&dir.path().join("gone.bvh")).unwrap_err().to_string();
    assert!(
        missing.contains("gone.bvh") && missing.contains("AMASS") && missing.contains("BVH"),
        "{missing}"
    );
    let txt = dir.path().join("walk.txt");
    std::fs::write(&txt, "hello").unwrap();
    let e = read(&txt).unwrap_err().to_string();
    assert!(
        e.contains("walk.txt") && e.contains(".smpl") && e.contains("BVH"),
        "{e}"
    );
    let npz = dir.path().join("other.npz");
    write_arrays(&npz, &[Array::f32("weights", &[2], &[1.0, 2.0])]);
    let e = read(&npz).unwrap_err().to_string();
    assert!(
        e.contains("other.npz") && e.contains("weights") && e.contains("AMASS"),
        "{e}"
    );
}
