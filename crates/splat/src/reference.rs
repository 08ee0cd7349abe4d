//! The readable reference renderer: gsplat 1.5.3's semantics written as plainly as possible.
//!
//! This is the specification the fast paths are tested against — the multi-threaded CPU op
//! in [`crate::cpu`] and any GPU kernels — as gsplat keeps `_torch_impl.py` beside its CUDA.
//! It shares nothing with them but the SH basis ([`crate::sh`]) and the exponential
//! ([`Real::raster_exp`], so that `f32` results can be compared to the last bit): its own
//! projection, no tiles, no footprint boxes, no early exit per tile. Every visible Gaussian is
//! evaluated at every pixel, in (depth, index) order. It is slow (O(pixels × Gaussians)) and
//! meant for small scenes.
//!
//! Per Gaussian (camera `x_c = R x + t`, intrinsics `fx, fy, cx, cy`, image `W × H`):
//! 1. culled when `z < near`, `z > far`, or the quaternion is zero;
//! 2. `Σ = R(q̂) S² R(q̂)ᵀ`, `Σc = R Σ Rᵀ`; the Jacobian is evaluated at `x/z`, `y/z` clamped to
//!    `[−cx/fx − 0.3·tan, (W − cx)/fx + 0.3·tan]` with `tan = W/(2 fx)` (same for y);
//!    `Σ₂ᴅ = J Σc Jᵀ + 0.3 I`, culled when `det Σ₂ᴅ ≤ 0`;
//! 3. `o = sigmoid(logit)`, culled when `o < 1/255`; radii `⌈k √Σ₂ᴅ[i][i]⌉` with
//!    `k = min(3.33, √(2 ln(255 o)))`, culled when the box holds no pixel centre;
//! 4. colour `max(0, 0.5 + Σ Y_k(d̂) f_k)` with `d̂` from the camera centre to the mean.
//!
//! Per pixel (centre `i + 0.5`), front to back: `σ = ½ dᵀ Σ₂ᴅ⁻¹ d`, skip when `σ < 0`;
//! `α = min(α_max, o e^{−σ})`, skip when `α < 1/255`; stop (exclusive) when `T (1 − α) ≤ 1e-4`;
//! `C += c α T`, `D += z α T`, `T ← T (1 − α)`; finally `C += T · background`, `A = 1 − T`.
//!
//! `crates/splat/GSPLAT.md` records gsplat's forward and backward formulas in full (with the
//! source lines they come from), for the GPU kernels.
//!
//! The Gaussian's box (step 3) is not used when compositing: the reference shows that the box
//! loses nothing, which is what lets the fast paths skip everything outside it.

use crate::cpu::{ScreenGaussian as Screen, pixel_box};
use crate::semantics::{
    ALPHA_MIN, EXTENT_MAX_SIGMAS, GaussianSlices, LOW_PASS, RenderOptions, TRANSMITTANCE_MIN,
};
use crate::{Camera, Real, sh};

/// One pixel's discrete decisions: the Gaussians composited (with whether their alpha was
/// clamped at `α_max`) and the Gaussian before which it stopped, if any. Finite-difference tests
/// use them to tell a smooth neighbourhood from a jump.
pub type PixelDecisions = (Vec<(u32, bool)>, Option<u32>);

/// Every discrete decision of a render.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Signature {
    /// Per Gaussian, the radii `[x, y]` (`[0, 0]` when culled).
    pub radii: Vec<[u32; 2]>,
    /// Per pixel, row-major.
    pub pixels: Vec<PixelDecisions>,
}

/// A reference render.
#[derive(Clone, Debug)]
pub struct Reference<T> {
    /// `[H,W,3]`, background composited.
    pub color: Vec<T>,
    /// `[H,W]`
    pub alpha: Vec<T>,
    /// `[H,W]`, `Σ zᵢ αᵢ Tᵢ`.
    pub depth: Vec<T>,
    /// The projected Gaussians (culled ones are `None`).
    pub projected: Vec<Option<Screen<T>>>,
    pub signature: Signature,
}

