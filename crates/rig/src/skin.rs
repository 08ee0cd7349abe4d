//! Sparse skin weights and linear blend skinning of points and Gaussians.
//!
//! A skinning transform maps a rest-space point to its posed position for one joint
//! (`world_j · inverse_bind_j`). LBS blends them per point: `x' = (Σ_k w_k M_{j_k}) x`.
//! Gaussians are posed with the same blended matrix `A`: the mean as a point, the rotation
//! left-multiplied by the rotation part of `A` (its polar factor, i.e. the nearest rotation), the
//! scales unchanged; their covariance therefore transforms as `R Σ Rᵀ`.

use glam::{Affine3A, Mat3, Quat, Vec3};
use rayon::prelude::*;

use crate::RigError;

/// Most joints influencing one vertex.
pub const MAX_INFLUENCES: usize = 8;

/// Up to [`MAX_INFLUENCES`] `(joint, weight)` pairs per point; unused slots have weight 0.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SkinWeights {
    pub joints: Vec<[u16; MAX_INFLUENCES]>,
    pub weights: Vec<[f32; MAX_INFLUENCES]>,
}

impl SkinWeights {
    /// From per-point `(joint, weight)` lists: keeps the largest [`MAX_INFLUENCES`] weights,
    /// and renormalises to sum 1. Errors name the first bad point.
    pub fn from_lists(lists: &[Vec<(usize, f32)>], num_joints: usize) -> Result<Self, RigError> {
        let mut out = Self {
            joints: Vec::with_capacity(lists.len()),
            weights: Vec::with_capacity(lists.len()),
        };
        for (i, list) in lists.iter().enumerate() {
            let mut pairs: Vec<(usize, f32)> =
                list.iter().copied().filter(|p| p.1 != 0.0).collect();
            if let Some(&(j, w)) = pairs
                .iter()
                .find(|(j, w)| *j >= num_joints || !w.is_finite() || *w < 0.0)
            {
                return Err(RigError::Model(format!(
                    "skin weight ({j}, {w}) of point {i}: joints must be < {num_joints}, weights finite and ≥ 0"
                )));
            }
            pairs.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
            pairs.truncate(MAX_INFLUENCES);
            let total: f32 = pairs.iter().map(|p| p.1).sum();
            if total <= 0.0 {
                return Err(RigError::Model(format!("point {i} has no skin weight")));
            }
            let mut joints = [0u16; MAX_INFLUENCES];
            let mut weights = [0f32; MAX_INFLUENCES];
            for (k, (j, w)) in pairs.into_iter().enumerate() {
                joints[k] = j as u16;
                weights[k] = w / total;
            }
            out.joints.push(joints);
            out.weights.push(weights);
        }
        Ok(out)
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.weights.len()
    }

    /// True without points.
    pub fn is_empty(&self) -> bool {
        self.weights.is_empty()
    }

    /// The non-zero `(joint, weight)` pairs of point `i`.
    pub fn influences(&self, i: usize) -> impl Iterator<Item = (usize, f32)> + '_ {
        self.joints[i]
            .iter()
            .zip(&self.weights[i])
            .filter(|(_, w)| **w > 0.0)
            .map(|(j, w)| (*j as usize, *w))
    }

    /// Weights blended from several points (e.g. barycentric interpolation over a triangle).
    pub fn mix(&self, points: &[(usize, f32)]) -> Vec<(usize, f32)> {
        let mut acc: Vec<(usize, f32)> = Vec::new();
        for &(p, t) in points {
            for (j, w) in self.influences(p) {
                match acc.iter_mut().find(|a| a.0 == j) {
                    Some(a) => a.1 += t * w,
                    None => acc.push((j, t * w)),
                }
            }
        }
        acc
    }

    /// The weights of a subset of points, in the given order.
    pub fn select(&self, indices: &[usize]) -> Self {
        Self {
            joints: indices.iter().map(|&i| self.joints[i]).collect(),
            weights: indices.iter().map(|&i| self.weights[i]).collect(),
        }
    }

    /// Dense `[points, joints]` row-major weights (for inpainting and tests).
    pub fn to_dense(&self, num_joints: usize) -> Vec<f32> {
        let mut dense = vec![0.0; self.len() * num_joints];
        for i in 0..self.len() {
            for (j, w) in self.influences(i) {
                dense[i * num_joints + j] += w;
            }
        }
        dense
    }
}

/// `Σ_k w_k M_{j_k}` for one point.
#[inline]
pub fn blend(
    transforms: &[Affine3A],
    joints: &[u16; MAX_INFLUENCES],
    weights: &[f32; MAX_INFLUENCES],
) -> Affine3A {
    let mut m = Mat3::ZERO;
    let mut t = Vec3::ZERO;
    for (j, &w) in joints.iter().zip(weights) {
        if w != 0.0 {
            let a = &transforms[*j as usize];
            m += Mat3::from(a.matrix3) * w;
            t += Vec3::from(a.translation) * w;
        }
    }
    Affine3A::from_mat3_translation(m, t)
}

/// Poses points with their skin weights (in parallel).
pub fn skin_points(transforms: &[Affine3A], skin: &SkinWeights, points: &[Vec3]) -> Vec<Vec3> {
    points
        .par_iter()
        .zip(skin.joints.par_iter().zip(&skin.weights))
        .map(|(p, (j, w))| blend(transforms, j, w).transform_point3(*p))
        .collect()
}

