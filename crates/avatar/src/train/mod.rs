//! Region-aware training (paper §3.5, Animatable Gaussians' schedule): the training
//! configuration, the run folder's writing side and the loop. Training may import
//! `crate::model` and `crate::infer` (the run folder's readers, report images); they never
//! import it.
//!
//! The method, one module each: `schedule.rs` (stages and learning rates), `losses.rs` (body,
//! face, adversarial, offset), `face_model.rs` (the canonical face model built from the body
//! branch), `step.rs` (one step on one device: gradients, then a separate apply, so that
//! data-parallel replicas can average their gradients between the two). Around them:
//! `config/` ([`TrainConfig`]: presets, JSON files, overrides, validation), `run.rs` (the run
//! folder's config, provenance with its format version, checkpoints, PCA), `restore.rs`
//! (networks, optimisers and replicas from a checkpoint), `parallel.rs` (one data-parallel
//! step), `validation.rs` (the validation grids), `pca.rs` (the pose PCA's fit), `profile.rs`
//! (`f3g bench train`'s phase timer and hooks). This module is the loop: it owns the run
//! folder, the loader, the log and checkpoints.
//!
//! `log.jsonl` is the one file of a run written in place: one JSON line is appended per step
//! (a kill can leave a partial last line, which readers skip), and a resumed run first
//! rewrites it, atomically, to the lines of the steps before its checkpoint. Every other
//! file is written whole and atomically.
//!
//! Samples are drawn by the loader as a pure function of the seed and the sample index, so a
//! resumed run continues exactly as an uninterrupted one would. With `R` replicas (one per
//! device), step `s` draws samples `s·R … s·R + R − 1`, one per replica, and applies the mean
//! of their gradients: one replica is the single-device run.
//!
//! Stages (see [`Stage`]):
//!
//! 1. **pretrain** — the body network reconstructs the canonical attributes (zero offsets,
//!    grey colour, opacity 0.1, the initial scales, identity rotations); Adam's state is reset
//!    afterwards.
//! 2. **body** — body-only rendering: L1 on the full (down-scaled) image, LPIPS on the
//!    mask-bounding-box square, offset regulariser. Not in the paper (pretraining, then joint
//!    steps): the `paper` preset has none, the `cpu` presets a few or more.
//! 3. *(face branch)* the canonical face model is averaged from the body branch over training
//!    frames; **face_pretrain** — the face networks learn zero residuals on it.
//! 4. **joint** — body losses plus, on the head crop rendered with its own intrinsics, L1,
//!    LPIPS and the non-saturating adversarial loss of a StyleGAN2 discriminator trained
//!    alternately (with lazy R1).
//! 5. **face_finetune** — the face losses train the face networks only.

mod config;
mod face_model;
mod losses;
mod parallel;
mod pca;
mod profile;
mod restore;
mod run;
mod sample;
mod schedule;
mod step;
mod validation;

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use burn::tensor::Device;
use serde::Serialize;

use crate::AvatarError;
use crate::infer::report;
use crate::infer::{Run, RunInfo, TrainState, evenly, load_face_base, read_state};
use crate::model::{AvatarNets, FaceBase, Setup};
use f3g_data::Dataset;
use f3g_data::loader::{ImageCache, Loader, LoaderOptions};
use f3g_data::split::{Protocol, Split, SplitKind, preset};
use f3g_rig::ModelSpec;
use sample::DeviceSample;
use step::Replica;

pub use config::{LossWeights, Stages, TrainConfig};
pub use profile::{BenchSamples, Phase, PhaseTimer, PhaseTimes};
pub use run::load_optim;
use schedule::Schedule;
pub use schedule::Stage;
pub use step::AllReduce;

/// What one step did.
#[derive(Clone, Debug, Serialize)]
pub struct StepReport {
    pub step: u64,
    pub stage: Stage,
    pub lr: f64,
    /// The first replica's sample.
    pub frame: usize,
    pub camera: usize,
    /// Named loss terms (already weighted; the mean over replicas) and their sum.
    pub losses: Vec<(String, f32)>,
    pub total: f32,
    pub seconds: f64,
}

/// How `train` ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    Finished,
    /// The stop flag was raised; a checkpoint was written.
    Stopped,
}

