//! Pose-dependent corrective offsets added to the rest mesh before skinning.

use glam::{Mat3, Vec3};
use rayon::prelude::*;

use crate::skeleton::JointPose;

/// Corrective blend shapes driven by joint rotations.
#[derive(Clone, Debug, PartialEq)]
pub enum PoseCorrectives {
    /// SMPL family: `offsets = Σ_f P[f] · feature_f` with features `vec(R_j − I)` (row-major
    /// 3×3) of the pose rotations of joints `first_joint..`; `posedirs` is `[features, V·3]`.
    Linear {
        first_joint: usize,
        posedirs: Vec<f32>,
    },
    /// MHR: 6-D features of joints `first_joint..first_joint + joints` (the first two columns of
    /// each pose rotation, column-major, minus 1 at entries 0 and 4), a sparse linear layer
    /// without bias (`(out, in, weight)` entries, `hidden` outputs), ReLU, then a dense linear
    /// layer `[hidden, V·3]`.
    Mlp {
        first_joint: usize,
        joints: usize,
        sparse: Vec<(u32, u32, f32)>,
        hidden: usize,
        dense: Vec<f32>,
    },
}

impl PoseCorrectives {
    /// Number of input features.
    pub fn features(&self, num_joints: usize) -> usize {
        match self {
            Self::Linear { first_joint, .. } => 9 * (num_joints - first_joint),
            Self::Mlp { joints, .. } => 6 * joints,
        }
    }

    /// Adds the corrective offsets for `poses` to `vertices`.
    pub fn apply(&self, poses: &[JointPose], vertices: &mut [Vec3]) {
        let n3 = vertices.len() * 3;
        let (weights, coefficients): (&[f32], Vec<f32>) = match self {
            Self::Linear {
                first_joint,
                posedirs,
            } => {
                let features: Vec<f32> = poses[*first_joint..]
                    .iter()
                    .flat_map(|p| {
                        (Mat3::from_quat(p.rotation) - Mat3::IDENTITY)
                            .transpose()
                            .to_cols_array()
                    })
                    .collect();
                (posedirs, features)
            }
            Self::Mlp {
                first_joint,
                joints,
                sparse,
                hidden,
                dense,
            } => {
                let features: Vec<f32> = poses[*first_joint..first_joint + joints]
                    .iter()
                    .flat_map(|p| {
                        let r = Mat3::from_quat(p.rotation);
                        [
                            r.x_axis.x - 1.0,
                            r.x_axis.y,
                            r.x_axis.z,
                            r.y_axis.x,
                            r.y_axis.y - 1.0,
                            r.y_axis.z,
                        ]
                    })
                    .collect();
                let mut h = vec![0.0f32; *hidden];
                for &(o, i, w) in sparse {
                    h[o as usize] += w * features[i as usize];
                }
                h.iter_mut().for_each(|v| *v = v.max(0.0));
                (dense, h)
            }
        };
        // offsets = Σ_f c_f · W[f, :], accumulated row by row in parallel chunks.
        const CHUNK: usize = 4096;
        let mut offsets = vec![0.0f32; n3];
        offsets
            .par_chunks_mut(CHUNK)
            .enumerate()
            .for_each(|(ci, chunk)| {
                let start = ci * CHUNK;
                for (f, &c) in coefficients.iter().enumerate() {
                    if c != 0.0 {
                        let row = &weights[f * n3 + start..f * n3 + start + chunk.len()];
                        for (o, w) in chunk.iter_mut().zip(row) {
                            *o += c * w;
                        }
                    }
                }
            });
        for (v, o) in vertices.iter_mut().zip(offsets.chunks_exact(3)) {
            *v += Vec3::new(o[0], o[1], o[2]);
        }
    }
}
