//! Where a network's CPU time goes: while a profile is running, every convolution `Flex`
//! computes (forward, input gradient, weight gradient) is timed with its shapes, so `f3g bench
//! nets --profile` can split a step into convolutions by phase and everything else. The CPU
//! backend computes eagerly, so wall time around a call is that call's cost; GPU devices are not
//! profiled (their work is queued).

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use serde::Serialize;

/// Which computation of a convolution.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    Forward,
    InputGrad,
    WeightGrad,
}

/// One timed convolution.
#[derive(Clone, Debug, Serialize)]
pub struct Record {
    pub phase: Phase,
    /// `[B, C_in, H, W]`
    pub input: [usize; 4],
    /// `[C_out, C_in / groups, kh, kw]`
    pub weight: [usize; 4],
    /// `[B, C_out, H_out, W_out]`
    pub output: [usize; 4],
    pub seconds: f64,
}

impl Record {
    /// Multiply-adds × 2: the same count for the forward and for each gradient.
    pub fn flops(&self) -> f64 {
        let [b, _, ho, wo] = self.output;
        let [cout, cin_per_group, kh, kw] = self.weight;
        2.0 * (b * cout * ho * wo * cin_per_group * kh * kw) as f64
    }
}

static ACTIVE: AtomicBool = AtomicBool::new(false);
static RECORDS: Mutex<Vec<Record>> = Mutex::new(Vec::new());

/// Starts recording (and forgets an unfinished profile).
pub fn start() {
    RECORDS.lock().unwrap_or_else(|e| e.into_inner()).clear();
    ACTIVE.store(true, Ordering::SeqCst);
}

/// Stops recording and returns what was recorded since [`start`].
pub fn finish() -> Vec<Record> {
    ACTIVE.store(false, Ordering::SeqCst);
    std::mem::take(&mut *RECORDS.lock().unwrap_or_else(|e| e.into_inner()))
}

/// Runs `f`, timed when a profile is running. `shapes` gives (input, weight, output) and is
/// called only then, after `f`.
pub(crate) fn timed<T>(
    phase: Phase,
    f: impl FnOnce() -> T,
    shapes: impl FnOnce(&T) -> [[usize; 4]; 3],
) -> T {
    if !ACTIVE.load(Ordering::Relaxed) {
        return f();
    }
    let start = Instant::now();
    let out = f();
    let seconds = start.elapsed().as_secs_f64();
    let [input, weight, output] = shapes(&out);
    RECORDS
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .push(Record {
            phase,
            input,
            weight,
            output,
            seconds,
        });
    out
}
