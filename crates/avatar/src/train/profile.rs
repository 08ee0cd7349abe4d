//! Where a training step's time goes (`f3g bench train`).
//!
//! GPU work runs asynchronously, so a phase's time is only meaningful when the device has
//! finished it: [`PhaseTimer::mark`] waits for the device, then charges the time since the
//! previous mark to the phase that just ended. Training never passes a timer, so it pays no
//! synchronisation. The backward pass is one phase: it runs through networks, splatting and
//! LPIPS together.

use std::sync::Mutex;
use std::time::Instant;

use burn::tensor::Device;
use serde::Serialize;

use crate::AvatarError;

/// The phases of a step, in the order they run.
pub const PHASES: [&str; 10] = [
    "data",
    "inputs",
    "networks",
    "render",
    "lpips",
    "adversarial",
    "readback",
    "backward",
    "optimiser",
    "discriminator",
];

/// What each phase means, for the bench's legend.
pub const PHASE_MEANINGS: [&str; 10] = [
    "waiting for the loader's worker thread (decoding, crops, the frame's joint transforms, upload)",
    "posed and view maps, skinning and nearest rotations of every Gaussian, on the device",
    "body and face networks forward, fusion into canonical Gaussians",
    "LBS and the splatting op forward (its intersection-count readback included)",
    "LPIPS forward on the body square and the head crop",
    "the discriminator's forward for the generator loss",
    "the loss values read back for the log and the non-finite check",
    "the backward pass through everything",
    "Adam steps of the body and face networks",
    "the discriminator's step (forward, R1, backward, Adam)",
];

/// Accumulated seconds per phase, with the device synchronised at every mark.
pub struct PhaseTimer {
    device: Device,
    state: Mutex<(Instant, [f64; PHASES.len()])>,
}

/// Milliseconds per phase of one or more steps.
#[derive(Clone, Debug, Serialize)]
pub struct PhaseTimes {
    pub phases: Vec<(String, f64)>,
}

impl PhaseTimer {
    pub fn new(device: &Device) -> Self {
        Self {
            device: device.clone(),
            state: Mutex::new((Instant::now(), [0.0; PHASES.len()])),
        }
    }

    /// Starts timing from now (the time since the last mark is not charged).
    pub fn restart(&self) -> Result<(), AvatarError> {
        self.sync()?;
        self.lock().0 = Instant::now();
        Ok(())
    }

    /// Ends `phase` (one of [`PHASES`]): waits for the device, charges the time since the
    /// previous mark to it.
    pub fn mark(&self, phase: &str) -> Result<(), AvatarError> {
        self.sync()?;
        let index = PHASES
            .iter()
            .position(|p| *p == phase)
            .ok_or_else(|| AvatarError::Invalid(format!("unknown phase `{phase}`")))?;
        let mut state = self.lock();
        let now = Instant::now();
        state.1[index] += (now - state.0).as_secs_f64();
        state.0 = now;
        Ok(())
    }

    /// Milliseconds per phase so far, divided by `steps`, and resets the totals.
    pub fn take(&self, steps: u64) -> PhaseTimes {
        let mut state = self.lock();
        let totals = std::mem::replace(&mut state.1, [0.0; PHASES.len()]);
        PhaseTimes {
            phases: PHASES
                .iter()
                .zip(totals)
                .map(|(p, t)| (p.to_string(), t * 1e3 / steps.max(1) as f64))
                .collect(),
        }
    }

    fn sync(&self) -> Result<(), AvatarError> {
        self.device
            .sync()
            .map_err(|e| AvatarError::Invalid(format!("the device failed: {e:?}")))
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, (Instant, [f64; PHASES.len()])> {
        // A panic while holding the lock leaves plain numbers: still usable.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Marks `phase` on `timer` when there is one.
pub fn mark(timer: Option<&PhaseTimer>, phase: &str) -> Result<(), AvatarError> {
    timer.map_or(Ok(()), |t| t.mark(phase))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_is_charged_to_the_phase_that_ended() {
        let timer = PhaseTimer::new(&Device::flex());
        timer.restart().unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
        timer.mark("render").unwrap();
        timer.mark("backward").unwrap();
        let times = timer.take(2);
        let get = |p: &str| times.phases.iter().find(|x| x.0 == p).unwrap().1;
        assert!(get("render") >= 10.0, "{times:?}");
        assert!(get("backward") < get("render"));
        assert_eq!(get("data"), 0.0);
        assert!(timer.mark("nonsense").is_err());
        assert!(timer.take(1).phases.iter().all(|p| p.1 < 10.0));
    }
}
