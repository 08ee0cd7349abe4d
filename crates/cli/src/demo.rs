//! `f3g demo` (synthetic capture → training → evaluation → animation → report.html) and
//! `f3g bench quality` (the face branch's effect, measured).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;
use f3g_avatar::eval::{EvalReport, Scores};
use f3g_data::split::SplitKind;
use serde::Serialize;

use crate::avatar::{AnimateArgs, EvalArgs, TrainArgs, animate, eval, train};
use crate::data::{SynthArgs, synth};

/// The synthetic capture and training overrides shared by `f3g demo` and `f3g bench quality`.
#[derive(Args, Debug)]
pub struct CaptureAndTraining {
    /// Seed of the capture's motion and of training.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Frames of the synthetic capture (the last 20 % are novel poses).
    #[arg(long, default_value_t = 20)]
    pub frames: usize,
    /// Image height of the synthetic capture.
    #[arg(long, default_value_t = 512)]
    pub resolution: usize,
    /// Override a training configuration key (repeatable), e.g. `--set steps.joint=50`.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
}

/// Options of `f3g demo`.
#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Output folder (capture, run, evaluation, animation, report.html).
    #[arg(long, default_value = "runs/demo")]
    pub out: PathBuf,
    #[command(flatten)]
    pub capture: CaptureAndTraining,
}

/// Makes the capture unless the folder already holds one.
fn ensure_capture(dir: &Path, c: &CaptureAndTraining) -> Result<()> {
    if dir.join("calibration_full.json").exists() {
        println!("reusing the capture in {}", dir.display());
        return Ok(());
    }
    synth(&SynthArgs {
        out: dir.to_path_buf(),
        cameras: Some(16),
        frames: Some(c.frames),
        resolution: Some(c.resolution),
        elevation: None,
        seed: c.seed,
        preset: None,
    })
}

/// Trains a run, or resumes it when the folder holds an unfinished one.
fn train_or_resume(run: &Path, data: &Path, seed: u64, set: &[String]) -> Result<()> {
    let mut args = TrainArgs {
        data: Some(data.to_path_buf()),
        out: Some(run.to_path_buf()),
        resume: None,
        config: None,
        preset: "cpu".into(),
        set: set.to_vec(),
        model: None,
        cameras: None,
        frames: None,
        no_face_branch: false,
        no_face_networks: false,
        no_adversarial: false,
        template: None,
        face_input: None,
        face_cm: None,
        face_n_mlp: None,
        seed: Some(seed),
        max_steps: None,
    };
    if run.join("config.json").exists() {
        println!("resuming the run in {}", run.display());
        args = TrainArgs {
            data: None,
            out: None,
            resume: Some(run.to_path_buf()),
            set: Vec::new(),
            seed: None,
            ..args
        };
    }
    train(&args)?;
    Ok(())
}

fn eval_args(run: &Path, split: SplitKind, every: usize) -> EvalArgs {
    EvalArgs {
        run: run.to_path_buf(),
        split,
        data: None,
        model: None,
        cameras: None,
        frames: None,
        every,
        scale: None,
        face_size: None,
        lpips_size: 512,
        lpips: None,
        out: None,
    }
}

pub fn demo(a: &DemoArgs) -> Result<()> {
    let start = std::time::Instant::now();
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let capture = a.out.join("capture");
    let run = a.out.join("run");
    println!("1/4 synthetic capture");
    ensure_capture(&capture, &a.capture)?;
    println!("2/4 training (cpu preset)");
    train_or_resume(&run, &capture, a.capture.seed, &a.capture.set)?;
    println!("3/4 evaluation");
    let novel_view = eval(&eval_args(&run, SplitKind::NovelView, 4))?;
    let novel_pose = eval(&eval_args(&run, SplitKind::NovelPose, 1))?;
    println!("4/4 animation");
    let animation = a.out.join("animation");
    animate(&AnimateArgs {
        run: run.clone(),
        motion: capture.join("body_params.npz"),
        camera: "orbit".into(),
        out: animation.clone(),
        export_ply: false,
        size: "288x384".into(),
        turns: 1.0,
        elevation: 5.0,
        fps: 8.0,
        no_pca: false,
    })?;
    let report = a.out.join("report.html");
    f3g_io::write_atomic(
        &report,
        html(
            &a.out,
            &novel_view,
            &novel_pose,
            start.elapsed().as_secs_f64(),
        )?
        .as_bytes(),
    )?;
    println!(
        "done in {:.1} min: open {}",
        start.elapsed().as_secs_f64() / 60.0,
        report.display()
    );
    Ok(())
}

fn rel(base: &Path, p: &Path) -> String {
    p.strip_prefix(base)
        .unwrap_or(p)
        .to_string_lossy()
        .replace('\\', "/")
}

fn cell(s: Option<&Scores>) -> String {
    match s {
        None => "<td>–</td><td>–</td><td>–</td>".into(),
        Some(s) => format!(
            "<td>{:.2}</td><td>{:.4}</td><td>{}</td>",
            s.psnr,
            s.ssim,
            s.lpips.map_or("n/a".into(), |v| format!("{v:.4}"))
        ),
    }
}

