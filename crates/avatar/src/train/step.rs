//! One training step on one device, in two halves: [`Replica::gradients`] computes the losses of
//! a sample and their gradients and changes nothing; [`Replica::apply`] runs the optimisers.
//! Between the two, data-parallel training averages the gradients of every replica
//! ([`sum_gradients`]), so every replica applies the same update and the replicas stay equal.
//! The discriminator step follows the same pattern on the detached head renders.
//!
//! Host readbacks in a step: the splat op's intersection count (one per render, inside the op)
//! and the loss values, read together as one `[terms]` tensor (for the log and the non-finite
//! check, which must stop a diverged run before its update is applied).

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor};

use super::losses::{Losses, Terms};
use super::profile::{PhaseTimer, mark};
use super::schedule::Stage;
use crate::AvatarError;
use crate::config::TrainConfig;
use crate::inputs::inputs_for;
use crate::model::{AvatarNets, Constants, body_outputs, canonical};
use crate::setup::Setup;
use f3g_data::loader::{Sample, View};
use f3g_nets::discriminator::{discriminator_loss, r1_penalty};
use f3g_nets::metrics::image_tensor;
use f3g_nets::{Discriminator, Lpips};

/// Adam of the avatar's networks.
pub fn adam(epsilon: f32) -> ModuleOptimizer {
    AdamConfig::new().with_epsilon(epsilon).init()
}

/// Adam of the discriminator (StyleGAN2's betas).
pub fn adam_disc() -> ModuleOptimizer {
    AdamConfig::new().with_beta_1(0.0).with_beta_2(0.99).init()
}

/// The optimisers of one replica: body and face networks separately (so that stages can freeze
/// one), and the discriminator's.
#[derive(Clone)]
pub struct Optimisers {
    pub body: ModuleOptimizer,
    pub face: Option<ModuleOptimizer>,
    pub disc: Option<ModuleOptimizer>,
}

/// A copy of everything trainable, and what the losses read, on one device.
pub struct Replica {
    /// The device, with autodiff.
    pub device: Device,
    pub nets: AvatarNets,
    pub constants: Constants,
    pub lpips: Lpips,
    pub disc: Option<Discriminator>,
    pub optimisers: Optimisers,
}

/// What every replica's step reads: the setup, the configuration, the step and its stage, and
/// the phase timer when `f3g bench train` asks.
#[derive(Clone, Copy)]
pub struct StepContext<'a> {
    pub setup: &'a Setup,
    pub config: &'a TrainConfig,
    pub stage: Stage,
    pub step: u64,
    pub timer: Option<&'a PhaseTimer>,
}

/// What a replica's samples give: the named loss values (weighted by their share, summed over
/// the samples) and the gradients of their sum.
pub struct SampleGradients {
    pub values: Vec<(String, f32)>,
    /// `None` when the stage had nothing to differentiate for this sample (a face stage on a
    /// sample without a head crop).
    pub body: Option<GradientsParams>,
    pub face: Option<GradientsParams>,
    /// The detached head render of each sample that has one, for the discriminator step.
    pub fakes: Vec<Option<Tensor<4>>>,
}

impl Replica {
    /// The losses of `samples` at `ctx.step`, each weighted by `share` (its part of the step's
    /// mean loss: `1 / (replicas · batch)`), and the gradients of their sum.
    pub fn gradients(
        &self,
        ctx: &StepContext,
        samples: &[Sample],
        share: f32,
    ) -> Result<SampleGradients, AvatarError> {
        let (config, step, timer) = (ctx.config, ctx.step, ctx.timer);
        let losses = Losses {
            config,
            constants: &self.constants,
            lpips: &self.lpips,
            disc: self.disc.as_ref(),
            device: &self.device,
            step,
            timer,
        };
        let mut terms = Terms::new();
        let mut fakes = Vec::with_capacity(samples.len());
        for sample in samples {
            let (sample_terms, fake) = self.sample_terms(ctx, &losses, sample)?;
            // One sample per step (the paper's setting) keeps its losses bit for bit.
            terms.extend(
                sample_terms
                    .into_iter()
                    .map(|(name, t)| (name, if share == 1.0 { t } else { t * share })),
            );
            fakes.push(fake);
        }
        let values = read_values(step, &terms)?;
        mark(timer, "readback")?;
        let (mut body, mut face) = (None, None);
        if let Some(total) = terms.into_iter().map(|t| t.1).reduce(|a, b| a + b) {
            let mut grads = total.backward();
            body = Some(GradientsParams::from_module(&mut grads, &self.nets.body));
            face = self
                .nets
                .face
                .as_ref()
                .map(|f| GradientsParams::from_module(&mut grads, f));
        }
        mark(timer, "backward")?;
        Ok(SampleGradients {
            values,
            body,
            face,
            fakes,
        })
    }

