//! `f3g fit`: a body model's parameters fitted to a capture's calibrated masks (and, where
//! given, 2D keypoints), frame by frame.
//!
//! Each frame is a least-squares problem over the pose parameters a silhouette sees
//! ([`Rig::posture_params`]: not the fingers, jaw or eyes) — and, on the first frame, the
//! body's shape, then held — solved with Levenberg–Marquardt
//! ([`f3g_rig::fit::levenberg_marquardt`]). Residuals are in metres (a pixel distance times
//! depth over focal length), so cameras of any resolution weigh alike:
//!
//! - **inside**: every body vertex a camera's image holds lies inside its mask — its
//!   projection's distance to the mask (an exact distance transform, zero inside), less
//!   [`INSIDE_SLACK`]. Occlusion does not matter: a silhouette is the union of every surface
//!   point's projection. Beyond the image's edge the mask says nothing.
//! - **cover**: every point of the mask's outline (not the image's edge) lies on the projected
//!   body — its distance to the nearest projected mesh edge at the nearest projected vertex,
//!   less [`COVER_SLACK`] pixels, under a Cauchy loss of scale [`COVER_SCALE`] so that clothes
//!   or hair the body model lacks pull only weakly.
//! - **keypoints** (optional): a joint's projection against the 2D keypoint of its role,
//!   weighted by the detector's confidence, under the same Cauchy loss.
//! - **prior**, **joint limit** and **smoothness**: pose parameters (not the root's) and the
//!   shape drawn weakly to the rest pose and template, pose parameters kept within
//!   ±[`JOINT_LIMIT`], every fitted parameter drawn to the previous frame's value.
//!
//! Distances and outlines are taken at the mask's resolution, at most [`WORK_WIDTH`] pixels
//! across; the per-camera IoU is reported at [`check::FIT_WIDTH`](crate::check::FIT_WIDTH), as
//! `f3g data check` reports it. The first frame starts from the rest pose stood along the
//! cameras' mean up direction, placed where the rays through the masks' centroids meet and
//! turned to the best of [`HEADINGS`] headings (the root and shape fitted from each); every
//! later frame starts from the previous one, and is fitted again from the rest pose when the
//! track is lost ([`LOST_TRACK`]). No step moves a parameter by more than [`MAX_STEP`].

use std::f32::consts::TAU;

use glam::{Mat3, Quat, Vec2, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::DataError;
use crate::check::{CameraFit, FIT_WIDTH, agreement, fit_size, silhouette};
use crate::dataset::Dataset;
use crate::imgops::{resized_camera, shrink_channel};
use f3g_camera::Camera;
use f3g_io::Image;
use f3g_rig::fit::{Column, levenberg_marquardt, point_jacobian};
use f3g_rig::{Posed, Rig, RigError, RigParams, Role};

/// Pixels (at [`WORK_WIDTH`]) an outline point may lie from the body's projected outline at no
/// cost: the rounding of the mask's edge to pixel centres.
pub const COVER_SLACK: f32 = 0.5;
/// Pixels (at [`WORK_WIDTH`]) a vertex may lie beyond the nearest inside pixel's centre at no
/// cost: the mask's edge runs half a pixel beyond it.
pub const INSIDE_SLACK: f32 = 0.5;
/// Scale (metres) of the Cauchy loss on the outline and keypoint terms: errors below it count
/// fully, larger ones (a skirt the body model lacks, a wrong detection) logarithmically.
pub const COVER_SCALE: f32 = 0.05;
/// The largest change of a parameter in one Levenberg–Marquardt step (radians, metres, shape
/// coefficients): an Euler angle taken past ±π lands on another branch of the same rotation,
/// where the prior pulls it the wrong way (measured: a 0.3 cap slows the fit to a worse
/// result, none lets necks and wrists wander to ±π and lose the track).
pub const MAX_STEP: f64 = 1.0;
/// The joint limit: no pose parameter but the root's goes beyond this many radians (143°)
/// without a cost of [`JOINT_LIMIT_WEIGHT`] per radian squared. Wrists, feet and necks, which
/// silhouettes barely see, otherwise drift to ±π, where a rotation has another set of angles
/// and the next frame starts lost.
pub const JOINT_LIMIT: f32 = 2.5;
/// Weight of the joint limit (m² per rad²: a tenth of a radian beyond costs as much as a
/// centimetre of silhouette at a hundred points).
pub const JOINT_LIMIT_WEIGHT: f32 = 1.0;
/// Headings tried for the first frame.
pub const HEADINGS: usize = 8;

/// Settings of a fit.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct FitOptions {
    /// Outline points per camera and frame.
    pub outline_points: usize,
    /// Levenberg–Marquardt iterations per stage of a frame (a later frame has one stage; the
    /// first has four, the shape's three times as long).
    pub iterations: usize,
    /// Weight of the smoothness term (per parameter, against the previous frame).
    pub smoothness: f32,
    /// Weight of the pose prior (per parameter, towards the rest pose).
    pub prior: f32,
    /// Weight of the keypoint term relative to the mask terms.
    pub keypoint_weight: f32,
    /// Fit the body's shape (identity coefficients) on the first frame and hold it.
    pub fit_shape: bool,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            outline_points: 400,
            iterations: 20,
            smoothness: 1e-4,
            prior: 1e-2,
            keypoint_weight: 1.0,
            fit_shape: true,
        }
    }
}

/// A 2D keypoint of a body role in one camera's image (full-resolution pixels).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Keypoint {
    pub role: Role,
    pub pixel: Vec2,
    /// The detector's confidence in [0, 1] (0: not seen).
    pub confidence: f32,
}

/// Widest image (pixels) the masks' distances and outlines are taken at: masks wider than it
/// are resized to it. Fine enough that a pixel's rounding is a small part of a body's outline
/// at [`FIT_WIDTH`](crate::check::FIT_WIDTH), where the IoU is reported.
pub const WORK_WIDTH: usize = 1024;

