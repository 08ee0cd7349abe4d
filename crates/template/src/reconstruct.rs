//! Clothed geometry from a capture itself: a visual hull carved from the calibrated masks of
//! one frame, brought to the canonical pose by inverse skinning, split into body and garment by
//! its distance to the posed body model.
//!
//! 1. **Carving.** A voxel grid covers the posed body's bounding box plus a margin. A voxel's
//!    occupancy is the smallest mask value (bilinear, `α ∈ [0, 1]`) at its projection over the
//!    cameras that see it (outside a camera's image it is unconstrained by that camera); voxels
//!    seen by fewer than `min_views` cameras are empty. The field `0.5 − occupancy`, blurred by
//!    a 3×3×3 box, is the signed function whose zero set is extracted.
//! 2. **Extraction** with Surface Nets (`fast-surface-nets`; the dual of marching cubes: one
//!    vertex per surface voxel, quads split into triangles), then Taubin smoothing (λ = 0.5,
//!    μ = −0.53), which removes voxel steps without shrinking the hull.
//! 3. **Canonical pose.** Every hull vertex takes the skin weights of its closest point on the
//!    posed body model and is moved by the inverse of that blended frame transform followed by
//!    the canonical one (`C · M⁻¹`), the inverse-LBS of clothed-template pipelines.
//! 4. **Garment.** Vertices farther than `garment_distance` from the posed body surface are
//!    garment; the garment mesh is the triangles whose three corners are garment, in the
//!    canonical pose. It feeds `Template::build`, whose robust transfer gives it skin weights
//!    (inpainting the vertices far from the body).

use fast_surface_nets::ndshape::{RuntimeShape, Shape};
use fast_surface_nets::{SurfaceNetsBuffer, surface_nets};
use glam::{Affine3A, Mat3, Vec3};
use rayon::prelude::*;

use crate::TemplateError;
use crate::mesh::SurfaceQuery;
use f3g_camera::Camera;
use f3g_io::Image;
use f3g_rig::{Mesh, Posed, Rig, RigParams};

/// Settings of the reconstruction.
#[derive(Clone, Debug, PartialEq)]
pub struct HullOptions {
    /// Voxels along the longest side of the box.
    pub resolution: usize,
    /// Margin around the posed body's bounding box, metres.
    pub margin: f32,
    /// A voxel must project into at least this many images.
    pub min_views: usize,
    /// Taubin smoothing iterations.
    pub smoothing: usize,
    /// Hull vertices farther than this from the body surface are garment, metres.
    pub garment_distance: f32,
}

impl Default for HullOptions {
    fn default() -> Self {
        Self {
            resolution: 128,
            margin: 0.08,
            min_views: 3,
            smoothing: 10,
            garment_distance: 0.015,
        }
    }
}

/// One calibrated silhouette: a camera and its alpha mask (`[H, W, 1]`).
pub struct Silhouette<'a> {
    pub camera: &'a Camera,
    pub mask: &'a Image,
}

/// What the reconstruction produced.
#[derive(Clone, Debug)]
pub struct Reconstruction {
    /// The smoothed visual hull in the frame's pose.
    pub hull: Mesh,
    /// The garment part in the canonical pose.
    pub garment: Mesh,
    /// Hull vertices classified as garment.
    pub garment_vertices: usize,
}

fn sample_mask(mask: &Image, u: f64, v: f64) -> f32 {
    let (x, y) = (u - 0.5, v - 0.5);
    let (x0, y0) = (x.floor(), y.floor());
    let (tx, ty) = ((x - x0) as f32, (y - y0) as f32);
    let at = |i: f64, j: f64| {
        let (i, j) = (
            (i.max(0.0) as usize).min(mask.width - 1),
            (j.max(0.0) as usize).min(mask.height - 1),
        );
        mask.data[j * mask.width + i]
    };
    at(x0, y0) * (1.0 - tx) * (1.0 - ty)
        + at(x0 + 1.0, y0) * tx * (1.0 - ty)
        + at(x0, y0 + 1.0) * (1.0 - tx) * ty
        + at(x0 + 1.0, y0 + 1.0) * tx * ty
}

