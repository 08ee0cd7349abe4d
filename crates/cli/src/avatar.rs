//! `f3g train`, `f3g eval`, `f3g animate` and `f3g export-ply`: train an avatar (or resume a
//! run), measure it on held-out views and poses, drive it with new poses, export it.

use std::path::PathBuf;
use std::sync::atomic::Ordering;

use anyhow::{Context, Result};
use clap::Args;
use f3g_avatar::infer::animate::{AnimateOptions, CameraPath};
use f3g_avatar::infer::eval::EvalOptions;
use f3g_avatar::model::TemplateChoice;

use crate::device::{DeviceArg, DeviceSpec};
use f3g_avatar::infer::TrainedAvatar;
use f3g_avatar::infer::export::{ExportOptions, Up, export_cloud};
use f3g_avatar::train::AllReduce;
use f3g_avatar::train::{Outcome, StepReport, TrainConfig, Trainer};
use f3g_data::split::{SplitKind, parse_indices};
use f3g_nets::LpipsNet;

use crate::data::CaptureModelArg;
use indicatif::{ProgressBar, ProgressStyle};

/// Options of `f3g train`.
#[derive(Args, Debug, Clone)]
pub struct TrainArgs {
    /// Capture folder (AvatarReX or THuman4.0 layout, or one made by `f3g synth`).
    #[arg(long, required_unless_present = "resume")]
    pub data: Option<PathBuf>,
    /// Run folder to create.
    #[arg(long, required_unless_present = "resume")]
    pub out: Option<PathBuf>,
    /// Resume the run in this folder from its newest checkpoint (its configuration is the
    /// run's: no flag that changes it).
    #[arg(long, conflicts_with_all = ["data", "out", "config", "preset", "set", "AblationArgs", "seed"])]
    pub resume: Option<PathBuf>,
    #[command(flatten)]
    pub config: ConfigArgs,
    #[command(flatten)]
    pub model: CaptureModelArg,
    /// Training cameras (`0,1,5` or `A..B`), instead of the capture's preset.
    #[arg(long)]
    pub cameras: Option<String>,
    /// Training frames (`A..B` or a list), instead of the capture's preset.
    #[arg(long)]
    pub frames: Option<String>,
    #[command(flatten)]
    pub ablation: AblationArgs,
    /// Seed of the weights, the samples and every random choice.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Stop after this many steps of this invocation (a checkpoint is written), e.g. to
    /// split training into sessions.
    #[arg(long)]
    pub max_steps: Option<u64>,
    #[command(flatten)]
    pub device: DeviceArg,
    /// Data-parallel training on several devices, e.g. `cuda:0,cuda:1`: each step draws one
    /// sample per device and applies the mean of their gradients (instead of --device).
    /// `cpu,cpu` runs two replicas on the CPU, which tests the path without GPUs.
    #[arg(long, value_delimiter = ',', conflicts_with = "device")]
    pub devices: Vec<DeviceSpec>,
}

/// The ablation flags of `f3g train`, each setting fields of the configuration.
#[derive(Args, Debug, Clone, Default)]
pub struct AblationArgs {
    /// Ablation: no face branch — no face networks and no face-crop losses (body Gaussians
    /// and body losses only; same number of steps).
    #[arg(long)]
    pub no_face_branch: bool,
    /// Ablation: no face networks, but the face-crop losses (L1, LPIPS, adversarial) train the
    /// body Gaussians.
    #[arg(long, conflicts_with = "no_face_branch")]
    pub no_face_networks: bool,
    /// Ablation: no adversarial face loss.
    #[arg(long)]
    pub no_adversarial: bool,
    /// Ablation: canonical template, `body` (the body model's surface) or `clothed` (with
    /// the capture's garment).
    #[arg(long)]
    pub template: Option<TemplateChoice>,
    /// Ablation: input (= output) resolution of the face networks.
    #[arg(long)]
    pub face_input: Option<usize>,
    /// Ablation: channel multiplier of the face networks.
    #[arg(long)]
    pub face_cm: Option<usize>,
    /// Ablation: depth of the face networks' mapping network.
    #[arg(long)]
    pub face_n_mlp: Option<usize>,
}