/// One camera's view of a frame.
pub struct View {
    name: String,
    /// The camera at the working resolution ([`WORK_WIDTH`]).
    camera: Pinhole,
    /// The camera at [`FIT_WIDTH`](crate::check::FIT_WIDTH), for the silhouette drawn to
    /// report the IoU, and the mask at that size.
    calibration: Camera,
    mask: Image,
    /// Working resolution.
    width: usize,
    height: usize,
    /// Pixel distance to the nearest inside pixel's centre (0 inside), row-major.
    distance: Vec<f32>,
    outline: Vec<Vec2>,
    /// `(joint, pixel, confidence)` at the working resolution.
    keypoints: Vec<(usize, Vec2, f32)>,
}

impl View {
    /// A camera's view from its calibration, its mask (any size; values above 0.5 are
    /// inside) and keypoints in its full-resolution pixels.
    pub fn new(
        rig: &Rig,
        name: &str,
        camera: &Camera,
        mask: &Image,
        keypoints: &[Keypoint],
        outline_points: usize,
    ) -> Result<Self, DataError> {
        if (mask.width, mask.height) != (camera.width as usize, camera.height as usize) {
            return Err(DataError::Invalid(format!(
                "camera `{name}`: its mask is {}×{}, its calibration {}×{}",
                mask.width, mask.height, camera.width, camera.height
            )));
        }
        let (width, height) = fit_size(camera, WORK_WIDTH);
        let inside: Vec<bool> = if (width, height) == (mask.width, mask.height) {
            mask.data
                .iter()
                .step_by(mask.channels)
                .map(|&m| m > 0.5)
                .collect()
        } else {
            shrink_channel(mask, width, height)
                .into_iter()
                .map(|m| m > 0.5)
                .collect()
        };
        let scale = width as f32 / camera.width as f32;
        let keypoints = keypoints
            .iter()
            .filter(|k| k.confidence > 0.0)
            .map(|k| Ok((rig.role(k.role)?, k.pixel * scale, k.confidence.min(1.0))))
            .collect::<Result<_, RigError>>()?;
        let (fit_w, fit_h) = fit_size(camera, FIT_WIDTH);
        Ok(Self {
            name: name.to_string(),
            camera: Pinhole::new(&resized_camera(camera, width, height)),
            calibration: resized_camera(camera, fit_w, fit_h),
            mask: Image {
                width: fit_w,
                height: fit_h,
                channels: 1,
                data: shrink_channel(mask, fit_w, fit_h),
            },
            width,
            height,
            distance: distance_to_mask(&inside, width, height),
            outline: outline(&inside, width, height, outline_points),
            keypoints,
        })
    }

    /// Whether a pixel lies in the image: beyond it the mask says nothing (a limb out of
    /// frame).
    fn sees(&self, p: Vec2) -> bool {
        p.x >= 0.0 && p.y >= 0.0 && p.x < self.width as f32 && p.y < self.height as f32
    }

    /// The distance transform at a point of the image (bilinear) and its gradient.
    fn distance_at(&self, p: Vec2) -> (f32, Vec2) {
        let x = (p.x - 0.5).clamp(0.0, (self.width - 1) as f32);
        let y = (p.y - 0.5).clamp(0.0, (self.height - 1) as f32);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let at = |x: usize, y: usize| self.distance[y * self.width + x];
        let (a, b, c, d) = (at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1));
        let value =
            a * (1.0 - fx) * (1.0 - fy) + b * fx * (1.0 - fy) + c * (1.0 - fx) * fy + d * fx * fy;
        let gradient = Vec2::new(
            (b - a) * (1.0 - fy) + (d - c) * fy,
            (c - a) * (1.0 - fx) + (d - b) * fx,
        );
        (value, gradient)
    }
}

/// A pinhole camera in f32 with the derivative of its projection.
#[derive(Clone, Copy, Debug)]
struct Pinhole {
    r: Mat3,
    t: Vec3,
    focal: Vec2,
    centre: Vec2,
}

impl Pinhole {
    fn new(c: &Camera) -> Self {
        let row = |i: usize| Vec3::new(c.r[i][0] as f32, c.r[i][1] as f32, c.r[i][2] as f32);
        Self {
            r: Mat3::from_cols(row(0), row(1), row(2)).transpose(),
            t: Vec3::new(c.t[0] as f32, c.t[1] as f32, c.t[2] as f32),
            focal: Vec2::new(c.fx() as f32, c.fy() as f32),
            centre: Vec2::new(c.cx() as f32, c.cy() as f32),
        }
    }

    /// Pixel, metres per pixel at the point's depth, and the rows of `d pixel / d point`;
    /// `None` for a point less than a centimetre in front of the camera.
    fn project(&self, x: Vec3) -> Option<(Vec2, f32, [Vec3; 2])> {
        let p = self.r * x + self.t;
        if p.z < 0.01 {
            return None;
        }
        let pixel = self.focal * Vec2::new(p.x, p.y) / p.z + self.centre;
        let rows = [self.r.row(0), self.r.row(1)];
        let dz = self.r.row(2);
        let d = [
            self.focal.x * (rows[0] - dz * (p.x / p.z)) / p.z,
            self.focal.y * (rows[1] - dz * (p.y / p.z)) / p.z,
        ];
        Some((pixel, p.z / self.focal.x.max(self.focal.y), d))
    }

    /// The world ray through a pixel: origin and unit direction.
    fn ray(&self, pixel: Vec2) -> (Vec3, Vec3) {
        let dir = (pixel - self.centre) / self.focal;
        let rt = self.r.transpose();
        (
            (rt * -self.t),
            (rt * Vec3::new(dir.x, dir.y, 1.0)).normalize(),
        )
    }
}

