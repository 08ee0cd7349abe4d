//! Region-aware training (paper §3.5, Animatable Gaussians' schedule).
//!
//! One `(frame, camera)` sample per step, drawn by the loader as a pure function of the seed and
//! the step, so that a resumed run continues exactly as an uninterrupted one would. Stages:
//!
//! 1. **pretrain** — the body network reconstructs the canonical attributes (zero offsets,
//!    grey colour, opacity 0.1, the initial scales, identity rotations); Adam's state is reset
//!    afterwards.
//! 2. **body** — body-only rendering: L1 on the full (down-scaled) image, LPIPS on the
//!    mask-bounding-box square, offset regulariser.
//! 3. *(face branch)* the canonical face model is averaged from the body branch over training
//!    frames; **face_pretrain** — the face networks learn zero residuals on it.
//! 4. **joint** — body losses plus, on the head crop rendered with its own intrinsics, L1,
//!    LPIPS and the non-saturating adversarial loss of a StyleGAN2 discriminator trained
//!    alternately (with lazy R1).
//! 5. **face_finetune** — the face losses train the face networks only.
//!
//! Without the face branch, stages 3–5 are body steps, so both variants take the same number of
//! steps. Learning rate: constant in pretraining, then `lr·((cos(π t/T) + 1)/2 · 0.95 + 0.05)`
//! over the rendering steps. In the boundary band the render is replaced by the background,
//! as in the ground truth.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::activation::sigmoid;
use burn::tensor::{Device, Tensor, TensorData};
use serde::Serialize;

use crate::AvatarError;
use crate::config::TrainConfig;
use crate::inputs::{NetInputs, inputs_for};
use crate::model::{
    AvatarNets, Canonical, Constants, FaceBase, body_attributes_host, body_outputs, canonical,
    nchw, render_posed,
};
use crate::report;
use crate::run::{Run, RunInfo, TrainState, load_face_base, load_optim, read_state};
use crate::setup::Setup;
use f3g_data::Dataset;
use f3g_data::imgops::CentredSquare;
use f3g_data::loader::{Loader, LoaderOptions, Sample, View};
use f3g_data::split::{Protocol, Split, SplitKind, preset};
use f3g_nets::discriminator::{discriminator_loss, generator_loss, r1_penalty};
use f3g_nets::layers::resize;
use f3g_nets::metrics::{image_tensor, l1_loss};
use f3g_nets::{Discriminator, Lpips};
use f3g_rig::ModelSpec;

/// A training stage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    Pretrain,
    Body,
    FacePretrain,
    Joint,
    FaceFinetune,
}

/// What one step did.
#[derive(Clone, Debug, Serialize)]
pub struct StepReport {
    pub step: u64,
    pub stage: Stage,
    pub lr: f64,
    pub frame: usize,
    pub camera: usize,
    /// Named loss terms (already weighted) and their sum.
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
pub fn training_split(
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
    pub config: TrainConfig,
    pub run: Run,
    pub setup: Setup,
    pub dataset: Arc<Dataset>,
    pub split: Split,
    device: Device,
    nets: AvatarNets,
    optim_body: ModuleOptimizer,
    optim_face: Option<ModuleOptimizer>,
    disc: Option<Discriminator>,
    optim_disc: Option<ModuleOptimizer>,
    face_base: Option<FaceBase>,
    constants: Constants,
    lpips: Lpips,
    state: TrainState,
    last_checkpoint: Option<PathBuf>,
    validation_view: Option<(usize, usize)>,
}

fn adam(epsilon: f32) -> ModuleOptimizer {
    AdamConfig::new().with_epsilon(epsilon).init()
}

fn adam_disc() -> ModuleOptimizer {
    AdamConfig::new().with_beta_1(0.0).with_beta_2(0.99).init()
}

impl Trainer {
    /// Starts a new run in `run_dir` (which must not hold one) on the capture `data`, training
    /// on `device` (with or without its autodiff flag: the trainer sets it).
    pub fn create(
        run_dir: &Path,
        data: &Path,
        model: Option<&ModelSpec>,
        config: TrainConfig,
        cameras: Option<&[usize]>,
        frames: Option<&[usize]>,
        device: &Device,
    ) -> Result<Self, AvatarError> {
        config.validate()?;
        let run = Run::new(run_dir);
        if run.dir.join("config.json").exists() {
            return Err(AvatarError::file(
                run_dir,
                "already holds a run: resume it with --resume, or choose another --out",
            ));
        }
        let dataset = Arc::new(Dataset::open(data, model)?);
        dataset.rig()?;
        let split = training_split(&dataset, cameras, frames)?;
        let identity = dataset.params[split.frames[0]].identity.clone();
        let setup = Setup::new(&dataset.model, &identity, &config)?;
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
        let pca_frames: Vec<_> = evenly(&train_params, 300);
        if pca_frames.len() >= 2 {
            run.write_pca(&setup.fit_pca(&pca_frames, config.pca_components, config.pca_sigma)?)?;
        }
        let state = TrainState {
            step: 0,
            seconds: 0.0,
            disc_steps: 0,
            device: String::new(),
        };
        Self::assemble(
            run, config, setup, dataset, split, state, None, None, device,
        )
    }

