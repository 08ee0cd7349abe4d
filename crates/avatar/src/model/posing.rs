//! Linear blend skinning on the device: what a frame's joint transforms make of every Gaussian,
//! as tensor operations, so that a training step uploads a few hundred joint transforms and the
//! template's vertex displacements instead of a transform per Gaussian.
//!
//! Conventions: an affine transform is `x' = A x + t`, stored row-major as `[.., 3, 4]`
//! (`[A | t]`); linear parts `[N, 3, 3]` are row-major (`a[n, i, j] = A_ij`); quaternions are
//! `(w, x, y, z)`. LBS blends the joints' transforms with each point's skin weights; Gaussians
//! take the blend's nearest rotation (its orthogonal polar factor), as `f3g_rig::skin` does on
//! the host, which stays the reference these tensors are tested against.
//!
//! On the CPU backend the skinning transforms and the gathers (which need no gradient: joint
//! transforms and the maps' inputs are data) are one parallel loop each instead
//! ([`Skinning::new`], [`Taps::apply`]): the tensor chain is about 600 operations on `[N, 1]`
//! columns, each a serial pass and an allocation on `Flex`. On GPU devices the skinning
//! is one kernel (`posing/cube.rs`), for the same reason: each of those operations is a launch.
//! The rotations' Hamilton product, which has a gradient, is one backend op each way
//! ([`quaternion`]); the view maps' normals and cosines are one op ([`view`]).

use std::sync::Arc;

use burn::tensor::{Device, Int, Tensor, TensorData};
use f3g_rig::SkinWeights;
use glam::Affine3A;
use rayon::prelude::*;

use super::{host_data, host_values};

#[cfg(any(feature = "gpu", feature = "cuda"))]
mod cube;
mod quaternion;
mod view;

pub use quaternion::{QuaternionBackend, quat_mul, quat_mul_as_tensors};
pub use view::{ViewBackend, view_cosines, view_cosines_as_tensors};

/// Whether this module's backend ops ([`QuaternionBackend`], [`ViewBackend`]) run on `t`'s
/// device: the CPU, and `Cube` devices (with this crate's GPU features) where `largest` values
/// (the most any of the op's tensors has) fit its kernel's 32-bit indices.
fn op_runs(t: &Tensor<2>, largest: usize) -> bool {
    if f3g_nets::fused::on_flex(t) {
        return true;
    }
    #[cfg(any(feature = "gpu", feature = "cuda"))]
    if cube::on_cube(&t.device()) {
        return u32::try_from(largest).is_ok();
    }
    let _ = largest;
    false
}

/// `t`, made by one of this module's ops on the inner backend, back on `device` as a constant
/// (with autodiff where `device` has it): those ops' inputs need no gradient.
fn constant_on<const D: usize>(device: &Device, t: Tensor<D>) -> Tensor<D> {
    if device.is_autodiff() {
        t.autodiff()
    } else {
        t
    }
}

/// Newton iterations of the polar decomposition. With determinant scaling the iteration
/// converges quadratically: blends of rotations less than 90° apart (as neighbouring joints of a
/// body are) match the host reference's `f32` result after 5 (tested with 5 while choosing), so
/// 8 leave a margin; a fixed count needs no data-dependent stop (which would be a readback).
pub const POLAR_ITERATIONS: usize = 8;

/// A weighted gather of fixed width: output row `i` is `Σ_k w[i, k] · x[j[i, k]]`. Rows with
/// fewer taps than the widest are padded with weight 0 on row 0. One type serves barycentric
/// interpolation (3 taps into template vertices), skinning (up to 8 joints), densification
/// (4 body Gaussians per face Gaussian) and the reduction of maps to network inputs. Taps are
/// stored tap-major (`[width, rows]`), so the sum runs over the outermost dimension, over
/// contiguous slabs.
#[derive(Clone, Debug)]
pub struct Taps {
    index: Tensor<1, Int>,
    weight: Tensor<3>,
    /// The same taps on the host, kept on the CPU backend only (for the host paths of
    /// [`Taps::apply`] and [`Skinning::new`]).
    host: Option<Arc<HostTaps>>,
    rows: usize,
    width: usize,
}

/// [`Taps`] on the host, tap-major (`[width, rows]`).
#[derive(Debug)]
struct HostTaps {
    index: Vec<u32>,
    weight: Vec<f32>,
}