/// Exact Euclidean distance (pixels) from every pixel to the nearest inside one, 0 inside
/// (Felzenszwalb and Huttenlocher's two passes of lower envelopes of parabolas). Without any
/// inside pixel, every distance is the image's diagonal.
pub fn distance_to_mask(inside: &[bool], width: usize, height: usize) -> Vec<f32> {
    let far = ((width * width + height * height) as f32).max(1.0);
    if !inside.iter().any(|&b| b) {
        return vec![far.sqrt(); width * height];
    }
    let big = 1e20f32;
    let mut grid: Vec<f32> = inside.iter().map(|&b| if b { 0.0 } else { big }).collect();
    let mut line = Vec::new();
    for x in 0..width {
        line.clear();
        line.extend((0..height).map(|y| grid[y * width + x]));
        for (y, v) in squared_1d(&line).into_iter().enumerate() {
            grid[y * width + x] = v;
        }
    }
    for y in 0..height {
        let row = &mut grid[y * width..(y + 1) * width];
        let out = squared_1d(row);
        row.copy_from_slice(&out);
    }
    grid.into_iter().map(f32::sqrt).collect()
}

/// One pass: `out[q] = min_p (q − p)² + f[p]`.
fn squared_1d(f: &[f32]) -> Vec<f32> {
    let n = f.len();
    let mut v = vec![0usize; n];
    let mut z = vec![0f32; n + 1];
    let mut k = 0usize;
    z[0] = f32::NEG_INFINITY;
    z[1] = f32::INFINITY;
    let meet = |q: usize, p: usize| -> f32 {
        let (qf, pf) = (q as f32, p as f32);
        ((f[q] + qf * qf) - (f[p] + pf * pf)) / (2.0 * (qf - pf))
    };
    for q in 1..n {
        let mut s = meet(q, v[k]);
        while s <= z[k] {
            k -= 1;
            s = meet(q, v[k]);
        }
        k += 1;
        v[k] = q;
        z[k] = s;
        z[k + 1] = f32::INFINITY;
    }
    k = 0;
    (0..n)
        .map(|q| {
            while z[k + 1] < q as f32 {
                k += 1;
            }
            let d = q as f32 - v[k] as f32;
            d * d + f[v[k]]
        })
        .collect()
}

/// At most `count` pixel centres of the mask's outline (inside pixels with a 4-neighbour
/// outside), evenly spaced in scan order. The image's edge is no outline: a body cut by it
/// goes on beyond.
fn outline(inside: &[bool], width: usize, height: usize, count: usize) -> Vec<Vec2> {
    let at = |x: usize, y: usize| inside[y * width + x];
    let mut all = Vec::new();
    for y in 1..height.saturating_sub(1) {
        for x in 1..width.saturating_sub(1) {
            if at(x, y) && !(at(x - 1, y) && at(x + 1, y) && at(x, y - 1) && at(x, y + 1)) {
                all.push(Vec2::new(x as f32 + 0.5, y as f32 + 0.5));
            }
        }
    }
    let step = all.len().div_ceil(count.max(1)).max(1);
    all.into_iter().step_by(step).collect()
}

/// Points of an image bucketed in square cells, for nearest-point queries: built in linear
/// time, as it is for every camera at every evaluation.
struct PixelGrid {
    columns: usize,
    rows: usize,
    /// Per cell, the range of `order` holding its points.
    start: Vec<u32>,
    order: Vec<u32>,
}

impl PixelGrid {
    /// Cell side, pixels.
    const CELL: f32 = 8.0;

    fn new(points: &[Vec2], width: usize, height: usize) -> Self {
        let columns = (width as f32 / Self::CELL).ceil() as usize + 1;
        let rows = (height as f32 / Self::CELL).ceil() as usize + 1;
        let mut grid = Self {
            columns,
            rows,
            start: vec![0; columns * rows + 1],
            order: vec![0; points.len()],
        };
        let cells: Vec<usize> = points.iter().map(|&p| grid.cell(p)).collect();
        for &c in &cells {
            grid.start[c + 1] += 1;
        }
        for c in 0..columns * rows {
            grid.start[c + 1] += grid.start[c];
        }
        let mut next = grid.start.clone();
        for (i, &c) in cells.iter().enumerate() {
            grid.order[next[c] as usize] = i as u32;
            next[c] += 1;
        }
        grid
    }

    /// The cell of a point; points beyond the image fall in its border cells, which brings
    /// them nearer, never farther, so the search's bound below stays valid.
    fn cell(&self, p: Vec2) -> usize {
        let x = (p.x / Self::CELL).clamp(0.0, (self.columns - 1) as f32) as usize;
        let y = (p.y / Self::CELL).clamp(0.0, (self.rows - 1) as f32) as usize;
        y * self.columns + x
    }

    /// The index of the point nearest `q` (`points` non-empty): rings of cells around `q`'s
    /// until the ring is farther than the best found.
    fn nearest(&self, points: &[Vec2], q: Vec2) -> usize {
        let centre = self.cell(q);
        let (cx, cy) = (
            (centre % self.columns) as isize,
            (centre / self.columns) as isize,
        );
        let mut best = (f32::INFINITY, 0usize);
        let reach = self.columns.max(self.rows) as isize;
        for ring in 0..=reach {
            // Every point of ring `ring` is at least (ring − 1) cells from q.
            let bound = (ring - 1).max(0) as f32 * Self::CELL;
            if best.0 <= bound * bound {
                break;
            }
            for y in cy - ring..=cy + ring {
                for x in cx - ring..=cx + ring {
                    let on_ring = (y - cy).abs() == ring || (x - cx).abs() == ring;
                    if !on_ring
                        || x < 0
                        || y < 0
                        || x >= self.columns as isize
                        || y >= self.rows as isize
                    {
                        continue;
                    }
                    let c = y as usize * self.columns + x as usize;
                    for &i in &self.order[self.start[c] as usize..self.start[c + 1] as usize] {
                        let d = points[i as usize].distance_squared(q);
                        if d < best.0 {
                            best = (d, i as usize);
                        }
                    }
                }
            }
        }
        best.1
    }
}

