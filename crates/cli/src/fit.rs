//! `f3g fit` (body parameters from a capture's masks and keypoints) and `f3g data keypoints`
//! (the keypoints a capture's own parameters project to, for testing a fit).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use rand::SeedableRng;
use serde::{Deserialize, Serialize};

use f3g_data::Dataset;
use f3g_data::check::CameraFit;
use f3g_data::fit::Keypoint;
use f3g_data::fit::{FitOptions, FrameFit, fit_frame, frame_views};
use f3g_data::keypoints::{openpose_json, project_roles, read_folder};
use f3g_rig::{ModelSpec, RigParams};

/// Options of `f3g fit`.
#[derive(Args, Debug)]
pub struct FitArgs {
    /// Capture folder (AvatarReX or THuman4.0 layout): calibration, images, masks. A parameter
    /// file it holds is neither read nor touched, except to report the fit's error against it.
    #[arg(long)]
    pub data: PathBuf,
    /// Body model to fit: builtin, smplx:MODEL.npz, mhr:DIR (or any --model spec).
    #[arg(long, default_value = "builtin")]
    pub model: ModelSpec,
    /// Folder of 2D keypoints per camera: OpenPose JSON (<camera>/<frame:08>_keypoints.json)
    /// or COCO keypoints (<camera>.json). None are needed.
    #[arg(long)]
    pub keypoints: Option<PathBuf>,
    /// Output parameter file (f3g's body_params.npz layout). Progress is kept beside it in
    /// <out>.fit.json: running the same command again resumes after the last frame fitted.
    #[arg(long)]
    pub out: PathBuf,
    /// Fit the first N frames (default all).
    #[arg(long, value_parser = crate::bounds::size::<1, 10_000_000>)]
    pub frames: Option<usize>,
    /// Levenberg–Marquardt iterations per stage of a frame (the first frame has four stages), 1–1000.
    #[arg(long, default_value_t = FitOptions::default().iterations, value_parser = crate::bounds::size::<1, 1000>)]
    pub iterations: usize,
    /// Keep the model's template shape instead of fitting one shape for the sequence.
    #[arg(long)]
    pub no_shape: bool,
    /// Also write the per-frame residuals as JSON here (they are in <out>.fit.json too).
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// What `f3g fit` has done, kept beside its output so that a run can resume.
#[derive(Serialize, Deserialize, Debug)]
pub struct FitRecord {
    pub capture: PathBuf,
    pub model: String,
    pub keypoints: Option<PathBuf>,
    pub options: FitOptions,
    pub frames: Vec<FrameRecord>,
    /// Against the capture's own parameters, when it has them for the same model: mean joint
    /// error and mean vertex error, metres, over the frames fitted.
    pub against_capture: Option<Errors>,
}

/// One fitted frame's residuals.
#[derive(Serialize, Deserialize, Debug)]
pub struct FrameRecord {
    pub frame: usize,
    pub mean_iou: f32,
    pub cameras: Vec<CameraFit>,
    pub cost: f64,
    pub seconds: f32,
}

/// A fit's errors against known parameters.
#[derive(Serialize, Deserialize, Debug, Clone, Copy)]
pub struct Errors {
    pub joint_m: f32,
    pub vertex_m: f32,
}

/// `<out>.fit.json`.
fn record_path(out: &Path) -> PathBuf {
    let mut name = out.file_name().unwrap_or_default().to_os_string();
    name.push(".fit.json");
    out.with_file_name(name)
}

pub fn fit(a: &FitArgs) -> Result<()> {
    let rig = a.model.load()?;
    let ds = Dataset::open_unfitted(&a.data, rig.clone(), a.model.to_string())?;
    let frames = a.frames.unwrap_or(ds.frames()).min(ds.frames());
    let options = FitOptions {
        iterations: a.iterations,
        fit_shape: !a.no_shape,
        ..FitOptions::default()
    };
    let names: Vec<String> = ds.cameras.iter().map(|c| c.name.clone()).collect();
    let keypoints = a
        .keypoints
        .as_ref()
        .map(|dir| read_folder(dir, &names, frames))
        .transpose()?;
    let capture = std::fs::canonicalize(&a.data).unwrap_or_else(|_| a.data.clone());
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let record_file = record_path(&a.out);
    let (mut record, mut fitted) = resume(a, &record_file, &capture, &options, &rig)?;
    if fitted.len() >= frames {
        println!(
            "{}: all {frames} frames already fitted (see {})",
            a.out.display(),
            record_file.display()
        );
    }
    let bar = ProgressBar::new(frames as u64).with_style(ProgressStyle::with_template(
        "{bar:30} {pos}/{len} frames, {msg} [{elapsed} < {eta}]",
    )?);
    bar.set_position(fitted.len() as u64);
    // The last frame fitted, as the next one starts from it.
    let mut previous = fitted
        .last()
        .zip(record.frames.last())
        .map(|(params, r)| FrameFit {
            params: params.clone(),
            cameras: Vec::new(),
            cost: r.cost,
        });
    for f in fitted.len()..frames {
        let start = Instant::now();
        let views = frame_views(
            &ds,
            &rig,
            f,
            keypoints.as_ref().map(|k| k[f].as_slice()),
            &options,
        )
        .with_context(|| format!("frame {f}"))?;
        let result = fit_frame(&rig, &views, previous.as_ref(), &options)
            .with_context(|| format!("fitting frame {f}"))?;
        // Later frames start from the last, so they keep the first frame's shape.
        let mean_iou = result.mean_iou();
        fitted.push(result.params.clone());
        record.frames.push(FrameRecord {
            frame: f,
            mean_iou,
            cameras: result.cameras.clone(),
            cost: result.cost,
            seconds: start.elapsed().as_secs_f32(),
        });
        previous = Some(result);
        // The parameters, then the record that says they are there: an interrupted run
        // resumes from what both hold.
        f3g_rig::sequence::write(&a.out, &rig, &fitted)?;
        f3g_io::write_atomic(
            &record_file,
            serde_json::to_string_pretty(&record)?.as_bytes(),
        )?;
        bar.set_message(format!("IoU {mean_iou:.3}"));
        bar.inc(1);
    }
    bar.finish_and_clear();
    record.against_capture = against_capture(&a.data, &a.model, &rig, &fitted)?;
    f3g_io::write_atomic(
        &record_file,
        serde_json::to_string_pretty(&record)?.as_bytes(),
    )?;
    if let Some(path) = &a.json {
        f3g_io::write_atomic(path, serde_json::to_string_pretty(&record)?.as_bytes())?;
    }
    report(&record);
    println!(
        "wrote {} ({} frames of {}) and {}",
        a.out.display(),
        fitted.len(),
        a.model,
        record_file.display()
    );
    Ok(())
}

/// The record and parameters of an earlier run with the same output, capture, model and
/// options, or a fresh start. An output file without a record is not f3g fit's: refused.
fn resume(
    a: &FitArgs,
    record_file: &Path,
    capture: &Path,
    options: &FitOptions,
    rig: &f3g_rig::Rig,
) -> Result<(FitRecord, Vec<RigParams>)> {
    let fresh = FitRecord {
        capture: capture.to_path_buf(),
        model: a.model.to_string(),
        keypoints: a.keypoints.clone(),
        options: options.clone(),
        frames: Vec::new(),
        against_capture: None,
    };
    match (a.out.exists(), record_file.exists()) {
        (false, _) => Ok((fresh, Vec::new())),
        (true, false) => bail!(
            "{} exists and was not written by `f3g fit` (no {} beside it): choose another --out, \
             or move it away",
            a.out.display(),
            record_file.display()
        ),
        (true, true) => {
            let text = std::fs::read_to_string(record_file)
                .with_context(|| format!("reading {}", record_file.display()))?;
            let mut old: FitRecord = serde_json::from_str(&text)
                .with_context(|| format!("{}: not a record of f3g fit", record_file.display()))?;
            if old.capture != fresh.capture
                || old.model != fresh.model
                || old.keypoints != fresh.keypoints
                || old.options != fresh.options
            {
                bail!(
                    "{} holds a fit of {} with model {}, keypoints {:?} and other settings: \
                     choose another --out to fit anew, or rerun with the same settings to resume",
                    a.out.display(),
                    old.capture.display(),
                    old.model,
                    old.keypoints
                );
            }
            let mut params = f3g_rig::sequence::read(&a.out, rig)?;
            let done = params.len().min(old.frames.len());
            params.truncate(done);
            old.frames.truncate(done);
            old.against_capture = None;
            if done > 0 {
                println!("resuming after frame {} of {}", done - 1, a.out.display());
            }
            Ok((old, params))
        }
    }
}

/// The fit's errors against the capture's own parameter file, when it holds one for the same
/// model (a synthetic capture's truth).
fn against_capture(
    capture: &Path,
    model: &ModelSpec,
    rig: &f3g_rig::Rig,
    fitted: &[RigParams],
) -> Result<Option<Errors>> {
    let Ok(ds) = Dataset::open(capture, Some(model)) else {
        return Ok(None);
    };
    if ds.params.len() < fitted.len() || ds.model != model.to_string() {
        return Ok(None);
    }
    let (joint_m, vertex_m) = f3g_data::fit::errors_against(rig, fitted, &ds.params)?;
    Ok(Some(Errors { joint_m, vertex_m }))
}

fn report(record: &FitRecord) {
    let n = record.frames.len().max(1) as f32;
    let iou = record.frames.iter().map(|f| f.mean_iou).sum::<f32>() / n;
    let worst = record
        .frames
        .iter()
        .min_by(|a, b| a.mean_iou.total_cmp(&b.mean_iou));
    println!(
        "{} frames: mean silhouette IoU {iou:.3}{}; {:.1} s per frame",
        record.frames.len(),
        worst
            .map(|w| format!(" (lowest {:.3} at frame {})", w.mean_iou, w.frame))
            .unwrap_or_default(),
        record.frames.iter().map(|f| f.seconds).sum::<f32>() / n
    );
    if let Some(e) = record.against_capture {
        println!(
            "against the capture's own parameters: mean joint error {:.1} cm, mean vertex error {:.1} cm",
            100.0 * e.joint_m,
            100.0 * e.vertex_m
        );
    }
}

/// Options of `f3g data keypoints`.
#[derive(Args, Debug)]
pub struct KeypointsArgs {
    /// Capture folder with body parameters (a synthetic capture's are the truth).
    pub dir: PathBuf,
    #[command(flatten)]
    pub model: crate::data::CaptureModelArg,
    /// Output folder: OpenPose JSON, <camera>/<frame:08>_keypoints.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Pixel noise added to every point (standard deviation per axis, full-resolution pixels).
    #[arg(long, default_value_t = 0.0)]
    pub noise: f32,
    /// Seed of the noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Replace keypoints already in --out.
    #[arg(long)]
    pub overwrite: bool,
}

/// Writes the keypoints a capture's body parameters project to, with noise.
pub fn keypoints(a: &KeypointsArgs) -> Result<()> {
    if !(a.noise.is_finite() && (0.0..=1000.0).contains(&a.noise)) {
        bail!("--noise {}: expected pixels in [0, 1000]", a.noise);
    }
    let ds = Dataset::open(&a.dir, a.model.spec.as_ref())?;
    let rig = ds.rig()?;
    let cameras: Vec<_> = ds.cameras.iter().map(|c| c.camera.clone()).collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(a.seed);
    let mut out = f3g_io::OutputDir::open(&a.out, "data keypoints", a.overwrite)?;
    for (f, params) in ds.params.iter().enumerate() {
        let posed = rig.pose(params)?;
        let seen: Vec<Vec<Keypoint>> = project_roles(rig, &posed, &cameras, a.noise, &mut rng)?;
        for (cam, points) in ds.cameras.iter().zip(seen) {
            let path = out.file(&format!("{}/{f:08}_keypoints.json", cam.name))?;
            f3g_io::write_atomic(&path, openpose_json(&points).as_bytes())?;
        }
    }
    let files = out.finish()?;
    println!(
        "wrote {files} keypoint files ({} frames × {} cameras, noise {} px) to {}",
        ds.frames(),
        ds.cameras.len(),
        a.noise,
        a.out.display()
    );
    Ok(())
}