    /// Reopens `run_dir` at its newest checkpoint (or at step 0 when it has none) on `device`,
    /// which may differ from the one the checkpoint was written on.
    pub fn resume(
        run_dir: &Path,
        model: Option<&ModelSpec>,
        device: &Device,
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
        let setup = Setup::new(&dataset.model, &info.identity, &config)?;
        let checkpoint = run.latest()?;
        let state = match &checkpoint {
            Some(c) => read_state(c)?,
            None => TrainState {
                step: 0,
                seconds: 0.0,
                disc_steps: 0,
                device: String::new(),
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
            run, config, setup, dataset, split, state, checkpoint, face_base, device,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn assemble(
        run: Run,
        config: TrainConfig,
        setup: Setup,
        dataset: Arc<Dataset>,
        split: Split,
        state: TrainState,
        checkpoint: Option<PathBuf>,
        face_base: Option<FaceBase>,
        device: &Device,
    ) -> Result<Self, AvatarError> {
        let device = device.clone().without_autodiff().autodiff();
        let mut nets = AvatarNets::new(&config, &setup, &device)?;
        let mut optim_body = adam(config.adam_epsilon);
        let mut optim_face = config.face_branch.then(|| adam(config.adam_epsilon));
        let with_disc = config.face_losses && config.adversarial;
        let mut disc = if with_disc {
            let d = f3g_nets::checkpoint::with_deterministic_ids(
                config
                    .discriminator
                    .init(config.seed.wrapping_add(20), &device)?,
                crate::model::DISCRIMINATOR_PARAM_IDS,
            );
            // A new run may start from pretrained discriminator weights; a resumed one has its
            // own in the checkpoint.
            Some(match (&config.discriminator_weights, &checkpoint) {
                (Some(path), None) => f3g_nets::checkpoint::load(d, Path::new(path))?,
                _ => d,
            })
        } else {
            None
        };
        let mut optim_disc = with_disc.then(adam_disc);
        if let Some(c) = &checkpoint {
            nets = f3g_nets::checkpoint::load(nets, &c.join("nets.bpk"))?;
            optim_body = load_optim(optim_body, &c.join("optim_body.bpk"), &nets.body)?;
            if let Some(face) = nets.face.as_ref()
                && let Some(o) = optim_face.take()
            {
                let path = c.join("optim_face.bpk");
                optim_face = Some(if path.exists() {
                    load_optim(o, &path, face)?
                } else {
                    o
                });
            }
            if let Some(d) = disc.take() {
                let path = c.join("disc.bpk");
                if path.exists() {
                    let d = f3g_nets::checkpoint::load(d, &path)?;
                    let o = optim_disc.take().expect("with the discriminator");
                    optim_disc = Some(load_optim(o, &c.join("optim_disc.bpk"), &d)?);
                    disc = Some(d);
                } else {
                    disc = Some(d);
                }
            }
        }
        let constants = Constants::new(&setup, &config, face_base.as_ref(), &device);
        let lpips = Lpips::load(config.lpips_net, &device)?;
        // Checkpoints from now on are written by this device.
        let mut state = state;
        state.device = format!("{:?}", device.clone().without_autodiff());
        let validation_view = preset(
            Protocol::of(&dataset),
            SplitKind::NovelView,
            dataset.cameras.len(),
            dataset.frames(),
        )
        .ok()
        .and_then(|s| {
            s.frames
                .iter()
                .flat_map(|&f| s.cameras.iter().map(move |&c| (c, f)))
                .find(|&(c, f)| dataset.has_image(c, f))
        });
        Ok(Self {
            config,
            run,
            setup,
            dataset,
            split,
            device,
            nets,
            optim_body,
            optim_face,
            disc,
            optim_disc,
            face_base,
            constants,
            lpips,
            state,
            last_checkpoint: checkpoint,
            validation_view,
        })
    }

    /// The next step to run.
    pub fn step(&self) -> u64 {
        self.state.step
    }

    /// Total steps of the configuration.
    pub fn total_steps(&self) -> u64 {
        self.config.steps.total()
    }

    /// The networks (for tests and evaluation).
    pub fn nets(&self) -> &AvatarNets {
        &self.nets
    }

    pub fn face_base(&self) -> Option<&FaceBase> {
        self.face_base.as_ref()
    }

    /// The stage of step `s`.
    pub fn stage(&self, s: u64) -> Stage {
        let st = &self.config.steps;
        let mut end = st.pretrain;
        if s < end {
            return Stage::Pretrain;
        }
        end += st.body;
        let c = &self.config;
        if s < end || !(c.face_branch || c.face_losses) {
            return Stage::Body;
        }
        if !c.face_branch {
            // Face-crop losses without face networks: nothing to pretrain or fine-tune alone.
            return Stage::Joint;
        }
        end += st.face_pretrain;
        if s < end {
            return Stage::FacePretrain;
        }
        end += st.joint;
        if s < end {
            return Stage::Joint;
        }
        Stage::FaceFinetune
    }

    /// The learning rate of step `s`.
    pub fn lr(&self, s: u64) -> f64 {
        let pre = self.config.steps.pretrain;
        if s < pre {
            return self.config.lr;
        }
        let t = (s - pre) as f64;
        let total = (self.config.steps.total() - pre).max(1) as f64;
        self.config.lr * (((std::f64::consts::PI * t / total).cos() + 1.0) / 2.0 * 0.95 + 0.05)
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
        let options = LoaderOptions {
            body_scale: self.config.body_scale,
            face_size: self.config.face_crop_size,
            face_padding: self.config.face_padding,
            cache_bytes: self.config.cache_bytes,
            prefetch: 4,
            random_background: true,
            band_radius: self.config.band_radius.unwrap_or(
                if Protocol::of(&self.dataset) == Protocol::Synthetic {
                    0.0
                } else {
                    2.0
                },
            ),
            seed: self.config.seed,
        };
        let mut loader = Loader::new(self.dataset.clone(), &self.split, options, self.state.step)?;
        let mut log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(self.run.log_path())
            .map_err(|e| AvatarError::file(&self.run.log_path(), e))?;
        while self.state.step < total {
            let s = self.state.step;
            let start = Instant::now();
            let sample = loader.next_sample()?;
            debug_assert_eq!(sample.index, s);
            let mut report = self.run_step(s, &sample)?;
            self.state.seconds += start.elapsed().as_secs_f64();
            report.seconds = self.state.seconds;
            self.state.step = s + 1;
            let line = serde_json::to_string(&report).expect("serialisable");
            writeln!(log, "{line}").map_err(|e| AvatarError::file(&self.run.log_path(), e))?;
            on_step(&report);
            let done = self.state.step == total;
            if self.state.step.is_multiple_of(self.config.validate_every) || done {
                self.validate()?;
                report::loss_curve(&self.run.log_path(), &self.run.dir.join("loss.png"))?;
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

    /// Writes a checkpoint of the current state.
    pub fn checkpoint(&mut self) -> Result<PathBuf, AvatarError> {
        let dir = self.run.write_checkpoint(
            &self.state,
            &self.nets,
            &self.optim_body,
            self.optim_face.as_ref(),
            self.disc.as_ref().zip(self.optim_disc.as_ref()),
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

    /// The network inputs of a sample (view noise seeded by the step).
    fn inputs(&self, sample: &Sample, noise_seed: Option<u64>) -> Result<NetInputs, AvatarError> {
        inputs_for(
            &self.setup,
            &self.constants,
            &sample.params,
            &sample.body.camera,
            noise_seed.map(|s| (self.config.view_noise, s)),
            None,
            &self.device,
        )
    }

    fn run_step(&mut self, s: u64, sample: &Sample) -> Result<StepReport, AvatarError> {
        let stage = self.stage(s);
        let lr = self.lr(s);
        if s == self.config.steps.pretrain && s > 0 {
            // Animatable Gaussians resets Adam after pretraining.
            self.optim_body = adam(self.config.adam_epsilon);
        }
        if self.config.face_branch
            && matches!(
                stage,
                Stage::FacePretrain | Stage::Joint | Stage::FaceFinetune
            )
            && self.face_base.is_none()
        {
            self.build_face_base()?;
        }
        let noise_seed = self.config.seed ^ s.wrapping_mul(0x2545_f491_4f6c_dd1d);
        let inputs = self.inputs(sample, Some(noise_seed))?;
        let mut terms: Vec<(String, Tensor<1>)> = Vec::new();
        let mut face_fake = None;
        match stage {
            Stage::Pretrain => {
                let raw = body_outputs(&self.nets, &self.constants, &inputs)?;
                terms.push(("pretrain".into(), self.pretrain_loss(&raw)));
            }
            Stage::FacePretrain => {
                let nets = self.face_only_nets();
                let c = canonical(&nets, &self.constants, &inputs)?;
                let r = c.face_residuals.expect("face branch");
                terms.push(("face_pretrain".into(), r.abs().mean()));
            }
            Stage::Body | Stage::Joint => {
                let c = canonical(&self.nets, &self.constants, &inputs)?;
                self.body_terms(&c, &inputs, sample, &mut terms)?;
                if stage == Stage::Joint && self.config.face_losses {
                    face_fake = self.face_terms(&c, &inputs, sample, &mut terms)?;
                }
            }
            Stage::FaceFinetune => {
                let nets = self.face_only_nets();
                let c = canonical(&nets, &self.constants, &inputs)?;
                face_fake = self.face_terms(&c, &inputs, sample, &mut terms)?;
            }
        }
        let mut values = Vec::new();
        for (name, t) in &terms {
            let v = t.clone().into_scalar::<f32>();
            if !v.is_finite() {
                return Err(self.non_finite(s, name, v));
            }
            values.push((name.clone(), v));
        }
        let total_value: f32 = values.iter().map(|v| v.1).sum();
        if let Some(total) = terms.into_iter().map(|t| t.1).reduce(|a, b| a + b) {
            let mut grads = total.backward();
            let body_grads = GradientsParams::from_module(&mut grads, &self.nets.body);
            let face_grads = self
                .nets
                .face
                .as_ref()
                .map(|f| GradientsParams::from_module(&mut grads, f));
            let AvatarNets { body, face } = self.nets.clone();
            let body = if matches!(stage, Stage::Pretrain | Stage::Body | Stage::Joint) {
                self.optim_body.step(lr, body, body_grads)
            } else {
                body
            };
            let face = match (face, face_grads, self.optim_face.as_mut()) {
                (Some(f), Some(g), Some(o))
                    if matches!(
                        stage,
                        Stage::FacePretrain | Stage::Joint | Stage::FaceFinetune
                    ) =>
                {
                    Some(o.step(lr, f, g))
                }
                (f, _, _) => f,
            };
            self.nets = AvatarNets { body, face };
        }
        if let (Some(fake), Some(real)) = (face_fake, sample.face.as_ref()) {
            let d_loss = self.discriminator_step(s, fake, real)?;
            values.push(("discriminator".into(), d_loss));
        }
        Ok(StepReport {
            step: s,
            stage,
            lr,
            frame: sample.frame,
            camera: sample.camera,
            losses: values,
            total: total_value,
            seconds: self.state.seconds,
        })
    }

    fn non_finite(&self, step: u64, name: &str, value: f32) -> AvatarError {
        AvatarError::NonFinite {
            step,
            name: name.to_string(),
            value,
            checkpoint: self.last_checkpoint.clone(),
        }
    }

    /// The networks with the body frozen (face-only stages): its graph is not tracked.
    fn face_only_nets(&self) -> AvatarNets {
        AvatarNets {
            body: self.nets.body.clone().no_grad(),
            face: self.nets.face.clone(),
        }
    }

    /// L1 between the body network's activated attributes and the initial ones (zero offsets,
    /// grey colour, opacity 0.1, the k-NN scales, identity rotations). Animatable Gaussians
    /// leaves the colour out; starting from grey instead of the untrained network's colour
    /// noise shortens the short CPU schedules noticeably.
    fn pretrain_loss(&self, raw: &Tensor<2>) -> Tensor<1> {
        let n = raw.dims()[0];
        let col = |a: usize, b: usize| raw.clone().slice([0..n, a..b]);
        let offsets = col(0, 3).abs().mean() + col(3, 6).abs().mean();
        let o0 = self.config.initial_opacity;
        let opacity = (sigmoid(col(6, 7) + crate::setup::logit(o0)) - o0)
            .abs()
            .mean();
        let (base, base_quats) = self.constants.initial_body();
        let scales = ((base.clone() + col(7, 10)).exp() - base.exp())
            .abs()
            .mean();
        let q = col(10, 14) + base_quats.clone();
        let norm = (q.clone().powf_scalar(2.0).sum_dim(1) + 1e-12).sqrt();
        let rotation = (q / norm - base_quats).abs().mean();
        offsets + opacity + scales + rotation
    }

    /// Renders the body view: L1, LPIPS on the mask box, offset regulariser.
    fn body_terms(
        &self,
        c: &Canonical,
        inputs: &NetInputs,
        sample: &Sample,
        terms: &mut Vec<(String, Tensor<1>)>,
    ) -> Result<(), AvatarError> {
        let w = &self.config.losses;
        let view = &sample.body;
        let pred = self.render_view(c, inputs, view, sample.background)?;
        let gt = image_tensor(&view.image, &self.device);
        terms.push(("l1".into(), l1_loss(pred.clone(), gt.clone()) * w.l1));
        if w.lpips > 0.0
            && let Some(square) = CentredSquare::around_mask(&view.mask, 0)
        {
            let size = self.config.lpips_size;
            let bg = sample.background;
            let crop = |t: Tensor<4>| resize(square_crop(t, &square, bg), size, size);
            let d = self.lpips.forward(crop(pred), crop(gt))?.mean();
            terms.push(("lpips".into(), d * w.lpips));
        }
        let mut offset = offset_norm(c.body_offsets.clone());
        if let Some(f) = &c.face_offsets {
            offset = offset + offset_norm(f.clone());
        }
        terms.push(("offset".into(), offset * w.offset));
        Ok(())
    }

    /// Renders the head crop: L1, LPIPS and the adversarial loss; returns the render for the
    /// discriminator step.
    fn face_terms(
        &self,
        c: &Canonical,
        inputs: &NetInputs,
        sample: &Sample,
        terms: &mut Vec<(String, Tensor<1>)>,
    ) -> Result<Option<Tensor<4>>, AvatarError> {
        let Some(view) = &sample.face else {
            return Ok(None);
        };
        let w = &self.config.losses;
        let pred = self.render_view(c, inputs, view, sample.background)?;
        let gt = image_tensor(&view.image, &self.device);
        terms.push((
            "face_l1".into(),
            l1_loss(pred.clone(), gt.clone()) * w.face_l1,
        ));
        if w.face_lpips > 0.0 {
            let d = self.lpips.forward(pred.clone(), gt)?.mean();
            terms.push(("face_lpips".into(), d * w.face_lpips));
        }
        if let Some(d) = &self.disc {
            let frozen = d.clone().no_grad();
            let g = generator_loss(frozen.forward(pred.clone())?);
            terms.push(("adversarial".into(), g * w.adversarial));
        }
        Ok(Some(pred.detach()))
    }

    fn render_view(
        &self,
        c: &Canonical,
        inputs: &NetInputs,
        view: &View,
        background: [f32; 3],
    ) -> Result<Tensor<4>, AvatarError> {
        let out = render_posed(
            c,
            &inputs.transforms,
            &view.camera,
            background,
            &self.device,
        )
        .map_err(|e| match e {
            // Diverged networks produce non-finite Gaussians before any loss sees them.
            AvatarError::Splat(f3g_splat::SplatError::NonFinite { name, value, .. }) => {
                self.non_finite(self.state.step, &format!("gaussians.{name}"), value as f32)
            }
            other => other,
        })?;
        let pred = nchw(out.color);
        // The boundary band is the background in the ground truth: the same in the render.
        let (h, w) = (view.image.height, view.image.width);
        let band: Vec<f32> = view.band.iter().map(|&b| b as u8 as f32).collect();
        let band = Tensor::<4>::from_data(TensorData::new(band, [1, 1, h, w]), &self.device);
        let bg = Tensor::<4>::from_data(
            TensorData::new(background.to_vec(), [1, 3, 1, 1]),
            &self.device,
        );
        Ok(pred * (band.clone() * -1.0 + 1.0) + bg * band)
    }

    /// One discriminator step on the real head crop and the (detached) render.
    fn discriminator_step(
        &mut self,
        s: u64,
        fake: Tensor<4>,
        real: &View,
    ) -> Result<f32, AvatarError> {
        let (Some(d), Some(optim)) = (self.disc.take(), self.optim_disc.as_mut()) else {
            return Ok(0.0);
        };
        let real = image_tensor(&real.image, &self.device);
        let mut loss = discriminator_loss(d.forward(real.clone())?, d.forward(fake)?);
        let interval = self.config.losses.r1_interval;
        if self.state.disc_steps.is_multiple_of(interval) && self.config.losses.r1_gamma > 0.0 {
            let r1 = r1_penalty(&d, real, self.config.losses.r1_gamma, 1, 1e-2, s ^ 0x51)?;
            loss = loss + r1 * interval as f32;
        }
        let value = loss.clone().into_scalar::<f32>();
        if !value.is_finite() {
            self.disc = Some(d);
            return Err(self.non_finite(s, "discriminator", value));
        }
        let grads = GradientsParams::from_grads(loss.backward(), &d);
        self.disc = Some(optim.step(self.config.lr_discriminator, d, grads));
        self.state.disc_steps += 1;
        Ok(value)
    }

    /// The canonical face model `𝒢`: the body branch's attributes averaged over
    /// `face_init_frames` training frames (each seen from a training camera), then blended
    /// into the densified face texels, with scales divided by the densification factor.
    fn build_face_base(&mut self) -> Result<(), AvatarError> {
        let head = self.setup.head.as_ref().expect("face branch");
        let k = self
            .config
            .face_init_frames
            .min(self.split.frames.len())
            .max(1);
        let plain = self.device.clone().without_autodiff();
        let body = self.nets.body.valid();
        let nets = AvatarNets { body, face: None };
        let constants = Constants::new(&self.setup, &self.config, None, &plain);
        let n = self.setup.body_count();
        let mut sum = [
            vec![0.0f64; 3 * n],
            vec![0.0f64; 3 * n],
            vec![0.0f64; n],
            vec![0.0f64; 3 * n],
            vec![0.0f64; 4 * n],
        ];
        for i in 0..k {
            let frame = self.split.frames[i * self.split.frames.len() / k];
            let camera = self.split.cameras[i % self.split.cameras.len()];
            let inputs = inputs_for(
                &self.setup,
                &constants,
                &self.dataset.params[frame],
                &self.dataset.cameras[camera].camera,
                None,
                None,
                &plain,
            )?;
            let raw = body_outputs(&nets, &constants, &inputs)?;
            let a = body_attributes_host(&raw, &constants);
            for (acc, v) in sum.iter_mut().zip([
                &a.positions,
                &a.colours,
                &a.opacity_logits,
                &a.log_scales,
                &a.quats,
            ]) {
                for (s, x) in acc.iter_mut().zip(v) {
                    *s += *x as f64 / k as f64;
                }
            }
        }
        let blend = |values: &[f64], cols: usize| -> Vec<f32> {
            head.sources
                .iter()
                .flat_map(|taps| {
                    (0..cols).map(move |c| {
                        taps.iter()
                            .map(|&(g, w)| values[g * cols + c] * w as f64)
                            .sum::<f64>() as f32
                    })
                })
                .collect()
        };
        let mut quats = blend(&sum[4], 4);
        for q in quats.chunks_exact_mut(4) {
            let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
            q.iter_mut().for_each(|v| *v /= norm);
        }
        // The densified grid is DENSIFY times finer: so are its Gaussians, or they would blur
        // the detail the face branch is there to add.
        let shrink = (f3g_template::head::DENSIFY as f32).ln();
        let base = FaceBase {
            positions: blend(&sum[0], 3),
            colours: blend(&sum[1], 3),
            opacity_logits: blend(&sum[2], 1),
            log_scales: blend(&sum[3], 3).iter().map(|s| s - shrink).collect(),
            quats,
        };
        self.constants = Constants::new(&self.setup, &self.config, Some(&base), &self.device);
        self.face_base = Some(base);
        Ok(())
    }

    /// Renders the validation view (a held-out camera) and writes GT | render | error grids.
    fn validate(&self) -> Result<(), AvatarError> {
        let Some((camera, frame)) = self.validation_view else {
            return Ok(());
        };
        let plain = self.device.clone().without_autodiff();
        let nets = AvatarNets {
            body: self.nets.body.valid(),
            face: self.nets.face.as_ref().map(Module::valid),
        };
        let constants = Constants::new(&self.setup, &self.config, self.face_base.as_ref(), &plain);
        let cache = std::sync::Mutex::new(f3g_data::loader::ImageCache::new(1 << 28));
        let options = LoaderOptions {
            body_scale: self.config.body_scale,
            face_size: self.config.face_crop_size,
            face_padding: self.config.face_padding,
            ..Default::default()
        };
        let (body, face, _) =
            f3g_data::loader::make_view(&self.dataset, &cache, camera, frame, &options, [1.0; 3])?;
        let inputs = inputs_for(
            &self.setup,
            &constants,
            &self.dataset.params[frame],
            &body.camera,
            None,
            None,
            &plain,
        )?;
        let c = canonical(&nets, &constants, &inputs)?;
        let mut rows = Vec::new();
        for view in std::iter::once(&body).chain(face.as_ref()) {
            let out = render_posed(&c, &inputs.transforms, &view.camera, [1.0; 3], &plain)?;
            let render = report::tensor_to_image(out.color);
            rows.push(report::comparison_row(&view.image, &render));
        }
        let dir = self.run.dir.join("validation");
        std::fs::create_dir_all(&dir).map_err(|e| AvatarError::file(&dir, e))?;
        let grid = report::stack_rows(&rows);
        f3g_io::write_png(&dir.join(format!("step-{:09}.png", self.state.step)), &grid)?;
        f3g_io::write_png(&self.run.dir.join("validation.png"), &grid)?;
        Ok(())
    }
}

/// Mean length of per-Gaussian offsets (smooth at zero).
fn offset_norm(offsets: Tensor<2>) -> Tensor<1> {
    (offsets.powf_scalar(2.0).sum_dim(1) + 1e-12).sqrt().mean()
}

/// The LPIPS square of Animatable Gaussians cut from `[1, 3, H, W]`: the mask's box, padded
/// with the background colour to the square (never clipped, so portrait frames keep the head).
fn square_crop(t: Tensor<4>, square: &CentredSquare, background: [f32; 3]) -> Tensor<4> {
    let [x0, y0, x1, y1] = square.bounds;
    let device = t.device();
    let region = t.slice([0..1, 0..3, y0..y1, x0..x1]);
    let fill = |h: usize, w: usize| {
        Tensor::<4>::from_data(TensorData::new(background.to_vec(), [1, 3, 1, 1]), &device)
            .expand([1, 3, h, w])
    };
    let (w, h, side) = (x1 - x0, y1 - y0, square.side);
    let (left, top) = (
        (x0 as i64 - square.x0) as usize,
        (y0 as i64 - square.y0) as usize,
    );
    let mut row = vec![region];
    if left > 0 {
        row.insert(0, fill(h, left));
    }
    if side - w - left > 0 {
        row.push(fill(h, side - w - left));
    }
    let mut column = vec![Tensor::cat(row, 3)];
    if top > 0 {
        column.insert(0, fill(top, side));
    }
    if side - h - top > 0 {
        column.push(fill(side - h - top, side));
    }
    Tensor::cat(column, 2)
}

/// `n` items spread evenly over `items` (all of them when there are fewer).
fn evenly<T: Clone>(items: &[T], n: usize) -> Vec<T> {
    if items.len() <= n {
        return items.to_vec();
    }
    (0..n).map(|i| items[i * items.len() / n].clone()).collect()
}
