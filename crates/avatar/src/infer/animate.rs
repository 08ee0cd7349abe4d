//! Animation: a trained avatar driven by a pose sequence, seen by an orbiting or a fixed
//! camera, written as PNG frames, an animated GIF, an H.264 video (`animation.mp4`) and
//! optionally the posed Gaussians of every frame as 3DGS `.ply` or SPZ files.

use std::path::{Path, PathBuf};

use glam::Vec3;
use serde::Serialize;

use super::eval::EvalAvatar;
use crate::AvatarError;
use f3g_io::Image;
use f3g_rig::{Rig, RigParams};
use f3g_splat::Camera;

/// Where the camera is.
#[derive(Clone, Debug)]
pub enum CameraPath {
    /// Circles the subject `turns` times over the sequence, at `elevation_deg`, keeping the
    /// posed body's centre in view.
    Orbit { turns: f32, elevation_deg: f32 },
    /// One calibrated camera (the `cam.json` format).
    Fixed(Camera),
}

/// Animation settings.
#[derive(Clone, Debug)]
pub struct AnimateOptions {
    pub camera: CameraPath,
    /// Image size of the orbit camera (a fixed camera brings its own).
    pub width: u32,
    pub height: u32,
    pub out: PathBuf,
    /// Write into an `out` that holds files of someone else (same names replaced).
    pub overwrite: bool,
    pub export_ply: bool,
    /// Every frame's posed Gaussians as SPZ too (`spz/frame_NNNNN.spz`: a tenth of the `.ply`,
    /// for sequences on the web).
    pub export_spz: bool,
    /// Frames per second of the GIF.
    pub fps: f32,
    /// Project poses onto the training poses' principal components (unseen poses).
    pub use_pca: bool,
    pub background: [f32; 3],
    /// Draw a floor (a chequered plane at the body's lowest point over the motion), hiding
    /// what goes below it: feet that float or sink show.
    pub floor: bool,
}

/// What was written.
#[derive(Clone, Debug, Serialize)]
pub struct AnimateReport {
    pub frames: usize,
    pub gif: PathBuf,
    pub video: PathBuf,
    pub plys: Vec<PathBuf>,
    pub spzs: Vec<PathBuf>,
    pub seconds_per_frame: f64,
}

/// A motion read for an avatar.
pub struct DrivingMotion {
    pub frames: Vec<RigParams>,
    /// How a motion of another format was retargeted (None for f3g's own sequences).
    pub retargeted: Option<f3g_motion::Retargeted>,
}

/// Reads a motion for the body model `rig`: an f3g sequence of that model (`.npz` naming its
/// model, as `f3g synth` and `f3g rig fit` write, or a `.json` pose) as it is; one of another
/// model (which must load) or any format [`f3g_motion`] reads, retargeted onto `rig` with the
/// shape of `subject` (the avatar's).
pub fn read_motion(
    path: &Path,
    rig: &Rig,
    subject: &RigParams,
    options: &f3g_motion::RetargetOptions,
) -> Result<DrivingMotion, AvatarError> {
    let own = match path.extension().and_then(|e| e.to_str()) {
        Some("json") => true,
        Some("npz") if path.is_file() => f3g_io::Npz::open(path)?.contains("model"),
        _ => false,
    };
    let options = f3g_motion::RetargetOptions {
        identity: subject.identity.clone(),
        ..options.clone()
    };
    // An f3g sequence that does not fit `rig` may be another body model's.
    let (own_frames, other_model) = match own {
        true => match f3g_rig::sequence::read(path, rig) {
            Ok(frames) => (Some(frames), None),
            Err(e) => match f3g_rig::sequence::model_of(path) {
                Ok(model) if model != rig.name => (None, Some(model)),
                _ => return Err(e.into()),
            },
        },
        false => (None, None),
    };
    let (frames, retargeted) = match (own_frames, other_model) {
        (Some(frames), _) => (frames, None),
        (None, Some(model)) => {
            // Another body model's sequence: its joint motion, retargeted.
            let spec: f3g_rig::ModelSpec = model
                .parse()
                .map_err(|e: String| AvatarError::file(path, format!("`model`: {e}")))?;
            let source = spec.load().map_err(|e| {
                AvatarError::file(
                    path,
                    format!("is a motion of the body model `{model}`, which cannot be loaded to retarget it: {e}"),
                )
            })?;
            let frames = f3g_rig::sequence::read(path, &source)?;
            let fps = options.fps.unwrap_or(30.0);
            let motion = f3g_motion::from_rig(&source, &frames, fps)?;
            let mut r = f3g_motion::retarget(&motion, rig, &options, path)?;
            (std::mem::take(&mut r.frames), Some(r))
        }
        (None, None) => {
            let motion = f3g_motion::read(path)?;
            let mut r = f3g_motion::retarget(&motion, rig, &options, path)?;
            (std::mem::take(&mut r.frames), Some(r))
        }
    };
    if frames.is_empty() {
        return Err(AvatarError::file(path, "holds no frames"));
    }
    let expected = (
        rig.num_pose_params(),
        rig.identity.len(),
        rig.expression.len(),
    );
    for (i, p) in frames.iter().enumerate() {
        if (p.pose.len(), p.identity.len(), p.expression.len()) != expected {
            return Err(AvatarError::file(
                path,
                format!("frame {i} does not belong to the body model `{}`", rig.name),
            ));
        }
    }
    Ok(DrivingMotion { frames, retargeted })
}

