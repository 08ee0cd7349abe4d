//! Mesh utilities: import (OBJ, PLY, glTF), cleaning, closest points, and the discrete
//! operators skin-weight inpainting needs (cotangent Laplacian, barycentric mass).

use std::collections::HashMap;
use std::path::Path;

use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};

use crate::TemplateError;
use f3g_rig::Mesh;

/// Reads a triangle mesh from `.obj`, `.ply` (ASCII or binary, `vertex` x/y/z and a `face`
/// index list) or `.gltf`/`.glb` (all triangle primitives, node transforms applied).
pub fn read_mesh(path: &Path) -> Result<Mesh, TemplateError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext.as_deref() {
        Some("obj") => Ok(f3g_rig::obj::read_obj(path)?),
        Some("ply") => read_ply_mesh(path),
        Some("gltf") | Some("glb") => read_gltf_mesh(path),
        _ => Err(TemplateError::file(
            path,
            "unknown mesh format: expected .obj, .ply, .gltf or .glb",
        )),
    }
}

fn read_ply_mesh(path: &Path) -> Result<Mesh, TemplateError> {
    use ply_rs_bw::ply::Property;
    let mut file = std::fs::File::open(path).map_err(|e| TemplateError::file(path, e))?;
    let ply = ply_rs_bw::parser::Parser::<ply_rs_bw::ply::DefaultElement>::new()
        .read_ply(&mut file)
        .map_err(|e| TemplateError::file(path, format!("cannot parse PLY: {e}")))?;
    let scalar = |p: Option<&Property>| -> Option<f32> {
        Some(match p? {
            Property::Float(v) => *v,
            Property::Double(v) => *v as f32,
            Property::Int(v) => *v as f32,
            Property::UInt(v) => *v as f32,
            Property::Short(v) => *v as f32,
            Property::UShort(v) => *v as f32,
            Property::Char(v) => *v as f32,
            Property::UChar(v) => *v as f32,
            _ => return None,
        })
    };
    let vertices = ply
        .payload
        .get("vertex")
        .ok_or_else(|| TemplateError::file(path, "no `vertex` element"))?;
    let mut mesh = Mesh::default();
    for (i, v) in vertices.iter().enumerate() {
        let (Some(x), Some(y), Some(z)) =
            (scalar(v.get("x")), scalar(v.get("y")), scalar(v.get("z")))
        else {
            return Err(TemplateError::file(
                path,
                format!("vertex {i} lacks numeric x, y, z"),
            ));
        };
        mesh.vertices.push(Vec3::new(x, y, z));
    }
    let faces = ply.payload.get("face").map(Vec::as_slice).unwrap_or(&[]);
    for (i, f) in faces.iter().enumerate() {
        let list = f.get("vertex_indices").or_else(|| f.get("vertex_index"));
        let idx: Vec<i64> = match list {
            Some(Property::ListInt(v)) => v.iter().map(|&x| x as i64).collect(),
            Some(Property::ListUInt(v)) => v.iter().map(|&x| x as i64).collect(),
            Some(Property::ListShort(v)) => v.iter().map(|&x| x as i64).collect(),
            Some(Property::ListUShort(v)) => v.iter().map(|&x| x as i64).collect(),
            Some(Property::ListUChar(v)) => v.iter().map(|&x| x as i64).collect(),
            Some(Property::ListChar(v)) => v.iter().map(|&x| x as i64).collect(),
            _ => {
                return Err(TemplateError::file(
                    path,
                    format!("face {i} has no vertex_indices list"),
                ));
            }
        };
        if idx.len() < 3
            || idx
                .iter()
                .any(|&x| x < 0 || x as usize >= mesh.vertices.len())
        {
            return Err(TemplateError::file(
                path,
                format!(
                    "face {i} has indices {idx:?} outside 0..{}",
                    mesh.vertices.len()
                ),
            ));
        }
        for k in 1..idx.len() - 1 {
            mesh.triangles
                .push([idx[0] as u32, idx[k] as u32, idx[k + 1] as u32]);
        }
    }
    Ok(mesh)
}

