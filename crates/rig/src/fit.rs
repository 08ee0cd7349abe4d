//! Fitting a rig's parameters to a posed mesh and joints (e.g. SMPL-X → built-in or MHR):
//!
//! `min Σ_i ‖V_i(θ) − T_i‖² + λ Σ_j ‖J_j(θ) − T_j‖² + ρ ‖θ‖²`
//!
//! over pose (and optionally identity and expression) parameters θ, with Levenberg–Marquardt.
//! `T_i` is a vertex of the same topology, a barycentric point of the target mesh (a
//! correspondence file), or the nearest target vertex (recomputed every iteration). The small
//! prior ρ keeps parameters the data does not see at zero.
//!
//! Jacobian columns of Momentum pose parameters are analytic — each joint degree of freedom moves
//! a point `x` attached below it by `ω × (x − c)` (rotation about axis ω through the joint
//! centre c), `ln 2 · (x − c)` (scale) or along the parent's axis (translation), chained through
//! skinning and the parameter transform as Momentum does. Other columns (identity, expression,
//! axis-angle poses) use central differences.

use faer::Mat;
use faer::linalg::solvers::Solve;
use glam::{Quat, Vec3};
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use crate::RigError;
use crate::rig::{Parameterization, Posed, Rig, RigParams};
use crate::skeleton::{PARAMS_PER_JOINT, Similarity};

/// How model vertices find their target points.
#[derive(Clone, Debug)]
pub enum Correspondence {
    /// Model vertex `i` ↔ target vertex `i` (same topology).
    Identity,
    /// Model vertex `i` ↔ `Σ_k w[i][k] · T[tri[i][k]]` (e.g. MHR's `smplx2mhr_mapping.npz`).
    Barycentric {
        triangles: Vec<[u32; 3]>,
        weights: Vec<[f32; 3]>,
    },
    /// Model vertex `i` ↔ the nearest target vertex, recomputed every iteration.
    Nearest,
}

impl Correspondence {
    /// [`Correspondence::Identity`] when the two meshes share their topology, otherwise
    /// [`Correspondence::Nearest`].
    pub fn between(source: &Rig, model: &Rig) -> Self {
        if source.mesh.vertices.len() == model.mesh.vertices.len()
            && source.mesh.triangles == model.mesh.triangles
        {
            Correspondence::Identity
        } else {
            Correspondence::Nearest
        }
    }

    /// How it is described to a user.
    pub fn describe(&self) -> &'static str {
        match self {
            Correspondence::Identity => "same-topology",
            Correspondence::Barycentric { .. } => "barycentric",
            Correspondence::Nearest => "nearest-vertex",
        }
    }
}

/// Settings of a fit.
#[derive(Clone, Debug)]
pub struct FitOptions {
    /// λ: weight of the joint term relative to the vertex term.
    pub joint_weight: f32,
    /// ρ: Tikhonov prior on the parameters.
    pub prior: f32,
    pub max_iterations: usize,
    pub fit_identity: bool,
    pub fit_expression: bool,
    /// At most this many model vertices enter the vertex term (an even subsample); 0 fits the
    /// joints alone.
    pub max_vertices: usize,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            joint_weight: 1.0,
            prior: 1e-6,
            max_iterations: 50,
            fit_identity: false,
            fit_expression: false,
            max_vertices: 2000,
        }
    }
}

/// What to fit to.
pub struct FitTarget<'a> {
    pub vertices: &'a [Vec3],
    /// `(model joint, target position)` pairs.
    pub joints: &'a [(usize, Vec3)],
}

/// A fitted frame and its residuals.
#[derive(Clone, Debug)]
pub struct FitResult {
    pub params: RigParams,
    /// RMS and maximum distance (metres) of the corresponded vertices.
    pub vertex_rms: f32,
    pub vertex_max: f32,
    /// RMS distance of the paired joints.
    pub joint_rms: f32,
    pub iterations: usize,
}

