//! Face crops: a square box around the projected head of the frame's posed body, padded,
//! resampled from the full-resolution image to `size × size`, with intrinsics
//! `fx' = s fx, cx' = s (cx − x0)` (`s = size / side`, R and t unchanged); and from which side
//! a camera sees the head ([`ViewClass`]).

use glam::Vec3;

use f3g_camera::Camera;
use f3g_io::Image;
use f3g_rig::{Posed, Rig, RigError, Role};

use crate::imgops::crop_resize;

/// A square in pixel coordinates of the full image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeadBox {
    pub x0: f32,
    pub y0: f32,
    pub side: f32,
}

/// The square around the projections of `points` (world), enlarged by `padding`; `None` when
/// the head is behind the camera or entirely outside the image.
pub fn head_box(camera: &Camera, points: &[Vec3], padding: f32) -> Option<HeadBox> {
    let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
    for p in points {
        let (uv, _) = camera.project([p.x as f64, p.y as f64, p.z as f64])?;
        for a in 0..2 {
            lo[a] = lo[a].min(uv[a]);
            hi[a] = hi[a].max(uv[a]);
        }
    }
    if points.is_empty()
        || hi[0] < 0.0
        || hi[1] < 0.0
        || lo[0] > camera.width as f64
        || lo[1] > camera.height as f64
    {
        return None;
    }
    let side = ((hi[0] - lo[0]).max(hi[1] - lo[1]) as f32 * padding).max(4.0);
    let centre = [0.5 * (lo[0] + hi[0]) as f32, 0.5 * (lo[1] + hi[1]) as f32];
    Some(HeadBox {
        x0: centre[0] - 0.5 * side,
        y0: centre[1] - 0.5 * side,
        side,
    })
}

/// The camera of the crop of `b` resampled to `size × size`.
pub fn crop_camera(camera: &Camera, b: &HeadBox, size: usize) -> Camera {
    camera.crop_resize(
        b.x0 as f64,
        b.y0 as f64,
        size as f64 / b.side as f64,
        size as u32,
        size as u32,
    )
}

/// Crops `image` to `b`, resampled to `size × size`, with its camera.
pub fn crop_view(
    image: &Image,
    camera: &Camera,
    b: &HeadBox,
    size: usize,
    fill: &[f32],
) -> (Image, Camera) {
    (
        crop_resize(image, b.x0, b.y0, b.side, size, fill),
        crop_camera(camera, b, size),
    )
}

/// From which side a camera sees the head, by the angle between the head's facing direction
/// and the direction from the head to the camera: front below [`FRONT_MAX_DEG`], back above
/// [`BACK_MIN_DEG`], side between.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum ViewClass {
    Front,
    Side,
    Back,
}

/// Front views: within 45° of the face's direction (both eyes and the mouth in view).
pub const FRONT_MAX_DEG: f32 = 45.0;
/// Back views: more than 135° from it (the face hidden).
pub const BACK_MIN_DEG: f32 = 135.0;

impl ViewClass {
    pub const ALL: [Self; 3] = [Self::Front, Self::Side, Self::Back];

    pub fn of_angle(deg: f32) -> Self {
        if deg < FRONT_MAX_DEG {
            Self::Front
        } else if deg > BACK_MIN_DEG {
            Self::Back
        } else {
            Self::Side
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Front => "front",
            Self::Side => "side",
            Self::Back => "back",
        }
    }
}

/// The posed head's facing direction in the world: the rest pose's +Z (every body model's
/// rest faces +Z) turned by the head joint's rest-to-posed transform.
pub fn head_facing(rig: &Rig, posed: &Posed) -> Result<Vec3, RigError> {
    Ok(posed.skinning[rig.role(Role::Head)?]
        .transform_vector3(Vec3::Z)
        .normalize_or_zero())
}

