//! Projection on the GPU: one unit per Gaussian, the same formulas and culling as
//! [`crate::cpu::project`] (EWA splatting, the 1.3× field-of-view clamp of the Jacobian, the 0.3
//! low-pass, SH colour clamped at 0, gsplat's opacity-aware per-axis radii, culling of
//! Gaussians whose box holds no pixel centre), plus the 16×16 tiles each footprint touches —
//! what the tile binning that follows needs.
//!
//! Outputs, one row per Gaussian (zeros when culled): `screen [N, 10]` in the layout of
//! [`crate::op::SCREEN_FLOATS`] (mean x, y; conic a, b, c; colour r, g, b; opacity; depth),
//! `radii [N, 2]`, `tiles [N]` (how many tiles) and `rects [N, 4]` (which: the first and last
//! tile column and row, inclusive), all i32. The arithmetic is f32 in a different order
//! than the CPU's (`W M (W M)ᵀ` for `W Σ Wᵀ`), so values agree to rounding, not bit for bit.

use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::{DType, Shape, TensorData};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::CubeDim;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;

#[cfg(feature = "cuda-source")]
use super::cuda_source::{CudaTarget, KernelSource, tensor};
use super::scan::{MAX_ROW, grid};
use crate::Camera;
use crate::op::{GaussianTensors, SCREEN_FLOATS};
use crate::semantics::{ALPHA_MIN, EXTENT_MAX_SIGMAS, LOW_PASS, TILE_SIZE};

/// Floats of the packed camera constants the kernel reads (see [`camera_constants`]).
const CAMERA_FLOATS: usize = 25;

/// Units per cube of the projection launch.
const UNITS: u32 = 256;

pub(super) mod kernels {
    // The prelude brings its own `Tensor`, `min` and `max`: kernels live apart.
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// The first `k` real SH basis functions at the unit direction `(x, y, z)` into `out`
    /// (the constants and signs of [`crate::sh::basis`]).
    #[cube]
    pub fn sh_basis(x: f32, y: f32, z: f32, out: &mut Array<f32>, #[comptime] k: usize) {
        out[0] = 0.282_094_8f32;
        if comptime![k > 1] {
            out[1] = -0.488_602_5f32 * y;
            out[2] = 0.488_602_5f32 * z;
            out[3] = -0.488_602_5f32 * x;
        }
        if comptime![k > 4] {
            let (xx, yy, zz) = (x * x, y * y, z * z);
            out[4] = 1.092_548_4f32 * x * y;
            out[5] = -1.092_548_4f32 * y * z;
            out[6] = 0.315_391_57f32 * (2.0f32 * zz - xx - yy);
            out[7] = -1.092_548_4f32 * x * z;
            out[8] = 0.546_274_24f32 * (xx - yy);
        }
        if comptime![k > 9] {
            let (xx, yy, zz) = (x * x, y * y, z * z);
            out[9] = -0.590_043_6f32 * y * (3.0f32 * xx - yy);
            out[10] = 2.890_611_4f32 * x * y * z;
            out[11] = -0.457_045_8f32 * y * (4.0f32 * zz - xx - yy);
            out[12] = 0.373_176_33f32 * z * (2.0f32 * zz - 3.0f32 * xx - 3.0f32 * yy);
            out[13] = -0.457_045_8f32 * x * (4.0f32 * zz - xx - yy);
            out[14] = 1.445_305_7f32 * z * (xx - yy);
            out[15] = -0.590_043_6f32 * x * (xx - 3.0f32 * yy);
        }
    }

