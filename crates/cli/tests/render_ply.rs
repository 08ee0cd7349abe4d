//! `f3g render-ply` end to end: files in, PNG and `.npy` out, clear errors for bad input.

use std::path::Path;
use std::process::Command;

use f3g_splat::{Camera, GaussianCloud, RenderOptions, cpu, ply};

fn f3g() -> Command {
    Command::new(env!("CARGO_BIN_EXE_f3g"))
}

fn scene() -> GaussianCloud {
    let n = 50;
    let mut cloud = GaussianCloud {
        sh_degree: 1,
        ..Default::default()
    };
    for i in 0..n {
        let t = i as f32 / n as f32 * std::f32::consts::TAU;
        cloud
            .means
            .extend([0.5 * t.cos(), 0.4 * t.sin(), 0.1 * (3.0 * t).sin()]);
        cloud
            .log_scales
            .extend([0.05f32.ln(), 0.03f32.ln(), 0.04f32.ln()]);
        cloud.quats.extend([1.0, 0.1 * t.sin(), 0.0, 0.2]);
        cloud.opacity_logits.push(1.0);
        cloud.sh.extend([1.0, -0.5, 0.3]);
        cloud
            .sh
            .extend((0..9).map(|j| 0.1 * ((i + j) as f32).sin()));
    }
    cloud
}

fn write_inputs(dir: &Path) -> (GaussianCloud, Camera) {
    let cloud = scene();
    ply::write_ply(&dir.join("scene.ply"), &cloud).unwrap();
    let camera = Camera::look_at([0.3, 0.2, 2.5], [0.0; 3], [0.0, 1.0, 0.0], 120.0, 96, 80);
    std::fs::write(
        dir.join("cam.json"),
        serde_json::to_string(&camera).unwrap(),
    )
    .unwrap();
    (cloud, camera)
}

#[test]
fn renders_png_and_raw_values() {
    let dir = tempfile::tempdir().unwrap();
    let (cloud, camera) = write_inputs(dir.path());
    let status = f3g()
        .args([
            "render-ply",
            "--ply",
            "scene.ply",
            "--camera",
            "cam.json",
            "--out",
            "out.png",
        ])
        .args(["--background", "0.2,0.4,0.6", "--raw", "out.npy"])
        .current_dir(dir.path())
        .status()
        .unwrap();
    assert!(status.success());
    let png = f3g_io::read_rgb(&dir.path().join("out.png")).unwrap();
    assert_eq!((png.width, png.height), (96, 80));
    let (shape, raw) = f3g_io::read_npy_f32(&dir.path().join("out.npy")).unwrap();
    assert_eq!(shape, vec![80, 96, 3]);
    let expected = cpu::render(
        &cloud.slices(),
        &camera,
        [0.2, 0.4, 0.6],
        &RenderOptions::default(),
    )
    .unwrap();
    assert_eq!(raw, expected.color);
    // The PNG is the same image quantised to 8 bits.
    for (p, r) in png.data.iter().zip(&raw) {
        assert!((p - r.clamp(0.0, 1.0)).abs() <= 0.5 / 255.0 + 1e-6);
    }
    // Corners show the background, the centre shows Gaussians.
    assert_eq!(&raw[..3], &[0.2, 0.4, 0.6]);
}