/// Carves the visual hull of `views` inside the box `[lo, hi]` and extracts its surface.
pub fn visual_hull(
    views: &[Silhouette],
    lo: Vec3,
    hi: Vec3,
    options: &HullOptions,
) -> Result<Mesh, TemplateError> {
    if views.len() < options.min_views.max(1) {
        return Err(TemplateError::Invalid(format!(
            "a visual hull needs at least {} views, got {}",
            options.min_views.max(1),
            views.len()
        )));
    }
    for v in views {
        if (v.mask.width, v.mask.height) != (v.camera.width as usize, v.camera.height as usize) {
            return Err(TemplateError::Invalid(format!(
                "a mask is {}×{} but its camera {}×{}",
                v.mask.width, v.mask.height, v.camera.width, v.camera.height
            )));
        }
    }
    let extent = hi - lo;
    if extent.min_element().is_nan() || extent.min_element() <= 0.0 || options.resolution < 8 {
        return Err(TemplateError::Invalid(
            "the hull's box is empty or the resolution below 8".into(),
        ));
    }
    let voxel = extent.max_element() / options.resolution as f32;
    // One padding voxel on each side keeps the surface closed.
    let dims = ((extent / voxel).ceil().as_uvec3() + 3).to_array();
    let shape = RuntimeShape::<u32, 3>::new(dims);
    let centre =
        |x: u32, y: u32, z: u32| lo + (Vec3::new(x as f32, y as f32, z as f32) - 1.0 + 0.5) * voxel;
    let occupancy: Vec<f32> = (0..shape.size())
        .into_par_iter()
        .map(|i| {
            let [x, y, z] = shape.delinearize(i);
            if x == 0
                || y == 0
                || z == 0
                || x + 1 >= dims[0]
                || y + 1 >= dims[1]
                || z + 1 >= dims[2]
            {
                return 0.0;
            }
            let p = centre(x, y, z);
            let mut seen = 0;
            let mut occ = 1.0f32;
            for v in views {
                let Some((uv, _)) = v.camera.project([p.x as f64, p.y as f64, p.z as f64]) else {
                    continue;
                };
                if uv[0] < 0.0
                    || uv[1] < 0.0
                    || uv[0] >= v.camera.width as f64
                    || uv[1] >= v.camera.height as f64
                {
                    continue;
                }
                seen += 1;
                occ = occ.min(sample_mask(v.mask, uv[0], uv[1]));
            }
            if seen < options.min_views { 0.0 } else { occ }
        })
        .collect();
    // Signed field, negative inside, blurred by a 3×3×3 box.
    let sdf: Vec<f32> = (0..shape.size())
        .into_par_iter()
        .map(|i| {
            let [x, y, z] = shape.delinearize(i);
            let mut sum = 0.0;
            let mut n = 0.0;
            for dz in -1i64..=1 {
                for dy in -1i64..=1 {
                    for dx in -1i64..=1 {
                        let (a, b, c) = (x as i64 + dx, y as i64 + dy, z as i64 + dz);
                        if a < 0 || b < 0 || c < 0 {
                            continue;
                        }
                        let (a, b, c) = (a as u32, b as u32, c as u32);
                        if a >= dims[0] || b >= dims[1] || c >= dims[2] {
                            continue;
                        }
                        sum += occupancy[shape.linearize([a, b, c]) as usize];
                        n += 1.0;
                    }
                }
            }
            0.5 - sum / n
        })
        .collect();
    let mut buffer = SurfaceNetsBuffer::default();
    surface_nets(
        &sdf,
        &shape,
        [0; 3],
        [dims[0] - 1, dims[1] - 1, dims[2] - 1],
        &mut buffer,
    );
    if buffer.indices.is_empty() {
        return Err(TemplateError::Invalid(
            "the masks carve nothing: check that the cameras see the person and the masks are not empty".into(),
        ));
    }
    let vertices: Vec<Vec3> = buffer
        .positions
        .iter()
        .map(|p| lo + (Vec3::from_array(*p) - 1.0 + 0.5) * voxel)
        .collect();
    let triangles = buffer
        .indices
        .chunks_exact(3)
        .map(|t| [t[0], t[1], t[2]])
        .collect();
    let mut mesh = Mesh {
        vertices,
        triangles,
    };
    taubin(&mut mesh, options.smoothing);
    Ok(mesh)
}

/// Taubin smoothing with uniform weights.
fn taubin(mesh: &mut Mesh, iterations: usize) {
    let n = mesh.vertices.len();
    let mut neighbours = vec![Vec::new(); n];
    for t in &mesh.triangles {
        for k in 0..3 {
            let (a, b) = (t[k] as usize, t[(k + 1) % 3] as usize);
            if !neighbours[a].contains(&b) {
                neighbours[a].push(b);
                neighbours[b].push(a);
            }
        }
    }
    let step = |v: &Vec<Vec3>, factor: f32| -> Vec<Vec3> {
        v.par_iter()
            .enumerate()
            .map(|(i, p)| {
                if neighbours[i].is_empty() {
                    return *p;
                }
                let mean: Vec3 =
                    neighbours[i].iter().map(|&j| v[j]).sum::<Vec3>() / neighbours[i].len() as f32;
                *p + factor * (mean - *p)
            })
            .collect()
    };
    for _ in 0..iterations {
        mesh.vertices = step(&mesh.vertices, 0.5);
        mesh.vertices = step(&mesh.vertices, -0.53);
    }
}