/// Which parameter a Jacobian column is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Column {
    Pose(usize),
    Identity(usize),
    Expression(usize),
}

impl Column {
    /// The parameter's value in `p`.
    pub fn get(self, p: &RigParams) -> f32 {
        match self {
            Column::Pose(i) => p.pose[i],
            Column::Identity(i) => p.identity[i],
            Column::Expression(i) => p.expression[i],
        }
    }

    /// Sets the parameter in `p`.
    pub fn set(self, p: &mut RigParams, v: f32) {
        match self {
            Column::Pose(i) => p.pose[i] = v,
            Column::Identity(i) => p.identity[i] = v,
            Column::Expression(i) => p.expression[i] = v,
        }
    }
}

struct Problem<'a> {
    rig: &'a Rig,
    target: &'a FitTarget<'a>,
    correspondence: &'a Correspondence,
    nearest: Option<ImmutableKdTree<f32, 3>>,
    sample: Vec<usize>,
    joints: Vec<usize>,
    columns: Vec<Column>,
    options: &'a FitOptions,
}

impl Problem<'_> {
    /// Target point of model vertex `i` given the model's posed vertex `v`.
    fn target_point(&self, i: usize, v: Vec3) -> Vec3 {
        match self.correspondence {
            Correspondence::Identity => self.target.vertices[i],
            Correspondence::Barycentric { triangles, weights } => {
                let (t, w) = (triangles[i], weights[i]);
                (0..3)
                    .map(|k| self.target.vertices[t[k] as usize] * w[k])
                    .sum()
            }
            Correspondence::Nearest => {
                let tree = self.nearest.as_ref().expect("built for Nearest");
                let hit = tree
                    .query(&v.to_array())
                    .nearest_one::<SquaredEuclidean<f32>>()
                    .execute();
                self.target.vertices[hit.item as usize]
            }
        }
    }

    fn residuals(&self, posed: &Posed, params: &RigParams) -> Vec<f64> {
        let lambda = (self.options.joint_weight as f64).sqrt();
        let prior = (self.options.prior as f64).sqrt();
        let mut r = Vec::with_capacity(
            3 * (self.sample.len() + self.target.joints.len()) + self.columns.len(),
        );
        for &i in &self.sample {
            let v = posed.vertices[i];
            r.extend((v - self.target_point(i, v)).to_array().map(f64::from));
        }
        for &(j, t) in self.target.joints {
            r.extend(
                (posed.joints[j].translation - t)
                    .to_array()
                    .map(|x| lambda * x as f64),
            );
        }
        r.extend(self.columns.iter().map(|&c| prior * c.get(params) as f64));
        r
    }

    fn pose(&self, params: &RigParams) -> Result<Posed, RigError> {
        self.rig.pose(params)
    }

    /// Jacobian `[residuals × columns]` (row-major), with target points held fixed (nearest
    /// correspondences are re-found at the next iteration).
    fn jacobian(&self, params: &RigParams, posed: &Posed) -> Result<Vec<f64>, RigError> {
        let points = 3 * (self.sample.len() + self.joints.len());
        let cols = self.columns.len();
        let mut jac = vec![0.0f64; (points + cols) * cols];
        let d = point_jacobian(
            self.rig,
            params,
            posed,
            &self.columns,
            &self.sample,
            &self.joints,
        )?;
        let lambda = self.options.joint_weight.sqrt();
        for (ci, column) in d.iter().enumerate() {
            for (p, v) in column.iter().enumerate() {
                let w = if p < self.sample.len() { 1.0 } else { lambda };
                for (c, x) in v.to_array().iter().enumerate() {
                    jac[(3 * p + c) * cols + ci] = (w * x) as f64;
                }
            }
        }
        let prior = (self.options.prior as f64).sqrt();
        for ci in 0..cols {
            jac[(points + ci) * cols + ci] = prior;
        }
        Ok(jac)
    }
}

