//! `f3g bench quality`: what each part of the face branch contributes, measured.
//!
//! Variants (one change each from the full method — the `cpu` preset with the paper's
//! adversarial loss, which the preset leaves out — same steps): the full method; the face-crop
//! losses on the body Gaussians without the face networks; no face branch at all (body losses
//! only); no adversarial loss; and the paper's Table 4 — 128² head crops instead of 256², face
//! networks of capacity (n_mlp, cm) = (2, 1) and (4, 2) beside the full method's (4, 1). Each
//! is trained with several seeds on one synthetic capture and evaluated on novel views and
//! novel poses; the report gives mean ± sample standard deviation
//! over seeds and, for each part, the difference of means against the seed-to-seed spread.
//!
//! Finished runs and their evaluations are reused, so several invocations with disjoint
//! `--seeds` can share the two cores' work and a last one writes the report.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use f3g_avatar::infer::eval::{EvalReport, Scores};
use f3g_avatar::train::TrainConfig;
use f3g_data::split::SplitKind;
use serde::Serialize;

use super::median;
use crate::avatar::{AblationArgs, eval};
use crate::demo::{CaptureAndTraining, ensure_capture, eval_args, train_or_resume};
use crate::device::DeviceArg;

/// One ablation of the full method.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Variant {
    /// The full method: face networks, face-crop L1 + LPIPS + adversarial losses.
    Full,
    /// The face-crop losses (L1 + LPIPS + adversarial) train the body Gaussians; no face
    /// networks.
    FaceLossesOnly,
    /// No face branch: body Gaussians and body losses only.
    NoFaceBranch,
    /// The full method without the adversarial loss.
    NoAdversarial,
    /// Head crops of 128² in training (and a 128² discriminator) instead of the preset's
    /// 256²: the resolution rows of the paper's Table 4.
    Crop128,
    /// Face networks with n_mlp 2 instead of 4: capacity (n_mlp, cm) = (2, 1) of Table 4
    /// (the full method is (4, 1)).
    FaceMlp2,
    /// Face networks with channel multiplier 2: capacity (4, 2) of Table 4. The `cpu` face
    /// networks already reach their 64-channel cap at every level (16², 8², 4²), so the cap
    /// doubles with the multiplier: 128 channels everywhere, twice the full method's.
    FaceCm2,
}

impl Variant {
    fn name(self) -> &'static str {
        match self {
            Self::Full => "full",
            Self::FaceLossesOnly => "face-losses-only",
            Self::NoFaceBranch => "no-face-branch",
            Self::NoAdversarial => "no-adversarial",
            Self::Crop128 => "crop-128",
            Self::FaceMlp2 => "face-mlp-2",
            Self::FaceCm2 => "face-cm-2",
        }
    }

    /// Changes the preset's configuration into this variant's: first the full method (the
    /// adversarial loss on, which the `cpu` preset leaves out), then the face-branch
    /// ablations as `f3g train`'s flags set them.
    fn apply(self, config: &mut TrainConfig) {
        config.adversarial = true;
        let none = AblationArgs::default();
        let flags = match self {
            Self::Full => none,
            Self::FaceLossesOnly => AblationArgs {
                no_face_networks: true,
                ..none
            },
            Self::NoFaceBranch => AblationArgs {
                no_face_branch: true,
                ..none
            },
            Self::NoAdversarial => AblationArgs {
                no_adversarial: true,
                ..none
            },
            Self::FaceMlp2 => AblationArgs {
                face_n_mlp: Some(2),
                ..none
            },
            Self::Crop128 => {
                config.model.face_crop_size = 128;
                config.discriminator.resolution = 128;
                none
            }
            Self::FaceCm2 => {
                config.model.face_net.channel_multiplier = 2;
                config.model.face_net.max_channels = 128;
                none
            }
        };
        flags.apply(config);
    }
}