/// The training split of a capture: the protocol's preset unless lists are given.
fn training_split(
    ds: &Dataset,
    cameras: Option<&[usize]>,
    frames: Option<&[usize]>,
) -> Result<Split, AvatarError> {
    let p = preset(
        Protocol::of(ds),
        SplitKind::Train,
        ds.cameras.len(),
        ds.frames(),
    )?;
    Ok(Split {
        cameras: cameras.map_or(p.cameras, <[usize]>::to_vec),
        frames: frames.map_or(p.frames, <[usize]>::to_vec),
    })
}

/// A training run in memory.
pub struct Trainer {
    config: TrainConfig,
    run: Run,
    /// Shared with the loader's worker, which poses each sample's frame.
    setup: Arc<Setup>,
    dataset: Arc<Dataset>,
    split: Split,
    schedule: Schedule,
    /// One per device; the first one's state is what checkpoints, validation and the
    /// accessors show (every replica holds the same weights).
    replicas: Vec<Replica>,
    /// How the replicas sum their gradients.
    all_reduce: AllReduce,
    face_base: Option<FaceBase>,
    state: TrainState,
    last_checkpoint: Option<PathBuf>,
    validation_view: Option<(usize, usize)>,
    /// The loaders' decoded images, kept for every loader this trainer makes (`bench` makes
    /// several).
    image_cache: Arc<Mutex<ImageCache>>,
}

impl Trainer {
    /// Starts a new run in `run_dir` (new or empty: a run's files have fixed names, which would
    /// replace a user's `config.json` or `log.jsonl`) on the capture `data`, training
    /// on `devices` (with or without their autodiff flag: the trainer sets it); more than one
    /// device trains data-parallel (module docs).
    pub fn create(
        run_dir: &Path,
        data: &Path,
        model: Option<&ModelSpec>,
        config: TrainConfig,
        cameras: Option<&[usize]>,
        frames: Option<&[usize]>,
        devices: &[Device],
    ) -> Result<Self, AvatarError> {
        config.validate()?;
        let run = Run::new(run_dir);
        if run.config_path().exists() {
            return Err(AvatarError::file(
                run_dir,
                "already holds a run: resume it with --resume, or choose another --out",
            ));
        }
        if std::fs::read_dir(run_dir).is_ok_and(|mut entries| entries.next().is_some()) {
            return Err(AvatarError::file(
                run_dir,
                "holds files and no run: a run is written into a new or empty folder (its \
                 files would replace a config.json, log.jsonl or checkpoints/ there); choose \
                 another --out",
            ));
        }
        let dataset = Arc::new(Dataset::open(data, model)?);
        dataset.rig()?;
        let split = training_split(&dataset, cameras, frames)?;
        let identity = dataset.params[split.frames[0]].identity.clone();
        let setup = Setup::new(&dataset.model, &identity, &config.model)?;
        let train_params: Vec<_> = split
            .frames
            .iter()
            .map(|&f| dataset.params[f].clone())
            .collect();
        for (f, p) in split.frames.iter().zip(&train_params) {
            setup.check_params(p, &format!("frame {f} of {}", data.display()))?;
        }
        run.write_config(&config)?;
        run.write_info(&RunInfo {
            data: std::fs::canonicalize(data).unwrap_or_else(|_| data.to_path_buf()),
            model: dataset.model.clone(),
            identity,
            train_cameras: split.cameras.clone(),
            train_frames: split.frames.clone(),
        })?;
        // What inference needs of the body model stays with the run, and so do the training
        // poses (baking samples them; a player can play them).
        setup.write(run.dir())?;
        f3g_rig::sequence::write(&run.poses_path(), &setup.rig, &train_params)?;
        let pca_frames: Vec<_> = evenly(&train_params, 300);
        if pca_frames.len() >= 2 {
            run.write_pca(&pca::fit_pose_pca(
                &setup,
                &pca_frames,
                config.model.pca_components,
                config.model.pca_sigma,
                &first_device(devices)?.without_autodiff(),
            )?)?;
        }
        let state = TrainState {
            step: 0,
            seconds: 0.0,
            disc_steps: 0,
            device: String::new(),
            replicas: 1,
        };
        Self::assemble(
            run, config, setup, dataset, split, state, None, None, devices,
        )
    }

