//! `f3g metrics` end to end: the JSON it prints, masks, and clear errors.

use std::process::Command;

fn f3g() -> Command {
    Command::new(env!("CARGO_BIN_EXE_f3g"))
}

fn example(name: &str) -> String {
    format!("{}/../nets/tests/data/{name}", env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn prints_psnr_ssim_and_lpips_as_json() {
    let out = f3g()
        .args(["metrics", &example("ex_ref.png"), &example("ex_p1.png")])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!((v["psnr"].as_f64().unwrap() - 13.8675).abs() < 1e-3, "{v}");
    // scikit-image's SSIM (the paper's) and the 3DGS one (tools/metrics_golden.py).
    assert!((v["ssim"].as_f64().unwrap() - 0.313156).abs() < 1e-5, "{v}");
    assert!(
        (v["ssim_3dgs"].as_f64().unwrap() - 0.37343).abs() < 1e-4,
        "{v}"
    );
    assert!((v["lpips"].as_f64().unwrap() - 0.1376).abs() < 1e-3, "{v}");
    assert_eq!(v["lpips_net"], "alex");
}

#[test]
fn a_mask_whitens_both_images_outside_it() {
    let dir = tempfile::tempdir().unwrap();
    let mask = dir.path().join("mask.png");
    f3g_io::write_png(&mask, &f3g_io::Image::filled(64, 64, 1, 0.0)).unwrap();
    let out = f3g()
        .args([
            "metrics",
            &example("ex_ref.png"),
            &example("ex_p0.png"),
            "--mask",
        ])
        .arg(&mask)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    // Everything is masked out: both images are white, hence identical.
    assert!((v["ssim"].as_f64().unwrap() - 1.0).abs() < 1e-5, "{v}");
    assert!(
        v["psnr"].is_null() || v["psnr"].as_f64().is_none_or(f64::is_infinite),
        "{v}"
    );
}

#[test]
fn bad_inputs_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let small = dir.path().join("small.png");
    f3g_io::write_png(&small, &f3g_io::Image::filled(8, 8, 3, 0.5)).unwrap();
    let out = f3g()
        .args(["metrics", &example("ex_ref.png")])
        .arg(&small)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(e.contains("small.png") && e.contains("same size"), "{e}");
    let broken = dir.path().join("broken.png");
    std::fs::write(&broken, b"\x89PNG truncated").unwrap();
    let out = f3g()
        .args(["metrics", &example("ex_ref.png")])
        .arg(&broken)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("broken.png"));
}