fn read_gltf_mesh(path: &Path) -> Result<Mesh, TemplateError> {
    let (doc, buffers) = f3g_rig::gltf::import(path)?;
    let mut mesh = Mesh::default();
    fn visit(
        node: gltf::Node,
        parent: glam::Mat4,
        buffers: &[gltf::buffer::Data],
        mesh: &mut Mesh,
    ) {
        let world = parent * glam::Mat4::from_cols_array_2d(&node.transform().matrix());
        if let Some(m) = node.mesh() {
            for prim in m
                .primitives()
                .filter(|p| p.mode() == gltf::mesh::Mode::Triangles)
            {
                let r = prim.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
                let Some(positions) = r.read_positions() else {
                    continue;
                };
                let start = mesh.vertices.len() as u32;
                let count = positions.len() as u32;
                mesh.vertices
                    .extend(positions.map(|p| world.transform_point3(Vec3::from(p))));
                match r.read_indices() {
                    Some(ix) => {
                        let ix: Vec<u32> = ix.into_u32().collect();
                        mesh.triangles.extend(
                            ix.chunks_exact(3)
                                .map(|t| [t[0] + start, t[1] + start, t[2] + start]),
                        );
                    }
                    None => mesh.triangles.extend(
                        (0..count / 3)
                            .map(|t| [start + 3 * t, start + 3 * t + 1, start + 3 * t + 2]),
                    ),
                }
            }
        }
        for c in node.children() {
            visit(c, world, buffers, mesh);
        }
    }
    for scene in doc.scenes() {
        for node in scene.nodes() {
            visit(node, glam::Mat4::IDENTITY, &buffers, &mut mesh);
        }
    }
    Ok(mesh)
}

/// What cleaning a mesh found.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MeshReport {
    /// Zero-area triangles removed.
    pub degenerate_triangles: usize,
    /// Edges shared by more than two triangles (kept; the operators below accept them).
    pub non_manifold_edges: usize,
    /// Vertices used by no triangle.
    pub unused_vertices: usize,
}

/// Rejects empty or non-finite meshes and drops degenerate triangles.
pub fn clean(mesh: &mut Mesh, label: &Path) -> Result<MeshReport, TemplateError> {
    if mesh.vertices.is_empty() || mesh.triangles.is_empty() {
        return Err(TemplateError::file(
            label,
            "the mesh is empty (no vertices or no triangles)",
        ));
    }
    if let Some(i) = mesh.vertices.iter().position(|v| !v.is_finite()) {
        return Err(TemplateError::file(
            label,
            format!("vertex {i} is not finite"),
        ));
    }
    if let Some(t) = mesh
        .triangles
        .iter()
        .position(|t| t.iter().any(|&i| i as usize >= mesh.vertices.len()))
    {
        return Err(TemplateError::file(
            label,
            format!("triangle {t} references a missing vertex"),
        ));
    }
    let before = mesh.triangles.len();
    let scale = bbox_diagonal(&mesh.vertices).max(1e-12);
    mesh.triangles.retain(|t| {
        let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
        t[0] != t[1]
            && t[1] != t[2]
            && t[0] != t[2]
            && (b - a).cross(c - a).length() > 1e-12 * scale * scale
    });
    if mesh.triangles.is_empty() {
        return Err(TemplateError::file(
            label,
            "every triangle is degenerate (zero area)",
        ));
    }
    let mut edges: HashMap<(u32, u32), u32> = HashMap::new();
    let mut used = vec![false; mesh.vertices.len()];
    for t in &mesh.triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            *edges.entry((a.min(b), a.max(b))).or_default() += 1;
            used[t[k] as usize] = true;
        }
    }
    Ok(MeshReport {
        degenerate_triangles: before - mesh.triangles.len(),
        non_manifold_edges: edges.values().filter(|&&c| c > 2).count(),
        unused_vertices: used.iter().filter(|u| !**u).count(),
    })
}

