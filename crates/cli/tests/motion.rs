//! `f3g motion export` and `f3g motion convert` end to end: a capture's motion out to BVH and
//! back onto the built-in human, the inferred joint map saved and used, and the errors a user
//! meets (nothing written on failure).

mod common;

use common::{f3g_in as f3g, ok};

#[test]
fn a_capture_motion_goes_out_as_bvh_and_back() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(&f3g(
        d,
        &[
            "synth",
            "--out",
            "cap",
            "--frames",
            "6",
            "--resolution",
            "64",
            "--cameras",
            "2",
        ],
    ));
    ok(&f3g(
        d,
        &[
            "motion",
            "export",
            "cap/body_params.npz",
            "--out",
            "cap.bvh",
            "--fps",
            "15",
        ],
    ));
    let bvh = std::fs::read_to_string(d.join("cap.bvh")).unwrap();
    assert!(bvh.starts_with("HIERARCHY\nROOT ") && bvh.contains("Frames: 6\n"));

    let out = f3g(
        d,
        &[
            "motion",
            "convert",
            "cap.bvh",
            "--to",
            "builtin",
            "--out",
            "back.npz",
            "--fps",
            "30",
            "--save-map",
            "map.json",
            "--report",
            "report.json",
        ],
    );
    ok(&out);
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(
        said.contains("same name") && said.contains("wrote back.npz"),
        "{said}"
    );
    // 6 frames at 15 fps last 1/3 s: 11 frames at 30 fps.
    let rig = f3g_rig::builtin::load().unwrap().rig;
    assert_eq!(
        f3g_rig::sequence::read(&d.join("back.npz"), &rig)
            .unwrap()
            .len(),
        11
    );
    let map: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("map.json")).unwrap()).unwrap();
    for role in ["pelvis", "head", "left_wrist", "right_knee"] {
        assert!(map[role].is_string(), "{role} missing from {map}");
    }
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["method"], "rotations");

    // The saved map drives the same conversion.
    ok(&f3g(
        d,
        &[
            "motion",
            "convert",
            "cap.bvh",
            "--out",
            "mapped.npz",
            "--joint-map",
            "map.json",
        ],
    ));

    // Through a body model's vertices: fitting the human to itself posed by the same motion
    // gives the pose the rotations gave.
    let out = f3g(
        d,
        &[
            "motion",
            "convert",
            "cap.bvh",
            "--fps",
            "30",
            "--via",
            "builtin",
            "--iterations",
            "20",
            "--out",
            "fitted.npz",
        ],
    );
    ok(&out);
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(said.contains("same-topology correspondence"), "{said}");
    let joints = |file: &str| -> Vec<glam::Vec3> {
        f3g_rig::sequence::read(&d.join(file), &rig)
            .unwrap()
            .iter()
            .flat_map(|p| rig.joint_world(p).unwrap())
            .map(|s| s.translation)
            .collect()
    };
    let (rotated, fitted) = (joints("back.npz"), joints("fitted.npz"));
    assert_eq!(rotated.len(), fitted.len());
    let worst = rotated
        .iter()
        .zip(&fitted)
        .map(|(a, b)| a.distance(*b))
        .fold(0.0f32, f32::max);
    assert!(worst < 0.005, "joints {worst} m apart");
}

#[test]
fn bad_motion_files_are_refused_and_nothing_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("notes.txt"), "not a motion").unwrap();
    std::fs::write(
        d.join("broken.bvh"),
        "HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 nan\n",
    )
    .unwrap();
    std::fs::write(d.join("map.json"), "{\"pelvis\": 3}").unwrap();
    for (args, needles) in [
        (vec!["gone.bvh"], vec!["gone.bvh", "AMASS", "BVH"]),
        (vec!["notes.txt"], vec!["notes.txt", ".smpl"]),
        (vec!["broken.bvh"], vec!["broken.bvh:4", "finite"]),
        (
            vec!["broken.bvh", "--joint-map", "map.json"],
            vec!["map.json", "role"],
        ),
    ] {
        let mut all = vec!["motion", "convert"];
        all.extend(args);
        all.extend(["--out", "m.npz"]);
        let out = f3g(d, &all);
        assert!(!out.status.success());
        let said = String::from_utf8_lossy(&out.stderr);
        for n in needles {
            assert!(said.contains(n), "expected `{n}` in: {said}");
        }
        assert!(!d.join("m.npz").exists());
    }
    let out = f3g(d, &["motion", "export", "notes.txt", "--out", "x.bvh"]);
    assert!(!out.status.success() && !d.join("x.bvh").exists());
}
