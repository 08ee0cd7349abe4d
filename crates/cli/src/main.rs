//! `f3g`: train, evaluate, animate and export face-focused full-body Gaussian avatars.

mod avatar;
mod bench;
mod bounds;
mod data;
mod demo;
mod device;
mod memory;
mod nets;
mod quality;
mod render_ply;
mod rig;
mod template;
mod train_bench;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[global_allocator]
static ALLOCATOR: memory::TrackingAllocator = memory::TrackingAllocator;

/// F3G-Avatar: face-focused full-body Gaussian avatars from multi-view video.
#[derive(Parser, Debug)]
#[command(name = "f3g", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// The whole pipeline on the built-in data: synthetic capture, training, evaluation,
    /// animation and an HTML report (a few minutes on two cores).
    Demo(demo::DemoArgs),
    /// Train an avatar on a capture (or resume a run).
    Train(avatar::TrainArgs),
    /// Evaluate a trained avatar on held-out views or poses (body and head metrics).
    Eval(avatar::EvalArgs),
    /// Animate a trained avatar with a pose sequence (PNG frames, GIF, optional .ply).
    Animate(avatar::AnimateArgs),
    /// Write a trained avatar's posed Gaussians as a standard 3DGS .ply.
    ExportPly(avatar::ExportPlyArgs),
    /// Render a standard 3DGS `.ply` from a camera JSON to PNG (and optionally `.npy`).
    RenderPly(render_ply::RenderPlyArgs),
    /// Body models: pose and inspect them, convert parameters between them.
    #[command(subcommand)]
    Rig(rig::RigCommand),
    /// Render a synthetic multi-view capture of the built-in human.
    Synth(data::SynthArgs),
    /// Captures: validate them, look at them.
    #[command(subcommand)]
    Data(data::DataCommand),
    /// Build a canonical clothed template (body model in the canonical pose + garment).
    Template(template::TemplateArgs),
    /// Write PNG pictures of a template's position maps (canonical, posed, head, mask).
    Posmaps(template::PosmapsArgs),
    /// PSNR, SSIM and LPIPS of two images, as JSON.
    Metrics(nets::MetricsArgs),
    /// Fetch and convert third-party weights (LPIPS VGG).
    #[command(subcommand)]
    Weights(nets::WeightsCommand),
    /// Performance benchmarks.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Demo(args) => demo::demo(&args),
        Command::Train(args) => avatar::train(&args).map(|_| ()),
        Command::Eval(args) => avatar::eval(&args).map(|_| ()),
        Command::Animate(args) => avatar::animate(&args).map(|_| ()),
        Command::ExportPly(args) => avatar::export_ply(&args),
        Command::RenderPly(args) => render_ply::run(&args),
        Command::Rig(cmd) => rig::run(&cmd),
        Command::Synth(args) => data::synth(&args),
        Command::Data(cmd) => data::run(&cmd),
        Command::Template(args) => template::run(&args),
        Command::Posmaps(args) => template::posmaps(&args),
        Command::Bench(bench::BenchCommand::Splat(args)) => bench::run_splat(&args),
        Command::Bench(bench::BenchCommand::Lbs(args)) => bench::run_lbs(&args),
        Command::Bench(bench::BenchCommand::Nets(args)) => nets::bench(&args),
        Command::Bench(bench::BenchCommand::Train(args)) => train_bench::run(&args),
        Command::Bench(bench::BenchCommand::Quality(args)) => quality::quality(&args),
        Command::Metrics(args) => nets::metrics(&args),
        Command::Weights(cmd) => nets::weights(&cmd),
    }
}

#[cfg(test)]
mod tests {
    use clap::{CommandFactory, Parser};

    /// clap's own consistency checks (duplicate flags, conflicts naming missing arguments),
    /// which it otherwise runs only in debug builds.
    #[test]
    fn the_command_line_is_consistent() {
        super::Cli::command().debug_assert();
    }

    /// The flattened argument groups (`--device`, `--model`, `--config/--preset/--set`) parse
    /// together: two groups with one argument id would panic here, not at compile time.
    #[test]
    fn flattened_arguments_parse_together() {
        for line in [
            "train --data d --out o --model builtin --device cpu --preset cpu --set lr=0.001",
            "train --resume r --device cpu",
            "eval r --model builtin --device cpu",
            "bench train --device cpu --preset cpu --set batch=2",
            "demo --device cpu --set steps.joint=1",
        ] {
            let args = std::iter::once("f3g").chain(line.split(' '));
            super::Cli::try_parse_from(args).unwrap_or_else(|e| panic!("{line}: {e}"));
        }
    }
}