/// Length of the axis-aligned bounding box's diagonal.
pub fn bbox_diagonal(points: &[Vec3]) -> f32 {
    let (lo, hi) = points
        .iter()
        .fold((Vec3::MAX, Vec3::MIN), |(l, h), p| (l.min(*p), h.max(*p)));
    (hi - lo).length()
}

/// Closest point on triangle `abc` to `p`, as barycentric coordinates (Ericson, Real-Time
/// Collision Detection §5.1.5).
pub fn closest_on_triangle(p: Vec3, a: Vec3, b: Vec3, c: Vec3) -> [f32; 3] {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return [1.0, 0.0, 0.0];
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return [0.0, 1.0, 0.0];
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return [1.0 - v, v, 0.0];
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return [0.0, 0.0, 1.0];
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return [1.0 - w, 0.0, w];
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return [0.0, 1.0 - w, w];
    }
    let denom = 1.0 / (va + vb + vc);
    let (v, w) = (vb * denom, vc * denom);
    [1.0 - v - w, v, w]
}

/// Closest-point queries against a triangle mesh: the candidates are the triangles around
/// the `CANDIDATES` nearest vertices, which finds the true closest point on meshes whose
/// triangles are small compared with the query distance (body meshes).
pub struct SurfaceQuery<'a> {
    mesh: &'a Mesh,
    tree: ImmutableKdTree<f32, 3>,
    incident: Vec<Vec<u32>>,
}

const CANDIDATES: usize = 16;

/// A closest point: triangle, barycentric coordinates, position and distance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    pub triangle: u32,
    pub bary: [f32; 3],
    pub point: Vec3,
    pub distance: f32,
}

impl<'a> SurfaceQuery<'a> {
    pub fn new(mesh: &'a Mesh) -> Result<Self, TemplateError> {
        let points: Vec<[f32; 3]> = mesh.vertices.iter().map(|v| v.to_array()).collect();
        let tree = ImmutableKdTree::new_from_slice(&points)
            .map_err(|e| TemplateError::Invalid(format!("cannot index the mesh: {e:?}")))?;
        let mut incident = vec![Vec::new(); mesh.vertices.len()];
        for (t, tri) in mesh.triangles.iter().enumerate() {
            for &v in tri {
                incident[v as usize].push(t as u32);
            }
        }
        Ok(Self {
            mesh,
            tree,
            incident,
        })
    }

    /// The closest point of the surface to `p`.
    pub fn closest(&self, p: Vec3) -> SurfacePoint {
        let near = self
            .tree
            .query(&p.to_array())
            .nearest_n::<SquaredEuclidean<f32>>(
                std::num::NonZero::new(CANDIDATES).expect("non-zero"),
            )
            .execute();
        let mut best = SurfacePoint {
            triangle: u32::MAX,
            bary: [1.0, 0.0, 0.0],
            point: Vec3::ZERO,
            distance: f32::INFINITY,
        };
        for n in near {
            for &t in &self.incident[n.item as usize] {
                let [a, b, c] =
                    self.mesh.triangles[t as usize].map(|i| self.mesh.vertices[i as usize]);
                let bary = closest_on_triangle(p, a, b, c);
                let point = a * bary[0] + b * bary[1] + c * bary[2];
                let d = (point - p).length();
                if d < best.distance {
                    best = SurfacePoint {
                        triangle: t,
                        bary,
                        point,
                        distance: d,
                    };
                }
            }
        }
        best
    }
}

