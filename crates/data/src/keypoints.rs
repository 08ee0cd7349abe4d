//! 2D body keypoints in the formats other tools write, for `f3g fit --keypoints DIR`.
//!
//! A keypoint folder holds, per camera (by its calibration name), either
//! - `<camera>/<frame:08>_keypoints.json`: OpenPose's per-image output (`--write_json`), the
//!   `pose_keypoints_2d` of BODY_25 or of the 18-point COCO model; of several people, the one
//!   with the highest summed confidence; or
//! - `<camera>.json`: COCO keypoint annotations (`images` with `file_name`s whose stem is the
//!   frame number, `annotations` with 17 `keypoints` as `x, y, visibility` and an optional
//!   `score`).
//!
//! A frame or camera without a file has no keypoints. Pixels are the full image's; detectors
//! put the top-left pixel's centre at (0, 0), f3g at (0.5, 0.5) (ARCHITECTURE's conventions),
//! so half a pixel is added on reading and taken off on writing. Points that name no role of
//! f3g's body models (nose, ears, mid-hip, feet) are read and dropped.

use std::collections::HashMap;
use std::path::Path;

use glam::Vec2;
use serde_json::{Value, json};

use crate::DataError;
use crate::fit::Keypoint;
use f3g_rig::Role;

/// A detector's pixel coordinates to f3g's (module docs).
const HALF_PIXEL: Vec2 = Vec2::splat(0.5);

/// OpenPose BODY_25's points that are body roles: `(index, role)`.
const BODY_25: [(usize, Role); 15] = [
    (1, Role::Neck),
    (2, Role::RightShoulder),
    (3, Role::RightElbow),
    (4, Role::RightWrist),
    (5, Role::LeftShoulder),
    (6, Role::LeftElbow),
    (7, Role::LeftWrist),
    (9, Role::RightHip),
    (10, Role::RightKnee),
    (11, Role::RightAnkle),
    (12, Role::LeftHip),
    (13, Role::LeftKnee),
    (14, Role::LeftAnkle),
    (15, Role::RightEye),
    (16, Role::LeftEye),
];

/// OpenPose's 18-point COCO model: `(index, role)`.
const OPENPOSE_COCO_18: [(usize, Role); 15] = [
    (1, Role::Neck),
    (2, Role::RightShoulder),
    (3, Role::RightElbow),
    (4, Role::RightWrist),
    (5, Role::LeftShoulder),
    (6, Role::LeftElbow),
    (7, Role::LeftWrist),
    (8, Role::RightHip),
    (9, Role::RightKnee),
    (10, Role::RightAnkle),
    (11, Role::LeftHip),
    (12, Role::LeftKnee),
    (13, Role::LeftAnkle),
    (14, Role::RightEye),
    (15, Role::LeftEye),
];

/// COCO's 17 keypoints: `(index, role)`.
const COCO_17: [(usize, Role); 14] = [
    (1, Role::LeftEye),
    (2, Role::RightEye),
    (5, Role::LeftShoulder),
    (6, Role::RightShoulder),
    (7, Role::LeftElbow),
    (8, Role::RightElbow),
    (9, Role::LeftWrist),
    (10, Role::RightWrist),
    (11, Role::LeftHip),
    (12, Role::RightHip),
    (13, Role::LeftKnee),
    (14, Role::RightKnee),
    (15, Role::LeftAnkle),
    (16, Role::RightAnkle),
];

/// Keypoints from a flat `[x, y, confidence]·n` array through an index→role map. A point
/// that is not finite, or whose confidence is outside [0, 1], is an error naming it.
fn from_triples(
    path: &Path,
    field: &str,
    values: &[f64],
    map: &[(usize, Role)],
    visibility: bool,
) -> Result<Vec<Keypoint>, DataError> {
    map.iter()
        .map(|&(i, role)| {
            let [x, y, c] = [values[3 * i], values[3 * i + 1], values[3 * i + 2]];
            // Finite as f32 too: 1e300 is a finite f64.
            if ![x, y, c].iter().all(|v| (*v as f32).is_finite()) {
                return Err(DataError::field(
                    path,
                    field,
                    format!("point {i} is not finite: [{x}, {y}, {c}]"),
                ));
            }
            // COCO's visibility: 0 not labelled, 1 labelled but hidden, 2 visible.
            let confidence = if visibility {
                if c > 0.0 { 1.0 } else { 0.0 }
            } else {
                c
            };
            if !(0.0..=1.0).contains(&confidence) {
                return Err(DataError::field(
                    path,
                    field,
                    format!("point {i}: confidence {c} is outside [0, 1]"),
                ));
            }
            Ok(Keypoint {
                role,
                pixel: Vec2::new(x as f32, y as f32) + HALF_PIXEL,
                confidence: confidence as f32,
            })
        })
        .collect()
}

