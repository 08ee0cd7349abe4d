//! Choosing four skin influences per Gaussian (glTF's `JOINTS_0`/`WEIGHTS_0`): of each
//! Gaussian's influences, the subset of at most four and the weights whose skinned positions
//! over the sample poses stay closest to those of all its influences.

use glam::{Affine3A, Vec3};

use f3g_rig::SkinWeights;

/// Four influences per Gaussian and what keeping only four costs.
pub(super) struct FourInfluences {
    pub joints: Vec<[u16; 4]>,
    pub weights: Vec<[f32; 4]>,
    /// Each Gaussian's RMS position error over the samples against all its influences.
    pub errors: Vec<f32>,
    /// Each Gaussian's skin weight on the influences left out.
    pub dropped: Vec<f32>,
}

/// The four influences of every Gaussian at `points` (with its full skin `skin`) over the
/// sample poses' skinning transforms `samples`, and the weight each leaves out.
pub(super) fn four_influences(
    skin: &SkinWeights,
    points: &[Vec3],
    samples: &[Vec<Affine3A>],
) -> FourInfluences {
    let (joints, weights, errors) = best_four(skin, points, samples);
    let dropped = (0..points.len())
        .map(|g| {
            skin.joints[g]
                .iter()
                .zip(&skin.weights[g])
                .filter(|(j, _)| {
                    !joints[g].contains(j)
                        || weights[g][joints[g].iter().position(|k| k == *j).unwrap_or(0)] == 0.0
                })
                .map(|(_, w)| *w)
                .sum()
        })
        .collect();
    FourInfluences {
        joints,
        weights,
        errors,
        dropped,
    }
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
