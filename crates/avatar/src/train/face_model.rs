//! The canonical face model `𝒢` of paper §3.3: the body branch's attributes averaged over
//! `face_init_frames` training frames (each seen from a training camera), then blended into
//! the densified face texels, with scales divided by the densification factor. Built once,
//! when the first face stage begins, from the body networks trained so far.

use burn::module::Module;
use burn::tensor::Device;

use super::config::TrainConfig;
use crate::AvatarError;
use crate::model::Setup;
use crate::model::{AvatarNets, BodyNets, Constants, FaceBase, body_attributes_host, body_outputs};
use f3g_data::Dataset;
use f3g_data::split::Split;

/// Builds `𝒢` from `body` (evaluated without autodiff on `device`).
pub fn build(
    setup: &Setup,
    config: &TrainConfig,
    body: &BodyNets,
    dataset: &Dataset,
    split: &Split,
    device: &Device,
) -> Result<FaceBase, AvatarError> {
    let head = setup.head.as_ref().ok_or_else(|| {
        AvatarError::Invalid("the canonical face model needs the face branch's head maps".into())
    })?;
    let k = config.face_init_frames.min(split.frames.len()).max(1);
    let plain = device.clone().without_autodiff();
    let nets = AvatarNets {
        body: body.valid(),
        face: None,
    };
    let constants = Constants::new(setup, &config.model, None, &plain);
    let n = setup.body_count();
    let mut sum = [
        vec![0.0f64; 3 * n],
        vec![0.0f64; 3 * n],
        vec![0.0f64; n],
        vec![0.0f64; 3 * n],
        vec![0.0f64; 4 * n],
    ];
    for i in 0..k {
        let frame = split.frames[i * split.frames.len() / k];
        let camera = split.cameras[i % split.cameras.len()];
        let pose = setup.pose(&dataset.params[frame])?.upload(&plain);
        let inputs = constants.inputs(&pose, &dataset.cameras[camera].camera, None, None)?;
        let raw = body_outputs(&nets, &constants, &inputs)?;
        let a = body_attributes_host(&raw, &constants);
        for (acc, v) in sum.iter_mut().zip([
            &a.positions,
            &a.colours,
            &a.opacity_logits,
            &a.log_scales,
            &a.quats,
        ]) {
            for (s, x) in acc.iter_mut().zip(v) {
                *s += *x as f64 / k as f64;
            }
        }
    }
    let blend = |values: &[f64], cols: usize| -> Vec<f32> {
        head.sources
            .iter()
            .flat_map(|taps| {
                (0..cols).map(move |c| {
                    taps.iter()
                        .map(|&(g, w)| values[g * cols + c] * w as f64)
                        .sum::<f64>() as f32
                })
            })
            .collect()
    };
    let mut quats = blend(&sum[4], 4);
    for q in quats.chunks_exact_mut(4) {
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        q.iter_mut().for_each(|v| *v /= norm);
    }
    // The densified grid is `size / S` times finer: so are its Gaussians, or they would blur
    // the detail the face branch is there to add.
    let shrink = (head.size as f32 / head.crop[2] as f32).ln();
    Ok(FaceBase {
        positions: blend(&sum[0], 3),
        colours: blend(&sum[1], 3),
        opacity_logits: blend(&sum[2], 1),
        log_scales: blend(&sum[3], 3).iter().map(|s| s - shrink).collect(),
        quats,
    })
}
