//! The body-model contract: roles resolved at load, the head region and canonical pose they
//! give, and a rigged glTF with names no table knows made usable by a role map alone.

use f3g_rig::{CanonicalPose, ModelSpec, Rig, RigParams, Role, RoleMap, Skeleton, gltf};

fn builtin() -> Rig {
    f3g_rig::builtin::load().unwrap().rig
}

/// The built-in human with its joints renamed `bone000`, `bone001`, … (no name tells a role).
fn anonymous(rig: &Rig) -> Rig {
    let joints = rig
        .skeleton
        .joints()
        .iter()
        .enumerate()
        .map(|(i, j)| f3g_rig::Joint {
            name: format!("bone{i:03}"),
            ..j.clone()
        })
        .collect();
    Rig {
        skeleton: Skeleton::new(joints).unwrap(),
        ..rig.clone()
    }
}

/// Parameters of `to` copied by name from `from` (pose parameters both models have).
fn by_name(from: &Rig, params: &RigParams, to: &Rig, rename: impl Fn(&str) -> String) -> RigParams {
    let names = to.pose_param_names();
    let mut out = to.zero_params();
    for (name, value) in from.pose_param_names().iter().zip(&params.pose) {
        if let Some(i) = names.iter().position(|n| *n == rename(name)) {
            out.pose[i] = *value;
        }
    }
    out.expression = params.expression.clone();
    out
}

#[test]
fn the_builtin_human_has_every_role_and_a_head() {
    let rig = builtin();
    rig.check_body_model().unwrap();
    assert!(Role::ALL.iter().all(|&r| rig.roles.get(r).is_some()));
    let head = rig.head_vertices().unwrap();
    let top = rig
        .mesh
        .vertices
        .iter()
        .map(|v| v.y)
        .fold(f32::MIN, f32::max);
    // The head region is the top ~25 cm of a 1.66 m body.
    assert!(head.len() > 100);
    assert!(head.iter().all(|&v| rig.mesh.vertices[v].y > top - 0.35));
    let canonical = rig.canonical_params(&CanonicalPose::default()).unwrap();
    let hip = rig.roles.get(Role::LeftHip).unwrap();
    let posed = rig.pose(&canonical).unwrap();
    let rest = rig.pose(&rig.zero_params()).unwrap();
    assert!(
        (posed.joints[hip]
            .rotation
            .angle_between(rest.joints[hip].rotation)
            - 25f32.to_radians())
        .abs()
            < 1e-4
    );
}

#[test]
fn a_rig_written_as_gltf_reads_back_and_poses_the_same() {
    let rig = builtin();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("human.glb");
    gltf::write(&rig, &path).unwrap();
    let back = gltf::load(&path, None).unwrap();
    let names =
        |r: &Rig| -> Vec<String> { r.skeleton.joints().iter().map(|j| j.name.clone()).collect() };
    assert_eq!(names(&back), names(&rig));
    assert_eq!(back.mesh.triangles, rig.mesh.triangles);
    assert_eq!(back.skin.joints, rig.skin.joints);
    assert_eq!(back.expression.names, rig.expression.names);
    // Names that follow the common conventions give the roles without a map.
    assert_eq!(back.roles.get(Role::Head), rig.roles.get(Role::Head));
    // A walking, smiling frame poses both the same.
    let frame = &f3g_rig::choreography::motion(&rig, 12, 3)[11];
    let frame = RigParams {
        identity: vec![0.0; rig.identity.len()],
        ..frame.clone()
    };
    let a = rig.pose(&frame).unwrap();
    let b = back
        .pose(&by_name(&rig, &frame, &back, str::to_string))
        .unwrap();
    let worst = a
        .vertices
        .iter()
        .zip(&b.vertices)
        .map(|(p, q)| (*p - *q).length())
        .fold(0.0, f32::max);
    assert!(worst < 1e-4, "worst vertex difference {worst} m");
}

