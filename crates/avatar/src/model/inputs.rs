//! The networks' inputs for one frame seen from one camera — posed position maps, view maps,
//! the template displacement and the skinning of every Gaussian — computed on the device from
//! what the host prepares per frame ([`crate::model::FramePose`]: joint transforms and the
//! template's vertex displacements). Training, evaluation and animation all build them here.
//!
//! Per frame the host uploads `2·J` joint transforms and `V` vertex displacements; everything
//! per Gaussian or per texel — barycentric interpolation of the displacements, densification
//! into the face Gaussians, skin blending, nearest rotations, posed maps, `n · v` maps, their
//! reduction to the networks' sizes and the pose PCA — is tensor work on the device
//! ([`GaussianTables`] holds the constant tables for it). Nothing is read back.

use burn::tensor::{Device, Tensor, TensorData};
use glam::Vec3;

use super::nets::Constants;
use super::posing::{
    Skinning, Taps, affine_tensor, blend, split_affine, transform_points, view_cosines,
};
use super::setup::{FramePose, Setup};
use crate::AvatarError;
use f3g_template::PosePca;

/// A frame's pose on the device.
#[derive(Clone, Debug)]
pub struct PoseTensors {
    /// `[J, 3, 4]` canonical-to-posed joint transforms with the root motion.
    pub joints: Tensor<3>,
    /// `[J, 3, 4]` the networks' input pose: no root motion, fingers at rest.
    pub input_joints: Tensor<3>,
    /// `[V, 3]` canonical displacement of every template vertex.
    pub displacement: Tensor<2>,
}

impl FramePose {
    /// Uploads the frame's pose (three small tensors).
    pub fn upload(&self, device: &Device) -> PoseTensors {
        PoseTensors {
            joints: affine_tensor(&self.joints, device),
            input_joints: affine_tensor(&self.input_joints, device),
            displacement: points_tensor(&self.displacement, device),
        }
    }
}

/// Points or vectors as a `[N, 3]` tensor.
fn points_tensor(points: &[Vec3], device: &Device) -> Tensor<2> {
    let values: Vec<f32> = points.iter().flat_map(|p| p.to_array()).collect();
    Tensor::from_data(TensorData::new(values, [points.len(), 3]), device)
}

/// One set of Gaussians laid out on a two-sided map (the body's, or the face's head map).
#[derive(Clone, Debug)]
struct Part {
    /// `[N, 3]` canonical template positions.
    positions: Tensor<2>,
    /// `[N, 3]` canonical normals.
    normals: Tensor<2>,
    /// One row per Gaussian, one tap per influencing joint.
    skin: Taps,
    /// The masked box filter of the map to the network's input: one row per input pixel
    /// (side, row, column), the mean of the Gaussians whose texels it covers.
    reduce: Taps,
    /// Side of the network input.
    size: usize,
}

impl Part {
    fn new(
        positions: &[Vec3],
        normals: &[Vec3],
        skin: &f3g_rig::SkinWeights,
        pixels: &[usize],
        map: usize,
        size: usize,
        device: &Device,
    ) -> Self {
        let reduce_rows = reduction(pixels, map, size);
        Self {
            positions: points_tensor(positions, device),
            normals: points_tensor(normals, device),
            skin: Taps::skin(skin, device),
            reduce: Taps::new(reduce_rows.iter().map(Vec::as_slice), device),
            size,
        }
    }

    /// Root-relative positions `[N, 3]` of canonical points in the networks' input pose.
    fn input_pose(&self, canonical: Tensor<2>, pose: &PoseTensors) -> Tensor<2> {
        let (linear, translation) = split_affine(blend(&pose.input_joints, &self.skin));
        transform_points(&linear, &translation, canonical)
    }

    /// Per-Gaussian values `[N, C]` as the network input `[1, 2C, S, S]` (front channels, then
    /// back).
    fn input(&self, values: Tensor<2>) -> Tensor<4> {
        let (s, c) = (self.size, values.dims()[1]);
        self.reduce
            .apply(values)
            .reshape([2, s, s, c])
            .permute([0, 3, 1, 2])
            .reshape([1, 2 * c, s, s])
    }

    /// Posed unit normals `[N, 3]` (the canonical normals turned by the skinning rotation) and
    /// the `n · v` maps `[1, 1, S, S]` (front, back) of them, `v` the unit direction from the
    /// posed Gaussian to the camera centre, moved by `noise` (`[N, 3]`, already scaled) and
    /// renormalised when given.
    fn normals_and_view(
        &self,
        canonical: &Tensor<2>,
        skinning: &Skinning,
        centre: &Tensor<2>,
        noise: Option<Tensor<2>>,
    ) -> (Tensor<2>, (Tensor<4>, Tensor<4>)) {
        let (normals, cosines) = view_cosines(skinning, canonical, &self.normals, centre, noise);
        let both = self.input(cosines);
        let s = self.size;
        let view = (
            both.clone().slice([0..1, 0..1, 0..s, 0..s]),
            both.slice([0..1, 1..2, 0..s, 0..s]),
        );
        (normals, view)
    }
}

