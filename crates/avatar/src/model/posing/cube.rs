//! [`Skinning`](super::Skinning) on `Cube` devices (wgpu, CUDA; under Burn's `fusion` a lazy
//! operation of its stream): the blend, the polar iteration and Shepperd's quaternion of every
//! point in one kernel, one thread per point; the rotations' Hamilton product
//! ([`super::quaternion`]), one thread per row; and the view maps' normals and cosines
//! ([`super::view`]), one thread per Gaussian; and the gather of [`super::Taps::apply`] for
//! inputs that need no gradient, one thread per output value.
//!
//! Why: as tensor operations on `[N, 1]` columns ([`super::Skinning::from_tensors`]) the
//! skinning of a `paper` step's body and face Gaussians launched about 1 300 kernels (the offline
//! driver's count, `tools/launch_sites.sh`), each a fixed cost on the host. The arithmetic is
//! the tensor path's, term by term (the same cofactors, fixed iteration count, guard and pivot
//! choice), so the two agree to float rounding.

#[cfg(feature = "fusion")]
use burn::backend::fusion::custom::TensorSpec;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Backend, Dispatch, TensorMetadata, backend_extension};
use burn::tensor::{DType, Device, Int, IntDType, Shape, Tensor};
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;
use f3g_nets::cube_grid::one_thread_per_value;

