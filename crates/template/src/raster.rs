//! A triangle rasteriser: orthographic or pinhole projection, depth test, back-face culling,
//! barycentric attribute interpolation (perspective-correct for pinhole cameras).
//!
//! A pixel `(i, j)` is covered when its centre `(i + 0.5, j + 0.5)` lies inside the projected
//! triangle (edges included). Rows are split into bands rasterised in parallel.

use glam::{Vec2, Vec3};
use rayon::prelude::*;

use f3g_camera::Camera;

/// How world points map to pixels.
#[derive(Clone, Debug, PartialEq)]
pub enum Projection {
    /// Looking along −Z (from +Z, `Front`) or +Z (from −Z, `Back`), with world `x` to the
    /// right in both (so front and back pixels share `(x, y)`) and `y` up. Pixel `(i, j)` has
    /// its centre at world `x = origin.x + (i + 0.5)·size`, `y = origin.y − (j + 0.5)·size`.
    Orthographic {
        view: View,
        origin: Vec2,
        pixel_size: f32,
    },
    /// A calibrated camera (OpenCV convention).
    Pinhole(Camera),
}

/// Which side an orthographic projection looks from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum View {
    Front,
    Back,
}

/// Per-pixel result of rasterising a mesh.
#[derive(Clone, Debug, PartialEq)]
pub struct Fragments {
    pub width: usize,
    pub height: usize,
    /// Triangle index per pixel, [`Fragments::EMPTY`] where nothing was drawn.
    pub triangle: Vec<u32>,
    /// Barycentric coordinates (of the triangle's three corners) per pixel.
    pub bary: Vec<[f32; 3]>,
    /// Distance along the view direction (camera z for pinhole cameras).
    pub depth: Vec<f32>,
}

impl Fragments {
    pub const EMPTY: u32 = u32::MAX;

    /// Whether pixel `p` (row-major) was drawn.
    pub fn covered(&self, p: usize) -> bool {
        self.triangle[p] != Self::EMPTY
    }

    /// Interpolates a per-vertex attribute at every covered pixel (`None` elsewhere).
    pub fn interpolate<T>(&self, triangles: &[[u32; 3]], values: &[T]) -> Vec<Option<T>>
    where
        T: Copy + std::ops::Mul<f32, Output = T> + std::ops::Add<Output = T> + Send + Sync,
    {
        self.triangle
            .par_iter()
            .zip(&self.bary)
            .map(|(&t, b)| {
                (t != Self::EMPTY).then(|| {
                    let [a, bb, c] = triangles[t as usize];
                    values[a as usize] * b[0]
                        + values[bb as usize] * b[1]
                        + values[c as usize] * b[2]
                })
            })
            .collect()
    }
}

/// Screen position `(x, y)` in pixels and depth of a world point.
fn to_screen(projection: &Projection, p: Vec3) -> Vec3 {
    match projection {
        Projection::Orthographic {
            view,
            origin,
            pixel_size,
        } => {
            let x = (p.x - origin.x) / pixel_size;
            let y = (origin.y - p.y) / pixel_size;
            let depth = match view {
                View::Front => -p.z,
                View::Back => p.z,
            };
            Vec3::new(x, y, depth)
        }
        Projection::Pinhole(cam) => {
            let c = cam.world_to_camera([p.x as f64, p.y as f64, p.z as f64]);
            let z = c[2];
            Vec3::new(
                (cam.fx() * c[0] / z + cam.cx()) as f32,
                (cam.fy() * c[1] / z + cam.cy()) as f32,
                z as f32,
            )
        }
    }
}

/// Whether a triangle faces the viewer (its normal points towards the camera).
fn front_facing(projection: &Projection, a: Vec3, b: Vec3, c: Vec3) -> bool {
    let n = (b - a).cross(c - a);
    match projection {
        Projection::Orthographic {
            view: View::Front, ..
        } => n.z > 0.0,
        Projection::Orthographic {
            view: View::Back, ..
        } => n.z < 0.0,
        Projection::Pinhole(cam) => {
            let centre = cam.center();
            n.dot(Vec3::new(centre[0] as f32, centre[1] as f32, centre[2] as f32) - a) > 0.0
        }
    }
}

