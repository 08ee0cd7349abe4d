//! `f3g bench splat`: the Gaussian rasteriser timed, written as a table and JSON.
//!
//! It renders a fixed, seeded scene: N Gaussians on a 1 m sphere shell seen from 3 m,
//! scales 1–2 cm, opacities 0.3–0.9, SH degree 0, the sphere filling ~85 % of the image width.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Result, ensure};
use burn::tensor::{Device, Tensor, TensorData};
use clap::Args;
use f3g_splat::cpu::{self, PixelGrads};
use f3g_splat::{Camera, GaussianCloud, RenderOptions, render};
use indicatif::{ProgressBar, ProgressStyle};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use super::{median, memory, millis};
use crate::device::{DeviceArg, DeviceSpec};

/// Bytes a CPU render holds per pixel (forward state, the backward's gradients and state) and
/// per Gaussian with its intersections: upper estimates, above the peaks `bench splat`
/// measured (40 MiB at 100k / 512², 235 MiB at 100k / 2048×1500).
const SPLAT_BYTES_PER_PIXEL: u64 = 96;
const SPLAT_BYTES_PER_GAUSSIAN: u64 = 400;

/// Options of `f3g bench splat`.
#[derive(Args, Debug)]
pub struct SplatBenchArgs {
    /// Gaussian counts, comma-separated (each at most 50 million).
    #[arg(long, value_delimiter = ',', default_value = "10000,100000,300000",
          value_parser = crate::bounds::size::<1, 50_000_000>)]
    pub gaussians: Vec<usize>,
    /// Image sizes, comma-separated: `N` for N×N or `WIDTHxHEIGHT` (16–8192 a side).
    #[arg(long, value_delimiter = ',', default_value = "512,1024",
          value_parser = crate::bounds::resolution)]
    pub resolutions: Vec<(u32, u32)>,
    /// Timed repetitions per case (the median is reported).
    #[arg(long, default_value_t = 7)]
    pub repeats: usize,
    /// Seed of the scene.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Write the results as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    #[command(flatten)]
    pub device: DeviceArg,
}

/// One measured case.
#[derive(Serialize, Debug)]
pub struct SplatCase {
    pub gaussians: usize,
    pub width: u32,
    pub height: u32,
    pub visible: usize,
    pub intersections: usize,
    /// Median milliseconds of the CPU reference: projection+binning+rasterisation.
    pub forward_ms: f64,
    /// Median milliseconds of forward + backward (CPU reference).
    pub forward_backward_ms: f64,
    /// Median milliseconds of forward + backward through the Burn autodiff op.
    pub burn_op_forward_backward_ms: f64,
    pub forward_evaluations: u64,
    pub backward_evaluations: u64,
    /// Gaussian–pixel evaluations (forward + backward) per second of forward+backward.
    pub evaluations_per_second: f64,
    /// Peak heap growth during one CPU forward+backward, in MiB.
    pub peak_mib: f64,
    /// Lower bound from the evaluation count at the measured FLOP rate, in ms.
    pub lower_bound_ms: f64,
    /// Median milliseconds per stage: project, bin, rasterise, rasterise backward, project backward.
    pub stage_ms: [f64; 5],
}

/// FLOPs of one forward Gaussian–pixel evaluation (offset, quadratic form, exp, alpha test).
pub const FORWARD_FLOPS_PER_EVAL: f64 = 20.0;
/// FLOPs of one backward evaluation (the forward recomputation plus the gradient terms).
pub const BACKWARD_FLOPS_PER_EVAL: f64 = 60.0;

/// The random colour gradient `[pixels, 3]` the backward is timed with (the same on every
/// device for a seed).
fn colour_gradient(seed: u64, pixels: usize) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xbe7c);
    (0..3 * pixels)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect()
}