use super::POLAR_ITERATIONS;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// Point `i` (`ABSOLUTE_POS`): the blend `m = Σ_k weight[k, i] · joints[index[k, i]]`
    /// (`[3, 4]` row-major), its linear part and translation, the nearest rotation of the linear
    /// part after `iterations` Newton steps `X ← ½(γX + X⁻ᵀ/γ)`, `γ = |det X|^(-1/3)` (`[3, 3]`
    /// row-major, `rotation[i, k]`), and that rotation's unit quaternion (w, x, y, z).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn skinning(
        joints: &Tensor<f32>,
        index: &Tensor<i32>,
        weight: &Tensor<f32>,
        linear: &mut Tensor<f32>,
        translation: &mut Tensor<f32>,
        rotation: &mut Tensor<f32>,
        quaternion: &mut Tensor<f32>,
        rows: u32,
        width: u32,
        #[comptime] iterations: u32,
    ) {
        let i = ABSOLUTE_POS as u32;
        if i >= rows {
            terminate!();
        }
        let mut m = Array::<f32>::new(12usize);
        for c in 0..12usize {
            m[c] = 0.0f32;
        }
        for k in 0..width {
            let tap = (k * rows + i) as usize;
            let j = u32::cast_from(index[tap]);
            let w = weight[tap];
            for c in 0..12u32 {
                m[c as usize] += w * joints[(j * 12 + c) as usize];
            }
        }
        let mut x = Array::<f32>::new(9usize);
        for r in 0..3u32 {
            for c in 0..3u32 {
                let value = m[(4 * r + c) as usize];
                x[(3 * r + c) as usize] = value;
                linear[(9 * i + 3 * r + c) as usize] = value;
            }
            translation[(3 * i + r) as usize] = m[(4 * r + 3) as usize];
        }
        for _ in 0..comptime![iterations] {
            let c0 = x[4] * x[8] - x[5] * x[7];
            let c1 = x[5] * x[6] - x[3] * x[8];
            let c2 = x[3] * x[7] - x[4] * x[6];
            let c3 = x[7] * x[2] - x[1] * x[8];
            let c4 = x[8] * x[0] - x[6] * x[2];
            let c5 = x[6] * x[1] - x[7] * x[0];
            let c6 = x[1] * x[5] - x[2] * x[4];
            let c7 = x[2] * x[3] - x[0] * x[5];
            let c8 = x[0] * x[4] - x[1] * x[3];
            let mut det = x[0] * c0 + x[1] * c1 + x[2] * c2;
            // A degenerate blend has no nearest rotation: kept finite, as the tensor path does.
            if f32::abs(det) < 1e-20f32 {
                det = 1e-20f32;
            }
            let gamma = f32::powf(f32::abs(det), -1.0f32 / 3.0f32);
            let g = gamma * 0.5f32;
            let h = (1.0f32 / (gamma * det)) * 0.5f32;
            x[0] = x[0] * g + c0 * h;
            x[1] = x[1] * g + c1 * h;
            x[2] = x[2] * g + c2 * h;
            x[3] = x[3] * g + c3 * h;
            x[4] = x[4] * g + c4 * h;
            x[5] = x[5] * g + c5 * h;
            x[6] = x[6] * g + c6 * h;
            x[7] = x[7] * g + c7 * h;
            x[8] = x[8] * g + c8 * h;
        }
        for k in 0..9u32 {
            rotation[(i * 9 + k) as usize] = x[k as usize];
        }
        // Shepperd's pivots and candidates, the first largest pivot's candidate kept.
        let s01 = x[1] + x[3];
        let s02 = x[2] + x[6];
        let s12 = x[5] + x[7];
        let d10 = x[3] - x[1];
        let d02 = x[2] - x[6];
        let d21 = x[7] - x[5];
        let t0 = (x[0] + x[4] + x[8]) + 1.0f32;
        let t1 = (x[0] - x[4] - x[8]) + 1.0f32;
        let t2 = (-x[0] + x[4] - x[8]) + 1.0f32;
        let t3 = (-x[0] - x[4] + x[8]) + 1.0f32;
        let mut q = Array::<f32>::new(4usize);
        q[0] = t0;
        q[1] = d21;
        q[2] = d02;
        q[3] = d10;
        let mut best = t0;
        if t1 > best {
            q[0] = d21;
            q[1] = t1;
            q[2] = s01;
            q[3] = s02;
        }
        best = f32::max(best, t1);
        if t2 > best {
            q[0] = d02;
            q[1] = s01;
            q[2] = t2;
            q[3] = s12;
        }
        best = f32::max(best, t2);
        if t3 > best {
            q[0] = d10;
            q[1] = s02;
            q[2] = s12;
            q[3] = t3;
        }
        let norm = f32::max(
            f32::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]),
            1e-12f32,
        );
        for c in 0..4u32 {
            quaternion[(4 * i + c) as usize] = q[c as usize] / norm;
        }
    }

    /// Row `i` (`ABSOLUTE_POS`) of `A ⊗ B` for `[rows, 4]` rows (w, x, y, z), `A` being `a` or
    /// its conjugate (`conjugate_a`), `B` likewise: `quaternion::hamilton`'s arithmetic.
    #[cube(launch)]
    pub fn quat_mul(
        a: &Tensor<f32>,
        b: &Tensor<f32>,
        out: &mut Tensor<f32>,
        rows: u32,
        #[comptime] conjugate_a: bool,
        #[comptime] conjugate_b: bool,
    ) {
        let i = ABSOLUTE_POS as u32;
        if i >= rows {
            terminate!();
        }
        let mut sa = 1.0f32;
        if comptime![conjugate_a] {
            sa = -1.0f32;
        }
        let mut sb = 1.0f32;
        if comptime![conjugate_b] {
            sb = -1.0f32;
        }
        let w1 = a[(4 * i) as usize];
        let x1 = sa * a[(4 * i + 1) as usize];
        let y1 = sa * a[(4 * i + 2) as usize];
        let z1 = sa * a[(4 * i + 3) as usize];
        let w2 = b[(4 * i) as usize];
        let x2 = sb * b[(4 * i + 1) as usize];
        let y2 = sb * b[(4 * i + 2) as usize];
        let z2 = sb * b[(4 * i + 3) as usize];
        out[(4 * i) as usize] = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2;
        out[(4 * i + 1) as usize] = w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2;
        out[(4 * i + 2) as usize] = w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2;
        out[(4 * i + 3) as usize] = w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2;
    }

    /// Gaussian `i` (`ABSOLUTE_POS`) of `view::view_row`'s arithmetic: the posed unit normal
    /// (`rotation · normal`, row-major `[rows, 9]`) and the cosine between it and the unit
    /// direction from the posed point (`linear · canonical + translation`) to `centre`, moved
    /// by `noise` and renormalised when `noisy`.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn view_cosines(
        linear: &Tensor<f32>,
        translation: &Tensor<f32>,
        rotation: &Tensor<f32>,
        canonical: &Tensor<f32>,
        normals: &Tensor<f32>,
        centre: &Tensor<f32>,
        noise: &Tensor<f32>,
        posed_normals: &mut Tensor<f32>,
        cosines: &mut Tensor<f32>,
        rows: u32,
        #[comptime] noisy: bool,
    ) {
        let i = ABSOLUTE_POS as u32;
        if i >= rows {
            terminate!();
        }
        let mut n = Array::<f32>::new(3usize);
        let mut v = Array::<f32>::new(3usize);
        for r in 0..3u32 {
            let m = (9 * i + 3 * r) as usize;
            let p = (3 * i) as usize;
            n[r as usize] = rotation[m] * normals[p]
                + rotation[m + 1] * normals[p + 1]
                + rotation[m + 2] * normals[p + 2];
            let posed = linear[m] * canonical[p]
                + linear[m + 1] * canonical[p + 1]
                + linear[m + 2] * canonical[p + 2]
                + translation[p + r as usize];
            v[r as usize] = centre[r as usize] - posed;
        }
        let n_norm = f32::max(f32::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]), 1e-12f32);
        let mut v_norm = f32::max(f32::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]), 1e-12f32);
        for r in 0..3usize {
            n[r] /= n_norm;
            v[r] /= v_norm;
        }
        if comptime![noisy] {
            for r in 0..3u32 {
                v[r as usize] += noise[(3 * i + r) as usize];
            }
            v_norm = f32::max(f32::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]), 1e-12f32);
            for r in 0..3usize {
                v[r] /= v_norm;
            }
        }
        for r in 0..3u32 {
            posed_normals[(3 * i + r) as usize] = n[r as usize];
        }
        cosines[i as usize] = n[0] * v[0] + n[1] * v[1] + n[2] * v[2];
    }

    /// Output value `t` (`ABSOLUTE_POS`, row `t / channels`, channel `t % channels`) of
    /// [`super::super::Taps::apply`]: `Σ_k weight[k, row] · x[index[k, row], channel]`, the taps
    /// tap-major and `x` row-major `[M, channels]`.
    #[cube(launch)]
    pub fn apply_taps(
        x: &Tensor<f32>,
        index: &Tensor<i32>,
        weight: &Tensor<f32>,
        out: &mut Tensor<f32>,
        rows: u32,
        width: u32,
        channels: u32,
    ) {
        let t = ABSOLUTE_POS as u32;
        if t >= rows * channels {
            terminate!();
        }
        let (i, c) = (t / channels, t % channels);
        let mut sum = 0.0f32;
        for k in 0..width {
            let tap = (k * rows + i) as usize;
            let j = u32::cast_from(index[tap]);
            sum += weight[tap] * x[(j * channels + c) as usize];
        }
        out[t as usize] = sum;
    }
}