/// The blended transform of every point, with the rotation used for Gaussians.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointTransform {
    pub affine: Affine3A,
    /// Nearest rotation to the linear part (polar decomposition).
    pub rotation: Quat,
}

/// Blended transforms of all points (in parallel): what posing Gaussians needs.
pub fn point_transforms(transforms: &[Affine3A], skin: &SkinWeights) -> Vec<PointTransform> {
    skin.joints
        .par_iter()
        .zip(&skin.weights)
        .map(|(j, w)| {
            let affine = blend(transforms, j, w);
            PointTransform {
                affine,
                rotation: nearest_rotation(Mat3::from(affine.matrix3)),
            }
        })
        .collect()
}

/// The rotation closest to `m` (the orthogonal polar factor), for matrices with positive
/// determinant such as blends of rotations, by Newton's iteration `X ← ½(γX + (γX)⁻ᵀ/γ)`
/// with determinant scaling γ.
pub fn nearest_rotation(m: Mat3) -> Quat {
    let mut x = m;
    for _ in 0..20 {
        let det = x.determinant();
        if det.abs() < 1e-20 {
            break;
        }
        let gamma = det.abs().powf(-1.0 / 3.0);
        let next = (x * gamma + x.inverse().transpose() / gamma) * 0.5;
        let change = (next - x)
            .abs()
            .to_cols_array()
            .iter()
            .fold(0.0f32, |a, v| a.max(*v));
        x = next;
        if change < 1e-7 {
            break;
        }
    }
    Quat::from_mat3(&x).normalize()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn from_lists_keeps_the_largest_eight_and_renormalises() {
        let list: Vec<(usize, f32)> = (0..10).map(|j| (j, (j + 1) as f32)).collect();
        let s = SkinWeights::from_lists(&[list], 10).unwrap();
        let total: f32 = s.weights[0].iter().sum();
        assert!((total - 1.0).abs() < 1e-6);
        assert!(
            !s.joints[0].contains(&0)
                || s.weights[0][s.joints[0].iter().position(|&j| j == 0).unwrap()] == 0.0
        );
        assert_eq!(s.joints[0][0], 9);
        assert!(
            SkinWeights::from_lists(&[vec![(3, 1.0)]], 2)
                .unwrap_err()
                .to_string()
                .contains("point 0")
        );
        assert!(SkinWeights::from_lists(&[vec![(0, f32::NAN)]], 2).is_err());
        assert!(
            SkinWeights::from_lists(&[vec![]], 2)
                .unwrap_err()
                .to_string()
                .contains("no skin weight")
        );
    }

    proptest! {
        #[test]
        fn nearest_rotation_recovers_rotations_and_scaled_rotations(ax in -1.0f32..1.0, ay in -1.0f32..1.0, az in -1.0f32..1.0, angle in -3.0f32..3.0, s in 0.2f32..5.0) {
            let axis = Vec3::new(ax, ay, az + 1.5).normalize();
            let q = Quat::from_axis_angle(axis, angle);
            let r = nearest_rotation(Mat3::from_quat(q) * s);
            prop_assert!(r.dot(q).abs() > 1.0 - 1e-5);
        }

        #[test]
        fn nearest_rotation_is_orthogonal_for_blends(a in -1.5f32..1.5, b in -1.5f32..1.5, t in 0.0f32..1.0) {
            let m = Mat3::from_rotation_x(a) * (1.0 - t) + Mat3::from_rotation_y(b) * t;
            let r = Mat3::from_quat(nearest_rotation(m));
            prop_assert!((r * r.transpose() - Mat3::IDENTITY).abs().to_cols_array().iter().all(|v| *v < 1e-4));
            prop_assert!((r.determinant() - 1.0).abs() < 1e-4);
        }
    }

    #[test]
    fn gaussian_covariances_transform_as_r_sigma_rt() {
        // One joint rotated rigidly: the posed covariance must equal R Σ Rᵀ.
        let r = Quat::from_euler(glam::EulerRot::XYZ, 0.4, -0.7, 1.1);
        let transforms = [Affine3A::from_rotation_translation(
            r,
            Vec3::new(0.1, 0.2, 0.3),
        )];
        let skin = SkinWeights::from_lists(&[vec![(0, 1.0)]], 1).unwrap();
        let q = Quat::from_euler(glam::EulerRot::XYZ, 0.2, 0.3, -0.5);
        let scales = Mat3::from_diagonal(Vec3::new(0.01, 0.02, 0.05));
        let sigma = |q: Quat| {
            let m = Mat3::from_quat(q) * scales;
            m * m.transpose()
        };
        // A Gaussian posed as training poses it: mean by the blended transform, rotation by
        // the blend's nearest rotation.
        let t = point_transforms(&transforms, &skin)[0];
        let (mean, rot) = (t.affine.transform_point3(Vec3::X), t.rotation * q);
        let expected = Mat3::from_quat(r) * sigma(q) * Mat3::from_quat(r).transpose();
        assert!(
            (sigma(rot) - expected)
                .abs()
                .to_cols_array()
                .iter()
                .all(|v| *v < 1e-7)
        );
        assert!((mean - (r * Vec3::X + Vec3::new(0.1, 0.2, 0.3))).length() < 1e-6);
    }
}