impl AblationArgs {
    /// Sets the configuration's fields the flags name (checked with the rest of the
    /// configuration by [`ConfigArgs::load`]).
    pub fn apply(&self, config: &mut TrainConfig) {
        if self.no_face_branch {
            config.model.face_branch = false;
            config.face_losses = false;
        }
        if self.no_face_networks {
            config.model.face_branch = false;
        }
        if self.no_adversarial {
            config.adversarial = false;
        }
        if let Some(template) = &self.template {
            config.model.template = template.clone();
        }
        let face_net = &mut config.model.face_net;
        if let Some(side) = self.face_input {
            face_net.input_size = side;
            face_net.output_size = side;
        }
        if let Some(multiplier) = self.face_cm {
            face_net.channel_multiplier = multiplier;
        }
        if let Some(depth) = self.face_n_mlp {
            face_net.n_mlp = depth;
        }
    }
}

/// `--config`, `--preset` and `--set`: a training configuration from the command line
/// (flattened into `train` and `bench train`).
#[derive(Args, Debug, Clone, Default)]
pub struct ConfigArgs {
    /// Configuration file (JSON; any subset of the keys, over the preset it names).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Preset when no config file is given: cpu (the demo's), cpu-long (`f3g demo --quality`)
    /// or paper (AvatarReX scale).
    #[arg(long, default_value = "cpu")]
    pub preset: String,
    /// Override a configuration key, e.g. `--set steps.joint=500` (repeatable; over the
    /// preset, the file and the other flags).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
}

impl ConfigArgs {
    /// The file's or the preset's configuration, changed by `flags` (the command's own flags)
    /// and then by `--set`, checked.
    pub fn load(&self, flags: impl FnOnce(&mut TrainConfig)) -> Result<TrainConfig> {
        let mut config = match &self.config {
            Some(path) => TrainConfig::from_file(path)?,
            None => TrainConfig::preset(&self.preset)?,
        };
        flags(&mut config);
        Ok(config.with_overrides(&self.set)?)
    }
}

/// The devices `--device` or `--devices` names, created.
fn training_devices(a: &TrainArgs) -> Result<Vec<burn::tensor::Device>> {
    if a.devices.is_empty() {
        return Ok(vec![a.device.open()?]);
    }
    a.devices.iter().map(|d| d.open()).collect()
}

/// The configuration of a new run: the flags of `a`, then `adjust` (a caller's own settings),
/// then `--set`.
fn config_of(a: &TrainArgs, adjust: impl FnOnce(&mut TrainConfig)) -> Result<TrainConfig> {
    a.config.load(|config| {
        a.ablation.apply(config);
        if let Some(seed) = a.seed {
            config.seed = seed;
        }
        adjust(config);
    })
}

pub fn train(a: &TrainArgs) -> Result<PathBuf> {
    train_with(a, |_| {})
}

