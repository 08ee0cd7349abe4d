//! Evaluation on held-out views or poses: body and head PSNR / SSIM / LPIPS.
//!
//! Protocol (Animatable Gaussians' `eval/score.py`, extended with the head):
//! - ground-truth pixels whose mask is ≤ 0.5 are white; the avatar is rendered over white;
//! - **body**: PSNR and SSIM (3DGS convention) on the full image at `scale` × the capture's
//!   resolution; LPIPS on the mask's bounding box padded by 50 px (at full resolution), made
//!   square with white and resized to `lpips_size`;
//! - **head**: the square around the projected head vertices of the frame's posed body model
//!   (padding as in training), cut from the full-resolution image and resized to
//!   `face_size` (default [`DEFAULT_FACE_SIZE`]; shrinking averages each pixel's footprint),
//!   and the avatar rendered with that crop's camera; PSNR, SSIM, LPIPS on it;
//! - novel poses go through the pose PCA (clamped coefficients) as in Animatable Gaussians;
//! - each image's head is classed by the side the camera sees it from
//!   ([`f3g_data::crop::ViewClass`]: front within 45° of the posed head's facing direction,
//!   back beyond 135°, side between), and head metrics are given per class beside the mean;
//!   `comparison.png` shows the frontal head crops first (the most frontal first), then side
//!   and back ones, then bodies; `comparison.mp4` shows every image's body (ground truth |
//!   render | error) in evaluation order.
//!
//! Renders and ground truths are rounded to 8 bits and written as PNG (`images/`: the body
//! image, its LPIPS crop and the head crop, each with `_gt`), and the metrics are computed on
//! exactly those pixels, so anyone can recompute them from the files.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use super::TrainedAvatar;
use super::report::{comparison_row, stack_rows};
use super::video::VideoWriter;
use crate::AvatarError;
use crate::model::host_values;
use f3g_data::Dataset;
use f3g_data::crop::{ViewClass, crop_view, head_box, head_facing, view_angle_deg};
use f3g_data::imgops::{
    CentredSquare, crop_resize, resize, resized_camera, scaled_size, square_image,
};
use f3g_data::split::{Protocol, Split, SplitKind, preset};
use f3g_io::Image;
use f3g_nets::metrics::{image_tensor, psnr, ssim_images, ssim_skimage};
use f3g_nets::{Lpips, LpipsNet};
use f3g_rig::RigParams;
use f3g_splat::Camera;

/// `comparison.mp4`: every evaluated image as ground truth | render | error, in evaluation
/// order, this many a second, at most this wide.
const VIDEO_FPS: f32 = 4.0;
const VIDEO_WIDTH: usize = 1920;

/// Side of the head crops unless asked otherwise: the paper's face resolution, cut from the
/// full-resolution images whatever crop size the avatar was trained with, so runs trained at
/// 128² and 256² are scored on the same pixels.
pub const DEFAULT_FACE_SIZE: usize = 256;

/// What to evaluate and how.
#[derive(Clone, Debug)]
pub struct EvalOptions {
    pub split: SplitKind,
    /// Explicit cameras/frames instead of the split preset.
    pub cameras: Option<Vec<usize>>,
    pub frames: Option<Vec<usize>>,
    /// Every `every`-th frame of the split.
    pub every: usize,
    /// Body images are scored at this fraction of the capture's resolution.
    pub scale: f32,
    pub face_size: usize,
    pub lpips_size: usize,
    pub lpips_net: LpipsNet,
    /// Output folder (default `RUN/eval/<split>`, which is f3g's own: written over freely).
    pub out: Option<PathBuf>,
    /// Write into an `out` that holds files of someone else (same names replaced).
    pub overwrite: bool,
}

/// Scores of one image (LPIPS `None` when the weights are unavailable).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Scores {
    pub psnr: f64,
    /// scikit-image's SSIM (7×7 uniform window), as the paper's evaluation.
    pub ssim: f64,
    /// SSIM as 3DGS computes it (11×11 Gaussian window), for comparison with 3DGS papers.
    pub ssim_3dgs: f64,
    pub lpips: Option<f64>,
    /// Share of the pixels where both the avatar and the ground truth are drawn whose local
    /// colour (the mean over a Gaussian of [`BLOTCH_SIGMA`] pixels of what both draw) is off by
    /// more than [`BLOTCH_ERROR`] in a channel: patches of wrong colour (green and magenta
    /// blotches, a limb shaded wrong under a pose far from training) that a mean hides. The
    /// silhouette's misfit is left out (PSNR has it), and so is high-contrast texture drawn a
    /// pixel or two off (the skirt's stripes), which averages out.
    pub blotched: f64,
}

