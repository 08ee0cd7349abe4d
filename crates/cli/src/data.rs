//! `f3g synth` and `f3g data`: make, check and look at captures.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use f3g_data::synth::{SynthOptions, generate, generate_motion};
use f3g_data::{Dataset, check};
use f3g_rig::ModelSpec;
use indicatif::{ProgressBar, ProgressStyle};

/// Render a synthetic multi-view capture of the built-in human (AvatarReX layout).
#[derive(Args, Debug)]
pub struct SynthArgs {
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Number of cameras in the ring (1–256).
    #[arg(long, value_parser = crate::bounds::size::<1, 256>)]
    pub cameras: Option<usize>,
    /// Number of frames (1–100000); with --motion, its first frames (default all).
    #[arg(long, value_parser = crate::bounds::size::<1, 100_000>)]
    pub frames: Option<usize>,
    /// The built-in human performs this motion instead of its own choreography: any file
    /// `--motion` reads elsewhere (an f3g sequence, AMASS .npz, .smpl, BVH, glTF, FBX),
    /// retargeted onto it and moved so that its first frame stands at the ring's centre.
    #[arg(long)]
    pub motion: Option<PathBuf>,
    #[command(flatten)]
    pub retarget: crate::motion::RetargetArgs,
    /// With --motion: resample it to this frame rate (default: the file's).
    #[arg(long, requires = "motion")]
    pub fps: Option<f32>,
    /// Image height in pixels, 16–8192 (width is 3/4 of it).
    #[arg(long, value_parser = crate::bounds::size::<16, 8192>)]
    pub resolution: Option<usize>,
    /// Camera elevation, degrees.
    #[arg(long)]
    pub elevation: Option<f32>,
    /// Samples per pixel along each axis, 1–4 (default 2: each pixel averages 2 × 2).
    #[arg(long, value_parser = crate::bounds::size::<1, 4>)]
    pub supersample: Option<usize>,
    /// Seed of the person's shape (with --motion too), the motion and the camera jitter.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// `paper`: AvatarReX scale (16 cameras, 1536×2048, 2000 frames); defaults otherwise
    /// (16 cameras, 576×768, 40 frames).
    #[arg(long)]
    pub preset: Option<String>,
    /// Replace the capture already in `--out` (its camera folders, calibration and body
    /// parameters; nothing else there is touched). Without it such a folder is refused.
    #[arg(long)]
    pub overwrite: bool,
}

/// The frames of `--motion` for the built-in human: retargeted onto the person `--seed` draws
/// (the shape `f3g synth --seed` renders; a sequence of the built-in human's own takes it too),
/// cut to `--frames`, centred.
fn synth_motion(path: &Path, a: &SynthArgs) -> Result<Vec<f3g_rig::RigParams>> {
    if let Some(fps) = a.fps
        && !(fps.is_finite() && fps > 0.0 && fps <= 1000.0)
    {
        bail!("--fps {fps}: expected a rate in (0, 1000]");
    }
    let rig = &f3g_rig::builtin::load()?.rig;
    let person = f3g_rig::RigParams {
        identity: f3g_rig::choreography::identity(rig, a.seed),
        ..rig.zero_params()
    };
    let read =
        f3g_avatar::infer::animate::read_motion(path, rig, &person, &a.retarget.options(a.fps)?)?;
    if let Some(r) = &read.retargeted {
        eprintln!("{}", crate::motion::describe(path, r, read.frames.len()));
    }
    let mut frames = read.frames;
    frames.truncate(a.frames.unwrap_or(usize::MAX));
    for frame in &mut frames {
        frame.identity.clone_from(&person.identity);
    }
    if frames.is_empty() {
        bail!("{}: the motion has no frames", path.display());
    }
    f3g_data::synth::centre_on_ring(rig, &mut frames)?;
    Ok(frames)
}

pub fn synth(a: &SynthArgs) -> Result<()> {
    let mut options = match a.preset.as_deref() {
        None => SynthOptions::default(),
        Some("paper") => SynthOptions::paper(),
        Some(other) => bail!("unknown --preset `{other}`: the only preset is `paper`"),
    };
    options.cameras = a.cameras.unwrap_or(options.cameras);
    options.frames = a.frames.unwrap_or(options.frames);
    options.resolution = a.resolution.unwrap_or(options.resolution);
    options.elevation_deg = a.elevation.unwrap_or(options.elevation_deg);
    options.supersample = a.supersample.unwrap_or(options.supersample);
    options.seed = a.seed;
    // Refused before the motion is read; an old capture is cleared only once it has been.
    let replaces = f3g_data::synth::holds_capture(&a.out);
    if replaces && !a.overwrite {
        bail!(
            "{} already holds a capture: pass --overwrite to replace it, or choose another --out",
            a.out.display()
        );
    }
    let motion = match &a.motion {
        Some(path) => {
            let frames = synth_motion(path, a)?;
            options.frames = frames.len();
            Some(frames)
        }
        None => None,
    };
    if replaces {
        f3g_data::synth::clear(&a.out)?;
    }
    let bar = ProgressBar::new(options.frames as u64).with_style(ProgressStyle::with_template(
        "{bar:30} {pos}/{len} frames × {msg} [{elapsed} < {eta}]",
    )?);
    bar.set_message(format!("{} cameras", options.cameras));
    let start = std::time::Instant::now();
    match &motion {
        Some(frames) => generate_motion(
            &a.out,
            &options,
            frames,
            a.motion.as_deref().map(|p| p.to_string_lossy()).as_deref(),
            &|f| bar.set_position(f as u64),
        )?,
        None => generate(&a.out, &options, &|f| bar.set_position(f as u64))?,
    }
    bar.finish_and_clear();
    println!(
        "wrote {} frames × {} cameras at {}×{} to {} in {:.1} s",
        options.frames,
        options.cameras,
        options.resolution * 3 / 4,
        options.resolution,
        a.out.display(),
        start.elapsed().as_secs_f32()
    );
    Ok(())
}

