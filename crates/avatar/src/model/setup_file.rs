//! A run's setup on disk, so that a trained avatar needs nothing but its run folder: the body
//! model as a rig file (`body_model.npz`, [`f3g_rig::file`]), the canonical template
//! (`template.npz`) and `setup.npz`, the Gaussians' tables made from them:
//!
//! - body: `map_resolution`, `map_origin (2)`, `map_pixel_size`, `map_pixels (N)`,
//!   `map_positions (N,3)`, `map_normals (N,3)`, `map_skin_joints (N,8)`, `map_skin_weights
//!   (N,8)`, `map_labels (N)`, `map_corners (N,3)`, `map_bary (N,3)`, `body_log_scales (N)`;
//! - face (with the face branch): `head_crop (3)`, `head_size`, `head_pixels (M)`,
//!   `head_positions (M,3)`, `head_normals (M,3)`, `head_skin_joints (M,8)`,
//!   `head_skin_weights (M,8)`, `head_sources (M,4)` (body Gaussian indices, −1 for none) and
//!   `head_source_weights (M,4)`;
//! - `head_vertices (K)` and `finger_params (F)` of the body model.
//!
//! Reading checks every size and index against the rig, the template and the model
//! configuration, so a damaged or foreign file is an error naming it.

use std::path::Path;

use glam::{Vec2, Vec3};

use super::config::ModelConfig;
use super::setup::Setup;
use crate::AvatarError;
use f3g_io::NpyValues::{F32, I64};
use f3g_rig::{MAX_INFLUENCES, SkinWeights};
use f3g_template::{HeadMaps, PositionMaps, Template};

/// The body model of a run.
const BODY_MODEL: &str = "body_model.npz";
/// The canonical template of a run.
const TEMPLATE: &str = "template.npz";
/// The Gaussians' tables of a run.
const TABLES: &str = "setup.npz";
/// The files of a run's stored setup.
pub const STORED_SETUP: [&str; 3] = [BODY_MODEL, TEMPLATE, TABLES];

fn flat(points: &[Vec3]) -> Vec<f32> {
    points.iter().flat_map(|p| p.to_array()).collect()
}

fn ints(values: impl IntoIterator<Item = usize>) -> Vec<i64> {
    values.into_iter().map(|v| v as i64).collect()
}

fn vec3s(values: &[f32]) -> Vec<Vec3> {
    values.chunks_exact(3).map(Vec3::from_slice).collect()
}

fn skin_arrays(skin: &SkinWeights) -> (Vec<i64>, Vec<f32>) {
    (
        skin.joints
            .iter()
            .flatten()
            .map(|&j| i64::from(j))
            .collect(),
        skin.weights.iter().flatten().copied().collect(),
    )
}

