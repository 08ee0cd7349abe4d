//! Robust skin-weight transfer (Abdrashitov et al. 2023, "Robust Skin Weights Transfer via
//! Weight Inpainting").
//!
//! 1. Every target vertex takes the weights (and normal) of its closest point on the body
//!    surface, interpolated barycentrically. The match is kept when the distance is at most
//!    `distance_ratio` × the target's bounding-box diagonal and the normals differ by at most
//!    `max_angle_deg`.
//! 2. Unmatched vertices are inpainted: with the cotangent Laplacian `L` and lumped mass `M`,
//!    `Q = −L + L M⁻¹ L`, solve `Q_UU W_U = −Q_UI W_I` (a sparse Cholesky per joint column) so the
//!    weights vary smoothly into the unmatched region.
//! 3. Weights are clipped to [0, 1] and renormalised, then kept to the 8 largest per vertex.
//!
//! A connected component of the target without a single match (e.g. a floating accessory)
//! cannot be inpainted; its vertices keep their closest-point weights, and the report counts
//! them. Vertices in no triangle likewise keep their closest-point weights.

use faer::Side;
use faer::linalg::solvers::Solve;
use faer::sparse::{SparseColMat, Triplet};
use glam::Vec3;
use rayon::prelude::*;

use crate::TemplateError;
use crate::mesh::{SurfaceQuery, barycentric_mass, bbox_diagonal, components, cotan_laplacian};
use f3g_rig::{Mesh, SkinWeights, vertex_normals};

/// Thresholds of the closest-point match.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TransferOptions {
    /// Maximum match distance as a fraction of the target's bounding-box diagonal.
    pub distance_ratio: f32,
    /// Maximum angle between the target and body normals, degrees.
    pub max_angle_deg: f32,
}

impl Default for TransferOptions {
    fn default() -> Self {
        Self {
            distance_ratio: 0.05,
            max_angle_deg: 30.0,
        }
    }
}

/// Transferred weights and what happened to each vertex.
#[derive(Clone, Debug)]
pub struct Transfer {
    pub skin: SkinWeights,
    /// Whether each target vertex matched the body (otherwise it was inpainted).
    pub matched: Vec<bool>,
    /// Vertices that could not be inpainted and kept their closest-point weights.
    pub fallback: usize,
}

/// Transfers skin weights from `body` (with `body_skin` over `num_joints` joints) to `target`.
pub fn transfer_weights(
    body: &Mesh,
    body_skin: &SkinWeights,
    num_joints: usize,
    target: &Mesh,
    options: &TransferOptions,
) -> Result<Transfer, TemplateError> {
    let n = target.vertices.len();
    let query = SurfaceQuery::new(body)?;
    let body_normals = vertex_normals(&body.vertices, &body.triangles);
    let target_normals = vertex_normals(&target.vertices, &target.triangles);
    let threshold = options.distance_ratio * bbox_diagonal(&target.vertices);
    let cos_limit = options.max_angle_deg.to_radians().cos();

    // 1. Closest-point weights, and whether each match is trusted.
    let closest: Vec<(Vec<(usize, f32)>, bool)> = target
        .vertices
        .par_iter()
        .zip(&target_normals)
        .map(|(&p, &normal)| {
            let hit = query.closest(p);
            let tri = body.triangles[hit.triangle as usize];
            let weights = body_skin.mix(&[
                (tri[0] as usize, hit.bary[0]),
                (tri[1] as usize, hit.bary[1]),
                (tri[2] as usize, hit.bary[2]),
            ]);
            let body_normal = (0..3)
                .map(|k| body_normals[tri[k] as usize] * hit.bary[k])
                .sum::<Vec3>()
                .normalize_or_zero();
            let ok = hit.distance <= threshold && normal.dot(body_normal) >= cos_limit;
            (weights, ok)
        })
        .collect();
    let matched: Vec<bool> = closest.iter().map(|c| c.1).collect();
    if !matched.iter().any(|m| *m) {
        return Err(TemplateError::Invalid(format!(
            "no vertex of the template lies within {threshold:.3} m of the body with a normal within {}°: is the mesh aligned with the canonical body?",
            options.max_angle_deg
        )));
    }

    // Vertices that take part in the inpainting: unmatched, in a triangle, in a component
    // that has at least one match.
    let label = components(n, &target.triangles);
    let mut component_has_match = std::collections::HashMap::new();
    let mut in_triangle = vec![false; n];
    for t in &target.triangles {
        for &v in t {
            in_triangle[v as usize] = true;
        }
    }
    for v in 0..n {
        if matched[v] {
            component_has_match.insert(label[v], true);
        }
    }
    let unknown: Vec<usize> = (0..n)
        .filter(|&v| !matched[v] && in_triangle[v] && component_has_match.contains_key(&label[v]))
        .collect();
    let fallback = (0..n).filter(|&v| !matched[v]).count() - unknown.len();

    let mut dense = vec![0.0f64; n * num_joints];
    for (v, (w, _)) in closest.iter().enumerate() {
        for &(j, x) in w {
            dense[v * num_joints + j] = x as f64;
        }
    }
    if !unknown.is_empty() {
        inpaint(target, &matched, &unknown, num_joints, &mut dense)?;
    }

    // 3. Clip, renormalise, keep the 8 largest.
    let lists: Vec<Vec<(usize, f32)>> = (0..n)
        .map(|v| {
            let row = &dense[v * num_joints..(v + 1) * num_joints];
            let clipped: Vec<(usize, f64)> = row
                .iter()
                .enumerate()
                .map(|(j, w)| (j, w.clamp(0.0, 1.0)))
                .filter(|(_, w)| *w > 1e-6)
                .collect();
            let total: f64 = clipped.iter().map(|p| p.1).sum();
            clipped
                .into_iter()
                .map(|(j, w)| (j, (w / total) as f32))
                .collect()
        })
        .collect();
    let skin = SkinWeights::from_lists(&lists, num_joints)?;
    Ok(Transfer {
        skin,
        matched,
        fallback,
    })
}