/// `f3g train` with `adjust` changing a new run's configuration after the flags (what
/// `f3g demo` and `f3g bench quality` set); returns the run folder.
pub fn train_with(a: &TrainArgs, adjust: impl FnOnce(&mut TrainConfig)) -> Result<PathBuf> {
    let devices = training_devices(a)?;
    let mut trainer = match &a.resume {
        Some(dir) => Trainer::resume(dir, a.model.spec.as_ref(), &devices)
            .with_context(|| format!("resuming {}", dir.display()))?,
        None => {
            let data = a.data.as_ref().context("--data is required")?;
            let out = a.out.as_ref().context("--out is required")?;
            let config = config_of(a, adjust)?;
            let ds_probe = f3g_data::Dataset::open(data, a.model.spec.as_ref())?;
            let cameras = a
                .cameras
                .as_deref()
                .map(|t| parse_indices(t, ds_probe.cameras.len(), "--cameras"))
                .transpose()?;
            let frames = a
                .frames
                .as_deref()
                .map(|t| parse_indices(t, ds_probe.frames(), "--frames"))
                .transpose()?;
            drop(ds_probe);
            Trainer::create(
                out,
                data,
                a.model.spec.as_ref(),
                config,
                cameras.as_deref(),
                frames.as_deref(),
                &devices,
            )?
        }
    };
    if a.devices.len() > 1 {
        let how = crate::device::all_reduce_for(&a.devices);
        trainer.set_all_reduce(how);
        println!(
            "{} replicas; gradients summed {}",
            a.devices.len(),
            match how {
                AllReduce::Collective => "with NCCL",
                AllReduce::Host => "through the first device",
            }
        );
    }
    let run_dir = trainer.run_dir().to_path_buf();
    let total = trainer.total_steps();
    println!(
        "training {} ({} body + {} face Gaussians, preset {}) on {} cameras × {} frames; {} of {} steps done",
        run_dir.display(),
        trainer.setup().body_count(),
        trainer.setup().face_count(),
        trainer.config().preset,
        trainer.split().cameras.len(),
        trainer.split().frames.len(),
        trainer.step(),
        total
    );
    let bar = ProgressBar::new(total).with_style(ProgressStyle::with_template(
        "{bar:30} {pos}/{len} {msg} [{per_sec} · {elapsed} < {eta}]",
    )?);
    bar.set_position(trainer.step());
    // An interrupt stops the trainer at the end of its step, with a checkpoint.
    let graceful = crate::interrupt::GracefulStop::new();
    let stop = graceful.flag();
    let limit = a.max_steps.map(|m| trainer.step() + m);
    let mut on_step = |r: &StepReport| {
        bar.set_position(r.step + 1);
        bar.set_message(format!("{:?} loss {:.4}", r.stage, r.total));
        if limit.is_some_and(|l| r.step + 1 >= l) {
            stop.store(true, Ordering::Relaxed);
        }
    };
    let outcome = trainer.train(stop, &mut on_step)?;
    bar.finish_and_clear();
    match outcome {
        Outcome::Finished => println!(
            "finished {} steps; loss curve {}, validation {}",
            total,
            run_dir.join("loss.png").display(),
            run_dir.join("validation.png").display()
        ),
        Outcome::Stopped => println!(
            "stopped at step {}; checkpoint written — continue with `f3g train --resume {}`",
            trainer.step(),
            run_dir.display()
        ),
    }
    Ok(run_dir)
}

/// Options of `f3g eval`.
#[derive(Args, Debug, Clone)]
pub struct EvalArgs {
    /// The avatar: a run folder, or a baked avatar file (a path ending in `.glb`, from
    /// `f3g export-avatar`; it does not name its capture, so give --data).
    #[arg(value_name = "RUN|AVATAR.glb")]
    pub run: PathBuf,
    /// Split: novel-view, novel-pose or train.
    #[arg(long, default_value = "novel-view")]
    pub split: SplitKind,
    /// Capture folder (default: the run's; required for an avatar file).
    #[arg(long)]
    pub data: Option<PathBuf>,
    #[command(flatten)]
    pub model: CaptureModelArg,
    /// Cameras to evaluate instead of the split's.
    #[arg(long)]
    pub cameras: Option<String>,
    /// Frames to evaluate instead of the split's.
    #[arg(long)]
    pub frames: Option<String>,
    /// Evaluate every N-th frame.
    #[arg(long, default_value_t = 1)]
    pub every: usize,
    /// Body images at this fraction of the capture's resolution, 0.01–4 (default: the run's
    /// `body_scale`, 1 for an avatar file; 1 is the paper's protocol).
    #[arg(long, value_parser = crate::bounds::eval_scale)]
    pub scale: Option<f32>,
    /// Side of the head crops, 32–2048, cut from the full-resolution images (default 256,
    /// the paper's face resolution, whatever the training crops were).
    #[arg(long, default_value_t = f3g_avatar::infer::eval::DEFAULT_FACE_SIZE, value_parser = crate::bounds::size::<32, 2048>)]
    pub face_size: usize,
    /// Side the body's LPIPS square is resized to, 32–2048 (512: the paper's protocol).
    #[arg(long, default_value_t = 512, value_parser = crate::bounds::size::<32, 2048>)]
    pub lpips_size: usize,
    /// LPIPS backbone (default: the run's training one; alex for an avatar file).
    #[arg(long)]
    pub lpips: Option<LpipsNet>,
    /// Output folder (default RUN/eval/<split>, or AVATAR.eval/<split> beside an avatar file):
    /// new, empty, or an earlier evaluation's.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write into an --out that holds other files (those of the same names are replaced,
    /// nothing else is removed).
    #[arg(long)]
    pub overwrite: bool,
    #[command(flatten)]
    pub device: DeviceArg,
}

