//! Front/back orthographic position maps of the canonical template.
//!
//! Layout: a map is `[R, 2R]` pixels, the front view in columns `0..R` and the back view in
//! columns `R..2R`. Both look along the Z axis with world x to the right and y up, so front
//! pixel `(i, j)` and back pixel `(i + R, j)` see the same `(x, y)`: the back view is the
//! 180°-rotated view mirrored horizontally, as in Animatable Gaussians. The square covers
//! `extent` metres around the centre of the template's x/y bounding box (default: 1.05 × its
//! larger side). Every covered pixel is one Gaussian; Gaussians are numbered in row-major order
//! over the `[R, 2R]` map.

use glam::{Vec2, Vec3};
use rayon::prelude::*;

use crate::TemplateError;
use crate::raster::{Projection, View, rasterize};
use crate::template::Template;
use f3g_rig::{Posed, Rig, RigParams, SkinWeights, skin_points, vertex_normals};

/// Canonical position maps and their Gaussians.
#[derive(Clone, Debug)]
pub struct PositionMaps {
    /// R: each side is `R × R`.
    pub resolution: usize,
    /// World `(x, y)` of the top-left corner of the maps, and the pixel size (metres).
    pub origin: Vec2,
    pub pixel_size: f32,
    /// Pixel index (into the `[R, 2R]` map) of every Gaussian, row-major.
    pub pixels: Vec<usize>,
    /// Canonical position, normal and skin weights of every Gaussian.
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub skin: SkinWeights,
    /// Template vertex label (body or garment) of the triangle each Gaussian lies on.
    pub labels: Vec<u8>,
    /// Template triangle corners and barycentric coordinates of each Gaussian.
    pub corners: Vec<[u32; 3]>,
    pub bary: Vec<[f32; 3]>,
}

impl PositionMaps {
    /// Renders the template's maps at `resolution` (each side `R × R`).
    pub fn build(
        template: &Template,
        resolution: usize,
        extent: Option<f32>,
    ) -> Result<Self, TemplateError> {
        if resolution < 2 {
            return Err(TemplateError::Invalid(format!(
                "map resolution {resolution} is too small"
            )));
        }
        let mesh = &template.mesh;
        let (lo, hi) = mesh
            .vertices
            .iter()
            .fold((Vec3::MAX, Vec3::MIN), |(l, h), v| (l.min(*v), h.max(*v)));
        let side = extent.unwrap_or(1.05 * (hi.x - lo.x).max(hi.y - lo.y));
        if !(side.is_finite() && side > 0.0) {
            return Err(TemplateError::Invalid(format!(
                "map extent {side} m is not positive"
            )));
        }
        let centre = Vec2::new(0.5 * (lo.x + hi.x), 0.5 * (lo.y + hi.y));
        let origin = Vec2::new(centre.x - 0.5 * side, centre.y + 0.5 * side);
        let pixel_size = side / resolution as f32;
        let normals = vertex_normals(&mesh.vertices, &mesh.triangles);
        let mut pixels = Vec::new();
        let mut positions = Vec::new();
        let mut gaussian_normals = Vec::new();
        let mut lists = Vec::new();
        let mut labels = Vec::new();
        let mut corners = Vec::new();
        let mut barys = Vec::new();
        let views = [View::Front, View::Back].map(|view| {
            rasterize(
                &mesh.vertices,
                &mesh.triangles,
                &Projection::Orthographic {
                    view,
                    origin,
                    pixel_size,
                },
                resolution,
                resolution,
                true,
            )
        });
        for row in 0..resolution {
            for (side_index, frags) in views.iter().enumerate() {
                for col in 0..resolution {
                    let p = row * resolution + col;
                    if !frags.covered(p) {
                        continue;
                    }
                    let tri = mesh.triangles[frags.triangle[p] as usize];
                    let b = frags.bary[p];
                    pixels.push(row * 2 * resolution + side_index * resolution + col);
                    positions.push((0..3).map(|k| mesh.vertices[tri[k] as usize] * b[k]).sum());
                    gaussian_normals.push(
                        (0..3)
                            .map(|k| normals[tri[k] as usize] * b[k])
                            .sum::<Vec3>()
                            .normalize_or_zero(),
                    );
                    lists.push(template.skin.mix(&[
                        (tri[0] as usize, b[0]),
                        (tri[1] as usize, b[1]),
                        (tri[2] as usize, b[2]),
                    ]));
                    labels.push(template.vertex_label[tri[0] as usize]);
                    corners.push(tri);
                    barys.push(b);
                }
            }
        }
        if pixels.is_empty() {
            return Err(TemplateError::Invalid(
                "the template covers no pixel of the position maps".into(),
            ));
        }
        let num_joints = template
            .skin
            .joints
            .iter()
            .flatten()
            .map(|&j| j as usize + 1)
            .max()
            .unwrap_or(1);
        let skin = SkinWeights::from_lists(&lists, num_joints)?;
        Ok(Self {
            resolution,
            origin,
            pixel_size,
            pixels,
            positions,
            normals: gaussian_normals,
            skin,
            labels,
            corners,
            bary: barys,
        })
    }

