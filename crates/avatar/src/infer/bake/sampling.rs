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
use f3g_splat::{Camera, GaussianCloud};

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

/// The directions towards the four horizontal views (front, sides, back).
const HORIZONTAL_DEGREES: [f32; 4] = [0.0, 90.0, 180.0, 270.0];

/// Unit direction towards the horizontal view at `deg` degrees about +Y from the front (+Z).
fn horizontal(deg: f32) -> Vec3 {
    let a = deg.to_radians();
    Vec3::new(a.sin(), 0.0, a.cos())
}

/// Four horizontal views of the avatar (front, sides, back) that its colours are averaged
/// over ([`view_weights`]), so the corrective colours do not depend on one view.
pub(super) fn horizontal_views() -> Vec<Camera> {
    let centre = Vec3::new(0.0, 0.0, 0.0);
    HORIZONTAL_DEGREES
        .iter()
        .map(|&deg| {
            let eye = centre + 1000.0 * horizontal(deg);
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

/// Side in pixels of the renders that measure how much of each Gaussian a view shows.
const VISIBILITY_PIXELS: u32 = 256;
/// The weight a view keeps in a Gaussian's colour where it shows nothing of it, relative to
/// the view that shows most of it (not zero, so that no Gaussian's colour is left undefined).
const HIDDEN_WEIGHT: f32 = 0.02;

/// Per Gaussian of `cloud`, the weights of the [`horizontal_views`] in its colour (summing to
/// one): what each view shows of the Gaussian (`Σ αᵢTᵢ` over a render's pixels from far along
/// the view's direction, framing the whole cloud: the gradient of the summed image with
/// respect to the Gaussian's colour) over what the view that shows most of it shows, plus
/// [`HIDDEN_WEIGHT`]; equal weights for a Gaussian no view shows. `[views][N]`.
pub(super) fn view_weights(cloud: &GaussianCloud) -> Result<Vec<Vec<f32>>, AvatarError> {
    let n = cloud.len();
    let points = || cloud.means.chunks_exact(3).map(Vec3::from_slice);
    let centre = points().fold(Vec3::ZERO, |a, p| a + p) / n.max(1) as f32;
    let radius = points()
        .map(|p| p.distance(centre))
        .fold(0.0f32, f32::max)
        .max(1e-3) as f64;
    // Far enough that every Gaussian sees the camera within 3° of the view's direction, and
    // the nearest points of the cloud still inside the frame.
    let distance = 20.0 * radius;
    let focal = 0.45 * VISIBILITY_PIXELS as f64 * (distance - radius) / radius;
    let sh = vec![0.0f32; 3 * n];
    let slices = f3g_splat::semantics::GaussianSlices {
        sh: &sh,
        ..cloud.slices()
    };
    let options = f3g_splat::RenderOptions::default();
    let pixels = (VISIBILITY_PIXELS * VISIBILITY_PIXELS) as usize;
    let mut colour_grad = vec![0.0f32; 3 * pixels];
    colour_grad.iter_mut().step_by(3).for_each(|g| *g = 1.0);
    let zeros = vec![0.0f32; pixels];
    let centre = centre.as_dvec3();
    let seen: Vec<Vec<f32>> = HORIZONTAL_DEGREES
        .iter()
        .map(|&deg| {
            let camera = Camera::look_at(
                (centre + distance * horizontal(deg).as_dvec3()).to_array(),
                centre.to_array(),
                [0.0, 1.0, 0.0],
                focal,
                VISIBILITY_PIXELS,
                VISIBILITY_PIXELS,
            );
            let forward = f3g_splat::cpu::render(&slices, &camera, [0.0; 3], &options)?;
            let grads = f3g_splat::cpu::rasterize_backward(
                &forward,
                &camera,
                &options,
                &f3g_splat::cpu::PixelGrads {
                    color: &colour_grad,
                    alpha: &zeros,
                    depth: &zeros,
                },
            );
            Ok::<_, AvatarError>(grads.screen.iter().map(|s| s.color[0]).collect())
        })
        .collect::<Result<_, _>>()?;
    let mut weights = vec![vec![0.0f32; n]; seen.len()];
    for g in 0..n {
        let most = seen.iter().map(|v| v[g]).fold(0.0f32, f32::max);
        let raw = |v: &Vec<f32>| {
            if most > 0.0 {
                v[g] / most + HIDDEN_WEIGHT
            } else {
                1.0
            }
        };
        let total: f32 = seen.iter().map(raw).sum();
        for (w, v) in weights.iter_mut().zip(&seen) {
            w[g] = raw(v) / total;
        }
    }
    Ok(weights)
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
/// first view's geometry; the colour averaged over the views with `view_weights`,
/// `[views][n]`), with the pose features of `feature_joints`.
pub(super) fn sample_outputs(
    avatar: &TrainedAvatar,
    samples: &[RigParams],
    views: &[Camera],
    view_weights: &[Vec<f32>],
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
            let weights = &view_weights[v];
            for (g, (acc, x)) in colour
                .chunks_exact_mut(3)
                .zip(host_values(c.colours).chunks_exact(3))
                .enumerate()
            {
                for (a, x) in acc.iter_mut().zip(x) {
                    *a += weights[g] * x;
                }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Two opaque Gaussians on the line of sight of the front view: a large one in front of
    /// the centre (+Z, 20 cm standard deviation) and a small one behind it (−Z, 3 cm).
    fn scene() -> GaussianCloud {
        GaussianCloud {
            means: vec![0.0, 0.0, 0.5, 0.0, 0.0, -0.5],
            log_scales: [[0.2f32.ln(); 3], [0.03f32.ln(); 3]].concat(),
            quats: [1.0, 0.0, 0.0, 0.0].repeat(2),
            opacity_logits: vec![6.0; 2],
            sh: vec![0.0; 6],
            sh_degree: 0,
        }
    }

    #[test]
    fn a_gaussian_takes_its_colour_from_the_views_that_show_it() {
        let w = view_weights(&scene()).unwrap();
        let [front, side, back, other_side] = [0, 1, 2, 3];
        assert_eq!(w.len(), HORIZONTAL_DEGREES.len());
        for g in 0..2 {
            let total: f32 = w.iter().map(|v| v[g]).sum();
            assert!(
                (total - 1.0).abs() < 1e-5,
                "Gaussian {g}: weights sum to {total}"
            );
        }
        // The large Gaussian hides the small one from the front view only.
        for seen_from in [side, back, other_side] {
            assert!(w[seen_from][1] > 10.0 * w[front][1], "{w:?}");
        }
        // The small one hides little of the large one: every view shows it.
        assert!(w.iter().all(|v| v[0] > 0.1), "{w:?}");
    }
}
