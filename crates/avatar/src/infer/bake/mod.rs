//! A trained avatar baked into a linear model that any renderer with skinning can play: the
//! networks' canonical Gaussians at their mean over poses, linear blend skinning with four
//! influences per Gaussian, `K` linear pose correctives and the body model's expressions.
//!
//! How the pose-dependent part is baked ([`BakedAvatar::bake`], one function per step: steps 1
//! and 2 in `sampling.rs`, 3 and 5 in `correctives.rs`; the four influences in
//! `influences.rs`):
//!
//! 1. Sample poses: the run's training poses (at most [`BakeOptions::poses`], spread evenly)
//!    and, for each, [`BakeOptions::perturbations`] copies with every joint parameter that is
//!    neither the root's nor a finger's moved by `N(0, σ²)` (σ = [`BakeOptions::spread_deg`]).
//! 2. For each pose, the networks' canonical outputs per Gaussian — position without the
//!    body model's displacement (3), colour averaged over four horizontal views (3), each view
//!    weighted by how much of the Gaussian it shows at the canonical pose (so a face's colour
//!    is its colour seen from the front, not blended with what the networks give for it seen
//!    from behind the head; evenly with SH bands, which are fitted around the mean over all
//!    directions), log-scale (3), opacity logit (1) — as one vector of `10·N` values.
//! 3. PCA of those vectors, each attribute divided by its spread over all samples first (so
//!    metres, colours and logits weigh alike): the mean is the baked avatar, the first `K`
//!    components (scaled back to their units) its correctives.
//! 4. Pose features `f` that a player computes from its bone matrices alone: for every joint
//!    that is neither a finger joint nor the root, `R_root⁻¹ R_j − I` (9 values), with `R` the
//!    rotation of the joint's skinning transform `S_j = W_j(pose) · W_j(canonical)⁻¹`, so the
//!    features do not see the global rotation, like the networks' root-free input. Features
//!    that do not vary over the samples are left out.
//! 5. A ridge regression from the centred features to the samples' corrective weights:
//!    `w = M (f − f̄)`, `M = Wᵀ F (Fᵀ F + λ I)⁻¹` with `λ = ridge · tr(FᵀF) / F`.
//!
//! Rotations stay those of the canonical pose (quaternions do not blend linearly), and the SH
//! beyond degree 0 are fitted to the colour network at the canonical pose
//! ([`crate::infer::export::export_cloud`]); their degree-0 term is the mean colour. Expressions:
//! per expression of the body model, the displacement of every Gaussian by the expression at
//! weight 1 (exact: blend shapes are linear). Posing: positions `Σ_k w_k S_{j_k} x`, rotations
//! by the polar factor of the blended transform, scales unchanged. An avatar trained with the
//! light fixed in the world ([`BakedShading`]) keeps its colours as albedo (the networks'
//! outputs before the light) and shades them per pose from its turned normals.

mod correctives;
mod influences;
mod sampling;

use glam::{Affine3A, Mat3, Quat, Vec3};

use crate::AvatarError;
use crate::infer::TrainedAvatar;
use crate::infer::export::{ExportOptions, Up, export_cloud};
use crate::model::host_values;
use correctives::{corrective_pca, ridge_map};
use f3g_rig::{Posed, Rig, RigParams, SkinWeights};
use f3g_splat::{Camera, GaussianCloud};
use influences::four_influences;
use sampling::{horizontal_views, sample_outputs, sample_poses, view_weights};

/// Values per Gaussian in a corrective: position (3), colour (3), log-scale (3), opacity (1).
pub const CORRECTIVE_VALUES: usize = 10;
/// Skin influences kept per Gaussian (glTF's `JOINTS_0`/`WEIGHTS_0`, Spark's skinning).
pub const INFLUENCES: usize = 4;
/// The most correctives a bake may ask for.
pub const MAX_CORRECTIVES: usize = 256;