#[test]
fn a_model_with_unknown_names_is_refused_naming_the_role_and_a_role_map_makes_it_a_body_model() {
    let rig = builtin();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bones.glb");
    gltf::write(&anonymous(&rig), &path).unwrap();
    let spec = ModelSpec::Gltf(path.clone());
    let e = spec.load().unwrap_err().to_string();
    assert!(e.contains("`pelvis`") && e.contains("roles.json"), "{e}");

    // The role map names each role's joint; nothing else about the model changes.
    let map = RoleMap(
        rig.roles
            .iter()
            .map(|(role, j)| (role, format!("bone{j:03}")))
            .collect(),
    );
    let map_path = RoleMap::beside(&path);
    assert_eq!(map_path, dir.path().join("bones.roles.json"));
    std::fs::write(&map_path, serde_json::to_string(&map).unwrap()).unwrap();
    let model = spec.load().unwrap();
    assert_eq!(model.roles, rig.roles);
    assert_eq!(model.head_vertices().unwrap(), rig.head_vertices().unwrap());
    let rename = |n: &str| {
        let (joint, channel) = n.rsplit_once('_').unwrap();
        let j = rig.skeleton.index_of(joint).unwrap();
        format!("bone{j:03}_{channel}")
    };
    let canonical = by_name(
        &rig,
        &rig.canonical_params(&CanonicalPose::default()).unwrap(),
        &model,
        rename,
    );
    assert_eq!(
        model.canonical_params(&CanonicalPose::default()).unwrap(),
        canonical
    );
    assert_eq!(
        model.finger_params().unwrap().len(),
        3 * rig
            .skeleton
            .joints()
            .iter()
            .enumerate()
            .filter(|(j, _)| {
                [Role::LeftWrist, Role::RightWrist].iter().any(|&w| {
                    let w = rig.roles.get(w).unwrap();
                    w != *j && rig.skeleton.is_ancestor_or_self(w, *j)
                })
            })
            .count()
    );

    // A map naming a joint the model lacks is an error naming the file and the joint.
    std::fs::write(&map_path, r#"{"head": "skull"}"#).unwrap();
    let e = spec.load().unwrap_err().to_string();
    assert!(e.contains("bones.roles.json") && e.contains("skull"), "{e}");
    std::fs::write(&map_path, r#"{"noggin": "bone001"}"#).unwrap();
    let e = spec.load().unwrap_err().to_string();
    assert!(
        e.contains("bones.roles.json") && e.contains("left_wrist"),
        "{e}"
    );
}

#[test]
fn a_rig_file_holds_the_whole_model() {
    let rig = builtin();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("body_model.npz");
    f3g_rig::file::write(&rig, &path).unwrap();
    let back = f3g_rig::file::read(&path).unwrap();
    assert_eq!(
        (&back.name, &back.roles, &back.surface),
        (&rig.name, &rig.roles, &rig.surface)
    );
    assert_eq!(back.pose_param_names(), rig.pose_param_names());
    let mut frame = f3g_rig::choreography::motion(&rig, 12, 5)[11].clone();
    frame.identity[0] = 0.5;
    let (a, b) = (rig.pose(&frame).unwrap(), back.pose(&frame).unwrap());
    assert_eq!(a.vertices, b.vertices);
}

/// `set_joint_rotation` sets what the model can turn and says what it set: a whole rotation on
/// a joint with all three channels, only the bend on a joint with one; the joint poses the rig
/// then computes are exactly what it returned. And the root goes where it is told.
#[test]
fn joint_rotations_and_the_root_are_set_as_said() {
    use glam::{Quat, Vec3};
    let rig = builtin();
    let names = rig.pose_param_names();
    let full = rig.skeleton.index_of("lowerarm01.L").unwrap();
    let single = (0..rig.skeleton.len())
        .find(|&j| {
            let n = &rig.skeleton.joints()[j].name;
            let channels = ["rx", "ry", "rz"].map(|c| names.contains(&format!("{n}_{c}")));
            channels == [true, false, false]
        })
        .expect("a joint with only rx");
    let rotation = Quat::from_euler(glam::EulerRot::XYZ, 0.4, -0.3, 0.7);
    let mut p = rig.zero_params();
    let set_full = rig.set_joint_rotation(&mut p, full, rotation);
    let set_single = rig.set_joint_rotation(&mut p, single, rotation);
    rig.set_root_translation(&mut p, Vec3::new(0.1, -0.2, 0.3))
        .unwrap();
    let poses = rig.joint_poses(&p.pose).unwrap();
    let close = |a: Quat, b: Quat| (a - b).length().min((a + b).length()) < 1e-5;
    assert!(close(set_full, rotation) && close(poses[full].rotation, rotation));
    assert!(close(poses[single].rotation, set_single) && !close(set_single, rotation));
    // What is left of the rotation about x is the bend the joint can make.
    assert!((set_single.to_axis_angle().0 - Vec3::X).length() < 1e-4);
    let root = rig.joint_world(&p).unwrap()[0].translation;
    let rest = rig.joint_world(&rig.zero_params()).unwrap()[0].translation;
    assert!((root - rest - Vec3::new(0.1, -0.2, 0.3)).length() < 1e-5);
}

/// What a silhouette sees: the root and the limbs, not the fingers, jaw or eyes — on the
/// built-in human (Momentum) and on the same rig read as an axis-angle model would name it.
#[test]
fn posture_parameters_leave_out_fingers_and_face() {
    let rig = builtin();
    let names = rig.pose_param_names();
    let posture: Vec<&str> = rig
        .posture_params()
        .unwrap()
        .iter()
        .map(|&p| names[p].as_str())
        .collect();
    for wanted in [
        "root_tx",
        "root_ry",
        "upperarm01.L_rz",
        "head_rx",
        "neck01_ry",
    ] {
        assert!(posture.contains(&wanted), "{wanted} missing");
    }
    let fingers = rig.finger_params().unwrap();
    assert!(!fingers.is_empty());
    for p in fingers {
        assert!(!posture.contains(&names[p].as_str()), "{}", names[p]);
    }
    for hidden in ["jaw_rx", "eye.L_rx"] {
        assert!(!posture.contains(&hidden), "{hidden} is the face's");
    }
}
