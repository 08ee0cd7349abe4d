//! A trained avatar baked into a linear model that any renderer with skinning can play: the
//! networks' canonical Gaussians at their mean over poses, linear blend skinning with four
//! influences per Gaussian, `K` linear pose correctives and the body model's expressions.
//!
//! How the pose-dependent part is baked:
//!
//! 1. Sample poses: the run's training poses (at most [`BakeOptions::poses`], spread evenly)
//!    and, for each, [`BakeOptions::perturbations`] copies with every joint parameter that is
//!    neither the root's nor a finger's moved by `N(0, σ²)` (σ = [`BakeOptions::spread_deg`]).
//! 2. For each pose, the networks' canonical outputs per Gaussian — position without the
//!    body model's displacement (3), colour averaged over four horizontal views (3), log-scale
//!    (3), opacity logit (1) — as one vector of `10·N` values.
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
//! ([`crate::export::export_cloud`]); their degree-0 term is the mean colour. Expressions:
//! per expression of the body model, the displacement of every Gaussian by the expression at
//! weight 1 (exact: blend shapes are linear). Posing: positions `Σ_k w_k S_{j_k} x`, rotations
//! by the polar factor of the blended transform, scales unchanged.

use faer::linalg::solvers::Solve;
use glam::{Affine3A, Mat3, Quat, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::AvatarError;
use crate::export::{ExportOptions, Up, export_cloud};
use crate::trained::TrainedAvatar;
use f3g_rig::{Posed, Rig, RigParams, SkinWeights};
use f3g_splat::{Camera, GaussianCloud};

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
    /// SH degree of the colour, 0..=3.
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
            sh_degree: 3,
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

fn host<const D: usize>(t: burn::tensor::Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec::<f32>().expect("f32 tensor")
}

/// `n` items spread evenly over `items` (all of them when there are fewer).
fn evenly<T: Clone>(items: &[T], n: usize) -> Vec<T> {
    if items.len() <= n {
        return items.to_vec();
    }
    (0..n).map(|i| items[i * items.len() / n].clone()).collect()
}

/// The best four (or fewer) of each point's influences and their weights: the subset and
/// the weights (`w ≥ 0`, `Σ w = 1`) whose skinned positions over the sample poses stay
/// closest, in least squares, to those of all its influences. Per point, the sums
/// `G_kl = Σ_s c_k·c_l`, `b_k = Σ_s c_k·t` over samples (`c_k` the point moved by candidate
/// `k` alone, `t` by the full skin) make every subset a small KKT system; subsets whose
/// solution has a negative weight are skipped. Returns the joints, weights and each point's
/// RMS position error over the samples.
fn best_four(
    skin: &SkinWeights,
    points: &[Vec3],
    samples: &[Vec<Affine3A>],
) -> (Vec<[u16; 4]>, Vec<[f32; 4]>, Vec<f32>) {
    use rayon::prelude::*;
    let fitted: Vec<([u16; 4], [f32; 4], f32)> = (0..points.len())
        .into_par_iter()
        .map(|g| {
            let x = points[g];
            let candidates: Vec<(u16, f32)> = skin.joints[g]
                .iter()
                .copied()
                .zip(skin.weights[g].iter().copied())
                .filter(|c| c.1 > 0.0)
                .collect();
            let m = candidates.len();
            let mut gram = [[0.0f64; 8]; 8];
            let mut b = [0.0f64; 8];
            let mut tt = 0.0f64;
            for s in samples {
                let moved: Vec<glam::DVec3> = candidates
                    .iter()
                    .map(|&(j, _)| s[j as usize].transform_point3(x).as_dvec3())
                    .collect();
                let t: glam::DVec3 = moved
                    .iter()
                    .zip(&candidates)
                    .map(|(c, &(_, w))| *c * w as f64)
                    .sum();
                tt += t.length_squared();
                for k in 0..m {
                    b[k] += moved[k].dot(t);
                    for l in 0..m {
                        gram[k][l] += moved[k].dot(moved[l]);
                    }
                }
            }
            let mut best: Option<(f64, Vec<usize>, Vec<f64>)> = None;
            for mask in 1u32..(1 << m) {
                if mask.count_ones() > 4 {
                    continue;
                }
                let subset: Vec<usize> = (0..m).filter(|k| mask & (1 << k) != 0).collect();
                let Some(w) = constrained_least_squares(&gram, &b, &subset) else {
                    continue;
                };
                if w.iter().any(|&v| v < -1e-9) {
                    continue;
                }
                let mut residual = tt;
                for (i, &k) in subset.iter().enumerate() {
                    residual -= 2.0 * w[i] * b[k];
                    for (jj, &l) in subset.iter().enumerate() {
                        residual += w[i] * w[jj] * gram[k][l];
                    }
                }
                if best.as_ref().is_none_or(|(r, _, _)| residual < *r) {
                    best = Some((residual, subset, w));
                }
            }
            let (residual, subset, w) = best.unwrap_or((0.0, vec![0], vec![1.0]));
            let mut joints = [0u16; 4];
            let mut weights = [0f32; 4];
            let total: f64 = w.iter().map(|v| v.max(0.0)).sum::<f64>().max(1e-12);
            for (i, &k) in subset.iter().enumerate() {
                joints[i] = candidates[k].0;
                weights[i] = (w[i].max(0.0) / total) as f32;
            }
            let rms = (residual.max(0.0) / samples.len().max(1) as f64).sqrt() as f32;
            (joints, weights, rms)
        })
        .collect();
    let mut joints = Vec::with_capacity(fitted.len());
    let mut weights = Vec::with_capacity(fitted.len());
    let mut errors = Vec::with_capacity(fitted.len());
    for (j, w, e) in fitted {
        joints.push(j);
        weights.push(w);
        errors.push(e);
    }
    (joints, weights, errors)
}

/// `argmin wᵀ G w − 2 wᵀ b` over the indices `subset` with `Σ w = 1`: the KKT system
/// `[G 1; 1ᵀ 0] [w; λ] = [b; 1]` by Gaussian elimination with partial pivoting (`None` when
/// singular).
fn constrained_least_squares(
    gram: &[[f64; 8]; 8],
    b: &[f64; 8],
    subset: &[usize],
) -> Option<Vec<f64>> {
    let n = subset.len();
    let size = n + 1;
    let mut a = [[0.0f64; 6]; 5];
    let trace: f64 = subset.iter().map(|&k| gram[k][k]).sum();
    for (i, &k) in subset.iter().enumerate() {
        for (j, &l) in subset.iter().enumerate() {
            a[i][j] = gram[k][l] + if i == j { 1e-12 * trace } else { 0.0 };
        }
        a[i][n] = 1.0;
        a[n][i] = 1.0;
        a[i][size] = b[k];
    }
    a[n][size] = 1.0;
    for col in 0..size {
        let pivot = (col..size).max_by(|&p, &q| a[p][col].abs().total_cmp(&a[q][col].abs()))?;
        if a[pivot][col].abs() < 1e-300 {
            return None;
        }
        a.swap(col, pivot);
        let pivot_row = a[col];
        for (r, row) in a.iter_mut().enumerate().take(size) {
            if r != col {
                let f = row[col] / pivot_row[col];
                for (x, p) in row
                    .iter_mut()
                    .zip(&pivot_row)
                    .skip(col)
                    .take(size + 1 - col)
                {
                    *x -= f * p;
                }
            }
        }
    }
    Some((0..n).map(|i| a[i][size] / a[i][i]).collect())
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

    /// Bakes `avatar` over the pose samples drawn from `poses` (module docs).
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
            },
        )?;
        let n = reference.len();
        // The samples.
        let skip: Vec<usize> = rig
            .finger_params()?
            .into_iter()
            .chain(rig.root_params())
            .collect();
        let sigma = options.spread_deg.to_radians();
        let mut rng = ChaCha8Rng::seed_from_u64(options.seed);
        // A standard normal value (Box–Muller).
        let mut normal = move || {
            let (u, v): (f32, f32) = (rng.random_range(f32::EPSILON..1.0), rng.random());
            (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
        };
        let mut samples: Vec<RigParams> = Vec::new();
        for p in evenly(poses, options.poses.max(1)) {
            samples.push(p.clone());
            for _ in 0..options.perturbations {
                let mut q = p.clone();
                for (i, v) in q.pose.iter_mut().enumerate() {
                    if !skip.contains(&i) {
                        *v += sigma * normal();
                    }
                }
                samples.push(q);
            }
        }
        let s = samples.len();
        f3g_io::memory::ensure_available(
            (s as u64 + options.correctives as u64 + 4) * (CORRECTIVE_VALUES * n) as u64 * 8,
            &format!("the pose correctives' PCA of {s} poses × {n} Gaussians"),
        )?;
        // Canonical outputs per sample; colours averaged over four horizontal views.
        let centre = Vec3::new(0.0, 0.0, 0.0);
        let views: Vec<Camera> = [0.0f32, 90.0, 180.0, 270.0]
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
            .collect();
        let root = rig
            .skeleton
            .joints()
            .iter()
            .position(|j| j.parent.is_none())
            .unwrap_or(0);
        let feature_joints: Vec<usize> = feature_joints(rig)?;
        let mut rows: Vec<Vec<f32>> = Vec::with_capacity(s);
        let mut sample_skinning: Vec<Vec<Affine3A>> = Vec::with_capacity(s);
        let mut features: Vec<Vec<f32>> = Vec::with_capacity(s);
        for params in &samples {
            let mut colour = vec![0.0f32; 3 * n];
            let mut row = vec![0.0f32; CORRECTIVE_VALUES * n];
            for (v, camera) in views.iter().enumerate() {
                let (c, inputs) = avatar.canonical_with_inputs(params, camera, false)?;
                for (acc, x) in colour.iter_mut().zip(host(c.colours)) {
                    *acc += x / views.len() as f32;
                }
                if v == 0 {
                    let means = host(c.means);
                    let displacement = host(inputs.displacement);
                    let scales = host(c.log_scales);
                    let opacity = host(c.opacity_logits);
                    for g in 0..n {
                        let r = &mut row[g * CORRECTIVE_VALUES..(g + 1) * CORRECTIVE_VALUES];
                        for k in 0..3 {
                            r[k] = means[3 * g + k] - displacement[3 * g + k];
                            r[6 + k] = scales[3 * g + k];
                        }
                        r[9] = opacity[g];
                    }
                    let frame = setup.pose(params)?;
                    features.push(pose_features(&frame.joints, root, &feature_joints));
                    sample_skinning.push(frame.joints);
                }
            }
            for g in 0..n {
                row[g * CORRECTIVE_VALUES + 3..g * CORRECTIVE_VALUES + 6]
                    .copy_from_slice(&colour[3 * g..3 * g + 3]);
            }
            rows.push(row);
        }
        // Per-attribute spreads, then the PCA in the normalised space.
        let groups: [std::ops::Range<usize>; 4] = [0..3, 3..6, 6..9, 9..10];
        let mut mean = vec![0.0f64; CORRECTIVE_VALUES * n];
        for r in &rows {
            for (m, v) in mean.iter_mut().zip(r) {
                *m += *v as f64 / s as f64;
            }
        }
        let mut spread = [0.0f64; CORRECTIVE_VALUES];
        for range in &groups {
            let mut sum = 0.0;
            let mut count = 0usize;
            for r in &rows {
                for g in 0..n {
                    for k in range.clone() {
                        let d =
                            r[g * CORRECTIVE_VALUES + k] as f64 - mean[g * CORRECTIVE_VALUES + k];
                        sum += d * d;
                        count += 1;
                    }
                }
            }
            let rms = (sum / count.max(1) as f64).sqrt().max(1e-9);
            for k in range.clone() {
                spread[k] = rms;
            }
        }
        let normalised: Vec<Vec<f32>> = rows
            .iter()
            .map(|r| {
                r.iter()
                    .enumerate()
                    .map(|(i, v)| (*v as f64 / spread[i % CORRECTIVE_VALUES]) as f32)
                    .collect()
            })
            .collect();
        drop(rows);
        let k = options.correctives.min(s.saturating_sub(1));
        let (correctives, weights, explained) = if k == 0 {
            (Vec::new(), vec![Vec::new(); s], 0.0)
        } else {
            let pca = f3g_template::PosePca::fit(&normalised, k, 1.0)?;
            let total: f64 = {
                let m: Vec<f64> = pca.mean.iter().map(|&v| v as f64).collect();
                normalised
                    .iter()
                    .map(|r| {
                        r.iter()
                            .zip(&m)
                            .map(|(v, m)| (*v as f64 - m).powi(2))
                            .sum::<f64>()
                    })
                    .sum()
            };
            let d = pca.mean.len();
            let weights: Vec<Vec<f32>> = normalised
                .iter()
                .map(|r| {
                    (0..pca.len())
                        .map(|c| {
                            pca.components[c * d..(c + 1) * d]
                                .iter()
                                .zip(r.iter().zip(&pca.mean))
                                .map(|(a, (x, m))| a * (x - m))
                                .sum()
                        })
                        .collect()
                })
                .collect();
            let captured: f64 = pca
                .stddev
                .iter()
                .map(|s2| (*s2 as f64).powi(2) * (s - 1) as f64)
                .sum();
            let basis: Vec<f32> = pca
                .components
                .iter()
                .enumerate()
                .map(|(i, v)| (*v as f64 * spread[i % CORRECTIVE_VALUES]) as f32)
                .collect();
            (basis, weights, captured / total.max(1e-30))
        };
        let k = weights.first().map_or(0, Vec::len);
        // The ridge map from the pose features to the weights.
        let all_f = features.first().map_or(0, Vec::len);
        let mut f_mean = vec![0.0f64; all_f];
        for f in &features {
            for (m, v) in f_mean.iter_mut().zip(f) {
                *m += *v as f64 / s as f64;
            }
        }
        let used: Vec<usize> = (0..all_f)
            .filter(|&i| {
                features
                    .iter()
                    .any(|f| (f[i] as f64 - f_mean[i]).abs() > 1e-6)
            })
            .collect();
        let fdim = used.len();
        let centred = faer::Mat::<f64>::from_fn(s, fdim, |r, c| {
            features[r][used[c]] as f64 - f_mean[used[c]]
        });
        let targets = faer::Mat::<f64>::from_fn(s, k, |r, c| weights[r][c] as f64);
        let (feature_map, weight_fit_error) = if k == 0 || fdim == 0 {
            (vec![0.0f32; k * fdim], 0.0)
        } else {
            let gram = centred.transpose() * &centred;
            let trace: f64 = (0..fdim).map(|i| gram[(i, i)]).sum();
            let lambda = options.ridge * trace / fdim as f64;
            let regularised = faer::Mat::<f64>::from_fn(fdim, fdim, |i, j| {
                gram[(i, j)] + if i == j { lambda } else { 0.0 }
            });
            let rhs = centred.transpose() * &targets;
            let solution = regularised
                .llt(faer::Side::Lower)
                .map_err(|e| AvatarError::Invalid(format!("ridge regression: {e:?}")))?
                .solve(&rhs);
            let predicted = &centred * &solution;
            let (mut err, mut norm) = (0.0, 0.0);
            for r in 0..s {
                for c in 0..k {
                    err += (predicted[(r, c)] - targets[(r, c)]).powi(2);
                    norm += targets[(r, c)].powi(2);
                }
            }
            let map: Vec<f32> = (0..k)
                .flat_map(|c| (0..fdim).map(move |i| (c, i)))
                .map(|(c, i)| solution[(i, c)] as f32)
                .collect();
            (map, (err / norm.max(1e-30)).sqrt())
        };
        let mean_means: Vec<f32> = (0..n)
            .flat_map(|g| (0..3).map(move |c| (g, c)))
            .map(|(g, c)| mean[g * CORRECTIVE_VALUES + c] as f32)
            .collect();
        // The mean avatar: the PCA mean, with the reference's rotations and SH.
        let mut means = vec![0.0f32; 3 * n];
        let mut log_scales = vec![0.0f32; 3 * n];
        let mut opacity = vec![0.0f32; n];
        let coeffs = f3g_splat::sh::num_coeffs(options.sh_degree);
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
        // Expressions: the displacement of every Gaussian by each at weight 1.
        let mut expression_names = Vec::new();
        let mut expressions = Vec::new();
        if options.expressions {
            let front = &views[0];
            let (_, base) = avatar.canonical_with_inputs(&canonical, front, false)?;
            let base = host(base.displacement);
            for (e, name) in rig.expression.names.iter().enumerate() {
                let mut p = canonical.clone();
                p.expression[e] = 1.0;
                let (_, inputs) = avatar.canonical_with_inputs(&p, front, false)?;
                let d = host(inputs.displacement);
                expressions.extend(d.iter().zip(&base).map(|(a, b)| a - b));
                expression_names.push(name.clone());
            }
        }
        let points: Vec<Vec3> = mean_means.chunks_exact(3).map(Vec3::from_slice).collect();
        let full_skin = avatar.skin();
        let (skin_joints, skin_weights, skin_error) =
            best_four(&full_skin, &points, &sample_skinning);
        let dropped: Vec<f32> = (0..n)
            .map(|g| {
                full_skin.joints[g]
                    .iter()
                    .zip(&full_skin.weights[g])
                    .filter(|(j, _)| {
                        !skin_joints[g].contains(j)
                            || skin_weights[g]
                                [skin_joints[g].iter().position(|k| k == *j).unwrap_or(0)]
                                == 0.0
                    })
                    .map(|(_, w)| *w)
                    .sum()
            })
            .collect();
        let baked = Self {
            rig: rig.clone(),
            canonical,
            means,
            quats: reference.quats.clone(),
            log_scales,
            opacity_logits: opacity,
            sh,
            sh_degree: options.sh_degree,
            skin_joints,
            skin_weights,
            correctives,
            feature_joints,
            feature_used: used.clone(),
            feature_mean: used.iter().map(|&i| f_mean[i] as f32).collect(),
            feature_map,
            expression_names,
            expressions,
            head_vertices: setup.head_vertices.clone(),
            face_padding: avatar.model.face_padding,
            face_crop_size: avatar.model.face_crop_size,
            step: avatar.step,
        };
        let report = BakeReport {
            gaussians: n,
            samples: s,
            features: fdim,
            explained_variance: explained,
            weight_fit_error,
            dropped_weight_mean: dropped.iter().map(|&d| d as f64).sum::<f64>() / n.max(1) as f64,
            dropped_weight_max: dropped.iter().copied().fold(0.0f32, f32::max) as f64,
            skin_error_mean: skin_error.iter().map(|&d| d as f64).sum::<f64>() / n.max(1) as f64,
            skin_error_max: skin_error.iter().copied().fold(0.0f32, f32::max) as f64,
            sh_rms: fit.rms,
            seconds: start.elapsed().as_secs_f64(),
        };
        Ok((baked, report))
    }
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
