//! Baking's steps 1 and 2 (module docs): the sample poses, and the networks' canonical
//! outputs at each as one row of `10·N` values.

use f3g_nets::init::standard_normal;
use glam::{Affine3A, Vec3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::{BakeOptions, CORRECTIVE_VALUES, pose_features};
use crate::AvatarError;
use crate::infer::{TrainedAvatar, evenly};
use crate::model::host_values;
use f3g_rig::{Rig, RigParams};
use f3g_splat::Camera;

/// The training poses (at most `options.poses`, spread evenly), each followed by
/// `options.perturbations` copies with every joint parameter that is neither the root's nor a
/// finger's moved by `N(0, σ²)`, σ = `options.spread_deg` (seeded by `options.seed`).
pub(super) fn sample_poses(
    rig: &Rig,
    poses: &[RigParams],
    options: &BakeOptions,
) -> Result<Vec<RigParams>, AvatarError> {
    let skip: Vec<usize> = rig
        .finger_params()?
        .into_iter()
        .chain(rig.root_params())
        .collect();
    let sigma = options.spread_deg.to_radians();
    let mut rng = ChaCha8Rng::seed_from_u64(options.seed);
    let mut samples: Vec<RigParams> = Vec::new();
    for p in evenly(poses, options.poses.max(1)) {
        samples.push(p.clone());
        for _ in 0..options.perturbations {
            let mut q = p.clone();
            for (i, v) in q.pose.iter_mut().enumerate() {
                if !skip.contains(&i) {
                    *v += sigma * standard_normal(&mut rng);
                }
            }
            samples.push(q);
        }
    }
    Ok(samples)
}

/// Four horizontal views of the avatar (front, sides, back) that its colours are averaged
/// over, so the corrective colours do not depend on one view.
pub(super) fn horizontal_views() -> Vec<Camera> {
    let centre = Vec3::new(0.0, 0.0, 0.0);
    [0.0f32, 90.0, 180.0, 270.0]
        .iter()
        .map(|deg| {
            let a = deg.to_radians();
            let eye = centre + 1000.0 * Vec3::new(a.sin(), 0.0, a.cos());
            Camera::look_at(
                eye.to_array().map(f64::from),
                centre.to_array().map(f64::from),
                [0.0, 1.0, 0.0],
                500.0,
                64,
                64,
            )
        })
        .collect()
}

/// The networks' canonical outputs over the samples: per sample one row of `10·N` values
/// (position without the body model's displacement, colour averaged over the views,
/// log-scale, opacity logit), its joints' skinning transforms and its pose features.
pub(super) struct SampleOutputs {
    pub rows: Vec<Vec<f32>>,
    pub skinning: Vec<Vec<Affine3A>>,
    pub features: Vec<Vec<f32>>,
}

/// The outputs of `avatar` (`n` Gaussians) at every sample pose, seen from `views` (the
/// first view's geometry), with the pose features of `feature_joints`.
pub(super) fn sample_outputs(
    avatar: &TrainedAvatar,
    samples: &[RigParams],
    views: &[Camera],
    n: usize,
    feature_joints: &[usize],
) -> Result<SampleOutputs, AvatarError> {
    let setup = &avatar.setup;
    let rig = &setup.rig;
    let s = samples.len();
    let root = rig
        .skeleton
        .joints()
        .iter()
        .position(|j| j.parent.is_none())
        .unwrap_or(0);
    let mut rows: Vec<Vec<f32>> = Vec::with_capacity(s);
    let mut sample_skinning: Vec<Vec<Affine3A>> = Vec::with_capacity(s);
    let mut features: Vec<Vec<f32>> = Vec::with_capacity(s);
    for params in samples {
        let mut colour = vec![0.0f32; 3 * n];
        let mut row = vec![0.0f32; CORRECTIVE_VALUES * n];
        let pose_views = avatar.views_of(params, false)?;
        for (v, camera) in views.iter().enumerate() {
            let (c, inputs) = pose_views.seen_from(camera)?;
            for (acc, x) in colour.iter_mut().zip(host_values(c.colours)) {
                *acc += x / views.len() as f32;
            }
            if v == 0 {
                let means = host_values(c.means);
                let displacement = host_values(inputs.displacement);
                let scales = host_values(c.log_scales);
                let opacity = host_values(c.opacity_logits);
                for g in 0..n {
                    let r = &mut row[g * CORRECTIVE_VALUES..(g + 1) * CORRECTIVE_VALUES];
                    for k in 0..3 {
                        r[k] = means[3 * g + k] - displacement[3 * g + k];
                        r[6 + k] = scales[3 * g + k];
                    }
                    r[9] = opacity[g];
                }
                let frame = setup.pose(params)?;
                features.push(pose_features(&frame.joints, root, feature_joints));
                sample_skinning.push(frame.joints);
            }
        }
        for g in 0..n {
            row[g * CORRECTIVE_VALUES + 3..g * CORRECTIVE_VALUES + 6]
                .copy_from_slice(&colour[3 * g..3 * g + 3]);
        }
        rows.push(row);
    }
    Ok(SampleOutputs {
        rows,
        skinning: sample_skinning,
        features,
    })
}