impl HostTaps {
    /// Tap `k` of `row` as (source row, weight), for taps of `rows` rows.
    fn tap(&self, k: usize, row: usize, rows: usize) -> (usize, f32) {
        (
            self.index[k * rows + row] as usize,
            self.weight[k * rows + row],
        )
    }
}

impl Taps {
    /// From each output row's `(source row, weight)` pairs.
    pub fn new<'a>(
        rows: impl ExactSizeIterator<Item = &'a [(usize, f32)]>,
        device: &Device,
    ) -> Self {
        let count = rows.len();
        let rows: Vec<&[(usize, f32)]> = rows.collect();
        let width = rows.iter().map(|r| r.len()).max().unwrap_or(0).max(1);
        let mut index = vec![0i64; count * width];
        let mut weight = vec![0f32; count * width];
        for (i, taps) in rows.iter().enumerate() {
            for (k, &(j, w)) in taps.iter().enumerate() {
                index[k * count + i] = j as i64;
                weight[k * count + i] = w;
            }
        }
        let host = (device.clone().without_autodiff() == Device::flex()).then(|| {
            Arc::new(HostTaps {
                index: index.iter().map(|&j| j as u32).collect(),
                weight: weight.clone(),
            })
        });
        Self {
            host,
            index: Tensor::from_data(TensorData::new(index, [count * width]), device),
            weight: Tensor::from_data(TensorData::new(weight, [width, count, 1]), device),
            rows: count,
            width,
        }
    }

    /// Skinning taps: one row per point, one tap per joint that influences it.
    pub fn skin(weights: &SkinWeights, device: &Device) -> Self {
        let lists: Vec<Vec<(usize, f32)>> = (0..weights.len())
            .map(|i| weights.influences(i).collect())
            .collect();
        Self::new(lists.iter().map(Vec::as_slice), device)
    }

    /// Number of output rows.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// `[rows, C]` from `x` `[M, C]`: for `x` that needs no gradient, one parallel loop on the
    /// CPU backend and one kernel on GPU devices (as tensor operations, a gather, a product and
    /// a sum: three launches); elsewhere tensor operations.
    pub fn apply(&self, x: Tensor<2>) -> Tensor<2> {
        match &self.host {
            Some(host) if !x.is_require_grad() => self.apply_on_host(host, x),
            #[cfg(any(feature = "gpu", feature = "cuda"))]
            _ if !x.is_require_grad() => {
                cube::apply_taps(self, &x).unwrap_or_else(|| self.apply_as_tensors(x))
            }
            _ => self.apply_as_tensors(x),
        }
    }

    /// [`Taps::apply`] on the host, row by row in parallel, uploaded to `x`'s device.
    fn apply_on_host(&self, host: &HostTaps, x: Tensor<2>) -> Tensor<2> {
        let (c, device) = (x.dims()[1], x.device());
        let values = host_values(x);
        let rows = self.rows;
        let mut out = vec![0.0f32; rows * c];
        out.par_chunks_mut(c.max(1))
            .with_min_len(256)
            .enumerate()
            .for_each(|(i, row)| {
                for k in 0..self.width {
                    let (j, w) = host.tap(k, i, rows);
                    for (o, &v) in row.iter_mut().zip(&values[j * c..j * c + c]) {
                        *o += w * v;
                    }
                }
            });
        Tensor::from_data(TensorData::new(out, [rows, c]), &device)
    }

    /// [`Taps::apply`] as tensor operations, for every device.
    pub fn apply_as_tensors(&self, x: Tensor<2>) -> Tensor<2> {
        let c = x.dims()[1];
        let picked = x
            .select(0, self.index.clone())
            .reshape([self.width, self.rows, c]);
        (picked * self.weight.clone())
            .sum_dim(0)
            .reshape([self.rows, c])
    }
}

/// Affine transforms as a `[N, 3, 4]` tensor.
pub fn affine_tensor(transforms: &[Affine3A], device: &Device) -> Tensor<3> {
    let mut values = Vec::with_capacity(12 * transforms.len());
    for a in transforms {
        for i in 0..3 {
            values.extend([
                a.matrix3.x_axis[i],
                a.matrix3.y_axis[i],
                a.matrix3.z_axis[i],
                a.translation[i],
            ]);
        }
    }
    Tensor::from_data(TensorData::new(values, [transforms.len(), 3, 4]), device)
}