pub fn eval(a: &EvalArgs) -> Result<f3g_avatar::infer::eval::EvalReport> {
    // A baked avatar file, or a run folder.
    let baked = if a.run.extension().is_some_and(|e| e == "glb") {
        Some(f3g_avatar::infer::avatar_file::read(&a.run)?)
    } else {
        None
    };
    let (data, scale, lpips_net, out) = match &baked {
        Some(_) => (
            a.data.clone().with_context(|| {
                format!(
                    "{}: an avatar file does not name its capture; give --data",
                    a.run.display()
                )
            })?,
            a.scale.unwrap_or(1.0),
            a.lpips.unwrap_or(LpipsNet::Alex),
            a.out
                .clone()
                .unwrap_or_else(|| a.run.with_extension("eval").join(a.split.to_string())),
        ),
        None => {
            let config = f3g_avatar::infer::Run::new(&a.run).config()?;
            let info = f3g_avatar::infer::Run::new(&a.run).info()?;
            (
                a.data.clone().unwrap_or(info.data),
                a.scale.unwrap_or(config.body_scale),
                a.lpips.unwrap_or(config.lpips_net),
                a.out
                    .clone()
                    .unwrap_or_else(|| a.run.join("eval").join(a.split.to_string())),
            )
        }
    };
    let (mut cameras, mut frames) = (None, None);
    if a.cameras.is_some() || a.frames.is_some() {
        let ds = f3g_data::Dataset::open(&data, a.model.spec.as_ref())?;
        cameras = a
            .cameras
            .as_deref()
            .map(|t| parse_indices(t, ds.cameras.len(), "--cameras"))
            .transpose()?;
        frames = a
            .frames
            .as_deref()
            .map(|t| parse_indices(t, ds.frames(), "--frames"))
            .transpose()?;
    }
    let options = EvalOptions {
        split: a.split,
        cameras,
        frames,
        every: a.every,
        scale,
        face_size: a.face_size,
        lpips_size: a.lpips_size,
        lpips_net,
        out: Some(out.clone()),
        // The default folder is f3g's own, beside the run or avatar file.
        overwrite: a.overwrite || a.out.is_none(),
    };
    let bar = ProgressBar::new(0).with_style(ProgressStyle::with_template(
        "{bar:30} {pos}/{len} images [{elapsed} < {eta}]",
    )?);
    let device = a.device.open()?;
    let mut progress = |i: usize, n: usize| {
        bar.set_length(n as u64);
        bar.set_position(i as u64);
    };
    let report = match &baked {
        Some(b) => f3g_avatar::infer::eval::evaluate_avatar(
            b,
            &a.run,
            &data,
            a.model.spec.as_ref(),
            &options,
            &out,
            &device,
            &mut progress,
        )?,
        None => {
            let avatar = TrainedAvatar::load(&a.run, &device)?;
            f3g_avatar::infer::eval::evaluate_avatar(
                &avatar,
                &a.run,
                &data,
                a.model.spec.as_ref(),
                &options,
                &out,
                avatar.device(),
                &mut progress,
            )?
        }
    };
    bar.finish_and_clear();
    // The header and the means (whole and per view class), not the per-image table.
    let markdown = f3g_avatar::infer::eval::markdown(&report);
    print!(
        "{}",
        markdown.split("\n\n| image").next().unwrap_or(&markdown)
    );
    println!("\n\nwrote {}", out.join("metrics.json").display());
    Ok(report)
}