/// Cauchy loss as a residual: `σ √ln(1 + (e/σ)²)` and its derivative in `e`.
fn cauchy(e: f32, sigma: f32) -> (f32, f32) {
    let u = (e / sigma).powi(2);
    if u < 1e-6 {
        // ln(1 + u) ≈ u: the residual is e itself.
        return (e, 1.0);
    }
    let r = sigma * u.ln_1p().sqrt() * e.signum();
    (r, e / (r * (1.0 + u)))
}

/// A point whose motion a residual follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
enum Point {
    Vertex(usize),
    Joint(usize),
}

/// A residual's derivative: `Σ gradient · d point / dθ` over one or two points (an edge's
/// ends), or a parameter's own weight.
#[derive(Clone, Copy, Debug)]
enum Row {
    Geometric { terms: [(Point, Vec3); 2] },
    Parameter { column: usize, weight: f32 },
}

impl Row {
    fn point(point: Point, gradient: Vec3) -> Self {
        Row::Geometric {
            terms: [(point, gradient), (point, Vec3::ZERO)],
        }
    }
}

/// What a frame's fit sees and holds fixed.
struct Frame<'a> {
    rig: &'a Rig,
    /// Per vertex: the vertices it shares a triangle edge with.
    neighbours: &'a [Vec<u32>],
    views: &'a [View],
    columns: Vec<Column>,
    /// Columns the prior draws to zero (not the root's).
    prior_columns: Vec<bool>,
    previous: Option<&'a RigParams>,
    options: &'a FitOptions,
}

/// One evaluation: the posed body and each residual's derivative.
struct Evaluation {
    posed: Posed,
    rows: Vec<Row>,
}

