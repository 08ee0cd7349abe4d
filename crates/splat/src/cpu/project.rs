//! Per-Gaussian projection to the screen (EWA splatting) and its analytic backward.
//!
//! For a Gaussian with mean `x`, log-scales `ℓ`, quaternion `q` (w, x, y, z), opacity logit
//! `a` and SH coefficients `f`, with the camera `x_c = W x + t`:
//! - `Σ = M Mᵀ`, `M = R(q/|q|) diag(exp ℓ)`;
//! - `Σ₂ᴅ = J W Σ Wᵀ Jᵀ + 0.3 I`, with the perspective Jacobian `J` evaluated at the camera
//!   point whose x/z and y/z are clamped to 1.3× the field of view (as 3DGS and gsplat do, so
//!   that far off-screen Gaussians do not blow up);
//! - mean `μ = (fx x_c/z + cx, fy y_c/z + cy)`, depth `z`, conic `Σ₂ᴅ⁻¹`;
//! - colour from SH along `normalize(x − camera centre)`, opacity `o = sigmoid(a)`;
//! - per-axis radii `⌈k √Σ₂ᴅ[0][0]⌉`, `⌈k √Σ₂ᴅ[1][1]⌉` with the opacity-aware extent
//!   `k = min(3.33, √(2 ln(255 o)))` (gsplat 1.5): the ellipse where `α = o e^{−½dᵀΣ⁻¹d}`
//!   reaches `1/255` has exactly these half-widths, so the box holds every pixel with
//!   `α ≥ 1/255` and the image does not depend on the box or the tile size.
//!
//! A Gaussian is culled (radii 0) when its depth is outside `[near, far]`, its 2D covariance
//! is degenerate (`det ≤ 0`), its quaternion is zero, its opacity is below `1/255`, or its box
//! holds no pixel centre.

use multiversion::multiversion;
use rayon::prelude::*;

use super::GaussianGrads;
use super::raster::pixel_box;
use crate::semantics::{ALPHA_MIN, GaussianSlices, LOW_PASS, opacity_extent};
use crate::{Camera, real::Real, sh};

/// One Gaussian on the screen, everything the rasteriser reads.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ScreenGaussian<T> {
    /// Mean in pixels.
    pub mean: [T; 2],
    /// Inverse 2D covariance `[a, b, c]` of `[[a, b], [b, c]]`.
    pub conic: [T; 3],
    /// RGB after SH evaluation and the clamp at 0.
    pub color: [T; 3],
    /// Opacity in (0, 1).
    pub opacity: T,
    /// Camera-space z (metres).
    pub depth: T,
    /// Footprint half-sizes in pixels along x and y; `[0, 0]` means culled.
    pub radii: [u32; 2],
    /// Pixels `[x0, x1) × [y0, y1)` of the footprint inside the image (see [`pixel_box`]).
    pub pixels: [u32; 4],
}

impl<T: Real> ScreenGaussian<T> {
    /// Whether the Gaussian survived culling.
    pub fn is_visible(&self) -> bool {
        self.radii != [0, 0]
    }

    /// Fills in `pixels` from the mean and radius; culls (radius 0) when no pixel is covered.
    pub fn with_footprint(mut self, width: usize, height: usize) -> Self {
        match self
            .is_visible()
            .then(|| pixel_box(&self, width, height))
            .flatten()
        {
            Some(b) => self.pixels = b.map(|v| v as u32),
            None => return Self::default(),
        }
        self
    }
}

/// The projected Gaussians, one per input (culled ones have radii 0).
pub type Projected<T> = Vec<ScreenGaussian<T>>;

/// Gradient of the loss with respect to one Gaussian's screen quantities.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ScreenGrads<T> {
    pub mean: [T; 2],
    pub conic: [T; 3],
    pub color: [T; 3],
    pub opacity: T,
    pub depth: T,
}

type M3<T> = [[T; 3]; 3];

/// Intermediate values of one Gaussian's projection, shared by forward and backward.
struct Frame<T> {
    /// Normalised quaternion and the norm of the raw one.
    q: [T; 4],
    q_norm: T,
    rot: M3<T>,
    scale: [T; 3],
    /// `R diag(s)`.
    m: M3<T>,
    /// Camera-space mean.
    p: [T; 3],
    /// Camera-space covariance `W Σ Wᵀ`.
    cov_cam: M3<T>,
    /// Clamped x and y used by the Jacobian, and whether each was clamped.
    tx: T,
    ty: T,
    x_clamped: bool,
    y_clamped: bool,
    jac: [[T; 3]; 2],
    /// 2D covariance with the low-pass filter.
    cov2d: [T; 3],
}