/// Degrees between `facing` and the direction from `centre` (the head) to the camera.
pub fn view_angle_deg(camera: &Camera, centre: Vec3, facing: Vec3) -> f32 {
    let [x, y, z] = camera.center();
    (Vec3::new(x as f32, y as f32, z as f32) - centre)
        .normalize_or_zero()
        .dot(facing)
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn view_classes_follow_the_angle_to_the_face() {
        let facing = Vec3::Z;
        let centre = Vec3::new(0.0, 1.6, 0.0);
        let at = |deg: f32| {
            let (s, c) = deg.to_radians().sin_cos();
            let eye = [3.0 * s as f64, 1.6, 3.0 * c as f64];
            let cam = Camera::look_at(eye, [0.0, 1.6, 0.0], [0.0, 1.0, 0.0], 500.0, 64, 64);
            view_angle_deg(&cam, centre, facing)
        };
        for (deg, class) in [
            (0.0, ViewClass::Front),
            (-30.0, ViewClass::Front),
            (60.0, ViewClass::Side),
            (-100.0, ViewClass::Side),
            (157.5, ViewClass::Back),
            (180.0, ViewClass::Back),
        ] {
            let angle = at(deg);
            assert!((angle - deg.abs()).abs() < 0.01, "{deg}: {angle}");
            assert_eq!(ViewClass::of_angle(angle), class, "{deg}");
        }
    }

    /// The posed head's direction follows the head joint: the built-in human turning its head
    /// 90° to its left faces +X.
    #[test]
    fn the_head_faces_where_its_joint_turns() {
        let human = f3g_rig::builtin::load().unwrap();
        let rig = &human.rig;
        let rest = rig.pose(&rig.zero_params()).unwrap();
        assert!((head_facing(rig, &rest).unwrap() - Vec3::Z).length() < 1e-5);
        let mut turned = rig.zero_params();
        let head = rig.role(Role::Head).unwrap();
        rig.set_joint_rotation(
            &mut turned,
            head,
            glam::Quat::from_rotation_y(90f32.to_radians()),
        );
        let facing = head_facing(rig, &rig.pose(&turned).unwrap()).unwrap();
        assert!((facing - Vec3::X).length() < 1e-3, "{facing}");
    }

    #[test]
    fn a_point_lands_on_the_same_content_after_crop_and_resize() {
        // An image whose pixel (i, j) stores its own centre coordinates: sampling the crop at a
        // projected point must return the full image's coordinates of that point.
        let cam = Camera::look_at([0.2, 0.1, 2.5], [0.0; 3], [0.0, 1.0, 0.0], 700.0, 600, 800);
        let data: Vec<f32> = (0..600 * 800)
            .flat_map(|p| [(p % 600) as f32 + 0.5, (p / 600) as f32 + 0.5, 0.0])
            .collect();
        let img = Image::from_vec(600, 800, 3, data).unwrap();
        let points = [
            Vec3::new(0.05, 0.12, 0.03),
            Vec3::new(-0.08, 0.2, -0.05),
            Vec3::new(0.0, 0.05, 0.1),
        ];
        let b = head_box(&cam, &points, 1.3).unwrap();
        let (crop, crop_cam) = crop_view(&img, &cam, &b, 96, &[0.0; 3]);
        for p in points {
            let x = [p.x as f64, p.y as f64, p.z as f64];
            let (full, _) = cam.project(x).unwrap();
            let (uv, _) = crop_cam.project(x).unwrap();
            // Bilinear sample of the crop at uv (sub-pixel).
            let (u, v) = (uv[0] - 0.5, uv[1] - 0.5);
            let (i, j) = (u.floor() as usize, v.floor() as usize);
            let (a, bb) = ((u - i as f64) as f32, (v - j as f64) as f32);
            let px = |i: usize, j: usize| crop.pixel(i, j).to_vec();
            let s: Vec<f32> = (0..2)
                .map(|c| {
                    px(i, j)[c] * (1.0 - a) * (1.0 - bb)
                        + px(i + 1, j)[c] * a * (1.0 - bb)
                        + px(i, j + 1)[c] * (1.0 - a) * bb
                        + px(i + 1, j + 1)[c] * a * bb
                })
                .collect();
            assert!(
                (s[0] as f64 - full[0]).abs() < 0.05 && (s[1] as f64 - full[1]).abs() < 0.05,
                "{s:?} vs {full:?}"
            );
        }
    }
}