/// The benchmark scene: `n` Gaussians on the unit sphere.
pub fn sphere_shell(n: usize, seed: u64) -> GaussianCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut cloud = GaussianCloud {
        sh_degree: 0,
        ..Default::default()
    };
    for _ in 0..n {
        let v: [f64; 3] = loop {
            let v = [
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            ];
            let r2: f64 = v.iter().map(|x| x * x).sum();
            if r2 > 1e-6 && r2 <= 1.0 {
                let r = r2.sqrt();
                break v.map(|x| x / r);
            }
        };
        cloud.means.extend(v.map(|x| x as f32));
        cloud
            .log_scales
            .extend((0..3).map(|_| rng.random_range(0.01f32..0.02).ln()));
        cloud
            .quats
            .extend((0..4).map(|_| rng.random_range(-1.0f32..1.0)));
        let o: f32 = rng.random_range(0.3..0.9);
        cloud.opacity_logits.push((o / (1.0 - o)).ln());
        cloud
            .sh
            .extend((0..3).map(|_| rng.random_range(-1.5f32..1.5)));
    }
    cloud
}

/// The benchmark camera: 3 m from the centre, focal length 1.2 × the image width.
pub fn bench_camera(width: u32, height: u32) -> Camera {
    Camera::look_at(
        [0.0, 0.3, 3.0],
        [0.0; 3],
        [0.0, 1.0, 0.0],
        1.2 * width as f64,
        width,
        height,
    )
}

/// Independent fused multiply-adds: 128 lanes (8 AVX-512 registers), enough to hide the FMA
/// latency. Compiled for the same instruction sets as the rasteriser's kernels.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512vl+avx512bw+avx512dq+avx2+fma",
    "x86_64+avx2+fma"
))]
fn fma_chains(seed: f32, iterations: usize) -> f32 {
    let mut acc = [seed; 128];
    let (m, c) = (
        std::hint::black_box(0.999_99f32),
        std::hint::black_box(1e-5f32),
    );
    for _ in 0..iterations {
        for a in acc.iter_mut() {
            *a = a.mul_add(m, c);
        }
    }
    acc.iter().sum()
}

/// Peak f32 throughput on all threads in GFLOP/s (an FMA counts as 2), measured with the
/// widest vectors this CPU offers the rasteriser; the best of three runs.
pub fn measure_flop_rate() -> f64 {
    const ITERATIONS: usize = 400_000;
    let threads = rayon::current_num_threads();
    (0..3)
        .map(|_| {
            let start = Instant::now();
            let sink: f32 =
                rayon::broadcast(|ctx| fma_chains(1.0 + ctx.index() as f32 * 1e-3, ITERATIONS))
                    .into_iter()
                    .sum();
            std::hint::black_box(sink);
            2.0 * 128.0 * ITERATIONS as f64 * threads as f64 / start.elapsed().as_secs_f64() / 1e9
        })
        .fold(0.0, f64::max)
}

fn burn_op_fwd_bwd(
    cloud: &GaussianCloud,
    camera: &Camera,
    grad_seed: &[f32],
    device: &Device,
) -> Result<f64> {
    let g = cloud.to_tensors(device);
    let g = f3g_splat::Gaussians {
        means: g.means.require_grad(),
        log_scales: g.log_scales.require_grad(),
        quats: g.quats.require_grad(),
        opacity_logits: g.opacity_logits.require_grad(),
        sh: g.sh.require_grad(),
    };
    let (w, h) = (camera.width as usize, camera.height as usize);
    let weights = Tensor::<3>::from_data(TensorData::new(grad_seed.to_vec(), [h, w, 3]), device);
    let bg = Tensor::<1>::from_data(TensorData::new(vec![1.0f32; 3], [3]), device);
    let start = Instant::now();
    let out = render(&g, camera, bg, &RenderOptions::default())?;
    let grads = (out.color * weights).sum().backward();
    let d = g.means.grad(&grads).expect("means receive a gradient");
    // Until the device has finished, not until the work is queued.
    device
        .sync()
        .map_err(|e| anyhow::anyhow!("running the splat op: {e:?}"))?;
    let elapsed = millis(start);
    ensure!(d.dims() == [cloud.len(), 3], "unexpected gradient shape");
    Ok(elapsed)
}