/// For every pixel `(side, y, x)` of a `[size, size]` input per side, the Gaussians (by the
/// index of their texel in `pixels`, a `[map, 2·map]` layout) inside its footprint, each with
/// weight `1 / count`: the mean of the covered texels (box filter; when up-sampling, the texel
/// under the pixel centre). Pixels that cover none get no taps (zero).
fn reduction(pixels: &[usize], map: usize, size: usize) -> Vec<Vec<(usize, f32)>> {
    let mut gaussian = vec![usize::MAX; map * 2 * map];
    for (g, &p) in pixels.iter().enumerate() {
        gaussian[p] = g;
    }
    let ratio = map as f32 / size as f32;
    let mut rows = Vec::with_capacity(2 * size * size);
    for side in 0..2 {
        for y in 0..size {
            for x in 0..size {
                let (y0, y1) = footprint(y, ratio, map);
                let (x0, x1) = footprint(x, ratio, map);
                let covered: Vec<usize> = (y0..y1)
                    .flat_map(|sy| (x0..x1).map(move |sx| sy * 2 * map + side * map + sx))
                    .map(|p| gaussian[p])
                    .filter(|&g| g != usize::MAX)
                    .collect();
                let w = 1.0 / covered.len().max(1) as f32;
                rows.push(covered.into_iter().map(|g| (g, w)).collect());
            }
        }
    }
    rows
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

/// The setup's constant per-Gaussian tables on one device.
#[derive(Clone, Debug)]
pub struct GaussianTables {
    /// Barycentric interpolation of template-vertex values at the body Gaussians.
    body_from_vertices: Taps,
    body: Part,
    /// The face Gaussians (with the face branch): their densification taps into the body
    /// Gaussians and their head map.
    face: Option<(Taps, Part)>,
}

impl GaussianTables {
    /// The tables of `setup` for network inputs of `body_size`² and `face_size`² per side.
    pub fn new(setup: &Setup, body_size: usize, face_size: usize, device: &Device) -> Self {
        let maps = &setup.maps;
        let bary: Vec<Vec<(usize, f32)>> = maps
            .corners
            .iter()
            .zip(&maps.bary)
            .map(|(c, b)| (0..3).map(|k| (c[k] as usize, b[k])).collect())
            .collect();
        let body = Part::new(
            &maps.positions,
            &maps.normals,
            &maps.skin,
            &maps.pixels,
            maps.resolution,
            body_size,
            device,
        );
        let face = setup.head.as_ref().map(|h| {
            (
                Taps::new(h.sources.iter().map(Vec::as_slice), device),
                Part::new(
                    &h.positions,
                    &h.normals,
                    &h.skin,
                    &h.pixels,
                    h.size,
                    face_size,
                    device,
                ),
            )
        });
        Self {
            body_from_vertices: Taps::new(bary.iter().map(Vec::as_slice), device),
            body,
            face,
        }
    }

    /// `[N_b, 3]` canonical template positions of the body Gaussians.
    pub fn body_positions(&self) -> &Tensor<2> {
        &self.body.positions
    }

    /// Number of Gaussians with skin (body, and face when the setup has the face branch).
    pub fn count(&self) -> usize {
        self.body.skin.rows() + self.face.as_ref().map_or(0, |f| f.1.skin.rows())
    }

    /// The body Gaussians' canonical displacement and displaced canonical positions, and their
    /// root-relative posed positions in the networks' input pose (what the body network and the
    /// pose PCA see), each `[N_b, 3]`.
    pub(crate) fn posed_body(&self, pose: &PoseTensors) -> (Tensor<2>, Tensor<2>, Tensor<2>) {
        let displacement = self.body_from_vertices.apply(pose.displacement.clone());
        let canonical = self.body.positions.clone() + displacement.clone();
        let posed = self.body.input_pose(canonical.clone(), pose);
        (displacement, canonical, posed)
    }
}

/// The pose PCA on the device: posed maps are projected onto the training poses' principal
/// components with coefficients clamped to `±σ·stddev` (Animatable Gaussians' treatment of
/// unseen poses).
#[derive(Clone, Debug)]
pub struct PcaTensors {
    /// `[1, D]`.
    mean: Tensor<2>,
    /// `[K, D]`.
    components: Tensor<2>,
    /// `[1, K]`.
    limit: Tensor<2>,
}

impl PcaTensors {
    pub fn new(pca: &PosePca, device: &Device) -> Self {
        let (d, k) = (pca.mean.len(), pca.len());
        let limit: Vec<f32> = pca.stddev.iter().map(|s| pca.sigma * s).collect();
        Self {
            mean: Tensor::from_data(TensorData::new(pca.mean.clone(), [1, d]), device),
            components: Tensor::from_data(TensorData::new(pca.components.clone(), [k, d]), device),
            limit: Tensor::from_data(TensorData::new(limit, [1, k]), device),
        }
    }

    /// Projects `[N, 3]` positions (flattened row-major, as the PCA was fitted).
    pub fn project(&self, x: Tensor<2>) -> Tensor<2> {
        let [n, c] = x.dims();
        let centred = x.reshape([1, n * c]) - self.mean.clone();
        let coefficients = centred
            .matmul(self.components.clone().transpose())
            .max_pair(self.limit.clone().neg())
            .min_pair(self.limit.clone());
        (self.mean.clone() + coefficients.matmul(self.components.clone())).reshape([n, c])
    }
}

/// Everything the networks need for one (frame, camera), as tensors.
pub struct NetInputs {
    pub body_map: Tensor<4>,
    pub body_view: (Tensor<4>, Tensor<4>),
    pub face_map: Option<Tensor<4>>,
    pub face_view: Option<(Tensor<4>, Tensor<4>)>,
    /// `[N, 3]` canonical displacement of every Gaussian by the frame's blend shapes and
    /// correctives (body then face).
    pub displacement: Tensor<2>,
    /// `[N, 3]` posed unit surface normals of every Gaussian's template point (body then
    /// face): the view maps' `n` and what the light fixed in the world falls on.
    pub normals: Tensor<2>,
    /// Skinning of every Gaussian (body then face).
    pub skinning: Skinning,
}

impl Constants {
    /// The network inputs for a frame's `pose` seen from `camera`, on the constants' device,
    /// for the body Gaussians and, once the canonical face model exists
    /// ([`Constants::has_face`]), the face Gaussians. `noise` (`[N, 3]` for every Gaussian with
    /// skin, already scaled; training only) jitters the view directions. With `pca`, the body's
    /// posed map is first projected onto the training poses' principal components (the head
    /// maps are used as they are).
    pub fn inputs(
        &self,
        pose: &PoseTensors,
        camera: &f3g_splat::Camera,
        noise: Option<&Tensor<2>>,
        pca: Option<&PcaTensors>,
    ) -> Result<NetInputs, AvatarError> {
        let tables = &self.tables;
        let nb = tables.body.skin.rows();
        if let Some(noise) = noise
            && noise.dims() != [tables.count(), 3]
        {
            return Err(AvatarError::Invalid(format!(
                "view noise of shape {:?} for {} Gaussians",
                noise.dims(),
                tables.count()
            )));
        }
        let noise_rows = |a: usize, b: usize| noise.map(|t| t.clone().slice([a..b, 0..3]));
        let c = camera.center();
        let centre = Tensor::<2>::from_data(
            TensorData::new(vec![c[0] as f32, c[1] as f32, c[2] as f32], [1, 3]),
            &pose.displacement.device(),
        );
        let (body_displacement, body_canonical, mut posed_body) = tables.posed_body(pose);
        if let Some(pca) = pca {
            posed_body = pca.project(posed_body);
        }
        let body_skinning = Skinning::new(&pose.joints, &tables.body.skin);
        let (body_normals, body_view) = tables.body.normals_and_view(
            &body_canonical,
            &body_skinning,
            &centre,
            noise_rows(0, nb),
        );
        let mut inputs = NetInputs {
            body_map: tables.body.input(posed_body),
            body_view,
            face_map: None,
            face_view: None,
            displacement: body_displacement.clone(),
            normals: body_normals,
            skinning: body_skinning,
        };
        if let (Some((from_body, face)), true) = (&tables.face, self.has_face()) {
            let displacement = from_body.apply(body_displacement);
            let canonical = face.positions.clone() + displacement.clone();
            let posed = face.input_pose(canonical.clone(), pose);
            let skinning = Skinning::new(&pose.joints, &face.skin);
            let total = tables.count();
            let (normals, view) =
                face.normals_and_view(&canonical, &skinning, &centre, noise_rows(nb, total));
            inputs.face_view = Some(view);
            inputs.face_map = Some(face.input(posed));
            inputs.displacement = Tensor::cat(vec![inputs.displacement, displacement], 0);
            inputs.normals = Tensor::cat(vec![inputs.normals, normals], 0);
            inputs.skinning = inputs.skinning.cat(skinning);
        }
        Ok(inputs)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn masked_reduction_averages_valid_texels_only() {
        // A [4, 8] two-sided map reduced to 2×2 per side: Gaussians at texels (0,0), (0,1),
        // (1,0) of the front and (3,3) of the back, with values 1, 3, 0 and 5.
        let n = 4;
        let pixels = [0, 1, 2 * n, 3 * 2 * n + n + 3];
        let device = Device::flex();
        let taps = Taps::new(reduction(&pixels, n, 2).iter().map(Vec::as_slice), &device);
        let values =
            Tensor::<2>::from_data(TensorData::new(vec![1.0, 3.0, 0.0, 5.0], [4, 1]), &device);
        let v = taps
            .apply(values)
            .into_data()
            .try_into_vec::<f32>()
            .unwrap();
        assert_eq!(v, vec![4.0 / 3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 5.0]);
    }

    #[test]
    fn up_sampling_takes_the_texel_under_the_pixel_centre() {
        // A 2-texel-wide map read at 4 pixels per side: each texel twice.
        let rows = reduction(&[0, 1, 4, 5], 2, 4);
        let first: Vec<usize> = rows[..4].iter().map(|r| r[0].0).collect();
        assert_eq!(first, vec![0, 0, 1, 1]);
        assert!(rows.iter().all(|r| r.len() <= 1));
    }
}
