//! Pinhole cameras in the OpenCV convention.
//!
//! - World → camera: `x_cam = R · x_world + t`; the camera looks down +Z, image x to the right,
//!   image y down. Units are metres.
//! - Intrinsics `K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`; pixel `(i, j)` (column, row) has
//!   its centre at `(i + 0.5, j + 0.5)`, so the continuous image spans `[0, W] × [0, H]`.
//! - Points with depth outside `[near, far]` are not rendered.

use serde::{Deserialize, Serialize};

/// A camera that projection cannot use; the message names the field.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("invalid camera: {0}")]
pub struct CameraError(pub String);

/// Default near plane (metres), as in gsplat.
pub const DEFAULT_NEAR: f64 = 0.01;
/// Default far plane (metres).
pub const DEFAULT_FAR: f64 = 1e4;

/// Largest image side a camera may ask for (a 16K frame; captures are at most a few thousand
/// pixels): checked before anything is allocated, so a camera file with an absurd size is an
/// error instead of an allocation failure.
pub const MAX_IMAGE_SIDE: u32 = 16384;
/// Largest image a camera may ask for, in pixels (64 Mpx: the image, alpha, depth and the
/// rasteriser's per-pixel state then stay within a few GiB).
pub const MAX_IMAGE_PIXELS: u64 = 1 << 26;
/// How far the principal point may lie from the image's centre, in image sizes (the larger
/// side): generous for crops of a larger image, which move it outside the crop.
pub const PRINCIPAL_POINT_REACH: f64 = 100.0;

/// A calibrated pinhole camera. This is also the `cam.json` format:
/// `{"K": [[..],[..],[..]], "R": [[..],[..],[..]], "t": [..], "width": W, "height": H}`
/// with optional `"near"` and `"far"`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// Intrinsic matrix (no skew).
    #[serde(rename = "K")]
    pub k: [[f64; 3]; 3],
    /// World-to-camera rotation.
    #[serde(rename = "R")]
    pub r: [[f64; 3]; 3],
    /// World-to-camera translation (metres).
    pub t: [f64; 3],
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Near clipping depth (metres).
    #[serde(default = "default_near")]
    pub near: f64,
    /// Far clipping depth (metres).
    #[serde(default = "default_far")]
    pub far: f64,
}

fn default_near() -> f64 {
    DEFAULT_NEAR
}

fn default_far() -> f64 {
    DEFAULT_FAR
}

impl Camera {
    /// A camera at `eye` looking at `target`, with world `up` pointing up in the image, focal
    /// lengths in pixels and the principal point at the image centre.
    pub fn look_at(
        eye: [f64; 3],
        target: [f64; 3],
        up: [f64; 3],
        focal: f64,
        width: u32,
        height: u32,
    ) -> Self {
        let forward = normalize(sub(target, eye));
        let right = normalize(cross(forward, up));
        let down = cross(forward, right);
        let r = [right, down, forward];
        let t = [-dot(r[0], eye), -dot(r[1], eye), -dot(r[2], eye)];
        Self {
            k: [
                [focal, 0.0, width as f64 / 2.0],
                [0.0, focal, height as f64 / 2.0],
                [0.0, 0.0, 1.0],
            ],
            r,
            t,
            width,
            height,
            near: DEFAULT_NEAR,
            far: DEFAULT_FAR,
        }
    }

    /// Focal length along x (pixels).
    pub fn fx(&self) -> f64 {
        self.k[0][0]
    }
    /// Focal length along y (pixels).
    pub fn fy(&self) -> f64 {
        self.k[1][1]
    }
    /// Principal point x (pixels).
    pub fn cx(&self) -> f64 {
        self.k[0][2]
    }
    /// Principal point y (pixels).
    pub fn cy(&self) -> f64 {
        self.k[1][2]
    }

    /// Camera centre in world coordinates, `-Rᵀ t`.
    pub fn center(&self) -> [f64; 3] {
        let r = &self.r;
        let t = &self.t;
        [
            -(r[0][0] * t[0] + r[1][0] * t[1] + r[2][0] * t[2]),
            -(r[0][1] * t[0] + r[1][1] * t[1] + r[2][1] * t[2]),
            -(r[0][2] * t[0] + r[1][2] * t[1] + r[2][2] * t[2]),
        ]
    }

    /// Projects a world point to pixel coordinates and depth; `None` behind the camera.
    pub fn project(&self, x: [f64; 3]) -> Option<([f64; 2], f64)> {
        let p = self.world_to_camera(x);
        (p[2] > 0.0).then(|| {
            (
                [
                    self.fx() * p[0] / p[2] + self.cx(),
                    self.fy() * p[1] / p[2] + self.cy(),
                ],
                p[2],
            )
        })
    }

    /// `R · x + t`.
    pub fn world_to_camera(&self, x: [f64; 3]) -> [f64; 3] {
        [
            dot(self.r[0], x) + self.t[0],
            dot(self.r[1], x) + self.t[1],
            dot(self.r[2], x) + self.t[2],
        ]
    }