/// How every point moves with every parameter: `[column][point]`, the points being the
/// posed `vertices` (by index) and then the centres of `joints`. Momentum pose columns are
/// analytic (module docs); the others are central differences of [`Rig::pose`].
pub fn point_jacobian(
    rig: &Rig,
    params: &RigParams,
    posed: &Posed,
    columns: &[Column],
    vertices: &[usize],
    joints: &[usize],
) -> Result<Vec<Vec<Vec3>>, RigError> {
    let analytic = analytic_pose_columns(rig, params, posed, columns, vertices, joints)?;
    analytic
        .into_par_iter()
        .zip(columns)
        .map(|(analytic, &c)| -> Result<Vec<Vec3>, RigError> {
            if let Some(col) = analytic {
                return Ok(col);
            }
            let h = 1e-3f32;
            let mut plus = params.clone();
            c.set(&mut plus, c.get(params) + h);
            let mut minus = params.clone();
            c.set(&mut minus, c.get(params) - h);
            let (pp, pm) = (rig.pose(&plus)?, rig.pose(&minus)?);
            let diff = |a: Vec3, b: Vec3| (a - b) / (2.0 * h);
            Ok(vertices
                .iter()
                .map(|&i| diff(pp.vertices[i], pm.vertices[i]))
                .chain(
                    joints
                        .iter()
                        .map(|&j| diff(pp.joints[j].translation, pm.joints[j].translation)),
                )
                .collect())
        })
        .collect()
}

/// Per column, its analytic derivatives (`[point]` as in [`point_jacobian`]) when it is a
/// Momentum pose parameter, else `None`.
fn analytic_pose_columns(
    rig: &Rig,
    params: &RigParams,
    posed: &Posed,
    columns: &[Column],
    vertices: &[usize],
    joints: &[usize],
) -> Result<Vec<Option<Vec<Vec3>>>, RigError> {
    let Parameterization::Momentum(transform) = &rig.parameterization else {
        return Ok(vec![None; columns.len()]);
    };
    let skeleton = &rig.skeleton;
    let joint_params = transform.apply(&params.pose)?;
    let axes = joint_axes(skeleton.joints(), &joint_params, &posed.joints);
    // The column of each model pose parameter, if it is one.
    let mut column_of = vec![None; transform.len()];
    for (ci, c) in columns.iter().enumerate() {
        if let Column::Pose(p) = c {
            column_of[*p] = Some(ci);
        }
    }
    // Columns per (row = joint·7 + channel).
    let mut by_row: Vec<Vec<(usize, f32)>> = vec![Vec::new(); skeleton.len() * PARAMS_PER_JOINT];
    for &(row, col, w) in &transform.entries {
        if let Some(ci) = column_of[col as usize] {
            by_row[row as usize].push((ci, w));
        }
    }
    let ancestors: Vec<Vec<usize>> = (0..skeleton.len())
        .map(|j| {
            let mut out = vec![j];
            let mut k = skeleton.joints()[j].parent;
            while let Some(p) = k {
                out.push(p);
                k = skeleton.joints()[p].parent;
            }
            out
        })
        .collect();
    let points = vertices.len() + joints.len();
    // `[column][point]`, allocated for the analytic columns only.
    let mut out: Vec<Option<Vec<Vec3>>> = vec![None; columns.len()];
    for &ci in column_of.iter().flatten() {
        out[ci] = Some(vec![Vec3::ZERO; points]);
    }
    // d(point attached below joint k)/dθ, accumulated into `point` with `weight`.
    let mut add_point = |point: usize, k: usize, x: Vec3, weight: f32| {
        for &a in &ancestors[k] {
            for ch in 0..PARAMS_PER_JOINT {
                let entries = &by_row[a * PARAMS_PER_JOINT + ch];
                if entries.is_empty() {
                    continue;
                }
                let d = axes[a].derivative(ch, x);
                for &(ci, w) in entries {
                    if let Some(col) = &mut out[ci] {
                        col[point] += weight * w * d;
                    }
                }
            }
        }
    };
    for (s, &i) in vertices.iter().enumerate() {
        for (k, w) in rig.skin.influences(i) {
            let x = posed.skinning[k].transform_point3(posed.rest_vertices[i]);
            add_point(s, k, x, w);
        }
    }
    for (p, &j) in joints.iter().enumerate() {
        add_point(vertices.len() + p, j, posed.joints[j].translation, 1.0);
    }
    Ok(out)
}

