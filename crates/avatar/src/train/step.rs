//! One training step on one device, in two halves: [`Replica::gradients`] computes the losses of
//! a sample and their gradients and changes nothing; [`Replica::apply`] runs the optimisers.
//! Between the two, data-parallel training sums the gradients of every replica (each already
//! weighted by its share of the mean; [`sum_gradients`], on the host or with NCCL, see
//! [`AllReduce`]), so every replica applies the same update and the replicas stay equal.
//! The discriminator step follows the same pattern on the detached head renders.
//!
//! Host readbacks in a step: the splat op's intersection count (one per render, inside the op),
//! the loss values, read together as one `[terms]` tensor, and the discriminator's loss (both
//! for the log and the non-finite check, which must stop a diverged run before its update is
//! applied). Uploads in a step are a few scalars (background colours, column scales) and, on
//! R1 steps, the R1 estimate's random directions; a sample's images and pose were uploaded by
//! the loader's worker thread ([`super::sample`]).

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::distributed::{ReduceOperation, all_reduce};
use burn::tensor::{Device, Tensor};

use super::config::TrainConfig;
use super::losses::{Losses, Terms};
use super::profile::{Phase, PhaseTimer, mark};
use super::sample::DeviceSample;
use super::schedule::Stage;
use crate::AvatarError;
use crate::model::{AvatarNets, Constants, body_outputs, canonical};
use f3g_nets::adam::{FusedAdam, ModuleAdam};
use f3g_nets::discriminator::{R1, discriminator_step_loss};
use f3g_nets::{Discriminator, Lpips};

/// Adam of the avatar's networks (Burn's defaults for the betas), one pass per parameter
/// (several parameters per kernel on GPUs).
pub fn adam(epsilon: f32) -> ModuleAdam {
    FusedAdam {
        beta_1: 0.9,
        beta_2: 0.999,
        epsilon,
    }
    .init()
}

/// Adam of the discriminator (StyleGAN2's betas; Burn's default ε).
pub fn adam_disc() -> ModuleAdam {
    FusedAdam {
        beta_1: 0.0,
        beta_2: 0.99,
        epsilon: 1e-5,
    }
    .init()
}