/// The colour error (of 1) beyond which a pixel counts as blotched.
pub const BLOTCH_ERROR: f32 = 0.3;

/// The standard deviation (pixels) of the Gaussian [`blotched`] averages colours over: at the
/// demo's 512-pixel-tall body images about 7 mm, so that a stripe drawn one pixel off is not a
/// blotch and a patch a few pixels wide is.
pub const BLOTCH_SIGMA: f32 = 2.0;

/// [`Scores::blotched`] of a render against its ground truth (both over white, of one size:
/// eval's scoring checks that with [`psnr`] first).
pub fn blotched(render: &Image, gt: &Image) -> f64 {
    let (width, height) = (render.width, render.height);
    // Drawn: any colour channel visibly below the white background.
    let drawn = |img: &Image, i: usize| {
        img.data[i * img.channels..][..3.min(img.channels)]
            .iter()
            .any(|&v| v < 0.98)
    };
    let both: Vec<f32> = (0..width * height)
        .map(|i| f32::from(u8::from(drawn(render, i) && drawn(gt, i))))
        .collect();
    let shown = both.iter().filter(|&&b| b > 0.0).count();
    if shown == 0 {
        return 0.0;
    }
    // Normalised convolution: the local mean of the colours both images draw, so that neither
    // the background nor the other image's silhouette bleeds into it.
    let weight = smooth(&both, width, height);
    let local = |img: &Image, c: usize| {
        let masked: Vec<f32> = (0..width * height)
            .map(|i| img.data[i * img.channels + c.min(img.channels - 1)] * both[i])
            .collect();
        smooth(&masked, width, height)
    };
    let mut off = vec![false; width * height];
    for c in 0..3 {
        let (r, g) = (local(render, c), local(gt, c));
        for (i, o) in off.iter_mut().enumerate() {
            *o |= both[i] > 0.0 && (r[i] - g[i]).abs() > BLOTCH_ERROR * weight[i];
        }
    }
    off.iter().filter(|&&o| o).count() as f64 / shown as f64
}

/// `values` (`[height, width]`) filtered by a separable Gaussian of [`BLOTCH_SIGMA`] pixels,
/// zero outside the image.
fn smooth(values: &[f32], width: usize, height: usize) -> Vec<f32> {
    let radius = (3.0 * BLOTCH_SIGMA).ceil() as isize;
    let taps: Vec<f32> = (-radius..=radius)
        .map(|d| (-(d * d) as f32 / (2.0 * BLOTCH_SIGMA * BLOTCH_SIGMA)).exp())
        .collect();
    let sum: f32 = taps.iter().sum();
    let taps: Vec<f32> = taps.iter().map(|t| t / sum).collect();
    let pass = |src: &[f32], step: usize, len: usize, lines: usize, stride: usize| {
        let mut out = vec![0.0f32; src.len()];
        for line in 0..lines {
            for x in 0..len {
                let mut acc = 0.0;
                for (k, t) in taps.iter().enumerate() {
                    let s = x as isize + k as isize - radius;
                    if (0..len as isize).contains(&s) {
                        acc += t * src[line * stride + s as usize * step];
                    }
                }
                out[line * stride + x * step] = acc;
            }
        }
        out
    };
    let rows = pass(values, 1, width, height, width);
    pass(&rows, width, height, width, 1)
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ImageScores {
    pub frame: usize,
    pub camera: String,
    pub body: Scores,
    /// `None` when the head is not in view.
    pub head: Option<Scores>,
    /// The side the camera sees the head from, and the angle (degrees) between the head's
    /// facing direction and the direction to the camera.
    pub view: ViewClass,
    pub view_angle_deg: f32,
}

/// Mean head scores of the images of one view class.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewScores {
    pub images: usize,
    #[serde(flatten)]
    pub head: Scores,
}

/// The evaluation report (`metrics.json`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvalReport {
    pub run: PathBuf,
    pub step: u64,
    pub split: SplitKind,
    pub lpips_net: String,
    pub lpips_available: bool,
    pub scale: f32,
    pub face_size: usize,
    pub images: Vec<ImageScores>,
    pub mean_body: Scores,
    pub mean_head: Option<Scores>,
    /// Mean head scores per view class that has images with the head in view.
    pub head_by_view: BTreeMap<ViewClass, ViewScores>,
}