/// How to bake.
#[derive(Clone, Debug, PartialEq)]
pub struct BakeOptions {
    /// Pose correctives `K` (0: plain LBS of the mean avatar).
    pub correctives: usize,
    /// SH degree of the colour, 0..=3: above 0 the view-dependent part is fitted to the colour
    /// network at the canonical pose, a pose no training frame shows. Measured, that part
    /// costs the poses an avatar is played in more than it gives (BENCHMARKS, "The baked
    /// avatar's view-dependent colour"), so the default is 0: each pose's colour from the
    /// views that show each Gaussian (module docs, step 2), as the correctives carry it.
    pub sh_degree: usize,
    /// View directions of the SH fit.
    pub directions: usize,
    /// Training poses used (spread evenly over the run's).
    pub poses: usize,
    /// Perturbed copies of each pose.
    pub perturbations: usize,
    /// Standard deviation of the perturbation of each joint parameter, degrees.
    pub spread_deg: f32,
    /// Ridge strength relative to the features' mean variance.
    pub ridge: f64,
    /// Whether the body model's expressions become morph targets.
    pub expressions: bool,
    pub seed: u64,
}

impl Default for BakeOptions {
    fn default() -> Self {
        Self {
            correctives: 16,
            sh_degree: 0,
            directions: 48,
            poses: 60,
            perturbations: 3,
            spread_deg: 8.0,
            ridge: 1e-2,
            expressions: true,
            seed: 0,
        }
    }
}

/// A baked avatar (module docs). Arrays are flat and row-major over Gaussians.
#[derive(Clone, Debug)]
pub struct BakedAvatar {
    /// The body model (its joint transforms for body parameters) and its canonical pose.
    pub rig: Rig,
    pub canonical: RigParams,
    /// Canonical Gaussians: `[N, 3]` means, `[N, 4]` quaternions (w, x, y, z), `[N, 3]`
    /// log-scales, `[N]` opacity logits, `[N, (d+1)², 3]` SH.
    pub means: Vec<f32>,
    pub quats: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub opacity_logits: Vec<f32>,
    pub sh: Vec<f32>,
    pub sh_degree: usize,
    /// Four influences per Gaussian (weights summing to 1).
    pub skin_joints: Vec<[u16; INFLUENCES]>,
    pub skin_weights: Vec<[f32; INFLUENCES]>,
    /// `[K, N, 10]` corrective directions (module docs).
    pub correctives: Vec<f32>,
    /// Joints whose rotations are the pose features (9 values each), and which of those
    /// `9·J` values are used.
    pub feature_joints: Vec<usize>,
    pub feature_used: Vec<usize>,
    /// `[F]` mean of the used features over the samples, `[K, F]` the ridge map.
    pub feature_mean: Vec<f32>,
    pub feature_map: Vec<f32>,
    /// The body model's expression names and `[E, N, 3]` displacements at weight 1.
    pub expression_names: Vec<String>,
    pub expressions: Vec<f32>,
    /// Rig vertices of the head, the head crops' padding and side (evaluation).
    pub head_vertices: Vec<usize>,
    pub face_padding: f32,
    pub face_crop_size: usize,
    /// The training step of the networks it was baked from.
    pub step: u64,
    /// The light fixed in the world, for an avatar trained with one.
    pub shading: Option<BakedShading>,
}

/// A baked avatar's light fixed in the world ([`crate::model::shading`]): posing turns each
/// Gaussian's canonical normal by its skinning rotation, and the degree-0 colour is multiplied
/// by the shading of that normal (the higher SH bands are added unshaded).
#[derive(Clone, Debug, PartialEq)]
pub struct BakedShading {
    /// `[9, 3]` row-major (basis function, channel).
    pub coefficients: Vec<f32>,
    /// `[N, 3]` canonical unit normals.
    pub normals: Vec<f32>,
}

