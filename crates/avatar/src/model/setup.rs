//! What a run derives from its body model and configuration before any training: the canonical
//! template, its position maps (one body Gaussian per covered texel), the densified head maps
//! (one face Gaussian per kept texel), the initial Gaussian attributes, and the host's share of
//! each frame: the joint transforms and the template's vertex displacements ([`FramePose`];
//! [`super::inputs`] turns them into the networks' inputs on the device).
//!
//! Conventions: positions in metres, +Y up, the body facing +Z. Maps are `[R, 2R]` front | back
//! (see `f3g_template::posmap`). The template follows each frame's blend shapes (expressions)
//! and pose correctives before it is posed, as the posed body model does. Gaussian order:
//! body Gaussians (row-major over the body map), then face Gaussians (row-major over the head
//! map).

use std::num::NonZeroUsize;

use glam::{Affine3A, Quat, Vec3};
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use super::config::{ModelConfig, TemplateChoice};
use crate::AvatarError;
use f3g_rig::{ModelSpec, Rig, RigParams};
use f3g_template::canonical::CanonicalPose;
use f3g_template::template::builtin_skirt;
use f3g_template::{HeadMaps, Poser, PositionMaps, Template, TransferOptions};

/// What the host computes of a frame's body parameters; everything per Gaussian follows on the
/// device ([`super::inputs`]).
#[derive(Clone, Debug)]
pub struct FramePose {
    /// Canonical-to-posed transform of every joint, with the global root motion (posing the
    /// Gaussians).
    pub joints: Vec<Affine3A>,
    /// The same without root motion and with the fingers at rest (the networks' input pose).
    pub input_joints: Vec<Affine3A>,
    /// How the frame's blend shapes and pose correctives move each template vertex, in the
    /// canonical pose.
    pub displacement: Vec<Vec3>,
}

/// The static part of an avatar.
pub struct Setup {
    /// The body model (its `name` is the spec it was loaded from, e.g. `builtin`).
    pub rig: Rig,
    pub template: Template,
    pub maps: PositionMaps,
    /// The face Gaussians, when the face branch is on.
    pub head: Option<HeadMaps>,
    /// Initial natural-log scale (isotropic) of each body Gaussian.
    pub body_log_scales: Vec<f32>,
    /// Rig vertices of the head, for face boxes.
    pub head_vertices: Vec<usize>,
    /// Pose parameters of the fingers, left out of the networks' inputs.
    finger_params: Vec<usize>,
}

impl Setup {
    /// Builds the template of `config` for the body model `model_text` (as named by the
    /// capture, loaded from its asset files), with the subject's `identity` (shape)
    /// parameters. A trained run keeps what this makes ([`Setup::write`]).
    pub fn new(
        model_text: &str,
        identity: &[f32],
        config: &ModelConfig,
    ) -> Result<Self, AvatarError> {
        let model: ModelSpec = model_text
            .parse()
            .map_err(|e: String| AvatarError::config("model", e))?;
        let rig = model.load()?;
        let pose = CanonicalPose::default();
        let garment = match (&config.template, &model, &config.garment) {
            (TemplateChoice::Body, _, _) => None,
            (TemplateChoice::Clothed, _, Some(path)) => {
                let path = std::path::PathBuf::from(path);
                Some((f3g_template::mesh::read_mesh(&path)?, path))
            }
            (TemplateChoice::Clothed, ModelSpec::Builtin, None) => Some((
                builtin_skirt(&pose)?,
                std::path::PathBuf::from("builtin:skirt"),
            )),
            (TemplateChoice::Clothed, _, None) => {
                return Err(AvatarError::config(
                    "garment",
                    "template = clothed needs a garment mesh for this body model (or use template = body)",
                ));
            }
        };
        let (template, _) = Template::build(
            &rig,
            &pose,
            Some(identity),
            garment.as_ref().map(|(m, p)| (m.clone(), p.as_path())),
            &TransferOptions::default(),
        )?;
        let maps = PositionMaps::build(&template, config.map_resolution, None)?;
        let head = if config.face_branch {
            Some(HeadMaps::build(
                &maps,
                &rig.head_joints()?,
                config.face_density,
            )?)
        } else {
            None
        };
        let body_log_scales = knn_log_scales(&maps.positions)?;
        let head_vertices = rig.head_vertices()?;
        let finger_params = rig.finger_params()?;
        Ok(Self::from_parts(
            rig,
            template,
            maps,
            head,
            body_log_scales,
            head_vertices,
            finger_params,
        ))
    }

    /// A setup of parts already made (read from a run folder, [`super::setup_file`]).
    pub(crate) fn from_parts(
        rig: Rig,
        template: Template,
        maps: PositionMaps,
        head: Option<HeadMaps>,
        body_log_scales: Vec<f32>,
        head_vertices: Vec<usize>,
        finger_params: Vec<usize>,
    ) -> Self {
        Self {
            rig,
            template,
            maps,
            head,
            body_log_scales,
            head_vertices,
            finger_params,
        }
    }

