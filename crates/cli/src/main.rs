//! `f3g`: train, evaluate, animate and export face-focused full-body Gaussian avatars.

mod avatar;
mod bench;
mod bounds;
mod cuda_probe;
mod data;
mod demo;
mod device;
mod fit;
mod interrupt;
mod metrics;
mod motion;
mod render_ply;
mod rig;
mod server;
mod template;
mod view;
mod weights;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};

#[global_allocator]
static ALLOCATOR: bench::memory::TrackingAllocator = bench::memory::TrackingAllocator;

/// F3G-Avatar: face-focused full-body Gaussian avatars from multi-view video.
#[derive(Parser, Debug)]
#[command(name = "f3g", version, long_about = None)]
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
    /// Animate a trained avatar with a motion (PNG frames, GIF, optional .ply).
    Animate(avatar::AnimateArgs),
    /// Write a trained avatar's posed Gaussians as a standard 3DGS .ply.
    ExportPly(avatar::ExportPlyArgs),
    /// Bake a trained avatar into one portable, animatable glTF file (.glb).
    ExportAvatar(avatar::ExportAvatarArgs),
    /// Play an avatar in the browser: a local server (or a static folder) with the player.
    View(view::ViewArgs),
    /// Render a standard 3DGS `.ply` from a camera JSON to PNG (and optionally `.npy`).
    RenderPly(render_ply::RenderPlyArgs),
    /// Body models: pose and inspect them, convert parameters between them.
    #[command(subcommand)]
    Rig(rig::RigCommand),
    /// Motions: retarget other tools' motions (AMASS, .smpl, BVH, glTF, FBX) onto a body
    /// model, write f3g's motions for them, draw a motion's contact sheet.
    #[command(subcommand)]
    Motion(motion::MotionCommand),
    /// Fit a body model's per-frame parameters to a capture's masks (and optional 2D
    /// keypoints): the body_params.npz a capture of your own needs for training.
    Fit(fit::FitArgs),
    /// Render a synthetic multi-view capture of the built-in human.
    Synth(data::SynthArgs),
    /// Captures: validate them, look at them.
    #[command(subcommand)]
    Data(data::DataCommand),
    /// Build a canonical clothed template (body model in the canonical pose + garment).
    Template(template::TemplateArgs),
    /// Write PNG pictures of a template's position maps (canonical, posed, head, mask).
    Posmaps(template::PosmapsArgs),
    /// PSNR, SSIM and LPIPS of two images, as JSON: `ssim` as scikit-image computes it (7×7
    /// uniform window: the paper's protocol), `ssim_3dgs` with the 3DGS Gaussian window.
    Metrics(metrics::MetricsArgs),
    /// Fetch and convert third-party weights (LPIPS VGG).
    #[command(subcommand)]
    Weights(weights::WeightsCommand),
    /// Performance benchmarks.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// The devices this binary can compute on, and what CUDA needs from this machine (driver,
    /// NVRTC, include directory, NCCL) with what is missing.
    Devices(device::DevicesArgs),
}

fn main() -> Result<()> {
    device::pin_burn_default_device();
    let cli = Cli::parse();
    interrupt::install()?;
    // The command runs on a worker of rayon's global pool rather than on the main thread: its
    // parallel loops (convolution tiles, fused ops, the splat op: thousands a training step)
    // then split work with the other workers instead of handing every loop to the pool and
    // sleeping until it is done, and no thread idles in a spin beside it. At least two
    // workers, so that one is free while the command's worker waits on another thread (the
    // loader) that needs the pool; a large stack, as the main thread had. `RAYON_NUM_THREADS`
    // is honoured as rayon would.
    let threads = std::env::var("RAYON_NUM_THREADS")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|&n| n > 0)
        .or_else(|| std::thread::available_parallelism().ok().map(|n| n.get()))
        .unwrap_or(2)
        .max(2);
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .stack_size(COMMAND_STACK_BYTES)
        .build_global()
        .context("starting the thread pool")?;
    rayon::scope(|_| run(cli))
}

/// Stack of each pool worker, one of which runs the command (the main thread's is 8 MiB).
const COMMAND_STACK_BYTES: usize = 64 << 20;

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Demo(args) => demo::demo(&args),
        Command::Train(args) => avatar::train(&args).map(|_| ()),
        Command::Eval(args) => avatar::eval(&args).map(|_| ()),
        Command::Animate(args) => avatar::animate(&args).map(|_| ()),
        Command::ExportPly(args) => avatar::export_ply(&args),
        Command::ExportAvatar(args) => avatar::export_avatar(&args),
        Command::View(args) => view::view(&args),
        Command::RenderPly(args) => render_ply::run(&args),
        Command::Rig(cmd) => rig::run(&cmd),
        Command::Motion(cmd) => motion::run(&cmd),
        Command::Synth(args) => data::synth(&args),
        Command::Fit(args) => fit::fit(&args),
        Command::Data(cmd) => data::run(&cmd),
        Command::Template(args) => template::run(&args),
        Command::Posmaps(args) => template::posmaps(&args),
        Command::Bench(cmd) => bench::run(&cmd),
        Command::Metrics(args) => metrics::run(&args),
        Command::Weights(cmd) => weights::run(&cmd),
        Command::Devices(args) => device::devices(&args),
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
            "train --data d --out o --template body --no-face-networks --face-cm 2 --seed 1",
        ] {
            let args = std::iter::once("f3g").chain(line.split(' '));
            super::Cli::try_parse_from(args).unwrap_or_else(|e| panic!("{line}: {e}"));
        }
    }

    /// Every flag of every command is in the README's command table, in the row of its
    /// command (rows start with `` `f3g COMMAND ``).
    #[test]
    fn every_flag_is_documented_in_the_readme() {
        let readme = include_str!("../../../README.md");
        let rows: Vec<&str> = readme
            .lines()
            .filter(|l| l.starts_with("| `f3g "))
            .collect();
        // The command path a row documents: `f3g bench train --device …` → "bench train".
        let root = super::Cli::command();
        let path_of = |row: &str| -> String {
            let cell = row.trim_start_matches("| `f3g ");
            let mut command = &root;
            let mut path = Vec::new();
            for word in cell.split([' ', '`']) {
                match command.find_subcommand(word) {
                    Some(sub) => {
                        path.push(word.to_string());
                        command = sub;
                    }
                    None => break,
                }
            }
            path.join(" ")
        };
        let mut missing = Vec::new();
        let mut stack: Vec<(String, &clap::Command)> = root
            .get_subcommands()
            .map(|c| (c.get_name().to_string(), c))
            .collect();
        while let Some((path, command)) = stack.pop() {
            stack.extend(
                command
                    .get_subcommands()
                    .map(|c| (format!("{path} {}", c.get_name()), c)),
            );
            let own: Vec<&&str> = rows.iter().filter(|r| path_of(r) == path).collect();
            let flags: Vec<String> = command
                .get_arguments()
                .filter_map(|a| a.get_long())
                .filter(|l| !["help", "version"].contains(l))
                .map(|l| format!("--{l}"))
                .collect();
            if own.is_empty() && !flags.is_empty() {
                missing.push(format!("`f3g {path}` has no row"));
            }
            for flag in flags {
                let documented = own.iter().any(|r| {
                    r.split(|c: char| !(c.is_alphanumeric() || c == '-'))
                        .any(|w| w == flag)
                });
                if !own.is_empty() && !documented {
                    missing.push(format!("`f3g {path}` {flag}"));
                }
            }
        }
        missing.sort();
        assert!(
            missing.is_empty(),
            "not in the README's command table: {missing:#?}"
        );
    }
}