fn html(out: &Path, nv: &EvalReport, np: &EvalReport, seconds: f64) -> Result<String> {
    let run = out.join("run");
    let config = std::fs::read_to_string(run.join("config.json"))?;
    let img = |p: PathBuf, caption: &str| {
        format!(
            "<figure><img src=\"{}\"><figcaption>{caption}</figcaption></figure>",
            rel(out, &p)
        )
    };
    let row = |name: &str, r: &EvalReport| {
        format!(
            "<tr><td>{name} ({} images, step {})</td>{}{}</tr>",
            r.images.len(),
            r.step,
            cell(Some(&r.mean_body)),
            cell(r.mean_head.as_ref())
        )
    };
    Ok(format!(
        r#"<!doctype html>
<html><head><meta charset="utf-8"><title>f3g demo</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}}
table{{border-collapse:collapse}}td,th{{border:1px solid #ccc;padding:4px 10px;text-align:right}}
td:first-child{{text-align:left}}img{{max-width:100%}}figure{{margin:1em 0}}
pre{{background:#f4f4f4;padding:1em;overflow:auto;max-height:300px}}</style></head><body>
<h1>F3G-Avatar demo</h1>
<p>A synthetic 16-camera capture of the built-in human, an avatar trained with the <code>cpu</code>
preset (body branch + face branch, region-aware losses, adversarial face loss), evaluated on
held-out cameras (novel view) and held-out frames (novel pose), and animated. Everything ran on
the CPU in {minutes:.1} minutes.</p>
<h2>Metrics</h2>
<table><tr><th></th><th>body PSNR ↑</th><th>body SSIM ↑</th><th>body LPIPS ({lpips}) ↓</th>
<th>head PSNR ↑</th><th>head SSIM ↑</th><th>head LPIPS ↓</th></tr>
{nv_row}
{np_row}
</table>
<p>Per-image numbers: <a href="{nv_md}">novel view</a>, <a href="{np_md}">novel pose</a>.</p>
<h2>Novel views: ground truth | render | error</h2>
{nv_grid}
<h2>Novel poses</h2>
{np_grid}
<h2>Animation (orbit over the capture's motion)</h2>
{gif}
<h2>Training</h2>
{loss}
{validation}
<h2>Configuration</h2>
<pre>{config}</pre>
</body></html>
"#,
        minutes = seconds / 60.0,
        lpips = nv.lpips_net,
        nv_row = row("novel view", nv),
        np_row = row("novel pose", np),
        nv_md = rel(out, &run.join("eval/novel-view/metrics.md")),
        np_md = rel(out, &run.join("eval/novel-pose/metrics.md")),
        nv_grid = img(
            run.join("eval/novel-view/comparison.png"),
            "held-out cameras 7 and 13"
        ),
        np_grid = img(
            run.join("eval/novel-pose/comparison.png"),
            "held-out frames"
        ),
        gif = img(out.join("animation/animation.gif"), "orbiting camera"),
        loss = img(run.join("loss.png"), "losses (moving average, log scale)"),
        validation = img(
            run.join("validation.png"),
            "last validation render (body and face crop)"
        ),
        config = config.replace('<', "&lt;"),
    ))
}

/// Options of `f3g bench quality`.
#[derive(Args, Debug)]
pub struct QualityArgs {
    /// Output folder (capture and the two runs).
    #[arg(long, default_value = "runs/quality")]
    pub out: PathBuf,
    #[command(flatten)]
    pub capture: CaptureAndTraining,
    /// Evaluate every N-th frame of the novel-view split.
    #[arg(long, default_value_t = 2)]
    pub every: usize,
}

#[derive(Serialize)]
struct Quality {
    face_branch: EvalReport,
    no_face_branch: EvalReport,
}

pub fn quality(a: &QualityArgs) -> Result<()> {
    let capture = a.out.join("capture");
    ensure_capture(&capture, &a.capture)?;
    let mut reports = Vec::new();
    for (name, extra) in [("face", None), ("no-face", Some("face_branch=false"))] {
        let run = a.out.join(name);
        let mut set = a.capture.set.clone();
        set.extend(extra.map(String::from));
        println!("training `{name}`");
        train_or_resume(&run, &capture, a.capture.seed, &set)?;
        reports.push(eval(&eval_args(&run, SplitKind::NovelView, a.every))?);
    }
    let no_face = reports.pop().expect("two runs");
    let face = reports.pop().expect("two runs");
    let line = |name: &str, r: &EvalReport| {
        let h = r.mean_head.clone().unwrap_or_default();
        let l = |v: Option<f64>| v.map_or("n/a".into(), |v| format!("{v:.4}"));
        format!(
            "| {name} | {:.3} | {:.4} | {} | {:.3} | {:.4} | {} |",
            r.mean_body.psnr,
            r.mean_body.ssim,
            l(r.mean_body.lpips),
            h.psnr,
            h.ssim,
            l(h.lpips)
        )
    };
    let table = format!(
        "| variant | body PSNR | body SSIM | body LPIPS | head PSNR | head SSIM | head LPIPS |\n|---|---|---|---|---|---|---|\n{}\n{}\n",
        line("face branch", &face),
        line("no face branch", &no_face)
    );
    println!("\n{table}");
    f3g_io::write_atomic(&a.out.join("quality.md"), table.as_bytes())?;
    f3g_io::write_atomic(
        &a.out.join("quality.json"),
        serde_json::to_string_pretty(&Quality {
            face_branch: face,
            no_face_branch: no_face,
        })?
        .as_bytes(),
    )?;
    println!("wrote {}", a.out.join("quality.json").display());
    Ok(())
}
