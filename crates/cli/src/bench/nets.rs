//! `f3g bench nets`: the networks' forward and forward+backward, timed.

use std::cell::Cell;
use std::path::Path;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Result, ensure};
use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use clap::Args;
use f3g_nets::conv::profile as conv_profile;
use f3g_nets::lpips::{Lpips, LpipsNet};
use f3g_nets::{DiscriminatorConfig, StyleUNetConfig};
use serde::Serialize;

use super::{kernel_count, median};
use crate::device::{DeviceArg, DeviceSpec};

/// Options of `f3g bench nets`.
#[derive(Args, Debug)]
pub struct NetsBenchArgs {
    /// Timed repetitions (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub repeats: usize,
    /// Side of the images LPIPS and the discriminator are timed on (32–2048).
    #[arg(long, default_value_t = 128, value_parser = crate::bounds::size::<32, 2048>)]
    pub image: usize,
    /// Also time the paper-sized presets (slow on a CPU).
    #[arg(long)]
    pub paper: bool,
    /// Time only the networks whose name contains this text (e.g. `body`, `LPIPS vgg`).
    #[arg(long)]
    pub only: Option<String>,
    /// Split each forward+backward into its convolutions (forward, input gradient, weight
    /// gradient: time and GFLOP/s) and everything else (CPU only).
    #[arg(long)]
    pub profile: bool,
    /// Write the results as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    #[command(flatten)]
    pub device: DeviceArg,
}

#[derive(Serialize)]
struct NetTiming {
    name: String,
    parameters: usize,
    #[serde(flatten)]
    timed: Timed,
}

/// One network's times.
#[derive(Serialize)]
struct Timed {
    /// Medians of the repetitions after the first.
    forward_ms: f64,
    forward_backward_ms: f64,
    /// The first repetition, forward and forward+backward together: in a fresh process on a
    /// GPU, the kernels' compilation (and autotuning) is in it.
    first_ms: f64,
    /// Distinct kernels the first repetition launched (GPU devices): each one compiled then.
    first_kernels: Option<usize>,
    /// Where a forward+backward goes (`--profile`).
    profile: Option<Profile>,
}

/// A forward+backward split by convolution phase, means over the timed repetitions.
#[derive(Serialize)]
struct Profile {
    forward: PhaseTime,
    input_grad: PhaseTime,
    weight_grad: PhaseTime,
    /// Everything that is not a convolution: activations, resampling, reductions, autodiff.
    other_ms: f64,
    /// The whole forward+backward, mean.
    total_ms: f64,
}

#[derive(Serialize)]
struct PhaseTime {
    ms: f64,
    gflop: f64,
    gflop_per_s: f64,
    convolutions: usize,
}

impl Profile {
    fn new(records: &[conv_profile::Record], repeats: usize, total_ms: f64) -> Self {
        let phase = |phase: conv_profile::Phase| {
            let of_phase = records.iter().filter(|r| r.phase == phase);
            let seconds: f64 = of_phase.clone().map(|r| r.seconds).sum();
            let flop: f64 = of_phase.clone().map(conv_profile::Record::flops).sum();
            PhaseTime {
                ms: seconds * 1e3 / repeats as f64,
                gflop: flop * 1e-9 / repeats as f64,
                gflop_per_s: if seconds > 0.0 {
                    flop * 1e-9 / seconds
                } else {
                    0.0
                },
                convolutions: of_phase.count() / repeats,
            }
        };
        let (forward, input_grad, weight_grad) = (
            phase(conv_profile::Phase::Forward),
            phase(conv_profile::Phase::InputGrad),
            phase(conv_profile::Phase::WeightGrad),
        );
        Self {
            other_ms: total_ms - forward.ms - input_grad.ms - weight_grad.ms,
            forward,
            input_grad,
            weight_grad,
            total_ms,
        }
    }
}

/// Keeps a timing and prints it at once: on a GPU the first repetition of a large network
/// (kernel compilation, autotuning) can take minutes, and a silent wait looks like a hang.
fn record(rows: &mut Vec<NetTiming>, row: NetTiming) {
    let t = &row.timed;
    let kernels = t
        .first_kernels
        .map(|n| format!(", {n} kernels"))
        .unwrap_or_default();
    eprintln!(
        "  {}: {:.1} / {:.1} ms (first repetition {:.0} ms{kernels})",
        row.name, t.forward_ms, t.forward_backward_ms, t.first_ms
    );
    rows.push(row);
}

