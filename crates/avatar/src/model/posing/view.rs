//! The view maps' per-Gaussian values as one backend op: posed unit normals and `n · v`, the
//! cosine between a Gaussian's posed normal and its direction to the camera.
//!
//! Why: as tensor ops ([`view_cosines_as_tensors`]: turning the normals, normalising them,
//! posing the points, the direction to the camera normalised, moved by the view noise and
//! normalised again, the dot product) one part's values were about 27 kernel launches on a GPU
//! (each normalisation six: product, sum, square root, the two of `clamp_min`, quotient), 54 in
//! a `paper` step's inputs. Here they are one pass per part: a parallel loop on the CPU, one
//! thread per Gaussian on a GPU (`posing/cube.rs`), with the tensor path's arithmetic term by
//! term, so that the two agree to float rounding.
//!
//! No gradient: the networks' inputs are data (skinning, template points and normals, camera).
//! [`view_cosines`] takes the tensor path when any input is tracked.
//!
//! Conventions: as [`super`]'s; rows of `[N, 3]` vectors; the camera centre `[1, 3]`.

#[cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))]
use burn::backend::fusion::custom::TensorSpec;
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, Flex, TensorMetadata, backend_extension};
#[cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))]
use burn::tensor::Shape;
use burn::tensor::Tensor;
use f3g_nets::host::{from_values, host_f32};
use rayon::prelude::*;

use super::{Skinning, normalize, transform_points};

/// Posed unit normals `[N, 3]` (the canonical `normals` turned by the skinning's nearest
/// rotation) and `n · v` `[N, 1]`, `v` the unit direction from each posed point (`canonical`
/// under the skinning's blend) to the camera `centre` `[1, 3]`, moved by `noise` (`[N, 3]`,
/// already scaled) and renormalised when given. Zero vectors stay zero. One op
/// ([`ViewBackend`]) where the backend has it and nothing is tracked; [`view_cosines_as_tensors`]
/// elsewhere.
pub fn view_cosines(
    skinning: &Skinning,
    canonical: &Tensor<2>,
    normals: &Tensor<2>,
    centre: &Tensor<2>,
    noise: Option<Tensor<2>>,
) -> (Tensor<2>, Tensor<2>) {
    let tracked = skinning.linear.is_require_grad()
        || skinning.translation.is_require_grad()
        || skinning.rotation.is_require_grad()
        || canonical.is_require_grad()
        || normals.is_require_grad()
        || centre.is_require_grad()
        || noise.as_ref().is_some_and(Tensor::is_require_grad);
    if tracked || !has_op(canonical) {
        return view_cosines_as_tensors(skinning, canonical, normals, centre, noise);
    }
    let n = canonical.dims()[0];
    let device = canonical.device();
    let on_op = |t: Tensor<2>| t.without_autodiff().into_dispatch();
    let noisy = noise.is_some();
    let (posed_normals, cosines) = <Dispatch as ViewBackend>::view_cosines(
        on_op(skinning.linear.clone().reshape([n, 9])),
        on_op(skinning.translation.clone()),
        on_op(skinning.rotation.clone().reshape([n, 9])),
        on_op(canonical.clone()),
        on_op(normals.clone()),
        on_op(centre.clone()),
        // Unread without noise: any tensor will do.
        on_op(noise.unwrap_or_else(|| centre.clone())),
        noisy,
    );
    (
        super::constant_on(&device, Tensor::from_dispatch(posed_normals)),
        super::constant_on(&device, Tensor::from_dispatch(cosines)),
    )
}

/// [`view_cosines`] in Burn's tensor ops (the reference the op is tested against, and the path
/// of tracked inputs and of backends without the op).
pub fn view_cosines_as_tensors(
    skinning: &Skinning,
    canonical: &Tensor<2>,
    normals: &Tensor<2>,
    centre: &Tensor<2>,
    noise: Option<Tensor<2>>,
) -> (Tensor<2>, Tensor<2>) {
    let normals = normalize(skinning.rotate(normals.clone()));
    let posed = transform_points(&skinning.linear, &skinning.translation, canonical.clone());
    let mut to_camera = normalize(centre.clone() - posed);
    if let Some(noise) = noise {
        to_camera = normalize(to_camera + noise);
    }
    let cosines = (normals.clone() * to_camera).sum_dim(1);
    (normals, cosines)
}