impl Setup {
    /// Writes the setup into the run folder `dir` (atomically, file by file).
    pub fn write(&self, dir: &Path) -> Result<(), AvatarError> {
        f3g_rig::file::write(&self.rig, &dir.join(BODY_MODEL))?;
        self.template.save(&dir.join(TEMPLATE), &self.rig)?;
        let m = &self.maps;
        let n = m.len();
        let (skin_joints, skin_weights) = skin_arrays(&m.skin);
        let pixels = ints(m.pixels.iter().copied());
        let positions = flat(&m.positions);
        let normals = flat(&m.normals);
        let labels: Vec<i64> = m.labels.iter().map(|&l| i64::from(l)).collect();
        let corners: Vec<i64> = m.corners.iter().flatten().map(|&c| i64::from(c)).collect();
        let bary: Vec<f32> = m.bary.iter().flatten().copied().collect();
        let resolution = [m.resolution as i64];
        let origin = m.origin.to_array();
        let pixel_size = [m.pixel_size];
        let head_vertices = ints(self.head_vertices.iter().copied());
        let finger_params = ints(self.finger_params().iter().copied());
        let s = MAX_INFLUENCES;
        let mut arrays: Vec<(&str, Vec<usize>, f3g_io::NpyValues)> = vec![
            ("map_resolution", vec![1], I64(&resolution)),
            ("map_origin", vec![2], F32(&origin)),
            ("map_pixel_size", vec![1], F32(&pixel_size)),
            ("map_pixels", vec![n], I64(&pixels)),
            ("map_positions", vec![n, 3], F32(&positions)),
            ("map_normals", vec![n, 3], F32(&normals)),
            ("map_skin_joints", vec![n, s], I64(&skin_joints)),
            ("map_skin_weights", vec![n, s], F32(&skin_weights)),
            ("map_labels", vec![n], I64(&labels)),
            ("map_corners", vec![n, 3], I64(&corners)),
            ("map_bary", vec![n, 3], F32(&bary)),
            ("body_log_scales", vec![n], F32(&self.body_log_scales)),
            (
                "head_vertices",
                vec![head_vertices.len()],
                I64(&head_vertices),
            ),
            (
                "finger_params",
                vec![finger_params.len()],
                I64(&finger_params),
            ),
        ];
        let head_arrays;
        if let Some(h) = &self.head {
            let k = h.len();
            let (joints, weights) = skin_arrays(&h.skin);
            let mut sources = vec![-1i64; 4 * k];
            let mut source_weights = vec![0f32; 4 * k];
            for (g, list) in h.sources.iter().enumerate() {
                for (t, &(b, w)) in list.iter().enumerate().take(4) {
                    sources[4 * g + t] = b as i64;
                    source_weights[4 * g + t] = w;
                }
            }
            head_arrays = (
                ints(h.crop),
                [h.size as i64],
                ints(h.pixels.iter().copied()),
                flat(&h.positions),
                flat(&h.normals),
                joints,
                weights,
                sources,
                source_weights,
            );
            let a = &head_arrays;
            arrays.extend([
                ("head_crop", vec![3], I64(&a.0)),
                ("head_size", vec![1], I64(&a.1)),
                ("head_pixels", vec![k], I64(&a.2)),
                ("head_positions", vec![k, 3], F32(&a.3)),
                ("head_normals", vec![k, 3], F32(&a.4)),
                ("head_skin_joints", vec![k, s], I64(&a.5)),
                ("head_skin_weights", vec![k, s], F32(&a.6)),
                ("head_sources", vec![k, 4], I64(&a.7)),
                ("head_source_weights", vec![k, 4], F32(&a.8)),
            ]);
        }
        let arrays: Vec<(&str, &[usize], f3g_io::NpyValues)> = arrays
            .iter()
            .map(|(n, s, v)| (*n, s.as_slice(), *v))
            .collect();
        Ok(f3g_io::write_npz(&dir.join(TABLES), &arrays)?)
    }

    /// Whether the run folder `dir` holds a stored setup ([`STORED_SETUP`]).
    pub fn stored_in(dir: &Path) -> bool {
        STORED_SETUP.iter().all(|f| dir.join(f).exists())
    }