/// Options of `f3g bench quality`.
#[derive(Args, Debug)]
pub struct QualityArgs {
    /// Output folder (the capture, a run per variant and seed, quality.md and quality.json).
    #[arg(long, default_value = "runs/quality")]
    pub out: PathBuf,
    /// Capture options; `--seed` is the capture's seed, `--set` applies to every run.
    #[command(flatten)]
    pub capture: CaptureAndTraining,
    /// Training seeds of every variant.
    #[arg(long, value_delimiter = ',', default_value = "0,1,2")]
    pub seeds: Vec<u64>,
    /// Variants to train.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "full,face-losses-only,no-face-branch,no-adversarial,crop-128,face-mlp-2,face-cm-2"
    )]
    pub variants: Vec<Variant>,
    /// Evaluate every N-th frame of the novel-view split (novel poses: every frame).
    #[arg(long, default_value_t = 2)]
    pub every: usize,
}

/// Mean and sample standard deviation over seeds.
#[derive(Clone, Copy, Debug, Default, Serialize)]
struct Stat {
    mean: f64,
    std: f64,
}

fn stat(values: &[f64]) -> Stat {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = if values.len() > 1 {
        values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)
    } else {
        0.0
    };
    Stat {
        mean,
        std: var.sqrt(),
    }
}

/// Metrics of one region over seeds.
#[derive(Clone, Debug, Default, Serialize)]
struct RegionStats {
    psnr: Stat,
    ssim: Stat,
    lpips: Option<Stat>,
}

fn region(scores: &[Scores]) -> RegionStats {
    let pick = |f: fn(&Scores) -> f64| stat(&scores.iter().map(f).collect::<Vec<_>>());
    let lpips: Option<Vec<f64>> = scores.iter().map(|s| s.lpips).collect();
    RegionStats {
        psnr: pick(|s| s.psnr),
        ssim: pick(|s| s.ssim),
        lpips: lpips.map(|v| stat(&v)),
    }
}

#[derive(Clone, Debug, Serialize)]
struct SplitStats {
    body: RegionStats,
    head: RegionStats,
}

fn split_stats(reports: &[EvalReport]) -> SplitStats {
    let body: Vec<Scores> = reports.iter().map(|r| r.mean_body.clone()).collect();
    let head: Vec<Scores> = reports
        .iter()
        .map(|r| r.mean_head.clone().unwrap_or_default())
        .collect();
    SplitStats {
        body: region(&body),
        head: region(&head),
    }
}

#[derive(Serialize)]
struct VariantResult {
    variant: Variant,
    seeds: Vec<u64>,
    novel_view: SplitStats,
    novel_pose: SplitStats,
    /// Milliseconds per training step of the joint stage (body steps without the face
    /// branch), the median of the log's step-to-step times, over seeds.
    ms_per_step: Stat,
    /// Per-seed reports (paths to the runs and every image's numbers).
    runs: Vec<(EvalReport, EvalReport)>,
}

/// The median wall time in milliseconds between consecutive logged steps of the joint stage
/// (of the body stage when there is no joint stage), so checkpoint and validation pauses do
/// not count.
fn ms_per_step(run: &Path) -> Result<f64> {
    let path = f3g_avatar::infer::Run::new(run).log_path();
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let lines: Vec<(String, f64)> = text
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| Some((v["stage"].as_str()?.to_string(), v["seconds"].as_f64()?)))
        .collect();
    for stage in ["joint", "body"] {
        let steps: Vec<f64> = lines
            .windows(2)
            .filter(|w| w[0].0 == stage && w[1].0 == stage)
            .map(|w| 1e3 * (w[1].1 - w[0].1))
            .collect();
        if !steps.is_empty() {
            return Ok(median(steps));
        }
    }
    anyhow::bail!("{}: no joint or body steps logged", path.display())
}

/// The evaluation of `split` in `run`, reused when it scored the run's final step with the
/// default head crops.
fn evaluation(run: &Path, split: SplitKind, every: usize, device: DeviceArg) -> Result<EvalReport> {
    let metrics = run
        .join("eval")
        .join(split.to_string())
        .join("metrics.json");
    let total = f3g_avatar::infer::Run::new(run).config()?.steps.total();
    if let Ok(text) = std::fs::read_to_string(&metrics)
        && let Ok(report) = serde_json::from_str::<EvalReport>(&text)
        && report.step == total
        && report.face_size == f3g_avatar::infer::eval::DEFAULT_FACE_SIZE
    {
        println!("reusing {}", metrics.display());
        return Ok(report);
    }
    eval(&eval_args(run, split, every, device))
}