/// What baking measured.
#[derive(Clone, Debug, serde::Serialize)]
pub struct BakeReport {
    pub gaussians: usize,
    pub samples: usize,
    pub features: usize,
    /// Share of the samples' (normalised) variance the `K` correctives explain.
    pub explained_variance: f64,
    /// RMS over samples of the weights' ridge prediction error, relative to the weights' RMS.
    pub weight_fit_error: f64,
    /// Skin weight of the influences left out by keeping four: mean and largest over
    /// Gaussians; and what it costs: the RMS over the sample poses of each Gaussian's position
    /// error against all its influences (metres), mean and largest over Gaussians.
    pub dropped_weight_mean: f64,
    pub dropped_weight_max: f64,
    pub skin_error_mean: f64,
    pub skin_error_max: f64,
    /// SH fit to the colour network (RMS colour error on held-out directions).
    pub sh_rms: f64,
    pub seconds: f64,
}

/// The pose features of skinning transforms `S` (module docs, step 4): `R_root⁻¹ R_j − I`
/// row-major for each of `joints`.
pub fn pose_features(skinning: &[Affine3A], root: usize, joints: &[usize]) -> Vec<f32> {
    let rotation = |a: &Affine3A| {
        let m = Mat3::from(a.matrix3);
        Mat3::from_quat(Quat::from_mat3(&m).normalize())
    };
    let root_inverse = rotation(&skinning[root]).transpose();
    joints
        .iter()
        .flat_map(|&j| {
            let r = root_inverse * rotation(&skinning[j]) - Mat3::IDENTITY;
            r.transpose().to_cols_array()
        })
        .collect()
}