/// Options of `f3g animate`.
#[derive(Args, Debug, Clone)]
pub struct AnimateArgs {
    /// The avatar: a run folder (rendered with its networks), or a baked avatar file (a path
    /// ending in `.glb`, from `f3g export-avatar`: its Gaussians, skin and correctives).
    #[arg(value_name = "RUN|AVATAR.glb")]
    pub run: PathBuf,
    /// Motion: an f3g sequence (e.g. a capture's body_params.npz), or AMASS .npz, .smpl,
    /// smpl_params.npz, BVH, glTF or FBX, retargeted onto the avatar and resampled to --fps.
    #[arg(long)]
    pub motion: PathBuf,
    #[command(flatten)]
    pub retarget: crate::motion::RetargetArgs,
    #[command(flatten)]
    pub frames: crate::motion::FramesArg,
    /// `orbit`, or a camera JSON (`f3g render-ply`'s cam.json format).
    #[arg(long, default_value = "orbit")]
    pub camera: String,
    /// Output folder: new, empty, or an earlier animation's (whose frames it replaces).
    #[arg(long)]
    pub out: PathBuf,
    /// Write into an --out that holds other files (those of the same names are replaced,
    /// nothing else is removed).
    #[arg(long)]
    pub overwrite: bool,
    /// Also write every frame's posed Gaussians as a 3DGS .ply.
    #[arg(long)]
    pub export_ply: bool,
    /// Also write every frame's posed Gaussians as SPZ (`spz/frame_NNNNN.spz`, a tenth of the
    /// size of the .ply).
    #[arg(long)]
    pub export_spz: bool,
    /// Image size of the orbit camera, WIDTHxHEIGHT (16–8192 pixels a side).
    #[arg(long, default_value = "384x512", value_parser = crate::bounds::image_size)]
    pub size: (u32, u32),
    /// Orbit turns over the sequence.
    #[arg(long, default_value_t = 1.0)]
    pub turns: f32,
    /// Orbit elevation, degrees.
    #[arg(long, default_value_t = 5.0)]
    pub elevation: f32,
    /// Frames per second of the GIF.
    #[arg(long, default_value_t = 8.0)]
    pub fps: f32,
    /// Feed poses as they are, without the pose-PCA projection.
    #[arg(long)]
    pub no_pca: bool,
    /// Leave out the floor (a chequered plane at the body's lowest point over the motion,
    /// hiding what goes below it).
    #[arg(long)]
    pub no_floor: bool,
    #[command(flatten)]
    pub device: DeviceArg,
}

pub fn animate(a: &AnimateArgs) -> Result<f3g_avatar::infer::animate::AnimateReport> {
    // A baked avatar file renders with f3g's renderer; a run with its networks.
    let avatar: Box<dyn f3g_avatar::infer::eval::EvalAvatar> =
        if a.run.extension().is_some_and(|e| e == "glb") {
            Box::new(f3g_avatar::infer::avatar_file::read(&a.run)?)
        } else {
            Box::new(TrainedAvatar::load(&a.run, &a.device.open()?)?)
        };
    let motion = f3g_avatar::infer::animate::read_motion(
        &a.motion,
        avatar.rig(),
        avatar.subject(),
        &a.retarget.options(Some(a.fps))?,
    )?;
    if let Some(r) = &motion.retargeted {
        eprintln!(
            "{}",
            crate::motion::describe(&a.motion, r, motion.frames.len())
        );
    }
    let motion = a.frames.cut(motion.frames)?;
    let (width, height) = a.size;
    let camera = if a.camera == "orbit" {
        CameraPath::Orbit {
            turns: a.turns,
            elevation_deg: a.elevation,
        }
    } else {
        let path = PathBuf::from(&a.camera);
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}", path.display()))?;
        let cam: f3g_splat::Camera = serde_json::from_str(&text)
            .with_context(|| format!("{}: not a camera JSON", path.display()))?;
        cam.validate().with_context(|| path.display().to_string())?;
        CameraPath::Fixed(cam)
    };
    let options = AnimateOptions {
        camera,
        width,
        height,
        out: a.out.clone(),
        overwrite: a.overwrite,
        export_ply: a.export_ply,
        export_spz: a.export_spz,
        fps: a.fps,
        use_pca: !a.no_pca,
        background: [1.0; 3],
        floor: !a.no_floor,
    };
    let bar = ProgressBar::new(motion.len() as u64).with_style(ProgressStyle::with_template(
        "{bar:30} {pos}/{len} frames [{elapsed} < {eta}]",
    )?);
    let report =
        f3g_avatar::infer::animate::animate(avatar.as_ref(), &motion, &options, &mut |i, _| {
            bar.set_position(i as u64)
        })?;
    bar.finish_and_clear();
    println!(
        "wrote {} frames ({:.2} s per frame), {} and {}{}",
        report.frames,
        report.seconds_per_frame,
        report.gif.display(),
        report.video.display(),
        [(report.plys.len(), ".ply"), (report.spzs.len(), ".spz")]
            .iter()
            .filter(|(n, _)| *n > 0)
            .map(|(n, kind)| format!(" and {n} {kind} files"))
            .collect::<String>()
    );
    Ok(report)
}