    /// Reads the setup stored in the run folder `dir` for a model of `config`.
    pub fn read(dir: &Path, config: &ModelConfig) -> Result<Self, AvatarError> {
        let rig = f3g_rig::file::read(&dir.join(BODY_MODEL))?;
        let template = Template::read(&dir.join(TEMPLATE), &rig)?;
        let path = dir.join(TABLES);
        let bad = |m: String| AvatarError::file(&path, m);
        let mut npz = f3g_io::Npz::open(&path)?;
        let j = rig.skeleton.len();
        let r = npz.indices("map_resolution", &[1], usize::MAX)?[0];
        if r != config.map_resolution {
            return Err(bad(format!(
                "maps of resolution {r}, but the configuration's map_resolution is {}",
                config.map_resolution
            )));
        }
        let n = match npz.shape("map_pixels")?[..] {
            [n] => n,
            ref other => return Err(bad(format!("`map_pixels` has shape {other:?}"))),
        };
        // The skin weights stored as `{part}skin_joints` and `{part}skin_weights`.
        let skin =
            |npz: &mut f3g_io::Npz<_>, part: &str, n: usize| -> Result<SkinWeights, AvatarError> {
                let joints = npz.indices(&format!("{part}skin_joints"), &[n, MAX_INFLUENCES], j)?;
                let weights =
                    npz.f32_exact(&format!("{part}skin_weights"), &[n, MAX_INFLUENCES])?;
                Ok(SkinWeights {
                    joints: joints
                        .chunks_exact(MAX_INFLUENCES)
                        .map(|c| std::array::from_fn(|k| c[k] as u16))
                        .collect(),
                    weights: weights
                        .chunks_exact(MAX_INFLUENCES)
                        .map(|c| std::array::from_fn(|k| c[k]))
                        .collect(),
                })
            };
        let v = template.mesh.vertices.len();
        let maps = PositionMaps {
            resolution: r,
            origin: Vec2::from_slice(&npz.f32_exact("map_origin", &[2])?),
            pixel_size: npz.f32_exact("map_pixel_size", &[1])?[0],
            pixels: npz.indices("map_pixels", &[n], 2 * r * r)?,
            positions: vec3s(&npz.f32_exact("map_positions", &[n, 3])?),
            normals: vec3s(&npz.f32_exact("map_normals", &[n, 3])?),
            skin: skin(&mut npz, "map_", n)?,
            labels: npz
                .indices("map_labels", &[n], 256)?
                .into_iter()
                .map(|l| l as u8)
                .collect(),
            corners: npz
                .indices("map_corners", &[n, 3], v)?
                .chunks_exact(3)
                .map(|c| [c[0] as u32, c[1] as u32, c[2] as u32])
                .collect(),
            bary: npz
                .f32_exact("map_bary", &[n, 3])?
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect(),
        };
        let body_log_scales = npz.f32_exact("body_log_scales", &[n])?;
        let count = |npz: &mut f3g_io::Npz<_>, name: &str| -> Result<usize, AvatarError> {
            match npz.shape(name)?[..] {
                [k] => Ok(k),
                ref other => Err(AvatarError::file(
                    &path,
                    format!("`{name}` has shape {other:?}, expected (K,)"),
                )),
            }
        };
        let k = count(&mut npz, "head_vertices")?;
        let head_vertices = npz.indices("head_vertices", &[k], rig.mesh.vertices.len())?;
        let f = count(&mut npz, "finger_params")?;
        let finger_params = npz.indices("finger_params", &[f], rig.num_pose_params())?;
        let head = match (config.face_branch, npz.contains("head_pixels")) {
            (false, _) => None,
            (true, false) => {
                return Err(bad(
                    "has no face Gaussians, but the configuration has the face branch".into(),
                ));
            }
            (true, true) => {
                let m = count(&mut npz, "head_pixels")?;
                let crop = npz.indices("head_crop", &[3], r + 1)?;
                let size = npz.indices("head_size", &[1], 4 * r + 1)?[0];
                let sources = npz.i64("head_sources")?.1;
                let source_weights = npz.f32_exact("head_source_weights", &[m, 4])?;
                if sources.len() != 4 * m || sources.iter().any(|&b| b < -1 || b >= n as i64) {
                    return Err(bad(format!(
                        "`head_sources` must be ({m}, 4) body Gaussians below {n}, or -1"
                    )));
                }
                Some(HeadMaps {
                    crop: [crop[0], crop[1], crop[2]],
                    size,
                    pixels: npz.indices("head_pixels", &[m], 2 * size * size)?,
                    positions: vec3s(&npz.f32_exact("head_positions", &[m, 3])?),
                    normals: vec3s(&npz.f32_exact("head_normals", &[m, 3])?),
                    skin: skin(&mut npz, "head_", m)?,
                    sources: sources
                        .chunks_exact(4)
                        .zip(source_weights.chunks_exact(4))
                        .map(|(b, w)| {
                            b.iter()
                                .zip(w)
                                .filter(|(b, _)| **b >= 0)
                                .map(|(b, w)| (*b as usize, *w))
                                .collect()
                        })
                        .collect(),
                })
            }
        };
        if maps.len() < 4 {
            return Err(bad(format!("{} body Gaussians", maps.len())));
        }
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
}