/// Solves `Q_UU W_U = −Q_UI W_I` for the unknown rows of `dense` (`[n, joints]`).
fn inpaint(
    target: &Mesh,
    matched: &[bool],
    unknown: &[usize],
    joints: usize,
    dense: &mut [f64],
) -> Result<(), TemplateError> {
    let n = target.vertices.len();
    let laplacian = cotan_laplacian(&target.vertices, &target.triangles);
    let mass = barycentric_mass(&target.vertices, &target.triangles);
    // Q = −L + L M⁻¹ L, assembled row by row from L's adjacency.
    let mut rows: Vec<std::collections::HashMap<usize, f64>> = vec![Default::default(); n];
    for &(i, j, w) in &laplacian {
        *rows[i].entry(j).or_default() += w;
    }
    let l_rows: Vec<Vec<(usize, f64)>> = rows
        .iter()
        .map(|r| r.iter().map(|(&j, &w)| (j, w)).collect())
        .collect();
    // Only the unknown rows of Q are needed.
    let q: Vec<std::collections::HashMap<usize, f64>> = unknown
        .par_iter()
        .map(|&i| {
            let mut row: std::collections::HashMap<usize, f64> = Default::default();
            for &(k, lik) in &l_rows[i] {
                *row.entry(k).or_default() -= lik;
                let scaled = lik / mass[k].max(1e-20);
                for &(j, lkj) in &l_rows[k] {
                    *row.entry(j).or_default() += scaled * lkj;
                }
            }
            row
        })
        .collect();
    let mut position = vec![usize::MAX; n];
    for (u, &v) in unknown.iter().enumerate() {
        position[v] = u;
    }
    let mut triplets = Vec::new();
    let mut rhs = faer::Mat::<f64>::zeros(unknown.len(), joints);
    for (u, row) in q.iter().enumerate() {
        for (&j, &w) in row {
            if position[j] != usize::MAX {
                triplets.push(Triplet::new(u, position[j], w));
            } else if matched[j] {
                for c in 0..joints {
                    rhs[(u, c)] -= w * dense[j * joints + c];
                }
            }
        }
    }
    let quu =
        SparseColMat::<usize, f64>::try_new_from_triplets(unknown.len(), unknown.len(), &triplets)
            .map_err(|e| TemplateError::Invalid(format!("inpainting system: {e:?}")))?;
    let llt = quu.sp_cholesky(Side::Lower).map_err(|e| TemplateError::Invalid(format!("the inpainting system is not positive definite ({e:?}); is the template mesh badly shaped?")))?;
    let solution = llt.solve(&rhs);
    for (u, &v) in unknown.iter().enumerate() {
        for c in 0..joints {
            dense[v * joints + c] = solution[(u, c)];
        }
    }
    Ok(())
}