/// Which way is up in an exported `.ply`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum UpArg {
    /// +Y up: f3g's world, three.js, glTF, GaussianSplats3D.
    #[value(name = "y")]
    Y,
    /// −Y up: COLMAP-style 3DGS scenes, SuperSplat (the avatar turned 180° about X).
    #[value(name = "-y")]
    NegY,
}

/// Options of `f3g export-ply`.
#[derive(Args, Debug, Clone)]
pub struct ExportPlyArgs {
    /// Run folder (`f3g train --out`; the networks colour the file, so not a baked avatar).
    pub run: PathBuf,
    /// Output .ply (standard 3DGS layout, always with the degree-3 SH properties), or, for a
    /// path ending in `.spz`, Niantic's compressed SPZ (about a tenth of the size; Spark and
    /// Niantic's own tools read it).
    #[arg(long)]
    pub out: PathBuf,
    /// Frame of the capture (or of --motion) to pose the avatar in.
    #[arg(long, default_value_t = 0)]
    pub frame: usize,
    /// Motion to take the frame from instead of the capture (any format `--motion` of
    /// `f3g animate` takes, at its own frame rate).
    #[arg(long)]
    pub motion: Option<PathBuf>,
    #[command(flatten)]
    pub retarget: crate::motion::RetargetArgs,
    /// SH degree fitted to the colour network over many view directions, so the file keeps
    /// the avatar's view-dependent colour (0: the mean colour over all directions).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u8).range(0..=3))]
    pub sh_degree: u8,
    /// View directions of the SH fit, 1–1024 (as many again measure its error).
    #[arg(long, default_value_t = 48, value_parser = crate::bounds::size::<1, 1024>)]
    pub directions: usize,
    /// Which way is up in the file: `y` (f3g's world: +Y up, as three.js and glTF) or `-y`
    /// (COLMAP-style 3DGS scenes, which SuperSplat assumes: the avatar turned 180° about X).
    #[arg(long, value_enum, default_value = "y", allow_hyphen_values = true)]
    pub up: UpArg,
    #[command(flatten)]
    pub device: DeviceArg,
}

pub fn export_ply(a: &ExportPlyArgs) -> Result<()> {
    let avatar = TrainedAvatar::load(&a.run, &a.device.open()?)?;
    let (params, use_pca) = match &a.motion {
        Some(m) => {
            let motion = f3g_avatar::infer::animate::read_motion(
                m,
                &avatar.setup.rig,
                &avatar.setup.template.canonical,
                &a.retarget.options(None)?,
            )?
            .frames;
            let p = motion.get(a.frame).cloned().with_context(|| {
                format!(
                    "--frame {}: {} has {} frames",
                    a.frame,
                    m.display(),
                    motion.len()
                )
            })?;
            (p, true)
        }
        None => match f3g_data::Dataset::open(&avatar.info.data, None) {
            Ok(ds) => {
                let p = ds.params.get(a.frame).cloned().with_context(|| {
                    format!(
                        "--frame {}: the capture has {} frames",
                        a.frame,
                        ds.frames()
                    )
                })?;
                (p, !avatar.info.train_frames.contains(&a.frame))
            }
            // A run away from its capture still has its training frames' poses.
            Err(e) => {
                let i = avatar.info.train_frames.iter().position(|&f| f == a.frame);
                let poses = avatar.training_poses()?;
                let p = i.and_then(|i| poses.get(i).cloned()).with_context(|| {
                    format!(
                        "--frame {}: the capture cannot be read ({e}) and the frame is not one of the run's training frames; give --motion",
                        a.frame
                    )
                })?;
                (p, false)
            }
        },
    };
    let options = ExportOptions {
        degree: a.sh_degree as usize,
        directions: a.directions,
        up: match a.up {
            UpArg::Y => Up::Y,
            UpArg::NegY => Up::NegY,
        },
        lit: true,
    };
    let (cloud, fit) = export_cloud(&avatar, &params, use_pca, &options)?;
    if a.out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("spz"))
    {
        f3g_splat::spz::write_spz(&a.out, &cloud)?;
    } else {
        f3g_splat::ply::write_ply(&a.out, &cloud)?;
    }
    println!(
        "wrote {} Gaussians to {} (SH degree {} fitted on {} view directions; colour error on \
         {} others: RMS {:.4}, max {:.4})",
        cloud.len(),
        a.out.display(),
        fit.degree,
        fit.fit_directions,
        fit.check_directions,
        fit.rms,
        fit.max
    );
    Ok(())
}