#[test]
fn bad_inputs_fail_with_a_message() {
    let dir = tempfile::tempdir().unwrap();
    write_inputs(dir.path());
    std::fs::write(dir.path().join("bad_cam.json"), r#"{"K": [[1,0,0],[0,1,0],[0,0,1]], "R": [[1,0,0],[0,1,0],[0,0,1]], "t": [0,0,0], "width": 0, "height": 10}"#).unwrap();
    // The size that used to abort the process with a failed 120 GB allocation.
    std::fs::write(dir.path().join("huge_cam.json"), r#"{"K": [[500,0,320],[0,500,240],[0,0,1]], "R": [[1,0,0],[0,1,0],[0,0,1]], "t": [0,0,3], "width": 100000, "height": 100000}"#).unwrap();
    std::fs::write(
        dir.path().join("truncated.ply"),
        &std::fs::read(dir.path().join("scene.ply")).unwrap()[..500],
    )
    .unwrap();
    let cases: [(&[&str], &str); 6] = [
        (
            &["--ply", "missing.ply", "--camera", "cam.json"],
            "missing.ply",
        ),
        (
            &["--ply", "truncated.ply", "--camera", "cam.json"],
            "truncated",
        ),
        (&["--ply", "scene.ply", "--camera", "bad_cam.json"], "empty"),
        (
            &["--ply", "scene.ply", "--camera", "huge_cam.json"],
            "image size (width 100000, height 100000) is too large",
        ),
        (&["--ply", "scene.ply", "--camera", "scene.ply"], "cam"),
        (
            &[
                "--ply",
                "scene.ply",
                "--camera",
                "cam.json",
                "--background",
                "1,2",
            ],
            "three",
        ),
    ];
    for (args, needle) in cases {
        let out = f3g()
            .arg("render-ply")
            .args(args)
            .args(["--out", "x.png"])
            .current_dir(dir.path())
            .output()
            .unwrap();
        assert!(!out.status.success(), "{args:?} should fail");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            stderr.contains(needle),
            "{args:?}: expected `{needle}` in: {stderr}"
        );
        assert!(!stderr.contains("panicked"), "{args:?} panicked: {stderr}");
    }
    assert!(!dir.path().join("x.png").exists());
}

#[test]
fn every_command_has_help() {
    for args in [
        &["--help"][..],
        &["render-ply", "--help"],
        &["bench", "--help"],
        &["bench", "splat", "--help"],
    ] {
        let out = f3g().args(args).output().unwrap();
        assert!(out.status.success(), "{args:?}");
        assert!(
            String::from_utf8_lossy(&out.stdout).contains("Usage"),
            "{args:?}"
        );
    }
}

#[test]
fn absurd_sizes_are_refused_when_the_command_line_is_parsed() {
    let dir = tempfile::tempdir().unwrap();
    let cases: [(&[&str], &str); 17] = [
        (
            &["synth", "--out", "cap", "--resolution", "100000"],
            "--resolution",
        ),
        (
            &["synth", "--out", "cap", "--cameras", "100000"],
            "--cameras",
        ),
        (
            &["synth", "--out", "cap", "--frames", "100000000"],
            "--frames",
        ),
        (&["demo", "--resolution", "100000"], "--resolution"),
        (&["demo", "--frames", "100000000"], "--frames"),
        (
            &[
                "posmaps",
                "--template",
                "t.npz",
                "--out",
                "m",
                "--resolution",
                "1000000",
            ],
            "--resolution",
        ),
        (
            &[
                "template",
                "reconstruct",
                "--data",
                "cap",
                "--frame",
                "0",
                "--out",
                "g.obj",
                "--resolution",
                "100000",
            ],
            "--resolution",
        ),
        (&["bench", "lbs", "--points", "1000000000000"], "--points"),
        (
            &["bench", "splat", "--resolutions", "512,100000"],
            "--resolutions",
        ),
        (
            &["bench", "splat", "--gaussians", "100000000000"],
            "--gaussians",
        ),
        (&["bench", "nets", "--image", "100000"], "--image"),
        (&["eval", "run", "--face-size", "100000"], "--face-size"),
        (&["eval", "run", "--lpips-size", "100000"], "--lpips-size"),
        (&["eval", "run", "--scale", "1e9"], "--scale"),
        (
            &[
                "export-ply",
                "run",
                "--out",
                "a.ply",
                "--directions",
                "100000000",
            ],
            "--directions",
        ),
        (
            &["animate", "run", "--out", "a", "--size", "100000x100000"],
            "--size",
        ),
        (
            &["data", "show", "cap", "--out", "s.png", "--thumb", "100000"],
            "--thumb",
        ),
    ];
    for (args, flag) in cases {
        let out = f3g().args(args).current_dir(dir.path()).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} should fail");
        assert!(
            stderr.contains("invalid value") && stderr.contains(flag),
            "{args:?}: {stderr}"
        );
    }
    // Nothing was created.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}
