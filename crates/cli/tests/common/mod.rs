//! What the end-to-end tests of training share: the success check and the tiny configuration.
#![allow(dead_code)]

use std::process::Output;

/// Asserts that a command succeeded, showing its output when it did not.
pub fn ok(out: &Output) {
    assert!(
        out.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The cpu preset shrunk so that a step takes a fraction of a second, with `steps` for
/// pretrain, body, face_pretrain, joint and face_finetune, and `extra` keys (`"key": value`
/// pairs, each preceded by a comma) appended.
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
  "face_crop_size": 32, "lpips_size": 32, "face_init_frames": 2,
  "discriminator": {{"resolution": 32, "max_channels": 16, "channel_base": 128}},
  "steps": {{"pretrain": {pretrain}, "body": {body}, "face_pretrain": {face_pretrain},
            "joint": {joint}, "face_finetune": {face_finetune}}}{extra}
}}"#
    )
}