/// The orbit camera of frame `i` of `n` around `centre`.
pub fn orbit_camera(
    centre: Vec3,
    i: usize,
    n: usize,
    turns: f32,
    elevation_deg: f32,
    width: u32,
    height: u32,
) -> Camera {
    let yaw = std::f32::consts::TAU * turns * i as f32 / n.max(1) as f32;
    let e = elevation_deg.to_radians();
    let distance = 3.0f32;
    let eye = centre + distance * Vec3::new(yaw.sin() * e.cos(), e.sin(), yaw.cos() * e.cos());
    // The 2 m tall view fills ~95 % of the image height.
    let focal = 0.95 * height as f64 * distance as f64 / 2.0;
    Camera::look_at(
        eye.to_array().map(f64::from),
        centre.to_array().map(f64::from),
        [0.0, 1.0, 0.0],
        focal,
        width,
        height,
    )
}

/// Renders `motion` with the avatar of `run_dir`.
pub fn animate(
    avatar: &dyn EvalAvatar,
    motion: &[RigParams],
    options: &AnimateOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<AnimateReport, AvatarError> {
    // The folder's earlier frames that this animation does not write again go at the end.
    let mut out = f3g_io::OutputDir::open(&options.out, "animate", options.overwrite)?;
    let start = std::time::Instant::now();
    let mut images = Vec::new();
    let (mut plys, mut spzs) = (Vec::new(), Vec::new());
    // The posed mesh's bounds of every frame, posed once for what needs them: the orbit
    // camera's centre, the floor (the lowest point over the motion: where the feet stand,
    // retargeted motions putting it on the floor where the source's feet touch theirs).
    let orbit = matches!(options.camera, CameraPath::Orbit { .. });
    let bounds = match orbit || options.floor {
        true => motion
            .iter()
            .map(|p| Ok(avatar.rig().pose(p)?.bounds()))
            .collect::<Result<Vec<_>, AvatarError>>()?,
        false => Vec::new(),
    };
    let floor = options
        .floor
        .then(|| bounds.iter().map(|b| b.0.y).fold(f32::INFINITY, f32::min));
    for (i, params) in motion.iter().enumerate() {
        let camera = match &options.camera {
            CameraPath::Fixed(c) => c.clone(),
            CameraPath::Orbit {
                turns,
                elevation_deg,
            } => {
                let (lo, hi) = bounds[i];
                orbit_camera(
                    0.5 * (lo + hi),
                    i,
                    motion.len(),
                    *turns,
                    *elevation_deg,
                    options.width,
                    options.height,
                )
            }
        };
        let img = match floor {
            Some(height) => over_floor(
                &avatar.render_layers(params, &camera, options.use_pca)?,
                &camera,
                height,
                options.background,
            ),
            None => avatar.render(params, &camera, options.background, options.use_pca)?,
        };
        f3g_io::write_png(&out.file(&format!("frames/frame_{i:05}.png"))?, &img)?;
        if options.export_ply || options.export_spz {
            let cloud = avatar.posed_cloud(params, &camera, options.use_pca)?;
            if options.export_ply {
                let path = out.file(&format!("ply/frame_{i:05}.ply"))?;
                f3g_splat::ply::write_ply(&path, &cloud)?;
                plys.push(path);
            }
            if options.export_spz {
                let path = out.file(&format!("spz/frame_{i:05}.spz"))?;
                f3g_splat::spz::write_spz(&path, &cloud)?;
                spzs.push(path);
            }
        }
        images.push(img);
        progress(i + 1, motion.len());
    }
    let gif = out.file("animation.gif")?;
    write_gif(&gif, &images, options.fps)?;
    let video = out.file("animation.mp4")?;
    super::video::write_mp4(&video, &images, options.fps)?;
    out.finish()?;
    Ok(AnimateReport {
        frames: motion.len(),
        gif,
        video,
        plys,
        spzs,
        seconds_per_frame: start.elapsed().as_secs_f64() / motion.len().max(1) as f64,
    })
}

/// The floor's chequer (metres per square) and its two greys.
const FLOOR_SQUARE: f64 = 0.5;
const FLOOR_GREYS: [f32; 2] = [0.90, 0.82];
/// Distance (metres) over which the floor fades into the background, so its far edge does
/// not alias.
const FLOOR_FADE: f64 = 12.0;

/// `layers` composited over a chequered floor at height `floor` (+Y up), seen by `camera`,
/// and `background` above its horizon: the floor hides what lies behind it (below it, seen
/// from above), so a sinking foot is cut and a floating one shows its gap. Each pixel's floor
/// colour averages 2×2 samples (the chequer's edges).
pub fn over_floor(
    layers: &super::eval::Layers,
    camera: &Camera,
    floor: f32,
    background: [f32; 3],
) -> Image {
    let (w, h) = (layers.color.width, layers.color.height);
    let r = camera.r;
    // Camera centre and world direction of a camera-space ray (x, y, 1).
    let centre: [f64; 3] =
        std::array::from_fn(|i| -(0..3).map(|k| r[k][i] * camera.t[k]).sum::<f64>());
    let to_world = |d: [f64; 3]| -> [f64; 3] {
        std::array::from_fn(|i| (0..3).map(|k| r[k][i] * d[k]).sum::<f64>())
    };
    let (fx, fy, cx, cy) = (
        camera.k[0][0],
        camera.k[1][1],
        camera.k[0][2],
        camera.k[1][2],
    );
    // The floor along the ray through image point (u, v): its depth and colour.
    let floor_at = |u: f64, v: f64| -> Option<(f64, [f32; 3])> {
        let dw = to_world([(u - cx) / fx, (v - cy) / fy, 1.0]);
        let s = (floor as f64 - centre[1]) / dw[1];
        if !(s > 0.0 && dw[1].abs() > 1e-9) {
            return None;
        }
        let (px, pz) = (centre[0] + s * dw[0], centre[2] + s * dw[2]);
        let square = ((px / FLOOR_SQUARE).floor() + (pz / FLOOR_SQUARE).floor()) as i64;
        let grey = FLOOR_GREYS[square.rem_euclid(2) as usize];
        let distance = ((px - centre[0]).powi(2) + (pz - centre[2]).powi(2)).sqrt();
        let fade = (-distance / FLOOR_FADE).exp() as f32;
        Some((s, background.map(|b| b + (grey - b) * fade)))
    };
    let mut out = layers.color.clone();
    for y in 0..h {
        for x in 0..w {
            let (u, v) = (x as f64, y as f64);
            // Depth at the pixel's centre, colour the mean of 2×2 samples (the background
            // where a sample misses the floor).
            let depth = floor_at(u + 0.5, v + 0.5).map_or(f64::INFINITY, |(d, _)| d);
            let mut colour = [0.0f32; 3];
            for (su, sv) in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)] {
                let sample = floor_at(u + su, v + sv).map_or(background, |(_, c)| c);
                for c in 0..3 {
                    colour[c] += 0.25 * sample[c];
                }
            }
            let i = y * w + x;
            let pixel = &mut out.data[3 * i..3 * i + 3];
            if (depth as f32) < layers.depth[i] {
                pixel.copy_from_slice(&colour);
            } else {
                let a = layers.alpha[i];
                for c in 0..3 {
                    pixel[c] += (1.0 - a) * colour[c];
                }
            }
        }
    }
    out
}