pub fn run(args: &SplatBenchArgs) -> Result<()> {
    ensure!(args.repeats > 0, "--repeats must be at least 1");
    let largest_n = args.gaussians.iter().copied().max().unwrap_or(0) as u64;
    let largest_image = args
        .resolutions
        .iter()
        .map(|&(w, h)| w as u64 * h as u64)
        .max()
        .unwrap_or(0);
    // The scene is made on the host on every device; the CPU render is counted on GPUs too
    // (it counts the evaluations).
    f3g_io::memory::ensure_available(
        largest_n * SPLAT_BYTES_PER_GAUSSIAN + largest_image * SPLAT_BYTES_PER_PIXEL,
        &format!("--gaussians {largest_n} with an image of {largest_image} pixels (--resolutions)"),
    )?;
    if args.device.spec == DeviceSpec::Cpu {
        run_on_cpu(args)
    } else {
        run_on_device(args)
    }
}

/// One case measured on a GPU.
#[derive(Serialize, Debug)]
pub struct DeviceSplatCase {
    pub gaussians: usize,
    pub width: u32,
    pub height: u32,
    pub visible: usize,
    pub intersections: usize,
    /// Median milliseconds of a forward render (until the device is done).
    pub forward_ms: f64,
    /// Median milliseconds of forward + backward through the autodiff op.
    pub forward_backward_ms: f64,
    /// Milliseconds of the first forward + backward (kernel compilation, autotuning).
    pub first_ms: f64,
    /// Gaussian–pixel evaluations of one forward + backward (counted by the CPU path on the
    /// same scene: the GPU evaluates the same pairs).
    pub evaluations: u64,
    /// Evaluations per second of forward + backward.
    pub evaluations_per_second: f64,
    /// The most device memory the allocator held after a forward + backward, in MiB (its
    /// pools only grow within a case, so this bounds the peak from below by at most a page).
    pub device_reserved_mib: Option<f64>,
}