impl BakedAvatar {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity_logits.is_empty()
    }

    /// Number of pose correctives `K`.
    pub fn corrective_count(&self) -> usize {
        self.correctives.len() / (CORRECTIVE_VALUES * self.len()).max(1)
    }

    /// The root joint (the one without a parent that the features are relative to).
    pub fn root_joint(&self) -> usize {
        self.rig
            .skeleton
            .joints()
            .iter()
            .position(|j| j.parent.is_none())
            .unwrap_or(0)
    }

    /// The rig posed at the canonical pose, without root motion (what skinning is relative to).
    fn canonical_posed(&self) -> Result<Posed, AvatarError> {
        Ok(self
            .rig
            .pose(&f3g_template::without_root(&self.rig, &self.canonical))?)
    }

    /// Canonical-to-posed skinning transforms of every joint for body parameters.
    pub fn skinning(&self, params: &RigParams) -> Result<Vec<Affine3A>, AvatarError> {
        let canonical = self.canonical_posed()?;
        let posed = self.rig.pose(params)?;
        Ok(Rig::relative_transforms(&canonical, &posed))
    }

    /// The corrective weights the ridge map predicts from skinning transforms.
    pub fn corrective_weights(&self, skinning: &[Affine3A]) -> Vec<f32> {
        let all = pose_features(skinning, self.root_joint(), &self.feature_joints);
        let f = self.feature_used.len();
        let centred: Vec<f32> = self
            .feature_used
            .iter()
            .zip(&self.feature_mean)
            .map(|(&i, m)| all[i] - m)
            .collect();
        (0..self.corrective_count())
            .map(|k| {
                self.feature_map[k * f..(k + 1) * f]
                    .iter()
                    .zip(&centred)
                    .map(|(a, b)| a * b)
                    .sum()
            })
            .collect()
    }

    /// The Gaussians posed by body parameters (correctives and expressions applied, then
    /// LBS), as a 3DGS cloud.
    pub fn posed(&self, params: &RigParams) -> Result<GaussianCloud, AvatarError> {
        let n = self.len();
        let skinning = self.skinning(params)?;
        let weights = self.corrective_weights(&skinning);
        let mut means = self.means.clone();
        let mut log_scales = self.log_scales.clone();
        let mut opacity = self.opacity_logits.clone();
        let mut sh = self.sh.clone();
        let coeffs = f3g_splat::sh::num_coeffs(self.sh_degree);
        let dc = 1.0 / f3g_splat::sh::SH_C0 as f32;
        for (k, &w) in weights.iter().enumerate() {
            let basis =
                &self.correctives[k * n * CORRECTIVE_VALUES..(k + 1) * n * CORRECTIVE_VALUES];
            for g in 0..n {
                let b = &basis[g * CORRECTIVE_VALUES..(g + 1) * CORRECTIVE_VALUES];
                for c in 0..3 {
                    means[3 * g + c] += w * b[c];
                    sh[g * coeffs * 3 + c] += w * b[3 + c] * dc;
                    log_scales[3 * g + c] += w * b[6 + c];
                }
                opacity[g] += w * b[9];
            }
        }
        for (e, name) in self.expression_names.iter().enumerate() {
            let Some(i) = self.rig.expression.names.iter().position(|n| n == name) else {
                continue;
            };
            let w = params.expression.get(i).copied().unwrap_or(0.0);
            if w != 0.0 {
                let d = &self.expressions[e * n * 3..(e + 1) * n * 3];
                for (m, d) in means.iter_mut().zip(d) {
                    *m += w * d;
                }
            }
        }
        let skin = SkinWeights {
            joints: self
                .skin_joints
                .iter()
                .map(|j| std::array::from_fn(|k| if k < 4 { j[k] } else { 0 }))
                .collect(),
            weights: self
                .skin_weights
                .iter()
                .map(|w| std::array::from_fn(|k| if k < 4 { w[k] } else { 0.0 }))
                .collect(),
        };
        let transforms = f3g_rig::point_transforms(&skinning, &skin);
        let mut quats = self.quats.clone();
        for (g, t) in transforms.iter().enumerate() {
            let p = t
                .affine
                .transform_point3(Vec3::from_slice(&means[3 * g..3 * g + 3]));
            means[3 * g..3 * g + 3].copy_from_slice(&p.to_array());
            let q = &quats[4 * g..4 * g + 4];
            let r = t.rotation * Quat::from_xyzw(q[1], q[2], q[3], q[0]);
            quats[4 * g..4 * g + 4].copy_from_slice(&[r.w, r.x, r.y, r.z]);
            if let Some(light) = &self.shading {
                let normal = t.rotation * Vec3::from_slice(&light.normals[3 * g..3 * g + 3]);
                let s = crate::model::shading::shade_host(&light.coefficients, normal.to_array());
                for (c, s) in s.into_iter().enumerate() {
                    let f = &mut sh[g * coeffs * 3 + c];
                    *f = ((0.5 + *f / dc) * s - 0.5) * dc;
                }
            }
        }
        Ok(GaussianCloud {
            means,
            log_scales,
            quats,
            opacity_logits: opacity,
            sh,
            sh_degree: self.sh_degree,
        })
    }

    /// Renders body parameters from `camera` over `background` with f3g's CPU renderer.
    pub fn render(
        &self,
        params: &RigParams,
        camera: &Camera,
        background: [f32; 3],
    ) -> Result<f3g_io::Image, AvatarError> {
        let cloud = self.posed(params)?;
        let out = f3g_splat::cpu::render(
            &cloud.slices(),
            camera,
            background,
            &f3g_splat::RenderOptions::default(),
        )?;
        f3g_io::Image::from_vec(camera.width as usize, camera.height as usize, 3, out.color)
            .map_err(AvatarError::Invalid)
    }

    /// [`Self::render`]'s layers (colour over black, coverage, depth) for compositing.
    pub fn render_layers(
        &self,
        params: &RigParams,
        camera: &Camera,
    ) -> Result<super::eval::Layers, AvatarError> {
        let cloud = self.posed(params)?;
        let out = f3g_splat::cpu::render(
            &cloud.slices(),
            camera,
            [0.0; 3],
            &f3g_splat::RenderOptions::default(),
        )?;
        let color =
            f3g_io::Image::from_vec(camera.width as usize, camera.height as usize, 3, out.color)
                .map_err(AvatarError::Invalid)?;
        Ok(super::eval::Layers::new(color, out.alpha, out.depth))
    }

    /// Bakes `avatar` over the pose samples drawn from `poses` (module docs): samples the
    /// poses, takes the networks' outputs at each, their PCA, the ridge map from the pose
    /// features to the corrective weights, the expressions and four skin influences.
    pub fn bake(
        avatar: &TrainedAvatar,
        poses: &[RigParams],
        options: &BakeOptions,
    ) -> Result<(Self, BakeReport), AvatarError> {
        let start = std::time::Instant::now();
        if options.correctives > MAX_CORRECTIVES {
            return Err(AvatarError::config(
                "correctives",
                format!("{} is more than {MAX_CORRECTIVES}", options.correctives),
            ));
        }
        if poses.is_empty() {
            return Err(AvatarError::Invalid(
                "baking needs the run's training poses; none were given".into(),
            ));
        }
        let setup = &avatar.setup;
        let rig = &setup.rig;
        let canonical = setup.template.canonical.clone();
        // Reference: the canonical pose, with the SH fitted to the colour network there.
        let (reference, fit) = export_cloud(
            avatar,
            &canonical,
            false,
            &ExportOptions {
                degree: options.sh_degree,
                directions: options.directions,
                up: Up::Y,
                lit: false,
            },
        )?;
        let n = reference.len();
        let samples = sample_poses(rig, poses, options)?;
        let s = samples.len();
        f3g_io::memory::ensure_available(
            (s as u64 + options.correctives as u64 + 4) * (CORRECTIVE_VALUES * n) as u64 * 8,
            &format!("the pose correctives' PCA of {s} poses × {n} Gaussians"),
        )?;
        let views = horizontal_views();
        let feature_joints = feature_joints(rig)?;
        // SH bands are fitted around the mean over all directions, so with bands each view
        // keeps an even share (a colour weighted towards the views that see the Gaussian would
        // count its view dependence twice: 0.149 head LPIPS against 0.135, BENCHMARKS).
        let weights = if options.sh_degree == 0 {
            view_weights(&reference)?
        } else {
            vec![vec![1.0 / views.len() as f32; n]; views.len()]
        };
        let outputs = sample_outputs(avatar, &samples, &views, &weights, n, &feature_joints)?;
        let pca = corrective_pca(outputs.rows, n, options.correctives)?;
        let ridge = ridge_map(&outputs.features, &pca.weights, options.ridge)?;
        let mean = mean_gaussians(&pca.mean, &reference, options.sh_degree);
        let (expression_names, expressions) = if options.expressions {
            expression_displacements(avatar, &canonical, &views[0])?
        } else {
            (Vec::new(), Vec::new())
        };
        let points: Vec<Vec3> = mean.means.chunks_exact(3).map(Vec3::from_slice).collect();
        let skin = four_influences(&avatar.skin(), &points, &outputs.skinning);
        let report = BakeReport {
            gaussians: n,
            samples: s,
            features: ridge.used.len(),
            explained_variance: pca.explained,
            weight_fit_error: ridge.fit_error,
            dropped_weight_mean: skin.dropped.iter().map(|&d| d as f64).sum::<f64>()
                / n.max(1) as f64,
            dropped_weight_max: skin.dropped.iter().copied().fold(0.0f32, f32::max) as f64,
            skin_error_mean: skin.errors.iter().map(|&d| d as f64).sum::<f64>() / n.max(1) as f64,
            skin_error_max: skin.errors.iter().copied().fold(0.0f32, f32::max) as f64,
            sh_rms: fit.rms,
            seconds: start.elapsed().as_secs_f64(),
        };
        let baked = Self {
            rig: rig.clone(),
            canonical,
            means: mean.means,
            quats: reference.quats.clone(),
            log_scales: mean.log_scales,
            opacity_logits: mean.opacity_logits,
            sh: mean.sh,
            sh_degree: options.sh_degree,
            skin_joints: skin.joints,
            skin_weights: skin.weights,
            correctives: pca.basis,
            feature_joints,
            feature_used: ridge.used,
            feature_mean: ridge.mean,
            feature_map: ridge.map,
            expression_names,
            expressions,
            head_vertices: setup.head_vertices.clone(),
            face_padding: avatar.model.face_padding,
            face_crop_size: avatar.model.face_crop_size,
            step: avatar.step,
            shading: avatar.world_light(),
        };
        Ok((baked, report))
    }
}