/// Carves the hull of a frame, moves it to the canonical pose of `canonical` and separates the
/// garment. `posed` is the body model evaluated at the frame's parameters; `skin_surface`
/// marks the rig vertices of the body's skin (garment helpers, teeth and the like are not).
pub fn reconstruct(
    views: &[Silhouette],
    rig: &Rig,
    posed: &Posed,
    skin_surface: &[bool],
    canonical: &RigParams,
    options: &HullOptions,
) -> Result<Reconstruction, TemplateError> {
    let (lo, hi) = posed
        .vertices
        .iter()
        .fold((Vec3::MAX, Vec3::MIN), |(l, h), v| (l.min(*v), h.max(*v)));
    let margin = Vec3::splat(options.margin);
    let hull = visual_hull(views, lo - margin, hi + margin, options)?;
    let (body, kept) = crate::template::submesh(
        &Mesh {
            vertices: posed.vertices.clone(),
            triangles: rig.mesh.triangles.clone(),
        },
        skin_surface,
    );
    let query = SurfaceQuery::new(&body)?;
    let canonical_posed = rig.pose(canonical)?;
    // Per hull vertex: closest body point, its distance and the blended frame → canonical map.
    let (moved, garment): (Vec<Vec3>, Vec<bool>) = hull
        .vertices
        .par_iter()
        .map(|&p| {
            let hit = query.closest(p);
            let tri = body.triangles[hit.triangle as usize].map(|v| kept[v as usize] as u32);
            let mut frame = Mat3::ZERO;
            let mut frame_t = Vec3::ZERO;
            let mut canon = Mat3::ZERO;
            let mut canon_t = Vec3::ZERO;
            for (k, &b) in hit.bary.iter().enumerate() {
                for (j, w) in rig.skin.influences(tri[k] as usize) {
                    let f = &posed.skinning[j];
                    let c = &canonical_posed.skinning[j];
                    frame += Mat3::from(f.matrix3) * (w * b);
                    frame_t += Vec3::from(f.translation) * (w * b);
                    canon += Mat3::from(c.matrix3) * (w * b);
                    canon_t += Vec3::from(c.translation) * (w * b);
                }
            }
            let to_rest = Affine3A::from_mat3_translation(frame, frame_t).inverse();
            let to_canonical = Affine3A::from_mat3_translation(canon, canon_t);
            (
                to_canonical.transform_point3(to_rest.transform_point3(p)),
                hit.distance > options.garment_distance,
            )
        })
        .unzip();
    let mut index = vec![u32::MAX; moved.len()];
    let mut vertices = Vec::new();
    for (i, &g) in garment.iter().enumerate() {
        if g {
            index[i] = vertices.len() as u32;
            vertices.push(moved[i]);
        }
    }
    let mut triangles: Vec<[u32; 3]> = hull
        .triangles
        .iter()
        .filter(|t| t.iter().all(|&v| garment[v as usize]))
        .map(|t| t.map(|v| index[v as usize]))
        .collect();
    // Small pieces are carving artefacts (concavities the cameras cannot see into), not
    // clothes: keep the connected pieces holding at least 5 % of the garment triangles.
    let label = crate::mesh::components(vertices.len(), &triangles);
    let mut size = std::collections::HashMap::new();
    for t in &triangles {
        *size.entry(label[t[0] as usize]).or_insert(0usize) += 1;
    }
    let total = triangles.len();
    triangles.retain(|t| size[&label[t[0] as usize]] * 20 >= total);
    if triangles.is_empty() {
        return Err(TemplateError::Invalid(format!(
            "no part of the hull is farther than {} m from the body: the capture shows no loose garment (use the body as the template)",
            options.garment_distance
        )));
    }
    let mut used = vec![false; vertices.len()];
    for t in &triangles {
        for &v in t {
            used[v as usize] = true;
        }
    }
    let (garment, _) = crate::template::submesh(
        &Mesh {
            vertices,
            triangles,
        },
        &used,
    );
    Ok(Reconstruction {
        hull,
        garment_vertices: garment.vertices.len(),
        garment,
    })
}