/// Per-point blended transforms `[N, 3, 4]` of joint transforms `[J, 3, 4]` with skin `taps`
/// (one row per point, one tap per influencing joint).
pub fn blend(joints: &Tensor<3>, skin: &Taps) -> Tensor<3> {
    let j = joints.dims()[0];
    skin.apply(joints.clone().reshape([j, 12]))
        .reshape([skin.rows(), 3, 4])
}

/// The linear part `[N, 3, 3]` and translation `[N, 3]` of `[N, 3, 4]` transforms.
pub fn split_affine(m: Tensor<3>) -> (Tensor<3>, Tensor<2>) {
    let n = m.dims()[0];
    let t = m.clone().slice([0..n, 0..3, 3..4]).reshape([n, 3]);
    (m.slice([0..n, 0..3, 0..3]), t)
}

/// `A x + t` for points `[N, 3]`.
pub fn transform_points(linear: &Tensor<3>, translation: &Tensor<2>, x: Tensor<2>) -> Tensor<2> {
    let n = x.dims()[0];
    (linear.clone() * x.reshape([n, 1, 3]))
        .sum_dim(2)
        .reshape([n, 3])
        + translation.clone()
}

/// The `[N, 1]` columns of a `[N, K]` tensor.
pub fn columns<const K: usize>(t: &Tensor<2>) -> [Tensor<2>; K] {
    let n = t.dims()[0];
    std::array::from_fn(|k| t.clone().slice([0..n, k..k + 1]))
}

/// The nearest rotation of each matrix `[N, 3, 3]` (its orthogonal polar factor), for matrices
/// with positive determinant such as blends of rotations, as nine `[N, 1]` columns (row-major:
/// `r[3i + j] = R_ij`). Newton's iteration `X ← ½(γX + X⁻ᵀ/γ)` with `γ = |det X|^(-1/3)`,
/// where `X⁻ᵀ` is the cofactor matrix over the determinant, for a fixed number of iterations
/// ([`POLAR_ITERATIONS`]), so that nothing is read back. Per component, the iteration is
/// elementwise arithmetic on `[N, 1]` columns, which every backend does fast (no gathers or
/// strided reductions over tiny dimensions).
pub fn nearest_rotation(a: Tensor<3>) -> [Tensor<2>; 9] {
    let n = a.dims()[0];
    let mut x: [Tensor<2>; 9] = columns(&a.reshape([n, 9]));
    for _ in 0..POLAR_ITERATIONS {
        let (c, det) = cofactors_and_determinant(&x);
        // A degenerate blend (opposite rotations averaged) has no nearest rotation; keep it
        // finite rather than dividing by zero.
        let det = det.clone().mask_fill(det.abs().lower_elem(1e-20), 1e-20);
        let gamma = det.clone().abs().powf_scalar(-1.0 / 3.0);
        let (g, h) = (gamma.clone() * 0.5, (gamma * det).recip() * 0.5);
        x = std::array::from_fn(|k| x[k].clone() * g.clone() + c[k].clone() * h.clone());
    }
    x
}

/// What the polar iteration and Shepperd's method compute with: `f32` on the host
/// ([`Skinning::new`]'s CPU path) or `[N, 1]` columns on a device, so that both paths share
/// one copy of the formulas below.
trait Scalar:
    Clone
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::Mul<f32, Output = Self>
    + std::ops::Add<f32, Output = Self>
{
}

impl<T> Scalar for T where
    T: Clone
        + std::ops::Add<Output = T>
        + std::ops::Sub<Output = T>
        + std::ops::Mul<Output = T>
        + std::ops::Mul<f32, Output = T>
        + std::ops::Add<f32, Output = T>
{
}

/// The cofactor matrix (row-major) and the determinant of a row-major 3×3 matrix. The minors'
/// indices are written out: computed as `(i + 1) % 3` they did not fold to constants on the
/// host, where the loop then took five times as long.
fn cofactors_and_determinant<T: Scalar>(x: &[T; 9]) -> ([T; 9], T) {
    let m = |k: usize| x[k].clone();
    let minor = |a: usize, b: usize, c: usize, d: usize| m(a) * m(b) - m(c) * m(d);
    let c = [
        minor(4, 8, 5, 7),
        minor(5, 6, 3, 8),
        minor(3, 7, 4, 6),
        minor(7, 2, 1, 8),
        minor(8, 0, 6, 2),
        minor(6, 1, 7, 0),
        minor(1, 5, 2, 4),
        minor(2, 3, 0, 5),
        minor(0, 4, 1, 3),
    ];
    let det = m(0) * c[0].clone() + m(1) * c[1].clone() + m(2) * c[2].clone();
    (c, det)
}

