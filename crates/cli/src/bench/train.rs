//! `f3g bench train`: milliseconds per training step, phase by phase, on a device.
//!
//! A run of the chosen preset is created on a capture (a small synthetic one unless `--data`
//! names one) in a temporary folder; the images the steps will draw are decoded first (a
//! training run's loader holds every view once its cache is warm, so the timed steps are a
//! run's steady state, without JPEG decoding and resampling on the loader's thread);
//! `--warmup` steps of the chosen stage compile kernels and build the face model, then
//! `--steps` steps are timed with the device synchronised at every phase boundary
//! (`f3g_avatar::train::PhaseTimer`). Nothing of the run is kept. On a GPU it
//! also counts the distinct kernels the warm-up launched (CubeCL's `LaunchedKernels`): in a
//! fresh process, what its first steps compile — autotune's candidates included.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use f3g_avatar::train::{Phase, PhaseTimer, PhaseTimes, Stage, Trainer};
use f3g_data::synth::{SynthOptions, generate};
use serde::Serialize;

use super::{kernel_count, memory};
use crate::avatar::ConfigArgs;
use crate::device::{DeviceArg, DeviceSpec};

/// The stage whose steps are timed.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum BenchStage {
    Pretrain,
    Body,
    FacePretrain,
    Joint,
    FaceFinetune,
}

impl From<BenchStage> for Stage {
    fn from(s: BenchStage) -> Self {
        match s {
            BenchStage::Pretrain => Stage::Pretrain,
            BenchStage::Body => Stage::Body,
            BenchStage::FacePretrain => Stage::FacePretrain,
            BenchStage::Joint => Stage::Joint,
            BenchStage::FaceFinetune => Stage::FaceFinetune,
        }
    }
}

/// Options of `f3g bench train`.
#[derive(Args, Debug)]
pub struct TrainBenchArgs {
    #[command(flatten)]
    pub device: DeviceArg,
    #[command(flatten)]
    pub config: ConfigArgs,
    /// The stage to time (joint: every network, both renders, LPIPS and the discriminator).
    #[arg(long, value_enum, default_value = "joint")]
    pub stage: BenchStage,
    /// Timed steps (1–100000).
    #[arg(long, default_value_t = 5, value_parser = crate::bounds::size::<1, 100_000>)]
    pub steps: usize,
    /// Untimed steps first (kernel compilation, autotuning, the face model).
    #[arg(long, default_value_t = 2, value_parser = crate::bounds::size::<0, 1000>)]
    pub warmup: usize,
    /// Capture to train on; default: a synthetic one (4 frames, the preset's image size:
    /// 576×768 for cpu presets, 1536×2048 for paper), made in a temporary folder.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Write the numbers as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Time whole steps only, as training runs them: no synchronisation at each phase's end
    /// (the device waits only where a step reads values back), so no phase times. What the
    /// phases' synchronisations cost is the step time with them minus this.
    #[arg(long)]
    pub unsynced: bool,
}

#[derive(Serialize)]
struct TrainBench {
    device: String,
    preset: String,
    stage: String,
    steps: usize,
    /// Milliseconds per step, wall clock, the phase synchronisations included.
    step_ms: f64,
    /// Milliseconds per step of each phase (none with `--unsynced`).
    phases: Option<PhaseTimes>,
    /// The most memory the device's allocator held (GPU), or the most the process allocated
    /// on the heap during the timed steps (CPU), MiB.
    peak_mib: Option<f64>,
    /// Milliseconds of the warm-up steps together: on a GPU in a fresh process, with every
    /// kernel's compilation (or its load from the kernel cache) and autotuning.
    warmup_ms: f64,
    /// Distinct kernels the warm-up steps launched, each compiled once by a fresh process
    /// (GPU devices only).
    warmup_kernels: Option<usize>,
    body_gaussians: usize,
    face_gaussians: usize,
}