pub fn run(a: &QualityArgs) -> Result<()> {
    anyhow::ensure!(!a.seeds.is_empty(), "--seeds: give at least one seed");
    let capture = a.out.join("capture");
    ensure_capture(&capture, &a.capture)?;
    let mut results = Vec::new();
    for &variant in &a.variants {
        let (mut runs, mut ms) = (Vec::new(), Vec::new());
        for &seed in &a.seeds {
            let run = a.out.join(variant.name()).join(format!("seed-{seed}"));
            println!("training `{}` with seed {seed}", variant.name());
            let device = a.capture.device;
            train_or_resume(
                &run,
                &capture,
                "cpu",
                seed,
                &a.capture.set,
                device,
                |config| {
                    a.capture.apply(config);
                    variant.apply(config);
                },
            )?;
            ms.push(ms_per_step(&run)?);
            runs.push((
                evaluation(&run, SplitKind::NovelView, a.every, device)?,
                evaluation(&run, SplitKind::NovelPose, 1, device)?,
            ));
        }
        let (nv, np): (Vec<_>, Vec<_>) = runs.iter().cloned().unzip();
        results.push(VariantResult {
            variant,
            seeds: a.seeds.clone(),
            novel_view: split_stats(&nv),
            novel_pose: split_stats(&np),
            ms_per_step: stat(&ms),
            runs,
        });
    }
    let md = markdown(&results, a.seeds.len());
    println!("\n{md}");
    f3g_io::write_atomic(&a.out.join("quality.md"), md.as_bytes())?;
    f3g_io::write_atomic(
        &a.out.join("quality.json"),
        serde_json::to_string_pretty(&results)?.as_bytes(),
    )?;
    println!("wrote {}", a.out.join("quality.json").display());
    Ok(())
}

fn pm(s: &Stat, digits: usize) -> String {
    format!("{:.digits$} ± {:.digits$}", s.mean, s.std)
}

