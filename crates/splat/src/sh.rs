//! Real spherical harmonics up to degree 3, in the basis order and sign convention of 3DGS
//! and gsplat (`C0 = 0.2820947917738781`, degree-1 terms `-C1 y, C1 z, -C1 x`, ...).
//!
//! Colour from coefficients `f[k]` along a unit direction `d` (from the camera centre to the
//! Gaussian) is `max(0, 0.5 + Σ_k Y_k(d) f[k])` per channel.

use crate::real::Real;

/// Number of coefficients per colour channel for an SH degree.
pub const fn num_coeffs(degree: usize) -> usize {
    (degree + 1) * (degree + 1)
}

/// The SH degree for a coefficient count, if it is a valid one (1, 4, 9, 16).
pub fn degree_for(coeffs: usize) -> Option<usize> {
    (0..=3).find(|&d| num_coeffs(d) == coeffs)
}

/// `Y_0`, the constant basis function: degree-0 colour is `0.5 + SH_C0 · f_dc`.
pub const SH_C0: f64 = 0.282_094_791_773_878_14;
/// The degree-1 constant (`Y_1 = −C1·y`, `C1·z`, `−C1·x`).
pub const SH_C1: f64 = 0.488_602_511_902_919_9;
/// The degree-2 constants, in the basis order of [`basis`].
pub const SH_C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
const SH_C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// Evaluates the first `n` basis functions at unit direction `d` into `out[..n]`.
#[inline]
pub fn basis<T: Real>(n: usize, d: [T; 3], out: &mut [T; 16]) {
    let [x, y, z] = d;
    let c = T::c;
    out[0] = c(SH_C0);
    if n <= 1 {
        return;
    }
    out[1] = -c(SH_C1) * y;
    out[2] = c(SH_C1) * z;
    out[3] = -c(SH_C1) * x;
    if n <= 4 {
        return;
    }
    let (xx, yy, zz) = (x * x, y * y, z * z);
    out[4] = c(SH_C2[0]) * x * y;
    out[5] = c(SH_C2[1]) * y * z;
    out[6] = c(SH_C2[2]) * (c(2.0) * zz - xx - yy);
    out[7] = c(SH_C2[3]) * x * z;
    out[8] = c(SH_C2[4]) * (xx - yy);
    if n <= 9 {
        return;
    }
    out[9] = c(SH_C3[0]) * y * (c(3.0) * xx - yy);
    out[10] = c(SH_C3[1]) * x * y * z;
    out[11] = c(SH_C3[2]) * y * (c(4.0) * zz - xx - yy);
    out[12] = c(SH_C3[3]) * z * (c(2.0) * zz - c(3.0) * xx - c(3.0) * yy);
    out[13] = c(SH_C3[4]) * x * (c(4.0) * zz - xx - yy);
    out[14] = c(SH_C3[5]) * z * (xx - yy);
    out[15] = c(SH_C3[6]) * x * (xx - c(3.0) * yy);
}

