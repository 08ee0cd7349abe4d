//! `f3g fit` end to end on a small synthetic capture, whose own parameters are the truth:
//! the fit's error against them, resuming, a parameter file it did not write left alone, and
//! keypoints written by `f3g data keypoints` read back.

mod common;

use common::{f3g_in, ok};

fn record(path: &std::path::Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[test]
fn a_capture_is_fitted_resumed_and_its_own_parameters_left_alone() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(&f3g_in(
        d,
        &[
            "synth",
            "--out",
            "cap",
            "--frames",
            "3",
            "--cameras",
            "8",
            "--resolution",
            "384",
            "--seed",
            "2",
        ],
    ));
    let fit = |extra: &[&str]| {
        let mut args = vec!["fit", "--data", "cap", "--iterations", "12"];
        args.extend_from_slice(extra);
        f3g_in(d, &args)
    };

    // Two frames, masks only: within 3 cm of the truth, the silhouettes agreeing.
    let out = fit(&["--out", "fit/body.npz", "--frames", "2", "--json", "r.json"]);
    ok(&out);
    let r = record(&d.join("r.json"));
    let joint = r["against_capture"]["joint_m"].as_f64().unwrap();
    assert!(joint < 0.03, "mean joint error {joint} m");
    let frames = r["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 2);
    for f in frames {
        let iou = f["mean_iou"].as_f64().unwrap();
        assert!(iou > 0.9, "frame {}: IoU {iou}", f["frame"]);
        assert_eq!(f["cameras"].as_array().unwrap().len(), 8);
    }

    // The same command again has nothing to do; a third frame resumes after the second.
    let again = fit(&["--out", "fit/body.npz", "--frames", "2"]);
    ok(&again);
    assert!(String::from_utf8_lossy(&again.stdout).contains("already fitted"));
    let more = fit(&["--out", "fit/body.npz"]);
    ok(&more);
    assert!(String::from_utf8_lossy(&more.stdout).contains("resuming after frame 1"));
    let r = record(&d.join("fit/body.npz.fit.json"));
    assert_eq!(r["frames"].as_array().unwrap().len(), 3);
    // Other settings on the same output are refused rather than mixed in.
    let other = fit(&["--out", "fit/body.npz", "--no-shape"]);
    assert!(!other.status.success());
    assert!(String::from_utf8_lossy(&other.stderr).contains("other settings"));

    // The capture's own parameter file is not f3g fit's: refused, and left as it was.
    let truth = std::fs::read(d.join("cap/body_params.npz")).unwrap();
    let refused = fit(&["--out", "cap/body_params.npz", "--frames", "1"]);
    assert!(!refused.status.success());
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("was not written by `f3g fit`"),
        "{}",
        String::from_utf8_lossy(&refused.stderr)
    );
    assert_eq!(std::fs::read(d.join("cap/body_params.npz")).unwrap(), truth);

    // Keypoints projected from the truth with pixel noise, read back as OpenPose JSON.
    ok(&f3g_in(
        d,
        &["data", "keypoints", "cap", "--out", "kp", "--noise", "1"],
    ));
    assert!(d.join("kp/cam00/00000002_keypoints.json").is_file());
    ok(&fit(&[
        "--out",
        "k.npz",
        "--frames",
        "1",
        "--keypoints",
        "kp",
    ]));
    let r = record(&d.join("k.npz.fit.json"));
    let joint = r["against_capture"]["joint_m"].as_f64().unwrap();
    assert!(joint < 0.03, "with keypoints: mean joint error {joint} m");
    // A keypoint folder with nothing for these cameras is an error naming what it expected.
    std::fs::create_dir_all(d.join("empty")).unwrap();
    let none = fit(&["--out", "e.npz", "--keypoints", "empty"]);
    assert!(!none.status.success());
    assert!(String::from_utf8_lossy(&none.stderr).contains("_keypoints.json"));
}