/// Shepperd's four pivots `1 ± r00 ± r11 ± r22` and four candidate quaternions (w, x, y, z) of
/// a row-major rotation; candidate `k` is the quaternion times 4·(its component `k`), well
/// conditioned where pivot `k` is the largest.
fn shepperd_candidates<T: Scalar>(r: &[T; 9]) -> ([T; 4], [[T; 4]; 4]) {
    let e = |i: usize, j: usize| r[3 * i + j].clone();
    let (s01, s02, s12) = (e(0, 1) + e(1, 0), e(0, 2) + e(2, 0), e(1, 2) + e(2, 1));
    let (d10, d02, d21) = (e(1, 0) - e(0, 1), e(0, 2) - e(2, 0), e(2, 1) - e(1, 2));
    let pivot = |a: f32, b: f32, c: f32| (e(0, 0) * a + e(1, 1) * b + e(2, 2) * c) + 1.0f32;
    let t = [
        pivot(1.0, 1.0, 1.0),
        pivot(1.0, -1.0, -1.0),
        pivot(-1.0, 1.0, -1.0),
        pivot(-1.0, -1.0, 1.0),
    ];
    let candidates = [
        [t[0].clone(), d21.clone(), d02.clone(), d10.clone()],
        [d21, t[1].clone(), s01.clone(), s02.clone()],
        [d02, s01, t[2].clone(), s12.clone()],
        [d10, s02, s12, t[3].clone()],
    ];
    (t, candidates)
}

/// Unit quaternions `[N, 4]` (w, x, y, z) of rotations given as nine `[N, 1]` columns
/// (row-major). Shepperd's method: of the four formulas, each row uses the one whose pivot
/// `1 ± r00 ± r11 ± r22` is largest, so no division is ill-conditioned; the sign of the result
/// is arbitrary.
pub fn quaternions(r: &[Tensor<2>; 9]) -> Tensor<2> {
    let (t, candidates) = shepperd_candidates(r);
    let [first, rest @ ..] = candidates;
    let mut q = first;
    let mut best = t[0].clone();
    for (candidate, pivot) in rest.into_iter().zip(t.into_iter().skip(1)) {
        let better = pivot.clone().greater(best.clone());
        q = std::array::from_fn(|k| {
            q[k].clone()
                .mask_where(better.clone(), candidate[k].clone())
        });
        best = best.max_pair(pivot);
    }
    normalize(Tensor::cat(q.to_vec(), 1))
}

/// Unit vectors (zero vectors stay zero).
pub fn normalize(v: Tensor<2>) -> Tensor<2> {
    let norm = (v.clone() * v.clone()).sum_dim(1).sqrt().clamp_min(1e-12);
    v / norm
}

/// The posing transforms of a set of Gaussians on the device: the blended affine transform and
/// its nearest rotation, as a matrix (for normals) and as a quaternion (for the Gaussians'
/// orientations).
#[derive(Clone, Debug)]
pub struct Skinning {
    /// `[N, 3, 3]`.
    pub linear: Tensor<3>,
    /// `[N, 3]`.
    pub translation: Tensor<2>,
    /// `[N, 3, 3]`, [`nearest_rotation`]'s (one tensor, so that turning normals is two
    /// launches on a GPU: as nine columns it was 24, the columns' copies among them).
    pub rotation: Tensor<3>,
    /// `[N, 4]` (w, x, y, z).
    pub quaternion: Tensor<2>,
}

impl Skinning {
    /// The skinning of points with `skin` under joint transforms `[J, 3, 4]`: for joints that
    /// need no gradient, on the CPU backend one parallel loop ([`Skinning::on_host`]) and on
    /// GPU devices one kernel (`cube`); elsewhere tensor operations
    /// ([`Skinning::from_tensors`]); they agree to float rounding (tested).
    pub fn new(joints: &Tensor<3>, skin: &Taps) -> Self {
        match &skin.host {
            Some(host) if !joints.is_require_grad() => Self::on_host(joints, skin, host),
            #[cfg(any(feature = "gpu", feature = "cuda"))]
            _ if !joints.is_require_grad() => cube::skinning(joints, &skin.index, &skin.weight)
                .unwrap_or_else(|| Self::from_tensors(joints, skin)),
            _ => Self::from_tensors(joints, skin),
        }
    }