/// Projects Gaussian `i`; `None` when culled.
pub fn project_one<T: Real>(g: &GaussianSlices<T>, camera: &Camera, i: usize) -> Option<Screen<T>> {
    let c = T::c;
    let mean: [T; 3] = std::array::from_fn(|k| g.means[3 * i + k]);
    let r = camera.r.map(|row| row.map(c));
    let p: [T; 3] = std::array::from_fn(|row| {
        r[row][0] * mean[0] + r[row][1] * mean[1] + r[row][2] * mean[2] + c(camera.t[row])
    });
    let z = p[2];
    if z < c(camera.near) || z > c(camera.far) {
        return None;
    }

    let q: [T; 4] = std::array::from_fn(|k| g.quats[4 * i + k]);
    let norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if norm <= T::zero() || norm.is_nan() {
        return None;
    }
    let [w, x, y, zq] = q.map(|v| v / norm);
    let (one, two) = (T::one(), c(2.0));
    let rot = [
        [
            one - two * (y * y + zq * zq),
            two * (x * y - w * zq),
            two * (x * zq + w * y),
        ],
        [
            two * (x * y + w * zq),
            one - two * (x * x + zq * zq),
            two * (y * zq - w * x),
        ],
        [
            two * (x * zq - w * y),
            two * (y * zq + w * x),
            one - two * (x * x + y * y),
        ],
    ];
    let s: [T; 3] = std::array::from_fn(|k| g.log_scales[3 * i + k].exp());
    // Σ = Σ_k s_k² r_k r_kᵀ (columns r_k of the rotation).
    let sigma: [[T; 3]; 3] = std::array::from_fn(|a| {
        std::array::from_fn(|b| {
            (0..3).fold(T::zero(), |acc, k| {
                acc + rot[a][k] * rot[b][k] * s[k] * s[k]
            })
        })
    });
    let sigma_cam: [[T; 3]; 3] = std::array::from_fn(|a| {
        std::array::from_fn(|b| {
            let mut acc = T::zero();
            for m in 0..3 {
                for n in 0..3 {
                    acc = acc + r[a][m] * sigma[m][n] * r[b][n];
                }
            }
            acc
        })
    });

    let (fx, fy, cx, cy) = (camera.fx(), camera.fy(), camera.cx(), camera.cy());
    let (width, height) = (camera.width as f64, camera.height as f64);
    let tan_x = 0.5 * width / fx;
    let tan_y = 0.5 * height / fy;
    let clamp = |v: T, lo: f64, hi: f64| v.max(c(lo)).min(c(hi));
    let tx = z * clamp(
        p[0] / z,
        -(cx / fx + 0.3 * tan_x),
        (width - cx) / fx + 0.3 * tan_x,
    );
    let ty = z * clamp(
        p[1] / z,
        -(cy / fy + 0.3 * tan_y),
        (height - cy) / fy + 0.3 * tan_y,
    );
    let jac = [
        [c(fx) / z, T::zero(), -c(fx) * tx / (z * z)],
        [T::zero(), c(fy) / z, -c(fy) * ty / (z * z)],
    ];
    let cov = |a: usize, b: usize| {
        let mut acc = T::zero();
        for m in 0..3 {
            for n in 0..3 {
                acc = acc + jac[a][m] * sigma_cam[m][n] * jac[b][n];
            }
        }
        acc
    };
    let (ca, cb, cc) = (cov(0, 0) + c(LOW_PASS), cov(0, 1), cov(1, 1) + c(LOW_PASS));
    let det = ca * cc - cb * cb;
    if det <= T::zero() || det.is_nan() {
        return None;
    }

    let opacity = one / (one + (-g.opacity_logits[i]).exp());
    if opacity < c(ALPHA_MIN) {
        return None;
    }
    let extent = (two * (opacity / c(ALPHA_MIN)).ln())
        .max(T::zero())
        .sqrt()
        .min(c(EXTENT_MAX_SIGMAS));
    let radius = |variance: T| (extent * variance.sqrt()).ceil().f64().min(u32::MAX as f64) as u32;

    let center = camera.center().map(c);
    let v: [T; 3] = std::array::from_fn(|k| mean[k] - center[k]);
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let dir = if len > T::zero() {
        v.map(|e| e / len)
    } else {
        [T::zero(), T::zero(), one]
    };
    let k = g.sh_coeffs();
    let mut basis = [T::zero(); 16];
    sh::basis(k, dir, &mut basis);
    let color: [T; 3] = std::array::from_fn(|ch| {
        (0..k)
            .fold(c(0.5), |acc, j| acc + basis[j] * g.sh[(i * k + j) * 3 + ch])
            .max(T::zero())
    });

    let screen = Screen {
        mean: [c(fx) * p[0] / z + c(cx), c(fy) * p[1] / z + c(cy)],
        conic: [cc / det, -cb / det, ca / det],
        color,
        opacity,
        depth: z,
        radii: [radius(ca), radius(cc)],
        pixels: [0; 4],
    };
    let pixels = pixel_box(&screen, camera.width as usize, camera.height as usize)?;
    Some(Screen {
        pixels: pixels.map(|v| v as u32),
        ..screen
    })
}