    /// Projects Gaussian `ABSOLUTE_POS`. `cam` is [`super::camera_constants`]. The culling
    /// tests are written `!(x > 0)` on purpose: they must also be true for NaN.
    #[allow(clippy::too_many_arguments, clippy::neg_cmp_op_on_partial_ord)]
    #[cube(launch)]
    pub fn project(
        means: &Tensor<f32>,
        log_scales: &Tensor<f32>,
        quats: &Tensor<f32>,
        opacity_logits: &Tensor<f32>,
        sh: &Tensor<f32>,
        cam: &Tensor<f32>,
        screen: &mut Tensor<f32>,
        radii: &mut Tensor<i32>,
        tiles: &mut Tensor<i32>,
        rects: &mut Tensor<i32>,
        width: u32,
        height: u32,
        alpha_min: f32,
        low_pass: f32,
        extent_max: f32,
        #[comptime] sh_coeffs: usize,
        #[comptime] tile_size: u32,
    ) {
        let i = ABSOLUTE_POS;
        if i >= opacity_logits.len() {
            terminate!();
        }
        // Culled until proven visible.
        for k in 0..10usize {
            screen[10 * i + k] = 0.0f32;
        }
        radii[2 * i] = 0i32;
        radii[2 * i + 1] = 0i32;
        tiles[i] = 0i32;
        for k in 0..4usize {
            rects[4 * i + k] = 0i32;
        }

        let mx = means[3 * i];
        let my = means[3 * i + 1];
        let mz = means[3 * i + 2];
        // Camera-space mean p = W x + t.
        let px = cam[0] * mx + cam[1] * my + cam[2] * mz + cam[9];
        let py = cam[3] * mx + cam[4] * my + cam[5] * mz + cam[10];
        let pz = cam[6] * mx + cam[7] * my + cam[8] * mz + cam[11];
        let qw = quats[4 * i];
        let qx = quats[4 * i + 1];
        let qy = quats[4 * i + 2];
        let qz = quats[4 * i + 3];
        let q_norm = f32::sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
        if !(q_norm > 0.0f32) || pz < cam[20] || pz > cam[21] {
            terminate!();
        }
        let w = qw / q_norm;
        let x = qx / q_norm;
        let y = qy / q_norm;
        let z = qz / q_norm;
        let r00 = 1.0f32 - 2.0f32 * (y * y + z * z);
        let r01 = 2.0f32 * (x * y - w * z);
        let r02 = 2.0f32 * (x * z + w * y);
        let r10 = 2.0f32 * (x * y + w * z);
        let r11 = 1.0f32 - 2.0f32 * (x * x + z * z);
        let r12 = 2.0f32 * (y * z - w * x);
        let r20 = 2.0f32 * (x * z - w * y);
        let r21 = 2.0f32 * (y * z + w * x);
        let r22 = 1.0f32 - 2.0f32 * (x * x + y * y);
        let s0 = f32::exp(log_scales[3 * i]);
        let s1 = f32::exp(log_scales[3 * i + 1]);
        let s2 = f32::exp(log_scales[3 * i + 2]);
        // T = W M with M = R diag(s), so that W Σ Wᵀ = T Tᵀ.
        let t00 = (cam[0] * r00 + cam[1] * r10 + cam[2] * r20) * s0;
        let t01 = (cam[0] * r01 + cam[1] * r11 + cam[2] * r21) * s1;
        let t02 = (cam[0] * r02 + cam[1] * r12 + cam[2] * r22) * s2;
        let t10 = (cam[3] * r00 + cam[4] * r10 + cam[5] * r20) * s0;
        let t11 = (cam[3] * r01 + cam[4] * r11 + cam[5] * r21) * s1;
        let t12 = (cam[3] * r02 + cam[4] * r12 + cam[5] * r22) * s2;
        let t20 = (cam[6] * r00 + cam[7] * r10 + cam[8] * r20) * s0;
        let t21 = (cam[6] * r01 + cam[7] * r11 + cam[8] * r21) * s1;
        let t22 = (cam[6] * r02 + cam[7] * r12 + cam[8] * r22) * s2;
        // The Jacobian at the mean with x/z, y/z clamped to 1.3× the field of view.
        let fx = cam[12];
        let fy = cam[13];
        let cx = cam[14];
        let cy = cam[15];
        let tx = pz * (px / pz).max(-cam[16]).min(cam[17]);
        let ty = pz * (py / pz).max(-cam[18]).min(cam[19]);
        let j00 = fx / pz;
        let j02 = -fx * tx / (pz * pz);
        let j11 = fy / pz;
        let j12 = -fy * ty / (pz * pz);
        // U = J T (2×3); Σ₂ᴅ = U Uᵀ + low-pass.
        let u00 = j00 * t00 + j02 * t20;
        let u01 = j00 * t01 + j02 * t21;
        let u02 = j00 * t02 + j02 * t22;
        let u10 = j11 * t10 + j12 * t20;
        let u11 = j11 * t11 + j12 * t21;
        let u12 = j11 * t12 + j12 * t22;
        let a = u00 * u00 + u01 * u01 + u02 * u02 + low_pass;
        let b = u00 * u10 + u01 * u11 + u02 * u12;
        let c = u10 * u10 + u11 * u11 + u12 * u12 + low_pass;
        let det = a * c - b * b;
        let opacity = 1.0f32 / (1.0f32 + f32::exp(-opacity_logits[i]));
        if !(det > 0.0f32) || opacity < alpha_min {
            terminate!();
        }
        // gsplat's opacity-aware extent, in standard deviations.
        let extent = f32::sqrt((2.0f32 * f32::ln(opacity / alpha_min)).max(0.0f32)).min(extent_max);
        let rx = f32::ceil(extent * f32::sqrt(a));
        let ry = f32::ceil(extent * f32::sqrt(c));
        let mean_x = fx * px / pz + cx;
        let mean_y = fy * py / pz + cy;
        // Pixels whose centre i + 0.5 lies in [m − r, m + r], inside the image.
        let x0 = f32::ceil(mean_x - rx - 0.5f32).max(0.0f32);
        let x1 = f32::floor(mean_x + rx - 0.5f32).min(f32::cast_from(width) - 1.0f32);
        let y0 = f32::ceil(mean_y - ry - 0.5f32).max(0.0f32);
        let y1 = f32::floor(mean_y + ry - 0.5f32).min(f32::cast_from(height) - 1.0f32);
        if !(x0 <= x1) || !(y0 <= y1) {
            terminate!();
        }
        // SH colour along the view direction from the camera centre.
        let dx = mx - cam[22];
        let dy = my - cam[23];
        let dz = mz - cam[24];
        let dn = f32::sqrt(dx * dx + dy * dy + dz * dz);
        let mut vx = 0.0f32;
        let mut vy = 0.0f32;
        let mut vz = 1.0f32;
        if dn > 0.0f32 {
            vx = dx / dn;
            vy = dy / dn;
            vz = dz / dn;
        }
        let mut basis = Array::<f32>::new(16usize);
        sh_basis(vx, vy, vz, &mut basis, sh_coeffs);
        let base = i * sh_coeffs * 3;
        for ch in 0..3usize {
            let mut v = 0.5f32;
            for j in 0..sh_coeffs {
                v += basis[j] * sh[base + 3 * j + ch];
            }
            screen[10 * i + 5 + ch] = v.max(0.0f32);
        }
        screen[10 * i] = mean_x;
        screen[10 * i + 1] = mean_y;
        screen[10 * i + 2] = c / det;
        screen[10 * i + 3] = -b / det;
        screen[10 * i + 4] = a / det;
        screen[10 * i + 8] = opacity;
        screen[10 * i + 9] = pz;
        radii[2 * i] = i32::cast_from(rx);
        radii[2 * i + 1] = i32::cast_from(ry);
        let ts = f32::cast_from(tile_size);
        let tx0 = f32::floor(x0 / ts);
        let tx1 = f32::floor(x1 / ts);
        let ty0 = f32::floor(y0 / ts);
        let ty1 = f32::floor(y1 / ts);
        tiles[i] = i32::cast_from((tx1 - tx0 + 1.0f32) * (ty1 - ty0 + 1.0f32));
        rects[4 * i] = i32::cast_from(tx0);
        rects[4 * i + 1] = i32::cast_from(ty0);
        rects[4 * i + 2] = i32::cast_from(tx1);
        rects[4 * i + 3] = i32::cast_from(ty1);
    }
}