/// A joint's degrees of freedom in world space: translation axes (parent frame, with scale),
/// rotation axes (after the rotations applied before them), and its centre.
#[derive(Clone, Copy, Debug)]
pub struct JointAxes {
    pub translation: [Vec3; 3],
    pub rotation: [Vec3; 3],
    pub centre: Vec3,
}

impl JointAxes {
    /// How a world point attached below the joint moves per unit of channel `ch`.
    pub fn derivative(&self, ch: usize, x: Vec3) -> Vec3 {
        match ch {
            0..3 => self.translation[ch],
            3..6 => self.rotation[ch - 3].cross(x - self.centre),
            _ => (x - self.centre) * std::f32::consts::LN_2,
        }
    }
}

/// World axes of every joint's degrees of freedom for Momentum joint parameters.
pub fn joint_axes(
    joints: &[crate::Joint],
    params: &[[f32; PARAMS_PER_JOINT]],
    world: &[Similarity],
) -> Vec<JointAxes> {
    joints
        .iter()
        .zip(params)
        .enumerate()
        .map(|(j, (joint, p))| {
            let parent = joint.parent.map_or(Similarity::IDENTITY, |q| world[q]);
            let frame = parent.rotation * joint.pre_rotation;
            let rz = Quat::from_rotation_z(p[5]);
            let ry = Quat::from_rotation_y(p[4]);
            JointAxes {
                translation: [Vec3::X, Vec3::Y, Vec3::Z]
                    .map(|e| parent.rotation * (e * parent.scale)),
                rotation: [
                    (frame * rz * ry) * Vec3::X,
                    (frame * rz) * Vec3::Y,
                    frame * Vec3::Z,
                ],
                centre: world[j].translation,
            }
        })
        .collect()
}

/// Fits one frame, starting from `init`. With nearest-vertex correspondences and joint pairs,
/// the joints are fitted alone first, so that the vertex term starts near the right pose
/// (nearest-point matching from far away falls into local minima).
pub fn fit(
    rig: &Rig,
    target: &FitTarget,
    correspondence: &Correspondence,
    init: &RigParams,
    options: &FitOptions,
) -> Result<FitResult, RigError> {
    let init = if matches!(correspondence, Correspondence::Nearest) && !target.joints.is_empty() {
        let joints_only = FitOptions {
            max_vertices: 0,
            ..options.clone()
        };
        fit_stage(rig, target, correspondence, init, &joints_only)?.params
    } else {
        init.clone()
    };
    fit_stage(rig, target, correspondence, &init, options)
}