/// Renders by compositing every visible Gaussian at every pixel (no validation: give it
/// finite inputs of the right shapes).
pub fn render<T: Real>(
    g: &GaussianSlices<T>,
    camera: &Camera,
    background: [T; 3],
    options: &RenderOptions,
) -> Reference<T> {
    let projected: Vec<Option<Screen<T>>> =
        (0..g.len()).map(|i| project_one(g, camera, i)).collect();
    let mut order: Vec<usize> = (0..projected.len())
        .filter(|&i| projected[i].is_some())
        .collect();
    let depth = |i: usize| projected[i].as_ref().map_or(T::zero(), |p| p.depth);
    order.sort_by(|&a, &b| depth(a).partial_cmp(&depth(b)).unwrap().then(a.cmp(&b)));

    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut out = Reference {
        color: vec![T::zero(); w * h * 3],
        alpha: vec![T::zero(); w * h],
        depth: vec![T::zero(); w * h],
        signature: Signature {
            radii: projected
                .iter()
                .map(|p| p.as_ref().map_or([0, 0], |p| p.radii))
                .collect(),
            pixels: Vec::with_capacity(w * h),
        },
        projected: Vec::new(),
    };
    let (alpha_max, alpha_min, t_min) = (
        T::c(options.alpha_max),
        T::c(ALPHA_MIN),
        T::c(TRANSMITTANCE_MIN),
    );
    for py in 0..h {
        for px in 0..w {
            let (u, v) = (T::c(px as f64 + 0.5), T::c(py as f64 + 0.5));
            let mut t = T::one();
            let mut rgb = [T::zero(); 3];
            let mut z = T::zero();
            let mut contributions = Vec::new();
            let mut stop = None;
            for &i in &order {
                let p = projected[i]
                    .as_ref()
                    .expect("only visible Gaussians are ordered");
                let (dx, dy) = (u - p.mean[0], v - p.mean[1]);
                let sigma = T::c(0.5) * (p.conic[0] * dx * dx + p.conic[2] * dy * dy)
                    + p.conic[1] * dx * dy;
                if sigma < T::zero() {
                    continue;
                }
                let raw = p.opacity * (-sigma).raster_exp();
                let a = raw.min(alpha_max);
                if a < alpha_min {
                    continue;
                }
                let next_t = t * (T::one() - a);
                if next_t <= t_min {
                    stop = Some(i as u32);
                    break;
                }
                for (acc, col) in rgb.iter_mut().zip(p.color) {
                    *acc = *acc + a * t * col;
                }
                z = z + a * t * p.depth;
                t = next_t;
                contributions.push((i as u32, raw >= alpha_max));
            }
            let o = py * w + px;
            for ch in 0..3 {
                out.color[3 * o + ch] = rgb[ch] + t * background[ch];
            }
            out.alpha[o] = T::one() - t;
            out.depth[o] = z;
            out.signature.pixels.push((contributions, stop));
        }
    }
    out.projected = projected;
    out
}
