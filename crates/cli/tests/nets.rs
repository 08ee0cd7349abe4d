//! `f3g bench nets`: `--only` picks networks by name, `--profile` splits a forward+backward
//! into its convolution phases (the weight gradient only where a weight is trained). And the
//! thread pool every command runs in.

mod common;

use common::{f3g_in, ok};

#[test]
fn the_profile_splits_a_network_into_convolution_phases() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(&f3g_in(
        d,
        &[
            "bench",
            "nets",
            "--only",
            "face cpu",
            "--profile",
            "--repeats",
            "2",
            "--json",
            "nets.json",
        ],
    ));
    let rows: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("nets.json")).unwrap()).unwrap();
    let rows = rows.as_array().unwrap();
    assert_eq!(rows.len(), 1, "{rows:?}");
    assert!(rows[0]["name"].as_str().unwrap().contains("face cpu"));
    let profile = &rows[0]["profile"];
    for phase in ["forward", "input_grad", "weight_grad"] {
        let p = &profile[phase];
        assert!(p["convolutions"].as_u64().unwrap() > 0, "{phase}: {p}");
        assert!(p["gflop"].as_f64().unwrap() > 0.0, "{phase}: {p}");
        assert!(p["ms"].as_f64().unwrap() > 0.0, "{phase}: {p}");
    }
    // The forward and each gradient do the same multiply-adds, convolution for convolution
    // (the first layer's input gradient is not needed: the input is not trained).
    let gflop = |phase: &str| profile[phase]["gflop"].as_f64().unwrap();
    assert!((gflop("forward") - gflop("weight_grad")).abs() < 1e-9);
    assert!(gflop("input_grad") < gflop("forward"));
    let parts: f64 = ["forward", "input_grad", "weight_grad"]
        .iter()
        .map(|p| profile[p]["ms"].as_f64().unwrap())
        .sum::<f64>()
        + profile["other_ms"].as_f64().unwrap();
    assert!((parts - profile["total_ms"].as_f64().unwrap()).abs() < 1e-6);
}

#[test]
fn only_matching_nothing_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let out = f3g_in(dir.path(), &["bench", "nets", "--only", "resnet"]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("--only") && stderr.contains("resnet"),
        "{stderr}"
    );
}

/// Every command runs on a worker of rayon's pool, which keeps at least two workers (one may
/// wait on the loader while the other serves the loader's parallel loops) and otherwise
/// follows `RAYON_NUM_THREADS`.
#[test]
fn commands_run_in_a_pool_of_at_least_two_threads() {
    let dir = tempfile::tempdir().unwrap();
    for (asked, expected) in [("1", "2 host threads"), ("3", "3 host threads")] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_f3g"))
            .args(["bench", "lbs", "--points", "1000", "--repeats", "1"])
            .env("RAYON_NUM_THREADS", asked)
            .current_dir(dir.path())
            .output()
            .unwrap();
        ok(&out);
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(
            stdout.contains(expected),
            "RAYON_NUM_THREADS={asked}: {stdout}"
        );
    }
}
