//! The canonical clothed template: a mesh in the canonical pose with skin weights, and the
//! body model and canonical parameters it belongs to.
//!
//! File format (`.npz`, written atomically): `vertices (V,3)` metres in canonical space,
//! `triangles (F,3)`, `skin_joints (V,8)`, `skin_weights (V,8)`, `vertex_label (V)` (0 body,
//! 1 garment), `canonical_pose (P)`, `canonical_identity (I)`, `canonical_expression (E)`, and
//! UTF-8 byte arrays `model` (the `--model` spec, e.g. `builtin`) and `pose_names`
//! (newline-separated) so a template is checked against the model it is used with.

use std::path::Path;

use glam::Vec3;

use crate::TemplateError;
use crate::canonical::CanonicalPose;
use crate::mesh::{MeshReport, clean};
use crate::transfer::{Transfer, TransferOptions, transfer_weights};
use f3g_rig::{MAX_INFLUENCES, Mesh, Rig, RigParams, SkinWeights};

/// Vertex labels.
pub const LABEL_BODY: u8 = 0;
pub const LABEL_GARMENT: u8 = 1;

/// A canonical template.
#[derive(Clone, Debug)]
pub struct Template {
    /// The body model, as given on the command line (`builtin`, `smplx:...`, ...).
    pub model: String,
    pub canonical: RigParams,
    pub mesh: Mesh,
    pub skin: SkinWeights,
    pub vertex_label: Vec<u8>,
    /// The body model's vertex each template vertex copies (`None` for garment vertices), so
    /// that a frame's blend shapes and pose correctives can move the template too.
    pub body_vertex: Vec<Option<u32>>,
}

/// How a template was made.
#[derive(Clone, Debug, Default)]
pub struct BuildReport {
    pub garment: Option<MeshReport>,
    pub matched: usize,
    pub inpainted: usize,
    pub fallback: usize,
}

/// The part of a mesh made of the selected vertices (triangles whose corners are all kept).
pub fn submesh(mesh: &Mesh, keep: &[bool]) -> (Mesh, Vec<usize>) {
    let mut index = vec![u32::MAX; mesh.vertices.len()];
    let mut kept = Vec::new();
    for (v, &k) in keep.iter().enumerate() {
        if k {
            index[v] = kept.len() as u32;
            kept.push(v);
        }
    }
    let triangles = mesh
        .triangles
        .iter()
        .filter(|t| t.iter().all(|&v| keep[v as usize]))
        .map(|t| t.map(|v| index[v as usize]))
        .collect();
    (
        Mesh {
            vertices: kept.iter().map(|&v| mesh.vertices[v]).collect(),
            triangles,
        },
        kept,
    )
}

/// The built-in human's skirt helper in the canonical pose, as a garment mesh for
/// [`Template::build`] (what `--clothes builtin:skirt` means).
pub fn builtin_skirt(pose: &CanonicalPose) -> Result<Mesh, TemplateError> {
    let human = f3g_rig::builtin::load()?;
    let params = human.rig.canonical_params(pose)?;
    let posed = human.rig.pose(&params)?;
    let skirt = human
        .part("skirt")
        .ok_or_else(|| TemplateError::Invalid("the built-in human has no skirt part".into()))?;
    let keep: Vec<bool> = human.vertex_part.iter().map(|p| *p == skirt).collect();
    Ok(submesh(
        &Mesh {
            vertices: posed.vertices,
            triangles: human.rig.mesh.triangles.clone(),
        },
        &keep,
    )
    .0)
}

