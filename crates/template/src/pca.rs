//! Pose PCA (Animatable Gaussians §3.4): principal components of the training posed maps,
//! used to project an unseen pose map onto the span of the training poses before it reaches
//! the network. Coefficients are clamped to ±σ·√(explained variance) (σ = 2 by default).

use faer::Side;

use crate::TemplateError;

/// A fitted pose PCA over vectors of length `D` (flattened posed positions).
#[derive(Clone, Debug, PartialEq)]
pub struct PosePca {
    pub mean: Vec<f32>,
    /// `[k, D]` orthonormal components, largest variance first.
    pub components: Vec<f32>,
    /// Standard deviation of each component over the training samples.
    pub stddev: Vec<f32>,
    /// Clamp in standard deviations.
    pub sigma: f32,
}

impl PosePca {
    /// Fits `k` components to `samples` (each of the same length), via the eigen-decomposition
    /// of the samples' Gram matrix (cheap when there are fewer samples than dimensions).
    pub fn fit(samples: &[Vec<f32>], k: usize, sigma: f32) -> Result<Self, TemplateError> {
        let n = samples.len();
        if n < 2 {
            return Err(TemplateError::Invalid(format!(
                "pose PCA needs at least 2 training maps, got {n}"
            )));
        }
        let d = samples[0].len();
        if samples.iter().any(|s| s.len() != d) {
            return Err(TemplateError::Invalid(
                "pose PCA samples have different lengths".into(),
            ));
        }
        let mut mean = vec![0.0f64; d];
        for s in samples {
            for (m, v) in mean.iter_mut().zip(s) {
                *m += *v as f64 / n as f64;
            }
        }
        let centred: Vec<Vec<f64>> = samples
            .iter()
            .map(|s| s.iter().zip(&mean).map(|(v, m)| *v as f64 - m).collect())
            .collect();
        let gram = faer::Mat::<f64>::from_fn(n, n, |i, j| {
            centred[i].iter().zip(&centred[j]).map(|(a, b)| a * b).sum()
        });
        let eig = gram
            .self_adjoint_eigen(Side::Lower)
            .map_err(|e| TemplateError::Invalid(format!("pose PCA: {e:?}")))?;
        let (values, vectors) = (eig.S(), eig.U());
        // Eigenvalues come in ascending order.
        let k = k.min(n - 1);
        let mut components = Vec::with_capacity(k * d);
        let mut stddev = Vec::with_capacity(k);
        for c in (0..n).rev().take(k) {
            let lambda = values[c].max(0.0);
            let norm = lambda.sqrt().max(1e-12);
            let mut comp = vec![0.0f64; d];
            for (i, row) in centred.iter().enumerate() {
                let coeff = vectors[(i, c)] / norm;
                for (x, v) in comp.iter_mut().zip(row) {
                    *x += coeff * v;
                }
            }
            components.extend(comp.iter().map(|&x| x as f32));
            stddev.push((lambda / (n - 1) as f64).sqrt() as f32);
        }
        Ok(Self {
            mean: mean.iter().map(|&m| m as f32).collect(),
            components,
            stddev,
            sigma,
        })
    }

    /// Number of components.
    pub fn len(&self) -> usize {
        self.stddev.len()
    }

    /// True without components.
    pub fn is_empty(&self) -> bool {
        self.stddev.is_empty()
    }

    /// Coefficients of `x` (unclamped).
    pub fn coefficients(&self, x: &[f32]) -> Vec<f32> {
        let d = self.mean.len();
        (0..self.len())
            .map(|c| {
                self.components[c * d..(c + 1) * d]
                    .iter()
                    .zip(x.iter().zip(&self.mean))
                    .map(|(p, (v, m))| p * (v - m))
                    .sum()
            })
            .collect()
    }

    /// Projects `x` onto the components with clamped coefficients and reconstructs it.
    pub fn project(&self, x: &[f32]) -> Result<Vec<f32>, TemplateError> {
        let d = self.mean.len();
        if x.len() != d {
            return Err(TemplateError::Invalid(format!(
                "pose map of length {} for a PCA of length {d}",
                x.len()
            )));
        }
        let mut out = self.mean.clone();
        for (c, coeff) in self.coefficients(x).into_iter().enumerate() {
            let limit = self.sigma * self.stddev[c];
            let coeff = coeff.clamp(-limit, limit);
            for (o, p) in out.iter_mut().zip(&self.components[c * d..(c + 1) * d]) {
                *o += coeff * p;
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_a_low_rank_family_and_clamps_outliers() {
        // Samples on a 2-D plane in 50-D: two components reconstruct them exactly.
        let basis: Vec<Vec<f32>> = (0..2)
            .map(|c| {
                (0..50)
                    .map(|i| ((i * (c + 3)) as f32 * 0.37).sin())
                    .collect()
            })
            .collect();
        let samples: Vec<Vec<f32>> = (0..12)
            .map(|s| {
                (0..50)
                    .map(|i| {
                        1.0 + (s as f32 * 0.3).cos() * basis[0][i]
                            + (s as f32 * 0.7).sin() * 0.5 * basis[1][i]
                    })
                    .collect()
            })
            .collect();
        let pca = PosePca::fit(&samples, 5, 100.0).unwrap();
        for s in &samples {
            let r = pca.project(s).unwrap();
            assert!(r.iter().zip(s).all(|(a, b)| (a - b).abs() < 1e-4));
        }
        // A far outlier along the first component is clamped to σ standard deviations.
        let clamped = PosePca {
            sigma: 2.0,
            ..pca.clone()
        };
        let outlier: Vec<f32> = (0..50).map(|i| 1.0 + 50.0 * basis[0][i]).collect();
        let coeff = clamped.coefficients(&clamped.project(&outlier).unwrap())[0];
        assert!((coeff.abs() - 2.0 * clamped.stddev[0]).abs() < 1e-3 * clamped.stddev[0].max(1.0));
        match PosePca::fit(&samples[..1], 2, 2.0) {
            Err(TemplateError::Invalid(e)) => {
                assert_eq!(e, "pose PCA needs at least 2 training maps, got 1")
            }
            other => panic!("one sample gave {other:?}"),
        }
    }
}
