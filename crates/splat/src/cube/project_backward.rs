//! The projection's backward on the GPU: one unit per Gaussian turns its screen-space
//! gradient (mean, conic, colour, opacity, depth) into gradients of the means, log-scales,
//! quaternions, opacity logits and SH coefficients — the formulas of
//! [`crate::cpu::project_backward`] (and `crates/splat/GSPLAT.md`), step for step: sigmoid;
//! SH colour clamped at 0 and its view direction; `dL/dΣ₂ᴅ = −K G K` for the conic;
//! `Σ₂ᴅ = J Σc Jᵀ` with the field-of-view clamp of the Jacobian; `Σc = W R S Sᵀ Rᵀ Wᵀ`; the
//! perspective division of the mean. Culled Gaussians get zeros.

use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::{DType, Shape, TensorData};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::CubeDim;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;

#[cfg(feature = "cuda-source")]
use super::cuda_source::{CudaTarget, KernelSource, tensor};
use super::project::camera_constants;
use super::scan::{MAX_ROW, grid};
use crate::Camera;
use crate::op::GaussianTensors;
use crate::semantics::LOW_PASS;

/// Units per cube.
const UNITS: usize = 256;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use crate::cube::project::kernels::sh_basis;

    /// `out[a] = Σ_k g[k] ∂Y_k/∂d_a` at the unit direction `(x, y, z)` over the first `k`
    /// basis functions ([`crate::sh::basis_vjp`]).
    #[cube]
    fn sh_basis_vjp(
        x: f32,
        y: f32,
        z: f32,
        g: &Array<f32>,
        out: &mut Array<f32>,
        #[comptime] k: usize,
    ) {
        out[0] = 0.0f32;
        out[1] = 0.0f32;
        out[2] = 0.0f32;
        if comptime![k > 1] {
            let c1 = 0.488_602_5f32;
            out[0] -= c1 * g[3];
            out[1] -= c1 * g[1];
            out[2] += c1 * g[2];
        }
        if comptime![k > 4] {
            let k0 = 1.092_548_4f32;
            let k1 = -1.092_548_4f32;
            let k2 = 0.315_391_57f32;
            let k3 = -1.092_548_4f32;
            let k4 = 0.546_274_24f32;
            out[0] +=
                g[4] * k0 * y - g[6] * 2.0f32 * k2 * x + g[7] * k3 * z + g[8] * 2.0f32 * k4 * x;
            out[1] +=
                g[4] * k0 * x + g[5] * k1 * z - g[6] * 2.0f32 * k2 * y - g[8] * 2.0f32 * k4 * y;
            out[2] += g[5] * k1 * y + g[6] * 4.0f32 * k2 * z + g[7] * k3 * x;
        }
        if comptime![k > 9] {
            let (xx, yy, zz) = (x * x, y * y, z * z);
            let k0 = -0.590_043_6f32;
            let k1 = 2.890_611_4f32;
            let k2 = -0.457_045_8f32;
            let k3 = 0.373_176_33f32;
            let k4 = -0.457_045_8f32;
            let k5 = 1.445_305_7f32;
            let k6 = -0.590_043_6f32;
            out[0] += g[9] * 6.0f32 * k0 * x * y + g[10] * k1 * y * z
                - g[11] * 2.0f32 * k2 * x * y
                - g[12] * 6.0f32 * k3 * x * z
                + g[13] * k4 * (4.0f32 * zz - 3.0f32 * xx - yy)
                + g[14] * 2.0f32 * k5 * x * z
                + g[15] * k6 * 3.0f32 * (xx - yy);
            out[1] += g[9] * k0 * 3.0f32 * (xx - yy)
                + g[10] * k1 * x * z
                + g[11] * k2 * (4.0f32 * zz - xx - 3.0f32 * yy)
                - g[12] * 6.0f32 * k3 * y * z
                - g[13] * 2.0f32 * k4 * x * y
                - g[14] * 2.0f32 * k5 * y * z
                - g[15] * 6.0f32 * k6 * x * y;
            out[2] += g[10] * k1 * x * y
                + g[11] * 8.0f32 * k2 * y * z
                + g[12] * k3 * (6.0f32 * zz - 3.0f32 * xx - 3.0f32 * yy)
                + g[13] * 8.0f32 * k4 * x * z
                + g[14] * k5 * (xx - yy);
        }
    }

    /// The backward of `project` for Gaussian `ABSOLUTE_POS`; `cam` is
    /// `project::camera_constants`, `grads` the screen-space gradient `[N, 10]`.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn project_backward(
        means: &Tensor<f32>,
        log_scales: &Tensor<f32>,
        quats: &Tensor<f32>,
        sh: &Tensor<f32>,
        cam: &Tensor<f32>,
        screen: &Tensor<f32>,
        radii: &Tensor<i32>,
        grads: &Tensor<f32>,
        d_means: &mut Tensor<f32>,
        d_log_scales: &mut Tensor<f32>,
        d_quats: &mut Tensor<f32>,
        d_opacity: &mut Tensor<f32>,
        d_sh: &mut Tensor<f32>,
        low_pass: f32,
        #[comptime] sh_coeffs: usize,
    ) {
        let i = ABSOLUTE_POS;
        if i >= d_opacity.len() {
            terminate!();
        }
        let base = i * sh_coeffs * 3;
        for a in 0..3usize {
            d_means[3 * i + a] = 0.0f32;
            d_log_scales[3 * i + a] = 0.0f32;
        }
        for a in 0..4usize {
            d_quats[4 * i + a] = 0.0f32;
        }
        d_opacity[i] = 0.0f32;
        for j in 0..comptime![3 * sh_coeffs] {
            d_sh[base + j] = 0.0f32;
        }
        if radii[2 * i] == 0i32 && radii[2 * i + 1] == 0i32 {
            terminate!();
        }
        let g = 10 * i;

        // Opacity: sigmoid'.
        let o = screen[g + 8];
        d_opacity[i] = grads[g + 8] * o * (1.0f32 - o);

        // Colour: clamp at 0, then the SH coefficients and the view direction.
        let mx = means[3 * i];
        let my = means[3 * i + 1];
        let mz = means[3 * i + 2];
        let vx = mx - cam[22];
        let vy = my - cam[23];
        let vz = mz - cam[24];
        let mut dist = f32::sqrt(vx * vx + vy * vy + vz * vz);
        let mut dir = Array::<f32>::new(3usize);
        dir[0] = 0.0f32;
        dir[1] = 0.0f32;
        dir[2] = 1.0f32;
        if dist > 0.0f32 {
            dir[0] = vx / dist;
            dir[1] = vy / dist;
            dir[2] = vz / dist;
        } else {
            dist = 1.0f32;
        }
        let mut basis = Array::<f32>::new(16usize);
        sh_basis(dir[0], dir[1], dir[2], &mut basis, sh_coeffs);
        let mut d_basis = Array::<f32>::new(16usize);
        for j in 0..16usize {
            d_basis[j] = 0.0f32;
        }
        for c in 0..3usize {
            let mut raw = 0.5f32;
            for j in 0..sh_coeffs {
                raw += basis[j] * sh[base + 3 * j + c];
            }
            let mut d_raw = 0.0f32;
            if raw > 0.0f32 {
                d_raw = grads[g + 5 + c];
            }
            for j in 0..sh_coeffs {
                d_sh[base + 3 * j + c] = basis[j] * d_raw;
                d_basis[j] += sh[base + 3 * j + c] * d_raw;
            }
        }
        let mut d_dir = Array::<f32>::new(3usize);
        sh_basis_vjp(dir[0], dir[1], dir[2], &d_basis, &mut d_dir, sh_coeffs);
        let radial = d_dir[0] * dir[0] + d_dir[1] * dir[1] + d_dir[2] * dir[2];
        let mut d_x = Array::<f32>::new(3usize);
        for a in 0..3usize {
            d_x[a] = (d_dir[a] - radial * dir[a]) / dist;
        }

        // The forward's intermediates: rotation, scales, M = R diag(s), Σc = W M Mᵀ Wᵀ.
        let qn = f32::sqrt(
            quats[4 * i] * quats[4 * i]
                + quats[4 * i + 1] * quats[4 * i + 1]
                + quats[4 * i + 2] * quats[4 * i + 2]
                + quats[4 * i + 3] * quats[4 * i + 3],
        );
        let qw = quats[4 * i] / qn;
        let qx = quats[4 * i + 1] / qn;
        let qy = quats[4 * i + 2] / qn;
        let qz = quats[4 * i + 3] / qn;
        let mut rot = Array::<f32>::new(9usize);
        rot[0] = 1.0f32 - 2.0f32 * (qy * qy + qz * qz);
        rot[1] = 2.0f32 * (qx * qy - qw * qz);
        rot[2] = 2.0f32 * (qx * qz + qw * qy);
        rot[3] = 2.0f32 * (qx * qy + qw * qz);
        rot[4] = 1.0f32 - 2.0f32 * (qx * qx + qz * qz);
        rot[5] = 2.0f32 * (qy * qz - qw * qx);
        rot[6] = 2.0f32 * (qx * qz - qw * qy);
        rot[7] = 2.0f32 * (qy * qz + qw * qx);
        rot[8] = 1.0f32 - 2.0f32 * (qx * qx + qy * qy);
        let mut scale = Array::<f32>::new(3usize);
        for a in 0..3usize {
            scale[a] = f32::exp(log_scales[3 * i + a]);
        }
        let mut m = Array::<f32>::new(9usize);
        for r in 0..3usize {
            for c in 0..3usize {
                m[3 * r + c] = rot[3 * r + c] * scale[c];
            }
        }
        // T = W M, so that Σc = T Tᵀ.
        let mut tm = Array::<f32>::new(9usize);
        for r in 0..3usize {
            for c in 0..3usize {
                tm[3 * r + c] =
                    cam[3 * r] * m[c] + cam[3 * r + 1] * m[3 + c] + cam[3 * r + 2] * m[6 + c];
            }
        }
        let mut cov = Array::<f32>::new(9usize);
        for r in 0..3usize {
            for c in 0..3usize {
                cov[3 * r + c] = tm[3 * r] * tm[3 * c]
                    + tm[3 * r + 1] * tm[3 * c + 1]
                    + tm[3 * r + 2] * tm[3 * c + 2];
            }
        }
        let px = cam[0] * mx + cam[1] * my + cam[2] * mz + cam[9];
        let py = cam[3] * mx + cam[4] * my + cam[5] * mz + cam[10];
        let z = cam[6] * mx + cam[7] * my + cam[8] * mz + cam[11];
        let fx = cam[12];
        let fy = cam[13];
        let xz = px / z;
        let yz = py / z;
        let x_clamped = xz < -cam[16] || xz > cam[17];
        let y_clamped = yz < -cam[18] || yz > cam[19];
        let tx = z * xz.max(-cam[16]).min(cam[17]);
        let ty = z * yz.max(-cam[18]).min(cam[19]);
        let z2 = z * z;
        let z3 = z2 * z;
        // The Jacobian, 2×3 row-major: [fx/z, 0, −fx tx/z²; 0, fy/z, −fy ty/z²].
        let mut jac = Array::<f32>::new(6usize);
        jac[0] = fx / z;
        jac[1] = 0.0f32;
        jac[2] = -fx * tx / z2;
        jac[3] = 0.0f32;
        jac[4] = fy / z;
        jac[5] = -fy * ty / z2;
        // J Σc (2×3), then Σ₂ᴅ.
        let mut jsc = Array::<f32>::new(6usize);
        for r in 0..2usize {
            for c in 0..3usize {
                jsc[3 * r + c] =
                    jac[3 * r] * cov[c] + jac[3 * r + 1] * cov[3 + c] + jac[3 * r + 2] * cov[6 + c];
            }
        }
        let a = jsc[0] * jac[0] + jsc[1] * jac[1] + jsc[2] * jac[2] + low_pass;
        let b = jsc[0] * jac[3] + jsc[1] * jac[4] + jsc[2] * jac[5];
        let c = jsc[3] * jac[3] + jsc[4] * jac[4] + jsc[5] * jac[5] + low_pass;

        // Conic = Σ₂ᴅ⁻¹: dL/dΣ₂ᴅ = −K G K, G the symmetric conic gradient.
        let det = a * c - b * b;
        let k00 = c / det;
        let k01 = -b / det;
        let k11 = a / det;
        let g00 = grads[g + 2];
        let g01 = 0.5f32 * grads[g + 3];
        let g11 = grads[g + 4];
        let kg00 = k00 * g00 + k01 * g01;
        let kg01 = k00 * g01 + k01 * g11;
        let kg10 = k01 * g00 + k11 * g01;
        let kg11 = k01 * g01 + k11 * g11;
        let mut g2 = Array::<f32>::new(4usize);
        g2[0] = -(kg00 * k00 + kg01 * k01);
        g2[1] = -(kg00 * k01 + kg01 * k11);
        g2[2] = -(kg10 * k00 + kg11 * k01);
        g2[3] = -(kg10 * k01 + kg11 * k11);

        // Σ₂ᴅ = J Σc Jᵀ: dL/dΣc = Jᵀ G J, dL/dJ = 2 G J Σc.
        let mut d_cov = Array::<f32>::new(9usize);
        for r in 0..3usize {
            for cc in 0..3usize {
                let mut acc = 0.0f32;
                for u in 0..2usize {
                    for v in 0..2usize {
                        acc += jac[3 * u + r] * g2[2 * u + v] * jac[3 * v + cc];
                    }
                }
                d_cov[3 * r + cc] = acc;
            }
        }
        let mut d_jac = Array::<f32>::new(6usize);
        for r in 0..2usize {
            for cc in 0..3usize {
                d_jac[3 * r + cc] = 2.0f32 * (g2[2 * r] * jsc[cc] + g2[2 * r + 1] * jsc[3 + cc]);
            }
        }

        // Σc = W Σ Wᵀ: dL/dΣ = Wᵀ (dL/dΣc) W; Σ = M Mᵀ: dL/dM = 2 (dL/dΣ) M.
        let mut wtd = Array::<f32>::new(9usize);
        for r in 0..3usize {
            for cc in 0..3usize {
                wtd[3 * r + cc] =
                    cam[r] * d_cov[cc] + cam[3 + r] * d_cov[3 + cc] + cam[6 + r] * d_cov[6 + cc];
            }
        }
        let mut d_sigma = Array::<f32>::new(9usize);
        for r in 0..3usize {
            for cc in 0..3usize {
                d_sigma[3 * r + cc] = wtd[3 * r] * cam[cc]
                    + wtd[3 * r + 1] * cam[3 + cc]
                    + wtd[3 * r + 2] * cam[6 + cc];
            }
        }
        let mut d_rot = Array::<f32>::new(9usize);
        for j in 0..3usize {
            let mut d_s = 0.0f32;
            for r in 0..3usize {
                let d_m = 2.0f32
                    * (d_sigma[3 * r] * m[j]
                        + d_sigma[3 * r + 1] * m[3 + j]
                        + d_sigma[3 * r + 2] * m[6 + j]);
                d_rot[3 * r + j] = d_m * scale[j];
                d_s += d_m * rot[3 * r + j];
            }
            d_log_scales[3 * i + j] = d_s * scale[j];
        }
        // R(q) for the normalised q, then the normalisation.
        let dw = 2.0f32
            * (-qz * d_rot[1] + qy * d_rot[2] + qz * d_rot[3] - qx * d_rot[5] - qy * d_rot[6]
                + qx * d_rot[7]);
        let dx = 2.0f32
            * (qy * d_rot[1] + qz * d_rot[2] + qy * d_rot[3] - qw * d_rot[5]
                + qz * d_rot[6]
                + qw * d_rot[7])
            - 4.0f32 * qx * (d_rot[4] + d_rot[8]);
        let dy = 2.0f32
            * (qx * d_rot[1] + qw * d_rot[2] + qx * d_rot[3] + qz * d_rot[5] - qw * d_rot[6]
                + qz * d_rot[7])
            - 4.0f32 * qy * (d_rot[0] + d_rot[8]);
        let dz = 2.0f32
            * (-qw * d_rot[1]
                + qx * d_rot[2]
                + qw * d_rot[3]
                + qy * d_rot[5]
                + qx * d_rot[6]
                + qy * d_rot[7])
            - 4.0f32 * qz * (d_rot[0] + d_rot[4]);
        let along = dw * qw + dx * qx + dy * qy + dz * qz;
        d_quats[4 * i] = (dw - along * qw) / qn;
        d_quats[4 * i + 1] = (dx - along * qx) / qn;
        d_quats[4 * i + 2] = (dy - along * qy) / qn;
        d_quats[4 * i + 3] = (dz - along * qz) / qn;

        // The camera-space mean: through the 2D mean, the depth and the Jacobian.
        let mut dp0 = grads[g] * fx / z;
        let mut dp1 = grads[g + 1] * fy / z;
        let mut dp2 = -grads[g] * fx * px / z2 - grads[g + 1] * fy * py / z2 + grads[g + 9];
        dp2 = dp2 - d_jac[0] * fx / z2 - d_jac[4] * fy / z2
            + d_jac[2] * 2.0f32 * fx * tx / z3
            + d_jac[5] * 2.0f32 * fy * ty / z3;
        let d_tx = -d_jac[2] * fx / z2;
        let d_ty = -d_jac[5] * fy / z2;
        // tx = z·clamp(x/z): ∂/∂x = 1 inside the limits; ∂/∂z = tx/z when clamped.
        if x_clamped {
            dp2 += d_tx * tx / z;
        } else {
            dp0 += d_tx;
        }
        if y_clamped {
            dp2 += d_ty * ty / z;
        } else {
            dp1 += d_ty;
        }
        for a in 0..3usize {
            d_means[3 * i + a] = d_x[a] + cam[a] * dp0 + cam[3 + a] * dp1 + cam[6 + a] * dp2;
        }
    }
}

