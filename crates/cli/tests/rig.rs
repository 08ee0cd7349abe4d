//! `f3g rig show` and `f3g rig fit` end to end on the built-in human.

use std::process::Command;

use f3g_rig::{builtin, sequence};

fn f3g() -> Command {
    Command::new(env!("CARGO_BIN_EXE_f3g"))
}

#[test]
fn show_writes_a_posed_obj() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("p.json"),
        r#"{"pose": {"jaw_rx": 0.3, "root_ty": 0.5}, "expression": {"eye-left-closure": 1.0}}"#,
    )
    .unwrap();
    let out = f3g()
        .args(["rig", "show", "--params", "p.json", "--out", "posed.obj"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mesh = f3g_rig::obj::read_obj(&dir.path().join("posed.obj")).unwrap();
    let h = builtin::load().unwrap();
    assert_eq!(mesh.vertices.len(), h.rig.mesh.vertices.len());
    // root_ty lifts the body by 0.5 m.
    let lowest = |v: &[glam::Vec3]| v.iter().map(|p| p.y).fold(f32::MAX, f32::min);
    assert!((lowest(&mesh.vertices) - lowest(&h.rig.mesh.vertices) - 0.5).abs() < 1e-3);

    std::fs::write(
        dir.path().join("bad.json"),
        r#"{"pose": {"knee_bend": 0.3}}"#,
    )
    .unwrap();
    let out = f3g()
        .args(["rig", "show", "--params", "bad.json", "--out", "x.obj"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("bad.json") && err.contains("pose.knee_bend"),
        "{err}"
    );
    let out = f3g()
        .args([
            "rig",
            "show",
            "--model",
            "smplx:missing.npz",
            "--out",
            "x.obj",
        ])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("missing.npz"));
}

#[test]
fn fit_recovers_a_sequence_of_the_same_model() {
    let dir = tempfile::tempdir().unwrap();
    let h = builtin::load().unwrap();
    let rig = &h.rig;
    let names = rig.pose_param_names();
    let frames: Vec<_> = (0..3)
        .map(|f| {
            let mut p = rig.zero_params();
            p.pose[names.iter().position(|n| n == "upperarm01.L_rz").unwrap()] = 0.2 * f as f32;
            p.pose[names.iter().position(|n| n == "lowerleg01.R_rx").unwrap()] = 0.15 * f as f32;
            p.pose[names.iter().position(|n| n == "root_ry").unwrap()] = 0.1;
            p
        })
        .collect();
    sequence::write(&dir.path().join("src.npz"), rig, &frames).unwrap();
    let out = f3g()
        .args([
            "rig",
            "fit",
            "--from",
            "builtin",
            "--params",
            "src.npz",
            "--to",
            "builtin",
            "--out",
            "fitted.npz",
        ])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("residuals: mean vertex RMS"), "{stdout}");
    let fitted = sequence::read(&dir.path().join("fitted.npz"), rig).unwrap();
    assert_eq!(fitted.len(), 3);
    for (a, b) in fitted.iter().zip(&frames) {
        let (pa, pb) = (rig.pose(a).unwrap(), rig.pose(b).unwrap());
        let worst = pa
            .vertices
            .iter()
            .zip(&pb.vertices)
            .map(|(x, y)| (*x - *y).length())
            .fold(0.0, f32::max);
        assert!(worst < 5e-3, "largest vertex error {worst} m");
    }
}