fn ramp(shape: [usize; 4], device: &Device) -> Tensor<4> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|i| ((i * 7919) % 97) as f32 / 97.0).collect();
    Tensor::from_data(TensorData::new(v, shape), device)
}

/// How every network of one `bench nets` run is timed.
struct Timing<'a> {
    repeats: usize,
    device: &'a Device,
    on_gpu: bool,
    profile: bool,
}

impl Timing<'_> {
    /// Times a scalar loss built by `f` on the device (forward) and on its autodiff twin
    /// (forward + backward). `f` receives the device and builds its inputs; networks are built
    /// once per device beforehand by `build`. The first repetition (kernel compilation,
    /// autotuning) is not counted, and each timing ends when the device has finished (`sync`),
    /// not when the work is queued. On a GPU every repetition is printed (the first one compiles
    /// and autotunes the kernels, which can take minutes) and the kernels the first one launches
    /// are counted; `profile` records the convolutions of the timed forward+backward
    /// repetitions.
    fn time_loss<N>(
        &self,
        build: impl Fn(&Device) -> N,
        f: impl Fn(&N, &Device) -> Tensor<1>,
    ) -> Result<Timed> {
        let plain = self.device.clone();
        let train = self.device.clone().autodiff();
        let (net_plain, net_train) = (build(&plain), build(&train));
        let mut fwd = Vec::new();
        let mut both = Vec::new();
        let (mut first_ms, mut first_kernels) = (0.0, None);
        let mut records = Vec::new();
        for rep in 0..=self.repeats {
            let counting = kernel_count::start(self.on_gpu && rep == 0);
            let start = Instant::now();
            std::hint::black_box(f(&net_plain, &plain).into_scalar::<f32>());
            let t_fwd = start.elapsed().as_secs_f64() * 1e3;
            let profiling = self.profile && rep > 0;
            if profiling {
                conv_profile::start();
            }
            let start = Instant::now();
            std::hint::black_box(f(&net_train, &train).backward());
            train
                .sync()
                .map_err(|e| anyhow::anyhow!("running on {:?}: {e:?}", self.device))?;
            let t_both = start.elapsed().as_secs_f64() * 1e3;
            if profiling {
                records.extend(conv_profile::finish());
            }
            if self.on_gpu {
                eprintln!("    repetition {rep}: {t_fwd:.1} / {t_both:.1} ms");
            }
            if rep > 0 {
                fwd.push(t_fwd);
                both.push(t_both);
            } else {
                first_ms = t_fwd + t_both;
                first_kernels = counting.map(kernel_count::finish);
            }
        }
        let mean_both = both.iter().sum::<f64>() / self.repeats as f64;
        Ok(Timed {
            forward_ms: median(fwd),
            forward_backward_ms: median(both),
            first_ms,
            first_kernels,
            profile: self
                .profile
                .then(|| Profile::new(&records, self.repeats, mean_both)),
        })
    }
}