impl Frame<'_> {
    fn evaluate(&self, params: &RigParams) -> Result<(Vec<f64>, Evaluation), RigError> {
        let posed = self.rig.pose(params)?;
        let per_view: Vec<(Vec<f64>, Vec<Row>)> = self
            .views
            .par_iter()
            .map(|view| self.view_residuals(view, &posed))
            .collect::<Result<_, _>>()?;
        let mut r = Vec::new();
        let mut rows = Vec::new();
        for (vr, vrows) in per_view {
            r.extend(vr);
            rows.extend(vrows);
        }
        let (prior, smooth) = (self.options.prior.sqrt(), self.options.smoothness.sqrt());
        for (ci, &c) in self.columns.iter().enumerate() {
            if self.prior_columns[ci] {
                let value = c.get(params);
                r.push((prior * value) as f64);
                rows.push(Row::Parameter {
                    column: ci,
                    weight: prior,
                });
                if matches!(c, Column::Pose(_)) && value.abs() > JOINT_LIMIT {
                    let limit = JOINT_LIMIT_WEIGHT.sqrt();
                    r.push((limit * (value.abs() - JOINT_LIMIT)) as f64);
                    rows.push(Row::Parameter {
                        column: ci,
                        weight: limit * value.signum(),
                    });
                }
            }
            if let Some(prev) = self.previous {
                r.push((smooth * (c.get(params) - c.get(prev))) as f64);
                rows.push(Row::Parameter {
                    column: ci,
                    weight: smooth,
                });
            }
        }
        Ok((r, Evaluation { posed, rows }))
    }

    fn view_residuals(&self, view: &View, posed: &Posed) -> Result<(Vec<f64>, Vec<Row>), RigError> {
        let mut r = Vec::new();
        let mut rows = Vec::new();
        // Per vertex: its projection (pixel, metres per pixel, d pixel / d point), if any.
        let mut projected = Vec::with_capacity(posed.vertices.len());
        let mut seen = Vec::with_capacity(posed.vertices.len());
        let mut at = vec![None; posed.vertices.len()];
        for (i, &v) in posed.vertices.iter().enumerate() {
            let Some((pixel, metres, d)) = view.camera.project(v) else {
                continue;
            };
            let (distance, gradient) = view.distance_at(pixel);
            if distance > INSIDE_SLACK && view.sees(pixel) {
                r.push((metres * (distance - INSIDE_SLACK)) as f64);
                rows.push(Row::point(
                    Point::Vertex(i),
                    metres * (d[0] * gradient.x + d[1] * gradient.y),
                ));
            }
            projected.push(pixel);
            seen.push(i);
            at[i] = Some((pixel, metres, d));
        }
        if !projected.is_empty() {
            let grid = PixelGrid::new(&projected, view.width, view.height);
            for &q in &view.outline {
                let nearest = seen[grid.nearest(&projected, q)];
                // The nearest point of the projected edges at the nearest vertex: the body's
                // outline runs along edges, its vertices a few pixels apart.
                let (pa, ma, da) = at[nearest].expect("projected");
                let mut best = (pa, 0.0f32, nearest, (pa - q).length());
                for &j in &self.neighbours[nearest] {
                    let Some((pb, _, _)) = at[j as usize] else {
                        continue;
                    };
                    let edge = pb - pa;
                    let t = ((q - pa).dot(edge) / edge.length_squared().max(1e-12)).clamp(0.0, 1.0);
                    let point = pa + t * edge;
                    let length = (point - q).length();
                    if length < best.3 {
                        best = (point, t, j as usize, length);
                    }
                }
                let (point, t, other, length) = best;
                if length <= COVER_SLACK {
                    continue;
                }
                let (value, slope) = cauchy(ma * (length - COVER_SLACK), COVER_SCALE);
                let dir = (point - q) / length;
                let (_, _, db) = at[other].expect("projected");
                let along = |d: [Vec3; 2]| slope * ma * (d[0] * dir.x + d[1] * dir.y);
                r.push(value as f64);
                rows.push(Row::Geometric {
                    terms: [
                        (Point::Vertex(nearest), (1.0 - t) * along(da)),
                        (Point::Vertex(other), t * along(db)),
                    ],
                });
            }
        }
        let weight = self.options.keypoint_weight.sqrt();
        for &(joint, target, confidence) in &view.keypoints {
            let Some((pixel, metres, d)) = view.camera.project(posed.joints[joint].translation)
            else {
                continue;
            };
            let offset = (pixel - target) * metres;
            let length = offset.length();
            if length < 1e-9 {
                continue;
            }
            // Iteratively reweighted: the offset scaled by the Cauchy residual over its length,
            // the scale held constant in the derivative.
            let scale = weight * confidence * cauchy(length, COVER_SCALE).0 / length;
            for k in 0..2 {
                r.push((scale * offset[k]) as f64);
                rows.push(Row::point(Point::Joint(joint), scale * metres * d[k]));
            }
        }
        Ok((r, rows))
    }

    /// The normal equations at an evaluation.
    fn normal(
        &self,
        params: &RigParams,
        eval: &Evaluation,
        r: &[f64],
    ) -> Result<(faer::Mat<f64>, faer::Mat<f64>), RigError> {
        // Each point the rows follow gets a slot: vertices first, then joints.
        const NONE: u32 = u32::MAX;
        let mut vertex_slot = vec![NONE; eval.posed.vertices.len()];
        let mut joint_slot = vec![NONE; eval.posed.joints.len()];
        let (mut vertices, mut joints) = (Vec::new(), Vec::new());
        for row in &eval.rows {
            if let Row::Geometric { terms } = row {
                for (point, _) in terms {
                    match *point {
                        Point::Vertex(i) if vertex_slot[i] == NONE => {
                            vertex_slot[i] = vertices.len() as u32;
                            vertices.push(i);
                        }
                        Point::Joint(j) if joint_slot[j] == NONE => {
                            joint_slot[j] = joints.len() as u32;
                            joints.push(j);
                        }
                        _ => {}
                    }
                }
            }
        }
        let slot = |point: Point| match point {
            Point::Vertex(i) => vertex_slot[i] as usize,
            Point::Joint(j) => vertices.len() + joint_slot[j] as usize,
        };
        let d = point_jacobian(
            self.rig,
            params,
            &eval.posed,
            &self.columns,
            &vertices,
            &joints,
        )?;
        // `[point][column]`, for rows filled one at a time.
        let cols = self.columns.len();
        let points = vertices.len() + joints.len();
        let mut by_point = vec![Vec3::ZERO; points * cols];
        for (b, column) in d.iter().enumerate() {
            for (p, v) in column.iter().enumerate() {
                by_point[p * cols + b] = *v;
            }
        }
        let mut j = faer::Mat::<f64>::zeros(eval.rows.len(), cols);
        for (a, row) in eval.rows.iter().enumerate() {
            match *row {
                Row::Geometric { terms } => {
                    for (point, gradient) in terms {
                        let p = slot(point);
                        for (b, v) in by_point[p * cols..(p + 1) * cols].iter().enumerate() {
                            j[(a, b)] += gradient.dot(*v) as f64;
                        }
                    }
                }
                Row::Parameter { column, weight } => j[(a, column)] = weight as f64,
            }
        }
        let rv = faer::Mat::<f64>::from_fn(r.len(), 1, |a, _| r[a]);
        Ok((j.transpose() * &j, j.transpose() * &rv))
    }

    fn solve(&self, init: RigParams, iterations: usize) -> Result<(RigParams, f64), RigError> {
        let (params, _, _) = levenberg_marquardt(
            init,
            &self.columns,
            iterations,
            MAX_STEP,
            |p| self.evaluate(p),
            |p, e, r| self.normal(p, e, r),
        )?;
        let cost = self.evaluate(&params)?.0.iter().map(|v| v * v).sum();
        Ok((params, cost))
    }
}

/// A fitted frame and how well it lies on the masks.
#[derive(Clone, Debug)]
pub struct FrameFit {
    pub params: RigParams,
    /// Per camera: IoU of the body's silhouette and the mask, and the share inside it.
    pub cameras: Vec<CameraFit>,
    /// The masks' and keypoints' cost (sum of squared residuals, m²; no prior or smoothness).
    pub cost: f64,
}

impl FrameFit {
    /// Mean IoU over the cameras.
    pub fn mean_iou(&self) -> f32 {
        self.cameras.iter().map(|c| c.iou).sum::<f32>() / self.cameras.len().max(1) as f32
    }
}

