//! `f3g bench`: measured performance, one command per file, and what they share: the median
//! of repetitions, the heap counter ([`memory`]) and the kernel count ([`kernel_count`]).

mod kernel_count;
mod lbs;
pub mod memory;
mod nets;
mod quality;
mod splat;
mod train;

use std::time::Instant;

use anyhow::Result;
use clap::Subcommand;

/// Benchmarks.
#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Forward and forward+backward time of the Gaussian rasteriser.
    Splat(splat::SplatBenchArgs),
    /// Posing the built-in human and skinning many Gaussians (the per-step LBS cost).
    Lbs(lbs::LbsBenchArgs),
    /// Forward and forward+backward time of the StyleUNets, LPIPS and the discriminator.
    Nets(nets::NetsBenchArgs),
    /// Milliseconds per training step of a preset on a device, phase by phase (data, inputs,
    /// networks, render, LPIPS, adversarial, readback, backward, optimiser, discriminator),
    /// and peak memory.
    Train(train::TrainBenchArgs),
    /// Ablations of the face branch (full, face-crop losses only, no face branch, no
    /// adversarial loss, smaller head crops, other face-network capacities), each with several
    /// seeds, on the synthetic capture: mean ± std of body and head metrics on novel views and
    /// novel poses.
    Quality(quality::QualityArgs),
}

/// Runs one benchmark.
pub fn run(command: &BenchCommand) -> Result<()> {
    match command {
        BenchCommand::Splat(args) => splat::run(args),
        BenchCommand::Lbs(args) => lbs::run(args),
        BenchCommand::Nets(args) => nets::run(args),
        BenchCommand::Train(args) => train::run(args),
        BenchCommand::Quality(args) => quality::run(args),
    }
}

/// The median of repetitions (the upper one of an even count); not empty.
fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// Milliseconds since `start`.
fn millis(start: Instant) -> f64 {
    start.elapsed().as_secs_f64() * 1e3
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_median_is_the_upper_middle_value() {
        assert_eq!(super::median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(super::median(vec![4.0, 1.0, 3.0, 2.0]), 3.0);
    }
}