/// Options of `f3g export-avatar`.
#[derive(Args, Debug, Clone)]
pub struct ExportAvatarArgs {
    /// Run folder (`f3g train --out`).
    pub run: PathBuf,
    /// Output `.glb`: the baked avatar (KHR_gaussian_splatting Gaussians, a glTF skin, pose
    /// correctives and expressions as morph targets, the body model).
    #[arg(long)]
    pub out: PathBuf,
    /// Pose correctives K, 0–256 (0: plain linear blend skinning of the mean avatar).
    #[arg(long, default_value_t = 16, value_parser = crate::bounds::size::<0, 256>)]
    pub correctives: usize,
    /// SH degree of the view-dependent colour, fitted to the colour network at the canonical
    /// pose (0: none, each pose's colour from the views that see each Gaussian; measured
    /// better at the poses an avatar is played in than 1–3, see BENCHMARKS).
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u8).range(0..=3))]
    pub sh_degree: u8,
    /// View directions of the SH fit (with `--sh-degree` above 0), 1–1024.
    #[arg(long, default_value_t = 48, value_parser = crate::bounds::size::<1, 1024>)]
    pub directions: usize,
    /// Training poses the correctives are fitted on, 1–10000 (spread evenly over the run's).
    #[arg(long, default_value_t = 60, value_parser = crate::bounds::size::<1, 10_000>)]
    pub poses: usize,
    /// Perturbed copies of each pose, 0–100.
    #[arg(long, default_value_t = 3, value_parser = crate::bounds::size::<0, 100>)]
    pub perturbations: usize,
    /// Leave the body model's expressions out (smaller file, no facial animation).
    #[arg(long)]
    pub no_expressions: bool,
    /// Compress the file (about a seventh of the size): the Gaussians as SPZ
    /// (`KHR_gaussian_splatting_compression_spz_2`, a Khronos draft: Babylon.js does not read it
    /// yet), the correctives and expressions quantised and deflated. f3g and its player read
    /// both kinds.
    #[arg(long)]
    pub compress: bool,
    /// Seed of the pose perturbations.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Write what baking measured as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    #[command(flatten)]
    pub device: DeviceArg,
}

pub fn export_avatar(a: &ExportAvatarArgs) -> Result<()> {
    export_avatar_files(a, None)
}