/// The baked avatar's Gaussians apart from rotations: means, log-scales and opacity logits
/// of the samples' mean, the SH of the reference cloud with the mean colour as degree 0.
struct MeanGaussians {
    means: Vec<f32>,
    log_scales: Vec<f32>,
    opacity_logits: Vec<f32>,
    sh: Vec<f32>,
}

/// The mean avatar of `mean` (`[N, 10]` in the rows' units) with the reference's SH of
/// degree `sh_degree`.
fn mean_gaussians(mean: &[f64], reference: &GaussianCloud, sh_degree: usize) -> MeanGaussians {
    let n = reference.len();
    let mut means = vec![0.0f32; 3 * n];
    let mut log_scales = vec![0.0f32; 3 * n];
    let mut opacity = vec![0.0f32; n];
    let coeffs = f3g_splat::sh::num_coeffs(sh_degree);
    let mut sh = vec![0.0f32; n * coeffs * 3];
    let reference_k = f3g_splat::sh::num_coeffs(reference.sh_degree.max(3));
    for g in 0..n {
        let m = |i: usize| mean[g * CORRECTIVE_VALUES + i] as f32;
        for c in 0..3 {
            means[3 * g + c] = m(c);
            log_scales[3 * g + c] = m(6 + c);
        }
        opacity[g] = m(9);
        for l in 0..coeffs {
            for c in 0..3 {
                sh[(g * coeffs + l) * 3 + c] = reference.sh[(g * reference_k + l) * 3 + c];
            }
        }
        for c in 0..3 {
            sh[g * coeffs * 3 + c] = (m(3 + c) - 0.5) / f3g_splat::sh::SH_C0 as f32;
        }
    }
    MeanGaussians {
        means,
        log_scales,
        opacity_logits: opacity,
        sh,
    }
}

