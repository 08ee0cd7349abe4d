//! Skeletons of the common naming families, made here (the fixtures' provenance): one humanoid
//! layout (T-pose, Y up, facing +Z, left +X, centimetres, hips 100 cm up) under Mixamo's, CMU's
//! and Blender's joint names, and motions on them.

#![allow(dead_code)]

use std::path::Path;

use f3g_motion::{Motion, Up};
use f3g_rig::{Joint, Skeleton};
use glam::{Quat, Vec3};

/// A joint of the layout: (generic key, parent key, position in cm).
const LAYOUT: [(&str, &str, [f32; 3]); 22] = [
    ("hips", "", [0.0, 100.0, 0.0]),
    ("spine", "hips", [0.0, 110.0, 0.0]),
    ("spine1", "spine", [0.0, 125.0, 0.0]),
    ("chest", "spine1", [0.0, 140.0, 0.0]),
    ("neck", "chest", [0.0, 155.0, 0.0]),
    ("head", "neck", [0.0, 165.0, 2.0]),
    ("l_clavicle", "chest", [5.0, 150.0, 0.0]),
    ("l_arm", "l_clavicle", [17.0, 150.0, 0.0]),
    ("l_forearm", "l_arm", [45.0, 150.0, 0.0]),
    ("l_hand", "l_forearm", [70.0, 150.0, 0.0]),
    ("r_clavicle", "chest", [-5.0, 150.0, 0.0]),
    ("r_arm", "r_clavicle", [-17.0, 150.0, 0.0]),
    ("r_forearm", "r_arm", [-45.0, 150.0, 0.0]),
    ("r_hand", "r_forearm", [-70.0, 150.0, 0.0]),
    ("l_upleg", "hips", [9.0, 95.0, 0.0]),
    ("l_leg", "l_upleg", [9.0, 52.0, 1.0]),
    ("l_foot", "l_leg", [9.0, 8.0, -2.0]),
    ("l_toe", "l_foot", [9.0, 2.0, 12.0]),
    ("r_upleg", "hips", [-9.0, 95.0, 0.0]),
    ("r_leg", "r_upleg", [-9.0, 52.0, 1.0]),
    ("r_foot", "r_leg", [-9.0, 8.0, -2.0]),
    ("r_toe", "r_foot", [-9.0, 2.0, 12.0]),
];

/// Generic key → (Mixamo, CMU, Blender) name.
pub fn names(key: &str) -> [String; 3] {
    let side = |l: &str, r: &str| -> (&'static str, String) {
        if let Some(rest) = key.strip_prefix("l_") {
            ("l", format!("{l}{rest}"))
        } else if let Some(rest) = key.strip_prefix("r_") {
            ("r", format!("{r}{rest}"))
        } else {
            ("", key.to_string())
        }
    };
    let (s, _) = side("", "");
    let upper = |x: &str| {
        if s == "l" {
            format!("Left{x}")
        } else {
            format!("Right{x}")
        }
    };
    let dot = |x: &str| {
        if s == "l" {
            format!("{x}.L")
        } else {
            format!("{x}.R")
        }
    };
    let base = key.trim_start_matches("l_").trim_start_matches("r_");
    let (mixamo, cmu, blender) = match (s, base) {
        ("", "hips") => ("Hips".into(), "Hips".into(), "spine".into()),
        ("", "spine") => ("Spine".into(), "LowerBack".into(), "spine.001".into()),
        ("", "spine1") => ("Spine1".into(), "Spine".into(), "spine.002".into()),
        ("", "chest") => ("Spine2".into(), "Spine1".into(), "spine.003".into()),
        ("", "neck") => ("Neck".into(), "Neck".into(), "spine.004".into()),
        ("", "head") => ("Head".into(), "Head".into(), "spine.006".into()),
        (_, "clavicle") => (upper("Shoulder"), upper("Shoulder"), dot("shoulder")),
        (_, "arm") => (upper("Arm"), upper("Arm"), dot("upper_arm")),
        (_, "forearm") => (upper("ForeArm"), upper("ForeArm"), dot("forearm")),
        (_, "hand") => (upper("Hand"), upper("Hand"), dot("hand")),
        (_, "upleg") => (upper("UpLeg"), upper("UpLeg"), dot("thigh")),
        (_, "leg") => (upper("Leg"), upper("Leg"), dot("shin")),
        (_, "foot") => (upper("Foot"), upper("Foot"), dot("foot")),
        (_, "toe") => (upper("ToeBase"), upper("ToeBase"), dot("toe")),
        _ => unreachable!("{key}"),
    };
    [format!("mixamorig:{mixamo}"), cmu, blender]
}

pub const FAMILIES: [&str; 3] = ["mixamo", "cmu", "blender"];

