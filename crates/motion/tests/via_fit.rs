//! Retargeting by rotations against a vertex fit: an SMPL-X sequence driven onto the built-in
//! human through joint rotations (`f3g motion convert`) and through the SMPL-X body's posed
//! vertices (`f3g motion convert --via smplx:…`, `f3g rig fit`) gives the same pose.
//!
//! SMPL-X's model cannot be shipped, so the test makes one of the same format from the built-in
//! human: its skeleton is the schematic SMPL-X rest skeleton that rotations are retargeted from
//! (scaled to the human), its mesh the human raised into that T-pose, skinned by handing each of
//! the human's bones to the SMPL-X bone it lies on. Both routes then drive the human; where they
//! differ is what retargeting by rotations costs against matching the body's surface.

use glam::{DMat4, DVec4, Vec3};

use f3g_motion::{Motion, RetargetOptions, Up, read, retarget};
use f3g_rig::fit::{Correspondence, FitOptions, fit_sequence};
use f3g_rig::smplx::{self, JOINT_NAMES, schematic_rest};
use f3g_rig::{Rig, RigParams, Role, Roles};
use f3g_testkit::{Array, write_arrays};

const J: usize = 55;

fn builtin() -> Rig {
    f3g_rig::builtin::load().unwrap().rig
}

/// Distance from `p` to the segment `a`–`b`.
fn segment_distance(p: Vec3, a: Vec3, b: Vec3) -> f32 {
    let ab = b - a;
    let t = if ab.length_squared() > 0.0 {
        ((p - a).dot(ab) / ab.length_squared()).clamp(0.0, 1.0)
    } else {
        0.0
    };
    p.distance(a + t * ab)
}

/// Regressor weights over four of `vertices` whose affine combination is exactly `p`: the
/// nearest vertex and three more from its neighbourhood spanning a tetrahedron.
fn regress(p: Vec3, vertices: &[Vec3]) -> [(usize, f32); 4] {
    let mut near: Vec<usize> = (0..vertices.len()).collect();
    near.sort_by(|&a, &b| p.distance(vertices[a]).total_cmp(&p.distance(vertices[b])));
    near.truncate(48);
    let v = |i: usize| vertices[i];
    let a = near[0];
    let b = *near
        .iter()
        .max_by(|&&x, &&y| v(x).distance(v(a)).total_cmp(&v(y).distance(v(a))))
        .unwrap();
    let off_line = |x: usize| (v(x) - v(a)).cross(v(b) - v(a)).length();
    let c = *near
        .iter()
        .max_by(|&&x, &&y| off_line(x).total_cmp(&off_line(y)))
        .unwrap();
    let normal = (v(b) - v(a)).cross(v(c) - v(a)).normalize();
    let off_plane = |x: usize| (v(x) - v(a)).dot(normal).abs();
    let d = *near
        .iter()
        .max_by(|&&x, &&y| off_plane(x).total_cmp(&off_plane(y)))
        .unwrap();
    let column = |i: usize| DVec4::from((v(i).as_dvec3(), 1.0));
    let m = DMat4::from_cols(column(a), column(b), column(c), column(d));
    let w = m.inverse() * DVec4::from((p.as_dvec3(), 1.0));
    assert!(
        w.is_finite(),
        "a joint's regressor tetrahedron is degenerate"
    );
    [
        (a, w.x as f32),
        (b, w.y as f32),
        (c, w.z as f32),
        (d, w.w as f32),
    ]
}

