//! The BVH reader and writer: channel orders, units and up axes, round trips, and errors
//! that name the line.

mod common;

use std::path::Path;

use f3g_motion::{Up, parse_bvh, write_bvh};
use glam::{EulerRot, Quat, Vec3};
use proptest::prelude::*;

/// Whether two rotations agree to `tol` (component-wise, up to the quaternion's sign; no acos,
/// whose f32 noise near 1 is 1e-3).
fn same_rotation(a: Quat, b: Quat, tol: f32) -> bool {
    (a - b).length().min((a + b).length()) < tol
}

const CMU_LIKE: &str = "HIERARCHY
ROOT Hips
{
  OFFSET 0.0 0.0 0.0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT LeftUpLeg
  {
    OFFSET 9.0 -5.0 0.0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT LeftLeg
    {
      OFFSET 0.0 -43.0 0.0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0.0 -44.0 0.0
      }
    }
  }
  JOINT Spine
  {
    OFFSET 0.0 10.0 0.0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Head
    {
      OFFSET 0.0 60.0 0.0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0.0 20.0 0.0
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0083333
0 90 0  0 0 0  10 20 30  0 0 0  0 0 0  0 0 0
1 91 2  0 90 0  0 0 0  0 45 0  0 0 0  0 0 0
";

#[test]
fn channels_compose_in_the_order_listed() {
    let m = parse_bvh(CMU_LIKE.as_bytes(), Path::new("cmu.bvh")).unwrap();
    assert_eq!(m.skeleton.len(), 5);
    assert_eq!(m.frames(), 2);
    assert!((m.fps - 120.0).abs() < 0.01);
    // 90 cm of hips height, 1.7 m in all along Y: centimetres, Y up.
    assert_eq!((m.metres_per_unit, m.up), (0.01, Up::Y));
    assert_eq!(m.root_translation[1], Vec3::new(1.0, 91.0, 2.0));
    // `Zrotation Xrotation Yrotation` 10 20 30 is Rz(10°) · Rx(20°) · Ry(30°).
    let expected = Quat::from_rotation_z(10f32.to_radians())
        * Quat::from_rotation_x(20f32.to_radians())
        * Quat::from_rotation_y(30f32.to_radians());
    assert!(same_rotation(m.frame(0)[1], expected, 1e-6));
    // The root turned 90° about Y (`Zrotation Yrotation Xrotation` 0 90 0) carries the left
    // hip from +X to −Z.
    let hip = m.world(1)[1].translation - m.world(1)[0].translation;
    assert!(hip.distance(Vec3::new(0.0, -5.0, -9.0)) < 1e-4, "{hip}");
}

#[test]
fn f3g_writes_its_own_euler_order() {
    // `Zrotation Yrotation Xrotation` is R = Rz·Ry·Rx, which glam's ZYX Euler angles give.
    let q = Quat::from_euler(EulerRot::ZYX, 0.3, -0.2, 1.1);
    let expected =
        Quat::from_rotation_z(0.3) * Quat::from_rotation_y(-0.2) * Quat::from_rotation_x(1.1);
    assert!(same_rotation(q, expected, 1e-6));
}

#[test]
fn a_written_motion_reads_back_to_the_same_joint_positions() {
    let dir = tempfile::tempdir().unwrap();
    for f in 0..3 {
        let walk = common::walk(f, 12);
        let back = common::through_bvh(&walk, dir.path(), "w.bvh");
        for i in 0..walk.frames() {
            for (a, b) in walk.world(i).iter().zip(back.world(i)) {
                assert!(a.translation.distance(b.translation) < 1e-3, "{a:?} {b:?}");
            }
        }
    }
}

#[test]
fn bad_files_are_refused_naming_the_line() {
    let bad = |text: &str, needle: &str| {
        let e = parse_bvh(text.as_bytes(), Path::new("bad.bvh"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("bad.bvh") && e.contains(needle),
            "expected `{needle}` in: {e}"
        );
    };
    bad("HIERARCHY\nROOT", "ends");
    bad(
        &CMU_LIKE.replace("10 20 30", "10 nan 30"),
        "frame 0, channel 7",
    );
    bad(
        &CMU_LIKE.replace("Frames: 2", "Frames: 99999999999"),
        "frames",
    );
    bad(&CMU_LIKE.replace("Frames: 2", "Frames: 3"), "bad.bvh:");
    bad(
        &CMU_LIKE.replace("Frame Time: 0.0083333", "Frame Time: 0"),
        "frame time",
    );
    bad(
        &CMU_LIKE.replace(
            "Zrotation Xrotation Yrotation",
            "Wrotation Xrotation Yrotation",
        ),
        "Wrotation",
    );
    bad(&CMU_LIKE.replace("CHANNELS 6", "CHANNELS 60"), "channels");
    bad(&CMU_LIKE.replace("JOINT Head", "JOINT LeftLeg"), "twice");
    bad(&format!("{CMU_LIKE}7\n"), "after the 2 frames");
}

/// A rotation 70 µrad from gimbal lock (proptest found it): the written angles still make it.
#[test]
fn a_rotation_next_to_gimbal_lock_round_trips() {
    let mut walk = common::walk(0, 2);
    walk.rotations[11] = Quat::from_euler(EulerRot::XYZ, 1.594844, -1.5708671, -1.546457);
    let text = write_bvh(&walk).unwrap();
    let back = parse_bvh(text.as_bytes(), Path::new("p.bvh")).unwrap();
    for (a, b) in walk.world(0).iter().zip(back.world(0)) {
        assert!(
            same_rotation(a.rotation, b.rotation, 1e-4),
            "{a:?} vs {b:?}"
        );
    }
}

proptest! {
    /// Any rotations and root positions survive writing and reading (to the written precision).
    #[test]
    fn rotations_round_trip(angles in prop::collection::vec(-3.1f32..3.1, 22 * 3 * 2), root in prop::array::uniform3(-200f32..200.0)) {
        let mut walk = common::walk(0, 2);
        for (k, q) in walk.rotations.iter_mut().enumerate() {
            *q = Quat::from_euler(EulerRot::XYZ, angles[3 * k], angles[3 * k + 1], angles[3 * k + 2]);
        }
        walk.root_translation[1] = Vec3::from_array(root);
        let text = write_bvh(&walk).unwrap();
        let back = parse_bvh(text.as_bytes(), Path::new("p.bvh")).unwrap();
        for i in 0..2 {
            for (a, b) in walk.world(i).iter().zip(back.world(i)) {
                prop_assert!(a.translation.distance(b.translation) < 1e-2);
                prop_assert!(same_rotation(a.rotation, b.rotation, 1e-4));
            }
        }
    }
}

#[test]
fn an_fbx_animation_stack_reads_to_the_same_joint_positions() {
    let walk = common::walk(0, 12);
    let text = f3g_motion::write_fbx(&walk).unwrap();
    let m = f3g_motion::parse_fbx(text.as_bytes(), Path::new("walk.fbx")).unwrap();
    assert_eq!((m.frames(), m.fps, m.up), (12, 30.0, Up::Y));
    assert!((m.metres_per_unit - 0.01).abs() < 1e-6);
    assert_eq!(m.skeleton.joints()[0].name, "mixamorig:Hips");
    assert_eq!(m.skeleton.len(), walk.skeleton.len());
    for i in 0..walk.frames() {
        let (a, b) = (walk.world(i), m.world(i));
        for (j, joint) in walk.skeleton.joints().iter().enumerate() {
            let k = m.skeleton.index_of(&joint.name).unwrap();
            let d = a[j].translation.distance(b[k].translation);
            assert!(d < 1e-2, "frame {i}, `{}`: {d} cm", joint.name);
        }
    }
    let e = f3g_motion::parse_fbx(b"; FBX 7.4.0 project file\nnot fbx", Path::new("bad.fbx"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("bad.fbx"), "{e}");
}