    /// [`Skinning::new`] as tensor operations, for every device.
    pub fn from_tensors(joints: &Tensor<3>, skin: &Taps) -> Self {
        let (linear, translation) = split_affine(blend(joints, skin));
        let columns = nearest_rotation(linear.clone());
        let n = translation.dims()[0];
        Self {
            quaternion: quaternions(&columns),
            linear,
            translation,
            rotation: Tensor::cat(columns.to_vec(), 1).reshape([n, 3, 3]),
        }
    }

    /// [`Skinning::new`] computed on the host, point by point in parallel, with the tensor
    /// path's arithmetic ([`nearest_rotation`], [`quaternions`]), uploaded to `joints`' device.
    fn on_host(joints: &Tensor<3>, skin: &Taps, host: &HostTaps) -> Self {
        let joint_values = host_data(joints.to_data());
        let rows = skin.rows;
        let per_point: Vec<PointSkinning> = (0..rows)
            .into_par_iter()
            .with_min_len(512)
            .map(|i| {
                let mut blended = [0.0f32; 12];
                for k in 0..skin.width {
                    let (j, w) = host.tap(k, i, rows);
                    for (b, &m) in blended.iter_mut().zip(&joint_values[12 * j..12 * j + 12]) {
                        *b += w * m;
                    }
                }
                PointSkinning::of_blend(&blended)
            })
            .collect();
        let device = joints.device();
        let upload = |values: Vec<f32>, width: usize| {
            Tensor::<2>::from_data(TensorData::new(values, [rows, width]), &device)
        };
        let (mut linear, mut translation, mut rotation, mut quaternion) = (
            Vec::with_capacity(9 * rows),
            Vec::with_capacity(3 * rows),
            Vec::with_capacity(9 * rows),
            Vec::with_capacity(4 * rows),
        );
        for p in &per_point {
            linear.extend_from_slice(&p.linear);
            translation.extend_from_slice(&p.translation);
            rotation.extend_from_slice(&p.rotation);
            quaternion.extend_from_slice(&p.quaternion);
        }
        Self {
            linear: upload(linear, 9).reshape([rows, 3, 3]),
            translation: upload(translation, 3),
            rotation: upload(rotation, 9).reshape([rows, 3, 3]),
            quaternion: upload(quaternion, 4),
        }
    }

    /// `R v` for vectors `[N, 3]`.
    pub fn rotate(&self, v: Tensor<2>) -> Tensor<2> {
        let n = v.dims()[0];
        (self.rotation.clone() * v.reshape([n, 1, 3]))
            .sum_dim(2)
            .reshape([n, 3])
    }

    /// Two sets of Gaussians' transforms, one after the other.
    pub fn cat(self, other: Self) -> Self {
        Self {
            linear: Tensor::cat(vec![self.linear, other.linear], 0),
            translation: Tensor::cat(vec![self.translation, other.translation], 0),
            rotation: Tensor::cat(vec![self.rotation, other.rotation], 0),
            quaternion: Tensor::cat(vec![self.quaternion, other.quaternion], 0),
        }
    }
}

/// One point's skinning transforms on the host (row-major, as [`Skinning`]'s tensors).
struct PointSkinning {
    linear: [f32; 9],
    translation: [f32; 3],
    rotation: [f32; 9],
    quaternion: [f32; 4],
}

impl PointSkinning {
    /// From a blended `[3, 4]` transform: [`nearest_rotation`]'s and [`quaternions`]'
    /// arithmetic on one matrix, the iteration stopped once it has converged.
    fn of_blend(m: &[f32; 12]) -> Self {
        let linear: [f32; 9] = std::array::from_fn(|k| m[4 * (k / 3) + k % 3]);
        let mut x = linear;
        for _ in 0..POLAR_ITERATIONS {
            let (cof, det) = cofactors_and_determinant(&x);
            let det = if det.abs() < 1e-20 { 1e-20 } else { det };
            let gamma = det.abs().powf(-1.0 / 3.0);
            let (g, h) = (gamma * 0.5, (gamma * det).recip() * 0.5);
            let next: [f32; 9] = std::array::from_fn(|k| x[k] * g + cof[k] * h);
            let change = next
                .iter()
                .zip(&x)
                .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
            x = next;
            // Converged (two or three iterations for a blend of nearby rotations): the tensor
            // path's remaining iterations would change nothing beyond rounding.
            if change < 1e-7 {
                break;
            }
        }
        Self {
            linear,
            translation: [m[3], m[7], m[11]],
            rotation: x,
            quaternion: shepperd(&x),
        }
    }
}