/// Camera constants in the working precision.
struct Cam<T> {
    w: M3<T>,
    t: [T; 3],
    fx: T,
    fy: T,
    cx: T,
    cy: T,
    lim_x: (T, T),
    lim_y: (T, T),
    near: T,
    far: T,
    center: [T; 3],
}

impl<T: Real> Cam<T> {
    fn new(camera: &Camera) -> Self {
        let (w, h) = (camera.width as f64, camera.height as f64);
        let (fx, fy, cx, cy) = (camera.fx(), camera.fy(), camera.cx(), camera.cy());
        let tan_x = 0.5 * w / fx;
        let tan_y = 0.5 * h / fy;
        Self {
            w: camera.r.map(|row| row.map(T::c)),
            t: camera.t.map(T::c),
            fx: T::c(fx),
            fy: T::c(fy),
            cx: T::c(cx),
            cy: T::c(cy),
            lim_x: (
                T::c(cx / fx + 0.3 * tan_x),
                T::c((w - cx) / fx + 0.3 * tan_x),
            ),
            lim_y: (
                T::c(cy / fy + 0.3 * tan_y),
                T::c((h - cy) / fy + 0.3 * tan_y),
            ),
            near: T::c(camera.near),
            far: T::c(camera.far),
            center: camera.center().map(T::c),
        }
    }
}

fn get3<T: Copy>(v: &[T], i: usize) -> [T; 3] {
    [v[3 * i], v[3 * i + 1], v[3 * i + 2]]
}

fn matmul<T: Real>(a: &M3<T>, b: &M3<T>) -> M3<T> {
    std::array::from_fn(|i| {
        std::array::from_fn(|j| a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j])
    })
}

fn transpose<T: Real>(a: &M3<T>) -> M3<T> {
    std::array::from_fn(|i| std::array::from_fn(|j| a[j][i]))
}

fn matvec<T: Real>(a: &M3<T>, v: [T; 3]) -> [T; 3] {
    std::array::from_fn(|i| a[i][0] * v[0] + a[i][1] * v[1] + a[i][2] * v[2])
}

/// Rotation matrix of a unit quaternion (w, x, y, z).
fn quat_to_rot<T: Real>(q: [T; 4]) -> M3<T> {
    let [w, x, y, z] = q;
    let (one, two) = (T::one(), T::c(2.0));
    [
        [
            one - two * (y * y + z * z),
            two * (x * y - w * z),
            two * (x * z + w * y),
        ],
        [
            two * (x * y + w * z),
            one - two * (x * x + z * z),
            two * (y * z - w * x),
        ],
        [
            two * (x * z - w * y),
            two * (y * z + w * x),
            one - two * (x * x + y * y),
        ],
    ]
}

/// Gradient with respect to the unit quaternion of `Σ G ∘ R(q)`.
fn quat_to_rot_vjp<T: Real>(q: [T; 4], g: &M3<T>) -> [T; 4] {
    let [w, x, y, z] = q;
    let two = T::c(2.0);
    let four = T::c(4.0);
    let dw =
        two * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1]);
    let dx = two
        * (y * g[0][1] + z * g[0][2] + y * g[1][0] - w * g[1][2] + z * g[2][0] + w * g[2][1])
        - four * x * (g[1][1] + g[2][2]);
    let dy = two
        * (x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2] - w * g[2][0] + z * g[2][1])
        - four * y * (g[0][0] + g[2][2]);
    let dz = two
        * (-w * g[0][1] + x * g[0][2] + w * g[1][0] + y * g[1][2] + x * g[2][0] + y * g[2][1])
        - four * z * (g[0][0] + g[1][1]);
    [dw, dx, dy, dz]
}

