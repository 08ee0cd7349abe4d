//! `f3g synth`: a synthetic multi-view capture of the built-in human, rendered with the
//! triangle rasteriser (not the Gaussian renderer), in the AvatarReX layout, with ground-truth
//! body parameters.
//!
//! - Look: procedural materials evaluated in the body's rest space (so patterns stick to the
//!   skin and cloth): skin with Lambertian + ambient shading under a light fixed in the world;
//!   a shirt with a check pattern, a ring print on the chest and side seams; a knee-length
//!   skirt (loose, skinned to the legs) with stripes, polka dots and seams; hair painted on the
//!   scalp with strand noise; dark brows; red lips; eyes with sclera, iris and pupil; teeth,
//!   tongue and shoes.
//! - Motion: from a still A-pose-like first frame, easing in over four frames: in-place
//!   walking, arm swings, torso and head turns, jaw opening and closing,
//!   blinks (eyelid closure shapes), smiles and brow raises, with seeded phases. The last 20 %
//!   of the frames switch to different poses (arms raised, a wider stance, a head tilt): the
//!   synthetic novel-pose split.
//! - Cameras: a ring (default 16, like AvatarReX) around the subject at 3 m, portrait images
//!   (width = 0.75 × height), configurable elevation, small seeded jitter.
//! - Images are rendered 2× supersampled and box-filtered; masks are the pixel coverage.
//!
//! Everything is deterministic for a seed.

use std::path::Path;

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::DataError;
use crate::calibration::{CaptureCamera, write_calibration};
use crate::dataset::BODY_PARAMS;
use crate::split::SYNTH_MARKER;
use f3g_camera::Camera;
use f3g_io::Image;
use f3g_rig::builtin::BuiltinHuman;
use f3g_rig::{RigParams, Role};
use f3g_template::{Projection, rasterize};

/// Settings of a synthetic capture.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SynthOptions {
    pub cameras: usize,
    pub frames: usize,
    /// Image height in pixels (width is 3/4 of it).
    pub resolution: usize,
    /// Camera elevation above the subject's centre, degrees.
    pub elevation_deg: f32,
    /// Supersampling factor per axis.
    pub supersample: usize,
    pub seed: u64,
}

impl Default for SynthOptions {
    fn default() -> Self {
        Self {
            cameras: 16,
            frames: 40,
            resolution: 768,
            elevation_deg: 8.0,
            supersample: 2,
            seed: 0,
        }
    }
}

impl SynthOptions {
    /// AvatarReX scale: 16 cameras, 1536 × 2048, 2000 frames.
    pub fn paper() -> Self {
        Self {
            cameras: 16,
            frames: 2000,
            resolution: 2048,
            ..Default::default()
        }
    }

    fn validate(&self) -> Result<(), DataError> {
        let bad = |m: &str| Err(DataError::Invalid(m.to_string()));
        if self.cameras == 0 || self.frames == 0 {
            return bad("--cameras and --frames must be at least 1");
        }
        if self.resolution < 32 {
            return bad("--resolution must be at least 32 pixels");
        }
        if !(-60.0..=60.0).contains(&self.elevation_deg) {
            return bad("--elevation must lie in [-60, 60] degrees");
        }
        if self.supersample == 0 || self.supersample > 4 {
            return bad("supersampling must be 1..=4");
        }
        Ok(())
    }
}