    /// The loss terms of one sample, and its detached head render when the stage renders one.
    fn sample_terms(
        &self,
        ctx: &StepContext,
        losses: &Losses,
        sample: &Sample,
    ) -> Result<(Terms, Option<Tensor<4>>), AvatarError> {
        let (setup, config, stage) = (ctx.setup, ctx.config, ctx.stage);
        // View noise is a pure function of the seed and the sample, like the sample itself.
        let noise_seed = config.seed ^ sample.index.wrapping_mul(0x2545_f491_4f6c_dd1d);
        let inputs = inputs_for(
            setup,
            &self.constants,
            &sample.params,
            &sample.body.camera,
            Some((config.view_noise, noise_seed)),
            None,
            &self.device,
        )?;
        mark(losses.timer, "inputs")?;
        let mut terms = Terms::new();
        let mut fake = None;
        match stage {
            Stage::Pretrain => {
                let raw = body_outputs(&self.nets, &self.constants, &inputs)?;
                terms.push(("pretrain".into(), losses.pretrain(&raw)));
                mark(losses.timer, "networks")?;
            }
            Stage::FacePretrain => {
                let c = canonical(&self.face_only_nets(), &self.constants, &inputs)?;
                let r = c.face_residuals.ok_or_else(|| {
                    AvatarError::Invalid("face pretraining without face networks".into())
                })?;
                terms.push(("face_pretrain".into(), r.abs().mean()));
                mark(losses.timer, "networks")?;
            }
            Stage::Body | Stage::Joint => {
                let c = canonical(&self.nets, &self.constants, &inputs)?;
                mark(losses.timer, "networks")?;
                losses.body(&c, &inputs, sample, &mut terms)?;
                if stage == Stage::Joint && config.face_losses {
                    fake = losses.face(&c, &inputs, sample, &mut terms)?;
                }
            }
            Stage::FaceFinetune => {
                let c = canonical(&self.face_only_nets(), &self.constants, &inputs)?;
                mark(losses.timer, "networks")?;
                fake = losses.face(&c, &inputs, sample, &mut terms)?;
            }
        }
        Ok((terms, fake))
    }

    /// Updates the networks `stage` trains with (averaged) gradients at learning rate `lr`.
    pub fn apply(
        &mut self,
        stage: Stage,
        lr: f64,
        body: Option<GradientsParams>,
        face: Option<GradientsParams>,
    ) {
        let AvatarNets { body: b, face: f } = self.nets.clone();
        let b = match body {
            Some(g) if stage.trains_body() => self.optimisers.body.step(lr, b, g),
            _ => b,
        };
        let f = match (f, face, self.optimisers.face.as_mut()) {
            (Some(f), Some(g), Some(o)) if stage.trains_face() => Some(o.step(lr, f, g)),
            (f, _, _) => f,
        };
        self.nets = AvatarNets { body: b, face: f };
    }

    /// The discriminator's loss on real head crops and detached renders (each pair weighted by
    /// `share`, its part of the step's mean), with the lazy R1 penalty when `r1`, and its
    /// gradients; `None` without a discriminator or without pairs.
    pub fn discriminator_gradients(
        &self,
        config: &TrainConfig,
        step: u64,
        r1: bool,
        pairs: Vec<(Tensor<4>, &View)>,
        share: f32,
    ) -> Result<Option<(f32, GradientsParams)>, AvatarError> {
        let Some(d) = &self.disc else {
            return Ok(None);
        };
        let mut total: Option<Tensor<1>> = None;
        for (fake, real) in pairs {
            let real = image_tensor(&real.image, &self.device);
            let mut loss = discriminator_loss(d.forward(real.clone())?, d.forward(fake)?);
            if r1 {
                let interval = config.losses.r1_interval;
                let penalty = r1_penalty(d, real, config.losses.r1_gamma, 1, 1e-2, step ^ 0x51)?;
                loss = loss + penalty * interval as f32;
            }
            let loss = if share == 1.0 { loss } else { loss * share };
            total = Some(match total {
                Some(t) => t + loss,
                None => loss,
            });
        }
        let Some(loss) = total else {
            return Ok(None);
        };
        let value = loss.clone().into_scalar::<f32>();
        if !value.is_finite() {
            return Err(non_finite(step, "discriminator", value));
        }
        Ok(Some((
            value,
            GradientsParams::from_grads(loss.backward(), d),
        )))
    }

