//! `rig fit` recovers known parameters from meshes posed by the same model.

use f3g_rig::builtin;
use f3g_rig::fit::{Correspondence, FitOptions, FitTarget, fit};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[test]
fn recovers_builtin_poses_and_identity() {
    let h = builtin::load().unwrap();
    let rig = &h.rig;
    let names = rig.pose_param_names();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for case in 0..2 {
        let mut truth = rig.zero_params();
        for (i, n) in names.iter().enumerate() {
            let limit = if n.starts_with("finger")
                || n.starts_with("eye")
                || n.starts_with("orbicularis")
            {
                0.0
            } else {
                0.35
            };
            truth.pose[i] = if n.starts_with("root_t") {
                rng.random_range(-0.2..0.2)
            } else {
                rng.random_range(-limit..=limit)
            };
        }
        truth.identity = vec![
            rng.random_range(-0.5..0.5),
            rng.random_range(0.0..0.5),
            0.0,
            0.0,
            rng.random_range(0.0..0.1),
        ];
        let posed = rig.pose(&truth).unwrap();
        let joints: Vec<_> = posed
            .joints
            .iter()
            .enumerate()
            .map(|(j, t)| (j, t.translation))
            .collect();
        let target = FitTarget {
            vertices: &posed.vertices,
            joints: &joints,
        };
        let options = FitOptions {
            fit_identity: true,
            max_iterations: 60,
            ..Default::default()
        };
        let result = fit(
            rig,
            &target,
            &Correspondence::Identity,
            &rig.zero_params(),
            &options,
        )
        .unwrap();
        assert!(
            result.vertex_rms < 1e-3,
            "case {case}: vertex RMS {} m after {} iterations",
            result.vertex_rms,
            result.iterations
        );
        assert!(
            result.joint_rms < 2e-3,
            "case {case}: joint RMS {} m",
            result.joint_rms
        );
        // Parameters such as root_rx and spine05_rx trade off (both turn the whole trunk), so the
        // check is on what the data determines: world orientations of the major joints.
        let fitted = rig.pose(&result.params).unwrap();
        for n in [
            "spine05",
            "spine02",
            "head",
            "upperleg01.L",
            "lowerleg01.R",
            "foot.L",
            "upperarm01.R",
            "lowerarm01.L",
            "wrist.R",
        ] {
            let j = rig.skeleton.index_of(n).unwrap();
            let angle = fitted.joints[j]
                .rotation
                .angle_between(posed.joints[j].rotation);
            assert!(angle < 0.03, "case {case}: {n} is off by {angle} rad");
        }
        for (k, (a, b)) in result
            .params
            .identity
            .iter()
            .zip(&truth.identity)
            .enumerate()
        {
            assert!(
                (a - b).abs() < 0.05,
                "case {case}: identity {k} = {a} vs {b}"
            );
        }
    }
}

#[test]
fn nearest_correspondences_align_a_moved_body() {
    // Without a vertex correspondence (different topologies), nearest vertices plus the joint
    // term pull a moved and posed body into place.
    let h = builtin::load().unwrap();
    let rig = &h.rig;
    let names = rig.pose_param_names();
    let mut truth = rig.zero_params();
    truth.pose[names.iter().position(|n| n == "root_ty").unwrap()] = 0.03;
    truth.pose[names.iter().position(|n| n == "root_ry").unwrap()] = 0.1;
    truth.pose[names.iter().position(|n| n == "upperarm01.L_rz").unwrap()] = -0.4;
    truth.pose[names.iter().position(|n| n == "lowerleg01.R_rx").unwrap()] = 0.5;
    let posed = rig.pose(&truth).unwrap();
    let joints: Vec<_> = [
        "spine05",
        "head",
        "upperarm01.L",
        "lowerarm01.L",
        "wrist.L",
        "lowerleg01.R",
        "foot.R",
        "foot.L",
    ]
    .iter()
    .map(|n| {
        let j = rig.skeleton.index_of(n).unwrap();
        (j, posed.joints[j].translation)
    })
    .collect();
    let target = FitTarget {
        vertices: &posed.vertices,
        joints: &joints,
    };
    let result = fit(
        rig,
        &target,
        &Correspondence::Nearest,
        &rig.zero_params(),
        &FitOptions::default(),
    )
    .unwrap();
    assert!(result.joint_rms < 5e-3, "joint RMS {}", result.joint_rms);
    assert!(
        result.vertex_rms < 3e-3,
        "vertex RMS {} after {} iterations",
        result.vertex_rms,
        result.iterations
    );
}

#[test]
fn mismatched_targets_are_rejected() {
    let h = builtin::load().unwrap();
    let target = FitTarget {
        vertices: &h.rig.mesh.vertices[..10],
        joints: &[],
    };
    let e = fit(
        &h.rig,
        &target,
        &Correspondence::Identity,
        &h.rig.zero_params(),
        &FitOptions::default(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("same-topology fit needs"), "{e}");
}