/// The kernels above as CUDA C, for the offline NVRTC check: one per SH degree (0 to 3).
#[cfg(feature = "cuda-source")]
pub(super) fn cuda_kernels(target: &CudaTarget) -> Result<Vec<KernelSource>, String> {
    (0..=3)
        .map(|degree| {
            let (s, p, t) = target.settings(CubeDim::new_1d(UNITS));
            target.source(
                format!("project (SH degree {degree})"),
                kernels::project::Project::new(
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
                    (),
                    (),
                    (),
                    (),
                    (),
                    crate::sh::num_coeffs(degree),
                    TILE_SIZE as u32,
                ),
            )
        })
        .collect()
}

/// The camera as the kernel reads it: `W` (row-major, 9), `t` (3), `fx, fy, cx, cy`, the
/// Jacobian's clamp limits `(−x, +x, −y, +y)` of x/z and y/z, `near, far`, the centre (3).
pub fn camera_constants(camera: &Camera) -> [f32; CAMERA_FLOATS] {
    let w = camera.width as f64;
    let h = camera.height as f64;
    let fx = camera.fx();
    let fy = camera.fy();
    let cx = camera.cx();
    let cy = camera.cy();
    let tan_x = 0.5 * w / fx;
    let tan_y = 0.5 * h / fy;
    let mut out = [0.0f32; CAMERA_FLOATS];
    for r in 0..3 {
        for c in 0..3 {
            out[3 * r + c] = camera.r[r][c] as f32;
        }
        out[9 + r] = camera.t[r] as f32;
    }
    let center = camera.center();
    let rest = [
        fx,
        fy,
        cx,
        cy,
        cx / fx + 0.3 * tan_x,
        (w - cx) / fx + 0.3 * tan_x,
        cy / fy + 0.3 * tan_y,
        (h - cy) / fy + 0.3 * tan_y,
        camera.near,
        camera.far,
        center[0],
        center[1],
        center[2],
    ];
    for (slot, v) in out[12..].iter_mut().zip(rest) {
        *slot = v as f32;
    }
    out
}