/// Captures.
/// `--model`: the body model of a capture that names none itself (an `smpl_params.npz`
/// needs the SMPL-X model file), flattened into every command that opens a capture.
#[derive(Args, Debug, Clone, Default)]
pub struct CaptureModelArg {
    /// Body model for captures with smpl_params.npz (smplx:MODEL.npz).
    #[arg(id = "model", long = "model")]
    pub spec: Option<ModelSpec>,
}

#[derive(Subcommand, Debug)]
pub enum DataCommand {
    /// Validate a capture: cameras, image and mask sizes, decodability, body parameters, and
    /// how well the posed body model lies on every camera's masks.
    Check(CheckArgs),
    /// Write a contact sheet of all cameras of one frame with the face boxes drawn (and, with
    /// --overlay, the posed body model's outline and its agreement with the masks).
    Show(ShowArgs),
    /// Write the 2D keypoints (OpenPose JSON) a capture's own body parameters project to, with
    /// pixel noise: a test of `f3g fit --keypoints` on a synthetic capture.
    Keypoints(crate::fit::KeypointsArgs),
}

/// Options of `f3g data check`.
#[derive(Args, Debug)]
pub struct CheckArgs {
    /// Capture folder.
    pub dir: PathBuf,
    #[command(flatten)]
    pub model: CaptureModelArg,
    /// Decode every N-th frame fully (1 decodes everything; headers are always checked).
    #[arg(long, default_value_t = 10)]
    pub decode_every: usize,
    /// Also write the report as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// Options of `f3g data show`.
#[derive(Args, Debug)]
pub struct ShowArgs {
    /// Capture folder.
    pub dir: PathBuf,
    /// Frame to show.
    #[arg(long, default_value_t = 0)]
    pub frame: usize,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub model: CaptureModelArg,
    /// Width of each camera's thumbnail (8–2048).
    #[arg(long, default_value_t = 256, value_parser = crate::bounds::size::<8, 2048>)]
    pub thumb: usize,
    /// Draw the posed body model's outline over every image, with its IoU against the mask
    /// and the share of it inside the mask (red: below 0.9, a camera to look at).
    #[arg(long)]
    pub overlay: bool,
}

/// Prints the body model's agreement with each camera's masks.
fn print_fits(fits: &[check::CameraFit]) {
    if fits.is_empty() {
        return;
    }
    println!("camera     frames  IoU    body in mask");
    for f in fits {
        println!(
            "{:<10} {:>6}  {:.3}  {:.3}{}",
            f.camera,
            f.frames,
            f.iou,
            f.body_in_mask,
            if f.flagged { "  flagged" } else { "" }
        );
    }
}

pub fn run(cmd: &DataCommand) -> Result<()> {
    match cmd {
        DataCommand::Check(a) => {
            let ds = Dataset::open(&a.dir, a.model.spec.as_ref())?;
            let r = check::check(&ds, a.decode_every);
            println!(
                "{}: {} layout, model {}, {} cameras, {} frames; {} images present ({} decoded), {} missing",
                a.dir.display(),
                r.layout,
                r.model,
                r.cameras,
                r.frames,
                r.images_present,
                r.images_decoded,
                r.images_missing
            );
            print_fits(&r.silhouettes);
            for w in &r.warnings {
                println!("warning: {w}");
            }
            for e in r.errors.iter().take(20) {
                println!("error: {e}");
            }
            if let Some(path) = &a.json {
                f3g_io::write_atomic(path, serde_json::to_string_pretty(&r)?.as_bytes())?;
            }
            if !r.errors.is_empty() {
                bail!("{} problems found (first 20 shown)", r.errors.len());
            }
            println!("ok");
            Ok(())
        }
        DataCommand::Keypoints(a) => crate::fit::keypoints(a),
        DataCommand::Show(a) => {
            let ds = Dataset::open(&a.dir, a.model.spec.as_ref())?;
            let (sheet, fits) = check::contact_sheet(&ds, a.frame, a.thumb, 1.3, a.overlay)
                .with_context(|| format!("drawing frame {}", a.frame))?;
            print_fits(&fits);
            f3g_io::write_png(&a.out, &sheet)?;
            println!("wrote {}", a.out.display());
            Ok(())
        }
    }
}
