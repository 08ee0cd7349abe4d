//! What `f3g bench train` uses: the phase timer, and the trainer's hooks that run steps of a
//! stage without writing anything.
//!
//! GPU work runs asynchronously, so a phase's time is only meaningful when the device has
//! finished it: [`PhaseTimer::mark`] waits for the device, then charges the time since the
//! previous mark to the phase that just ended. Training never passes a timer, so it pays no
//! synchronisation. The backward pass is one phase: it runs through networks, splatting and
//! LPIPS together.

use std::fmt;
use std::sync::Mutex;
use std::time::Instant;

use burn::tensor::Device;
use serde::Serialize;

use f3g_data::loader::Loader;

use super::sample::DeviceSample;
use super::schedule::Stage;
use super::{StepReport, Trainer, next_samples};
use crate::AvatarError;

/// The phases of a step, in the order they run (a phase is a type, so a misspelt one does
/// not compile).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    Data,
    Inputs,
    Networks,
    Render,
    Lpips,
    Adversarial,
    Readback,
    Backward,
    Optimiser,
    Discriminator,
}

impl Phase {
    /// Every phase, in the order they run.
    pub const ALL: [Phase; 10] = [
        Phase::Data,
        Phase::Inputs,
        Phase::Networks,
        Phase::Render,
        Phase::Lpips,
        Phase::Adversarial,
        Phase::Readback,
        Phase::Backward,
        Phase::Optimiser,
        Phase::Discriminator,
    ];

    /// The name the bench prints and writes (as serialised).
    pub fn name(self) -> &'static str {
        match self {
            Phase::Data => "data",
            Phase::Inputs => "inputs",
            Phase::Networks => "networks",
            Phase::Render => "render",
            Phase::Lpips => "lpips",
            Phase::Adversarial => "adversarial",
            Phase::Readback => "readback",
            Phase::Backward => "backward",
            Phase::Optimiser => "optimiser",
            Phase::Discriminator => "discriminator",
        }
    }

    /// What the phase times, for the bench's legend.
    pub fn meaning(self) -> &'static str {
        match self {
            Phase::Data => {
                "waiting for the loader's worker thread (decoding, crops, the frame's joint transforms, upload)"
            }
            Phase::Inputs => {
                "posed and view maps, skinning and nearest rotations of every Gaussian, on the device"
            }
            Phase::Networks => "body and face networks forward, fusion into canonical Gaussians",
            Phase::Render => {
                "LBS and the splatting op forward (its intersection-count readback included)"
            }
            Phase::Lpips => "LPIPS forward on the body square and the head crop",
            Phase::Adversarial => "the discriminator's forward for the generator loss",
            Phase::Readback => "the loss values read back for the log and the non-finite check",
            Phase::Backward => "the backward pass through everything",
            Phase::Optimiser => "Adam steps of the body and face networks",
            Phase::Discriminator => "the discriminator's step (forward, R1, backward, Adam)",
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// The phase's name, padded as asked (`{phase:<14}`).
impl fmt::Display for Phase {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.pad(self.name())
    }
}

/// Accumulated seconds per phase, with the device synchronised at every mark.
pub struct PhaseTimer {
    device: Device,
    state: Mutex<(Instant, [f64; Phase::ALL.len()])>,
    on_sync: Option<SyncHook>,
}

/// Called right after each of the timer's synchronisations, with the phase that just ended
/// (`None`: a step starts). All device work launched before it is then done, so a tool that
/// logs launches can tell which phase each belongs to (`f3g bench train`'s
/// `F3G_PHASE_TRACE`, tools/phase_profile.py).
type SyncHook = Box<dyn Fn(Option<Phase>) + Send + Sync>;

/// Milliseconds per phase of one or more steps.
#[derive(Clone, Debug, Serialize)]
pub struct PhaseTimes {
    pub phases: Vec<(Phase, f64)>,
}

impl PhaseTimer {
    pub fn new(device: &Device) -> Self {
        Self {
            device: device.clone(),
            state: Mutex::new((Instant::now(), [0.0; Phase::ALL.len()])),
            on_sync: None,
        }
    }

    /// The timer calling `hook` after each synchronisation (see [`SyncHook`]).
    pub fn with_sync_hook(mut self, hook: impl Fn(Option<Phase>) + Send + Sync + 'static) -> Self {
        self.on_sync = Some(Box::new(hook));
        self
    }

    /// Starts timing from now (the time since the last mark is not charged).
    pub fn restart(&self) -> Result<(), AvatarError> {
        self.sync()?;
        self.synced(None);
        self.lock().0 = Instant::now();
        Ok(())
    }

    /// Ends `phase`: waits for the device, charges the time since the previous mark to it.
    pub fn mark(&self, phase: Phase) -> Result<(), AvatarError> {
        self.sync()?;
        self.synced(Some(phase));
        let mut state = self.lock();
        let now = Instant::now();
        state.1[phase.index()] += (now - state.0).as_secs_f64();
        state.0 = now;
        Ok(())
    }