/// The body model's expressions (names) and the displacement of every Gaussian by each at
/// weight 1 (`[E, N, 3]`; exact, blend shapes being linear), from the canonical pose seen
/// from `front`.
fn expression_displacements(
    avatar: &TrainedAvatar,
    canonical: &RigParams,
    front: &Camera,
) -> Result<(Vec<String>, Vec<f32>), AvatarError> {
    let mut expression_names = Vec::new();
    let mut expressions = Vec::new();
    let (_, base) = avatar.canonical_with_inputs(canonical, front, false)?;
    let base = host_values(base.displacement);
    for (e, name) in avatar.setup.rig.expression.names.iter().enumerate() {
        let mut p = canonical.clone();
        p.expression[e] = 1.0;
        let (_, inputs) = avatar.canonical_with_inputs(&p, front, false)?;
        let d = host_values(inputs.displacement);
        expressions.extend(d.iter().zip(&base).map(|(a, b)| a - b));
        expression_names.push(name.clone());
    }
    Ok((expression_names, expressions))
}

/// Joints whose rotations are pose features: every joint but the root(s) and those below a
/// wrist (the networks see the hands at rest).
pub fn feature_joints(rig: &Rig) -> Result<Vec<usize>, AvatarError> {
    let wrists = [
        rig.role(f3g_rig::Role::LeftWrist)?,
        rig.role(f3g_rig::Role::RightWrist)?,
    ];
    let joints = rig.skeleton.joints();
    Ok((0..joints.len())
        .filter(|&j| joints[j].parent.is_some())
        .filter(|&j| {
            !wrists
                .iter()
                .any(|&w| w != j && rig.skeleton.is_ancestor_or_self(w, j))
        })
        .collect())
}
