//! One data-parallel step: every replica computes the gradients of its samples (in its own
//! thread when there are several), the gradients are summed across replicas, and every
//! replica applies the same update; then the discriminator the same way.

use burn::tensor::{Device, Tensor};

use super::profile::{Phase, PhaseTimer, mark};
use super::sample::DeviceSample;
use super::schedule::Stage;
use super::step::{SampleGradients, StepContext, adam, add_values, sum_gradients};
use super::{StepReport, Trainer, face_model};
use crate::AvatarError;
use crate::model::Constants;

impl Trainer {
    /// Step `s` on one sample per replica: gradients on every replica, their mean, the same
    /// update everywhere; then the discriminator the same way.
    pub(super) fn run_step(
        &mut self,
        s: u64,
        samples: &[DeviceSample],
        timer: Option<&PhaseTimer>,
    ) -> Result<StepReport, AvatarError> {
        let stage = self.schedule.stage(s);
        let lr = self.schedule.lr(s);
        if self.schedule.resets_body_optimiser(s) {
            for r in &mut self.replicas {
                r.optimisers.body = adam(self.config.adam_epsilon);
            }
        }
        if self.schedule.needs_face_model(s) && self.face_base.is_none() {
            let r = &self.replicas[0];
            let base = face_model::build(
                &self.setup,
                &self.config,
                &r.nets.body,
                &self.dataset,
                &self.split,
                &r.device,
            )?;
            for r in &mut self.replicas {
                r.constants =
                    Constants::new(&self.setup, &self.config.model, Some(&base), &r.device);
            }
            self.face_base = Some(base);
        }
        let per_rank = self.gradients(stage, s, samples, timer)?;
        let devices: Vec<Device> = self.replicas.iter().map(|r| r.device.clone()).collect();
        let mut values: Vec<(String, f32)> = Vec::new();
        let (mut body, mut face, mut fakes) = (Vec::new(), Vec::new(), Vec::new());
        for g in per_rank {
            add_values(&mut values, &g.values);
            body.push(g.body);
            face.push(g.face);
            fakes.extend(g.fakes);
        }
        let nets = &self.replicas[0].nets;
        let body = sum_gradients(&nets.body, body, &devices, self.all_reduce);
        let face = match &nets.face {
            Some(f) => sum_gradients(f, face, &devices, self.all_reduce),
            None => face,
        };
        for ((r, b), f) in self.replicas.iter_mut().zip(body).zip(face) {
            r.apply(stage, lr, b, f);
        }
        mark(timer, Phase::Optimiser)?;
        let total = values.iter().map(|v| v.1).sum();
        if let Some(d_loss) = self.discriminator_step(s, fakes, samples)? {
            values.push(("discriminator".into(), d_loss));
        }
        mark(timer, Phase::Discriminator)?;
        Ok(StepReport {
            step: s,
            stage,
            lr,
            frame: samples[0].frame,
            camera: samples[0].camera,
            losses: values,
            total,
            seconds: self.state.seconds,
        })
    }

    /// Every replica's gradients for its `batch` samples (in parallel threads when there are
    /// several replicas).
    fn gradients(
        &self,
        stage: Stage,
        s: u64,
        samples: &[DeviceSample],
        timer: Option<&PhaseTimer>,
    ) -> Result<Vec<SampleGradients>, AvatarError> {
        let ctx = StepContext {
            config: &self.config,
            stage,
            step: s,
            timer,
        };
        let share = 1.0 / samples.len() as f32;
        if let [replica] = self.replicas.as_slice() {
            return Ok(vec![replica.gradients(&ctx, samples, share)?]);
        }
        std::thread::scope(|scope| {
            let handles: Vec<_> = self
                .replicas
                .iter()
                .zip(samples.chunks(self.config.batch))
                .map(|(r, own)| scope.spawn(move || r.gradients(&ctx, own, share)))
                .collect();
            handles
                .into_iter()
                .map(|h| {
                    h.join()
                        .map_err(|_| AvatarError::Invalid("a replica's thread panicked".into()))?
                })
                .collect()
        })
    }

    /// The discriminator's step on every head render of the step (`fakes`, in sample order),
    /// the mean over them as one update on every replica; its mean loss, or `None` when no
    /// sample had a head render (or there is no discriminator).
    fn discriminator_step(
        &mut self,
        s: u64,
        fakes: Vec<Option<Tensor<4>>>,
        samples: &[DeviceSample],
    ) -> Result<Option<f32>, AvatarError> {
        if self.replicas[0].disc.is_none() {
            return Ok(None);
        }
        let mut pairs: Vec<Vec<(Tensor<4>, Tensor<4>)>> = vec![Vec::new(); self.replicas.len()];
        for (i, (fake, sample)) in fakes.into_iter().zip(samples).enumerate() {
            if let (Some(fake), Some(real)) = (fake, sample.face.as_ref()) {
                pairs[i / self.config.batch].push((fake, real.image.clone()));
            }
        }
        let count = pairs.iter().map(Vec::len).sum::<usize>();
        if count == 0 {
            return Ok(None);
        }
        let share = 1.0 / count as f32;
        let interval = self.config.losses.r1_interval;
        let r1 =
            self.state.disc_steps.is_multiple_of(interval) && self.config.losses.r1_gamma > 0.0;
        let mut grads = Vec::with_capacity(pairs.len());
        let mut loss = 0.0;
        for (r, own) in self.replicas.iter().zip(pairs) {
            let g = r.discriminator_gradients(&self.config, s, r1, own, share)?;
            grads.push(g.map(|(value, g)| {
                loss += value;
                g
            }));
        }
        let devices: Vec<Device> = self.replicas.iter().map(|r| r.device.clone()).collect();
        if let Some(disc) = self.replicas[0].disc.as_ref() {
            let grads = sum_gradients(disc, grads, &devices, self.all_reduce);
            for (r, g) in self.replicas.iter_mut().zip(grads) {
                if let Some(g) = g {
                    r.apply_discriminator(self.config.lr_discriminator, g);
                }
            }
        }
        self.state.disc_steps += 1;
        Ok(Some(loss))
    }
}