fn fit_stage(
    rig: &Rig,
    target: &FitTarget,
    correspondence: &Correspondence,
    init: &RigParams,
    options: &FitOptions,
) -> Result<FitResult, RigError> {
    let n = rig.mesh.vertices.len();
    match correspondence {
        Correspondence::Identity if target.vertices.len() != n => {
            return Err(RigError::Params(format!(
                "same-topology fit needs {n} target vertices, got {}",
                target.vertices.len()
            )));
        }
        Correspondence::Barycentric { triangles, weights }
            if triangles.len() != n || weights.len() != n =>
        {
            return Err(RigError::Params(format!(
                "the correspondence maps {} vertices, the model has {n}",
                triangles.len()
            )));
        }
        Correspondence::Barycentric { triangles, .. }
            if triangles
                .iter()
                .flatten()
                .any(|&t| t as usize >= target.vertices.len()) =>
        {
            return Err(RigError::Params(
                "the correspondence references target vertices that do not exist".into(),
            ));
        }
        _ => {}
    }
    if let Some(&(j, _)) = target.joints.iter().find(|(j, _)| *j >= rig.skeleton.len()) {
        return Err(RigError::Params(format!(
            "joint pair references model joint {j}"
        )));
    }
    let sample: Vec<usize> = match options.max_vertices {
        0 => Vec::new(),
        m => (0..n).step_by(n.div_ceil(m).max(1)).collect(),
    };
    let mut columns: Vec<Column> = (0..rig.num_pose_params()).map(Column::Pose).collect();
    if options.fit_identity {
        columns.extend((0..rig.identity.len()).map(Column::Identity));
    }
    if options.fit_expression {
        columns.extend((0..rig.expression.len()).map(Column::Expression));
    }
    let nearest = matches!(correspondence, Correspondence::Nearest).then(|| {
        let points: Vec<[f32; 3]> = target.vertices.iter().map(|v| v.to_array()).collect();
        ImmutableKdTree::new_from_slice(&points)
    });
    let nearest = match nearest {
        Some(Ok(t)) => Some(t),
        Some(Err(e)) => {
            return Err(RigError::Params(format!(
                "cannot index the target vertices: {e:?}"
            )));
        }
        None => None,
    };
    let problem = Problem {
        rig,
        target,
        correspondence,
        nearest,
        sample,
        joints: target.joints.iter().map(|&(j, _)| j).collect(),
        columns,
        options,
    };

    let (params, posed, iterations) = levenberg_marquardt(
        init.clone(),
        &problem.columns,
        options.max_iterations,
        f64::INFINITY,
        |p| {
            let posed = problem.pose(p)?;
            Ok((problem.residuals(&posed, p), posed))
        },
        |p, posed, r| {
            let jacobian = problem.jacobian(p, posed)?;
            Ok(normal_equations(&jacobian, r, problem.columns.len()))
        },
    )?;
    let distances: Vec<f32> = problem
        .sample
        .iter()
        .map(|&i| (posed.vertices[i] - problem.target_point(i, posed.vertices[i])).length())
        .collect();
    let joint_d: Vec<f32> = target
        .joints
        .iter()
        .map(|&(j, t)| (posed.joints[j].translation - t).length())
        .collect();
    let rms = |d: &[f32]| {
        if d.is_empty() {
            0.0
        } else {
            (d.iter().map(|x| x * x).sum::<f32>() / d.len() as f32).sqrt()
        }
    };
    Ok(FitResult {
        vertex_rms: rms(&distances),
        vertex_max: distances.iter().copied().fold(0.0, f32::max),
        joint_rms: rms(&joint_d),
        params,
        iterations,
    })
}

/// The normal equations `(JᵀJ, Jᵀr)` of residuals `r` with Jacobian `jacobian`
/// (`[residuals × columns]`, row-major).
pub fn normal_equations(jacobian: &[f64], r: &[f64], columns: usize) -> (Mat<f64>, Mat<f64>) {
    let j = Mat::<f64>::from_fn(r.len(), columns, |a, b| jacobian[a * columns + b]);
    let rv = Mat::<f64>::from_fn(r.len(), 1, |a, _| r[a]);
    (j.transpose() * &j, j.transpose() * &rv)
}

