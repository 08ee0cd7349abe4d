//! The scalar type the CPU reference is generic over.
//!
//! Production renders in `f32`; the finite-difference tests instantiate the very same code in
//! `f64` so that analytic and numeric gradients can be compared to many digits.

/// A floating-point scalar usable by the CPU renderer (`f32` or `f64`).
pub trait Real:
    num_traits::Float + num_traits::FloatConst + Default + Send + Sync + std::fmt::Debug + 'static
{
    /// Converts an `f64` constant to this type (rounding for `f32`).
    fn c(x: f64) -> Self;
    /// Widens to `f64` (exact for both implementations).
    fn f64(self) -> f64;
    /// `exp` as the rasteriser evaluates it, for arguments `≤ 0`. In `f32` a branch-free
    /// polynomial (≤ 2 ulp from `f32::exp`) that the compiler can vectorise, with arguments
    /// below −25 clamped to −25: such a density gives an alpha under 10⁻¹⁰, far below the
    /// 1/255 cut-off, so nothing rendered changes, but lanes outside a footprint never produce
    /// subnormal floats (which cost the CPU a microcode assist each). In `f64` the standard
    /// `exp`. The reference renderer in the tests uses the same function.
    fn raster_exp(self) -> Self;
}

impl Real for f32 {
    #[inline(always)]
    fn c(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn f64(self) -> f64 {
        self as f64
    }
    #[inline(always)]
    fn raster_exp(self) -> Self {
        exp_f32(self)
    }
}

impl Real for f64 {
    #[inline(always)]
    fn c(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn f64(self) -> f64 {
        self
    }
    #[inline(always)]
    fn raster_exp(self) -> Self {
        self.exp()
    }
}

/// Cephes-style `expf`: `2^n · p(r)` with `n = round(x / ln 2)`, `r = x − n ln 2` (split in two
/// parts for accuracy) and a degree-6 polynomial in fused multiply-adds (single instructions in
/// the AVX2/AVX-512 kernels; exact `fmaf` elsewhere, so every caller gets identical values). It rounds with the 1.5·2²³ trick and builds
/// `2^n` from the mantissa bits of `n + 127 + 2²³`, avoiding `floor` and float→int casts so that
/// every step vectorises.
#[inline(always)]
fn exp_f32(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0;
    // Compare-and-select rather than `clamp`, which adds NaN handling that does not vectorise
    // to a single instruction (inputs are never NaN here).
    let x = if x > -25.0 { x } else { -25.0 };
    let x = if x < 88.0 { x } else { 88.0 };
    let n = (x * std::f32::consts::LOG2_E + MAGIC) - MAGIC;
    let r = x - n * 0.693_359_4 - n * -2.121_944_4e-4;
    let mut p = 1.987_569_2e-4f32;
    p = p.mul_add(r, 1.398_2e-3);
    p = p.mul_add(r, 8.333_452e-3);
    p = p.mul_add(r, 4.166_579_6e-2);
    p = p.mul_add(r, 0.166_666_65);
    p = p.mul_add(r, 0.5);
    let y = (p * r).mul_add(r, r) + 1.0;
    // n + 127 ∈ [1, 254] sits in the low mantissa bits of n + 127 + 2²³; shifting by 23 moves it
    // into the exponent field and drops the helper's own exponent bits.
    let biased = (n + (127.0 + 8_388_608.0)).to_bits() << 23;
    y * f32::from_bits(biased)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn raster_exp_matches_std_exp() {
        let mut worst = 0.0f64;
        for i in 0..=200_000 {
            let x = -25.0 * i as f32 / 200_000.0;
            let fast = exp_f32(x) as f64;
            let exact = (x as f64).exp();
            worst = worst.max((fast - exact).abs() / exact);
        }
        assert!(worst < 3e-7, "worst relative error {worst}");
        assert_eq!(exp_f32(0.0), 1.0);
        assert!((exp_f32(10.0) as f64 - 10f64.exp()).abs() < 3e-7 * 10f64.exp());
        // Far below the alpha cut-off the value saturates at exp(−25) instead of going subnormal.
        assert_eq!(exp_f32(-1e9), exp_f32(-25.0));
        assert!(exp_f32(-25.0) < 1.4e-11 && exp_f32(-25.0).is_normal());
    }
}