    /// The camera seeing the crop of its image whose top-left corner is `(x0, y0)` (pixels),
    /// resized by `scale` into a `width × height` image: `fx' = s fx`, `cx' = s (cx − x0)`
    /// (and likewise for y); R and t are unchanged.
    pub fn crop_resize(&self, x0: f64, y0: f64, scale: f64, width: u32, height: u32) -> Self {
        let mut cam = self.clone();
        cam.k[0][0] = scale * self.fx();
        cam.k[1][1] = scale * self.fy();
        cam.k[0][2] = scale * (self.cx() - x0);
        cam.k[1][2] = scale * (self.cy() - y0);
        cam.width = width;
        cam.height = height;
        cam
    }

    /// Checks everything projection relies on; the error names the offending field.
    pub fn validate(&self) -> Result<(), CameraError> {
        let bad = |m: String| Err(CameraError(m));
        // Every number with the field it belongs to.
        let values = self
            .k
            .iter()
            .flatten()
            .map(|&v| ("K", v))
            .chain(self.r.iter().flatten().map(|&v| ("R", v)))
            .chain(self.t.iter().map(|&v| ("t", v)))
            .chain([("near", self.near), ("far", self.far)]);
        if let Some((field, v)) = values.clone().find(|(_, v)| !v.is_finite()) {
            return bad(format!("{field} must be finite, found {v}"));
        }
        // The renderers compute in f32: a value beyond its range would become infinite there
        // and render nothing without an error.
        let limit = f64::from(f32::MAX);
        if let Some((field, v)) = values.clone().find(|(_, v)| v.abs() > limit) {
            return bad(format!(
                "{field} = {v:e} is beyond the single-precision range (±{limit:e}) the renderers \
                 compute in"
            ));
        }
        if self.width == 0 || self.height == 0 {
            return bad(format!(
                "image size {}x{} is empty",
                self.width, self.height
            ));
        }
        let (w, h) = (self.width as u64, self.height as u64);
        if w > MAX_IMAGE_SIDE as u64 || h > MAX_IMAGE_SIDE as u64 || w * h > MAX_IMAGE_PIXELS {
            return bad(format!(
                "image size (width {w}, height {h}) is too large: at most {MAX_IMAGE_SIDE} \
                 pixels per side and {MAX_IMAGE_PIXELS} pixels in all"
            ));
        }
        // A principal point farther than this from the image puts the whole image that many
        // image sizes off the optical axis: no lens or crop does that, and the renderers would
        // draw an empty image without an error.
        let reach = PRINCIPAL_POINT_REACH * w.max(h) as f64;
        let (cx, cy) = (self.cx(), self.cy());
        if (cx - w as f64 / 2.0).abs() > reach || (cy - h as f64 / 2.0).abs() > reach {
            return bad(format!(
                "principal point (cx {cx}, cy {cy}) is more than {PRINCIPAL_POINT_REACH} image \
                 sizes ({reach} pixels) from the centre of the {w}x{h} image"
            ));
        }
        if !(self.fx() > 0.0 && self.fy() > 0.0) {
            return bad(format!(
                "focal lengths must be positive, got fx={} fy={}",
                self.fx(),
                self.fy()
            ));
        }
        if self.k[0][1] != 0.0 || self.k[1][0] != 0.0 || self.k[2] != [0.0, 0.0, 1.0] {
            return bad(format!(
                "K must be [[fx,0,cx],[0,fy,cy],[0,0,1]] (no skew), got {:?}",
                self.k
            ));
        }
        for i in 0..3 {
            for j in 0..3 {
                let rrt = dot(self.r[i], self.r[j]);
                let expected = if i == j { 1.0 } else { 0.0 };
                if (rrt - expected).abs() > 1e-4 {
                    return bad(format!("R is not orthonormal (R Rᵀ[{i}][{j}] = {rrt})"));
                }
            }
        }
        if dot(cross(self.r[0], self.r[1]), self.r[2]) < 0.0 {
            return bad("R is a reflection (det R = -1), expected a rotation".into());
        }
        if !(self.near > 0.0 && self.far > self.near) {
            return bad(format!(
                "need 0 < near < far, got near={} far={}",
                self.near, self.far
            ));
        }
        Ok(())
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn front_camera() -> Camera {
        Camera::look_at([0.0, 0.0, 3.0], [0.0; 3], [0.0, 1.0, 0.0], 500.0, 640, 480)
    }

    #[test]
    fn look_at_follows_opencv_axes() {
        let cam = front_camera();
        cam.validate().unwrap();
        // The target projects to the principal point; world +X appears to the right, +Y up.
        let (uv, depth) = cam.project([0.0; 3]).unwrap();
        assert!((uv[0] - 320.0).abs() < 1e-12 && (uv[1] - 240.0).abs() < 1e-12);
        assert!((depth - 3.0).abs() < 1e-12);
        let (right, _) = cam.project([0.1, 0.0, 0.0]).unwrap();
        let (up, _) = cam.project([0.0, 0.1, 0.0]).unwrap();
        assert!(right[0] > 320.0 && up[1] < 240.0);
        let c = cam.center();
        assert!((c[0]).abs() < 1e-12 && (c[2] - 3.0).abs() < 1e-12);
    }

    #[test]
    fn crop_resize_keeps_content_aligned() {
        let cam = front_camera();
        let crop = cam.crop_resize(100.0, 50.0, 2.5, 512, 512);
        let x = [0.05, -0.02, 0.1];
        let (full, _) = cam.project(x).unwrap();
        let (cropped, _) = crop.project(x).unwrap();
        assert!((cropped[0] - 2.5 * (full[0] - 100.0)).abs() < 1e-9);
        assert!((cropped[1] - 2.5 * (full[1] - 50.0)).abs() < 1e-9);
    }

    #[test]
    fn validation_names_the_problem() {
        let mut cam = front_camera();
        cam.k[0][0] = f64::NAN;
        assert!(cam.validate().unwrap_err().to_string().contains("finite"));
        let mut cam = front_camera();
        cam.r[0] = [2.0, 0.0, 0.0];
        assert!(
            cam.validate()
                .unwrap_err()
                .to_string()
                .contains("orthonormal")
        );
        let mut cam = front_camera();
        cam.r[2] = [-cam.r[2][0], -cam.r[2][1], -cam.r[2][2]];
        assert!(
            cam.validate()
                .unwrap_err()
                .to_string()
                .contains("reflection")
        );
        let mut cam = front_camera();
        cam.width = 0;
        assert!(cam.validate().unwrap_err().to_string().contains("empty"));
        let mut cam = front_camera();
        (cam.width, cam.height) = (100_000, 100_000);
        let e = cam.validate().unwrap_err().to_string();
        assert!(e.contains("width 100000") && e.contains("too large"), "{e}");
        (cam.width, cam.height) = (MAX_IMAGE_SIDE, MAX_IMAGE_SIDE);
        assert!(
            cam.validate()
                .unwrap_err()
                .to_string()
                .contains("too large")
        );
        (cam.width, cam.height) = (MAX_IMAGE_SIDE, 4096);
        cam.validate().unwrap();
        let mut cam = front_camera();
        cam.k[0][1] = 1.0;
        assert!(cam.validate().unwrap_err().to_string().contains("skew"));
        let mut cam = front_camera();
        cam.near = 0.0;
        assert!(cam.validate().unwrap_err().to_string().contains("near"));
        // A focal length that overflows f32 (1e300 in a cam.json) is refused, not rendered as
        // an empty image.
        let mut cam = front_camera();
        cam.k[0][0] = 1e300;
        let e = cam.validate().unwrap_err().to_string();
        assert!(
            e.contains("K = 1e300") && e.contains("single-precision"),
            "{e}"
        );
        let mut cam = front_camera();
        cam.far = 1e39;
        let e = cam.validate().unwrap_err().to_string();
        assert!(
            e.contains("far = 1e39") && e.contains("single-precision"),
            "{e}"
        );
        let mut cam = front_camera();
        cam.t[2] = f64::NAN;
        let e = cam.validate().unwrap_err().to_string();
        assert!(e.contains("t must be finite, found NaN"), "{e}");
        // A principal point far off the image (1e30 in a calibration) is refused, not rendered
        // as a blank image; one outside the image, as a crop gives, is fine.
        for (i, v) in [(0, 1e30), (1, -1e30), (0, 1e6)] {
            let mut cam = front_camera();
            cam.k[i][2] = v;
            let e = cam.validate().unwrap_err().to_string();
            assert!(e.contains("principal point"), "{e}");
        }
        let mut cam = front_camera();
        cam.k[0][2] = -3.0 * cam.width as f64;
        cam.validate().unwrap();
    }

    #[test]
    fn json_round_trip_and_defaults() {
        let json = r#"{"K": [[500,0,320],[0,500,240],[0,0,1]], "R": [[1,0,0],[0,1,0],[0,0,1]],
                       "t": [0,0,3], "width": 640, "height": 480}"#;
        let cam: Camera = serde_json::from_str(json).unwrap();
        assert_eq!(cam.near, DEFAULT_NEAR);
        assert_eq!(cam.far, DEFAULT_FAR);
        let back: Camera = serde_json::from_str(&serde_json::to_string(&cam).unwrap()).unwrap();
        assert_eq!(back, cam);
        let unknown = json.replace("\"width\"", "\"widht\"");
        let e = serde_json::from_str::<Camera>(&unknown).unwrap_err();
        assert!(e.to_string().contains("unknown field `widht`"), "{e}");
    }
}