/// Fits one frame seen by `views`: from the previous frame's fit when given, else from the
/// rest pose placed in the views ([module docs](self)). A track whose cost comes out above
/// [`LOST_TRACK`] times the previous frame's (a jump in the motion) is fitted again from the
/// rest pose, with the previous frame's shape, and the better kept. The shape is fitted only
/// without a previous frame, and with `options.fit_shape`.
pub fn fit_frame(
    rig: &Rig,
    views: &[View],
    previous: Option<&FrameFit>,
    options: &FitOptions,
) -> Result<FrameFit, DataError> {
    if views.is_empty() {
        return Err(DataError::Invalid("no camera sees this frame".into()));
    }
    let fitter = Fitter {
        rig,
        views,
        options,
        neighbours: edge_neighbours(rig),
        posture: rig.posture_params()?,
        roots: rig.root_params(),
    };
    let (params, cost) = match previous {
        Some(prev) => {
            let tracked = fitter.track(&prev.params)?;
            let cost = fitter.data_cost(&tracked)?;
            if cost > LOST_TRACK * prev.cost {
                let anew = fitter.anew(&prev.params.identity, false)?;
                let anew_cost = fitter.data_cost(&anew)?;
                if anew_cost < cost {
                    (anew, anew_cost)
                } else {
                    (tracked, cost)
                }
            } else {
                (tracked, cost)
            }
        }
        None => {
            let zero = vec![0.0; rig.identity.len()];
            let params = fitter.anew(&zero, options.fit_shape)?;
            let cost = fitter.data_cost(&params)?;
            (params, cost)
        }
    };
    let posed = rig.pose(&params)?;
    let cameras = views
        .par_iter()
        .map(|v| {
            let body = silhouette(
                &posed.vertices,
                &rig.mesh.triangles,
                &v.calibration,
                v.mask.width,
                v.mask.height,
            );
            let (iou, inside) = agreement(&body, &v.mask);
            CameraFit::new(&v.name, (iou, inside, 1))
        })
        .collect();
    Ok(FrameFit {
        params,
        cameras,
        cost,
    })
}

/// A track costing more than this many times the previous frame's is refitted from the rest
/// pose.
pub const LOST_TRACK: f64 = 3.0;

/// One frame's fitting stages.
struct Fitter<'a> {
    rig: &'a Rig,
    views: &'a [View],
    options: &'a FitOptions,
    neighbours: Vec<Vec<u32>>,
    posture: Vec<usize>,
    roots: Vec<usize>,
}

impl Fitter<'_> {
    /// The problem over `columns`: the prior on every column but the root's, smoothness
    /// against `previous` when given.
    fn frame<'b>(&'b self, columns: Vec<Column>, previous: Option<&'b RigParams>) -> Frame<'b> {
        Frame {
            rig: self.rig,
            neighbours: &self.neighbours,
            prior_columns: columns
                .iter()
                .map(|c| !matches!(c, Column::Pose(p) if self.roots.contains(p)))
                .collect(),
            columns,
            views: self.views,
            previous,
            options: self.options,
        }
    }

    fn pose_columns(&self, parameters: &[usize]) -> Vec<Column> {
        parameters.iter().map(|&p| Column::Pose(p)).collect()
    }

    /// The masks' and keypoints' cost alone (no prior, no smoothness): comparable between
    /// frames and starts.
    fn data_cost(&self, params: &RigParams) -> Result<f64, DataError> {
        // No columns: no prior and no smoothness rows.
        let frame = self.frame(Vec::new(), None);
        Ok(frame.evaluate(params)?.0.iter().map(|v| v * v).sum())
    }

    /// The frame from the previous one's parameters.
    fn track(&self, previous: &RigParams) -> Result<RigParams, DataError> {
        let frame = self.frame(self.pose_columns(&self.posture), Some(previous));
        Ok(frame.solve(previous.clone(), self.options.iterations)?.0)
    }

    /// The frame from the rest pose with `identity`, placed in the views and turned to the best
    /// of [`HEADINGS`] headings (the root, and the shape, fitted from each), then every posture
    /// parameter, then (with `fit_shape`) the shape with them.
    fn anew(&self, identity: &[f32], fit_shape: bool) -> Result<RigParams, DataError> {
        let mut start = self.rig.zero_params();
        start.identity = identity.to_vec();
        let start = placed(self.rig, self.views, start)?;
        // The root, and the shape when it is fitted: a body of the wrong size placed well
        // is a poor start for the limbs.
        let mut root_columns = self.pose_columns(&self.roots);
        if fit_shape {
            root_columns.extend((0..self.rig.identity.len()).map(Column::Identity));
        }
        let root_only = self.frame(root_columns, None);
        let mut best: Option<(RigParams, f64)> = None;
        for k in 0..HEADINGS {
            let turned = turned(self.rig, &start, TAU * k as f32 / HEADINGS as f32)?;
            let fitted = root_only.solve(turned, self.options.iterations / 2)?;
            if best.as_ref().is_none_or(|b| fitted.1 < b.1) {
                best = Some(fitted);
            }
        }
        let (params, _) = best.expect("HEADINGS > 0");
        let pose_columns = self.pose_columns(&self.posture);
        let params = self
            .frame(pose_columns.clone(), None)
            .solve(params, self.options.iterations)?
            .0;
        if !fit_shape || self.rig.identity.is_empty() {
            return Ok(params);
        }
        let mut columns = pose_columns;
        columns.extend((0..self.rig.identity.len()).map(Column::Identity));
        Ok(self
            .frame(columns, None)
            .solve(params, 3 * self.options.iterations)?
            .0)
    }
}

/// Per vertex of the rig's mesh: the vertices it shares a triangle edge with.
fn edge_neighbours(rig: &Rig) -> Vec<Vec<u32>> {
    let mut out = vec![Vec::new(); rig.mesh.vertices.len()];
    for t in &rig.mesh.triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            out[a as usize].push(b);
            out[b as usize].push(a);
        }
    }
    for n in &mut out {
        n.sort_unstable();
        n.dedup();
    }
    out
}

