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

    // A frame range: frames 2, 3 and 4 of the six; one past the end is refused.
    ok(&f3g(
        d,
        &[
            "motion", "convert", "cap.bvh", "--out", "cut.npz", "--frames", "2..5",
        ],
    ));
    ok(&f3g(
        d,
        &["motion", "convert", "cap.bvh", "--out", "whole.npz"],
    ));
    let rig = f3g_rig::builtin::load().unwrap().rig;
    let cut = f3g_rig::sequence::read(&d.join("cut.npz"), &rig).unwrap();
    let whole = f3g_rig::sequence::read(&d.join("whole.npz"), &rig).unwrap();
    assert_eq!((cut.len(), whole.len()), (3, 6));
    assert_eq!(cut, whole[2..5]);
    let past = f3g(
        d,
        &[
            "motion", "convert", "cap.bvh", "--out", "x.npz", "--frames", "4..7",
        ],
    );
    assert!(!past.status.success());
    assert!(String::from_utf8_lossy(&past.stderr).contains("not inside the 6 frames"));

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

/// `f3g synth --motion`: a motion of each kind `--motion` reads becomes a capture of the
/// built-in human whose body parameters are that motion retargeted onto the person `f3g synth`
/// draws with the same seed (cut to `--frames`, its first frame moved over the ring's centre),
/// with the body in view.
#[test]
fn every_motion_kind_becomes_a_capture_of_that_motion() {
    use f3g_testkit::{Array, write_arrays};
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
            "32",
        ],
    ));
    let mut files = vec!["cap/body_params.npz".to_string()];
    for format in ["bvh", "glb", "fbx"] {
        let out = format!("walk.{format}");
        ok(&f3g(
            d,
            &[
                "motion",
                "export",
                "cap/body_params.npz",
                "--format",
                format,
                "--out",
                &out,
            ],
        ));
        files.push(out);
    }
    // AMASS (SMPL-H, Z up, walking away from the origin) and the `.smpl` codec.
    let frames = 4;
    let mut poses = vec![0.0f32; frames * 156];
    for f in 0..frames {
        poses[f * 156] = std::f32::consts::FRAC_PI_2;
        poses[f * 156 + 12] = 0.1 * f as f32;
    }
    let trans: Vec<f32> = (0..frames)
        .flat_map(|f| [2.0 + 0.1 * f as f32, 1.0, 0.9])
        .collect();
    write_arrays(
        &d.join("amass.npz"),
        &[
            Array::f32("poses", &[frames, 156], &poses),
            Array::f32("trans", &[frames, 3], &trans),
            Array::f32("betas", &[16], &[0.0; 16]),
            Array::f32("mocap_framerate", &[], &[30.0]),
        ],
    );
    files.push("amass.npz".into());
    write_arrays(
        &d.join("walk.smpl"),
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
    files.push("walk.smpl".into());

    let rig = &f3g_rig::builtin::load().unwrap().rig;
    // The person of the seed-0 capture: every motion's capture shows that body.
    let person = f3g_rig::sequence::read(&d.join("cap/body_params.npz"), rig).unwrap()[0].clone();
    assert!(
        person.identity.iter().any(|&v| v != 0.0),
        "{:?}",
        person.identity
    );
    let rest = f3g_rig::RigParams {
        identity: person.identity.clone(),
        ..rig.zero_params()
    };
    for (i, file) in files.iter().enumerate() {
        let out = format!("of{i}");
        ok(&f3g(
            d,
            &[
                "synth",
                "--out",
                &out,
                "--motion",
                file,
                "--frames",
                "3",
                "--cameras",
                "2",
                "--resolution",
                "48",
                "--supersample",
                "1",
            ],
        ));
        let mut expected =
            f3g_avatar::infer::animate::read_motion(&d.join(file), rig, &rest, &Default::default())
                .unwrap()
                .frames;
        expected.truncate(3);
        for e in &mut expected {
            e.identity.clone_from(&person.identity);
        }
        f3g_data::synth::centre_on_ring(rig, &mut expected).unwrap();
        let got = f3g_rig::sequence::read(&d.join(&out).join("body_params.npz"), rig).unwrap();
        assert_eq!(got.len(), expected.len(), "{file}");
        for (g, e) in got.iter().zip(&expected) {
            for (a, b) in g.pose.iter().zip(&e.pose) {
                assert!((a - b).abs() < 1e-5, "{file}: {a} ≠ {b}");
            }
            assert_eq!(g.identity, person.identity, "{file}");
        }
        // The first frame stands where the human stands at rest: root over the ring's centre,
        // feet on the rest pose's floor; the body in view.
        let (root, rest_root) = (
            rig.joint_world(&got[0]).unwrap()[0].translation,
            rig.joint_world(&rest).unwrap()[0].translation,
        );
        assert!((root.x - rest_root.x).abs() < 1e-4, "{file}: {root}");
        assert!((root.z - rest_root.z).abs() < 1e-4, "{file}: {root}");
        let lowest = |p: &f3g_rig::RigParams| rig.pose(p).unwrap().bounds().0.y;
        assert!((lowest(&got[0]) - lowest(&rest)).abs() < 1e-3, "{file}");
        let mask = f3g_io::read_rgb(&d.join(&out).join("cam00/mask/pha/00000000.jpg")).unwrap();
        assert!(mask.data.iter().any(|&v| v > 0.5), "{file}: nobody in view");
        let meta = std::fs::read_to_string(d.join(&out).join("synth.json")).unwrap();
        assert!(meta.contains(file.as_str()), "{meta}");
    }
}