fn markdown(results: &[VariantResult], seeds: usize) -> String {
    let mut md = format!(
        "Mean ± sample standard deviation over {seeds} seed(s); PSNR in dB, SSIM as \
         scikit-image, LPIPS on the body's square crop and on the head crop.\n"
    );
    for (title, pick) in [
        (
            "Novel views",
            (|r: &VariantResult| &r.novel_view) as fn(&_) -> &_,
        ),
        ("Novel poses", |r: &VariantResult| &r.novel_pose),
    ] {
        md += &format!(
            "\n### {title}\n\n| variant | body PSNR ↑ | body SSIM ↑ | body LPIPS ↓ | head PSNR ↑ | \
             head SSIM ↑ | head LPIPS ↓ | ms / step |\n|---|---|---|---|---|---|---|---|\n"
        );
        for r in results {
            let s = pick(r);
            let l = |x: &Option<Stat>| x.as_ref().map_or("n/a".into(), |v| pm(v, 4));
            md += &format!(
                "| {} | {} | {} | {} | {} | {} | {} | {} |\n",
                r.variant.name(),
                pm(&s.body.psnr, 2),
                pm(&s.body.ssim, 4),
                l(&s.body.lpips),
                pm(&s.head.psnr, 2),
                pm(&s.head.ssim, 4),
                l(&s.head.lpips),
                pm(&r.ms_per_step, 0),
            );
        }
    }
    let find = |v: Variant| results.iter().find(|r| r.variant == v);
    let parts = [
        ("face networks", Variant::Full, Variant::FaceLossesOnly),
        (
            "face-crop losses",
            Variant::FaceLossesOnly,
            Variant::NoFaceBranch,
        ),
        ("adversarial loss", Variant::Full, Variant::NoAdversarial),
    ];
    let mut lines = String::new();
    for (part, with, without) in parts {
        let (Some(a), Some(b)) = (find(with), find(without)) else {
            continue;
        };
        for (split, sa, sb) in [
            ("novel views", &a.novel_view, &b.novel_view),
            ("novel poses", &a.novel_pose, &b.novel_pose),
        ] {
            let verdict = |a: &Stat, b: &Stat, digits: usize| {
                let d = a.mean - b.mean;
                let spread = (a.std.powi(2) + b.std.powi(2)).sqrt();
                let word = if seeds < 2 {
                    "one seed"
                } else if d.abs() > spread {
                    "beyond spread"
                } else {
                    "within spread"
                };
                format!("{d:+.digits$} (± {spread:.digits$}, {word})")
            };
            let lpips = match (&sa.head.lpips, &sb.head.lpips) {
                (Some(a), Some(b)) => verdict(a, b, 4),
                _ => "n/a".into(),
            };
            lines += &format!(
                "| {part} ({} vs {}) | {split} | {} | {lpips} | {:+.2} |\n",
                with.name(),
                without.name(),
                verdict(&sa.head.psnr, &sb.head.psnr, 2),
                sa.body.psnr.mean - sb.body.psnr.mean,
            );
        }
    }
    if !lines.is_empty() {
        md += "\n### What each part contributes\n\nDifference of means (with − without), ± the seed-to-seed spread √(s₁² + s₂²); \
               \"beyond spread\" when the difference is larger.\n\n| part | split | Δ head PSNR (dB) | Δ head LPIPS | Δ body PSNR (dB) |\n|---|---|---|---|---|\n";
        md += &lines;
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sample_standard_deviation() {
        let s = stat(&[1.0, 2.0, 3.0]);
        assert_eq!((s.mean, s.std), (2.0, 1.0));
        assert_eq!(stat(&[5.0]).std, 0.0);
    }

    /// A capacity variant that leaves the face networks as they are measures seed noise (the
    /// multiplier alone did: every level was already at the channel cap).
    #[test]
    fn every_capacity_variant_changes_the_face_networks() {
        let parameters = |v: Variant| {
            let mut config = TrainConfig::cpu();
            v.apply(&mut config);
            config.validate().unwrap();
            let net = config.model.face_nets()[0]
                .init(0, &burn::tensor::Device::flex())
                .unwrap();
            burn::module::Module::num_params(&net)
        };
        let full = parameters(Variant::Full);
        for v in [Variant::FaceMlp2, Variant::FaceCm2] {
            assert_ne!(parameters(v), full, "{}", v.name());
        }
    }

    /// Each variant is one valid change of the full method's configuration, which is the
    /// `cpu` preset with the paper's adversarial loss.
    #[test]
    fn every_variant_is_a_valid_change_of_the_full_method() {
        let full = TrainConfig {
            adversarial: true,
            ..TrainConfig::cpu()
        };
        for v in Variant::value_variants() {
            let mut config = TrainConfig::cpu();
            v.apply(&mut config);
            config.validate().unwrap();
            assert_eq!(*v == Variant::Full, config == full, "{}", v.name());
        }
    }

    #[test]
    fn step_time_is_the_joint_stages_median_gap() {
        let dir = tempfile::tempdir().unwrap();
        let line = |stage: &str, seconds: f64| {
            format!("{{\"stage\":\"{stage}\",\"seconds\":{seconds}}}\n")
        };
        // Body steps 1 s apart, joint steps 0.5 s apart with one 9-s checkpoint pause, and a
        // partial last line.
        let log: String = [
            line("body", 1.0),
            line("body", 2.0),
            line("joint", 2.5),
            line("joint", 3.0),
            line("joint", 12.0),
            line("joint", 12.5),
            line("joint", 13.0),
            "{\"stage\":\"jo".into(),
        ]
        .concat();
        std::fs::write(dir.path().join("log.jsonl"), log).unwrap();
        assert_eq!(ms_per_step(dir.path()).unwrap(), 500.0);
        std::fs::write(
            dir.path().join("log.jsonl"),
            line("body", 1.0) + &line("body", 1.25),
        )
        .unwrap();
        assert_eq!(ms_per_step(dir.path()).unwrap(), 250.0);
        std::fs::write(dir.path().join("log.jsonl"), "").unwrap();
        assert!(
            ms_per_step(dir.path())
                .unwrap_err()
                .to_string()
                .contains("log.jsonl")
        );
    }
}