/// `params` (at rest) stood upright along the cameras' mean up direction, its centre where the
/// rays through the masks' centroids meet (least squares).
fn placed(rig: &Rig, views: &[View], mut params: RigParams) -> Result<RigParams, DataError> {
    let up = views
        .iter()
        .map(|v| -v.camera.r.row(1))
        .sum::<Vec3>()
        .normalize_or(Vec3::Y);
    let (mut a, mut b) = (Mat3::ZERO, Vec3::ZERO);
    for v in views {
        let (sum, n) = v
            .mask
            .data
            .chunks_exact(v.mask.channels)
            .enumerate()
            .filter(|(_, m)| m[0] > 0.5)
            .fold((Vec2::ZERO, 0usize), |(s, n), (p, _)| {
                let (x, y) = (p % v.mask.width, p / v.mask.width);
                (s + Vec2::new(x as f32 + 0.5, y as f32 + 0.5), n + 1)
            });
        if n == 0 {
            continue;
        }
        let (origin, dir) = Pinhole::new(&v.calibration).ray(sum / n as f32);
        let m = Mat3::IDENTITY - Mat3::from_cols(dir * dir.x, dir * dir.y, dir * dir.z);
        a += m;
        b += m * origin;
    }
    if a.determinant().abs() < 1e-9 {
        return Err(DataError::Invalid(
            "the masks do not place the body: fewer than two cameras see it from different directions".into(),
        ));
    }
    let centre = a.inverse() * b;
    rig.set_joint_rotation(&mut params, 0, Quat::from_rotation_arc(Vec3::Y, up));
    place(rig, &mut params, centre)?;
    Ok(params)
}

/// Moves the root so that the posed body's bounding-box centre is at `centre`.
fn place(rig: &Rig, params: &mut RigParams, centre: Vec3) -> Result<(), DataError> {
    let (lo, hi) = rig.pose(params)?.bounds();
    let t = rig.root_translation(params) + centre - (lo + hi) / 2.0;
    rig.set_root_translation(params, t)?;
    Ok(())
}

/// `params` turned by `angle` about the body's own up axis, in place.
fn turned(rig: &Rig, params: &RigParams, angle: f32) -> Result<RigParams, DataError> {
    let posed = rig.pose(params)?;
    let (lo, hi) = posed.bounds();
    let root = posed.joints[0].rotation;
    let mut out = params.clone();
    rig.set_joint_rotation(&mut out, 0, root * Quat::from_rotation_y(angle));
    place(rig, &mut out, (lo + hi) / 2.0)?;
    Ok(out)
}

/// The views of one frame of a capture: every camera with an image, with its mask and its
/// keypoints (`keypoints[camera]`, when given).
pub fn frame_views(
    ds: &Dataset,
    rig: &Rig,
    frame: usize,
    keypoints: Option<&[Vec<Keypoint>]>,
    options: &FitOptions,
) -> Result<Vec<View>, DataError> {
    (0..ds.cameras.len())
        .into_par_iter()
        .filter(|&c| ds.has_image(c, frame))
        .map(|c| {
            let cam = &ds.cameras[c];
            View::new(
                rig,
                &cam.name,
                &cam.camera,
                &ds.mask(c, frame)?,
                keypoints.map_or(&[][..], |k| &k[c]),
                options.outline_points,
            )
        })
        .collect()
}