/// Gradient with respect to the unit direction `d` of `Σ_k g[k] · Y_k(d)` over the first `n`
/// basis functions (the chain rule through the basis, before the normalisation of `d`).
#[inline]
pub fn basis_vjp<T: Real>(n: usize, d: [T; 3], g: &[T; 16]) -> [T; 3] {
    let [x, y, z] = d;
    let c = T::c;
    let mut out = [T::zero(); 3];
    if n <= 1 {
        return out;
    }
    let c1 = c(SH_C1);
    out[0] = out[0] - c1 * g[3];
    out[1] = out[1] - c1 * g[1];
    out[2] = out[2] + c1 * g[2];
    if n <= 4 {
        return out;
    }
    let (xx, yy, zz) = (x * x, y * y, z * z);
    let two = c(2.0);
    let k = SH_C2.map(c);
    // d/dx, d/dy, d/dz of each degree-2 basis function.
    let grads2 = [
        [k[0] * y, k[0] * x, T::zero()],
        [T::zero(), k[1] * z, k[1] * y],
        [-two * k[2] * x, -two * k[2] * y, c(4.0) * k[2] * z],
        [k[3] * z, T::zero(), k[3] * x],
        [two * k[4] * x, -two * k[4] * y, T::zero()],
    ];
    for (i, gr) in grads2.iter().enumerate() {
        for a in 0..3 {
            out[a] = out[a] + g[4 + i] * gr[a];
        }
    }
    if n <= 9 {
        return out;
    }
    let k = SH_C3.map(c);
    let three = c(3.0);
    let grads3 = [
        [c(6.0) * k[0] * x * y, k[0] * three * (xx - yy), T::zero()],
        [k[1] * y * z, k[1] * x * z, k[1] * x * y],
        [
            -two * k[2] * x * y,
            k[2] * (c(4.0) * zz - xx - three * yy),
            c(8.0) * k[2] * y * z,
        ],
        [
            -c(6.0) * k[3] * x * z,
            -c(6.0) * k[3] * y * z,
            k[3] * (c(6.0) * zz - three * xx - three * yy),
        ],
        [
            k[4] * (c(4.0) * zz - three * xx - yy),
            -two * k[4] * x * y,
            c(8.0) * k[4] * x * z,
        ],
        [two * k[5] * x * z, -two * k[5] * y * z, k[5] * (xx - yy)],
        [k[6] * three * (xx - yy), -c(6.0) * k[6] * x * y, T::zero()],
    ];
    for (i, gr) in grads3.iter().enumerate() {
        for a in 0..3 {
            out[a] = out[a] + g[9 + i] * gr[a];
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(v: [f64; 3]) -> [f64; 3] {
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        v.map(|x| x / n)
    }

    #[test]
    fn degree_table() {
        assert_eq!([0, 1, 2, 3].map(num_coeffs), [1, 4, 9, 16]);
        assert_eq!(degree_for(9), Some(2));
        assert_eq!(degree_for(5), None);
    }

    #[test]
    fn closed_form_values() {
        // Along +z only the zonal terms are non-zero: Y_2 = C1, Y_6 = 2 C2[2], Y_12 = 2 C3[3].
        let mut b = [0.0; 16];
        basis(16, [0.0, 0.0, 1.0], &mut b);
        for (k, v) in b.iter().enumerate() {
            let expected = match k {
                0 => SH_C0,
                2 => SH_C1,
                6 => 2.0 * SH_C2[2],
                12 => 2.0 * SH_C3[3],
                _ => 0.0,
            };
            assert!(
                (v - expected).abs() < 1e-15,
                "Y_{k}(+z) = {v}, expected {expected}"
            );
        }
    }

    #[test]
    fn orthonormal_on_the_sphere() {
        // Monte-Carlo-free check: a Fibonacci sphere quadrature of Y_i Y_j ≈ δ_ij / (4π)·4π.
        let n = 20_000;
        let mut gram = [[0.0f64; 16]; 16];
        for i in 0..n {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = i as f64 * std::f64::consts::PI * (3.0 - 5f64.sqrt());
            let mut b = [0.0; 16];
            basis(16, [r * phi.cos(), r * phi.sin(), z], &mut b);
            for a in 0..16 {
                for c in 0..16 {
                    gram[a][c] += b[a] * b[c] * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for (a, row) in gram.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                let expected = if a == c { 1.0 } else { 0.0 };
                assert!((v - expected).abs() < 2e-3, "<Y_{a}, Y_{c}> = {v}");
            }
        }
    }

    #[test]
    fn vjp_matches_finite_differences() {
        let d = unit([0.3, -0.5, 0.8]);
        let g: [f64; 16] = std::array::from_fn(|k| ((k * 7 + 3) % 11) as f64 / 5.0 - 1.0);
        let f = |d: [f64; 3]| {
            let mut b = [0.0; 16];
            basis(16, d, &mut b);
            b.iter().zip(&g).map(|(b, g)| b * g).sum::<f64>()
        };
        let analytic = basis_vjp(16, d, &g);
        for a in 0..3 {
            let h = 1e-6;
            let (mut p, mut m) = (d, d);
            p[a] += h;
            m[a] -= h;
            let numeric = (f(p) - f(m)) / (2.0 * h);
            assert!(
                (numeric - analytic[a]).abs() < 1e-7,
                "axis {a}: {numeric} vs {}",
                analytic[a]
            );
        }
    }
}
