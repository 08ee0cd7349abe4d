//! What a run derives from its body model and configuration before any training: the canonical
//! template, its position maps (one body Gaussian per covered texel), the densified head maps
//! (one face Gaussian per kept texel), the initial Gaussian attributes, and per-frame inputs
//! of the networks (posed maps, view maps, skinning transforms).
//!
//! Conventions: positions in metres, +Y up, the body facing +Z. Maps are `[R, 2R]` front | back
//! (see `f3g_template::posmap`); network inputs are `[1, 6, S, S]` (front xyz ‖ back xyz) of
//! root-relative posed positions, reduced from the maps by a masked box filter. The template
//! follows each frame's blend shapes (expressions) and pose correctives before it is posed, as
//! the posed body model does. Gaussian order:
//! body Gaussians (row-major over the body map), then face Gaussians (row-major over the head
//! map).

use std::num::NonZeroUsize;

use burn::tensor::{Device, Tensor, TensorData};
use glam::{Quat, Vec3};
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use crate::AvatarError;
use crate::config::{TemplateChoice, TrainConfig};
use f3g_rig::{ModelSpec, PointTransform, Rig, RigParams, point_transforms};
use f3g_splat::Camera;
use f3g_template::canonical::CanonicalPose;
use f3g_template::template::builtin_skirt;
use f3g_template::{HeadMaps, PosePca, Poser, PositionMaps, Template, TransferOptions};

/// What one frame's body parameters make of the avatar's Gaussians (body first, then face).
pub struct FrameGeometry {
    /// Canonical positions moved by the frame's blend shapes and correctives.
    pub canonical: Vec<Vec3>,
    /// That displacement alone.
    pub displacement: Vec<Vec3>,
    /// Root-relative posed positions of the body Gaussians (the body network's input).
    pub posed_body: Vec<Vec3>,
    /// Root-relative posed positions of the face Gaussians (the face networks' input).
    pub posed_face: Option<Vec<Vec3>>,
    /// Skinning transforms with the global root motion.
    pub transforms: Vec<PointTransform>,
}

/// The static part of an avatar.
pub struct Setup {
    pub model: ModelSpec,
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

/// `ln(p / (1 − p))`.
pub fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

impl Setup {
    /// Builds the template of `config` for the body model `model` (as named by the capture),
    /// with the subject's `identity` (shape) parameters.
    pub fn new(
        model_text: &str,
        identity: &[f32],
        config: &TrainConfig,
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
            &model,
            model_text,
            &pose,
            Some(identity),
            garment.as_ref().map(|(m, p)| (m.clone(), p.as_path())),
            &TransferOptions::default(),
        )?;
        let maps = PositionMaps::build(&template, config.map_resolution, None)?;
        let head = if config.face_branch {
            Some(HeadMaps::build(&maps, &rig.skeleton)?)
        } else {
            None
        };
        let body_log_scales = knn_log_scales(&maps.positions)?;
        let head_vertices = f3g_data::crop::head_vertices(&rig)?;
        let finger_params = rig.finger_params();
        Ok(Self {
            model,
            rig,
            template,
            maps,
            head,
            body_log_scales,
            head_vertices,
            finger_params,
        })
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