fn numbers(path: &Path, field: &str, v: &Value) -> Result<Vec<f64>, DataError> {
    v.as_array()
        .ok_or_else(|| DataError::field(path, field, "expected an array of numbers"))?
        .iter()
        .map(|x| {
            x.as_f64()
                .ok_or_else(|| DataError::field(path, field, format!("`{x}` is not a number")))
        })
        .collect()
}

fn read_json(path: &Path) -> Result<Value, DataError> {
    let text = std::fs::read_to_string(path).map_err(|e| DataError::file(path, e))?;
    serde_json::from_str(&text).map_err(|e| DataError::file(path, format!("not JSON: {e}")))
}

/// The keypoints of one OpenPose JSON file (the most confident person; none without people).
pub fn read_openpose(path: &Path) -> Result<Vec<Keypoint>, DataError> {
    let json = read_json(path)?;
    let people = json
        .get("people")
        .and_then(Value::as_array)
        .ok_or_else(|| DataError::field(path, "people", "expected an array (OpenPose JSON)"))?;
    let mut best: Option<(f64, Vec<f64>)> = None;
    for (k, person) in people.iter().enumerate() {
        let field = format!("people[{k}].pose_keypoints_2d");
        let values = numbers(
            path,
            &field,
            person.get("pose_keypoints_2d").unwrap_or(&Value::Null),
        )?;
        if values.len() != 75 && values.len() != 54 {
            return Err(DataError::field(
                path,
                &field,
                format!(
                    "{} numbers: expected 75 (BODY_25) or 54 (COCO-18), as x, y, confidence",
                    values.len()
                ),
            ));
        }
        let total: f64 = values.iter().skip(2).step_by(3).sum();
        if best.as_ref().is_none_or(|b| total > b.0) {
            best = Some((total, values));
        }
    }
    let Some((_, values)) = best else {
        return Ok(Vec::new());
    };
    let map = if values.len() == 75 {
        BODY_25.to_vec()
    } else {
        OPENPOSE_COCO_18.to_vec()
    };
    from_triples(path, "pose_keypoints_2d", &values, &map, false)
}

/// The keypoints of a COCO keypoint file, by frame (the number a `file_name`'s stem reads as).
pub fn read_coco(path: &Path) -> Result<HashMap<usize, Vec<Keypoint>>, DataError> {
    let json = read_json(path)?;
    let array = |field: &str| {
        json.get(field)
            .and_then(Value::as_array)
            .ok_or_else(|| DataError::field(path, field, "expected an array (COCO keypoints)"))
    };
    let mut frame_of = HashMap::new();
    for (k, image) in array("images")?.iter().enumerate() {
        let field = format!("images[{k}]");
        let id = image
            .get("id")
            .and_then(Value::as_i64)
            .ok_or_else(|| DataError::field(path, &format!("{field}.id"), "expected an integer"))?;
        let name = image
            .get("file_name")
            .and_then(Value::as_str)
            .ok_or_else(|| {
                DataError::field(path, &format!("{field}.file_name"), "expected a string")
            })?;
        let stem = Path::new(name)
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or_default();
        let frame: usize = stem.parse().map_err(|_| {
            DataError::field(
                path,
                &format!("{field}.file_name"),
                format!("`{name}`: expected a frame number as its name (e.g. 00000012.jpg)"),
            )
        })?;
        frame_of.insert(id, frame);
    }
    let mut out: HashMap<usize, (f64, Vec<Keypoint>)> = HashMap::new();
    for (k, a) in array("annotations")?.iter().enumerate() {
        let field = format!("annotations[{k}]");
        let id = a.get("image_id").and_then(Value::as_i64).ok_or_else(|| {
            DataError::field(path, &format!("{field}.image_id"), "expected an integer")
        })?;
        let frame = *frame_of.get(&id).ok_or_else(|| {
            DataError::field(
                path,
                &format!("{field}.image_id"),
                format!("{id} names no image of `images`"),
            )
        })?;
        let kf = format!("{field}.keypoints");
        let values = numbers(path, &kf, a.get("keypoints").unwrap_or(&Value::Null))?;
        if values.len() != 51 {
            return Err(DataError::field(
                path,
                &kf,
                format!(
                    "{} numbers: expected 51 (17 × x, y, visibility)",
                    values.len()
                ),
            ));
        }
        let score = a.get("score").and_then(Value::as_f64).unwrap_or(1.0);
        let mut points = from_triples(path, &kf, &values, &COCO_17, true)?;
        for p in &mut points {
            p.confidence *= score.clamp(0.0, 1.0) as f32;
        }
        if out.get(&frame).is_none_or(|(s, _)| score > *s) {
            out.insert(frame, (score, points));
        }
    }
    Ok(out.into_iter().map(|(f, (_, p))| (f, p)).collect())
}