/// Whether the backend of `canonical` (`[N, 3]`) implements [`ViewBackend`] for `N` rows (the
/// largest input: the `[N, 9]` linear parts).
fn has_op(canonical: &Tensor<2>) -> bool {
    super::op_runs(canonical, 3 * canonical.shape().num_elements())
}

/// The view values as a backend op.
#[backend_extension(
    Flex,
    Cube: cfg(any(feature = "gpu", feature = "cuda")),
    Fusion: cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))
)]
pub trait ViewBackend: Backend {
    /// `linear` `[N, 9]` and `rotation` `[N, 9]` (row-major), `translation`, `canonical`,
    /// `normals` and, read when `noisy`, `noise` `[N, 3]`, `centre` `[1, 3]` → posed unit
    /// normals `[N, 3]` and cosines `[N, 1]`.
    #[fusion(meta = |_linear, translation, _rotation, _canonical, _normals, _centre, _noise, _noisy| {
        let rows = translation.shape[0];
        let spec = |dims: [usize; 2]| TensorSpec::new(Shape::new(dims), translation.dtype);
        (spec([rows, 3]), spec([rows, 1]))
    })]
    #[allow(clippy::too_many_arguments)]
    fn view_cosines(
        linear: FloatTensor<Self>,
        translation: FloatTensor<Self>,
        rotation: FloatTensor<Self>,
        canonical: FloatTensor<Self>,
        normals: FloatTensor<Self>,
        centre: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        noisy: bool,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);
}

/// `v / max(|v|, 1e-12)`: [`normalize`]'s arithmetic on one row.
fn unit(v: [f32; 3]) -> [f32; 3] {
    let norm = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-12);
    v.map(|x| x / norm)
}

/// One Gaussian's posed unit normal and cosine (the CPU's loop and the reference of the GPU
/// kernel's arithmetic): `linear` and `rotation` row-major.
fn view_row(
    linear: &[f32],
    translation: &[f32],
    rotation: &[f32],
    canonical: &[f32],
    normal: &[f32],
    centre: &[f32],
    noise: Option<&[f32]>,
) -> ([f32; 3], f32) {
    let times = |m: &[f32], v: &[f32], r: usize| {
        m[3 * r] * v[0] + m[3 * r + 1] * v[1] + m[3 * r + 2] * v[2]
    };
    let posed_normal = unit(std::array::from_fn(|r| times(rotation, normal, r)));
    let to_camera: [f32; 3] =
        std::array::from_fn(|r| centre[r] - (times(linear, canonical, r) + translation[r]));
    let mut v = unit(to_camera);
    if let Some(noise) = noise {
        v = unit(std::array::from_fn(|r| v[r] + noise[r]));
    }
    let cosine = posed_normal[0] * v[0] + posed_normal[1] * v[1] + posed_normal[2] * v[2];
    (posed_normal, cosine)
}