/// The layout under family `f` (0 Mixamo, 1 CMU, 2 Blender), with `arm_drop_deg` lowering
/// both arms from the T-pose at the shoulder (an A-pose for 45).
pub fn skeleton(f: usize, arm_drop_deg: f32) -> Skeleton {
    let position = |key: &str| -> Vec3 {
        let (_, _, p) = LAYOUT.iter().find(|(k, _, _)| *k == key).unwrap();
        let p = Vec3::from_array(*p);
        for (side, sign) in [("l_", 1.0f32), ("r_", -1.0)] {
            let arm = Vec3::from_array(
                LAYOUT
                    .iter()
                    .find(|(k, _, _)| *k == format!("{side}arm"))
                    .unwrap()
                    .2,
            );
            if ["forearm", "hand"]
                .iter()
                .any(|b| key == format!("{side}{b}"))
            {
                let drop = Quat::from_rotation_z(-sign * arm_drop_deg.to_radians());
                return arm + drop * (p - arm);
            }
        }
        p
    };
    let index = |key: &str| LAYOUT.iter().position(|(k, _, _)| *k == key);
    Skeleton::new(
        LAYOUT
            .iter()
            .map(|(key, parent, _)| {
                let parent = index(parent);
                Joint {
                    name: names(key)[f].clone(),
                    parent,
                    offset: position(key) - parent.map_or(Vec3::ZERO, |p| position(LAYOUT[p].0)),
                    pre_rotation: Quat::IDENTITY,
                }
            })
            .collect(),
    )
    .unwrap()
}

/// The generic key of a layout joint index.
pub fn key(j: usize) -> &'static str {
    LAYOUT[j].0
}

/// A walk with arm swings on the T-pose layout of family `f`: `frames` frames at 30 fps.
/// (The spine bends only at the chest, whose role every family names the same way.)
pub fn walk(f: usize, frames: usize) -> Motion {
    let skeleton = skeleton(f, 0.0);
    let n = skeleton.len();
    let mut rotations = Vec::with_capacity(frames * n);
    let mut root = Vec::new();
    for i in 0..frames {
        let t = i as f32 / 30.0;
        let s = (std::f32::consts::TAU * 0.8 * t).sin();
        for j in 0..n {
            let q = match key(j) {
                "hips" => Quat::from_rotation_y(0.3 * t),
                "chest" => Quat::from_rotation_x(0.1 * s),
                "neck" => Quat::from_rotation_y(0.2 * s),
                "l_arm" => Quat::from_rotation_z(-1.1) * Quat::from_rotation_x(0.4 * s),
                "r_arm" => Quat::from_rotation_z(1.1) * Quat::from_rotation_x(-0.4 * s),
                "l_forearm" => Quat::from_rotation_y(0.5 + 0.2 * s),
                "r_forearm" => Quat::from_rotation_y(-0.5 + 0.2 * s),
                "l_upleg" => Quat::from_rotation_x(-0.5 * s),
                "r_upleg" => Quat::from_rotation_x(0.5 * s),
                "l_leg" => Quat::from_rotation_x(0.6 * s.max(0.0)),
                "r_leg" => Quat::from_rotation_x(0.6 * (-s).max(0.0)),
                _ => Quat::IDENTITY,
            };
            rotations.push(q);
        }
        root.push(Vec3::new(0.0, 3.0 * s.abs(), 40.0 * t));
    }
    Motion {
        skeleton,
        rotations,
        root_translation: root,
        fps: 30.0,
        metres_per_unit: 0.01,
        up: Up::Y,
        smpl: None,
    }
}

/// `motion` written as BVH into `dir/name` and read back.
pub fn through_bvh(motion: &Motion, dir: &Path, name: &str) -> Motion {
    let path = dir.join(name);
    std::fs::write(&path, f3g_motion::write_bvh(motion).unwrap()).unwrap();
    f3g_motion::read(&path).unwrap()
}

/// The same motion on the A-pose layout (arms lowered 45° at the shoulders): every joint at
/// the same place in every frame, the arms' rotations re-expressed against the A-pose rest.
pub fn on_a_pose(t_pose: &Motion, f: usize) -> Motion {
    let skeleton = skeleton(f, 45.0);
    let n = skeleton.len();
    let correction = |j: usize| -> Quat {
        match key(j) {
            "l_arm" | "l_forearm" | "l_hand" => {
                Quat::from_rotation_z(-45f32.to_radians()).inverse()
            }
            "r_arm" | "r_forearm" | "r_hand" => Quat::from_rotation_z(45f32.to_radians()).inverse(),
            _ => Quat::IDENTITY,
        }
    };
    let mut rotations = Vec::with_capacity(t_pose.rotations.len());
    for i in 0..t_pose.frames() {
        let world: Vec<Quat> = t_pose
            .world(i)
            .iter()
            .enumerate()
            .map(|(j, w)| w.rotation * correction(j))
            .collect();
        for j in 0..n {
            let parent = skeleton.joints()[j]
                .parent
                .map_or(Quat::IDENTITY, |p| world[p]);
            rotations.push(parent.inverse() * world[j]);
        }
    }
    Motion {
        skeleton,
        rotations,
        ..t_pose.clone()
    }
}