/// Writes an SMPL-X-format model (v1.0 layout: 10 betas, 10 expressions, no shape or pose
/// correctives) made from the built-in human, as the module docs say.
fn write_smplx_like_the_human(path: &std::path::Path, human: &Rig) {
    // The human raised into the schematic T-pose, by retargeting the schematic rest.
    let schematic = schematic_rest();
    let t_pose = Motion {
        rotations: vec![glam::Quat::IDENTITY; schematic.len()],
        skeleton: schematic.clone(),
        root_translation: vec![Vec3::ZERO],
        fps: 30.0,
        metres_per_unit: 1.0,
        up: Up::Y,
        smpl: None,
    };
    let raised = retarget(
        &t_pose,
        human,
        &RetargetOptions::default(),
        std::path::Path::new("t-pose"),
    )
    .unwrap();
    let posed = human.pose(&raised.frames[0]).unwrap();
    let bones: Vec<Vec3> = posed.joints.iter().map(|s| s.translation).collect();

    // The schematic joints scaled and moved onto the raised human's (by role, least squares);
    // the mesh then moved so the pelvis sits where SMPL-X's does, near the origin.
    let schematic_at: Vec<Vec3> = schematic.rest(None).iter().map(|s| s.translation).collect();
    let source_roles = Roles::infer(&schematic);
    let pairs: Vec<(Vec3, Vec3)> = Role::ALL
        .iter()
        .filter_map(|&r| {
            Some((
                schematic_at[source_roles.get(r)?],
                bones[human.roles.get(r)?],
            ))
        })
        .collect();
    let n = pairs.len() as f32;
    let (sc, hc) = pairs
        .iter()
        .fold((Vec3::ZERO, Vec3::ZERO), |(a, b), (s, h)| (a + *s, b + *h));
    let (sc, hc) = (sc / n, hc / n);
    let scale = (pairs
        .iter()
        .map(|(_, h)| (*h - hc).length_squared())
        .sum::<f32>()
        / pairs
            .iter()
            .map(|(s, _)| (*s - sc).length_squared())
            .sum::<f32>())
    .sqrt();
    let shift = hc - scale * sc;
    let joints: Vec<Vec3> = schematic_at.iter().map(|p| scale * *p).collect();
    let template: Vec<Vec3> = posed.vertices.iter().map(|v| *v - shift).collect();
    let bones: Vec<Vec3> = bones.iter().map(|b| *b - shift).collect();

    // Each of the human's bones (its joint to its first child, or its joint if a leaf) goes
    // to the SMPL-X joint whose bone it lies nearest: a joint turns the bones to its children.
    let parents: Vec<Option<usize>> = schematic.joints().iter().map(|j| j.parent).collect();
    let smplx_bones: Vec<(usize, Vec3, Vec3)> = (0..J)
        .flat_map(|j| {
            let children: Vec<usize> = (0..J).filter(|&c| parents[c] == Some(j)).collect();
            match children.is_empty() {
                true => vec![(j, joints[j], joints[j])],
                false => children
                    .iter()
                    .map(|&c| (j, joints[j], joints[c]))
                    .collect(),
            }
        })
        .collect();
    let human_joints = human.skeleton.joints();
    let owner: Vec<usize> = (0..human_joints.len())
        .map(|b| {
            let child = (0..human_joints.len()).find(|&c| human_joints[c].parent == Some(b));
            let mid = child.map_or(bones[b], |c| 0.5 * (bones[b] + bones[c]));
            smplx_bones
                .iter()
                .min_by(|x, y| {
                    segment_distance(mid, x.1, x.2).total_cmp(&segment_distance(mid, y.1, y.2))
                })
                .unwrap()
                .0
        })
        .collect();
    let v = template.len();
    let mut weights = vec![0.0f32; v * J];
    for (i, (js, ws)) in human
        .skin
        .joints
        .iter()
        .zip(&human.skin.weights)
        .enumerate()
    {
        for (&b, &w) in js.iter().zip(ws) {
            weights[i * J + owner[b as usize]] += w;
        }
    }
    let mut regressor = vec![0.0f32; J * v];
    for (j, &p) in joints.iter().enumerate() {
        for (i, w) in regress(p, &template) {
            regressor[j * v + i] += w;
        }
    }
    let kintree: Vec<i64> = parents
        .iter()
        .map(|p| p.map_or(-1, |p| p as i64))
        .chain(0..J as i64)
        .collect();
    let faces: Vec<i64> = human
        .mesh
        .triangles
        .iter()
        .flatten()
        .map(|&i| i as i64)
        .collect();
    let flat: Vec<f32> = template.iter().flat_map(|p| p.to_array()).collect();
    write_arrays(
        path,
        &[
            Array::f32("v_template", &[v, 3], &flat),
            Array::f32("shapedirs", &[v, 3, 20], &vec![0.0; v * 3 * 20]),
            Array::f32("posedirs", &[v, 3, 486], &vec![0.0; v * 3 * 486]),
            Array::f32("J_regressor", &[J, v], &regressor),
            Array::f32("weights", &[v, J], &weights),
            Array::i64("kintree_table", &[2, J], &kintree),
            Array::i64("f", &[faces.len() / 3, 3], &faces),
        ],
    );
}