/// `bench splat --device wgpu|cuda`: the Burn op (forward, and forward + backward on the
/// autodiff device) on the GPU; each timing ends when the device has finished.
fn run_on_device(args: &SplatBenchArgs) -> Result<()> {
    let plain = args.device.open()?;
    let train = plain.clone().autodiff();
    eprintln!(
        "timing the splat op on {} (the first repetition of each case compiles kernels and is not counted)",
        args.device
    );
    let options = RenderOptions::default();
    let sync = |device: &Device| {
        device
            .sync()
            .map_err(|e| anyhow::anyhow!("running on {}: {e:?}", args.device))
    };
    let mut cases = Vec::new();
    for &n in &args.gaussians {
        let cloud = sphere_shell(n, args.seed);
        for &(width, height) in &args.resolutions {
            let camera = bench_camera(width, height);
            let pixels = (width * height) as usize;
            let d_color = colour_gradient(args.seed, pixels);
            // The work done, counted once by the CPU path.
            let bg = [1.0f32; 3];
            let fwd = cpu::render(&cloud.slices(), &camera, bg, &options)?;
            let zeros = vec![0.0f32; pixels];
            let raster = cpu::rasterize_backward(
                &fwd,
                &camera,
                &options,
                &PixelGrads {
                    color: &d_color,
                    alpha: &zeros,
                    depth: &zeros,
                },
            );
            let evaluations = fwd.evaluations + raster.evaluations;
            let visible = fwd.projected.iter().filter(|p| p.is_visible()).count();
            let intersections = fwd.bins.num_intersections();
            drop((fwd, raster));

            let gaussians = cloud.to_tensors(&plain);
            let bg_plain = Tensor::<1>::ones([3], &plain);
            let (mut forward, mut both, mut first, mut reserved) =
                (Vec::new(), Vec::new(), 0.0, None);
            for rep in 0..=args.repeats {
                let start = Instant::now();
                let out = render(&gaussians, &camera, bg_plain.clone(), &options)?;
                std::hint::black_box(&out);
                sync(&plain)?;
                let t_fwd = millis(start);
                drop(out);
                let t_both = burn_op_fwd_bwd(&cloud, &camera, &d_color, &train)?;
                if let Some(usage) = train.memory_pool_usage() {
                    let mib = usage.bytes_reserved as f64 / (1 << 20) as f64;
                    reserved = Some(reserved.map_or(mib, |r: f64| r.max(mib)));
                }
                if rep == 0 {
                    first = t_both;
                    eprintln!("  N={n} {width}x{height}: first forward+backward {t_both:.0} ms");
                } else {
                    forward.push(t_fwd);
                    both.push(t_both);
                }
            }
            let forward_backward_ms = median(both);
            cases.push(DeviceSplatCase {
                gaussians: n,
                width,
                height,
                visible,
                intersections,
                forward_ms: median(forward),
                forward_backward_ms,
                first_ms: first,
                evaluations,
                evaluations_per_second: evaluations as f64 / (forward_backward_ms / 1e3),
                device_reserved_mib: reserved,
            });
        }
    }
    println!(
        "{:>8} {:>9} {:>9} {:>9} {:>9} {:>10} {:>8} {:>12}",
        "N", "image", "fwd ms", "fwd+bwd", "first ms", "evals M", "Geval/s", "device MiB"
    );
    for c in &cases {
        println!(
            "{:>8} {:>9} {:>9.2} {:>9.2} {:>9.0} {:>10.1} {:>8.2} {:>12}",
            c.gaussians,
            format!("{}x{}", c.width, c.height),
            c.forward_ms,
            c.forward_backward_ms,
            c.first_ms,
            c.evaluations as f64 / 1e6,
            c.evaluations_per_second / 1e9,
            c.device_reserved_mib
                .map_or("n/a".to_string(), |m| format!("{m:.0}"))
        );
    }
    if let Some(path) = &args.json {
        let doc = serde_json::json!({ "device": args.device.to_string(), "cases": cases });
        f3g_io::write_atomic(path, serde_json::to_string_pretty(&doc)?.as_bytes())?;
    }
    Ok(())
}