/// The keypoints of every `(frame, camera)` in a keypoint folder ([module docs](self)):
/// `[frame][camera]`, empty where there are none.
pub fn read_folder(
    dir: &Path,
    cameras: &[String],
    frames: usize,
) -> Result<Vec<Vec<Vec<Keypoint>>>, DataError> {
    if !dir.is_dir() {
        return Err(DataError::file(dir, "not a folder of keypoints"));
    }
    let mut out = vec![vec![Vec::new(); cameras.len()]; frames];
    let mut found = 0;
    for (c, name) in cameras.iter().enumerate() {
        let coco = dir.join(format!("{name}.json"));
        if coco.is_file() {
            for (f, points) in read_coco(&coco)? {
                if f < frames {
                    out[f][c] = points;
                    found += 1;
                }
            }
            continue;
        }
        for (f, frame) in out.iter_mut().enumerate() {
            let path = dir.join(name).join(format!("{f:08}_keypoints.json"));
            if path.is_file() {
                frame[c] = read_openpose(&path)?;
                found += 1;
            }
        }
    }
    if found == 0 {
        return Err(DataError::file(
            dir,
            format!(
                "holds no keypoints of these cameras: expected <camera>/<frame:08>_keypoints.json (OpenPose) or <camera>.json (COCO), e.g. {}/00000000_keypoints.json",
                cameras.first().map(String::as_str).unwrap_or("cam00")
            ),
        ));
    }
    Ok(out)
}

/// One person's BODY_25 OpenPose JSON with the given keypoints (points of no role zero).
pub fn openpose_json(points: &[Keypoint]) -> String {
    let mut flat = vec![0.0f32; 75];
    for p in points {
        if let Some(&(i, _)) = BODY_25.iter().find(|(_, r)| *r == p.role) {
            let pixel = p.pixel - HALF_PIXEL;
            flat[3 * i..3 * i + 3].copy_from_slice(&[pixel.x, pixel.y, p.confidence]);
        }
    }
    json!({"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": flat}]}).to_string()
}

/// The body roles OpenPose's BODY_25 has.
pub fn body_25_roles() -> Vec<Role> {
    BODY_25.iter().map(|&(_, r)| r).collect()
}

