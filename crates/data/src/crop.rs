//! Face crops: a square box around the projected head of the frame's posed body, padded,
//! resampled from the full-resolution image to `size × size`, with intrinsics
//! `fx' = s fx, cx' = s (cx − x0)` (`s = size / side`, R and t unchanged).

use glam::Vec3;

use f3g_camera::Camera;
use f3g_io::Image;

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

#[cfg(test)]
mod tests {
    use super::*;

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
