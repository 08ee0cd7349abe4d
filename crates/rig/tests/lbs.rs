//! Linear blend skinning on the built-in human: the rest pose is the identity, one joint's
//! rotation moves exactly the vertices it (or its descendants) weights, as a hand computation
//! says, and the rest skeleton follows the identity shapes.

use f3g_rig::builtin;
use glam::{Quat, Vec3};

#[test]
fn rest_pose_is_the_identity() {
    let h = builtin::load().unwrap();
    let posed = h.rig.pose(&h.rig.zero_params()).unwrap();
    for (a, b) in posed.vertices.iter().zip(&h.rig.mesh.vertices) {
        assert!((*a - *b).length() < 1e-6);
    }
    for s in &posed.skinning {
        assert!(
            (s.matrix3 - glam::Mat3A::IDENTITY)
                .abs()
                .to_cols_array()
                .iter()
                .all(|v| *v < 1e-6)
        );
        assert!(Vec3::from(s.translation).length() < 1e-6);
    }
}

#[test]
fn rotating_one_joint_matches_a_hand_computation() {
    let h = builtin::load().unwrap();
    let rig = &h.rig;
    let joint = rig.skeleton.index_of("lowerarm01.L").unwrap();
    let mut params = rig.zero_params();
    let names = rig.pose_param_names();
    let angle = 0.6;
    params.pose[names.iter().position(|n| n == "lowerarm01.L_rz").unwrap()] = angle;
    let posed = rig.pose(&params).unwrap();

    // By hand: a rotation of `angle` about world Z through the joint's rest position, applied to
    // the joint and all its descendants; every other joint stays put.
    let centre = rig.skeleton.rest(None)[joint].translation;
    let rotate = |p: Vec3| Quat::from_rotation_z(angle) * (p - centre) + centre;
    let mut moved = 0;
    for (i, rest) in rig.mesh.vertices.iter().enumerate() {
        let expected: Vec3 = rig
            .skin
            .influences(i)
            .map(|(j, w)| {
                w * if rig.skeleton.is_ancestor_or_self(joint, j) {
                    rotate(*rest)
                } else {
                    *rest
                }
            })
            .sum();
        assert!((posed.vertices[i] - expected).length() < 1e-5, "vertex {i}");
        let affected = rig
            .skin
            .influences(i)
            .any(|(j, _)| rig.skeleton.is_ancestor_or_self(joint, j));
        if affected {
            moved += 1;
        } else {
            // Unaffected vertices stay put (to float rounding of world · rest⁻¹, < 1 µm).
            assert!(
                (posed.vertices[i] - *rest).length() < 1e-6,
                "vertex {i} is not weighted to the forearm and must not move"
            );
        }
    }
    assert!(moved > 300, "only {moved} vertices follow the forearm");
}

#[test]
fn the_skeleton_follows_the_identity() {
    let h = builtin::load().unwrap();
    let rig = &h.rig;
    let mut params = rig.zero_params();
    params.identity[rig
        .identity
        .names
        .iter()
        .position(|n| n == "height")
        .unwrap()] = 0.2;
    let tall = rig.pose(&params).unwrap();
    let head = rig.skeleton.index_of("head").unwrap();
    let base = rig.skeleton.rest(None)[head].translation;
    assert!(
        tall.joints[head].translation.y > base.y + 0.05,
        "the head joint must rise with height"
    );
    // Still the identity at the rest pose: the shaped mesh is not moved by skinning.
    for (a, b) in tall.vertices.iter().zip(&tall.rest_vertices) {
        assert!((*a - *b).length() < 1e-5);
    }
}

#[test]
fn bad_parameters_are_rejected() {
    let h = builtin::load().unwrap();
    let mut p = h.rig.zero_params();
    p.pose.pop();
    assert!(
        h.rig
            .pose(&p)
            .unwrap_err()
            .to_string()
            .contains("pose parameters")
    );
    let mut p = h.rig.zero_params();
    p.expression[3] = f32::NAN;
    assert!(
        h.rig
            .pose(&p)
            .unwrap_err()
            .to_string()
            .contains("expression parameter 3")
    );
}
