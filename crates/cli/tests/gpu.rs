//! The `f3g` binary on a wgpu device (Mesa lavapipe in CI): `render-ply --device wgpu` gives
//! the CPU's image, `bench splat --device wgpu` measures and writes its JSON, and a missing
//! adapter is an error that lists the ones there are. Run with `cargo test --release -p
//! f3g-cli --features gpu --test gpu`.
#![cfg(feature = "gpu")]

use std::process::Command;

use f3g_splat::{Camera, GaussianCloud, ply};

fn f3g() -> Command {
    Command::new(env!("CARGO_BIN_EXE_f3g"))
}

/// A ring of 300 overlapping Gaussians with SH degree 3.
fn scene() -> GaussianCloud {
    let n = 300;
    let mut cloud = GaussianCloud {
        sh_degree: 3,
        ..Default::default()
    };
    for i in 0..n {
        let t = i as f32 / n as f32 * std::f32::consts::TAU;
        cloud
            .means
            .extend([0.5 * t.cos(), 0.4 * t.sin(), 0.1 * (3.0 * t).sin()]);
        cloud
            .log_scales
            .extend([0.06f32.ln(), 0.03f32.ln(), 0.045f32.ln()]);
        cloud.quats.extend([1.0, 0.3 * t.sin(), 0.1, 0.2 * t.cos()]);
        cloud.opacity_logits.push(0.5 + (5.0 * t).sin());
        cloud.sh.extend([1.0, -0.5 + 0.3 * t.cos(), 0.3]);
        cloud
            .sh
            .extend((0..45).map(|j| 0.1 * ((i * 7 + j) as f32).sin()));
    }
    cloud
}

#[test]
fn render_ply_on_wgpu_gives_the_cpu_image() {
    let dir = tempfile::tempdir().unwrap();
    ply::write_ply(&dir.path().join("scene.ply"), &scene()).unwrap();
    let camera = Camera::look_at([0.3, 0.2, 2.5], [0.0; 3], [0.0, 1.0, 0.0], 120.0, 96, 80);
    std::fs::write(
        dir.path().join("cam.json"),
        serde_json::to_string(&camera).unwrap(),
    )
    .unwrap();
    let mut images = Vec::new();
    for device in ["cpu", "wgpu"] {
        let out = f3g()
            .args(["render-ply", "--ply", "scene.ply", "--camera", "cam.json"])
            .args(["--out", &format!("{device}.png")])
            .args(["--raw", &format!("{device}.npy"), "--device", device])
            .args(["--background", "0.1,0.2,0.3"])
            .current_dir(dir.path())
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{device}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let (shape, raw) = f3g_io::read_npy_f32(&dir.path().join(format!("{device}.npy"))).unwrap();
        assert_eq!(shape, vec![80, 96, 3]);
        images.push(raw);
    }
    let differs = images[0]
        .iter()
        .zip(&images[1])
        .filter(|(a, b)| (*a - *b).abs() > 1e-5 * (1.0 + a.abs()))
        .count();
    assert_eq!(differs, 0, "{differs} values differ by more than 1e-5");
    assert!(
        images[0].iter().any(|&v| v > 0.5),
        "the ring is not in view"
    );
}

#[test]
fn bench_splat_on_wgpu_writes_its_measurements() {
    let dir = tempfile::tempdir().unwrap();
    let out = f3g()
        .args(["bench", "splat", "--device", "wgpu", "--gaussians", "2000"])
        .args([
            "--resolutions",
            "64,96x48",
            "--repeats",
            "1",
            "--json",
            "b.json",
        ])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("b.json")).unwrap()).unwrap();
    assert_eq!(doc["device"], "wgpu");
    let cases = doc["cases"].as_array().unwrap();
    assert_eq!(cases.len(), 2);
    assert_eq!(
        (cases[1]["width"].as_u64(), cases[1]["height"].as_u64()),
        (Some(96), Some(48))
    );
    for c in cases {
        assert!(c["forward_backward_ms"].as_f64().unwrap() > 0.0, "{c}");
        assert!(c["evaluations"].as_u64().unwrap() > 0, "{c}");
        assert!(c["intersections"].as_u64().unwrap() > 0, "{c}");
    }
}

#[test]
fn a_missing_adapter_is_an_error_listing_the_adapters() {
    let dir = tempfile::tempdir().unwrap();
    ply::write_ply(&dir.path().join("scene.ply"), &scene()).unwrap();
    let camera = Camera::look_at([0.3, 0.2, 2.5], [0.0; 3], [0.0, 1.0, 0.0], 120.0, 32, 32);
    std::fs::write(
        dir.path().join("cam.json"),
        serde_json::to_string(&camera).unwrap(),
    )
    .unwrap();
    let out = f3g()
        .args(["render-ply", "--ply", "scene.ply", "--camera", "cam.json"])
        .args(["--out", "x.png", "--device", "wgpu:99"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("there is no wgpu:99") && stderr.contains("adapters"),
        "{stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
}
