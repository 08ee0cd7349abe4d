//! The PyTorch twin of the `paper` step (`tools/paper_step_torch.py`, issue #47) runs, and its
//! networks are f3g's: a CPU smoke run of its `--small` sizes (the `cpu` preset's networks)
//! must finish with finite losses, draw Gaussians in both renders, time every phase, and
//! build networks and a discriminator with exactly the parameter counts of f3g's own.
//!
//! Ignored by default: it needs Python with PyTorch and gsplat 1.5.3 (whose pure-PyTorch
//! projection the twin's CPU stand-in renderer loads). CI installs both from PyPI into a
//! virtual environment and runs `F3G_TORCH_PYTHON=VENV/bin/python cargo test --release
//! --workspace --test torch_twin -- --ignored` (`--workspace`, not `-p f3g-nets`: the features
//! of the README's test build, whose test binary this is; `-p` alone compiles Burn again).

use std::path::Path;
use std::process::Command;

use burn::module::Module;
use burn::tensor::Device;
use f3g_nets::{DiscriminatorConfig, StyleUNetConfig};
use serde_json::Value;

/// f3g's parameter counts of the twin's six networks, in its order (body position, colour
/// with the view, other; face the same), each on the 6-channel posed maps.
fn f3g_network_parameters(device: &Device) -> Vec<usize> {
    let nets = [
        StyleUNetConfig::cpu_body(3, false),
        StyleUNetConfig::cpu_body(3, true),
        StyleUNetConfig::cpu_body(8, false),
        StyleUNetConfig::cpu_face(3, false),
        StyleUNetConfig::cpu_face(3, true),
        StyleUNetConfig::cpu_face(8, false),
    ];
    nets.into_iter()
        .map(|mut c| {
            c.in_channels = 6;
            c.init(0, device).unwrap().num_params()
        })
        .collect()
}

fn numbers(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap_or_else(|| panic!("expected an array, got {v}"))
        .iter()
        .map(|x| x.as_f64().unwrap_or_else(|| panic!("not a number: {x}")))
        .collect()
}

#[test]
#[ignore = "needs Python with PyTorch and gsplat 1.5.3 (F3G_TORCH_PYTHON)"]
fn the_torch_twin_runs_a_small_step_with_the_networks_of_f3g() {
    let python = std::env::var("F3G_TORCH_PYTHON").unwrap_or_else(|_| "python3".into());
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("step.json");
    // One warm-up step and two timed ones: the optimisers' first updates run, and the
    // discriminator's lazy R1 falls on the warm-up step (its first).
    let out = Command::new(&python)
        .arg(root.join("tools/paper_step_torch.py"))
        .args([
            "--device", "cpu", "--small", "--warmup", "1", "--steps", "2",
        ])
        .arg("--json")
        .arg(&json)
        .output()
        .unwrap_or_else(|e| panic!("running {python}: {e}"));
    assert!(
        out.status.success(),
        "the twin failed ({}):\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    let report: Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();

    let device = Device::flex();
    let f3g: Vec<f64> = f3g_network_parameters(&device)
        .into_iter()
        .map(|n| n as f64)
        .collect();
    assert_eq!(numbers(&report["network_parameters"]), f3g);
    let discriminator = DiscriminatorConfig::cpu(32)
        .init(0, &device)
        .unwrap()
        .num_params();
    assert_eq!(
        report["discriminator_parameters"].as_f64(),
        Some(discriminator as f64)
    );

    // Loss terms: body L1, body LPIPS, offsets, face L1, face LPIPS, adversarial.
    let terms = numbers(&report["loss_terms"]);
    assert_eq!(terms.len(), 6, "{terms:?}");
    assert!(
        terms.iter().all(|t| t.is_finite() && *t >= 0.0),
        "{terms:?}"
    );
    assert!(terms[0] > 0.0 && terms[3] > 0.0, "{terms:?}");
    for render in ["body", "head"] {
        let hits = report["intersections"][render].as_f64().unwrap();
        assert!(hits > 0.0, "no Gaussian reached the {render} render");
    }
    let phases = report["phases"]["phases"].as_array().unwrap();
    let names: Vec<&str> = phases.iter().map(|p| p[0].as_str().unwrap()).collect();
    assert_eq!(
        names,
        [
            "data",
            "inputs",
            "networks",
            "render",
            "lpips",
            "adversarial",
            "readback",
            "backward",
            "optimiser",
            "discriminator"
        ]
    );
    for p in phases {
        if [
            "networks",
            "render",
            "backward",
            "optimiser",
            "discriminator",
        ]
        .contains(&p[0].as_str().unwrap())
        {
            assert!(p[1].as_f64().unwrap() > 0.0, "phase {p} took no time");
        }
    }
    assert!(report["step_ms"].as_f64().unwrap() > 0.0);
}