/// Writes frames as a looping animated GIF, atomically.
pub fn write_gif(path: &Path, frames: &[Image], fps: f32) -> Result<(), AvatarError> {
    use image::codecs::gif::{GifEncoder, Repeat};
    use image::{Delay, Frame, RgbaImage};
    let mut bytes = Vec::new();
    {
        let mut encoder = GifEncoder::new_with_speed(&mut bytes, 10);
        encoder
            .set_repeat(Repeat::Infinite)
            .map_err(|e| AvatarError::file(path, e))?;
        let delay = Delay::from_numer_denom_ms((1000.0 / fps.max(0.1)) as u32, 1);
        for f in frames {
            let rgba: Vec<u8> = f
                .data
                .chunks_exact(f.channels)
                .flat_map(|p| {
                    let c = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
                    [c(p[0]), c(p[1 % f.channels]), c(p[2 % f.channels]), 255]
                })
                .collect();
            let img =
                RgbaImage::from_raw(f.width as u32, f.height as u32, rgba).expect("sized buffer");
            encoder
                .encode_frame(Frame::from_parts(img, 0, 0, delay))
                .map_err(|e| AvatarError::file(path, e))?;
        }
    }
    Ok(f3g_io::write_atomic(path, &bytes)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::infer::eval::Layers;

    /// 32² layers of one grey `value` at `depth` and `alpha` everywhere.
    fn layers(value: f32, alpha: f32, depth: f32) -> Layers {
        Layers {
            color: Image::from_vec(32, 32, 3, vec![value * alpha; 32 * 32 * 3]).unwrap(),
            alpha: vec![alpha; 32 * 32],
            depth: vec![depth; 32 * 32],
        }
    }

    #[test]
    fn the_floor_hides_what_lies_behind_it_and_shows_under_what_is_transparent() {
        // 1 m above the floor (y = 0), looking down at it 3 m ahead: the bottom rows see the
        // floor about 3 m away, the top rows the sky.
        let camera = Camera::look_at(
            [0.0, 1.0, 3.0],
            [0.0, 0.5, 0.0],
            [0.0, 1.0, 0.0],
            32.0,
            32,
            32,
        );
        let pixel = |img: &Image, x: usize, y: usize| img.data[3 * (y * 32 + x)];
        let sky = [1.0; 3];
        // Nothing drawn: the floor below, the background above.
        let bare = over_floor(&layers(0.0, 0.0, f32::INFINITY), &camera, 0.0, sky);
        let floor = pixel(&bare, 16, 31);
        assert!((0.8..0.95).contains(&floor), "floor grey {floor}");
        assert_eq!(pixel(&bare, 16, 0), 1.0);
        // An opaque body 100 m away is behind the floor where the floor is, in the sky else.
        let far = over_floor(&layers(0.2, 1.0, 100.0), &camera, 0.0, sky);
        assert_eq!(pixel(&far, 16, 31), floor);
        assert_eq!(pixel(&far, 16, 0), 0.2);
        // One 0.5 m away is in front of it everywhere; a half-transparent one lets it through.
        let near = over_floor(&layers(0.2, 1.0, 0.5), &camera, 0.0, sky);
        assert_eq!(pixel(&near, 16, 31), 0.2);
        let half = over_floor(&layers(0.2, 0.5, 0.5), &camera, 0.0, sky);
        assert!((pixel(&half, 16, 31) - (0.1 + 0.5 * floor)).abs() < 1e-6);
    }
}