/// The projected Gaussians on the device (see the module docs for the layout).
#[derive(Clone, Debug)]
pub struct Projection {
    pub screen: FloatTensor<CubeBackend>,
    pub radii: IntTensor<CubeBackend>,
    pub tiles: IntTensor<CubeBackend>,
    pub rects: IntTensor<CubeBackend>,
}

/// Projects `inputs` (f32 tensors on a Cube device) seen by `camera`. `sh` must be `[N, K, 3]`
/// with `K` = 1, 4, 9 or 16.
pub fn project(inputs: &GaussianTensors<CubeBackend>, camera: &Camera) -> Projection {
    let contiguous = |t: &FloatTensor<CubeBackend>| into_contiguous(t.clone());
    let means = contiguous(&inputs.means);
    let n = means.meta.shape()[0];
    let sh_coeffs = inputs.sh.meta.shape()[1];
    let client = means.client.clone();
    let device = means.device.clone();
    let cam = CubeBackend::float_from_data(
        TensorData::new(camera_constants(camera).to_vec(), [CAMERA_FLOATS]),
        &device,
    );
    let screen = empty_device_contiguous_dtype(
        client.clone(),
        device.clone(),
        Shape::new([n, SCREEN_FLOATS]),
        DType::F32,
    );
    let radii = empty_device_contiguous_dtype(
        client.clone(),
        device.clone(),
        Shape::new([n, 2]),
        DType::I32,
    );
    let tiles =
        empty_device_contiguous_dtype(client.clone(), device.clone(), Shape::new([n]), DType::I32);
    let rects = empty_device_contiguous_dtype(
        client.clone(),
        device.clone(),
        Shape::new([n, 4]),
        DType::I32,
    );
    if n > 0 {
        kernels::project::launch(
            &client,
            grid(n.div_ceil(UNITS as usize), MAX_ROW),
            CubeDim::new_1d(UNITS),
            means.into_tensor_arg(),
            contiguous(&inputs.log_scales).into_tensor_arg(),
            contiguous(&inputs.quats).into_tensor_arg(),
            contiguous(&inputs.opacity_logits).into_tensor_arg(),
            contiguous(&inputs.sh).into_tensor_arg(),
            cam.into_tensor_arg(),
            screen.clone().into_tensor_arg(),
            radii.clone().into_tensor_arg(),
            tiles.clone().into_tensor_arg(),
            rects.clone().into_tensor_arg(),
            camera.width,
            camera.height,
            ALPHA_MIN as f32,
            LOW_PASS as f32,
            EXTENT_MAX_SIGMAS as f32,
            sh_coeffs,
            TILE_SIZE as u32,
        );
    }
    Projection {
        screen,
        radii,
        tiles,
        rects,
    }
}