/// Forward intermediates of Gaussian `i`; `None` when culled by depth or a zero quaternion.
fn frame<T: Real>(g: &GaussianSlices<T>, cam: &Cam<T>, i: usize) -> Option<Frame<T>> {
    let raw_q = [
        g.quats[4 * i],
        g.quats[4 * i + 1],
        g.quats[4 * i + 2],
        g.quats[4 * i + 3],
    ];
    let q_norm = raw_q.iter().fold(T::zero(), |s, v| s + *v * *v).sqrt();
    let p = {
        let wp = matvec(&cam.w, get3(g.means, i));
        [wp[0] + cam.t[0], wp[1] + cam.t[1], wp[2] + cam.t[2]]
    };
    if q_norm <= T::zero() || q_norm.is_nan() || p[2] < cam.near || p[2] > cam.far {
        return None;
    }
    let q = raw_q.map(|v| v / q_norm);
    let rot = quat_to_rot(q);
    let scale = get3(g.log_scales, i).map(|l| l.exp());
    let m: M3<T> = std::array::from_fn(|r| std::array::from_fn(|c| rot[r][c] * scale[c]));
    let sigma = matmul(&m, &transpose(&m));
    let cov_cam = matmul(&matmul(&cam.w, &sigma), &transpose(&cam.w));
    let z = p[2];
    let (xz, yz) = (p[0] / z, p[1] / z);
    let x_clamped = xz < -cam.lim_x.0 || xz > cam.lim_x.1;
    let y_clamped = yz < -cam.lim_y.0 || yz > cam.lim_y.1;
    let tx = z * xz.max(-cam.lim_x.0).min(cam.lim_x.1);
    let ty = z * yz.max(-cam.lim_y.0).min(cam.lim_y.1);
    let jac = [
        [cam.fx / z, T::zero(), -cam.fx * tx / (z * z)],
        [T::zero(), cam.fy / z, -cam.fy * ty / (z * z)],
    ];
    // J Σc Jᵀ, 2×2 symmetric.
    let jc: [[T; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|c| {
            jac[r][0] * cov_cam[0][c] + jac[r][1] * cov_cam[1][c] + jac[r][2] * cov_cam[2][c]
        })
    });
    let entry =
        |r: usize, c: usize| jc[r][0] * jac[c][0] + jc[r][1] * jac[c][1] + jc[r][2] * jac[c][2];
    let low_pass = T::c(LOW_PASS);
    let cov2d = [entry(0, 0) + low_pass, entry(0, 1), entry(1, 1) + low_pass];
    Some(Frame {
        q,
        q_norm,
        rot,
        scale,
        m,
        p,
        cov_cam,
        tx,
        ty,
        x_clamped,
        y_clamped,
        jac,
        cov2d,
    })
}

/// Unit view direction from the camera centre to the mean, and the distance.
fn view_dir<T: Real>(mean: [T; 3], center: [T; 3]) -> ([T; 3], T) {
    let v = [
        mean[0] - center[0],
        mean[1] - center[1],
        mean[2] - center[2],
    ];
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if n > T::zero() {
        (v.map(|x| x / n), n)
    } else {
        ([T::zero(), T::zero(), T::one()], T::one())
    }
}

/// `0.5 + Σ_k Y_k f[k]` per channel (before the clamp) and the basis values.
fn sh_color<T: Real>(sh: &[T], k: usize, i: usize, dir: [T; 3]) -> ([T; 3], [T; 16]) {
    let mut basis = [T::zero(); 16];
    sh::basis(k, dir, &mut basis);
    let coeffs = &sh[i * k * 3..(i + 1) * k * 3];
    let mut raw = [T::c(0.5); 3];
    for (b, f) in basis[..k].iter().zip(coeffs.chunks_exact(3)) {
        for c in 0..3 {
            raw[c] = raw[c] + *b * f[c];
        }
    }
    (raw, basis)
}

fn sigmoid<T: Real>(x: T) -> T {
    T::one() / (T::one() + (-x).exp())
}

/// Projects every Gaussian (in parallel); culled ones get radii 0.
pub fn project<T: Real>(g: &GaussianSlices<T>, camera: &Camera) -> Projected<T> {
    let cam = Cam::new(camera);
    let k = g.sh_coeffs();
    let (width, height) = (camera.width as usize, camera.height as usize);
    (0..g.len())
        .into_par_iter()
        .map(|i| project_one(g, &cam, k, width, height, i))
        .collect()
}

/// Projects Gaussian `i` (compiled for AVX2/AVX-512 too, for inline rounding and FMA).
#[multiversion(targets(
    "x86_64+avx512f+avx512vl+avx512bw+avx512dq+avx2+fma",
    "x86_64+avx2+fma"
))]
fn project_one<T: Real>(
    g: &GaussianSlices<T>,
    cam: &Cam<T>,
    k: usize,
    width: usize,
    height: usize,
    i: usize,
) -> ScreenGaussian<T> {
    let Some(f) = frame(g, cam, i) else {
        return ScreenGaussian::default();
    };
    let [a, b, c] = f.cov2d;
    let det = a * c - b * b;
    let opacity = sigmoid(g.opacity_logits[i]);
    if det <= T::zero() || det.is_nan() || opacity < T::c(ALPHA_MIN) {
        return ScreenGaussian::default();
    }
    let extent = opacity_extent(opacity);
    let radius = |variance: T| {
        (extent * variance.sqrt())
            .ceil()
            .to_f64()
            .unwrap_or(0.0)
            .min(u32::MAX as f64) as u32
    };
    let z = f.p[2];
    let mean = [cam.fx * f.p[0] / z + cam.cx, cam.fy * f.p[1] / z + cam.cy];
    let (dir, _) = view_dir(get3(g.means, i), cam.center);
    let (raw, _) = sh_color(g.sh, k, i, dir);
    ScreenGaussian {
        mean,
        conic: [c / det, -b / det, a / det],
        color: raw.map(|v| v.max(T::zero())),
        opacity,
        depth: z,
        radii: [radius(a), radius(c)],
        pixels: [0; 4],
    }
    .with_footprint(width, height)
}