impl Template {
    /// The body model's skin surface ([`Rig::surface`]) alone in the canonical pose, or with a
    /// garment mesh (aligned with the canonical body) whose skin weights are transferred from
    /// the body. `identity` gives the body its subject's shape (zero when `None`).
    pub fn build(
        rig: &Rig,
        pose: &CanonicalPose,
        identity: Option<&[f32]>,
        garment: Option<(Mesh, &Path)>,
        transfer: &TransferOptions,
    ) -> Result<(Self, BuildReport), TemplateError> {
        let mut canonical = rig.canonical_params(pose)?;
        if let Some(id) = identity {
            if id.len() != canonical.identity.len() || id.iter().any(|v| !v.is_finite()) {
                return Err(TemplateError::Invalid(format!(
                    "identity of {} finite values expected for {}, got {}",
                    canonical.identity.len(),
                    rig.name,
                    id.len()
                )));
            }
            canonical.identity = id.to_vec();
        }
        let posed = rig.pose(&canonical)?;
        let (body, kept) = submesh(
            &f3g_rig::Mesh {
                vertices: posed.vertices.clone(),
                triangles: rig.mesh.triangles.clone(),
            },
            &rig.surface,
        );
        let body_skin = rig.skin.select(&kept);
        let mut report = BuildReport::default();
        let mut mesh = body.clone();
        let mut skin = body_skin.clone();
        let mut vertex_label = vec![LABEL_BODY; mesh.vertices.len()];
        let mut body_vertex: Vec<Option<u32>> = kept.iter().map(|&v| Some(v as u32)).collect();
        if let Some((mut g, label)) = garment {
            report.garment = Some(clean(&mut g, label)?);
            let Transfer {
                skin: gs,
                matched,
                fallback,
            } = transfer_weights(&body, &body_skin, rig.skeleton.len(), &g, transfer)?;
            report.matched = matched.iter().filter(|m| **m).count();
            report.inpainted = matched.len() - report.matched - fallback;
            report.fallback = fallback;
            let offset = mesh.vertices.len() as u32;
            mesh.vertices.extend(&g.vertices);
            mesh.triangles
                .extend(g.triangles.iter().map(|t| t.map(|v| v + offset)));
            skin.joints.extend(gs.joints);
            skin.weights.extend(gs.weights);
            vertex_label.extend(std::iter::repeat_n(LABEL_GARMENT, g.vertices.len()));
            body_vertex.extend(std::iter::repeat_n(None, g.vertices.len()));
        }
        Ok((
            Self {
                model: rig.name.clone(),
                canonical,
                mesh,
                skin,
                vertex_label,
                body_vertex,
            },
            report,
        ))
    }

    /// Writes the template (`.npz`), atomically.
    pub fn save(&self, path: &Path, rig: &Rig) -> Result<(), TemplateError> {
        use f3g_io::NpyValues::{F32, I64};
        let v = self.mesh.vertices.len();
        let verts: Vec<f32> = self
            .mesh
            .vertices
            .iter()
            .flat_map(|p| p.to_array())
            .collect();
        let tris: Vec<i64> = self
            .mesh
            .triangles
            .iter()
            .flatten()
            .map(|&i| i as i64)
            .collect();
        let sj: Vec<i64> = self
            .skin
            .joints
            .iter()
            .flatten()
            .map(|&j| j as i64)
            .collect();
        let sw: Vec<f32> = self.skin.weights.iter().flatten().copied().collect();
        let labels: Vec<i64> = self.vertex_label.iter().map(|&l| l as i64).collect();
        let sources: Vec<i64> = self
            .body_vertex
            .iter()
            .map(|b| b.map_or(-1, i64::from))
            .collect();
        let bytes = |s: &str| s.bytes().map(i64::from).collect::<Vec<i64>>();
        let (model, names) = (
            bytes(&self.model),
            bytes(&rig.pose_param_names().join("\n")),
        );
        f3g_io::write_npz(
            path,
            &[
                ("vertices", &[v, 3], F32(&verts)),
                ("triangles", &[self.mesh.triangles.len(), 3], I64(&tris)),
                ("skin_joints", &[v, MAX_INFLUENCES], I64(&sj)),
                ("skin_weights", &[v, MAX_INFLUENCES], F32(&sw)),
                ("vertex_label", &[v], I64(&labels)),
                ("body_vertex", &[v], I64(&sources)),
                (
                    "canonical_pose",
                    &[self.canonical.pose.len()],
                    F32(&self.canonical.pose),
                ),
                (
                    "canonical_identity",
                    &[self.canonical.identity.len()],
                    F32(&self.canonical.identity),
                ),
                (
                    "canonical_expression",
                    &[self.canonical.expression.len()],
                    F32(&self.canonical.expression),
                ),
                ("model", &[model.len()], I64(&model)),
                ("pose_names", &[names.len()], I64(&names)),
            ],
        )?;
        Ok(())
    }

    /// Reads a template and loads the body model it names, checking that they agree.
    pub fn load(path: &Path) -> Result<(Self, Rig), TemplateError> {
        let mut npz = f3g_io::Npz::open(path)?;
        let model = npz_text(&mut npz, path, "model")?;
        let spec: f3g_rig::ModelSpec = model
            .parse()
            .map_err(|e: String| TemplateError::file(path, format!("`model`: {e}")))?;
        let rig = spec.load()?;
        Ok((Self::read(path, &rig)?, rig))
    }

