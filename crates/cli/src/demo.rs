//! `f3g demo`: synthetic capture → training → evaluation → animation → report.html.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;
use f3g_avatar::infer::eval::{EvalReport, Scores};
use f3g_avatar::train::TrainConfig;
use f3g_data::split::SplitKind;

use crate::avatar::{AnimateArgs, ConfigArgs, EvalArgs, TrainArgs, animate, eval, train_with};
use crate::data::{SynthArgs, synth};
use crate::device::DeviceArg;

/// The synthetic capture and training overrides shared by `f3g demo` and `f3g bench quality`.
#[derive(Args, Debug)]
pub struct CaptureAndTraining {
    /// Seed of the capture's motion and of training.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Frames of the synthetic capture, 5–10000 (the last 20 % are novel poses).
    #[arg(long, default_value_t = 20, value_parser = crate::bounds::size::<5, 10_000>)]
    pub frames: usize,
    /// Image height of the synthetic capture (64–4096). The default, AvatarReX's 2048, puts
    /// the head at about 230 pixels for the face crops; the body is trained and evaluated at
    /// 512 pixels tall (`body_scale`, unless `--set body_scale=…` says otherwise).
    #[arg(long, default_value_t = 2048, value_parser = crate::bounds::size::<64, 4096>)]
    pub resolution: usize,
    /// Override a training configuration key (repeatable), e.g. `--set steps.joint=50`.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    #[command(flatten)]
    pub device: DeviceArg,
}

/// Height in pixels of the body views the demo trains and evaluates on, whatever the
/// capture's resolution: the networks' cost is set by the maps, but the body's render, its
/// losses and the loader's images grow with the pixels.
const BODY_HEIGHT: usize = 512;

impl CaptureAndTraining {
    /// Shows the body at [`BODY_HEIGHT`] pixels (`--set body_scale=…` has the last word).
    pub fn apply(&self, config: &mut TrainConfig) {
        config.body_scale = (BODY_HEIGHT as f32 / self.resolution as f32).min(1.0);
    }
}

/// Options of `f3g demo`.
#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Output folder (capture, run, evaluation, animation, report.html); default
    /// `runs/demo`, or `runs/demo-quality` with `--quality`.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Train the `cpu-long` preset (about 25 minutes on two cores) instead of `cpu`:
    /// the same avatar, closer to the ground truth.
    #[arg(long)]
    pub quality: bool,
    #[command(flatten)]
    pub capture: CaptureAndTraining,
}

/// Makes the capture unless the folder already holds one.
pub(crate) fn ensure_capture(dir: &Path, c: &CaptureAndTraining) -> Result<()> {
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
        // At 1024 pixels and above the head crops and the body views are cut down from the
        // capture, which filters them: one sample per pixel halves the capture's time.
        supersample: Some(if c.resolution >= 1024 { 1 } else { 2 }),
        seed: c.seed,
        preset: None,
        overwrite: false,
        motion: None,
        retarget: Default::default(),
        fps: None,
    })
}

/// Trains a run, or resumes it when the folder holds an unfinished one; a new run's
/// configuration is the preset's with `seed`, then `adjust`, then the `--set`s in `set`.
pub(crate) fn train_or_resume(
    run: &Path,
    data: &Path,
    preset: &str,
    seed: u64,
    set: &[String],
    device: DeviceArg,
    adjust: impl FnOnce(&mut TrainConfig),
) -> Result<()> {
    let mut args = TrainArgs {
        data: Some(data.to_path_buf()),
        out: Some(run.to_path_buf()),
        resume: None,
        config: ConfigArgs {
            config: None,
            preset: preset.into(),
            set: set.to_vec(),
        },
        model: Default::default(),
        cameras: None,
        frames: None,
        ablation: Default::default(),
        seed: Some(seed),
        max_steps: None,
        device,
        devices: Vec::new(),
    };
    if run.join("config.json").exists() {
        println!("resuming the run in {}", run.display());
        args = TrainArgs {
            data: None,
            out: None,
            resume: Some(run.to_path_buf()),
            config: ConfigArgs::default(),
            seed: None,
            ..args
        };
    }
    train_with(&args, adjust)?;
    Ok(())
}