    /// Reopens `run_dir` at its newest checkpoint (or at step 0 when it has none) on
    /// `devices`, which may differ from the ones the checkpoint was written on (with another
    /// number of devices the run continues, but draws other samples than it would have).
    pub fn resume(
        run_dir: &Path,
        model: Option<&ModelSpec>,
        devices: &[Device],
    ) -> Result<Self, AvatarError> {
        let run = Run::new(run_dir);
        let config = run.config()?;
        let info = run.info()?;
        run.remove_temporaries()?;
        let dataset = Arc::new(Dataset::open(&info.data, model)?);
        if dataset.model != info.model {
            return Err(AvatarError::file(
                &info.data,
                format!(
                    "the capture's body model is `{}` but the run was trained on `{}`",
                    dataset.model, info.model
                ),
            ));
        }
        let split = Split {
            cameras: info.train_cameras.clone(),
            frames: info.train_frames.clone(),
        };
        // Runs of this format keep their setup; `info` refused any other format.
        let setup = Setup::read(run.dir(), &config.model)?;
        let checkpoint = run.latest()?;
        let state = match &checkpoint {
            Some(c) => read_state(c)?,
            None => TrainState {
                step: 0,
                seconds: 0.0,
                disc_steps: 0,
                device: String::new(),
                replicas: 1,
            },
        };
        let face_base = match &checkpoint {
            Some(c) if c.join("face_base.npz").exists() => Some(load_face_base(
                &c.join("face_base.npz"),
                setup.face_count(),
            )?),
            _ => None,
        };
        Self::assemble(
            run, config, setup, dataset, split, state, checkpoint, face_base, devices,
        )
    }

    /// Chooses how the replicas sum their gradients (the host's way unless told; the caller
    /// knows whether the devices can run a collective).
    pub fn set_all_reduce(&mut self, how: AllReduce) {
        self.all_reduce = how;
    }

    /// The run's configuration.
    pub fn config(&self) -> &TrainConfig {
        &self.config
    }

    /// The run folder.
    pub fn run_dir(&self) -> &Path {
        self.run.dir()
    }

    /// The run's setup (template, maps, Gaussian counts).
    pub fn setup(&self) -> &Setup {
        &self.setup
    }

    /// The training split: cameras and frames.
    pub fn split(&self) -> &Split {
        &self.split
    }

    /// The next step to run.
    pub fn step(&self) -> u64 {
        self.state.step
    }

    /// Total steps of the configuration.
    pub fn total_steps(&self) -> u64 {
        self.schedule.total()
    }

    /// The networks (for tests and evaluation).
    pub fn nets(&self) -> &AvatarNets {
        &self.replicas[0].nets
    }

    /// The networks of every replica (data-parallel tests check they stay equal).
    pub fn replica_nets(&self) -> impl Iterator<Item = &AvatarNets> {
        self.replicas.iter().map(|r| &r.nets)
    }

    /// The loader options of this run (`replicas · batch` samples per step).
    fn loader_options(&self) -> LoaderOptions {
        LoaderOptions {
            body_scale: self.config.body_scale,
            face_size: self.config.model.face_crop_size,
            face_padding: self.config.model.face_padding,
            cache_bytes: self.config.cache_bytes,
            prefetch: 4 * self.replicas.len() * self.config.batch,
            random_background: true,
            band_radius: self.config.band_radius.unwrap_or(
                if Protocol::of(&self.dataset) == Protocol::Synthetic {
                    0.0
                } else {
                    2.0
                },
            ),
            seed: self.config.seed,
        }
    }

    /// The loader of this run from sample `start`: its worker thread also poses each sample's
    /// frame and uploads the sample to the device of the replica that takes it (replica `r` of
    /// `R` takes samples `(s·R + r)·batch …` of step `s`).
    fn loader(&self, start: u64) -> Result<Loader<Result<DeviceSample, AvatarError>>, AvatarError> {
        let setup = self.setup.clone();
        let config = self.config.clone();
        let devices: Vec<Device> = self.replicas.iter().map(|r| r.device.clone()).collect();
        Ok(Loader::with_preparation(
            self.dataset.clone(),
            &self.split,
            self.loader_options(),
            self.image_cache.clone(),
            start,
            move |sample| {
                let replica = (sample.index / config.batch as u64) as usize % devices.len();
                DeviceSample::prepare(&setup, &config, sample, &devices[replica])
            },
        )?)
    }

    /// Fails when the loader's image cache would grow beyond the memory the machine has: it
    /// holds up to `cache_bytes` of prepared views (16 bytes per pixel of the body image at
    /// `body_scale` and of the full-resolution window around the head, at most a quarter of
    /// the image height squared), or every training image's when they take less.
    fn ensure_cache_fits(&self) -> Result<(), AvatarError> {
        let images: u64 = f3g_data::loader::available(&self.dataset, &self.split)
            .iter()
            .map(|&(c, _)| {
                let cam = &self.dataset.cameras[c].camera;
                let (w, h) = f3g_data::imgops::scaled_size(
                    cam.width as usize,
                    cam.height as usize,
                    self.config.body_scale,
                );
                let head = (cam.height as u64).div_ceil(4).pow(2);
                16 * (w as u64 * h as u64 + head)
            })
            .sum();
        let bytes = images.min(self.config.cache_bytes as u64);
        Ok(f3g_io::memory::ensure_available(
            bytes,
            &format!(
                "the loader's image cache (configuration `cache_bytes` = {})",
                self.config.cache_bytes
            ),
        )?)
    }