/// Rasterises a mesh. With `cull_back_faces`, triangles facing away are skipped. For pinhole
/// cameras, triangles with a corner at or behind `near` are skipped (no clipping).
pub fn rasterize(
    vertices: &[Vec3],
    triangles: &[[u32; 3]],
    projection: &Projection,
    width: usize,
    height: usize,
    cull_back_faces: bool,
) -> Fragments {
    let screen: Vec<Vec3> = vertices
        .par_iter()
        .map(|&v| to_screen(projection, v))
        .collect();
    let near = match projection {
        Projection::Pinhole(cam) => cam.near as f32,
        Projection::Orthographic { .. } => f32::NEG_INFINITY,
    };
    let perspective = matches!(projection, Projection::Pinhole(_));
    // Triangles that survive culling, with their screen bounding rows.
    let candidates: Vec<(u32, f32, f32)> = triangles
        .par_iter()
        .enumerate()
        .filter_map(|(t, tri)| {
            let [a, b, c] = tri.map(|i| vertices[i as usize]);
            if cull_back_faces && !front_facing(projection, a, b, c) {
                return None;
            }
            let s = tri.map(|i| screen[i as usize]);
            if s.iter().any(|v| !v.is_finite() || v.z <= near) {
                return None;
            }
            let (ymin, ymax) = (
                s[0].y.min(s[1].y).min(s[2].y),
                s[0].y.max(s[1].y).max(s[2].y),
            );
            Some((t as u32, ymin, ymax))
        })
        .collect();

    const BAND: usize = 16;
    let mut triangle = vec![Fragments::EMPTY; width * height];
    let mut bary = vec![[0.0f32; 3]; width * height];
    let mut depth = vec![f32::INFINITY; width * height];
    triangle
        .par_chunks_mut(BAND * width.max(1))
        .zip(bary.par_chunks_mut(BAND * width.max(1)))
        .zip(depth.par_chunks_mut(BAND * width.max(1)))
        .enumerate()
        .for_each(|(band, ((tri_out, bary_out), depth_out))| {
            let y0 = band * BAND;
            let rows = tri_out.len() / width.max(1);
            for &(t, ymin, ymax) in &candidates {
                if ymax < y0 as f32 || ymin > (y0 + rows) as f32 {
                    continue;
                }
                let tri = triangles[t as usize];
                let [p0, p1, p2] = tri.map(|i| screen[i as usize]);
                let area = (p1.x - p0.x) * (p2.y - p0.y) - (p2.x - p0.x) * (p1.y - p0.y);
                if area.abs() < 1e-12 {
                    continue;
                }
                let xmin = (p0.x.min(p1.x).min(p2.x) - 0.5).ceil().max(0.0) as usize;
                let xmax = ((p0.x.max(p1.x).max(p2.x) - 0.5).floor() as i64).min(width as i64 - 1);
                let rmin = ((ymin - 0.5).ceil() as i64).max(y0 as i64);
                let rmax = ((ymax - 0.5).floor() as i64).min((y0 + rows) as i64 - 1);
                if xmax < xmin as i64 || rmax < rmin {
                    continue;
                }
                for y in rmin as usize..=rmax as usize {
                    let py = y as f32 + 0.5;
                    for x in xmin..=xmax as usize {
                        let px = x as f32 + 0.5;
                        let w1 = ((px - p0.x) * (p2.y - p0.y) - (p2.x - p0.x) * (py - p0.y)) / area;
                        let w2 = ((p1.x - p0.x) * (py - p0.y) - (px - p0.x) * (p1.y - p0.y)) / area;
                        let w0 = 1.0 - w1 - w2;
                        if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                            continue;
                        }
                        let mut b = [w0, w1, w2];
                        let z = if perspective {
                            // 1/z is affine in screen space; attributes are affine in b/z.
                            let inv = w0 / p0.z + w1 / p1.z + w2 / p2.z;
                            b = [w0 / p0.z / inv, w1 / p1.z / inv, w2 / p2.z / inv];
                            1.0 / inv
                        } else {
                            w0 * p0.z + w1 * p1.z + w2 * p2.z
                        };
                        let o = (y - y0) * width + x;
                        if z < depth_out[o] {
                            depth_out[o] = z;
                            tri_out[o] = t;
                            bary_out[o] = b;
                        }
                    }
                }
            }
        });
    Fragments {
        width,
        height,
        triangle,
        bary,
        depth,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quad(z: f32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
        (
            vec![
                Vec3::new(-1.0, -1.0, z),
                Vec3::new(1.0, -1.0, z),
                Vec3::new(1.0, 1.0, z),
                Vec3::new(-1.0, 1.0, z),
            ],
            vec![[0, 1, 2], [0, 2, 3]],
        )
    }

    #[test]
    fn orthographic_front_covers_and_interpolates() {
        let (v, t) = quad(0.25);
        let proj = Projection::Orthographic {
            view: View::Front,
            origin: Vec2::new(-2.0, 2.0),
            pixel_size: 0.5,
        };
        let f = rasterize(&v, &t, &proj, 8, 8, true);
        // Pixel centres at -1.75, -1.25, ..., 1.75: the quad [-1, 1] covers columns 2..6.
        let covered: usize = (0..64).filter(|&p| f.covered(p)).count();
        assert_eq!(covered, 16);
        let pos = f.interpolate(&t, &v);
        let p = pos[3 * 8 + 2].unwrap();
        assert!((p - Vec3::new(-0.75, 0.25, 0.25)).length() < 1e-6);
        // Seen from the back it faces away and is culled.
        let back = Projection::Orthographic {
            view: View::Back,
            origin: Vec2::new(-2.0, 2.0),
            pixel_size: 0.5,
        };
        assert_eq!(
            rasterize(&v, &t, &back, 8, 8, true)
                .triangle
                .iter()
                .filter(|&&x| x != Fragments::EMPTY)
                .count(),
            0
        );
        assert_eq!(
            rasterize(&v, &t, &back, 8, 8, false)
                .triangle
                .iter()
                .filter(|&&x| x != Fragments::EMPTY)
                .count(),
            16
        );
    }

    #[test]
    fn depth_test_keeps_the_nearest_surface() {
        let (mut v, mut t) = quad(0.0);
        let (v2, t2) = quad(0.5);
        t.extend(t2.iter().map(|x| x.map(|i| i + 4)));
        v.extend(v2);
        let proj = Projection::Orthographic {
            view: View::Front,
            origin: Vec2::new(-2.0, 2.0),
            pixel_size: 0.5,
        };
        let f = rasterize(&v, &t, &proj, 8, 8, true);
        let p = 3 * 8 + 3;
        assert!(f.triangle[p] >= 2, "the quad at z = 0.5 is in front");
        assert!((f.depth[p] + 0.5).abs() < 1e-6);
    }

    #[test]
    fn pinhole_interpolation_is_perspective_correct() {
        // A slanted quad: interpolated 3D positions must project back onto their pixel centres.
        let v = vec![
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(1.0, -1.0, -2.0),
            Vec3::new(1.0, 1.0, -2.0),
            Vec3::new(-1.0, 1.0, 0.0),
        ];
        let t = vec![[0, 1, 2], [0, 2, 3]];
        let cam = Camera::look_at([0.0, 0.0, 4.0], [0.0; 3], [0.0, 1.0, 0.0], 60.0, 64, 48);
        let f = rasterize(&v, &t, &Projection::Pinhole(cam.clone()), 64, 48, false);
        let pos = f.interpolate(&t, &v);
        let mut checked = 0;
        for (p, x) in pos.iter().enumerate() {
            if let Some(x) = x {
                let (uv, _) = cam.project([x.x as f64, x.y as f64, x.z as f64]).unwrap();
                assert!(
                    (uv[0] - ((p % 64) as f64 + 0.5)).abs() < 1e-3
                        && (uv[1] - ((p / 64) as f64 + 0.5)).abs() < 1e-3
                );
                checked += 1;
            }
        }
        assert!(checked > 300);
    }
}