/// `bench splat --device cpu`: the CPU path stage by stage, and the Burn op on Flex.
fn run_on_cpu(args: &SplatBenchArgs) -> Result<()> {
    let flop_rate = measure_flop_rate();
    println!(
        "machine: {} threads; measured peak f32 FMA throughput {:.1} GFLOP/s",
        rayon::current_num_threads(),
        flop_rate
    );
    let device = Device::flex().autodiff();
    let options = RenderOptions::default();
    let total = (args.gaussians.len() * args.resolutions.len()) as u64;
    let bar = ProgressBar::new(total).with_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} {msg} [{elapsed} < {eta}]")
            .expect("valid template"),
    );
    let mut cases = Vec::new();
    for &n in &args.gaussians {
        let cloud = sphere_shell(n, args.seed);
        for &(width, height) in &args.resolutions {
            bar.set_message(format!("N={n} {width}×{height}"));
            let camera = bench_camera(width, height);
            let pixels = (width * height) as usize;
            let d_color = colour_gradient(args.seed, pixels);
            let zeros = vec![0.0f32; pixels];
            let grads = PixelGrads {
                color: &d_color,
                alpha: &zeros,
                depth: &zeros,
            };
            let bg = [1.0f32; 3];

            let mut forward = Vec::new();
            let mut both = Vec::new();
            let mut op = Vec::new();
            let mut stages: [Vec<f64>; 5] = Default::default();
            let mut peak = 0usize;
            let mut stats = (0usize, 0usize, 0u64, 0u64);
            for rep in 0..=args.repeats {
                let before = memory::live_bytes();
                memory::reset_peak();
                let start = Instant::now();
                let projected = cpu::project(&cloud.slices(), &camera);
                let t_project = millis(start);
                let bins = cpu::bin_tiles(&projected, width as usize, height as usize);
                let t_bin = millis(start);
                let fwd = cpu::rasterize(projected, bins, &camera, bg, &options);
                let t_fwd = millis(start);
                let raster = cpu::rasterize_backward(&fwd, &camera, &options, &grads);
                let t_raster_bwd = millis(start);
                let g =
                    cpu::project_backward(&cloud.slices(), &camera, &fwd.projected, &raster.screen);
                let t_both = millis(start);
                let marks = [t_project, t_bin, t_fwd, t_raster_bwd, t_both];
                std::hint::black_box(&g);
                peak = peak.max(memory::peak_bytes().saturating_sub(before));
                stats = (
                    fwd.projected.iter().filter(|p| p.is_visible()).count(),
                    fwd.bins.num_intersections(),
                    fwd.evaluations,
                    raster.evaluations,
                );
                let t_op = burn_op_fwd_bwd(&cloud, &camera, &d_color, &device)?;
                if rep > 0 {
                    for (k, stage) in stages.iter_mut().enumerate() {
                        stage.push(marks[k] - if k == 0 { 0.0 } else { marks[k - 1] });
                    }
                    forward.push(t_fwd);
                    both.push(t_both);
                    op.push(t_op);
                }
            }
            let (visible, intersections, fe, be) = stats;
            let fb = median(both);
            let lower = (fe as f64 * FORWARD_FLOPS_PER_EVAL + be as f64 * BACKWARD_FLOPS_PER_EVAL)
                / (flop_rate * 1e9)
                * 1e3;
            cases.push(SplatCase {
                gaussians: n,
                width,
                height,
                visible,
                intersections,
                forward_ms: median(forward),
                forward_backward_ms: fb,
                burn_op_forward_backward_ms: median(op),
                forward_evaluations: fe,
                backward_evaluations: be,
                evaluations_per_second: (fe + be) as f64 / (fb / 1e3),
                peak_mib: peak as f64 / (1 << 20) as f64,
                lower_bound_ms: lower,
                stage_ms: stages.map(median),
            });
            bar.inc(1);
        }
    }
    bar.finish_and_clear();

    println!(
        "{:>8} {:>9} {:>9} {:>8} {:>10} {:>10} {:>8} {:>8} {:>9} {:>8}",
        "N",
        "image",
        "fwd ms",
        "fwd+bwd",
        "op fwd+bwd",
        "evals M",
        "Geval/s",
        "peak MiB",
        "bound ms",
        "ratio"
    );
    for c in &cases {
        println!(
            "{:>8} {:>9} {:>9.1} {:>8.1} {:>10.1} {:>10.1} {:>8.2} {:>8.1} {:>9.2} {:>8.1}",
            c.gaussians,
            format!("{}x{}", c.width, c.height),
            c.forward_ms,
            c.forward_backward_ms,
            c.burn_op_forward_backward_ms,
            (c.forward_evaluations + c.backward_evaluations) as f64 / 1e6,
            c.evaluations_per_second / 1e9,
            c.peak_mib,
            c.lower_bound_ms,
            c.forward_backward_ms / c.lower_bound_ms
        );
    }
    println!(
        "stage medians (ms): project / bin / rasterise / rasterise backward / project backward"
    );
    for c in &cases {
        let s = c.stage_ms;
        println!(
            "{:>8} {:>9}  {:.1} / {:.1} / {:.1} / {:.1} / {:.1}",
            c.gaussians,
            format!("{}x{}", c.width, c.height),
            s[0],
            s[1],
            s[2],
            s[3],
            s[4]
        );
    }
    if let Some(path) = &args.json {
        let doc = serde_json::json!({ "flop_rate_gflops": flop_rate, "threads": rayon::current_num_threads(), "cases": cases });
        f3g_io::write_atomic(path, serde_json::to_string_pretty(&doc)?.as_bytes())?;
    }
    Ok(())
}