impl ViewBackend for Flex {
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
        let rows = translation.shape().dims::<2>()[0];
        let [
            linear,
            translation,
            rotation,
            canonical,
            normals,
            centre,
            noise,
        ] = [
            &linear,
            &translation,
            &rotation,
            &canonical,
            &normals,
            &centre,
            &noise,
        ]
        .map(host_f32);
        let mut posed_normals = vec![0.0f32; 3 * rows];
        let mut cosines = vec![0.0f32; rows];
        posed_normals
            .par_chunks_mut(3)
            .zip(cosines.par_iter_mut())
            .enumerate()
            .with_min_len(512)
            .for_each(|(i, (n, c))| {
                let (three, nine) = (3 * i..3 * i + 3, 9 * i..9 * i + 9);
                let (normal, cosine) = view_row(
                    &linear[nine.clone()],
                    &translation[three.clone()],
                    &rotation[nine],
                    &canonical[three.clone()],
                    &normals[three.clone()],
                    &centre,
                    noisy.then(|| &noise[three]),
                );
                n.copy_from_slice(&normal);
                *c = cosine;
            });
        (
            from_values(posed_normals, vec![rows, 3]),
            from_values(cosines, vec![rows, 1]),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::posing::{Taps, affine_tensor};
    use burn::tensor::{Device, TensorData};
    use glam::{Affine3A, Quat, Vec3};

    fn values(t: Tensor<2>) -> Vec<f32> {
        crate::model::host_values(t)
    }

    /// Rows `[n, 3]` of a smooth ramp.
    fn ramp(n: usize, phase: f32, scale: f32, device: &Device) -> Tensor<2> {
        let v = (0..3 * n)
            .map(|i| scale * (i as f32 * 0.73 + phase).sin())
            .collect();
        Tensor::from_data(TensorData::new(v, [n, 3]), device)
    }

    /// The op equals the tensor ops on the CPU, with and without view noise, for points
    /// skinned to two joints (so the blend is not a rotation and the normals need
    /// renormalising), one of them a zero normal, which stays zero.
    #[test]
    fn the_op_equals_the_tensor_ops() {
        let device = Device::flex();
        let n = 700;
        let joints = [
            Affine3A::from_rotation_translation(
                Quat::from_rotation_y(0.7),
                Vec3::new(0.1, 0.2, 0.3),
            ),
            Affine3A::from_rotation_translation(
                Quat::from_rotation_x(-1.1),
                Vec3::new(-0.2, 0.0, 0.4),
            ),
        ];
        let rows: Vec<Vec<(usize, f32)>> = (0..n)
            .map(|i| {
                let w = i as f32 / n as f32;
                vec![(0, w), (1, 1.0 - w)]
            })
            .collect();
        let skin = Taps::new(rows.iter().map(Vec::as_slice), &device);
        let skinning = Skinning::new(&affine_tensor(&joints, &device), &skin);
        let canonical = ramp(n, 0.3, 0.8, &device);
        let mut normal_values = values(ramp(n, 1.9, 1.0, &device));
        normal_values[3 * 5..3 * 6].fill(0.0);
        let normals = Tensor::from_data(TensorData::new(normal_values, [n, 3]), &device);
        let centre = Tensor::from_data(TensorData::new(vec![0.5, -1.0, 3.0], [1, 3]), &device);
        assert!(has_op(&canonical), "the CPU has the op");
        for noise in [None, Some(ramp(n, 0.9, 0.2, &device))] {
            let what = if noise.is_some() {
                "noisy"
            } else {
                "noiseless"
            };
            let (normals_op, cos_op) =
                view_cosines(&skinning, &canonical, &normals, &centre, noise.clone());
            let (normals_ref, cos_ref) =
                view_cosines_as_tensors(&skinning, &canonical, &normals, &centre, noise);
            assert_eq!(normals_op.dims(), [n, 3]);
            assert_eq!(cos_op.dims(), [n, 1]);
            for (got, expected, name) in [
                (values(normals_op), values(normals_ref), "normals"),
                (values(cos_op), values(cos_ref), "cosines"),
            ] {
                for (i, (g, e)) in got.iter().zip(&expected).enumerate() {
                    assert!((g - e).abs() < 1e-6, "{what} {name}[{i}]: {g} vs {e}");
                }
            }
        }
    }

    /// `view_row` by hand: a point at the origin seen from `+z` with the identity skinning has
    /// the cosine of its normal's angle to `+z`; noise along `x` of the same length as the
    /// direction turns it by 45°.
    #[test]
    fn a_row_by_hand() {
        let identity = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        let (normal, cosine) = view_row(
            &identity,
            &[0.0; 3],
            &identity,
            &[0.0; 3],
            &[0.0, 3.0, 4.0],
            &[0.0, 0.0, 2.0],
            None,
        );
        assert_eq!(normal, [0.0, 0.6, 0.8]);
        assert!((cosine - 0.8).abs() < 1e-7);
        let (_, cosine) = view_row(
            &identity,
            &[0.0; 3],
            &identity,
            &[0.0; 3],
            &[0.0, 0.0, 1.0],
            &[0.0, 0.0, 2.0],
            Some(&[1.0, 0.0, 0.0]),
        );
        assert!((cosine - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6);
    }
}