/// The skinning and gathering kernels as backend ops, so that `Dispatch` routes them to the
/// `Cube` backend.
#[backend_extension(Cube, Fusion: cfg(feature = "fusion"))]
pub trait SkinningBackend: Backend {
    /// `joints` `[J, 3, 4]`, taps tap-major (`index` `[width · rows]`, `weight` `[width, rows,
    /// 1]`) → linear parts `[rows, 9]`, translations `[rows, 3]`, nearest rotations as nine
    /// columns `[9, rows]`, quaternions `[rows, 4]`.
    #[fusion(meta = |_joints, _index, weight| {
        let rows = weight.shape[1];
        let spec = |dims: [usize; 2]| TensorSpec::new(Shape::new(dims), weight.dtype);
        (spec([rows, 9]), spec([rows, 3]), spec([9, rows]), spec([rows, 4]))
    })]
    fn skinning(
        joints: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    );

    /// `x` `[M, C]` gathered by taps (`index` `[width · rows]`, `weight` `[width, rows, 1]`,
    /// tap-major) → `[rows, C]`: [`super::Taps::apply`].
    #[fusion(meta = |x, _index, weight| {
        TensorSpec::new(Shape::new([weight.shape[1], x.shape[1]]), x.dtype)
    })]
    fn apply_taps(
        x: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

impl SkinningBackend for CubeBackend {
    fn skinning(
        joints: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    ) {
        let [width, rows, _] = weight.shape().dims();
        let index = contiguous_i32(index);
        let [joints, weight] = [joints, weight].map(into_contiguous);
        let empty = |shape: [usize; 2]| {
            empty_device_contiguous_dtype(
                joints.client.clone(),
                joints.device.clone(),
                Shape::new(shape),
                DType::F32,
            )
        };
        let (linear, translation) = (empty([rows, 9]), empty([rows, 3]));
        let (rotation, quaternion) = (empty([rows, 9]), empty([rows, 4]));
        if rows > 0 {
            let (cubes, cube) = one_thread_per_value(rows);
            let rows = u32::try_from(rows).expect("fewer than 2^32 skinned points");
            kernels::skinning::launch(
                &joints.client,
                cubes,
                cube,
                joints.clone().into_tensor_arg(),
                index.into_tensor_arg(),
                weight.into_tensor_arg(),
                linear.clone().into_tensor_arg(),
                translation.clone().into_tensor_arg(),
                rotation.clone().into_tensor_arg(),
                quaternion.clone().into_tensor_arg(),
                rows,
                u32::try_from(width).expect("a few taps per point"),
                POLAR_ITERATIONS as u32,
            );
        }
        (linear, translation, rotation, quaternion)
    }

    fn apply_taps(
        x: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let [width, rows, _] = weight.shape().dims();
        let channels = x.shape()[1];
        let index = contiguous_i32(index);
        let [x, weight] = [x, weight].map(into_contiguous);
        let out = empty_device_contiguous_dtype(
            x.client.clone(),
            x.device.clone(),
            Shape::new([rows, channels]),
            DType::F32,
        );
        if rows * channels > 0 {
            let (cubes, cube) = one_thread_per_value(rows * channels);
            let small = |n: usize| u32::try_from(n).expect("checked by cube::apply_taps");
            kernels::apply_taps::launch(
                &x.client,
                cubes,
                cube,
                x.clone().into_tensor_arg(),
                index.into_tensor_arg(),
                weight.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                small(rows),
                small(width),
                small(channels),
            );
        }
        out
    }
}

/// Tap indices as the kernels read them: contiguous 32-bit integers.
fn contiguous_i32(index: IntTensor<CubeBackend>) -> IntTensor<CubeBackend> {
    use burn::backend::ops::IntTensorOps;
    if index.dtype == DType::I32 {
        into_contiguous(index)
    } else {
        into_contiguous(CubeBackend::int_cast(index, IntDType::I32))
    }
}

impl super::QuaternionBackend for CubeBackend {
    fn quat_mul(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        conjugate_a: bool,
        conjugate_b: bool,
    ) -> FloatTensor<Self> {
        let [rows, _] = a.shape().dims();
        let [a, b] = [a, b].map(into_contiguous);
        let out = empty_device_contiguous_dtype(
            a.client.clone(),
            a.device.clone(),
            a.shape(),
            DType::F32,
        );
        if rows > 0 {
            let (cubes, cube) = one_thread_per_value(rows);
            kernels::quat_mul::launch(
                &a.client,
                cubes,
                cube,
                a.clone().into_tensor_arg(),
                b.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                u32::try_from(rows).expect("checked by quaternion::has_op"),
                conjugate_a,
                conjugate_b,
            );
        }
        out
    }
}

impl super::ViewBackend for CubeBackend {
    fn view_cosines(
        linear: FloatTensor<Self>,
        translation: FloatTensor<Self>,
        rotation: FloatTensor<Self>,
        canonical: FloatTensor<Self>,
        normals: FloatTensor<Self>,
        centre: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        noisy: bool,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let [rows, _] = translation.shape().dims();
        let (client, device) = (linear.client.clone(), linear.device.clone());
        let empty = |width: usize| {
            empty_device_contiguous_dtype(
                client.clone(),
                device.clone(),
                Shape::new([rows, width]),
                DType::F32,
            )
        };
        let (posed_normals, cosines) = (empty(3), empty(1));
        if rows > 0 {
            let (cubes, cube) = one_thread_per_value(rows);
            let arg = |t: FloatTensor<Self>| into_contiguous(t).into_tensor_arg();
            kernels::view_cosines::launch(
                &client,
                cubes,
                cube,
                arg(linear),
                arg(translation),
                arg(rotation),
                arg(canonical),
                arg(normals),
                arg(centre),
                arg(noise),
                posed_normals.clone().into_tensor_arg(),
                cosines.clone().into_tensor_arg(),
                u32::try_from(rows).expect("checked by view::has_op"),
                noisy,
            );
        }
        (posed_normals, cosines)
    }
}

/// The kernel's outputs as [`super::Skinning`]'s tensors, or `None` off `Cube` devices.
pub(super) fn skinning(
    joints: &Tensor<3>,
    index: &Tensor<1, Int>,
    weight: &Tensor<3>,
) -> Option<super::Skinning> {
    let device = joints.device();
    if !on_cube(&device) {
        return None;
    }
    let (linear, translation, rotation, quaternion) = <Dispatch as SkinningBackend>::skinning(
        joints.clone().without_autodiff().into_dispatch(),
        index.clone().without_autodiff().into_dispatch(),
        weight.clone().without_autodiff().into_dispatch(),
    );
    let on_device = |t: Tensor<2>| super::constant_on(&device, t);
    let linear = on_device(Tensor::<2>::from_dispatch(linear));
    let rows = linear.dims()[0];
    let rotation = on_device(Tensor::<2>::from_dispatch(rotation));
    Some(super::Skinning {
        linear: linear.reshape([rows, 3, 3]),
        translation: on_device(Tensor::from_dispatch(translation)),
        rotation: rotation.reshape([rows, 3, 3]),
        quaternion: on_device(Tensor::from_dispatch(quaternion)),
    })
}

/// [`super::Taps::apply`] of `x` (which needs no gradient) in one kernel, or `None` off `Cube`
/// devices and where a tensor has too many values for the kernel's 32-bit indices.
pub(super) fn apply_taps(taps: &super::Taps, x: &Tensor<2>) -> Option<Tensor<2>> {
    let device = x.device();
    if !on_cube(&device) {
        return None;
    }
    let [sources, channels] = x.dims();
    let fits = |n: usize| u32::try_from(n).is_ok();
    if !(fits(sources * channels) && fits(taps.rows * channels) && fits(taps.width * taps.rows)) {
        return None;
    }
    let out = Tensor::<2>::from_dispatch(<Dispatch as SkinningBackend>::apply_taps(
        x.clone().without_autodiff().into_dispatch(),
        taps.index.clone().without_autodiff().into_dispatch(),
        taps.weight.clone().without_autodiff().into_dispatch(),
    ));
    Some(super::constant_on(&device, out))
}

/// Whether `device` (with autodiff or not) is a `Cube` device, where these kernels run.
pub(super) fn on_cube(device: &Device) -> bool {
    matches!(
        device.clone().without_autodiff().as_dispatch(),
        burn::backend::DispatchDevice::Cube(_)
    )
}