pub fn run(a: &NetsBenchArgs) -> Result<()> {
    ensure!(a.repeats > 0, "--repeats must be at least 1");
    let device = a.device.open()?;
    let on_gpu = a.device.spec != DeviceSpec::Cpu;
    ensure!(
        !(a.profile && on_gpu),
        "--profile splits the CPU's time; a GPU queues its work, so it cannot be timed per call"
    );
    let timing = Timing {
        repeats: a.repeats,
        device: &device,
        on_gpu,
        profile: a.profile,
    };
    // Whether `--only` matched a network, timed or not (LPIPS without its weights is not).
    let matched = Cell::new(false);
    let wanted = |name: &str| {
        let wanted = a
            .only
            .as_ref()
            .is_none_or(|only| name.to_lowercase().contains(&only.to_lowercase()));
        matched.set(matched.get() || wanted);
        wanted
    };
    eprintln!(
        "timing on {} (the first repetition of each network is not counted)",
        a.device
    );
    let mut nets = vec![
        (
            "body cpu (colour, view)",
            StyleUNetConfig::cpu_body(3, true),
        ),
        ("body cpu (position)", StyleUNetConfig::cpu_body(3, false)),
        ("body cpu (other)", StyleUNetConfig::cpu_body(8, false)),
        (
            "face cpu (colour, view)",
            StyleUNetConfig::cpu_face(3, true),
        ),
    ];
    if a.paper {
        nets.push((
            "body paper (colour, view)",
            StyleUNetConfig::paper_body(3, true),
        ));
        nets.push(("face paper (other)", StyleUNetConfig::paper_face(8, false)));
    }
    let mut rows = Vec::new();
    for (name, config) in nets {
        let s = config.input_size;
        let name = format!("StyleUNet {name} {s}→{}", config.output_size);
        if !wanted(&name) {
            continue;
        }
        let parameters = config.init(0, &Device::flex())?.num_params();
        let timed = timing.time_loss(
            |device| config.init(0, device).expect("valid preset"),
            |net, device| {
                let view = config
                    .view_conditioned
                    .then(|| (ramp([1, 1, s, s], device), ramp([1, 1, s, s], device)));
                let y = net
                    .forward(ramp([1, 3, s, s], device), view)
                    .expect("shapes");
                y.front.mean() + y.back.mean()
            },
        )?;
        record(
            &mut rows,
            NetTiming {
                name,
                parameters,
                timed,
            },
        );
    }
    let size = a.image;
    for net in [LpipsNet::Alex, LpipsNet::Vgg] {
        let name = format!("LPIPS {net} {size}²");
        if !wanted(&name) {
            continue;
        }
        if let Err(e) = Lpips::load(net, &device) {
            println!("LPIPS {net}: not timed ({e})");
            continue;
        }
        let timed = timing.time_loss(
            |device| Lpips::load(net, device).expect("loaded above"),
            |lpips, device| {
                let mut x = ramp([1, 3, size, size], device);
                if device.is_autodiff() {
                    x = x.require_grad();
                }
                lpips
                    .forward(x, ramp([1, 3, size, size], device) * 0.5)
                    .expect("shapes")
                    .sum()
            },
        )?;
        record(
            &mut rows,
            NetTiming {
                name,
                parameters: 0,
                timed,
            },
        );
    }
    let disc = DiscriminatorConfig::cpu(size.next_power_of_two().max(8));
    let r = disc.resolution;
    let name = format!("discriminator cpu {r}²");
    if wanted(&name) {
        let timed = timing.time_loss(
            |device| disc.init(0, device).expect("valid"),
            |d, device| {
                d.forward(ramp([1, 3, r, r], device))
                    .expect("shapes")
                    .mean()
            },
        )?;
        record(
            &mut rows,
            NetTiming {
                name,
                parameters: disc.init(0, &Device::flex())?.num_params(),
                timed,
            },
        );
    }
    ensure!(
        matched.get(),
        "--only {:?} matches no network",
        a.only.as_deref().unwrap_or_default()
    );
    println!(
        "| network | parameters | forward ms | forward+backward ms | first repetition ms | its kernels |\n|---|---|---|---|---|---|"
    );
    for r in &rows {
        let t = &r.timed;
        let kernels = t.first_kernels.map_or("—".to_string(), |n| n.to_string());
        println!(
            "| {} | {} | {:.1} | {:.1} | {:.0} | {kernels} |",
            r.name, r.parameters, t.forward_ms, t.forward_backward_ms, t.first_ms
        );
    }
    if a.profile {
        print_profile(&rows);
    }
    match a.device.spec {
        DeviceSpec::Cpu => println!("(cpu, {} threads)", rayon::current_num_threads()),
        other => println!("({other})"),
    }
    if let Some(path) = &a.json {
        write_json(path, &rows)?;
    }
    Ok(())
}

/// The `--profile` table: per network, each convolution phase's time and rate, and the rest.
fn print_profile(rows: &[NetTiming]) {
    println!(
        "\n| network | forward+backward ms | conv forward ms (GFLOP/s) | conv input grad ms (GFLOP/s) | conv weight grad ms (GFLOP/s) | other ms |\n|---|---|---|---|---|---|"
    );
    let cell = |p: &PhaseTime| {
        if p.convolutions == 0 {
            "—".to_string()
        } else {
            format!("{:.1} ({:.0})", p.ms, p.gflop_per_s)
        }
    };
    for row in rows {
        if let Some(p) = &row.timed.profile {
            println!(
                "| {} | {:.1} | {} | {} | {} | {:.1} |",
                row.name,
                p.total_ms,
                cell(&p.forward),
                cell(&p.input_grad),
                cell(&p.weight_grad),
                p.other_ms
            );
        }
    }
}

fn write_json(path: &Path, value: &impl Serialize) -> Result<()> {
    f3g_io::write_atomic(path, serde_json::to_string_pretty(value)?.as_bytes())?;
    Ok(())
}