    /// Pose parameters of the fingers, left out of the networks' inputs.
    pub fn finger_params(&self) -> &[usize] {
        &self.finger_params
    }

    /// Initial log-scales `[N, 3]`: the k-NN scale in the surface's tangent plane and
    /// `thickness` times it along the normal (the third axis of [`Self::initial_quats`]).
    pub fn initial_log_scales(&self, thickness: f32) -> Vec<f32> {
        let t = thickness.ln();
        self.body_log_scales
            .iter()
            .flat_map(|&s| [s, s, s + t])
            .collect()
    }

    /// Initial rotations `[N, 4]` (w, x, y, z): identity for isotropic Gaussians, otherwise the
    /// rotation taking the local z axis to the canonical surface normal.
    pub fn initial_quats(&self, thickness: f32) -> Vec<f32> {
        self.maps
            .normals
            .iter()
            .flat_map(|n| {
                let q = if thickness == 1.0 || n.length_squared() < 1e-12 {
                    Quat::IDENTITY
                } else {
                    Quat::from_rotation_arc(Vec3::Z, n.normalize())
                };
                quat_wxyz(q)
            })
            .collect()
    }

    pub fn body_count(&self) -> usize {
        self.maps.len()
    }

    pub fn face_count(&self) -> usize {
        self.head.as_ref().map_or(0, HeadMaps::len)
    }

    /// Checks that a capture's parameters belong to this avatar's body model.
    pub fn check_params(&self, params: &RigParams, what: &str) -> Result<(), AvatarError> {
        let expected = (
            self.rig.num_pose_params(),
            self.rig.identity.len(),
            self.rig.expression.len(),
        );
        let got = (
            params.pose.len(),
            params.identity.len(),
            params.expression.len(),
        );
        if got != expected {
            return Err(AvatarError::Invalid(format!(
                "{what}: body parameters with {} pose, {} identity and {} expression values do not belong to the avatar's body model `{}` ({} / {} / {})",
                got.0, got.1, got.2, self.template.model, expected.0, expected.1, expected.2
            )));
        }
        Ok(())
    }

    /// The frame's joint transforms and template displacements: the host's share of posing.
    pub fn pose(&self, params: &RigParams) -> Result<FramePose, AvatarError> {
        let poser = Poser::new(&self.rig, &self.template)?;
        let (root_free, posed) = poser.frame(params, false)?;
        // The networks see the pose without root motion and without finger articulation.
        let input_joints = match self.hand_free(params) {
            None => root_free,
            Some(p) => poser.transforms(&p, false)?,
        };
        Ok(FramePose {
            joints: poser.transforms(params, true)?,
            input_joints,
            displacement: poser.displacements(&self.template, &posed),
        })
    }

    /// `params` with the fingers at rest (Animatable Gaussians feeds its networks hand-free
    /// poses, so noisy hand poses of real captures do not reach them); `None` when they
    /// already are.
    fn hand_free(&self, params: &RigParams) -> Option<RigParams> {
        let moved = |i: &usize| params.pose.get(*i).is_some_and(|v| *v != 0.0);
        self.finger_params.iter().any(moved).then(|| {
            let mut p = params.clone();
            for &i in &self.finger_params {
                p.pose[i] = 0.0;
            }
            p
        })
    }
}

/// Initial log-scales: `ln √(mean squared distance to the 3 nearest neighbours)` (AG §2d).
fn knn_log_scales(points: &[Vec3]) -> Result<Vec<f32>, AvatarError> {
    if points.len() < 4 {
        return Err(AvatarError::Invalid(format!(
            "the position maps hold {} Gaussians; raise map_resolution",
            points.len()
        )));
    }
    let array: Vec<[f32; 3]> = points.iter().map(|p| p.to_array()).collect();
    let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&array)
        .map_err(|e| AvatarError::Invalid(format!("k-d tree of the Gaussians: {e:?}")))?;
    let k = NonZeroUsize::new(4).expect("non-zero");
    Ok(array
        .par_iter()
        .map(|p| {
            let hits = tree
                .query(p)
                .nearest_n::<SquaredEuclidean<f32>>(k)
                .execute();
            let mean = hits.iter().map(|h| h.distance).sum::<f32>() / 3.0;
            0.5 * mean.max(1e-14).ln()
        })
        .collect())
}

/// Rotation of a quaternion as `[w, x, y, z]`.
fn quat_wxyz(q: Quat) -> [f32; 4] {
    [q.w, q.x, q.y, q.z]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn knn_scales_of_a_grid_are_its_spacing() {
        let pts: Vec<Vec3> = (0..100)
            .map(|i| Vec3::new((i % 10) as f32 * 0.02, (i / 10) as f32 * 0.02, 0.0))
            .collect();
        let s = knn_log_scales(&pts).unwrap();
        // An interior point has 4 neighbours at 2 cm: the 3 nearest are all at 2 cm.
        assert!((s[55].exp() - 0.02).abs() < 1e-5, "{}", s[55].exp());
    }
}