    /// Per-Gaussian values interpolated from per-template-vertex values.
    pub fn interpolate(&self, per_vertex: &[Vec3]) -> Vec<Vec3> {
        self.corners
            .iter()
            .zip(&self.bary)
            .map(|(t, b)| (0..3).map(|k| per_vertex[t[k] as usize] * b[k]).sum())
            .collect()
    }

    /// Number of Gaussians (covered pixels).
    pub fn len(&self) -> usize {
        self.pixels.len()
    }

    /// True when no pixel is covered.
    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }

    /// Map width (2R) and height (R).
    pub fn size(&self) -> (usize, usize) {
        (2 * self.resolution, self.resolution)
    }

    /// Scatters per-Gaussian values into a `[R, 2R, C]` map (zeros where uncovered).
    pub fn scatter<const C: usize>(&self, values: &[[f32; C]]) -> Vec<f32> {
        let (w, h) = self.size();
        let mut map = vec![0.0f32; w * h * C];
        for (&p, v) in self.pixels.iter().zip(values) {
            map[p * C..(p + 1) * C].copy_from_slice(v);
        }
        map
    }

    /// The coverage mask `[R, 2R]`.
    pub fn mask(&self) -> Vec<bool> {
        let (w, h) = self.size();
        let mut m = vec![false; w * h];
        for &p in &self.pixels {
            m[p] = true;
        }
        m
    }
}

/// The canonical pose of a template, posed once, for repeated posing of its maps.
pub struct Poser<'a> {
    rig: &'a Rig,
    canonical: Posed,
}

impl<'a> Poser<'a> {
    pub fn new(rig: &'a Rig, template: &Template) -> Result<Self, TemplateError> {
        Ok(Self {
            rig,
            canonical: rig.pose(&crate::canonical::without_root(rig, &template.canonical))?,
        })
    }

    /// Transforms taking canonical points to the frame's pose; with `root` false the global
    /// rotation and translation are left out (the posed-map convention). The canonical pose
    /// itself has no root motion.
    pub fn transforms(
        &self,
        params: &RigParams,
        root: bool,
    ) -> Result<Vec<glam::Affine3A>, TemplateError> {
        Ok(self.frame(params, root)?.0)
    }

    /// The frame's transforms (as [`Self::transforms`]) and its posed body model, whose rest
    /// vertices carry the frame's blend shapes and pose correctives.
    pub fn frame(
        &self,
        params: &RigParams,
        root: bool,
    ) -> Result<(Vec<glam::Affine3A>, Posed), TemplateError> {
        let frame = if root {
            params.clone()
        } else {
            crate::canonical::without_root(self.rig, params)
        };
        let posed = self.rig.pose(&frame)?;
        Ok((Rig::relative_transforms(&self.canonical, &posed), posed))
    }

    /// How a frame's blend shapes and pose correctives move each template vertex, expressed in
    /// the canonical pose: for a body vertex `v`, `A_canon(v) · (rest_frame(v) − rest_canon(v))`
    /// with `A_canon(v)` the linear part of its canonical skinning transform (so that skinning
    /// the displaced canonical point equals skinning the displaced rest vertex); garment
    /// vertices do not move.
    pub fn displacements(&self, template: &Template, frame: &Posed) -> Vec<Vec3> {
        template
            .body_vertex
            .par_iter()
            .map(|b| match b {
                Some(v) => {
                    let v = *v as usize;
                    let a = f3g_rig::skin::blend(
                        &self.canonical.skinning,
                        &self.rig.skin.joints[v],
                        &self.rig.skin.weights[v],
                    );
                    let delta = frame.rest_vertices[v] - self.canonical.rest_vertices[v];
                    glam::Mat3::from(a.matrix3) * delta
                }
                None => Vec3::ZERO,
            })
            .collect()
    }

    /// Posed positions of points with skin weights (root-relative when `root` is false).
    pub fn pose_points(
        &self,
        points: &[Vec3],
        skin: &SkinWeights,
        params: &RigParams,
        root: bool,
    ) -> Result<Vec<Vec3>, TemplateError> {
        Ok(skin_points(&self.transforms(params, root)?, skin, points))
    }
}

/// Root-relative posed positions of every Gaussian of the maps: the network input.
pub fn posed_positions(
    poser: &Poser,
    maps: &PositionMaps,
    params: &RigParams,
) -> Result<Vec<Vec3>, TemplateError> {
    poser.pose_points(&maps.positions, &maps.skin, params, false)
}

/// Encodes positions as colours for inspection: each axis scaled from its range to [0, 1].
pub fn position_colours(values: &[Vec3]) -> Vec<[f32; 3]> {
    let (lo, hi) = values
        .iter()
        .fold((Vec3::MAX, Vec3::MIN), |(l, h), v| (l.min(*v), h.max(*v)));
    let span = (hi - lo).max(Vec3::splat(1e-9));
    values
        .par_iter()
        .map(|v| ((*v - lo) / span).to_array())
        .collect()
}