/// The ring of cameras.
pub fn ring_cameras(options: &SynthOptions) -> Vec<CaptureCamera> {
    let mut rng = ChaCha8Rng::seed_from_u64(options.seed ^ 0xca3e);
    let height = options.resolution as u32;
    let width = (options.resolution * 3 / 4) as u32;
    let target = Vec3::new(0.0, 0.02, 0.0);
    // The 1.9 m tall view at 3 m fills the image height.
    let focal = 0.5 * height as f64 * 3.0 / 0.98;
    (0..options.cameras)
        .map(|i| {
            let yaw = std::f32::consts::TAU * i as f32 / options.cameras as f32
                + rng.random_range(-0.03..0.03);
            let elevation = (options.elevation_deg + rng.random_range(-2.0..2.0)).to_radians();
            let distance = 3.0 + rng.random_range(-0.1..0.1);
            let eye = target
                + distance
                    * Vec3::new(
                        yaw.sin() * elevation.cos(),
                        elevation.sin(),
                        yaw.cos() * elevation.cos(),
                    );
            let camera = Camera::look_at(
                eye.to_array().map(f64::from),
                target.to_array().map(f64::from),
                [0.0, 1.0, 0.0],
                focal,
                width,
                height,
            );
            CaptureCamera {
                name: format!("cam{i:02}"),
                camera,
            }
        })
        .collect()
}

/// Materials of the look, evaluated at a rest-space point of a part.
struct Look {
    eye_centres: [Vec3; 2],
    light: Vec3,
    parts: Parts,
}

#[derive(Clone, Copy)]
struct Parts {
    eye_l: u8,
    eye_r: u8,
    teeth_upper: u8,
    teeth_lower: u8,
    tongue: u8,
    skirt: u8,
}

fn stripe(x: f32, period: f32, width: f32) -> bool {
    (x / period).rem_euclid(1.0) < width
}