/// Mean distance (metres) between the joints of every body role, and between all vertices,
/// of two parameter sequences of one body model: a fit against the truth.
pub fn errors_against(
    rig: &Rig,
    fitted: &[RigParams],
    truth: &[RigParams],
) -> Result<(f32, f32), DataError> {
    let roles: Vec<usize> = Role::ALL
        .iter()
        .filter(|r| !matches!(r, Role::Jaw | Role::LeftEye | Role::RightEye))
        .filter_map(|&r| rig.role(r).ok())
        .collect();
    let (mut joints, mut vertices, mut n) = (0.0f64, 0.0f64, 0usize);
    for (f, t) in fitted.iter().zip(truth) {
        let (a, b) = (rig.pose(f)?, rig.pose(t)?);
        joints += roles
            .iter()
            .map(|&j| a.joints[j].translation.distance(b.joints[j].translation) as f64)
            .sum::<f64>()
            / roles.len().max(1) as f64;
        vertices += a
            .vertices
            .iter()
            .zip(&b.vertices)
            .map(|(p, q)| p.distance(*q) as f64)
            .sum::<f64>()
            / a.vertices.len().max(1) as f64;
        n += 1;
    }
    let n = n.max(1) as f64;
    Ok(((joints / n) as f32, (vertices / n) as f32))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Eight cameras around the built-in human posed by `truth`, with its masks.
    fn ring(rig: &Rig, truth: &RigParams, keypoints: bool) -> Vec<View> {
        let posed = rig.pose(truth).unwrap();
        (0..8)
            .map(|k| {
                let a = TAU * k as f32 / 8.0 + 0.3;
                let eye = [3.0 * a.sin() as f64, 0.3, 3.0 * a.cos() as f64];
                let cam = Camera::look_at(eye, [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 800.0, 480, 640);
                let drawn = silhouette(&posed.vertices, &rig.mesh.triangles, &cam, 480, 640);
                let mask = Image {
                    width: 480,
                    height: 640,
                    channels: 1,
                    data: drawn.iter().map(|&b| b as u8 as f32).collect(),
                };
                let points: Vec<Keypoint> = if keypoints {
                    crate::keypoints::project_roles(
                        rig,
                        &posed,
                        std::slice::from_ref(&cam),
                        0.0,
                        &mut rand::rng(),
                    )
                    .unwrap()
                    .remove(0)
                } else {
                    Vec::new()
                };
                View::new(rig, &format!("c{k}"), &cam, &mask, &points, 300).unwrap()
            })
            .collect()
    }

    /// The normal equations' `Jᵀr` is the gradient of half the squared residuals (central
    /// differences), for every term: inside, cover, keypoints, prior and smoothness.
    #[test]
    fn the_gradient_matches_finite_differences() {
        let rig = f3g_rig::builtin::load().unwrap().rig;
        let mut truth = rig.zero_params();
        let posture = rig.posture_params().unwrap();
        let mut start = truth.clone();
        for (k, &p) in posture.iter().enumerate() {
            truth.pose[p] = 0.05 * ((k * 37 % 11) as f32 / 11.0 - 0.5);
            start.pose[p] = truth.pose[p] + 0.15 * ((k * 53 % 7) as f32 / 7.0 - 0.5);
        }
        let views = ring(&rig, &truth, true);
        let options = FitOptions::default();
        let columns: Vec<Column> = posture.iter().map(|&p| Column::Pose(p)).collect();
        let neighbours = edge_neighbours(&rig);
        let frame = Frame {
            rig: &rig,
            neighbours: &neighbours,
            views: &views,
            prior_columns: vec![true; columns.len()],
            columns: columns.clone(),
            previous: Some(&truth),
            options: &options,
        };
        let (r, eval) = frame.evaluate(&start).unwrap();
        let (_, jtr) = frame.normal(&start, &eval, &r).unwrap();
        let half_cost = |p: &RigParams| -> f64 {
            frame
                .evaluate(p)
                .unwrap()
                .0
                .iter()
                .map(|v| v * v)
                .sum::<f64>()
                / 2.0
        };
        let scale = (0..columns.len())
            .map(|c| jtr[(c, 0)].abs())
            .fold(0.0, f64::max);
        assert!(scale > 0.0);
        for ci in (0..columns.len()).step_by(7) {
            let h = 2e-3;
            let (mut plus, mut minus) = (start.clone(), start.clone());
            columns[ci].set(&mut plus, columns[ci].get(&start) + h);
            columns[ci].set(&mut minus, columns[ci].get(&start) - h);
            let numeric = (half_cost(&plus) - half_cost(&minus)) / (2.0 * h as f64);
            assert!(
                (numeric - jtr[(ci, 0)]).abs() < 0.05 * scale,
                "column {ci} ({}): analytic {} numeric {numeric} (largest {scale})",
                rig.pose_param_names()[posture[ci]],
                jtr[(ci, 0)]
            );
        }
    }

    /// The first frame, from the rest pose placed in eight views, lands within centimetres of
    /// the pose and shape that drew the masks.
    #[test]
    fn a_frame_is_found_from_the_rest_pose() {
        let rig = f3g_rig::builtin::load().unwrap().rig;
        let mut truth = f3g_rig::choreography::motion(&rig, 1, 0).remove(0);
        truth.identity = f3g_rig::choreography::identity(&rig, 3);
        let views = ring(&rig, &truth, false);
        let fit = fit_frame(&rig, &views, None, &FitOptions::default()).unwrap();
        let (joint, vertex) = errors_against(
            &rig,
            std::slice::from_ref(&fit.params),
            std::slice::from_ref(&truth),
        )
        .unwrap();
        assert!(
            joint < 0.02 && vertex < 0.03 && fit.mean_iou() > 0.93,
            "joint error {joint} m, vertex error {vertex} m, IoU {}",
            fit.mean_iou()
        );
    }

    proptest::proptest! {
        /// The grid's nearest point is the brute-force nearest, for points inside, on the edge
        /// of and beyond the image.
        #[test]
        fn the_grid_finds_the_nearest_point(
            points in proptest::collection::vec((-40.0f32..140.0, -40.0f32..100.0), 1..60),
            queries in proptest::collection::vec((0.0f32..100.0, 0.0f32..60.0), 1..20),
        ) {
            let points: Vec<Vec2> = points.into_iter().map(|(x, y)| Vec2::new(x, y)).collect();
            let grid = PixelGrid::new(&points, 100, 60);
            for (x, y) in queries {
                let q = Vec2::new(x, y);
                let found = points[grid.nearest(&points, q)].distance(q);
                let best = points.iter().map(|p| p.distance(q)).fold(f32::INFINITY, f32::min);
                proptest::prop_assert!((found - best).abs() < 1e-4, "{found} vs {best}");
            }
        }
    }

    #[test]
    fn the_distance_transform_is_exact() {
        let (w, h) = (9, 7);
        let mut inside = vec![false; w * h];
        inside[3 * w + 4] = true;
        inside[w + 1] = true;
        let d = distance_to_mask(&inside, w, h);
        for y in 0..h {
            for x in 0..w {
                let brute = [(4.0f32, 3.0f32), (1.0, 1.0)]
                    .iter()
                    .map(|(a, b)| ((x as f32 - a).powi(2) + (y as f32 - b).powi(2)).sqrt())
                    .fold(f32::INFINITY, f32::min);
                assert!((d[y * w + x] - brute).abs() < 1e-5, "({x}, {y})");
            }
        }
    }

    #[test]
    fn the_cauchy_residual_has_its_derivative() {
        for e in [-0.3f32, -0.01, 0.002, 0.05, 0.4] {
            let h = 1e-4;
            let numeric = (cauchy(e + h, 0.05).0 - cauchy(e - h, 0.05).0) / (2.0 * h);
            assert!((numeric - cauchy(e, 0.05).1).abs() < 1e-2, "{e}");
        }
    }

    #[test]
    fn the_projection_has_its_derivative() {
        let cam = Camera::look_at(
            [0.3, 1.2, 3.0],
            [0.0, 1.0, 0.0],
            [0.0, 1.0, 0.0],
            800.0,
            600,
            800,
        );
        let pin = Pinhole::new(&cam);
        let x = Vec3::new(0.1, 0.9, 0.2);
        let (p, _, d) = pin.project(x).unwrap();
        let expected = cam.project([0.1, 0.9, 0.2]).unwrap().0;
        assert!((p - Vec2::new(expected[0] as f32, expected[1] as f32)).length() < 1e-3);
        for k in 0..3 {
            let h = 1e-3;
            let mut e = Vec3::ZERO;
            e[k] = h;
            let numeric =
                (pin.project(x + e).unwrap().0 - pin.project(x - e).unwrap().0) / (2.0 * h);
            assert!((numeric.x - d[0][k]).abs() < 0.5 && (numeric.y - d[1][k]).abs() < 0.5);
        }
    }
}