    /// Milliseconds per phase so far, divided by `steps`, and resets the totals.
    pub fn take(&self, steps: u64) -> PhaseTimes {
        let mut state = self.lock();
        let totals = std::mem::replace(&mut state.1, [0.0; Phase::ALL.len()]);
        PhaseTimes {
            phases: Phase::ALL
                .into_iter()
                .zip(totals)
                .map(|(p, t)| (p, t * 1e3 / steps.max(1) as f64))
                .collect(),
        }
    }

    fn sync(&self) -> Result<(), AvatarError> {
        self.device
            .sync()
            .map_err(|e| AvatarError::Invalid(format!("the device failed: {e:?}")))
    }

    fn synced(&self, ended: Option<Phase>) {
        if let Some(hook) = &self.on_sync {
            hook(ended);
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, (Instant, [f64; Phase::ALL.len()])> {
        // A panic while holding the lock leaves plain numbers: still usable.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The samples [`Trainer::bench`] draws, from [`Trainer::bench_samples`].
pub struct BenchSamples {
    loader: Loader<Result<DeviceSample, AvatarError>>,
    /// The stage's first step and its number of steps.
    first: u64,
    len: u64,
    /// Steps drawn so far.
    drawn: u64,
}

/// Marks `phase` on `timer` when there is one.
pub(super) fn mark(timer: Option<&PhaseTimer>, phase: Phase) -> Result<(), AvatarError> {
    timer.map_or(Ok(()), |t| t.mark(phase))
}

impl Trainer {
    /// The samples of `stage`'s first steps, in the order [`Trainer::bench`] draws them. Its
    /// loader's worker starts preparing them (posing, upload) as soon as it exists: made before
    /// the warm-up, the timed steps' samples are ready when they start, as in a training run,
    /// whose loader runs throughout (made at their start, the first one's preparation was
    /// charged to them: about 200 ms of host time for a `paper` sample on the 2-core VM).
    pub fn bench_samples(&self, stage: Stage) -> Result<BenchSamples, AvatarError> {
        let (first, len) = self.stage_steps(stage)?;
        let per_step = (self.replicas.len() * self.config.batch) as u64;
        Ok(BenchSamples {
            loader: self.loader(first * per_step)?,
            first,
            len,
            drawn: 0,
        })
    }

    /// Runs `warmup + steps` steps (cycling through the stage's steps) on `samples` and writes
    /// nothing: `timer` holds the phases of the last `steps` steps afterwards; without one the
    /// steps run as training runs them, the device synchronised only where a step reads values
    /// back. For `f3g bench train`: the trainer is left mid-run and must not be checkpointed or
    /// trained further.
    pub fn bench(
        &mut self,
        samples: &mut BenchSamples,
        warmup: u64,
        steps: u64,
        timer: Option<&PhaseTimer>,
    ) -> Result<Vec<StepReport>, AvatarError> {
        let per_step = (self.replicas.len() * self.config.batch) as u64;
        let mut reports = Vec::new();
        for i in 0..warmup + steps {
            if let Some(timer) = timer {
                if i == warmup {
                    timer.take(1);
                }
                timer.restart()?;
            }
            let s = samples.first + samples.drawn % samples.len;
            samples.drawn += 1;
            let drawn = next_samples(&mut samples.loader, per_step)?;
            mark(timer, Phase::Data)?;
            let report = self.run_step(s, &drawn, timer)?;
            if i >= warmup {
                reports.push(report);
            }
        }
        Ok(reports)
    }

    /// Decodes the images of the first `steps` steps of `stage` into the loaders' cache, as
    /// [`Trainer::bench`] will draw them: a run's loader holds every training view once its
    /// cache is warm, so a bench that times steps without decoding times a run's steady state.
    pub fn decode_ahead(&mut self, stage: Stage, steps: u64) -> Result<(), AvatarError> {
        let (first, _) = self.stage_steps(stage)?;
        let per_step = (self.replicas.len() * self.config.batch) as u64;
        let mut loader = self.loader(first * per_step)?;
        next_samples(&mut loader, steps * per_step).map(|_| ())
    }

    /// The first step of `stage` and how many steps it has.
    fn stage_steps(&self, stage: Stage) -> Result<(u64, u64), AvatarError> {
        let in_stage: Vec<u64> = (0..self.total_steps())
            .filter(|&s| self.schedule.stage(s) == stage)
            .collect();
        match in_stage.first() {
            Some(&first) => Ok((first, in_stage.len() as u64)),
            None => Err(AvatarError::config(
                "steps",
                format!("the configuration has no {stage:?} steps to time"),
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_is_charged_to_the_phase_that_ended() {
        let timer = PhaseTimer::new(&Device::flex());
        timer.restart().unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
        timer.mark(Phase::Render).unwrap();
        timer.mark(Phase::Backward).unwrap();
        let times = timer.take(2);
        let get = |p: Phase| times.phases.iter().find(|x| x.0 == p).unwrap().1;
        assert!(get(Phase::Render) >= 10.0, "{times:?}");
        assert!(get(Phase::Backward) < get(Phase::Render));
        assert_eq!(get(Phase::Data), 0.0);
        assert!(timer.take(1).phases.iter().all(|p| p.1 < 10.0));
    }
}
