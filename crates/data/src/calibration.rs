//! Multi-view calibrations in the AvatarReX / THuman4.0 JSON format:
//! `{name: {"K": [9 or 3×3], "R": [9 or 3×3], "T": [3], "imgSize": [W, H]}, ...}` with
//! `x_cam = R x_world + T` (OpenCV), no distortion; a camera's index is its key's position.

use std::path::Path;

use serde_json::Value;

use crate::DataError;
use f3g_camera::Camera;

/// A named camera of a capture.
#[derive(Clone, Debug, PartialEq)]
pub struct CaptureCamera {
    pub name: String,
    pub camera: Camera,
}

fn matrix3(file: &Path, field: &str, v: Option<&Value>) -> Result<[[f64; 3]; 3], DataError> {
    let v = v.ok_or_else(|| DataError::field(file, field, "missing"))?;
    let flat: Vec<f64> = match v {
        Value::Array(rows) if rows.len() == 3 && rows.iter().all(|r| r.is_array()) => rows
            .iter()
            .flat_map(|r| r.as_array().cloned().unwrap_or_default())
            .map(|x| x.as_f64().unwrap_or(f64::NAN))
            .collect(),
        Value::Array(items) => items
            .iter()
            .map(|x| x.as_f64().unwrap_or(f64::NAN))
            .collect(),
        _ => {
            return Err(DataError::field(
                file,
                field,
                "expected 9 numbers or a 3×3 array",
            ));
        }
    };
    if flat.len() != 9 || flat.iter().any(|x| !x.is_finite()) {
        return Err(DataError::field(
            file,
            field,
            format!("expected 9 finite numbers, got {}", flat.len()),
        ));
    }
    Ok([
        [flat[0], flat[1], flat[2]],
        [flat[3], flat[4], flat[5]],
        [flat[6], flat[7], flat[8]],
    ])
}

/// Reads a calibration file.
pub fn read_calibration(path: &Path) -> Result<Vec<CaptureCamera>, DataError> {
    let text = std::fs::read_to_string(path).map_err(|e| DataError::file(path, e))?;
    let json: Value = serde_json::from_str(&text)
        .map_err(|e| DataError::file(path, format!("not valid JSON: {e}")))?;
    let cameras = json
        .as_object()
        .ok_or_else(|| DataError::file(path, "expected an object of cameras"))?;
    let mut out = Vec::new();
    for (name, entry) in cameras {
        // Per-frame blocks (numeric keys) of crop calibrations are not cameras.
        if name.chars().all(|c| c.is_ascii_digit())
            && entry
                .as_object()
                .is_some_and(|o| o.values().all(Value::is_object))
        {
            continue;
        }
        let field = |f: &str| format!("{name}.{f}");
        let k = matrix3(path, &field("K"), entry.get("K"))?;
        let r = matrix3(path, &field("R"), entry.get("R"))?;
        let t: Vec<f64> = entry
            .get("T")
            .and_then(Value::as_array)
            .ok_or_else(|| DataError::field(path, &field("T"), "missing"))?
            .iter()
            .map(|x| x.as_f64().unwrap_or(f64::NAN))
            .collect();
        let t: [f64; 3] = t.try_into().map_err(|t: Vec<f64>| {
            DataError::field(
                path,
                &field("T"),
                format!("expected 3 numbers, got {}", t.len()),
            )
        })?;
        let size: Vec<u64> = entry
            .get("imgSize")
            .and_then(Value::as_array)
            .ok_or_else(|| DataError::field(path, &field("imgSize"), "missing"))?
            .iter()
            .map(|x| x.as_u64().unwrap_or(0))
            .collect();
        let [width, height] = size[..] else {
            return Err(DataError::field(
                path,
                &field("imgSize"),
                "expected [width, height]",
            ));
        };
        let (Ok(width), Ok(height)) = (u32::try_from(width), u32::try_from(height)) else {
            return Err(DataError::field(
                path,
                &field("imgSize"),
                format!("{width}×{height} is too large (at most 16384 pixels a side)"),
            ));
        };
        let camera = Camera {
            k,
            r,
            t,
            width,
            height,
            near: f3g_camera::DEFAULT_NEAR,
            far: f3g_camera::DEFAULT_FAR,
        };
        camera
            .validate()
            .map_err(|e| DataError::field(path, name, e))?;
        out.push(CaptureCamera {
            name: name.clone(),
            camera,
        });
    }
    if out.is_empty() {
        return Err(DataError::file(path, "no cameras"));
    }
    Ok(out)
}

/// Writes a calibration file (row-major 9-value `K` and `R`), atomically.
pub fn write_calibration(path: &Path, cameras: &[CaptureCamera]) -> Result<(), DataError> {
    let mut map = serde_json::Map::new();
    for c in cameras {
        let flat = |m: &[[f64; 3]; 3]| m.iter().flatten().copied().collect::<Vec<f64>>();
        map.insert(
            c.name.clone(),
            serde_json::json!({"K": flat(&c.camera.k), "R": flat(&c.camera.r), "T": c.camera.t, "imgSize": [c.camera.width, c.camera.height]}),
        );
    }
    let text =
        serde_json::to_string_pretty(&Value::Object(map)).map_err(|e| DataError::file(path, e))?;
    f3g_io::write_atomic(path, text.as_bytes())?;
    Ok(())
}