/// Levenberg–Marquardt on `columns` of `params` from the given start: `evaluate` gives the
/// residuals at parameters (and what the derivatives need of them), `normal` the normal
/// equations `(JᵀJ, Jᵀr)` there (see [`normal_equations`]). A step moving any parameter by more
/// than `max_step` is shortened to it (a trust region: an Euler angle taken past ±π in one
/// step lands on another branch of the same rotation, far from the rest pose). Stops after
/// `max_iterations`, or when a step no longer lowers the cost by a relative 1e-7. Returns the
/// parameters, their evaluation and the iterations taken.
pub fn levenberg_marquardt<T>(
    mut params: RigParams,
    columns: &[Column],
    max_iterations: usize,
    max_step: f64,
    evaluate: impl Fn(&RigParams) -> Result<(Vec<f64>, T), RigError>,
    normal: impl Fn(&RigParams, &T, &[f64]) -> Result<(Mat<f64>, Mat<f64>), RigError>,
) -> Result<(RigParams, T, usize), RigError> {
    let (mut r, mut state) = evaluate(&params)?;
    let mut cost: f64 = r.iter().map(|v| v * v).sum();
    let mut mu = 1e-3f64;
    let mut iterations = 0;
    let cols = columns.len();
    for _ in 0..max_iterations {
        iterations += 1;
        let (jtj, jtr) = normal(&params, &state, &r)?;
        // Marquardt's damping scales with each parameter's own curvature; the floor keeps a
        // parameter the data barely sees (a twist no residual resolves) from taking huge steps.
        let floor = 1e-6 * (0..cols).map(|a| jtj[(a, a)]).fold(1e-9, f64::max);
        let mut improved = false;
        for _ in 0..10 {
            let damped = Mat::<f64>::from_fn(cols, cols, |a, b| {
                jtj[(a, b)]
                    + if a == b {
                        mu * jtj[(a, a)].max(floor)
                    } else {
                        0.0
                    }
            });
            let Ok(llt) = damped.llt(faer::Side::Lower) else {
                mu *= 10.0;
                continue;
            };
            let delta = llt.solve(&jtr);
            let largest = (0..cols).map(|c| delta[(c, 0)].abs()).fold(0.0, f64::max);
            let shorten = if largest > max_step {
                max_step / largest
            } else {
                1.0
            };
            let mut trial = params.clone();
            for (ci, &c) in columns.iter().enumerate() {
                c.set(
                    &mut trial,
                    c.get(&params) - (shorten * delta[(ci, 0)]) as f32,
                );
            }
            let (trial_r, trial_state) = evaluate(&trial)?;
            let trial_cost: f64 = trial_r.iter().map(|v| v * v).sum();
            if trial_cost < cost {
                let relative = (cost - trial_cost) / cost.max(1e-30);
                params = trial;
                state = trial_state;
                r = trial_r;
                cost = trial_cost;
                mu = (mu / 3.0).max(1e-9);
                improved = relative > 1e-7;
                break;
            }
            mu *= 4.0;
        }
        if !improved {
            break;
        }
    }
    Ok((params, state, iterations))
}

/// `(model joint, source joint)` pairs: by identical names when the models share joint names,
/// otherwise by the joint roles of the body-model contract ([`Rig::roles`]).
pub fn default_joint_map(source: &Rig, model: &Rig) -> Vec<(usize, usize)> {
    let by_name: Vec<(usize, usize)> = model
        .skeleton
        .joints()
        .iter()
        .enumerate()
        .filter_map(|(m, j)| source.skeleton.index_of(&j.name).map(|s| (m, s)))
        .collect();
    if !by_name.is_empty() {
        return by_name;
    }
    model
        .roles
        .iter()
        .filter_map(|(role, m)| Some((m, source.roles.get(role)?)))
        .collect()
}

/// A fitted sequence and its residuals.
#[derive(Clone, Debug)]
pub struct SequenceFit {
    pub frames: Vec<RigParams>,
    /// Mean over frames of the vertex RMS (metres).
    pub mean_vertex_rms: f32,
    /// The largest vertex RMS and its frame.
    pub worst: (f32, usize),
}