    /// Trains until the last step or until `stop` is raised, calling `on_step` after each step.
    pub fn train(
        &mut self,
        stop: &AtomicBool,
        on_step: &mut dyn FnMut(&StepReport),
    ) -> Result<Outcome, AvatarError> {
        let total = self.total_steps();
        self.truncate_log()?;
        if self.state.step >= total {
            return Ok(Outcome::Finished);
        }
        self.ensure_cache_fits()?;
        let per_step = (self.replicas.len() * self.config.batch) as u64;
        let mut loader = self.loader(self.state.step * per_step)?;
        let mut log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(self.run.log_path())
            .map_err(|e| AvatarError::file(&self.run.log_path(), e))?;
        while self.state.step < total {
            let s = self.state.step;
            let start = Instant::now();
            let samples = next_samples(&mut loader, per_step)?;
            debug_assert_eq!(samples[0].index, s * per_step);
            let mut report = self.run_step(s, &samples, None).map_err(|e| match e {
                AvatarError::NonFinite {
                    step, name, value, ..
                } => AvatarError::NonFinite {
                    step,
                    name,
                    value,
                    checkpoint: self.last_checkpoint.clone(),
                },
                other => other,
            })?;
            self.state.seconds += start.elapsed().as_secs_f64();
            report.seconds = self.state.seconds;
            self.state.step = s + 1;
            let line = serde_json::to_string(&report).expect("serialisable");
            writeln!(log, "{line}").map_err(|e| AvatarError::file(&self.run.log_path(), e))?;
            on_step(&report);
            let done = self.state.step == total;
            if self.state.step.is_multiple_of(self.config.validate_every) || done {
                self.validate()?;
                report::loss_curve(&self.run.log_path(), &self.run.dir().join("loss.png"))?;
            }
            let stopping = stop.load(Ordering::Relaxed);
            if self.state.step.is_multiple_of(self.config.checkpoint_every) || done || stopping {
                self.checkpoint()?;
            }
            if stopping && !done {
                return Ok(Outcome::Stopped);
            }
        }
        Ok(Outcome::Finished)
    }

    /// Writes a checkpoint of the current state (the first replica's; all are equal).
    fn checkpoint(&mut self) -> Result<PathBuf, AvatarError> {
        let r = &self.replicas[0];
        let dir = self.run.write_checkpoint(
            &self.state,
            &r.nets,
            &r.optimisers.body,
            r.optimisers.face.as_ref(),
            r.disc.as_ref().zip(r.optimisers.disc.as_ref()),
            self.face_base.as_ref(),
        )?;
        self.last_checkpoint = Some(dir.clone());
        Ok(dir)
    }

    /// Keeps only the log lines of steps before the current one (after a resume).
    fn truncate_log(&self) -> Result<(), AvatarError> {
        let path = self.run.log_path();
        if !path.exists() {
            return Ok(());
        }
        let text = std::fs::read_to_string(&path).map_err(|e| AvatarError::file(&path, e))?;
        let kept: String = text
            .lines()
            .filter(|l| {
                serde_json::from_str::<serde_json::Value>(l)
                    .ok()
                    .and_then(|v| v["step"].as_u64())
                    .is_some_and(|st| st < self.state.step)
            })
            .map(|l| format!("{l}\n"))
            .collect();
        Ok(f3g_io::write_atomic(&path, kept.as_bytes())?)
    }
}

/// The next `count` samples of `loader`.
pub(super) fn next_samples(
    loader: &mut Loader<Result<DeviceSample, AvatarError>>,
    count: u64,
) -> Result<Vec<DeviceSample>, AvatarError> {
    (0..count).map(|_| loader.next_sample()?).collect()
}

/// The first of the training devices (the one that checkpoints and validates).
fn first_device(devices: &[Device]) -> Result<Device, AvatarError> {
    devices
        .first()
        .cloned()
        .ok_or_else(|| AvatarError::Invalid("training needs at least one device".into()))
}