/// A held-out split that names cameras the run trained on (a run trained before the synthetic
/// split held out its frontal camera) would score seen views as novel: refused, unless the
/// cameras were chosen by hand.
fn refuse_training_cameras(
    avatar: &dyn EvalAvatar,
    ds: &Dataset,
    split: &Split,
    options: &EvalOptions,
) -> Result<(), AvatarError> {
    let Some((data, trained)) = avatar.training_views() else {
        return Ok(());
    };
    let same_capture = match (data.canonicalize(), ds.root.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    if options.split == SplitKind::Train || options.cameras.is_some() || !same_capture {
        return Ok(());
    }
    match split.cameras.iter().find(|c| trained.contains(c)) {
        Some(&c) => Err(AvatarError::Invalid(format!(
            "camera {} of the {:?} split is one this run trained on (it was trained with an \
             older split of this capture): retrain the run, or choose held-out cameras with \
             --cameras",
            ds.cameras[c].name, options.split
        ))),
        None => Ok(()),
    }
}

/// Mean of scores (LPIPS only when every image has it).
fn mean(scores: &[&Scores]) -> Option<Scores> {
    if scores.is_empty() {
        return None;
    }
    let n = scores.len() as f64;
    let lpips: Option<Vec<f64>> = scores.iter().map(|s| s.lpips).collect();
    Some(Scores {
        psnr: scores.iter().map(|s| s.psnr).sum::<f64>() / n,
        ssim: scores.iter().map(|s| s.ssim).sum::<f64>() / n,
        ssim_3dgs: scores.iter().map(|s| s.ssim_3dgs).sum::<f64>() / n,
        lpips: lpips.map(|v| v.iter().sum::<f64>() / n),
        blotched: scores.iter().map(|s| s.blotched).sum::<f64>() / n,
    })
}

/// Rounds to 8 bits per channel: renders are scored as the PNG files they are saved as (the
/// reference scores images read back from disk), so the numbers can be recomputed from them.
fn quantise(mut img: Image) -> Image {
    img.data
        .iter_mut()
        .for_each(|v| *v = (v.clamp(0.0, 1.0) * 255.0).round() / 255.0);
    img
}

/// White where the mask is ≤ 0.5 (hard threshold, as the reference evaluation).
fn whiten(image: &Image, mask: &Image) -> Image {
    let mut out = image.clone();
    for (p, rgb) in out.data.chunks_exact_mut(3).enumerate() {
        if mask.data[p] <= 0.5 {
            rgb.fill(1.0);
        }
    }
    out
}

fn lpips_distance(
    lpips: Option<&Lpips>,
    a: &Image,
    b: &Image,
    device: &Device,
) -> Result<Option<f64>, AvatarError> {
    let Some(l) = lpips else { return Ok(None) };
    let v = l.forward(image_tensor(a, device), image_tensor(b, device))?;
    Ok(Some(host_values(v)[0] as f64))
}

fn scores(
    lpips: Option<&Lpips>,
    render: &Image,
    gt: &Image,
    device: &Device,
) -> Result<Scores, AvatarError> {
    Ok(Scores {
        psnr: psnr(render, gt)?,
        ssim: ssim_skimage(render, gt)?,
        ssim_3dgs: ssim_images(render, gt)?,
        lpips: lpips_distance(lpips, render, gt, device)?,
        blotched: blotched(render, gt),
    })
}

/// The smallest head crop (capture pixels a side) that is scored: below it the crop is
/// degenerate (a head far off or a broken avatar), and upsampling it to `face_size` would score
/// a few flat pixels as a head.
const MIN_HEAD_PIXELS: f32 = 8.0;

/// Padding (capture pixels) of the body's LPIPS box (Animatable Gaussians' `eval/score.py`).
const LPIPS_PAD: f32 = 50.0;

/// Host bytes evaluating one image holds, per capture pixel (the image, its mask and the
/// whitened ground truth), per pixel at `--scale` (ground truth, render, the CPU renderer's
/// state, and the eight comparison rows of the grid) and per Gaussian (its render state):
/// upper estimates.
const EVAL_BYTES_PER_CAPTURE_PIXEL: u64 = 32;
const EVAL_BYTES_PER_SCALED_PIXEL: u64 = 420;
const EVAL_BYTES_PER_GAUSSIAN: u64 = 400;

/// Fails before anything is decoded when the largest image of `pairs` at `options.scale`
/// cannot be evaluated in the memory the machine has.
fn ensure_memory(
    ds: &Dataset,
    pairs: &[(usize, usize)],
    gaussians: usize,
    options: &EvalOptions,
) -> Result<(), AvatarError> {
    let Some(camera) = pairs
        .iter()
        .map(|&(c, _)| &ds.cameras[c])
        .max_by_key(|c| c.camera.width as u64 * c.camera.height as u64)
    else {
        return Ok(());
    };
    let (w, h) = (camera.camera.width as usize, camera.camera.height as usize);
    let (sw, sh) = scaled_size(w, h, options.scale);
    let face = (options.face_size * options.face_size) as u64;
    let bytes = (w * h) as u64 * EVAL_BYTES_PER_CAPTURE_PIXEL
        + ((sw * sh) as u64 + face) * EVAL_BYTES_PER_SCALED_PIXEL
        + gaussians as u64 * EVAL_BYTES_PER_GAUSSIAN;
    Ok(f3g_io::memory::ensure_available(
        bytes,
        &format!(
            "evaluating the {w}×{h} images of camera `{}` at --scale {} ({sw}×{sh})",
            camera.name, options.scale
        ),
    )?)
}

/// A render's layers, for compositing over a scene (animate's floor): the colour over black
/// (so premultiplied by coverage), the coverage `1 − T` and the mean camera-space depth along
/// each pixel's ray (`Σ zᵢαᵢTᵢ / α`; infinite where nothing is drawn), row-major.
pub struct Layers {
    pub color: Image,
    pub alpha: Vec<f32>,
    pub depth: Vec<f32>,
}

impl Layers {
    /// From a renderer's outputs: the depth it accumulates weighted by coverage, divided out.
    pub fn new(color: Image, alpha: Vec<f32>, weighted_depth: Vec<f32>) -> Self {
        let depth = weighted_depth
            .iter()
            .zip(&alpha)
            .map(|(d, a)| if *a > 1e-4 { d / a } else { f32::INFINITY })
            .collect();
        Self {
            color,
            alpha,
            depth,
        }
    }
}

/// What evaluation needs of an avatar: the trained networks ([`TrainedAvatar`]) or a baked
/// avatar file ([`super::bake::BakedAvatar`]).
pub trait EvalAvatar {
    /// Renders body parameters; `unseen` says the pose is not a training pose (the networks
    /// then project it onto the training poses' PCA).
    fn render(
        &self,
        params: &RigParams,
        camera: &Camera,
        background: [f32; 3],
        unseen: bool,
    ) -> Result<Image, AvatarError>;
    /// [`Self::render`]'s layers instead of a picture over a background.
    fn render_layers(
        &self,
        params: &RigParams,
        camera: &Camera,
        unseen: bool,
    ) -> Result<Layers, AvatarError>;
    fn gaussian_count(&self) -> usize;
    /// Rig vertices of the head (head crops) and the crops' padding.
    fn head_vertices(&self) -> &[usize];
    fn face_padding(&self) -> f32;
    /// The body model it was trained on, as the capture names it.
    fn model_name(&self) -> &str;
    /// Training step of its networks.
    fn step(&self) -> u64;
    /// Its body model.
    fn rig(&self) -> &f3g_rig::Rig;
    /// The canonical parameters: the subject's shape, which motions from other skeletons are
    /// retargeted onto.
    fn subject(&self) -> &RigParams;
    /// The posed Gaussians of a frame with their colour as seen from `camera` (degree-0
    /// colour, padded to the degree-3 layout), for per-frame `.ply` files.
    fn posed_cloud(
        &self,
        params: &RigParams,
        camera: &Camera,
        unseen: bool,
    ) -> Result<f3g_splat::GaussianCloud, AvatarError>;
    /// The capture and cameras it was trained on, when known (a run; an avatar file does not
    /// record them).
    fn training_views(&self) -> Option<(&Path, &[usize])> {
        None
    }
}

impl EvalAvatar for TrainedAvatar {
    fn training_views(&self) -> Option<(&Path, &[usize])> {
        Some((&self.info.data, &self.info.train_cameras))
    }
    fn render(
        &self,
        params: &RigParams,
        camera: &Camera,
        background: [f32; 3],
        unseen: bool,
    ) -> Result<Image, AvatarError> {
        TrainedAvatar::render(self, params, camera, background, unseen)
    }
    fn render_layers(
        &self,
        params: &RigParams,
        camera: &Camera,
        unseen: bool,
    ) -> Result<Layers, AvatarError> {
        TrainedAvatar::render_layers(self, params, camera, unseen)
    }
    fn gaussian_count(&self) -> usize {
        TrainedAvatar::gaussian_count(self)
    }
    fn head_vertices(&self) -> &[usize] {
        &self.setup.head_vertices
    }
    fn face_padding(&self) -> f32 {
        self.model.face_padding
    }
    fn model_name(&self) -> &str {
        &self.info.model
    }
    fn step(&self) -> u64 {
        self.step
    }
    fn rig(&self) -> &f3g_rig::Rig {
        &self.setup.rig
    }
    fn subject(&self) -> &RigParams {
        &self.setup.template.canonical
    }
    fn posed_cloud(
        &self,
        params: &RigParams,
        camera: &Camera,
        unseen: bool,
    ) -> Result<f3g_splat::GaussianCloud, AvatarError> {
        TrainedAvatar::posed_cloud(self, params, camera, unseen)
    }
}

impl EvalAvatar for super::bake::BakedAvatar {
    fn render(
        &self,
        params: &RigParams,
        camera: &Camera,
        background: [f32; 3],
        _unseen: bool,
    ) -> Result<Image, AvatarError> {
        super::bake::BakedAvatar::render(self, params, camera, background)
    }
    fn render_layers(
        &self,
        params: &RigParams,
        camera: &Camera,
        _unseen: bool,
    ) -> Result<Layers, AvatarError> {
        super::bake::BakedAvatar::render_layers(self, params, camera)
    }
    fn gaussian_count(&self) -> usize {
        self.len()
    }
    fn head_vertices(&self) -> &[usize] {
        &self.head_vertices
    }
    fn face_padding(&self) -> f32 {
        self.face_padding
    }
    fn model_name(&self) -> &str {
        &self.rig.name
    }
    fn step(&self) -> u64 {
        self.step
    }
    fn rig(&self) -> &f3g_rig::Rig {
        &self.rig
    }
    fn subject(&self) -> &RigParams {
        &self.canonical
    }
    fn posed_cloud(
        &self,
        params: &RigParams,
        _camera: &Camera,
        _unseen: bool,
    ) -> Result<f3g_splat::GaussianCloud, AvatarError> {
        Ok(self.posed(params)?.padded_to_degree(3))
    }
}

/// Evaluates the run at `run_dir` on `options.split` of its capture (or of `data`), rendering
/// and scoring LPIPS on `device`.
pub fn evaluate(
    run_dir: &Path,
    data: Option<&Path>,
    model: Option<&f3g_rig::ModelSpec>,
    options: &EvalOptions,
    device: &Device,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<EvalReport, AvatarError> {
    let avatar = TrainedAvatar::load(run_dir, device)?;
    let device = avatar.device().clone();
    let data = data.map_or_else(|| avatar.info.data.clone(), Path::to_path_buf);
    let out = options
        .out
        .clone()
        .unwrap_or_else(|| run_dir.join("eval").join(options.split.to_string()));
    evaluate_avatar(
        &avatar, run_dir, &data, model, options, &out, &device, progress,
    )
}

/// Evaluates `avatar` (read from `source`) on `options.split` of the capture `data`,
/// writing into `out_dir` and scoring LPIPS on `device`.
#[allow(clippy::too_many_arguments)]
pub fn evaluate_avatar(
    avatar: &dyn EvalAvatar,
    source: &Path,
    data: &Path,
    model: Option<&f3g_rig::ModelSpec>,
    options: &EvalOptions,
    out_dir: &Path,
    device: &Device,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<EvalReport, AvatarError> {
    let ds = Dataset::open(data, model)?;
    if ds.model != avatar.model_name() {
        return Err(AvatarError::file(
            data,
            format!(
                "the capture's body model is `{}`, the avatar's `{}`",
                ds.model,
                avatar.model_name()
            ),
        ));
    }
    let split = match (&options.cameras, &options.frames) {
        (Some(c), Some(f)) => Split {
            cameras: c.clone(),
            frames: f.clone(),
        },
        (c, f) => {
            let p = preset(
                Protocol::of(&ds),
                options.split,
                ds.cameras.len(),
                ds.frames(),
            )?;
            Split {
                cameras: c.clone().unwrap_or(p.cameras),
                frames: f.clone().unwrap_or(p.frames),
            }
        }
    };
    refuse_training_cameras(avatar, &ds, &split, options)?;
    let pairs: Vec<(usize, usize)> = split
        .frames
        .iter()
        .step_by(options.every.max(1))
        .flat_map(|&f| split.cameras.iter().map(move |&c| (c, f)))
        .filter(|&(c, f)| ds.has_image(c, f))
        .collect();
    if pairs.is_empty() {
        return Err(AvatarError::Invalid(format!(
            "the {:?} split of {} has no images",
            options.split,
            data.display()
        )));
    }
    ensure_memory(&ds, &pairs, avatar.gaussian_count(), options)?;
    if avatar.head_vertices().is_empty() {
        return Err(AvatarError::file(
            source,
            "names no head vertices, so its head crops cannot be cut: head metrics would be \
             missing",
        ));
    }
    let lpips = Lpips::load(options.lpips_net, device).ok();
    // The images of an earlier evaluation that this one does not write again (other frames or
    // cameras) go at the end.
    let mut out =
        f3g_io::OutputDir::open(out_dir, "eval", options.overwrite || options.out.is_none())?;
    let use_pca = options.split == SplitKind::NovelPose;
    let rig = ds.rig()?;
    let mut images = Vec::new();
    let mut rows = ComparisonRows::default();
    let mut video = VideoWriter::new(VIDEO_FPS).map_err(AvatarError::Invalid)?;
    let mut video_size = None;
    for (i, &(c, f)) in pairs.iter().enumerate() {
        let cam = &ds.cameras[c];
        let full = ds.image(c, f)?;
        let mask = ds.mask(c, f)?;
        let gt_full = quantise(whiten(&full, &mask));
        let params = &ds.params[f];
        // Body: the whole image at `scale`.
        let (w, h) = scaled_size(full.width, full.height, options.scale);
        let camera = resized_camera(&cam.camera, w, h);
        let gt = quantise(whiten(&resize(&full, w, h), &resize(&mask, w, h)));
        let render = quantise(avatar.render(params, &camera, [1.0; 3], use_pca)?);
        let mut body = Scores {
            lpips: None,
            ..scores(None, &render, &gt, device)?
        };
        let pad = (LPIPS_PAD * options.scale).round() as usize;
        if let Some(square) = CentredSquare::around_mask(&resize(&mask, w, h), pad) {
            let lpips_crop = |img: &Image| {
                let sq = square_image(img, &square, &[1.0; 3]);
                quantise(crop_resize(
                    &sq,
                    0.0,
                    0.0,
                    square.side as f32,
                    options.lpips_size,
                    &[1.0; 3],
                ))
            };
            let (a, b) = (lpips_crop(&render), lpips_crop(&gt));
            body.lpips = lpips_distance(lpips.as_ref(), &a, &b, device)?;
            let name = format!("{}_{f:08}_lpips", cam.name);
            f3g_io::write_png(&out.file(&format!("images/{name}.png"))?, &a)?;
            f3g_io::write_png(&out.file(&format!("images/{name}_gt.png"))?, &b)?;
        }
        // Head: the face crop at full resolution.
        let posed = rig.pose(params)?;
        let head_points: Vec<glam::Vec3> = avatar
            .head_vertices()
            .iter()
            .map(|&v| posed.vertices[v])
            .collect();
        let head_centre =
            head_points.iter().copied().sum::<glam::Vec3>() / head_points.len().max(1) as f32;
        let view_angle_deg = view_angle_deg(&cam.camera, head_centre, head_facing(rig, &posed)?);
        let view = ViewClass::of_angle(view_angle_deg);
        let head = match head_box(&cam.camera, &head_points, avatar.face_padding()) {
            Some(b) if b.side < MIN_HEAD_PIXELS => {
                return Err(AvatarError::Invalid(format!(
                    "the head crop of {} at frame {f} is {:.1} pixels wide: too small to score \
                     (at least {MIN_HEAD_PIXELS})",
                    cam.name, b.side
                )));
            }
            Some(b) => {
                let (gt_face, face_cam) =
                    crop_view(&gt_full, &cam.camera, &b, options.face_size, &[1.0; 3]);
                let gt_face = quantise(gt_face);
                let face = quantise(avatar.render(params, &face_cam, [1.0; 3], use_pca)?);
                let s = scores(lpips.as_ref(), &face, &gt_face, device)?;
                let name = format!("{}_{f:08}_head", cam.name);
                f3g_io::write_png(&out.file(&format!("images/{name}.png"))?, &face)?;
                f3g_io::write_png(&out.file(&format!("images/{name}_gt.png"))?, &gt_face)?;
                rows.offer_head(view, view_angle_deg, || comparison_row(&gt_face, &face));
                Some(s)
            }
            None => None,
        };
        let name = format!("{}_{f:08}", cam.name);
        f3g_io::write_png(&out.file(&format!("images/{name}.png"))?, &render)?;
        f3g_io::write_png(&out.file(&format!("images/{name}_gt.png"))?, &gt)?;
        let row = comparison_row(&gt, &render);
        rows.offer_body(|| row.clone());
        let (vw, vh) = *video_size.get_or_insert_with(|| {
            let w = row.width.min(VIDEO_WIDTH);
            (w, (row.height * w / row.width).max(1))
        });
        let row = if (row.width, row.height) == (vw, vh) {
            row
        } else {
            resize(&row, vw, vh)
        };
        video.push(&row).map_err(AvatarError::Invalid)?;
        images.push(ImageScores {
            frame: f,
            camera: cam.name.clone(),
            body,
            head,
            view,
            view_angle_deg,
        });
        progress(i + 1, pairs.len());
    }
    let mean_body = mean(&images.iter().map(|i| &i.body).collect::<Vec<_>>()).expect("≥ 1 image");
    let mean_head = mean(
        &images
            .iter()
            .filter_map(|i| i.head.as_ref())
            .collect::<Vec<_>>(),
    );
    let head_by_view = ViewClass::ALL
        .into_iter()
        .filter_map(|class| {
            let heads: Vec<&Scores> = images
                .iter()
                .filter(|i| i.view == class)
                .filter_map(|i| i.head.as_ref())
                .collect();
            let head = mean(&heads)?;
            Some((
                class,
                ViewScores {
                    images: heads.len(),
                    head,
                },
            ))
        })
        .collect();
    let report = EvalReport {
        run: source.to_path_buf(),
        step: avatar.step(),
        split: options.split,
        lpips_net: options.lpips_net.to_string(),
        lpips_available: lpips.is_some(),
        scale: options.scale,
        face_size: options.face_size,
        images,
        mean_body,
        mean_head,
        head_by_view,
    };
    f3g_io::write_atomic(
        &out.file("metrics.json")?,
        serde_json::to_string_pretty(&report)
            .expect("serialisable")
            .as_bytes(),
    )?;
    f3g_io::write_atomic(&out.file("metrics.md")?, markdown(&report).as_bytes())?;
    let grids = rows.into_rows();
    if !grids.is_empty() {
        f3g_io::write_png(&out.file("comparison.png")?, &stack_rows(&grids))?;
    }
    video.write(&out.file("comparison.mp4")?)?;
    out.finish()?;
    Ok(report)
}

fn fmt_lpips(v: Option<f64>) -> String {
    v.map_or("n/a".into(), |v| format!("{v:.4}"))
}

/// The Markdown table of a report (means, then every image).
pub fn markdown(r: &EvalReport) -> String {
    let mut s = format!(
        "# Evaluation: {:?}, step {}\n\nLPIPS: {}{}; body images at {} × capture resolution, head crops {}².\n\n",
        r.split,
        r.step,
        r.lpips_net,
        if r.lpips_available {
            ""
        } else {
            " (weights not installed: n/a)"
        },
        r.scale,
        r.face_size
    );
    let header = "| PSNR ↑ | SSIM ↑ | LPIPS ↓ | blotched ↓ ";
    let columns = format!("|{}|\n", "---|".repeat(9));
    s += &format!(
        "| {}{}|\n{columns}",
        header.replace("| ", "| body "),
        header.replace("| ", "| head ")
    );
    let cells = |x: Option<&Scores>| -> String {
        x.map_or("– | – | – | –".into(), |x| {
            format!(
                "{:.3} | {:.4} | {} | {:.2} %",
                x.psnr,
                x.ssim,
                fmt_lpips(x.lpips),
                100.0 * x.blotched
            )
        })
    };
    let row = |name: String, b: Option<&Scores>, h: Option<&Scores>| {
        format!("| {name} | {} | {} |\n", cells(b), cells(h))
    };
    s += &row(
        format!("**mean of {}**", r.images.len()),
        Some(&r.mean_body),
        r.mean_head.as_ref(),
    );
    for (class, v) in &r.head_by_view {
        s += &row(
            format!("head seen from the {} ({})", class.name(), v.images),
            None,
            Some(&v.head),
        );
    }
    s += &format!(
        "\n| image (view, angle) {}{}|\n{columns}",
        header.replace("| ", "| body "),
        header.replace("| ", "| head ")
    );
    for i in &r.images {
        s += &row(
            format!(
                "{} / {} ({} {:.0}°)",
                i.camera,
                i.frame,
                i.view.name(),
                i.view_angle_deg
            ),
            Some(&i.body),
            i.head.as_ref(),
        );
    }
    s
}

/// The rows of `comparison.png`, chosen as images are scored so that only those kept are held:
/// head crops by view class (the most frontal first; at most [`HEAD_ROWS`] of each class), then
/// the first [`BODY_ROWS`] bodies.
#[derive(Default)]
struct ComparisonRows {
    heads: Vec<(ViewClass, f32, Image)>,
    bodies: Vec<Image>,
}

/// Head rows kept per view class (front, side, back) and body rows: eight rows at most.
const HEAD_ROWS: [usize; 3] = [3, 2, 1];
const BODY_ROWS: usize = 2;

impl ComparisonRows {
    fn offer_head(&mut self, view: ViewClass, angle: f32, row: impl FnOnce() -> Image) {
        let cap = HEAD_ROWS[view as usize];
        let same: Vec<usize> = (0..self.heads.len())
            .filter(|&i| self.heads[i].0 == view)
            .collect();
        if same.len() < cap {
            self.heads.push((view, angle, row()));
        } else if let Some(&worst) = same
            .iter()
            .max_by(|&&a, &&b| self.heads[a].1.total_cmp(&self.heads[b].1))
            && (view == ViewClass::Front && angle < self.heads[worst].1)
        {
            // Frontal rows keep the most frontal views; the others the first seen.
            self.heads[worst] = (view, angle, row());
        }
    }

    fn offer_body(&mut self, row: impl FnOnce() -> Image) {
        if self.bodies.len() < BODY_ROWS {
            self.bodies.push(row());
        }
    }

    fn into_rows(mut self) -> Vec<Image> {
        self.heads
            .sort_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)));
        self.heads
            .into_iter()
            .map(|(_, _, row)| row)
            .chain(self.bodies)
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `size`² image whose pixel `(x, y)` has the colour `colour(x, y)`.
    fn image(size: usize, colour: impl Fn(usize, usize) -> [f32; 3]) -> Image {
        let data = (0..size * size)
            .flat_map(|i| colour(i % size, i / size))
            .collect();
        Image::from_vec(size, size, 3, data).unwrap()
    }

    #[test]
    fn blotched_counts_patches_of_wrong_colour() {
        let grey = |_, _| [0.5, 0.5, 0.5];
        let gt = image(40, grey);
        assert_eq!(blotched(&gt, &gt), 0.0);
        // A 12×12 green patch: its inside counts, its rim (where the local mean mixes it with
        // the grey around) only in part, nothing else.
        let render = image(40, |x, y| {
            match (10..22).contains(&x) && (10..22).contains(&y) {
                true => [0.5, 1.0, 0.5],
                false => [0.5, 0.5, 0.5],
            }
        });
        let share = blotched(&render, &gt);
        assert!(share > 64.0 / 1600.0 && share < 144.0 / 1600.0, "{share}");
        // The same patch off by 0.2 only: no blotch.
        let faint = image(40, |x, y| {
            match (10..22).contains(&x) && (10..22).contains(&y) {
                true => [0.5, 0.7, 0.5],
                false => [0.5, 0.5, 0.5],
            }
        });
        assert_eq!(blotched(&faint, &gt), 0.0);
    }

    #[test]
    fn stripes_a_pixel_off_and_the_silhouette_are_not_blotches() {
        // Black and white one-pixel stripes, drawn one pixel to the side: every pixel is off by
        // 0.8, but the local colours agree.
        let stripes = |shift: usize| {
            move |x: usize, _| match (x + shift) % 2 {
                0 => [0.1, 0.1, 0.1],
                _ => [0.9, 0.9, 0.9],
            }
        };
        assert!(blotched(&image(40, stripes(1)), &image(40, stripes(0))) < 0.01);
        // A dark ground truth on its left half only, the render dark everywhere: the white
        // background beside the ground truth's silhouette does not bleed into its local mean.
        let half = image(40, |x, _| match x < 20 {
            true => [0.2, 0.2, 0.2],
            false => [1.0, 1.0, 1.0],
        });
        assert_eq!(blotched(&image(40, |_, _| [0.2, 0.2, 0.2]), &half), 0.0);
    }
}
