//! Gaussians in host memory: the exchange format between files, tensors and the CPU renderer.

use burn::tensor::{Device, Tensor, TensorData};

use crate::semantics::GaussianSlices;
use crate::{Gaussians, SplatError, sh};

/// Gaussian parameters as flat `f32` arrays (layouts as in [`crate::cpu`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianCloud {
    /// `[N, 3]`
    pub means: Vec<f32>,
    /// `[N, 3]`
    pub log_scales: Vec<f32>,
    /// `[N, 4]` (w, x, y, z)
    pub quats: Vec<f32>,
    /// `[N]`
    pub opacity_logits: Vec<f32>,
    /// `[N, K, 3]`
    pub sh: Vec<f32>,
    /// SH degree, 0..=3 (K = (degree + 1)²).
    pub sh_degree: usize,
}

impl GaussianCloud {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    /// True when there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.opacity_logits.is_empty()
    }

    /// SH coefficients per channel.
    pub fn sh_coeffs(&self) -> usize {
        sh::num_coeffs(self.sh_degree)
    }

    /// The same Gaussians with SH degree `degree` (≥ the current one), the new coefficients
    /// zero: the same colours, in the layout of tools that read only degree-3 files.
    pub fn padded_to_degree(self, degree: usize) -> Self {
        let (k, k2) = (self.sh_coeffs(), sh::num_coeffs(degree.max(self.sh_degree)));
        if k2 == k {
            return self;
        }
        let mut sh = vec![0.0; self.len() * k2 * 3];
        for (dst, src) in sh.chunks_exact_mut(k2 * 3).zip(self.sh.chunks_exact(k * 3)) {
            dst[..k * 3].copy_from_slice(src);
        }
        Self {
            sh,
            sh_degree: degree.max(self.sh_degree),
            ..self
        }
    }

    /// Borrowed view for the CPU renderer.
    pub fn slices(&self) -> GaussianSlices<'_, f32> {
        GaussianSlices {
            means: &self.means,
            log_scales: &self.log_scales,
            quats: &self.quats,
            opacity_logits: &self.opacity_logits,
            sh: &self.sh,
        }
    }

    /// Checks shapes, the SH degree and finiteness.
    pub fn validate(&self) -> Result<(), SplatError> {
        if self.sh_degree > 3 {
            return Err(SplatError::ShDegree {
                coeffs: self.sh_coeffs(),
            });
        }
        self.slices().validate()?;
        if self.sh.len() != self.len() * self.sh_coeffs() * 3 {
            return Err(SplatError::Shape {
                name: "sh",
                got: vec![self.sh.len()],
                expected: format!(
                    "N·K·3 = {} values for degree {}",
                    self.len() * self.sh_coeffs() * 3,
                    self.sh_degree
                ),
            });
        }
        Ok(())
    }

    /// Uploads to tensors on `device`.
    pub fn to_tensors(&self, device: &Device) -> Gaussians {
        let n = self.len();
        let k = self.sh_coeffs();
        let t2 = |v: &Vec<f32>, c: usize| {
            Tensor::<2>::from_data(TensorData::new(v.clone(), [n, c]), device)
        };
        Gaussians {
            means: t2(&self.means, 3),
            log_scales: t2(&self.log_scales, 3),
            quats: t2(&self.quats, 4),
            opacity_logits: Tensor::<1>::from_data(
                TensorData::new(self.opacity_logits.clone(), [n]),
                device,
            ),
            sh: Tensor::<3>::from_data(TensorData::new(self.sh.clone(), [n, k, 3]), device),
        }
    }

    /// Downloads tensors (any device) into host memory.
    pub fn from_tensors(g: &Gaussians) -> Result<Self, SplatError> {
        g.validate_shapes()?;
        let k = g.sh.dims()[1];
        let host = |t: TensorData, name: &'static str| {
            t.try_into_vec_as::<f32>().map_err(|e| SplatError::Shape {
                name,
                got: vec![],
                expected: format!("readable f32 data ({e:?})"),
            })
        };
        Ok(Self {
            means: host(g.means.to_data(), "means")?,
            log_scales: host(g.log_scales.to_data(), "log_scales")?,
            quats: host(g.quats.to_data(), "quats")?,
            opacity_logits: host(g.opacity_logits.to_data(), "opacity_logits")?,
            sh: host(g.sh.to_data(), "sh")?,
            sh_degree: sh::degree_for(k).ok_or(SplatError::ShDegree { coeffs: k })?,
        })
    }
}