    /// Everything a frame's body parameters determine: the frame's blend shapes and
    /// correctives as canonical displacements, the root-relative posed positions (the network
    /// input) and the skinning transforms with the root motion (to pose the Gaussians).
    pub fn frame(&self, params: &RigParams) -> Result<FrameGeometry, AvatarError> {
        let poser = Poser::new(&self.rig, &self.template)?;
        let (root_free, posed) = poser.frame(params, false)?;
        let joints = poser.transforms(params, true)?;
        let per_vertex = poser.displacements(&self.template, &posed);
        let mut displacement = self.maps.interpolate(&per_vertex);
        let mut canonical: Vec<Vec3> = self
            .maps
            .positions
            .iter()
            .zip(&displacement)
            .map(|(p, d)| *p + *d)
            .collect();
        // The networks see the pose without root motion and without finger articulation.
        let input_pose = match self.hand_free(params) {
            None => root_free,
            Some(p) => poser.transforms(&p, false)?,
        };
        let posed_body = f3g_rig::skin_points(&input_pose, &self.maps.skin, &canonical);
        let mut transforms = point_transforms(&joints, &self.maps.skin);
        let posed_face = match &self.head {
            Some(h) => {
                let d = h.from_body(&displacement);
                let c: Vec<Vec3> = h.positions.iter().zip(&d).map(|(p, d)| *p + *d).collect();
                let posed = f3g_rig::skin_points(&input_pose, &h.skin, &c);
                transforms.extend(point_transforms(&joints, &h.skin));
                displacement.extend(d);
                canonical.extend(c);
                Some(posed)
            }
            None => None,
        };
        Ok(FrameGeometry {
            canonical,
            displacement,
            posed_body,
            posed_face,
            transforms,
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

    /// The body network's input: the posed map reduced to `[1, 6, S, S]`.
    pub fn body_input(&self, posed: &[Vec3], size: usize, device: &Device) -> Tensor<4> {
        let r = self.maps.resolution;
        let values: Vec<[f32; 3]> = posed.iter().map(|p| p.to_array()).collect();
        let map = self.maps.scatter(&values);
        let mask = self.maps.mask();
        two_sided_input(&map, &mask, r, 3, size, device)
    }

    /// The face networks' input: the posed head map resampled to `[1, 6, F, F]`.
    pub fn face_input(&self, posed_face: &[Vec3], size: usize, device: &Device) -> Tensor<4> {
        let head = self.head.as_ref().expect("face branch");
        let values: Vec<[f32; 3]> = posed_face.iter().map(|p| p.to_array()).collect();
        two_sided_input(
            &head.scatter(&values),
            &head_mask(head),
            head.size,
            3,
            size,
            device,
        )
    }

    /// View-conditioning maps `n · v` of the body (`[1, 1, S, S]` front and back), from the
    /// posed normals and the camera centre, with optional noise on the view direction.
    pub fn body_view_maps(
        &self,
        frame: &FrameGeometry,
        camera: &Camera,
        size: usize,
        noise: Option<(f32, u64)>,
        device: &Device,
    ) -> (Tensor<4>, Tensor<4>) {
        let n = self.maps.len();
        let values = view_cosines(
            &frame.canonical[..n],
            &self.maps.normals,
            &frame.transforms[..n],
            camera,
            noise,
        );
        let map = self.maps.scatter(&values);
        split_view(&map, &self.maps.mask(), self.maps.resolution, size, device)
    }

    /// View-conditioning maps of the face Gaussians, resampled to `[1, 1, F, F]` per side.
    pub fn face_view_maps(
        &self,
        frame: &FrameGeometry,
        camera: &Camera,
        size: usize,
        noise: Option<(f32, u64)>,
        device: &Device,
    ) -> (Tensor<4>, Tensor<4>) {
        let head = self.head.as_ref().expect("face branch");
        let n = self.maps.len();
        let values = view_cosines(
            &frame.canonical[n..],
            &head.normals,
            &frame.transforms[n..],
            camera,
            noise,
        );
        split_view(
            &head.scatter(&values),
            &head_mask(head),
            head.size,
            size,
            device,
        )
    }

    /// Fits the pose PCA on the posed maps of `frames` (body Gaussians, root-relative).
    pub fn fit_pca(
        &self,
        frames: &[RigParams],
        components: usize,
        sigma: f32,
    ) -> Result<PosePca, AvatarError> {
        // The posed maps in f32, their centred copy in f64, and the components.
        let values = 3 * self.body_count() as u64;
        f3g_io::memory::ensure_available(
            values * 12 * (frames.len() as u64 + components as u64),
            &format!(
                "the pose PCA of {} frames × {} body Gaussians (training frames, map_resolution)",
                frames.len(),
                self.body_count()
            ),
        )?;
        let samples = frames
            .par_iter()
            .map(|p| {
                self.frame(p).map(|f| {
                    f.posed_body
                        .iter()
                        .flat_map(|v| v.to_array())
                        .collect::<Vec<f32>>()
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(PosePca::fit(&samples, components, sigma)?)
    }
}

fn head_mask(head: &HeadMaps) -> Vec<bool> {
    let mut m = vec![false; head.size * 2 * head.size];
    for &p in &head.pixels {
        m[p] = true;
    }
    m
}

/// `n · v` per Gaussian: canonical normals rotated by the skinning rotation, `v` the unit
/// direction to the camera (jittered by `N(0, σ²)` per component when `noise` is given, as
/// Animatable Gaussians does in training).
fn view_cosines(
    positions: &[Vec3],
    normals: &[Vec3],
    transforms: &[PointTransform],
    camera: &Camera,
    noise: Option<(f32, u64)>,
) -> Vec<[f32; 1]> {
    let c = camera.center();
    let centre = Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32);
    positions
        .par_iter()
        .zip(normals)
        .zip(transforms)
        .enumerate()
        .map(|(i, ((p, n), t))| {
            let posed = t.affine.transform_point3(*p);
            let normal = (t.rotation * *n).normalize_or_zero();
            let mut v = centre - posed;
            v = v.normalize_or_zero();
            if let Some((sigma, seed)) = noise {
                v = (v + sigma * gaussian3(seed, i as u64)).normalize_or_zero();
            }
            [normal.dot(v)]
        })
        .collect()
}

/// Three standard normal values from a counter-based hash (order-independent, so parallel
/// evaluation stays deterministic).
fn gaussian3(seed: u64, i: u64) -> Vec3 {
    let mut state = seed ^ i.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    let mut uniform = || {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    let pair = |u1: f64, u2: f64| {
        let r = (-2.0 * u1.ln()).sqrt();
        let a = std::f64::consts::TAU * u2;
        (r * a.cos(), r * a.sin())
    };
    let (a, b) = pair(uniform(), uniform());
    let (c, _) = pair(uniform(), uniform());
    Vec3::new(a as f32, b as f32, c as f32)
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

/// Reduces a `[n, 2n, C]` two-sided map with validity `mask` to a `[1, 2C, S, S]` tensor
/// (front channels, then back), averaging the valid texels inside each output pixel's
/// footprint (box filter; when up-sampling, the texel under the pixel centre).
fn two_sided_input(
    map: &[f32],
    mask: &[bool],
    n: usize,
    channels: usize,
    size: usize,
    device: &Device,
) -> Tensor<4> {
    let mut out = vec![0.0f32; 2 * channels * size * size];
    let ratio = n as f32 / size as f32;
    for side in 0..2 {
        for y in 0..size {
            for x in 0..size {
                let (y0, y1) = footprint(y, ratio, n);
                let (x0, x1) = footprint(x, ratio, n);
                let mut acc = vec![0.0f32; channels];
                let mut count = 0.0f32;
                for sy in y0..y1 {
                    for sx in x0..x1 {
                        let p = sy * 2 * n + side * n + sx;
                        if mask[p] {
                            count += 1.0;
                            for (a, v) in acc.iter_mut().zip(&map[p * channels..(p + 1) * channels])
                            {
                                *a += v;
                            }
                        }
                    }
                }
                if count > 0.0 {
                    for (c, a) in acc.iter().enumerate() {
                        out[((side * channels + c) * size + y) * size + x] = a / count;
                    }
                }
            }
        }
    }
    Tensor::from_data(TensorData::new(out, [1, 2 * channels, size, size]), device)
}

/// Source rows/columns `[a, b)` covered by output pixel `i` at `ratio` source texels per pixel.
fn footprint(i: usize, ratio: f32, n: usize) -> (usize, usize) {
    if ratio <= 1.0 {
        let s = (((i as f32 + 0.5) * ratio) as usize).min(n - 1);
        (s, s + 1)
    } else {
        let a = (i as f32 * ratio).floor() as usize;
        let b = (((i + 1) as f32 * ratio).ceil() as usize).min(n);
        (a.min(n - 1), b.max(a + 1))
    }
}

fn split_view(
    map: &[f32],
    mask: &[bool],
    n: usize,
    size: usize,
    device: &Device,
) -> (Tensor<4>, Tensor<4>) {
    let both = two_sided_input(map, mask, n, 1, size, device);
    (
        both.clone().slice([0..1, 0..1, 0..size, 0..size]),
        both.slice([0..1, 1..2, 0..size, 0..size]),
    )
}

/// Rotation of a quaternion as `[w, x, y, z]`.
pub fn quat_wxyz(q: Quat) -> [f32; 4] {
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

    #[test]
    fn masked_reduction_averages_valid_texels_only() {
        // n = 4, two sides, 1 channel; reduce to 2×2.
        let n = 4;
        let mut map = vec![0.0f32; n * 2 * n];
        let mut mask = vec![false; n * 2 * n];
        for (y, x, v) in [(0, 0, 1.0), (0, 1, 3.0), (1, 0, 0.0)] {
            map[y * 2 * n + x] = v;
            mask[y * 2 * n + x] = true;
        }
        map[3 * 2 * n + n + 3] = 5.0;
        mask[3 * 2 * n + n + 3] = true;
        let t = two_sided_input(&map, &mask, n, 1, 2, &Device::flex());
        let v = t.into_data().try_into_vec::<f32>().unwrap();
        assert_eq!(v, vec![4.0 / 3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 5.0]);
    }

    #[test]
    fn counter_noise_is_deterministic_and_standard() {
        let a: Vec<Vec3> = (0..2000).map(|i| gaussian3(7, i)).collect();
        let b: Vec<Vec3> = (0..2000).map(|i| gaussian3(7, i)).collect();
        assert_eq!(a, b);
        let var = a.iter().map(|v| v.length_squared()).sum::<f32>() / (3.0 * a.len() as f32);
        assert!((var - 1.0).abs() < 0.1, "{var}");
    }
}