/// An AMASS SMPL-X file (Z up): a few frames of walking-like bends of the legs, the spine, the
/// arms and the head, drifting forward.
fn amass_motion(path: &std::path::Path, frames: usize) {
    let width = 165;
    let mut poses = vec![0.0f32; frames * width];
    let mut set = |f: usize, joint: &str, axis_angle: [f32; 3]| {
        let j = JOINT_NAMES.iter().position(|n| *n == joint).unwrap();
        poses[f * width + 3 * j..f * width + 3 * j + 3].copy_from_slice(&axis_angle);
    };
    for f in 0..frames {
        let t = f as f32 / (frames - 1) as f32;
        set(f, "pelvis", [std::f32::consts::FRAC_PI_2, 0.0, 0.0]);
        set(f, "left_hip", [-0.6 * t, 0.0, 0.1 * t]);
        set(f, "left_knee", [0.9 * t, 0.0, 0.0]);
        set(f, "right_hip", [0.35 * t, 0.0, -0.1 * t]);
        set(f, "right_knee", [0.3 * t, 0.0, 0.0]);
        set(f, "spine1", [0.15 * t, 0.1 * t, 0.0]);
        set(f, "spine3", [0.1 * t, 0.0, 0.05 * t]);
        set(f, "left_shoulder", [0.0, 0.2 * t, -t]);
        set(f, "right_shoulder", [0.0, -0.3 * t, 0.7 * t]);
        set(f, "left_elbow", [0.0, -1.1 * t, 0.0]);
        set(f, "right_elbow", [0.0, 0.6 * t, 0.0]);
        set(f, "neck", [0.1 * t, 0.2 * t, 0.0]);
        set(f, "head", [0.15 * t, 0.0, 0.0]);
    }
    let trans: Vec<f32> = (0..frames)
        .flat_map(|f| [0.0, 0.03 * f as f32, 1.0])
        .collect();
    write_arrays(
        path,
        &[
            Array::f32("poses", &[frames, width], &poses),
            Array::f32("trans", &[frames, 3], &trans),
            Array::f32("betas", &[16], &[0.0; 16]),
            Array::f32("mocap_frame_rate", &[], &[30.0]),
        ],
    );
}

/// Positions of the human's role joints of each frame, relative to its pelvis, and the
/// pelvis itself.
fn pose_and_root(rig: &Rig, frames: &[RigParams]) -> (Vec<Vec<Vec3>>, Vec<Vec3>) {
    let pelvis = rig.roles.get(Role::Pelvis).unwrap();
    frames
        .iter()
        .map(|p| {
            let w = rig.joint_world(p).unwrap();
            let root = w[pelvis].translation;
            let joints = rig
                .roles
                .iter()
                .map(|(_, j)| w[j].translation - root)
                .collect();
            (joints, root)
        })
        .unzip()
}

#[test]
fn rotations_and_a_vertex_fit_of_an_smplx_sequence_pose_the_human_alike() {
    let dir = tempfile::tempdir().unwrap();
    let human = builtin();
    let model = dir.path().join("SMPLX_LIKE.npz");
    write_smplx_like_the_human(&model, &human);
    let smplx = smplx::load(&model, 10, 10).unwrap();
    // The model is sound: its rest joints are the schematic's, scaled.
    let rest = smplx.joint_world(&smplx.zero_params()).unwrap();
    let schematic = schematic_rest().rest(None);
    let height = |s: &[f3g_rig::Similarity]| s[15].translation.y - s[7].translation.y;
    let scale = height(&rest) / height(&schematic);
    for (a, b) in rest.iter().zip(&schematic) {
        assert!(a.translation.distance(scale * b.translation) < 1e-4);
    }

    let path = dir.path().join("walk.npz");
    amass_motion(&path, 5);
    let motion = read(&path).unwrap();
    let options = RetargetOptions::default();
    let by_rotations = retarget(&motion, &human, &options, &path).unwrap();
    assert_eq!(by_rotations.method, "rotations");
    let on_smplx = retarget(&motion, &smplx, &options, &path).unwrap();
    assert_eq!(on_smplx.method, "parameters");
    let fitted = fit_sequence(
        &smplx,
        &on_smplx.frames,
        &human,
        &Correspondence::between(&smplx, &human),
        &FitOptions::default(),
        |_| {},
    )
    .unwrap();
    assert!(
        fitted.mean_vertex_rms < 0.02,
        "the human fits the SMPL-X-like body to {} m RMS",
        fitted.mean_vertex_rms
    );

    let (pose_r, root_r) = pose_and_root(&human, &by_rotations.frames);
    let (pose_f, root_f) = pose_and_root(&human, &fitted.frames);
    let distances: Vec<f32> = pose_r
        .iter()
        .flatten()
        .zip(pose_f.iter().flatten())
        .map(|(a, b)| a.distance(*b))
        .collect();
    let mean = distances.iter().sum::<f32>() / distances.len() as f32;
    let worst = distances.iter().copied().fold(0.0, f32::max);
    eprintln!("joints relative to the pelvis: mean {mean} m, worst {worst} m");
    assert!(mean < 0.02, "mean {mean} m, worst {worst} m");
    // The root moves alike (the two place it on the floor by different rules: compare the
    // way it travels).
    for f in 1..root_r.len() {
        let (dr, df) = (root_r[f] - root_r[0], root_f[f] - root_f[0]);
        assert!(dr.distance(df) < 0.02, "frame {f}: {dr} against {df}");
    }
}
