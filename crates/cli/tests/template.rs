//! `f3g template` and `f3g posmaps` end to end.

use std::process::Command;

fn f3g() -> Command {
    Command::new(env!("CARGO_BIN_EXE_f3g"))
}

#[test]
fn builds_a_clothed_template_and_draws_its_maps() {
    let dir = tempfile::tempdir().unwrap();
    let out = f3g()
        .args(["template", "--clothes", "builtin:skirt", "--out", "t.npz"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("inpainted"));
    std::fs::write(
        dir.path().join("p.json"),
        r#"{"pose": {"jaw_rx": 0.3, "upperarm01.L_rz": 0.5}}"#,
    )
    .unwrap();
    let out = f3g()
        .args([
            "posmaps",
            "--template",
            "t.npz",
            "--out",
            "maps",
            "--resolution",
            "64",
            "--params",
            "p.json",
        ])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for name in [
        "canonical.png",
        "normals.png",
        "mask.png",
        "head.png",
        "posed.png",
        "head_posed.png",
    ] {
        let img = f3g_io::read_rgb(&dir.path().join("maps").join(name)).unwrap();
        assert!(img.data.iter().any(|&v| v > 0.0), "{name} is blank");
    }
    let (w, h) = f3g_io::image_size(&dir.path().join("maps/canonical.png")).unwrap();
    assert_eq!((w, h), (128, 64));
}

#[test]
fn bad_meshes_are_reported() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("empty.obj"), "# nothing\n").unwrap();
    let out = f3g()
        .args(["template", "--clothes", "empty.obj", "--out", "t.npz"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("empty.obj"));
    std::fs::write(
        dir.path().join("far.obj"),
        "v 10 0 0\nv 11 0 0\nv 10 1 0\nf 1 2 3\n",
    )
    .unwrap();
    let out = f3g()
        .args(["template", "--clothes", "far.obj", "--out", "t.npz"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("aligned with the canonical body"));
    assert!(!dir.path().join("t.npz").exists());
    std::fs::write(dir.path().join("broken.npz"), b"PK not really").unwrap();
    let out = f3g()
        .args(["posmaps", "--template", "broken.npz", "--out", "m"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("broken.npz"));
}
