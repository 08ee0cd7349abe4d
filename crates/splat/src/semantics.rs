//! The rendering semantics every path shares — the readable reference, the CPU renderer and
//! the GPU kernels — as constants, options and input checks: what an image means does not
//! depend on which path made it.
//!
//! Semantics (gsplat 1.5.3's, identical in every path including [`crate::reference`]):
//! - a Gaussian is evaluated at every pixel centre (`i + 0.5`) inside its box
//!   `|u − μ_u| ≤ r_x`, `|v − μ_v| ≤ r_y` with the opacity-aware radii of [`crate::cpu::project`] ([`opacity_extent`]); the box
//!   holds every pixel where its `α ≥ 1/255`, so the image equals "every pixel, every visible
//!   Gaussian" and does not depend on the tile size;
//! - `α = min(α_max, o · exp(−½ dᵀ Σ₂ᴅ⁻¹ d))`; contributions with `α < 1/255` (or a positive
//!   exponent) are skipped;
//! - a pixel stops before the Gaussian that would bring its transmittance to `1e-4` or below
//!   (`T (1 − α) ≤ 1e-4`; that Gaussian is not composited);
//! - outputs: colour `Σ cᵢ αᵢ Tᵢ + T_final · background`, alpha `1 − T_final`, depth
//!   `Σ zᵢ αᵢ Tᵢ` (camera-space z, not normalised by alpha: gsplat's `D` mode).
//!
//! All arrays are flat and row-major: means `[N,3]`, log-scales `[N,3]`, quaternions `[N,4]`
//! (w, x, y, z), opacity logits `[N]`, SH `[N,K,3]`; images `[H,W,3]` and `[H,W]`.

use crate::real::Real;
use crate::{SplatError, sh};

/// Edge length of a square screen tile in pixels.
pub const TILE_SIZE: usize = 16;
/// Contributions below this alpha are skipped.
pub const ALPHA_MIN: f64 = 1.0 / 255.0;
/// A pixel stops compositing before its transmittance would fall to this or below.
pub const TRANSMITTANCE_MIN: f64 = 1e-4;
/// The most (Gaussian, tile) pairs a render lists: tile offsets are 32-bit (i32 on GPUs,
/// whose Int tensors are i32), and the lists would take tens of GB beyond it anyway.
pub const MAX_INTERSECTIONS: u64 = i32::MAX as u64;
/// Isotropic screen-space variance (pixels²) added to every projected covariance.
pub const LOW_PASS: f64 = 0.3;

/// Settings that change the rendered values.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderOptions {
    /// Upper clamp of a single Gaussian's alpha (3DGS: 0.99, gsplat: 0.999).
    pub alpha_max: f64,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self { alpha_max: 0.99 }
    }
}

impl RenderOptions {
    /// Checks that `alpha_max` lies in `[1/255, 1)`.
    pub fn validate(&self) -> Result<(), SplatError> {
        if !(self.alpha_max >= ALPHA_MIN && self.alpha_max < 1.0) {
            return Err(SplatError::Option {
                name: "alpha_max",
                reason: format!("{} is outside [1/255, 1)", self.alpha_max),
            });
        }
        Ok(())
    }
}

/// Borrowed Gaussian parameters (flat, row-major; see the module docs for layouts).
#[derive(Clone, Copy, Debug)]
pub struct GaussianSlices<'a, T> {
    pub means: &'a [T],
    pub log_scales: &'a [T],
    pub quats: &'a [T],
    pub opacity_logits: &'a [T],
    pub sh: &'a [T],
}

impl<'a, T: Real> GaussianSlices<'a, T> {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    /// True when there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.opacity_logits.is_empty()
    }

    /// SH coefficients per channel (K).
    pub fn sh_coeffs(&self) -> usize {
        self.sh.len().checked_div(3 * self.len()).unwrap_or(1)
    }

    /// Checks shapes and finiteness; errors name the field and the first bad index.
    pub fn validate(&self) -> Result<(), SplatError> {
        let n = self.len();
        let shape = |name, len: usize, per: usize, expected: &str| {
            if len != n * per {
                return Err(SplatError::Shape {
                    name,
                    got: vec![len],
                    expected: format!("{} values ({expected} with N = {n})", n * per),
                });
            }
            Ok(())
        };
        shape("means", self.means.len(), 3, "[N,3]")?;
        shape("log_scales", self.log_scales.len(), 3, "[N,3]")?;
        shape("quats", self.quats.len(), 4, "[N,4]")?;
        if n > 0 {
            if !self.sh.len().is_multiple_of(3 * n) {
                return Err(SplatError::Shape {
                    name: "sh",
                    got: vec![self.sh.len()],
                    expected: format!("N·K·3 values with N = {n}"),
                });
            }
            let k = self.sh.len() / (3 * n);
            if sh::degree_for(k).is_none() {
                return Err(SplatError::ShDegree { coeffs: k });
            }
        }
        let fields: [(&'static str, &[T]); 5] = [
            ("means", self.means),
            ("log_scales", self.log_scales),
            ("quats", self.quats),
            ("opacity_logits", self.opacity_logits),
            ("sh", self.sh),
        ];
        for (name, values) in fields {
            check_finite(name, values)?;
        }
        Ok(())
    }
}

/// Fails on the first NaN or infinity in `values`.
pub fn check_finite<T: Real>(name: &'static str, values: &[T]) -> Result<(), SplatError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(SplatError::NonFinite {
            name,
            index,
            value: values[index].f64(),
        }),
        None => Ok(()),
    }
}

/// Most standard deviations a footprint reaches (gsplat's cap; it binds only for `o > 1`).
pub const EXTENT_MAX_SIGMAS: f64 = 3.33;

/// Half-width in standard deviations of the region where `o · exp(−½ m²) ≥ 1/255`.
pub fn opacity_extent<T: Real>(opacity: T) -> T {
    (T::c(2.0) * (opacity / T::c(ALPHA_MIN)).ln())
        .max(T::zero())
        .sqrt()
        .min(T::c(EXTENT_MAX_SIGMAS))
}