pub fn run(a: &TrainBenchArgs) -> Result<()> {
    let device = a.device.open()?;
    let mut config = a.config.load(|_| {})?;
    let preset = config.preset.clone();
    // Nothing is written during the bench; keep the run's own periodic outputs out of it too.
    config.checkpoint_every = u64::MAX;
    config.validate_every = u64::MAX;
    let work = tempfile::tempdir().context("creating a temporary folder")?;
    let data = match &a.data {
        Some(d) => d.clone(),
        None => {
            let mut options = if preset == "paper" {
                SynthOptions::paper()
            } else {
                SynthOptions::default()
            };
            options.frames = 4;
            eprintln!(
                "making a synthetic capture ({} cameras × {} frames, {}×{})",
                options.cameras,
                options.frames,
                options.resolution * 3 / 4,
                options.resolution
            );
            let dir = work.path().join("capture");
            generate(&dir, &options, &|_| {})?;
            dir
        }
    };
    let mut trainer = Trainer::create(
        &work.path().join("run"),
        &data,
        None,
        config,
        None,
        None,
        std::slice::from_ref(&device),
    )?;
    let timer = phase_trace(PhaseTimer::new(&device))?;
    eprintln!(
        "timing {} + {} warm-up steps of the {:?} stage on {} ({} body + {} face Gaussians)",
        a.steps,
        a.warmup,
        Stage::from(a.stage),
        a.device,
        trainer.setup().body_count(),
        trainer.setup().face_count()
    );
    let stage = Stage::from(a.stage);
    // The timed steps replay the warm-up's samples: every one of their images decoded now,
    // before the warm-up's clock and kernel count start, and their loader made now, so that
    // its worker has prepared them when they start (a training run's loader runs throughout).
    trainer.decode_ahead(stage, a.warmup.max(a.steps) as u64)?;
    let mut warmup_samples = trainer.bench_samples(stage)?;
    let mut timed_samples = trainer.bench_samples(stage)?;
    // The device's work done before a clock is read.
    let finish = || {
        device
            .sync()
            .map_err(|e| anyhow::anyhow!("the device failed: {e:?}"))
    };
    let launched = kernel_count::start(a.device.spec != DeviceSpec::Cpu);
    let start = Instant::now();
    let phase_timer = (!a.unsynced).then_some(&timer);
    trainer.bench(&mut warmup_samples, a.warmup as u64, 0, phase_timer)?;
    drop(warmup_samples);
    finish()?;
    let warmup_ms = start.elapsed().as_secs_f64() * 1e3;
    let warmup_kernels = launched.map(kernel_count::finish);
    let before = memory::live_bytes();
    memory::reset_peak();
    let start = Instant::now();
    trainer.bench(&mut timed_samples, 0, a.steps as u64, phase_timer)?;
    finish()?;
    let step_ms = start.elapsed().as_secs_f64() * 1e3 / a.steps as f64;
    let phases = phase_timer.map(|t| t.take(a.steps as u64));
    let peak_mib = match device.memory_pool_usage() {
        Some(usage) => Some(usage.bytes_reserved as f64 / (1 << 20) as f64),
        None if a.device.spec == DeviceSpec::Cpu => {
            Some(memory::peak_bytes().saturating_sub(before) as f64 / (1 << 20) as f64)
        }
        None => None,
    };
    let result = TrainBench {
        device: a.device.to_string(),
        preset,
        stage: format!("{stage:?}"),
        steps: a.steps,
        step_ms,
        phases,
        peak_mib,
        warmup_ms,
        warmup_kernels,
        body_gaussians: trainer.setup().body_count(),
        face_gaussians: trainer.setup().face_count(),
    };
    match &result.phases {
        Some(phases) => {
            println!("{:<14} {:>10}  what", "phase", "ms/step");
            for (phase, ms) in &phases.phases {
                println!("{phase:<14} {ms:>10.1}  {}", phase.meaning());
            }
            let phase_sum: f64 = phases.phases.iter().map(|p| p.1).sum();
            println!(
                "{:<14} {:>10.1}  wall clock per step (phases sum to {phase_sum:.1})",
                "step", result.step_ms
            );
        }
        None => println!(
            "{:<14} {:>10.1}  wall clock per step, without the phases' synchronisations",
            "step", result.step_ms
        ),
    }
    match result.peak_mib {
        Some(m) => println!("peak memory {m:.0} MiB"),
        None => println!("peak memory: not reported by this device"),
    }
    match result.warmup_kernels {
        Some(n) => println!(
            "warm-up: {} steps in {:.1} s, {n} distinct kernels launched (each compiled, or loaded \
             from the kernel cache, once per process)",
            a.warmup,
            warmup_ms / 1e3
        ),
        None => println!("warm-up: {} steps in {:.1} s", a.warmup, warmup_ms / 1e3),
    }
    debug_assert!(
        result
            .phases
            .as_ref()
            .is_none_or(|p| p.phases.len() == Phase::ALL.len())
    );
    if let Some(path) = &a.json {
        f3g_io::write_atomic(path, serde_json::to_string_pretty(&result)?.as_bytes())?;
    }
    Ok(())
}

/// With `F3G_PHASE_TRACE=FILE`, the timer appends `P start` when a step starts and `P <phase>`
/// when a phase ends, each after the device finished the phase's work: beside a driver that
/// appends its launches to the same file (tools/offline-cuda's `F3G_OFFLINE_TRACE`), every
/// launch lands between the marks of its phase (tools/phase_profile.py).
fn phase_trace(timer: PhaseTimer) -> Result<PhaseTimer> {
    let Some(path) = std::env::var_os("F3G_PHASE_TRACE").filter(|p| !p.is_empty()) else {
        return Ok(timer);
    };
    let file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&path)
        .with_context(|| format!("opening F3G_PHASE_TRACE {}", PathBuf::from(&path).display()))?;
    Ok(timer.with_sync_hook(move |ended| {
        use std::io::Write;
        let name = ended.map_or("start", Phase::name);
        // One unbuffered write per mark, so the driver's lines and these stay in order.
        let _ = (&file).write_all(format!("P {name}\n").as_bytes());
    }))
}