/// `export-avatar`, and from the same bake a compressed copy at `compressed` (the demo writes
/// the float file for other viewers and the compressed one for its player).
pub fn export_avatar_files(
    a: &ExportAvatarArgs,
    compressed: Option<&std::path::Path>,
) -> Result<()> {
    use f3g_avatar::infer::avatar_file::Encoding;
    use f3g_avatar::infer::bake::{BakeOptions, BakedAvatar};
    let avatar = TrainedAvatar::load(&a.run, &a.device.open()?)?;
    let poses = avatar.training_poses()?;
    let options = BakeOptions {
        correctives: a.correctives,
        sh_degree: a.sh_degree as usize,
        directions: a.directions,
        poses: a.poses,
        perturbations: a.perturbations,
        expressions: !a.no_expressions,
        seed: a.seed,
        ..BakeOptions::default()
    };
    let (baked, report) = BakedAvatar::bake(&avatar, &poses, &options)?;
    let encoding = if a.compress {
        Encoding::Compressed
    } else {
        Encoding::Float
    };
    let bytes = f3g_avatar::infer::avatar_file::write(&baked, &a.out, encoding)?;
    println!(
        "wrote {} ({:.1} MB, {} bytes per Gaussian): {} Gaussians, {} correctives explaining {:.1} % \
         of the pose variation ({} poses; weights predicted from {} pose features to {:.1} % RMS), \
         {} expressions, SH degree {} (colour RMS {:.4}); four skin influences per Gaussian, chosen \
         and weighted over the sample poses, leave out {:.4} of the weight on average ({:.3} at \
         most) and move a Gaussian by {:.2} mm RMS on average ({:.1} mm at most); {:.1} s",
        a.out.display(),
        bytes as f64 / 1e6,
        bytes / report.gaussians.max(1) as u64,
        report.gaussians,
        baked.corrective_count(),
        100.0 * report.explained_variance,
        report.samples,
        report.features,
        100.0 * report.weight_fit_error,
        baked.expression_names.len(),
        baked.sh_degree,
        report.sh_rms,
        report.dropped_weight_mean,
        report.dropped_weight_max,
        1e3 * report.skin_error_mean,
        1e3 * report.skin_error_max,
        report.seconds
    );
    if let Some(path) = compressed {
        let size = f3g_avatar::infer::avatar_file::write(&baked, path, Encoding::Compressed)?;
        println!(
            "wrote {} ({:.1} MB, compressed)",
            path.display(),
            size as f64 / 1e6
        );
    }
    if let Some(path) = &a.json {
        let mut value = serde_json::to_value(&report)?;
        value["bytes"] = serde_json::json!(bytes);
        value["correctives"] = serde_json::json!(baked.corrective_count());
        f3g_io::write_atomic(path, serde_json::to_string_pretty(&value)?.as_bytes())?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        train: TrainArgs,
    }

    fn parse(flags: &str) -> Result<TrainArgs, clap::Error> {
        let line = format!("f3g --data d --out o {flags}");
        Cli::try_parse_from(line.split_whitespace()).map(|cli| cli.train)
    }

    /// Each ablation flag sets the configuration keys `--set` would, and `--set` has the
    /// last word.
    #[test]
    fn the_ablation_flags_set_their_configuration_keys() {
        let cases: [(&str, &[&str]); 10] = [
            ("", &[]),
            (
                "--no-face-branch",
                &["face_branch=false", "face_losses=false"],
            ),
            ("--no-face-networks", &["face_branch=false"]),
            ("--no-adversarial", &["adversarial=false"]),
            ("--template body", &["template=body"]),
            (
                "--face-input 64",
                &["face_net.input_size=64", "face_net.output_size=64"],
            ),
            ("--face-cm 2", &["face_net.channel_multiplier=2"]),
            ("--face-n-mlp 2", &["face_net.n_mlp=2"]),
            ("--seed 7", &["seed=7"]),
            (
                "--no-adversarial --set adversarial=true",
                &["adversarial=true"],
            ),
        ];
        for (flags, keys) in cases {
            let config = config_of(&parse(flags).unwrap(), |_| {}).unwrap();
            let keys: Vec<String> = keys.iter().map(|k| k.to_string()).collect();
            let expected = TrainConfig::cpu().with_overrides(&keys).unwrap();
            assert_eq!(config, expected, "{flags}");
        }
        // The `cpu` preset has no adversarial loss to drop; the `paper` preset has one.
        let paper = |flags: &str| {
            config_of(&parse(&format!("--preset paper {flags}")).unwrap(), |_| {}).unwrap()
        };
        assert!(paper("").adversarial);
        assert!(!paper("--no-adversarial").adversarial);
    }

    #[test]
    fn a_bad_ablation_flag_is_an_error_naming_it() {
        let e = parse("--template skirt").unwrap_err().to_string();
        assert!(
            e.contains("--template") && e.contains("expected body or clothed"),
            "{e}"
        );
        // A resumed run keeps its configuration: flags that would change it are refused.
        for flags in ["--no-adversarial", "--template body", "--seed 3"] {
            let line = format!("f3g --resume r {flags}");
            let e = Cli::try_parse_from(line.split_whitespace())
                .err()
                .unwrap_or_else(|| panic!("--resume with {flags} was accepted"));
            assert!(
                e.to_string().contains("cannot be used with"),
                "{flags}: {e}"
            );
        }
        let config = config_of(&parse("--face-input 48").unwrap(), |_| {});
        let e = config.unwrap_err().to_string();
        assert!(e.contains("face_net"), "{e}");
    }
}