    /// Reads a template made for `rig` (a body model already loaded, e.g. from a run folder),
    /// checking that they agree.
    pub fn read(path: &Path, rig: &Rig) -> Result<Self, TemplateError> {
        let mut npz = f3g_io::Npz::open(path)?;
        let model = npz_text(&mut npz, path, "model")?;
        let names = npz_text(&mut npz, path, "pose_names")?;
        if names.lines().map(String::from).collect::<Vec<_>>() != rig.pose_param_names() {
            return Err(TemplateError::file(
                path,
                format!(
                    "`pose_names` do not match the parameters of {} (the template was made for another version of the model)",
                    rig.name
                ),
            ));
        }
        let shape_check = |name: &str, shape: &[usize], expected: &[usize]| {
            if shape != expected {
                return Err(TemplateError::file(
                    path,
                    format!("`{name}` has shape {shape:?}, expected {expected:?}"),
                ));
            }
            Ok(())
        };
        let (vs, verts) = npz.f32("vertices")?;
        if vs.len() != 2 || vs[1] != 3 {
            return Err(TemplateError::file(
                path,
                format!("`vertices` has shape {vs:?}, expected (V, 3)"),
            ));
        }
        let v = vs[0];
        if verts.iter().any(|x| !x.is_finite()) {
            return Err(TemplateError::file(
                path,
                "`vertices` holds non-finite values",
            ));
        }
        let (ts, tris) = npz.i64("triangles")?;
        if ts.len() != 2 || ts[1] != 3 || tris.iter().any(|&i| i < 0 || i as usize >= v) {
            return Err(TemplateError::file(
                path,
                "`triangles` must be (F, 3) indices into the vertices",
            ));
        }
        let (js, sj) = npz.i64("skin_joints")?;
        shape_check("skin_joints", &js, &[v, MAX_INFLUENCES])?;
        let (ws, sw) = npz.f32("skin_weights")?;
        shape_check("skin_weights", &ws, &[v, MAX_INFLUENCES])?;
        let lists: Vec<Vec<(usize, f32)>> = sj
            .chunks(MAX_INFLUENCES)
            .zip(sw.chunks(MAX_INFLUENCES))
            .map(|(j, w)| {
                j.iter()
                    .zip(w)
                    // A negative joint becomes one past every joint: an error unless its
                    // weight is zero (then it is padding).
                    .map(|(&j, &w)| (usize::try_from(j).unwrap_or(usize::MAX), w))
                    .collect()
            })
            .collect();
        let skin = SkinWeights::from_lists(&lists, rig.skeleton.len())
            .map_err(|e| TemplateError::file(path, format!("`skin_weights`: {e}")))?;
        let (ls, labels) = npz.i64("vertex_label")?;
        shape_check("vertex_label", &ls, &[v])?;
        if let Some(l) = labels
            .iter()
            .find(|&&l| l != i64::from(LABEL_BODY) && l != i64::from(LABEL_GARMENT))
        {
            return Err(TemplateError::file(
                path,
                format!(
                    "`vertex_label` holds {l}; expected {LABEL_BODY} (body) or {LABEL_GARMENT} (garment)"
                ),
            ));
        }
        // Templates written before blend-shape support have no `body_vertex`: nothing moves.
        let body_vertex = if npz.contains("body_vertex") {
            let (bs, b) = npz.i64("body_vertex")?;
            shape_check("body_vertex", &bs, &[v])?;
            let count = rig.mesh.vertices.len() as i64;
            if b.iter().any(|&i| i < -1 || i >= count) {
                return Err(TemplateError::file(
                    path,
                    format!(
                        "`body_vertex` must be -1 or a vertex of {} (< {count})",
                        rig.name
                    ),
                ));
            }
            b.into_iter().map(|i| u32::try_from(i).ok()).collect()
        } else {
            vec![None; v]
        };
        let mut block = |name: &str, len: usize| -> Result<Vec<f32>, TemplateError> {
            let (s, values) = npz.f32(name)?;
            shape_check(name, &s, &[len])?;
            if values.iter().any(|x| !x.is_finite()) {
                return Err(TemplateError::file(
                    path,
                    format!("`{name}` holds non-finite values"),
                ));
            }
            Ok(values)
        };
        let canonical = RigParams {
            pose: block("canonical_pose", rig.num_pose_params())?,
            identity: block("canonical_identity", rig.identity.len())?,
            expression: block("canonical_expression", rig.expression.len())?,
        };
        let mesh = Mesh {
            vertices: verts
                .chunks_exact(3)
                .map(|c| Vec3::new(c[0], c[1], c[2]))
                .collect(),
            triangles: tris
                .chunks_exact(3)
                .map(|t| [t[0] as u32, t[1] as u32, t[2] as u32])
                .collect(),
        };
        Ok(Self {
            model,
            canonical,
            mesh,
            skin,
            vertex_label: labels.into_iter().map(|l| l as u8).collect(),
            body_vertex,
        })
    }
}

/// A UTF-8 byte array of a template file.
fn npz_text<R: std::io::Read + std::io::Seek>(
    npz: &mut f3g_io::Npz<R>,
    path: &Path,
    name: &str,
) -> Result<String, TemplateError> {
    let (_, b) = npz.i64(name)?;
    String::from_utf8(b.into_iter().map(|x| x as u8).collect())
        .map_err(|e| TemplateError::file(path, format!("`{name}`: {e}")))
}