pub(crate) fn eval_args(run: &Path, split: SplitKind, every: usize, device: DeviceArg) -> EvalArgs {
    EvalArgs {
        run: run.to_path_buf(),
        split,
        data: None,
        model: Default::default(),
        cameras: None,
        frames: None,
        every,
        scale: None,
        face_size: f3g_avatar::infer::eval::DEFAULT_FACE_SIZE,
        lpips_size: 512,
        lpips: None,
        out: None,
        overwrite: false,
        device,
    }
}

pub fn demo(a: &DemoArgs) -> Result<()> {
    let start = std::time::Instant::now();
    let (preset, default_out) = if a.quality {
        ("cpu-long", "runs/demo-quality")
    } else {
        ("cpu", "runs/demo")
    };
    let out = a.out.clone().unwrap_or_else(|| default_out.into());
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let capture = out.join("capture");
    let run = out.join("run");
    println!("1/5 synthetic capture");
    ensure_capture(&capture, &a.capture)?;
    // The posed body over every camera's first frame: what a user checks their own capture with.
    let (sheet, fits) = f3g_data::check::contact_sheet(
        &f3g_data::Dataset::open(&capture, None)?,
        0,
        192,
        1.3,
        true,
    )?;
    f3g_io::write_png(&out.join("capture_check.png"), &sheet)?;
    println!("2/5 training ({preset} preset)");
    let device = a.capture.device;
    train_or_resume(
        &run,
        &capture,
        preset,
        a.capture.seed,
        &a.capture.set,
        device,
        |config| a.capture.apply(config),
    )?;
    println!("3/5 evaluation");
    let novel_view = eval(&eval_args(&run, SplitKind::NovelView, 4, device))?;
    let novel_pose = eval(&eval_args(&run, SplitKind::NovelPose, 1, device))?;
    println!("4/5 animation");
    let animation = out.join("animation");
    animate(&AnimateArgs {
        run: run.clone(),
        motion: capture.join("body_params.npz"),
        retarget: Default::default(),
        frames: Default::default(),
        camera: "orbit".into(),
        out: animation.clone(),
        // The demo's own subfolders: an earlier demo's (of any version) are written over.
        overwrite: true,
        export_ply: false,
        export_spz: false,
        size: (288, 384),
        turns: 1.0,
        elevation: 5.0,
        fps: 8.0,
        no_pca: false,
        no_floor: false,
        device,
    })?;
    println!("5/5 avatar file and browser player");
    let glb = out.join("avatar.glb");
    let compressed = out.join("avatar.compressed.glb");
    crate::avatar::export_avatar_files(
        &crate::avatar::ExportAvatarArgs {
            run: run.clone(),
            out: glb.clone(),
            correctives: 16,
            sh_degree: 0,
            directions: 48,
            poses: 60,
            perturbations: 3,
            no_expressions: false,
            compress: false,
            seed: a.capture.seed,
            json: None,
            device,
        },
        Some(&compressed),
    )?;
    // The player is the web's copy of the avatar: the compressed file (a seventh of the size).
    crate::view::view(&crate::view::ViewArgs {
        source: compressed.clone(),
        motion: vec![capture.join("body_params.npz")],
        retarget: Default::default(),
        frames: Default::default(),
        port: 0,
        host: std::net::IpAddr::from([127, 0, 0, 1]),
        static_dir: Some(out.join("player")),
        overwrite: true,
        correctives: 16,
        fps: 8.0,
        device,
    })?;
    let faces = frontal_faces(
        &run.join("eval/novel-view"),
        &novel_view,
        &out.join("face_front.png"),
    )?;
    let report = out.join("report.html");
    f3g_io::write_atomic(
        &report,
        html(
            &out,
            preset,
            &novel_view,
            &novel_pose,
            &fits,
            faces,
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

/// The faces the evaluation saw from the front (`images/*_head[_gt].png` of the frontal view
/// class, most frontal first, at most four), as rows of ground truth | render at the crops'
/// size; returns whether there was one (nothing is written when no image was frontal).
fn frontal_faces(eval: &Path, report: &EvalReport, out: &Path) -> Result<bool> {
    use f3g_data::crop::ViewClass;
    let mut front: Vec<_> = report
        .images
        .iter()
        .filter(|i| i.view == ViewClass::Front && i.head.is_some())
        .collect();
    front.sort_by(|a, b| a.view_angle_deg.total_cmp(&b.view_angle_deg));
    let mut rows = Vec::new();
    for image in front.iter().take(4) {
        let name = format!("{}_{:08}_head", image.camera, image.frame);
        let read = |suffix: &str| {
            let path = eval.join(format!("images/{name}{suffix}.png"));
            f3g_io::read_rgb(&path).with_context(|| path.display().to_string())
        };
        rows.push([read("_gt")?, read("")?]);
    }
    let Some([first, _]) = rows.first() else {
        return Ok(false);
    };
    let (w, h, gap) = (first.width, first.height, 6);
    let mut sheet = f3g_io::Image::filled(2 * w + gap, rows.len() * (h + gap) - gap, 3, 1.0);
    for (r, pair) in rows.iter().enumerate() {
        for (c, face) in pair.iter().enumerate() {
            if (face.width, face.height) != (w, h) {
                anyhow::bail!("the head crops of {} differ in size", eval.display());
            }
            for y in 0..h {
                for x in 0..w {
                    sheet
                        .pixel_mut(c * (w + gap) + x, r * (h + gap) + y)
                        .copy_from_slice(&face.pixel(x, y)[..3]);
                }
            }
        }
    }
    f3g_io::write_png(out, &sheet)?;
    Ok(true)
}

/// A file's size in MB (0 when it cannot be read).
fn megabytes(path: &Path) -> f64 {
    std::fs::metadata(path).map_or(0.0, |m| m.len() as f64 / 1e6)
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

/// What the capture's check sheet shows, with its numbers.
fn capture_caption(fits: &[f3g_data::check::CameraFit]) -> String {
    let low = |f: fn(&f3g_data::check::CameraFit) -> f32| {
        fits.iter().map(f).fold(f32::INFINITY, f32::min)
    };
    let flagged: Vec<&str> = fits
        .iter()
        .filter(|f| f.flagged)
        .map(|f| f.camera.as_str())
        .collect();
    format!(
        "frame 0 of every camera with the posed body model's outline (cyan; <code>f3g data \
         show --overlay</code>): IoU with the masks ≥ {:.3}, body inside the masks ≥ {:.3}; \
         cameras flagged: {}",
        low(|f| f.iou),
        low(|f| f.body_in_mask),
        if flagged.is_empty() {
            "none".to_string()
        } else {
            flagged.join(", ")
        }
    )
}

fn html(
    out: &Path,
    preset: &str,
    nv: &EvalReport,
    np: &EvalReport,
    fits: &[f3g_data::check::CameraFit],
    faces: bool,
    seconds: f64,
) -> Result<String> {
    let run = out.join("run");
    let config_path = run.join("config.json");
    let config = std::fs::read_to_string(&config_path)?;
    // The file the run wrote holds every key: its text, shown below, parses as it is. The
    // `cpu` presets leave the paper's adversarial loss out (at their lengths its time buys
    // more in joint steps).
    let adversarial = serde_json::from_str::<TrainConfig>(&config)
        .with_context(|| format!("reading {}", config_path.display()))?
        .adversarial;
    let face_losses = if adversarial {
        "region-aware losses, adversarial face loss"
    } else {
        "region-aware losses; the paper's adversarial face loss left out at this length"
    };
    let img = |p: PathBuf, caption: &str| {
        format!(
            "<figure><img src=\"{}\"><figcaption>{caption}</figcaption></figure>",
            rel(out, &p)
        )
    };
    // The means, then the head seen from the front, the side and the back.
    let row = |name: &str, r: &EvalReport| {
        let mut rows = format!(
            "<tr><td>{name} ({} images, step {})</td>{}{}</tr>",
            r.images.len(),
            r.step,
            cell(Some(&r.mean_body)),
            cell(r.mean_head.as_ref())
        );
        for (class, v) in &r.head_by_view {
            rows += &format!(
                "\n<tr><td>&nbsp;&nbsp;head seen from the {} ({} images)</td>{}{}</tr>",
                class.name(),
                v.images,
                cell(None),
                cell(Some(&v.head))
            );
        }
        rows
    };
    let cameras = {
        let mut names: Vec<&str> = nv.images.iter().map(|i| i.camera.as_str()).collect();
        names.dedup();
        names.sort();
        names.dedup();
        names.join(", ")
    };
    Ok(format!(
        r#"<!doctype html>
<html><head><meta charset="utf-8"><title>f3g demo</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}}
table{{border-collapse:collapse}}td,th{{border:1px solid #ccc;padding:4px 10px;text-align:right}}
td:first-child{{text-align:left}}img{{max-width:100%}}figure{{margin:1em 0}}
pre{{background:#f4f4f4;padding:1em;overflow:auto;max-height:300px}}</style></head><body>
<h1>F3G-Avatar demo</h1>
<p>A synthetic 16-camera capture of the built-in human, an avatar trained with the <code>{preset}</code>
preset (body branch + face branch, {face_losses}), evaluated on
held-out cameras (novel view) and held-out frames (novel pose), and animated. Everything ran on
the CPU in {minutes:.1} minutes.</p>
<h2>The capture</h2>
{capture}
<h2>Metrics</h2>
<table><tr><th></th><th>body PSNR ↑</th><th>body SSIM ↑</th><th>body LPIPS ({lpips}) ↓</th>
<th>head PSNR ↑</th><th>head SSIM ↑</th><th>head LPIPS ↓</th></tr>
{nv_row}
{np_row}
</table>
<p>Per-image numbers: <a href="{nv_md}">novel view</a>, <a href="{np_md}">novel pose</a>.</p>
<h2>The face from the front</h2>
{faces}
<h2>Against the paper</h2>
<p>The paper's Table 1 is measured on AvatarReX (real captures of people, 16 cameras at
2048×1500, 405 000 training steps on a GPU); this demo is a synthetic capture of the built-in
human trained for minutes on a CPU. The numbers are <em>not</em> comparable number for number; they show the
scale the method reaches there.</p>
<table><tr><th></th><th>body PSNR ↑</th><th>body SSIM ↑</th><th>body LPIPS ↓</th>
<th>head PSNR ↑</th><th>head SSIM ↑</th><th>head LPIPS ↓</th></tr>
<tr><td>F3G-Avatar (paper, AvatarReX)</td><td>30.214</td><td>0.970</td><td>0.032</td><td>26.243</td><td>0.964</td><td>0.084</td></tr>
<tr><td>Animatable Gaussians (paper's Table 1, AvatarReX)</td><td>30.361</td><td>0.968</td><td>0.034</td><td>25.671</td><td>0.957</td><td>0.114</td></tr>
<tr><td>this demo (synthetic, <code>{preset}</code> preset)</td>{demo_cells}</tr>
</table>
<h2>Novel views: ground truth | render | error</h2>
{nv_grid}
<h2>Novel poses</h2>
{np_grid}
<h2>Animation (orbit over the capture's motion)</h2>
<video src="{mp4}" controls loop autoplay muted playsinline style="max-width:100%"></video>
<p>The same as <a href="{mp4}">H.264 video</a> and <a href="{gif_path}">GIF</a>. Every held-out
view as ground truth | render | error: <a href="{nv_mp4}">novel views</a>,
<a href="{np_mp4}">novel poses</a>.</p>
<h2>The avatar in your browser</h2>
<p>The avatar baked into one portable file, <a href="avatar.glb">avatar.glb</a> ({glb_mb:.1} MB:
glTF 2.0 with <code>KHR_gaussian_splatting</code> and a skin, every value a float, which
Babylon.js and other <code>KHR_gaussian_splatting</code> viewers read), and compressed,
<a href="avatar.compressed.glb">avatar.compressed.glb</a> ({compressed_mb:.1} MB: SPZ Gaussians,
quantised correctives; what the player loads). The player: <code>f3g view {glb}</code> and open
<code>http://127.0.0.1:8080/</code>, or serve the folder <a href="player/">player/</a> with any
static file server (browsers do not run it from <code>file://</code>).</p>
<h2>Training</h2>
{loss}
{validation}
<h2>Configuration</h2>
<pre>{config}</pre>
</body></html>
"#,
        minutes = seconds / 60.0,
        capture = img(out.join("capture_check.png"), &capture_caption(fits)),
        lpips = nv.lpips_net,
        nv_row = row("novel view", nv),
        np_row = row("novel pose", np),
        nv_md = rel(out, &run.join("eval/novel-view/metrics.md")),
        np_md = rel(out, &run.join("eval/novel-pose/metrics.md")),
        faces = if faces {
            img(
                out.join("face_front.png"),
                "the held-out views that see the face from the front (within 45°), most frontal \
                 first: ground truth | render, 256² crops",
            )
        } else {
            "<p>No held-out view sees the face from the front.</p>".into()
        },
        demo_cells = cell(Some(&nv.mean_body)) + &cell(nv.mean_head.as_ref()),
        nv_grid = img(
            run.join("eval/novel-view/comparison.png"),
            &format!(
                "held-out cameras {cameras}: head crops seen from the front first, then from \
                 the side and the back, then whole bodies"
            )
        ),
        np_grid = img(
            run.join("eval/novel-pose/comparison.png"),
            "held-out frames"
        ),
        mp4 = rel(out, &out.join("animation/animation.mp4")),
        gif_path = rel(out, &out.join("animation/animation.gif")),
        nv_mp4 = rel(out, &run.join("eval/novel-view/comparison.mp4")),
        np_mp4 = rel(out, &run.join("eval/novel-pose/comparison.mp4")),
        glb = out.join("avatar.compressed.glb").display(),
        glb_mb = megabytes(&out.join("avatar.glb")),
        compressed_mb = megabytes(&out.join("avatar.compressed.glb")),
        loss = img(run.join("loss.png"), "losses (moving average, log scale)"),
        validation = img(
            run.join("validation.png"),
            "last validation render (body and face crop)"
        ),
        config = config.replace('<', "&lt;"),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        capture: CaptureAndTraining,
    }

    /// The `body_scale` of the demo's configuration for these flags.
    fn body_scale(args: &[&str]) -> f32 {
        let capture = Cli::parse_from(std::iter::once("f3g").chain(args.iter().copied())).capture;
        let config = ConfigArgs {
            config: None,
            preset: "cpu".into(),
            set: capture.set.clone(),
        };
        config.load(|c| capture.apply(c)).unwrap().body_scale
    }

    #[test]
    fn the_body_is_seen_at_the_body_height_unless_set() {
        assert_eq!(body_scale(&[]), 0.25);
        assert_eq!(
            body_scale(&["--resolution", "1024", "--set", "steps.joint=5"]),
            0.5
        );
        assert_eq!(body_scale(&["--resolution", "300"]), 1.0);
        assert_eq!(body_scale(&["--set", "body_scale=0.5"]), 0.5);
    }

    /// The report parses the run's `config.json` as it is (not over a preset): the file a run
    /// writes holds every key, whichever preset it came from.
    #[test]
    fn a_runs_config_file_parses_whole() {
        let dir = tempfile::tempdir().unwrap();
        let run = f3g_avatar::infer::Run::new(dir.path());
        for preset in ["cpu", "cpu-long", "paper"] {
            let config = TrainConfig::preset(preset).unwrap();
            run.write_config(&config).unwrap();
            let text = std::fs::read_to_string(dir.path().join("config.json")).unwrap();
            assert_eq!(serde_json::from_str::<TrainConfig>(&text).unwrap(), config);
        }
    }
}