/// Fits `model` to `source` posed by each of `frames` (vertices through `correspondence`,
/// joints through [`default_joint_map`]). Each frame starts from the previous frame's result;
/// the identity is fitted on the first frame and then held (`options.fit_identity` is ignored).
/// `progress` sees each frame's result.
pub fn fit_sequence(
    source: &Rig,
    frames: &[RigParams],
    model: &Rig,
    correspondence: &Correspondence,
    options: &FitOptions,
    mut progress: impl FnMut(&FitResult),
) -> Result<SequenceFit, RigError> {
    let joint_map = default_joint_map(source, model);
    let mut current = model.zero_params();
    let mut fitted = Vec::with_capacity(frames.len());
    let (mut sum, mut worst) = (0.0f32, (0.0f32, 0usize));
    for (f, params) in frames.iter().enumerate() {
        let posed = source.pose(params)?;
        let joints: Vec<_> = joint_map
            .iter()
            .map(|&(m, s)| (m, posed.joints[s].translation))
            .collect();
        let target = FitTarget {
            vertices: &posed.vertices,
            joints: &joints,
        };
        let options = FitOptions {
            fit_identity: f == 0,
            ..options.clone()
        };
        let result = fit(model, &target, correspondence, &current, &options)?;
        progress(&result);
        sum += result.vertex_rms;
        if result.vertex_rms > worst.0 {
            worst = (result.vertex_rms, f);
        }
        current = result.params.clone();
        fitted.push(result.params);
    }
    Ok(SequenceFit {
        mean_vertex_rms: sum / frames.len().max(1) as f32,
        frames: fitted,
        worst,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gltf;
    use std::path::PathBuf;

    /// The analytic pose columns equal central differences on a Momentum character with every
    /// channel type (translations, rotations with pre-rotations, scales, joint references),
    /// for vertices and joint centres.
    #[test]
    fn analytic_jacobian_matches_finite_differences() {
        let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/pymomentum");
        let rig = gltf::load(&dir.join("char_a.glb"), Some(&dir.join("char_a.model"))).unwrap();
        let mut params = rig.zero_params();
        for (i, p) in params.pose.iter_mut().enumerate() {
            *p = ((i * 7919) % 13) as f32 / 13.0 - 0.5;
        }
        let posed = rig.pose(&params).unwrap();
        let vertices: Vec<usize> = (0..rig.mesh.vertices.len()).collect();
        let joint_list: Vec<usize> = (0..rig.skeleton.len()).collect();
        let columns: Vec<Column> = (0..rig.num_pose_params()).map(Column::Pose).collect();
        let analytic =
            analytic_pose_columns(&rig, &params, &posed, &columns, &vertices, &joint_list).unwrap();
        assert!(analytic.iter().all(Option::is_some));
        for (ci, col) in analytic.iter().enumerate() {
            let col = col.as_ref().unwrap();
            // f32 positions near 1 m: a larger step keeps rounding out of the differences.
            let h = 1e-2;
            let mut plus = params.clone();
            plus.pose[ci] += h;
            let mut minus = params.clone();
            minus.pose[ci] -= h;
            let (pp, pm) = (rig.pose(&plus).unwrap(), rig.pose(&minus).unwrap());
            let mut numeric: Vec<f32> = pp
                .vertices
                .iter()
                .zip(&pm.vertices)
                .flat_map(|(a, b)| ((*a - *b) / (2.0 * h)).to_array())
                .collect();
            numeric.extend(
                pp.joints
                    .iter()
                    .zip(&pm.joints)
                    .flat_map(|(a, b)| ((a.translation - b.translation) / (2.0 * h)).to_array()),
            );
            let scale = numeric.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-3);
            let analytic = col.iter().flat_map(|v| v.to_array());
            for (r, (a, n)) in analytic.zip(&numeric).enumerate() {
                assert!(
                    (a - n).abs() < 2e-3 * scale + 2e-5,
                    "parameter {} row {r}: analytic {a} numeric {n}",
                    rig.pose_param_names()[ci]
                );
            }
        }
    }
}