/// [`quaternions`] for one row-major rotation matrix (the same candidates, chosen by a branch).
fn shepperd(r: &[f32; 9]) -> [f32; 4] {
    let (t, candidates) = shepperd_candidates(r);
    let (mut q, mut best) = (candidates[0], t[0]);
    for (candidate, &pivot) in candidates.iter().zip(&t).skip(1) {
        if pivot > best {
            q = *candidate;
        }
        best = best.max(pivot);
    }
    let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
    q.map(|v| v / norm)
}

/// Linear blend skinning of Gaussians, the one training, inference and `f3g bench lbs` use:
/// means `[N, 3]` by their blended transforms, rotations `[N, 4]` (w, x, y, z) by the nearest
/// rotation of each blend; scales are unchanged.
pub fn pose_gaussians(
    means: Tensor<2>,
    quats: Tensor<2>,
    skinning: &Skinning,
) -> (Tensor<2>, Tensor<2>) {
    (
        transform_points(&skinning.linear, &skinning.translation, means),
        quat_mul(skinning.quaternion.clone(), quats),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Mat3, Quat, Vec3};
    use proptest::prelude::*;

    #[test]
    fn taps_gather_weighted_rows_and_pad_with_nothing() {
        let device = Device::flex();
        let x = Tensor::<2>::from_data(
            TensorData::new(vec![1.0, 10.0, 2.0, 20.0, 3.0, 30.0], [3, 2]),
            &device,
        );
        let rows: Vec<Vec<(usize, f32)>> = vec![vec![(2, 1.0)], vec![(0, 0.5), (1, 0.25)], vec![]];
        let taps = Taps::new(rows.iter().map(Vec::as_slice), &device);
        let expected = vec![3.0, 30.0, 1.0, 10.0, 0.0, 0.0];
        let host_taps = taps.host.as_deref().expect("taps on Flex keep host copies");
        assert_eq!(
            host_values(taps.apply_on_host(host_taps, x.clone())),
            expected
        );
        assert_eq!(host_values(taps.apply_as_tensors(x.clone())), expected);
        assert_eq!(host_values(taps.apply(x)), expected);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// Blends of up to four rotations (up to ±0.78 rad about random axes, so less than 90°
        /// apart, as LBS blends neighbouring joints; one scaled), with translations: the
        /// device's blended transforms, nearest rotations and quaternions equal
        /// `f3g_rig::point_transforms` (Newton to 1e-7 on the host, in f32), on the CPU path and
        /// the tensor path alike. Rotations further apart can blend to a singular matrix, which
        /// has no nearest rotation.
        #[test]
        fn device_skinning_equals_the_host_reference(
            angles in proptest::collection::vec((-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0, -0.78f32..0.78, 0.7f32..1.4), 4),
            weights in proptest::collection::vec(proptest::collection::vec(0.0f32..1.0, 4), 1..6),
            point in (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0),
        ) {
            let device = Device::flex();
            let joints: Vec<Affine3A> = angles
                .iter()
                .enumerate()
                .map(|(j, &(x, y, z, angle, s))| {
                    let axis = Vec3::new(x, y, z + 1.5).normalize();
                    let scale = if j == 3 { s } else { 1.0 };
                    Affine3A::from_mat3_translation(
                        Mat3::from_quat(Quat::from_axis_angle(axis, angle)) * scale,
                        Vec3::new(x, -y, 0.1 * j as f32),
                    )
                })
                .collect();
            // Each point: the first two joints always, the others as drawn.
            let lists: Vec<Vec<(usize, f32)>> = weights
                .iter()
                .map(|w| {
                    let mut l = vec![(0, 0.3 + w[0]), (1, 0.3 + w[1])];
                    l.extend((2..4).filter(|&j| w[j] > 0.5).map(|j| (j, w[j])));
                    l
                })
                .collect();
            let skin = SkinWeights::from_lists(&lists, 4).unwrap();
            let expected = f3g_rig::point_transforms(&joints, &skin);
            let (joint_tensor, taps) = (affine_tensor(&joints, &device), Taps::skin(&skin, &device));
            let n = skin.len();
            let p = Vec3::new(point.0, point.1, point.2);
            // Both paths: the CPU's loop and the tensor chain every other device runs.
            let host_taps = taps.host.as_deref().expect("taps on Flex keep host copies");
            for skinning in [Skinning::on_host(&joint_tensor, &taps, host_taps), Skinning::from_tensors(&joint_tensor, &taps)] {
                let points = Tensor::<2>::from_data(TensorData::new(p.to_array().repeat(n), [n, 3]), &device);
                let got = host_values(transform_points(&skinning.linear, &skinning.translation, points));
                let q = host_values(skinning.quaternion.clone());
                let r = host_values(skinning.rotation.clone().reshape([n, 9]));
                for (i, e) in expected.iter().enumerate() {
                    let want = e.affine.transform_point3(p);
                    prop_assert!((Vec3::from_slice(&got[3 * i..3 * i + 3]) - want).length() < 1e-5);
                    let quat = Quat::from_xyzw(q[4 * i + 1], q[4 * i + 2], q[4 * i + 3], q[4 * i]);
                    prop_assert!(quat.dot(e.rotation).abs() > 1.0 - 1e-5, "{quat:?} vs {:?}", e.rotation);
                    let m = Mat3::from_quat(e.rotation);
                    for a in 0..3 {
                        for b in 0..3 {
                            prop_assert!((r[9 * i + 3 * a + b] - m.col(b)[a]).abs() < 1e-4);
                        }
                    }
                }
            }
        }

        /// Shepperd's four branches, as tensors and on the host: every rotation, including half
        /// turns (w = 0), comes back.
        #[test]
        fn quaternions_of_rotation_matrices_round_trip(
            x in -1.0f32..1.0, y in -1.0f32..1.0, z in -1.0f32..1.0,
            angle in prop_oneof![Just(std::f32::consts::PI), -3.1f32..3.1],
        ) {
            let device = Device::flex();
            let axis = Vec3::new(x, y, z);
            prop_assume!(axis.length() > 0.1);
            let q = Quat::from_axis_angle(axis.normalize(), angle);
            let m = Mat3::from_quat(q);
            let r: [Tensor<2>; 9] = std::array::from_fn(|k| {
                Tensor::from_data(TensorData::new(vec![m.col(k % 3)[k / 3]], [1, 1]), &device)
            });
            let rows: [f32; 9] = std::array::from_fn(|k| m.col(k % 3)[k / 3]);
            for got in [host_values(quaternions(&r)), shepperd(&rows).to_vec()] {
                let got = Quat::from_xyzw(got[1], got[2], got[3], got[0]);
                prop_assert!(got.dot(q).abs() > 1.0 - 1e-6, "{got:?} vs {q:?}");
            }
        }
    }

    #[test]
    fn posing_gaussians_moves_means_and_turns_orientations() {
        let device = Device::flex();
        let rot = Quat::from_euler(glam::EulerRot::XYZ, 0.3, -0.5, 0.9);
        let joint =
            Affine3A::from_mat3_translation(Mat3::from_quat(rot) * 1.2, Vec3::new(0.1, -0.2, 0.3));
        let skin = SkinWeights::from_lists(&[vec![(0, 1.0)], vec![(0, 1.0)]], 1).unwrap();
        let skinning = Skinning::new(
            &affine_tensor(&[joint], &device),
            &Taps::skin(&skin, &device),
        );
        let means = vec![0.5, 0.1, -0.2, -1.0, 0.4, 0.7];
        let quat = Quat::from_euler(glam::EulerRot::XYZ, -0.2, 0.1, 0.4);
        let (m, q) = pose_gaussians(
            Tensor::from_data(TensorData::new(means.clone(), [2, 3]), &device),
            Tensor::from_data(
                TensorData::new([quat.w, quat.x, quat.y, quat.z].repeat(2), [2, 4]),
                &device,
            ),
            &skinning,
        );
        let (m, q) = (host_values(m), host_values(q));
        for g in 0..2 {
            let e = joint.transform_point3(Vec3::from_slice(&means[3 * g..3 * g + 3]));
            assert!((Vec3::from_slice(&m[3 * g..3 * g + 3]) - e).length() < 1e-5);
            let got = Quat::from_xyzw(q[4 * g + 1], q[4 * g + 2], q[4 * g + 3], q[4 * g]);
            assert!(got.dot(rot * quat).abs() > 1.0 - 1e-6);
        }
    }
}