/// Chains screen-space gradients back to the Gaussian parameters (in parallel).
pub fn project_backward<T: Real>(
    g: &GaussianSlices<T>,
    camera: &Camera,
    projected: &Projected<T>,
    screen: &[ScreenGrads<T>],
) -> GaussianGrads<T> {
    let cam = Cam::new(camera);
    let n = g.len();
    let k = g.sh_coeffs();
    let mut out = GaussianGrads {
        means: vec![T::zero(); 3 * n],
        log_scales: vec![T::zero(); 3 * n],
        quats: vec![T::zero(); 4 * n],
        opacity_logits: vec![T::zero(); n],
        sh: vec![T::zero(); 3 * k * n],
        background: [T::zero(); 3],
        means2d: vec![T::zero(); 2 * n],
    };
    out.means
        .par_chunks_mut(3)
        .zip(out.log_scales.par_chunks_mut(3))
        .zip(out.quats.par_chunks_mut(4))
        .zip(out.opacity_logits.par_iter_mut())
        .zip(out.sh.par_chunks_mut(3 * k))
        .zip(out.means2d.par_chunks_mut(2))
        .enumerate()
        .for_each(
            |(i, (((((d_mean, d_log_scale), d_quat), d_opacity), d_sh), d_mean2d))| {
                let grads = OneGrads {
                    mean: d_mean,
                    log_scale: d_log_scale,
                    quat: d_quat,
                    opacity: d_opacity,
                    sh: d_sh,
                    mean2d: d_mean2d,
                };
                backward_one(g, &cam, k, &projected[i], &screen[i], i, grads);
            },
        );
    out
}

/// Gradient slots of one Gaussian.
struct OneGrads<'a, T> {
    mean: &'a mut [T],
    log_scale: &'a mut [T],
    quat: &'a mut [T],
    opacity: &'a mut T,
    sh: &'a mut [T],
    mean2d: &'a mut [T],
}

