//! Parameter files: one pose as JSON, or sequences as `.npz`.
//!
//! - JSON, one frame, values by name (missing ones are 0):
//!   `{"pose": {"jaw_rx": 0.3}, "identity": {"height": 0.1}, "expression": {"mouth-open": 1.0}}`
//! - `smpl_params.npz` (SMPL-X only; see [`crate::smplx::read_params`]).
//! - f3g's own `.npz`: `pose (N,P)`, `identity (N,I)`, `expression (N,E)`, and `pose_names`,
//!   `identity_names`, `expression_names`, `model` as UTF-8 byte arrays (names newline-separated),
//!   so a file can be checked against the model it is applied to.

use std::collections::BTreeMap;
use std::path::Path;

use crate::rig::{Rig, RigParams};
use crate::{RigError, smplx};

fn io(e: f3g_io::IoError) -> RigError {
    RigError::File {
        file: e.path,
        reason: e.reason,
    }
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct NamedParams {
    #[serde(default)]
    pose: BTreeMap<String, f32>,
    #[serde(default)]
    identity: BTreeMap<String, f32>,
    #[serde(default)]
    expression: BTreeMap<String, f32>,
}

/// Reads every frame of a parameter file for `rig`.
pub fn read(path: &Path, rig: &Rig) -> Result<Vec<RigParams>, RigError> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("json") => read_json(path, rig).map(|p| vec![p]),
        Some("npz") => {
            let is_smpl = f3g_io::Npz::open(path)
                .map_err(io)?
                .contains("global_orient");
            if is_smpl {
                smplx::read_params(path)?
                    .frames_for(rig)
                    .map_err(|e| RigError::file(path, e))
            } else {
                read_npz(path, rig)
            }
        }
        _ => Err(RigError::file(
            path,
            "unknown parameter file type: expected .json or .npz",
        )),
    }
}

fn read_json(path: &Path, rig: &Rig) -> Result<RigParams, RigError> {
    let text = std::fs::read_to_string(path).map_err(|e| RigError::file(path, e))?;
    let named: NamedParams = serde_json::from_str(&text).map_err(|e| RigError::file(path, e))?;
    let mut p = rig.zero_params();
    let fill = |block: &str,
                values: &BTreeMap<String, f32>,
                names: &[String],
                out: &mut [f32]|
     -> Result<(), RigError> {
        for (name, &v) in values {
            let i = names.iter().position(|n| n == name).ok_or_else(|| {
                let shown: Vec<&str> = names.iter().take(12).map(String::as_str).collect();
                RigError::field(
                    path,
                    &format!("{block}.{name}"),
                    format!(
                        "not a {block} parameter of {} (they are: {}{})",
                        rig.name,
                        shown.join(", "),
                        if names.len() > 12 { ", ..." } else { "" }
                    ),
                )
            })?;
            if !v.is_finite() {
                return Err(RigError::field(
                    path,
                    &format!("{block}.{name}"),
                    "is not finite",
                ));
            }
            out[i] = v;
        }
        Ok(())
    };
    fill("pose", &named.pose, &rig.pose_param_names(), &mut p.pose)?;
    fill(
        "identity",
        &named.identity,
        &rig.identity.names,
        &mut p.identity,
    )?;
    fill(
        "expression",
        &named.expression,
        &rig.expression.names,
        &mut p.expression,
    )?;
    Ok(p)
}

fn text(
    npz: &mut f3g_io::Npz<std::io::BufReader<std::fs::File>>,
    name: &str,
) -> Result<String, RigError> {
    let (_, bytes) = npz.i64(name).map_err(io)?;
    String::from_utf8(bytes.into_iter().map(|b| b as u8).collect())
        .map_err(|e| RigError::field(npz.path(), name, e))
}

/// The body model an f3g `.npz` sequence was written for (its `model` text, a
/// [`crate::ModelSpec`] such as `builtin`).
pub fn model_of(path: &Path) -> Result<String, RigError> {
    let mut npz = f3g_io::Npz::open(path).map_err(io)?;
    text(&mut npz, "model")
}

fn read_npz(path: &Path, rig: &Rig) -> Result<Vec<RigParams>, RigError> {
    let mut npz = f3g_io::Npz::open(path).map_err(io)?;
    let names = text(&mut npz, "pose_names")?;
    let names: Vec<String> = names.lines().map(String::from).collect();
    if names != rig.pose_param_names() {
        let model = text(&mut npz, "model").unwrap_or_default();
        return Err(RigError::field(
            path,
            "pose_names",
            format!(
                "the file's {} pose parameters (model `{model}`) do not match {}'s {}",
                names.len(),
                rig.name,
                rig.num_pose_params()
            ),
        ));
    }
    let mut block = |name: &str, width: usize| -> Result<(usize, Vec<f32>), RigError> {
        let (shape, values) = npz.f32(name).map_err(io)?;
        if shape.len() != 2 || shape[1] != width {
            return Err(RigError::field(
                path,
                name,
                format!("has shape {shape:?}, expected (frames, {width})"),
            ));
        }
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(RigError::field(
                path,
                name,
                format!("non-finite value in frame {}", i / width.max(1)),
            ));
        }
        Ok((shape[0], values))
    };
    let (frames, pose) = block("pose", rig.num_pose_params())?;
    let (fi, identity) = block("identity", rig.identity.len())?;
    let (fe, expression) = block("expression", rig.expression.len())?;
    if fi != frames || fe != frames {
        return Err(RigError::file(
            path,
            format!("pose has {frames} frames, identity {fi}, expression {fe}"),
        ));
    }
    let row = |v: &[f32], w: usize, i: usize| v[i * w..(i + 1) * w].to_vec();
    Ok((0..frames)
        .map(|i| RigParams {
            pose: row(&pose, rig.num_pose_params(), i),
            identity: row(&identity, rig.identity.len(), i),
            expression: row(&expression, rig.expression.len(), i),
        })
        .collect())
}

/// Writes frames in f3g's `.npz` layout, atomically.
pub fn write(path: &Path, rig: &Rig, frames: &[RigParams]) -> Result<(), RigError> {
    use f3g_io::NpyValues::{F32, I64};
    let n = frames.len();
    let bytes = |s: String| {
        s.into_bytes()
            .into_iter()
            .map(i64::from)
            .collect::<Vec<i64>>()
    };
    let (pose_names, identity_names, expression_names, model) = (
        bytes(rig.pose_param_names().join("\n")),
        bytes(rig.identity.names.join("\n")),
        bytes(rig.expression.names.join("\n")),
        bytes(rig.name.clone()),
    );
    let flat = |f: fn(&RigParams) -> &Vec<f32>| {
        frames
            .iter()
            .flat_map(|p| f(p).iter().copied())
            .collect::<Vec<f32>>()
    };
    let (pose, identity, expression) = (
        flat(|p| &p.pose),
        flat(|p| &p.identity),
        flat(|p| &p.expression),
    );
    f3g_io::write_npz(
        path,
        &[
            ("pose", &[n, rig.num_pose_params()], F32(&pose)),
            ("identity", &[n, rig.identity.len()], F32(&identity)),
            ("expression", &[n, rig.expression.len()], F32(&expression)),
            ("pose_names", &[pose_names.len()], I64(&pose_names)),
            (
                "identity_names",
                &[identity_names.len()],
                I64(&identity_names),
            ),
            (
                "expression_names",
                &[expression_names.len()],
                I64(&expression_names),
            ),
            ("model", &[model.len()], I64(&model)),
        ],
    )
    .map_err(io)
}