/// The optimisers of one replica: body and face networks separately (so that stages can freeze
/// one), and the discriminator's.
#[derive(Clone)]
pub struct Optimisers {
    pub body: ModuleAdam,
    pub face: Option<ModuleAdam>,
    pub disc: Option<ModuleAdam>,
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

/// What every replica's step reads: the configuration, the step and its stage, and the phase
/// timer when `f3g bench train` asks.
#[derive(Clone, Copy)]
pub struct StepContext<'a> {
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
        samples: &[DeviceSample],
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
        mark(timer, Phase::Readback)?;
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
        mark(timer, Phase::Backward)?;
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
        sample: &DeviceSample,
    ) -> Result<(Terms, Option<Tensor<4>>), AvatarError> {
        let (config, stage) = (ctx.config, ctx.stage);
        let inputs = self.constants.inputs(
            &sample.pose,
            &sample.body.camera,
            sample.noise.as_ref(),
            None,
        )?;
        mark(losses.timer, Phase::Inputs)?;
        let mut terms = Terms::new();
        let mut fake = None;
        match stage {
            Stage::Pretrain => {
                let raw = body_outputs(&self.nets, &self.constants, &inputs)?;
                terms.push(("pretrain".into(), losses.pretrain(&raw)));
                mark(losses.timer, Phase::Networks)?;
            }
            Stage::FacePretrain => {
                let c = canonical(&self.face_only_nets(), &self.constants, &inputs)?;
                let r = c.face_residuals.ok_or_else(|| {
                    AvatarError::Invalid("face pretraining without face networks".into())
                })?;
                terms.push(("face_pretrain".into(), r.abs().mean()));
                mark(losses.timer, Phase::Networks)?;
            }
            Stage::Body | Stage::Joint => {
                let c = canonical(&self.nets, &self.constants, &inputs)?;
                mark(losses.timer, Phase::Networks)?;
                losses.body(&c, &inputs, sample, &mut terms)?;
                if stage == Stage::Joint && config.face_losses {
                    fake = losses.face(&c, &inputs, sample, &mut terms)?;
                }
            }
            Stage::FaceFinetune => {
                let c = canonical(&self.face_only_nets(), &self.constants, &inputs)?;
                mark(losses.timer, Phase::Networks)?;
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

    /// The discriminator's loss on (detached render, real head crop) pairs (each pair weighted
    /// by `share`, its part of the step's mean), with the lazy R1 penalty when `r1`, and its
    /// gradients; `None` without a discriminator or without pairs.
    pub fn discriminator_gradients(
        &self,
        config: &TrainConfig,
        step: u64,
        r1: bool,
        pairs: Vec<(Tensor<4>, Tensor<4>)>,
        share: f32,
    ) -> Result<Option<(f32, GradientsParams)>, AvatarError> {
        let Some(d) = &self.disc else {
            return Ok(None);
        };
        let mut total: Option<Tensor<1>> = None;
        for (fake, real) in pairs {
            // The lazy R1 penalty every `r1_interval` steps, weighted by the interval.
            let r1 = r1.then_some(R1 {
                gamma: config.losses.r1_gamma * config.losses.r1_interval as f32,
                epsilon: 1e-2,
                seed: step ^ 0x51,
            });
            let loss = discriminator_step_loss(d, real, fake, r1)?;
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

/// How data-parallel replicas sum their gradients.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum AllReduce {
    /// On the host's terms: every gradient moves to the first device with
    /// `Tensor::to_device`, is summed there in rank order and moves back. Every backend has it,
    /// and the sum does not depend on timing (what the CPU equivalence test runs).
    #[default]
    Host,
    /// Burn's collective `all_reduce` (NCCL through cubecl-cuda): device to device, in NCCL's
    /// order. Only for ranks that are distinct CUDA devices of a machine with `libnccl`; the
    /// caller, which knows the devices, chooses it.
    Collective,
}

/// The data-parallel all-reduce: sums the gradients of `module`'s parameters over the ranks
/// (each rank's loss is already its share of the step's mean, so the sum is the gradient of the
/// mean; a parameter missing on a rank counts as zero there) and gives every rank the result on
/// its own device. One rank is returned untouched.
pub fn sum_gradients<M: Module>(
    module: &M,
    ranks: Vec<Option<GradientsParams>>,
    devices: &[Device],
    how: AllReduce,
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
        how,
    };
    module.visit(&mut sum);
    sum.out.into_iter().map(Some).collect()
}

struct Sum {
    ranks: Vec<GradientsParams>,
    out: Vec<GradientsParams>,
    devices: Vec<Device>,
    how: AllReduce,
}

impl ModuleVisitor for Sum {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let grads: Vec<Option<Tensor<D>>> = self
            .ranks
            .iter_mut()
            .map(|g| g.remove::<D>(param.id))
            .collect();
        // Every rank takes part or none does (a collective needs all of them).
        let Some(shape) = grads.iter().flatten().next().map(Tensor::shape) else {
            return;
        };
        let sums: Vec<Tensor<D>> = match self.how {
            AllReduce::Host => {
                let first = &self.devices[0];
                let sum = grads
                    .into_iter()
                    .flatten()
                    .map(|g| g.to_device(first))
                    .reduce(|a, b| a + b)
                    .expect("one gradient at least");
                self.devices
                    .iter()
                    .map(|d| sum.clone().to_device(d))
                    .collect()
            }
            AllReduce::Collective => {
                // Issue every rank's reduction before waiting for any.
                let pending: Vec<_> = grads
                    .into_iter()
                    .zip(&self.devices)
                    .map(|(g, d)| {
                        let g = g.unwrap_or_else(|| Tensor::zeros(shape.clone(), d));
                        all_reduce(g, ReduceOperation::Sum, self.devices.clone())
                    })
                    .collect();
                pending.into_iter().map(|p| p.resolve()).collect()
            }
        };
        for (out, s) in self.out.iter_mut().zip(sums) {
            out.register::<D>(param.id, s);
        }
    }
}
