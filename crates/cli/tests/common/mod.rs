//! What the end-to-end tests share: running the binary, the success check, the tiny
//! training configuration and the largest difference between paired values.
#![allow(dead_code)]

use std::path::Path;
use std::process::{Command, Output};

/// Runs the `f3g` binary with `args` in `dir`.
pub fn f3g_in(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_f3g"))
        .args(args)
        .current_dir(dir)
        .output()
        .unwrap()
}

/// `(step, total loss)` of every line of a run's log (none when there is no log yet).
pub fn losses(run: &Path) -> Vec<(u64, f64)> {
    std::fs::read_to_string(run.join("log.jsonl"))
        .unwrap_or_default()
        .lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            (v["step"].as_u64().unwrap(), v["total"].as_f64().unwrap())
        })
        .collect()
}

/// The largest absolute difference between paired values.
pub fn worst_difference(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max)
}

/// Asserts that a command succeeded, showing its output when it did not.
pub fn ok(out: &Output) {
    assert!(
        out.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A 5-frame synthetic capture `cap` (128 px high) in `d` and `tiny.json`, the tiny
/// configuration with `steps` for the five stages.
pub fn tiny_capture(d: &Path, steps: [u64; 5]) {
    ok(&f3g_in(
        d,
        &[
            "synth",
            "--out",
            "cap",
            "--frames",
            "5",
            "--resolution",
            "128",
        ],
    ));
    std::fs::write(d.join("tiny.json"), tiny_config(steps, "")).unwrap();
}

/// The cpu preset shrunk so that a step takes a fraction of a second, with the paper's
/// adversarial loss (which the preset leaves out) so that runs go through the discriminator,
/// `steps` for pretrain, body, face_pretrain, joint and face_finetune, and `extra` keys
/// (`"key": value` pairs, each preceded by a comma) appended.
pub fn tiny_config(steps: [u64; 5], extra: &str) -> String {
    let [pretrain, body, face_pretrain, joint, face_finetune] = steps;
    format!(
        r#"{{
  "preset": "cpu",
  "map_resolution": 32,
  "body_net": {{"input_size": 16, "output_size": 32, "max_channels": 16, "channel_base": 256,
               "style_dim": 16, "middle_size": 4}},
  "face_net": {{"input_size": 16, "output_size": 16, "max_channels": 16, "channel_base": 128,
               "style_dim": 16, "middle_size": 4}},
  "face_crop_size": 32, "lpips_size": 32, "face_init_frames": 2, "adversarial": true,
  "discriminator": {{"resolution": 32, "max_channels": 16, "channel_base": 128}},
  "steps": {{"pretrain": {pretrain}, "body": {body}, "face_pretrain": {face_pretrain},
            "joint": {joint}, "face_finetune": {face_finetune}}}{extra}
}}"#
    )
}