/// Cotangent Laplacian (`L_ij = ½(cot α_ij + cot β_ij)`, `L_ii = −Σ_j L_ij`) as triplets.
pub fn cotan_laplacian(vertices: &[Vec3], triangles: &[[u32; 3]]) -> Vec<(usize, usize, f64)> {
    let mut entries = Vec::with_capacity(triangles.len() * 12);
    for t in triangles {
        for k in 0..3 {
            let (i, j, o) = (
                t[(k + 1) % 3] as usize,
                t[(k + 2) % 3] as usize,
                t[k] as usize,
            );
            let (u, v) = (
                (vertices[i] - vertices[o]).as_dvec3(),
                (vertices[j] - vertices[o]).as_dvec3(),
            );
            let cot = u.dot(v) / u.cross(v).length().max(1e-20);
            let w = 0.5 * cot;
            entries.extend([(i, j, w), (j, i, w), (i, i, -w), (j, j, -w)]);
        }
    }
    entries
}

/// Barycentric lumped mass: a third of the area of every incident triangle.
pub fn barycentric_mass(vertices: &[Vec3], triangles: &[[u32; 3]]) -> Vec<f64> {
    let mut m = vec![0.0f64; vertices.len()];
    for t in triangles {
        let [a, b, c] = t.map(|i| vertices[i as usize].as_dvec3());
        let area = 0.5 * (b - a).cross(c - a).length();
        for &i in t {
            m[i as usize] += area / 3.0;
        }
    }
    m
}

/// Connected component label of every vertex (by shared triangles).
pub fn components(n: usize, triangles: &[[u32; 3]]) -> Vec<usize> {
    let mut parent: Vec<usize> = (0..n).collect();
    fn find(p: &mut [usize], mut x: usize) -> usize {
        while p[x] != x {
            p[x] = p[p[x]];
            x = p[x];
        }
        x
    }
    for t in triangles {
        for k in 1..3 {
            let (a, b) = (
                find(&mut parent, t[0] as usize),
                find(&mut parent, t[k] as usize),
            );
            parent[a] = b;
        }
    }
    (0..n).map(|v| find(&mut parent, v)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn closest_point_regions() {
        let (a, b, c) = (Vec3::ZERO, Vec3::X, Vec3::Y);
        assert_eq!(
            closest_on_triangle(Vec3::new(-1.0, -1.0, 0.0), a, b, c),
            [1.0, 0.0, 0.0]
        );
        let inside = closest_on_triangle(Vec3::new(0.25, 0.25, 3.0), a, b, c);
        assert!((inside[1] - 0.25).abs() < 1e-6 && (inside[2] - 0.25).abs() < 1e-6);
        let edge = closest_on_triangle(Vec3::new(0.5, -2.0, 0.0), a, b, c);
        assert!((edge[1] - 0.5).abs() < 1e-6 && edge[2] == 0.0);
    }

    #[test]
    fn laplacian_rows_sum_to_zero_and_mass_is_area() {
        let v = vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::new(1.0, 1.0, 0.0)];
        let t = vec![[0, 1, 2], [1, 3, 2]];
        let mut rows = [0.0f64; 4];
        for (i, _, w) in cotan_laplacian(&v, &t) {
            rows[i] += w;
        }
        assert!(rows.iter().all(|r| r.abs() < 1e-12));
        assert!((barycentric_mass(&v, &t).iter().sum::<f64>() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn cleaning_reports_and_rejects() {
        let mut m = Mesh {
            vertices: vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::new(2.0, 0.0, 0.0)],
            triangles: vec![[0, 1, 2], [0, 1, 3]],
        };
        let r = clean(&mut m, Path::new("m.obj")).unwrap();
        assert_eq!(r.degenerate_triangles, 1);
        assert_eq!(r.unused_vertices, 1);
        let mut empty = Mesh::default();
        assert!(
            clean(&mut empty, Path::new("e.obj"))
                .unwrap_err()
                .to_string()
                .contains("empty")
        );
        let mut flat = Mesh {
            vertices: vec![Vec3::ZERO, Vec3::X, Vec3::new(2.0, 0.0, 0.0)],
            triangles: vec![[0, 1, 2]],
        };
        assert!(
            clean(&mut flat, Path::new("f.obj"))
                .unwrap_err()
                .to_string()
                .contains("degenerate")
        );
    }
}