/// The backward of [`project_one`] for Gaussian `i`.
#[multiversion(targets(
    "x86_64+avx512f+avx512vl+avx512bw+avx512dq+avx2+fma",
    "x86_64+avx2+fma"
))]
fn backward_one<T: Real>(
    g: &GaussianSlices<T>,
    cam: &Cam<T>,
    k: usize,
    projected: &ScreenGaussian<T>,
    s: &ScreenGrads<T>,
    i: usize,
    out: OneGrads<'_, T>,
) {
    let OneGrads {
        mean: d_mean,
        log_scale: d_log_scale,
        quat: d_quat,
        opacity: d_opacity,
        sh: d_sh,
        mean2d: d_mean2d,
    } = out;

    if !projected.is_visible() {
        return;
    }
    let Some(f) = frame(g, cam, i) else { return };

    d_mean2d.copy_from_slice(&s.mean);
    let zero = T::zero();

    // Opacity: sigmoid'.
    let o = projected.opacity;
    *d_opacity = s.opacity * o * (T::one() - o);

    // Colour: clamp at 0, then SH coefficients and the view direction.
    let mean = get3(g.means, i);
    let (dir, dist) = view_dir(mean, cam.center);
    let (raw, basis) = sh_color(g.sh, k, i, dir);
    let d_raw: [T; 3] = std::array::from_fn(|c| if raw[c] > zero { s.color[c] } else { zero });
    let mut d_basis = [zero; 16];
    let coeffs = &g.sh[i * k * 3..(i + 1) * k * 3];
    for j in 0..k {
        for c in 0..3 {
            d_sh[3 * j + c] = basis[j] * d_raw[c];
            d_basis[j] = d_basis[j] + coeffs[3 * j + c] * d_raw[c];
        }
    }
    let d_dir = sh::basis_vjp(k, dir, &d_basis);
    let radial = d_dir[0] * dir[0] + d_dir[1] * dir[1] + d_dir[2] * dir[2];
    let mut d_x: [T; 3] = std::array::from_fn(|a| (d_dir[a] - radial * dir[a]) / dist);

    // Conic = Σ₂ᴅ⁻¹: dL/dΣ₂ᴅ = −K G K with G the symmetric conic gradient.
    let [a, b, c] = f.cov2d;
    let det = a * c - b * b;
    let kk = [[c / det, -b / det], [-b / det, a / det]];
    let half = T::c(0.5);
    let gk = [
        [s.conic[0], half * s.conic[1]],
        [half * s.conic[1], s.conic[2]],
    ];
    let kg: [[T; 2]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|cc| kk[r][0] * gk[0][cc] + kk[r][1] * gk[1][cc])
    });
    let g2: [[T; 2]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|cc| -(kg[r][0] * kk[0][cc] + kg[r][1] * kk[1][cc]))
    });

    // Σ₂ᴅ = J Σc Jᵀ: dL/dΣc = Jᵀ G J, dL/dJ = 2 G J Σc.
    let jac = &f.jac;
    let d_cov_cam: M3<T> = std::array::from_fn(|r| {
        std::array::from_fn(|cc| {
            let mut acc = zero;
            for u in 0..2 {
                for v in 0..2 {
                    acc = acc + jac[u][r] * g2[u][v] * jac[v][cc];
                }
            }
            acc
        })
    });
    let jsc: [[T; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|cc| {
            jac[r][0] * f.cov_cam[0][cc]
                + jac[r][1] * f.cov_cam[1][cc]
                + jac[r][2] * f.cov_cam[2][cc]
        })
    });
    let two = T::c(2.0);
    let d_jac: [[T; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|cc| two * (g2[r][0] * jsc[0][cc] + g2[r][1] * jsc[1][cc]))
    });

    // Σc = W Σ Wᵀ, Σ = M Mᵀ, M = R diag(s).
    let d_sigma = matmul(&matmul(&transpose(&cam.w), &d_cov_cam), &cam.w);
    let d_m: M3<T> = std::array::from_fn(|r| {
        std::array::from_fn(|cc| {
            two * (d_sigma[r][0] * f.m[0][cc]
                + d_sigma[r][1] * f.m[1][cc]
                + d_sigma[r][2] * f.m[2][cc])
        })
    });
    let d_rot: M3<T> = std::array::from_fn(|r| std::array::from_fn(|cc| d_m[r][cc] * f.scale[cc]));
    for j in 0..3 {
        let d_s = d_m[0][j] * f.rot[0][j] + d_m[1][j] * f.rot[1][j] + d_m[2][j] * f.rot[2][j];
        d_log_scale[j] = d_s * f.scale[j];
    }
    let d_qn = quat_to_rot_vjp(f.q, &d_rot);
    let along = d_qn[0] * f.q[0] + d_qn[1] * f.q[1] + d_qn[2] * f.q[2] + d_qn[3] * f.q[3];
    for j in 0..4 {
        d_quat[j] = (d_qn[j] - along * f.q[j]) / f.q_norm;
    }

    // Camera-space mean: through the 2D mean, the depth and the Jacobian.
    let [px, py, z] = f.p;
    let (fx, fy) = (cam.fx, cam.fy);
    let z2 = z * z;
    let z3 = z2 * z;
    let mut d_p = [
        s.mean[0] * fx / z,
        s.mean[1] * fy / z,
        -s.mean[0] * fx * px / z2 - s.mean[1] * fy * py / z2 + s.depth,
    ];
    d_p[2] = d_p[2] - d_jac[0][0] * fx / z2 - d_jac[1][1] * fy / z2
        + d_jac[0][2] * two * fx * f.tx / z3
        + d_jac[1][2] * two * fy * f.ty / z3;
    let d_tx = -d_jac[0][2] * fx / z2;
    let d_ty = -d_jac[1][2] * fy / z2;
    // tx = z·clamp(x/z): ∂/∂x = 1 inside the limits; ∂/∂z = tx/z when clamped.
    if f.x_clamped {
        d_p[2] = d_p[2] + d_tx * f.tx / z;
    } else {
        d_p[0] = d_p[0] + d_tx;
    }
    if f.y_clamped {
        d_p[2] = d_p[2] + d_ty * f.ty / z;
    } else {
        d_p[1] = d_p[1] + d_ty;
    }
    let d_world = matvec(&transpose(&cam.w), d_p);
    for a in 0..3 {
        d_x[a] = d_x[a] + d_world[a];
    }
    d_mean.copy_from_slice(&d_x);
}