/// The kernels above as CUDA C, for the offline NVRTC check: one per SH degree (0 to 3).
#[cfg(feature = "cuda-source")]
pub(super) fn cuda_kernels(target: &CudaTarget) -> Result<Vec<KernelSource>, String> {
    (0..=3)
        .map(|degree| {
            let (s, p, t) = target.settings(CubeDim::new_1d(UNITS as u32));
            target.source(
                format!("project_backward (SH degree {degree})"),
                kernels::project_backward::ProjectBackward::new(
                    s,
                    p,
                    t,
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    (),
                    crate::sh::num_coeffs(degree),
                ),
            )
        })
        .collect()
}

/// Gradients of `inputs` (without the background, which the rasteriser's backward gives)
/// from the screen-space gradient `grads` `[N, 10]` of their projection (`screen`, `radii`).
pub fn project_backward(
    inputs: &GaussianTensors<CubeBackend>,
    camera: &Camera,
    screen: &FloatTensor<CubeBackend>,
    radii: &IntTensor<CubeBackend>,
    grads: &FloatTensor<CubeBackend>,
) -> GaussianTensors<CubeBackend> {
    let contiguous = |t: &FloatTensor<CubeBackend>| into_contiguous(t.clone());
    let means = contiguous(&inputs.means);
    let n = means.meta.shape()[0];
    let sh_coeffs = inputs.sh.meta.shape()[1];
    let (client, device) = (means.client.clone(), means.device.clone());
    let empty = |shape: &[usize]| -> FloatTensor<CubeBackend> {
        empty_device_contiguous_dtype(
            client.clone(),
            device.clone(),
            Shape::from(shape.to_vec()),
            DType::F32,
        )
    };
    let out: GaussianTensors<CubeBackend> = GaussianTensors {
        means: empty(&[n, 3]),
        log_scales: empty(&[n, 3]),
        quats: empty(&[n, 4]),
        opacity_logits: empty(&[n]),
        sh: empty(&[n, sh_coeffs, 3]),
        background: empty(&[3]),
    };
    if n > 0 {
        let constants = camera_constants(camera).to_vec();
        let len = constants.len();
        let cam = CubeBackend::float_from_data(TensorData::new(constants, [len]), &device);
        kernels::project_backward::launch(
            &client,
            grid(n.div_ceil(UNITS), MAX_ROW),
            CubeDim::new_1d(UNITS as u32),
            means.into_tensor_arg(),
            contiguous(&inputs.log_scales).into_tensor_arg(),
            contiguous(&inputs.quats).into_tensor_arg(),
            contiguous(&inputs.sh).into_tensor_arg(),
            cam.into_tensor_arg(),
            contiguous(screen).into_tensor_arg(),
            into_contiguous(radii.clone()).into_tensor_arg(),
            contiguous(grads).into_tensor_arg(),
            out.means.clone().into_tensor_arg(),
            out.log_scales.clone().into_tensor_arg(),
            out.quats.clone().into_tensor_arg(),
            out.opacity_logits.clone().into_tensor_arg(),
            out.sh.clone().into_tensor_arg(),
            LOW_PASS as f32,
            sh_coeffs,
        );
    }
    out
}