/// The keypoints a perfect detector with Gaussian pixel noise (standard deviation `noise`
/// pixels per axis, seeded) would find: each BODY_25 role's joint of the posed body projected
/// into each camera, `[camera]`; a joint behind a camera or outside its image is not seen.
/// What `f3g data keypoints` writes for a synthetic capture, whose parameters are the truth.
pub fn project_roles(
    rig: &f3g_rig::Rig,
    posed: &f3g_rig::Posed,
    cameras: &[f3g_camera::Camera],
    noise: f32,
    rng: &mut impl rand::Rng,
) -> Result<Vec<Vec<Keypoint>>, DataError> {
    let roles = body_25_roles();
    let joints = roles
        .iter()
        .map(|&r| rig.role(r))
        .collect::<Result<Vec<_>, _>>()?;
    let mut gaussian = || {
        // Box–Muller.
        let (u, v): (f32, f32) = (rng.random::<f32>().max(1e-12), rng.random());
        (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
    };
    Ok(cameras
        .iter()
        .map(|cam| {
            roles
                .iter()
                .zip(&joints)
                .filter_map(|(&role, &j)| {
                    let x = posed.joints[j].translation.as_dvec3().to_array();
                    let (p, _) = cam.project(x)?;
                    let pixel = Vec2::new(p[0] as f32, p[1] as f32)
                        + noise * Vec2::new(gaussian(), gaussian());
                    let inside = pixel.x >= 0.0
                        && pixel.y >= 0.0
                        && pixel.x < cam.width as f32
                        && pixel.y < cam.height as f32;
                    inside.then_some(Keypoint {
                        role,
                        pixel,
                        confidence: 1.0,
                    })
                })
                .collect()
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(text: &str) -> (tempfile::TempDir, std::path::PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("k.json");
        std::fs::write(&path, text).unwrap();
        (dir, path)
    }

    #[test]
    fn openpose_round_trips_and_keeps_the_most_confident_person() {
        let points = vec![
            Keypoint {
                role: Role::LeftWrist,
                pixel: Vec2::new(10.5, 20.5),
                confidence: 0.9,
            },
            Keypoint {
                role: Role::Neck,
                pixel: Vec2::new(3.0, 4.0),
                confidence: 0.5,
            },
        ];
        let text = openpose_json(&points);
        let (_d, path) = file(&text);
        let back = read_openpose(&path).unwrap();
        for p in &points {
            let q = back.iter().find(|q| q.role == p.role).unwrap();
            assert_eq!((q.pixel, q.confidence), (p.pixel, p.confidence));
        }
        // A second, more confident person wins.
        let mut json: Value = serde_json::from_str(&text).unwrap();
        let mut other = vec![0.0f32; 75];
        other[3 * 7..3 * 7 + 3].copy_from_slice(&[99.0, 98.0, 1.0]);
        other[3 * 4 + 2] = 1.0;
        json["people"]
            .as_array_mut()
            .unwrap()
            .push(serde_json::json!({"pose_keypoints_2d": other}));
        let (_d, path) = file(&json.to_string());
        let back = read_openpose(&path).unwrap();
        let wrist = back.iter().find(|q| q.role == Role::LeftWrist).unwrap();
        assert_eq!(wrist.pixel, Vec2::new(99.5, 98.5));
    }

    #[test]
    fn coco_keypoints_are_read_by_frame() {
        let mut kp = vec![0.0f64; 51];
        kp[3 * 9..3 * 9 + 3].copy_from_slice(&[40.0, 50.0, 2.0]);
        let text = serde_json::json!({
            "images": [{"id": 7, "file_name": "cam00/00000012.jpg"}],
            "annotations": [{"image_id": 7, "keypoints": kp, "score": 0.8}],
        })
        .to_string();
        let (_d, path) = file(&text);
        let frames = read_coco(&path).unwrap();
        let wrist = frames[&12]
            .iter()
            .find(|q| q.role == Role::LeftWrist)
            .unwrap();
        assert_eq!(wrist.pixel, Vec2::new(40.5, 50.5));
        assert!((wrist.confidence - 0.8).abs() < 1e-6);
        let hidden = frames[&12].iter().find(|q| q.role == Role::Neck);
        assert!(hidden.is_none(), "COCO has no neck");
    }

    #[test]
    fn bad_keypoint_files_are_refused_naming_the_field() {
        let bad = |text: &str, needle: &str, coco: bool| {
            let (_d, path) = file(text);
            let e = if coco {
                read_coco(&path).map(|_| ()).unwrap_err()
            } else {
                read_openpose(&path).map(|_| ()).unwrap_err()
            }
            .to_string();
            assert!(
                e.contains("k.json") && e.contains(needle),
                "`{needle}` in: {e}"
            );
        };
        bad("{", "not JSON", false);
        bad("{}", "people", false);
        bad(
            r#"{"people": [{"pose_keypoints_2d": [1, 2, 3]}]}"#,
            "expected 75",
            false,
        );
        let mut confident = vec![serde_json::json!(0.0); 75];
        confident[8] = serde_json::json!(2.0);
        bad(
            &serde_json::json!({"people": [{"pose_keypoints_2d": confident}]}).to_string(),
            "confidence 2",
            false,
        );
        bad(
            r#"{"people": [{"pose_keypoints_2d": "x"}]}"#,
            "array of numbers",
            false,
        );
        bad(r#"{"images": []}"#, "annotations", true);
        bad(
            r#"{"images": [{"id": 1, "file_name": "front.jpg"}], "annotations": []}"#,
            "frame number",
            true,
        );
        bad(
            r#"{"images": [], "annotations": [{"image_id": 3, "keypoints": []}]}"#,
            "names no image",
            true,
        );
        bad(
            r#"{"images": [{"id": 1, "file_name": "1.jpg"}], "annotations": [{"image_id": 1, "keypoints": [1]}]}"#,
            "expected 51",
            true,
        );
    }
}