    /// One optimiser step of the discriminator.
    pub fn apply_discriminator(&mut self, lr: f64, grads: GradientsParams) {
        if let (Some(d), Some(o)) = (self.disc.take(), self.optimisers.disc.as_mut()) {
            self.disc = Some(o.step(lr, d, grads));
        }
    }

    /// The networks with the body frozen (face-only stages): its graph is not tracked.
    fn face_only_nets(&self) -> AvatarNets {
        AvatarNets {
            body: self.nets.body.clone().no_grad(),
            face: self.nets.face.clone(),
        }
    }
}

/// The values of the loss terms, read back together; a NaN or infinite one stops the step.
fn read_values(step: u64, terms: &Terms) -> Result<Vec<(String, f32)>, AvatarError> {
    if terms.is_empty() {
        return Ok(Vec::new());
    }
    // One readback for every term of the step.
    let all = Tensor::cat(terms.iter().map(|t| t.1.clone().detach()).collect(), 0);
    let data = all.into_data().convert::<f32>();
    let numbers = data
        .as_slice::<f32>()
        .map_err(|e| AvatarError::Invalid(format!("loss values: {e:?}")))?;
    let mut values: Vec<(String, f32)> = Vec::new();
    for ((name, _), &v) in terms.iter().zip(numbers) {
        if !v.is_finite() {
            return Err(non_finite(step, name, v));
        }
        // Several samples give the same terms: their shares add up to the mean.
        add_values(&mut values, &[(name.clone(), v)]);
    }
    Ok(values)
}

/// Adds loss values (each already its share of the step's mean) to `values`, by name.
pub fn add_values(values: &mut Vec<(String, f32)>, more: &[(String, f32)]) {
    for (name, v) in more {
        match values.iter_mut().find(|o| &o.0 == name) {
            Some(o) => o.1 += v,
            None => values.push((name.clone(), *v)),
        }
    }
}

fn non_finite(step: u64, name: &str, value: f32) -> AvatarError {
    AvatarError::NonFinite {
        step,
        name: name.to_string(),
        value,
        checkpoint: None,
    }
}

/// The data-parallel all-reduce: sums the gradients of `module`'s parameters over the ranks
/// (each rank's loss is already its share of the step's mean, so the sum is the gradient of the
/// mean; a parameter missing on a rank counts as zero there) and gives every rank the result on
/// its own device. The sum runs on the first rank's device in rank order, so the result does
/// not depend on timing. One rank is returned untouched.
///
/// This is the host-side all-reduce: every backend has it (tensors move through
/// `Tensor::to_device`), which is what the CPU equivalence test runs. Burn's NCCL
/// `all_reduce` (cubecl-cuda only) is the drop-in replacement for CUDA ranks.
pub fn sum_gradients<M: Module>(
    module: &M,
    ranks: Vec<Option<GradientsParams>>,
    devices: &[Device],
) -> Vec<Option<GradientsParams>> {
    if ranks.len() <= 1 || ranks.iter().all(Option::is_none) {
        return ranks;
    }
    let mut sum = Sum {
        ranks: ranks.into_iter().map(Option::unwrap_or_default).collect(),
        out: devices.iter().map(|_| GradientsParams::new()).collect(),
        devices: devices
            .iter()
            .map(|d| d.clone().without_autodiff())
            .collect(),
    };
    module.visit(&mut sum);
    sum.out.into_iter().map(Some).collect()
}

struct Sum {
    ranks: Vec<GradientsParams>,
    out: Vec<GradientsParams>,
    devices: Vec<Device>,
}

impl ModuleVisitor for Sum {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let mut sum: Option<Tensor<D>> = None;
        for grads in &mut self.ranks {
            if let Some(g) = grads.remove::<D>(param.id) {
                let g = g.to_device(&self.devices[0]);
                sum = Some(match sum {
                    Some(s) => s + g,
                    None => g,
                });
            }
        }
        if let Some(sum) = sum {
            for (out, device) in self.out.iter_mut().zip(&self.devices) {
                out.register::<D>(param.id, sum.clone().to_device(device));
            }
        }
    }
}