fn mix(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

/// A smooth hash noise in [0, 1) for strand patterns.
fn noise(x: f32, y: f32) -> f32 {
    let h = |i: i32, j: i32| {
        ((i.wrapping_mul(374_761_393) ^ j.wrapping_mul(668_265_263)) as u32)
            .wrapping_mul(2_246_822_519) as f32
            / u32::MAX as f32
    };
    let (i, j) = (x.floor() as i32, y.floor() as i32);
    let (fx, fy) = (x - x.floor(), y - y.floor());
    let (a, b, c, d) = (h(i, j), h(i + 1, j), h(i, j + 1), h(i + 1, j + 1));
    let top = a + (b - a) * fx;
    let bottom = c + (d - c) * fx;
    top + (bottom - top) * fy
}

impl Look {
    fn albedo(&self, part: u8, r: Vec3) -> [f32; 3] {
        const SKIN: [f32; 3] = [0.86, 0.66, 0.54];
        let p = self.parts;
        if part == p.eye_l || part == p.eye_r {
            let centre = self.eye_centres[if part == p.eye_l { 0 } else { 1 }];
            let d = (r - centre).normalize_or_zero();
            let angle = d.z.clamp(-1.0, 1.0).acos();
            return if angle < 0.16 {
                [0.04, 0.03, 0.03]
            } else if angle < 0.38 {
                mix([0.15, 0.35, 0.55], [0.08, 0.2, 0.35], (angle - 0.16) / 0.22)
            } else {
                [0.95, 0.94, 0.92]
            };
        }
        if part == p.teeth_upper || part == p.teeth_lower {
            return [0.93, 0.91, 0.84];
        }
        if part == p.tongue {
            return [0.75, 0.3, 0.32];
        }
        if part == p.skirt {
            // Navy with cream stripes, polka dots and side seams.
            let angle = r.z.atan2(r.x);
            let mut c = [0.1, 0.14, 0.35];
            if stripe(r.y, 0.04, 0.3) {
                c = [0.9, 0.86, 0.72];
            }
            let (u, v) = (angle * 0.2 / 0.03, r.y / 0.03);
            let (du, dv) = (u - u.round(), v - v.round());
            if du * du + dv * dv < 0.08 && !stripe(r.y, 0.04, 0.3) {
                c = [0.85, 0.25, 0.2];
            }
            if (angle.abs() - std::f32::consts::FRAC_PI_2).abs()
                > std::f32::consts::FRAC_PI_2 - 0.03
            {
                c = [0.05, 0.05, 0.08];
            }
            return c;
        }
        // The body: head and face details, hair, shirt, shoes, skin.
        let (x, y, z) = (r.x, r.y, r.z);
        if y > 0.6 {
            let hair =
                (z < -0.01 && y > 0.66) || y > 0.79 || (x.abs() > 0.066 && y > 0.745 && z < 0.07);
            if hair {
                let strands =
                    noise(x * 400.0, y * 25.0) * 0.5 + noise(x * 900.0 + z * 300.0, y * 60.0) * 0.5;
                return mix([0.16, 0.09, 0.05], [0.38, 0.24, 0.12], strands);
            }
            let brow = (0.752..0.761).contains(&y) && (0.012..0.05).contains(&x.abs()) && z > 0.1;
            if brow {
                return [0.2, 0.12, 0.07];
            }
            let lip_half_height = 0.0085 * (1.0 - (x / 0.026).powi(2)).max(0.0).sqrt();
            if x.abs() < 0.026 && (y - 0.676).abs() < lip_half_height && z > 0.12 {
                return [0.72, 0.27, 0.3];
            }
            return SKIN;
        }
        if y < -0.74 {
            return [0.15, 0.12, 0.1];
        }
        // Shirt: torso from the waist to the shoulders and short sleeves.
        let sleeve = y > 0.38 && x.abs() < 0.27;
        if (y > 0.02 && y < 0.56 && x.abs() < 0.19) || sleeve {
            let check = (stripe(x, 0.025, 0.5) ^ stripe(y, 0.025, 0.5)) as u8 as f32;
            let mut c = mix([0.85, 0.55, 0.15], [0.75, 0.42, 0.1], check);
            let chest = Vec3::new(0.0, 0.36, 0.1);
            let d = ((x - chest.x).powi(2) + (y - chest.y).powi(2)).sqrt();
            if z > 0.05 && d < 0.06 && stripe(d, 0.012, 0.45) {
                c = [0.1, 0.35, 0.3];
            }
            if (x.abs() - 0.165).abs() < 0.004 && !sleeve {
                c = [0.4, 0.22, 0.05];
            }
            return c;
        }
        SKIN
    }

    fn shade(&self, albedo: [f32; 3], normal: Vec3) -> [f32; 3] {
        let light = 0.35 + 0.65 * normal.dot(self.light).max(0.0);
        albedo.map(|c| (c * light).min(1.0))
    }
}

/// One rendered view: RGB over a grey background, and the coverage.
fn render_view(
    human: &BuiltinHuman,
    look: &Look,
    posed: &[Vec3],
    normals: &[Vec3],
    camera: &Camera,
    supersample: usize,
) -> (Image, Image) {
    let rig = &human.rig;
    let s = supersample;
    let big = camera.crop_resize(
        0.0,
        0.0,
        s as f64,
        camera.width * s as u32,
        camera.height * s as u32,
    );
    let (bw, bh) = (big.width as usize, big.height as usize);
    let frags = rasterize(
        posed,
        &rig.mesh.triangles,
        &Projection::Pinhole(big),
        bw,
        bh,
        true,
    );
    let (w, h) = (camera.width as usize, camera.height as usize);
    let background = [0.5f32; 3];
    let mut image = Image::filled(w, h, 3, 0.0);
    let mut mask = Image::filled(w, h, 1, 0.0);
    let rows: Vec<(Vec<f32>, Vec<f32>)> = (0..h)
        .into_par_iter()
        .map(|y| {
            let mut rgb_row = vec![0.0f32; 3 * w];
            let mut a_row = vec![0.0f32; w];
            for x in 0..w {
                let mut acc = [0.0f32; 3];
                let mut covered = 0.0f32;
                for sy in 0..s {
                    for sx in 0..s {
                        let p = (y * s + sy) * bw + x * s + sx;
                        let colour = if frags.covered(p) {
                            covered += 1.0;
                            let tri = rig.mesh.triangles[frags.triangle[p] as usize];
                            let b = frags.bary[p];
                            let rest: Vec3 = (0..3)
                                .map(|k| rig.mesh.vertices[tri[k] as usize] * b[k])
                                .sum();
                            let normal: Vec3 = (0..3)
                                .map(|k| normals[tri[k] as usize] * b[k])
                                .sum::<Vec3>()
                                .normalize_or_zero();
                            look.shade(
                                look.albedo(human.vertex_part[tri[0] as usize], rest),
                                normal,
                            )
                        } else {
                            background
                        };
                        for c in 0..3 {
                            acc[c] += colour[c];
                        }
                    }
                }
                let n = (s * s) as f32;
                for c in 0..3 {
                    rgb_row[3 * x + c] = acc[c] / n;
                }
                a_row[x] = covered / n;
            }
            (rgb_row, a_row)
        })
        .collect();
    for (y, (rgb, a)) in rows.into_iter().enumerate() {
        image.data[3 * w * y..3 * w * (y + 1)].copy_from_slice(&rgb);
        mask.data[w * y..w * (y + 1)].copy_from_slice(&a);
    }
    (image, mask)
}

/// The calibration file of a capture (AvatarReX's name).
const CALIBRATION: &str = "calibration_full.json";

/// Whether `dir` already holds a capture (a calibration or body parameters).
pub fn holds_capture(dir: &Path) -> bool {
    dir.join(CALIBRATION).exists() || dir.join(BODY_PARAMS).exists()
}

/// Removes what [`generate`] writes in `dir` (calibration, body parameters, marker and the
/// `camNN` folders) and nothing else; returns how many entries went.
pub fn clear(dir: &Path) -> Result<usize, DataError> {
    Ok(f3g_io::clear_outputs(dir, |name, is_dir| {
        let camera = name.len() > 3
            && name.starts_with("cam")
            && name[3..].chars().all(|c| c.is_ascii_digit());
        (is_dir && camera) || [CALIBRATION, BODY_PARAMS, SYNTH_MARKER].contains(&name)
    })?)
}

/// Writes a synthetic capture of the built-in choreography (`options.frames` frames, seeded)
/// into `out`; `progress` is called after each frame.
pub fn generate(
    out: &Path,
    options: &SynthOptions,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<(), DataError> {
    options.validate()?;
    let rig = &f3g_rig::builtin::load()?.rig;
    let params = f3g_rig::choreography::motion(rig, options.frames, options.seed);
    generate_motion(out, options, &params, None, progress)
}

/// Moves a motion of the built-in human so that its first frame stands where the human stands
/// in its own captures: the root over the ring's centre as at rest, the lowest point of the
/// body on the floor of the rest pose with the first frame's shape. A walk recorded elsewhere
/// in its room, or a skeleton whose origin is on the floor rather than at the pelvis, then
/// starts in view.
pub fn centre_on_ring(rig: &f3g_rig::Rig, frames: &mut [RigParams]) -> Result<(), DataError> {
    let Some(first) = frames.first() else {
        return Ok(());
    };
    let lowest =
        |params: &RigParams| -> Result<f32, DataError> { Ok(rig.pose(params)?.bounds().0.y) };
    let rest = RigParams {
        identity: first.identity.clone(),
        ..rig.zero_params()
    };
    let (root, rest_root) = (
        rig.joint_world(first)?[0].translation,
        rig.joint_world(&rest)?[0].translation,
    );
    let shift = Vec3::new(
        root.x - rest_root.x,
        lowest(first)? - lowest(&rest)?,
        root.z - rest_root.z,
    );
    for f in frames.iter_mut() {
        let t = rig.root_translation(f);
        rig.set_root_translation(f, t - shift)?;
    }
    Ok(())
}

/// Writes a synthetic capture of the built-in human performing `params` (one frame each;
/// `options.frames` is not read) into `out`; `motion` names where the motion came from, for
/// `synth.json`.
pub fn generate_motion(
    out: &Path,
    options: &SynthOptions,
    params: &[RigParams],
    motion: Option<&str>,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<(), DataError> {
    let options = &SynthOptions {
        frames: params.len(),
        ..options.clone()
    };
    options.validate()?;
    let human = f3g_rig::builtin::load()?;
    let rig = &human.rig;
    std::fs::create_dir_all(out).map_err(|e| DataError::file(out, e))?;
    let cameras = ring_cameras(options);
    let part = |n: &str| human.part(n).expect("documented part");
    let rest = rig.skeleton.rest(None);
    let eye = |role| -> Result<Vec3, DataError> { Ok(rest[rig.role(role)?].translation) };
    let look = Look {
        eye_centres: [eye(Role::LeftEye)?, eye(Role::RightEye)?],
        light: Vec3::new(0.3, 0.8, 0.5).normalize(),
        parts: Parts {
            eye_l: part("eye_l"),
            eye_r: part("eye_r"),
            teeth_upper: part("teeth_upper"),
            teeth_lower: part("teeth_lower"),
            tongue: part("tongue"),
            skirt: part("skirt"),
        },
    };
    for c in &cameras {
        let dir = out.join(&c.name).join("mask/pha");
        std::fs::create_dir_all(&dir).map_err(|e| DataError::file(&dir, e))?;
    }
    for (f, p) in params.iter().enumerate() {
        let posed = rig.pose(p)?;
        let normals = rig.vertex_normals(&posed.vertices);
        cameras
            .par_iter()
            .try_for_each(|c| -> Result<(), DataError> {
                let (image, mask) = render_view(
                    &human,
                    &look,
                    &posed.vertices,
                    &normals,
                    &c.camera,
                    options.supersample,
                );
                f3g_io::write_jpeg(&out.join(&c.name).join(format!("{f:08}.jpg")), &image, 95)?;
                f3g_io::write_jpeg(
                    &out.join(&c.name)
                        .join("mask/pha")
                        .join(format!("{f:08}.jpg")),
                    &mask,
                    95,
                )?;
                Ok(())
            })?;
        progress(f + 1);
    }
    write_calibration(&out.join(CALIBRATION), &cameras)?;
    f3g_rig::sequence::write(&out.join(BODY_PARAMS), rig, params)?;
    let meta = serde_json::json!({
        "generator": "f3g synth", "model": "builtin", "options": options, "motion": motion,
    });
    f3g_io::write_atomic(
        &out.join(SYNTH_MARKER),
        serde_json::to_string_pretty(&meta)
            .map_err(|e| DataError::Invalid(e.to_string()))?
            .as_bytes(),
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::crop::{ViewClass, head_facing, view_angle_deg};
    use crate::split::SYNTH_HELD_OUT;

    /// The synthetic split's held-out cameras see the head of the first (still, facing) frame
    /// from the front, the back and the side, in that order.
    #[test]
    fn the_held_out_cameras_see_the_face_from_front_back_and_side() {
        let human = f3g_rig::builtin::load().unwrap();
        let rig = &human.rig;
        let cameras = ring_cameras(&SynthOptions::default());
        let first = &f3g_rig::choreography::motion(rig, 20, 0)[0];
        let posed = rig.pose(first).unwrap();
        let facing = head_facing(rig, &posed).unwrap();
        let h = rig.role(Role::Head).unwrap();
        let head = posed.skinning[h].transform_point3(rig.skeleton.rest(None)[h].translation);
        let classes: Vec<ViewClass> = SYNTH_HELD_OUT
            .iter()
            .map(|&c| ViewClass::of_angle(view_angle_deg(&cameras[c].camera, head, facing)))
            .collect();
        assert_eq!(
            classes,
            [ViewClass::Front, ViewClass::Back, ViewClass::Side]
        );
    }
}
