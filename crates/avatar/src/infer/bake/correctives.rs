//! Baking's steps 3 and 5 (module docs): the pose correctives as the principal components of
//! the samples' rows, and the ridge map from pose features to their weights.

use faer::linalg::solvers::Solve;

use super::CORRECTIVE_VALUES;
use crate::AvatarError;

/// The correctives' PCA.
pub(super) struct Correctives {
    /// `[N·10]` mean of the samples' rows, in their units: the baked avatar.
    pub mean: Vec<f64>,
    /// `[K, N, 10]` corrective directions, in the rows' units.
    pub basis: Vec<f32>,
    /// Each sample's `K` corrective weights.
    pub weights: Vec<Vec<f32>>,
    /// Share of the samples' (normalised) variance the correctives explain.
    pub explained: f64,
}

/// The mean of `rows` (one per sample, `n` Gaussians of [`CORRECTIVE_VALUES`]) and up to
/// `correctives` principal components, each attribute divided by its spread over all samples
/// first (so metres, colours and logits weigh alike) and the components scaled back.
pub(super) fn corrective_pca(
    rows: Vec<Vec<f32>>,
    n: usize,
    correctives: usize,
) -> Result<Correctives, AvatarError> {
    let s = rows.len();
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
                    let d = r[g * CORRECTIVE_VALUES + k] as f64 - mean[g * CORRECTIVE_VALUES + k];
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
    let k = correctives.min(s.saturating_sub(1));
    let (basis, weights, explained) = if k == 0 {
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
    Ok(Correctives {
        mean,
        basis,
        weights,
        explained,
    })
}

/// The ridge map from the centred pose features to the corrective weights.
pub(super) struct RidgeMap {
    /// Which pose features vary over the samples (the others are left out).
    pub used: Vec<usize>,
    /// `[F]` the used features' mean over the samples.
    pub mean: Vec<f32>,
    /// `[K, F]` row-major: `w = map (f − mean)`.
    pub map: Vec<f32>,
    /// RMS over samples of the weights' prediction error, relative to the weights' RMS.
    pub fit_error: f64,
}

/// The ridge regression `M = Wᵀ F (Fᵀ F + λ I)⁻¹`, `λ = ridge · tr(FᵀF) / F`, from each
/// sample's pose `features` (centred, the varying ones) to its corrective `weights`.
pub(super) fn ridge_map(
    features: &[Vec<f32>],
    weights: &[Vec<f32>],
    ridge: f64,
) -> Result<RidgeMap, AvatarError> {
    let s = features.len();
    let k = weights.first().map_or(0, Vec::len);
    let all_f = features.first().map_or(0, Vec::len);
    let mut f_mean = vec![0.0f64; all_f];
    for f in features {
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
        let lambda = ridge * trace / fdim as f64;
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
    Ok(RidgeMap {
        mean: used.iter().map(|&i| f_mean[i] as f32).collect(),
        used,
        map: feature_map,
        fit_error: weight_fit_error,
    })
}
