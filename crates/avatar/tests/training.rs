//! Training on a tiny synthetic capture: the loss falls, every network learns, a killed run
//! resumes exactly, evaluation numbers can be recomputed from its images, and bad runs fail
//! clearly.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};

use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Device, Tensor};
use f3g_avatar::infer::TrainedAvatar;
use f3g_avatar::infer::eval::{EvalOptions, evaluate};
use f3g_avatar::train::{Outcome, TrainConfig, Trainer};
use f3g_data::split::SplitKind;
use f3g_data::synth::{SynthOptions, generate};
use f3g_nets::LpipsNet;

/// 16 cameras (the synthetic split holds out 0, 7 and 13), 5 frames, 96×128.
fn capture(dir: &Path) {
    let options = SynthOptions {
        cameras: 16,
        frames: 5,
        resolution: 128,
        supersample: 1,
        ..Default::default()
    };
    generate(dir, &options, &|_| {}).unwrap();
}

/// The cpu preset shrunk to run a step in a fraction of a second, with the paper's
/// adversarial loss (which the preset leaves out), so that every test goes through the
/// discriminator.
fn tiny(steps: [u64; 5]) -> TrainConfig {
    let c = TrainConfig::cpu();
    let mut config = TrainConfig {
        adversarial: true,
        lpips_size: 32,
        body_scale: 0.5,
        face_init_frames: 2,
        checkpoint_every: 1000,
        validate_every: 1000,
        ..c
    };
    config.model.map_resolution = 32;
    config.model.face_crop_size = 32;
    config.model.body_net.input_size = 16;
    config.model.body_net.output_size = 32;
    config.model.body_net.max_channels = 16;
    config.model.body_net.channel_base = 256;
    config.model.body_net.style_dim = 16;
    config.model.body_net.middle_size = 4;
    config.model.face_net.input_size = 16;
    config.model.face_net.output_size = 16;
    config.model.face_net.max_channels = 16;
    config.model.face_net.channel_base = 128;
    config.model.face_net.style_dim = 16;
    config.model.face_net.middle_size = 4;
    config.discriminator.resolution = 32;
    config.discriminator.max_channels = 16;
    config.discriminator.channel_base = 128;
    config.losses.r1_interval = 2;
    let [pretrain, body, face_pretrain, joint, face_finetune] = steps;
    config.steps = f3g_avatar::train::Stages {
        pretrain,
        body,
        face_pretrain,
        joint,
        face_finetune,
    };
    config.validate().unwrap();
    config
}

/// `tiny(steps)` without the face branch (body Gaussians and body losses only).
fn tiny_body(steps: [u64; 5]) -> TrainConfig {
    let mut config = TrainConfig {
        face_losses: false,
        ..tiny(steps)
    };
    config.model.face_branch = false;
    config
}

/// A new run of `config` on `cap` (the protocol's training split) on the CPU.
fn create(run: &Path, cap: &Path, config: TrainConfig) -> Result<Trainer, f3g_avatar::AvatarError> {
    Trainer::create(run, cap, None, config, None, None, &[Device::flex()])
}

/// Trains a new run of `config` on `cap` to its last step.
fn train_to_end(run: &Path, cap: &Path, config: TrainConfig) {
    create(run, cap, config)
        .unwrap()
        .train(&AtomicBool::new(false), &mut |_| {})
        .unwrap();
}

/// Every float parameter's values, in visiting order.
struct Values(Vec<Vec<f32>>);
impl ModuleVisitor for Values {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        self.0
            .push(param.val().into_data().try_into_vec::<f32>().unwrap());
    }
}

fn values<M: Module>(m: &M) -> Vec<Vec<f32>> {
    let mut v = Values(Vec::new());
    m.visit(&mut v);
    v.0
}

fn losses(run: &Path) -> Vec<(u64, String, f32)> {
    std::fs::read_to_string(run.join("log.jsonl"))
        .unwrap()
        .lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            (
                v["step"].as_u64().unwrap(),
                v["stage"].as_str().unwrap().to_string(),
                v["total"].as_f64().unwrap() as f32,
            )
        })
        .collect()
}

#[test]
fn training_lowers_the_loss_and_reaches_every_network() {
    let dir = tempfile::tempdir().unwrap();
    capture(&dir.path().join("cap"));
    let run = dir.path().join("run");
    let config = tiny([30, 25, 3, 6, 2]);
    let mut t = create(&run, &dir.path().join("cap"), config).unwrap();
    let stop = AtomicBool::new(false);
    let mut trainer_steps = 0;
    let outcome = t.train(&stop, &mut |_| trainer_steps += 1).unwrap();
    assert_eq!((outcome, trainer_steps), (Outcome::Finished, 66));
    let log = losses(&run);
    let mean = |stage: &str, first: bool| {
        let v: Vec<f32> = log.iter().filter(|l| l.1 == stage).map(|l| l.2).collect();
        let part = if first { &v[..5] } else { &v[v.len() - 5..] };
        part.iter().sum::<f32>() / 5.0
    };
    assert!(
        mean("pretrain", false) < 0.8 * mean("pretrain", true),
        "{log:?}"
    );
    assert!(mean("body", false) < mean("body", true), "{log:?}");
    // The joint stage logs the adversarial and discriminator terms.
    let text = std::fs::read_to_string(run.join("log.jsonl")).unwrap();
    assert!(text.contains("\"adversarial\"") && text.contains("\"discriminator\""));
    for f in [
        "loss.png",
        "validation.png",
        "pca.npz",
        "config.json",
        "run.json",
    ] {
        assert!(run.join(f).exists(), "{f}");
    }
}

#[test]
fn every_network_and_the_discriminator_are_updated() {
    let dir = tempfile::tempdir().unwrap();
    capture(&dir.path().join("cap"));
    let cap = dir.path().join("cap");
    // Two runs with the same seed: one stops before the face stages, one after them.
    let before = dir.path().join("before");
    let after = dir.path().join("after");
    let stop = AtomicBool::new(false);
    let mut t = create(&before, &cap, tiny([2, 2, 0, 0, 0])).unwrap();
    t.train(&stop, &mut |_| {}).unwrap();
    let mut u = create(&after, &cap, tiny([2, 2, 2, 3, 2])).unwrap();
    u.train(&stop, &mut |_| {}).unwrap();
    let b = TrainedAvatar::load(&before, &Device::flex()).unwrap();
    let a = TrainedAvatar::load(&after, &Device::flex()).unwrap();
    let face_init = tiny([1, 0, 0, 0, 0]);
    let fresh_face = f3g_avatar::model::AvatarNets::new(
        &face_init.model,
        face_init.seed,
        &a.setup,
        &Device::flex(),
    )
    .unwrap()
    .face
    .unwrap();
    // The body moved between step 4 and the end (joint stage), and so did the face networks
    // from their initial weights.
    assert_ne!(values(&b.nets.body), values(&a.nets.body));
    let trained_face = a.nets.face.as_ref().unwrap();
    for (name, fresh, trained) in [
        (
            "position",
            values(&fresh_face.position),
            values(&trained_face.position),
        ),
        (
            "colour",
            values(&fresh_face.colour),
            values(&trained_face.colour),
        ),
        ("aux", values(&fresh_face.aux), values(&trained_face.aux)),
    ] {
        assert_ne!(fresh, trained, "the face {name} network did not learn");
    }
    // The discriminator saved with the last checkpoint differs from its initialisation.
    let ckpt = std::fs::read_to_string(after.join("checkpoints/latest")).unwrap();
    let device = burn::tensor::Device::flex();
    let d0 = face_init
        .discriminator
        .init(face_init.seed.wrapping_add(20), &device)
        .unwrap();
    let d1 = f3g_nets::checkpoint::load(
        face_init.discriminator.init(0, &device).unwrap(),
        &after.join("checkpoints").join(ckpt.trim()).join("disc.bpk"),
    )
    .unwrap();
    assert_ne!(values(&d0), values(&d1), "the discriminator did not learn");
    assert!(a.face_base.is_some() && b.face_base.is_none());
    // A new run can start from those discriminator weights.
    let mut config = tiny([1, 0, 0, 0, 0]);
    let weights = after.join("checkpoints").join(ckpt.trim()).join("disc.bpk");
    config.discriminator_weights = Some(weights.to_string_lossy().into_owned());
    let third = dir.path().join("third");
    create(&third, &cap, config.clone())
        .unwrap()
        .train(&stop, &mut |_| {})
        .unwrap();
    let ckpt3 = std::fs::read_to_string(third.join("checkpoints/latest")).unwrap();
    let d3 = f3g_nets::checkpoint::load(
        face_init.discriminator.init(0, &device).unwrap(),
        &third
            .join("checkpoints")
            .join(ckpt3.trim())
            .join("disc.bpk"),
    )
    .unwrap();
    assert_eq!(values(&d1), values(&d3));
    config.discriminator_weights = Some("missing.bpk".into());
    let e = create(&dir.path().join("fourth"), &cap, config)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("missing.bpk"), "{e}");
}

/// Every logged loss term of every step, by name.
fn loss_terms(run: &Path) -> Vec<Vec<(String, f64)>> {
    std::fs::read_to_string(run.join("log.jsonl"))
        .unwrap()
        .lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            v["losses"]
                .as_array()
                .unwrap()
                .iter()
                .map(|t| (t[0].as_str().unwrap().into(), t[1].as_f64().unwrap()))
                .collect()
        })
        .collect()
}

/// The data-parallel step: two replicas (on the CPU, with the host all-reduce), each on its own
/// sample, give the update of one replica stepping on both samples' mean loss (`batch = 2`, one
/// graph, one backward) — through every stage, the discriminator included — and stay equal.
#[test]
fn two_replicas_apply_the_update_of_one_batch_of_two() {
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("cap");
    capture(&cap);
    let steps = [1, 2, 1, 3, 1];
    let (replicas, batch, single) = (
        dir.path().join("replicas"),
        dir.path().join("batch"),
        dir.path().join("single"),
    );
    let stop = AtomicBool::new(false);
    let devices = [Device::flex(), Device::flex()];
    let mut two =
        Trainer::create(&replicas, &cap, None, tiny(steps), None, None, &devices).unwrap();
    two.train(&stop, &mut |_| {}).unwrap();
    let config = TrainConfig {
        batch: 2,
        ..tiny(steps)
    };
    let mut one = create(&batch, &cap, config).unwrap();
    one.train(&stop, &mut |_| {}).unwrap();
    train_to_end(&single, &cap, tiny(steps));

    let (a, b) = (loss_terms(&replicas), loss_terms(&batch));
    assert_eq!(a.len(), 8);
    assert!(a[5].iter().any(|t| t.0 == "discriminator"), "{:?}", a[5]);
    for (step, (x, y)) in a.iter().zip(&b).enumerate() {
        assert_eq!(x.len(), y.len(), "step {step}: {x:?} vs {y:?}");
        for (p, q) in x.iter().zip(y) {
            assert_eq!(p.0, q.0);
            assert!(
                (p.1 - q.1).abs() <= 1e-5 * (1.0 + q.1.abs()),
                "step {step} {}: {} vs {}",
                p.0,
                p.1,
                q.1
            );
        }
    }
    // The premise: the replicas drew different samples (a single sample per step differs).
    let c = loss_terms(&single);
    assert!(
        a.iter().zip(&c).any(|(x, y)| x[0].1 != y[0].1),
        "two replicas trained like one sample per step"
    );
    let nets: Vec<_> = two.replica_nets().map(values).collect();
    assert_eq!(nets[0], nets[1], "the replicas diverged");
    let mut largest = 0.0f32;
    for (x, y) in nets[0]
        .iter()
        .flatten()
        .zip(values(one.nets()).iter().flatten())
    {
        largest = largest.max((x - y).abs());
    }
    assert!(largest < 1e-4, "weights differ by {largest}");
}

#[test]
fn a_killed_run_resumes_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("cap");
    capture(&cap);
    let steps = [2, 2, 1, 3, 1];
    let whole = dir.path().join("whole");
    let stop = AtomicBool::new(false);
    create(&whole, &cap, tiny(steps))
        .unwrap()
        .train(&stop, &mut |_| {})
        .unwrap();
    // Stop after step 5 (inside the face stages), reopen, finish.
    let parts = dir.path().join("parts");
    let stop = AtomicBool::new(false);
    let mut t = create(&parts, &cap, tiny(steps)).unwrap();
    let outcome = t
        .train(&stop, &mut |r| {
            if r.step == 5 {
                stop.store(true, Ordering::Relaxed);
            }
        })
        .unwrap();
    assert_eq!(outcome, Outcome::Stopped);
    drop(t);
    let mut t = Trainer::resume(&parts, None, &[Device::flex()]).unwrap();
    assert_eq!(t.step(), 6);
    t.train(&AtomicBool::new(false), &mut |_| {}).unwrap();
    let (a, b) = (
        TrainedAvatar::load(&whole, &Device::flex()).unwrap(),
        TrainedAvatar::load(&parts, &Device::flex()).unwrap(),
    );
    assert_eq!(values(&a.nets), values(&b.nets));
    assert_eq!(a.face_base, b.face_base);
    assert_eq!(losses(&whole), losses(&parts));
}

#[test]
fn evaluation_numbers_equal_metrics_of_the_saved_images() {
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("cap");
    capture(&cap);
    let run = dir.path().join("run");
    train_to_end(&run, &cap, tiny([2, 3, 1, 2, 1]));
    let options = EvalOptions {
        split: SplitKind::NovelView,
        cameras: None,
        frames: None,
        every: 2,
        scale: 0.5,
        face_size: 32,
        lpips_size: 64,
        lpips_net: LpipsNet::Alex,
        out: None,
        overwrite: false,
    };
    let report = evaluate(&run, None, None, &options, &Device::flex(), &mut |_, _| {}).unwrap();
    assert!(!report.images.is_empty() && report.lpips_available);
    let images = run.join("eval/novel-view/images");
    let lpips = f3g_nets::Lpips::load(LpipsNet::Alex, &Device::flex()).unwrap();
    let device = burn::tensor::Device::flex();
    for i in &report.images {
        let name = format!("{}_{:08}", i.camera, i.frame);
        let read =
            |suffix: &str| f3g_io::read_rgb(&images.join(format!("{name}{suffix}.png"))).unwrap();
        let (render, gt) = (read(""), read("_gt"));
        let psnr = f3g_nets::metrics::psnr(&render, &gt).unwrap();
        let ssim = f3g_nets::metrics::ssim_skimage(&render, &gt).unwrap();
        let ssim_3dgs = f3g_nets::metrics::ssim_images(&render, &gt).unwrap();
        assert!(
            (psnr - i.body.psnr).abs() < 1e-9
                && (ssim - i.body.ssim).abs() < 1e-9
                && (ssim_3dgs - i.body.ssim_3dgs).abs() < 1e-9,
            "{name}"
        );
        let (a, b) = (read("_lpips"), read("_lpips_gt"));
        let d = lpips
            .forward(
                f3g_nets::metrics::image_tensor(&a, &device),
                f3g_nets::metrics::image_tensor(&b, &device),
            )
            .unwrap()
            .into_data()
            .try_into_vec::<f32>()
            .unwrap()[0] as f64;
        assert!((d - i.body.lpips.unwrap()).abs() < 1e-6, "{name}");
        assert_eq!(
            f3g_avatar::infer::eval::blotched(&render, &gt),
            i.body.blotched,
            "{name}"
        );
        let head = i.head.as_ref().expect("the head is in view");
        let (hr, hg) = (read("_head"), read("_head_gt"));
        assert!((f3g_nets::metrics::psnr(&hr, &hg).unwrap() - head.psnr).abs() < 1e-9);
    }
    let mean = report.images.iter().map(|i| i.body.psnr).sum::<f64>() / report.images.len() as f64;
    assert!((mean - report.mean_body.psnr).abs() < 1e-9);
    let md = std::fs::read_to_string(run.join("eval/novel-view/metrics.md")).unwrap();
    assert!(md.contains("body PSNR") && md.contains("head LPIPS"));
    // Per view class: each class's mean is that of its images' heads, and the classes share
    // out every head. The first frame stands still facing camera 0: cam00 sees it from the
    // front, cam07 from the back.
    let mut counted = 0;
    for (class, v) in &report.head_by_view {
        let heads: Vec<f64> = report
            .images
            .iter()
            .filter(|i| i.view == *class)
            .filter_map(|i| i.head.as_ref().map(|h| h.psnr))
            .collect();
        assert_eq!(heads.len(), v.images, "{class:?}");
        let mean = heads.iter().sum::<f64>() / heads.len() as f64;
        assert!((mean - v.head.psnr).abs() < 1e-9, "{class:?}");
        counted += v.images;
    }
    assert_eq!(
        counted,
        report.images.iter().filter(|i| i.head.is_some()).count()
    );
    let first = |camera: &str| {
        report
            .images
            .iter()
            .find(|i| i.camera == camera && i.frame == 0)
            .unwrap_or_else(|| panic!("{camera} at frame 0 evaluated"))
            .view
    };
    assert_eq!(first("cam00"), f3g_data::crop::ViewClass::Front);
    assert_eq!(first("cam07"), f3g_data::crop::ViewClass::Back);
}

/// Mean body and head PSNR of `run` on the novel views of its capture, and the best flat
/// baseline's body PSNR on the same ground truths: per image, the better of an all-white image
/// (the background alone) and the image's mean colour everywhere.
fn novel_view_psnr(run: &Path) -> (f64, f64, f64) {
    let options = EvalOptions {
        split: SplitKind::NovelView,
        cameras: None,
        frames: None,
        every: 1,
        scale: 0.5,
        face_size: 32,
        lpips_size: 32,
        lpips_net: LpipsNet::Alex,
        out: None,
        overwrite: false,
    };
    let report = evaluate(run, None, None, &options, &Device::flex(), &mut |_, _| {}).unwrap();
    let images = run.join("eval/novel-view/images");
    let mut flat = 0.0;
    for i in &report.images {
        let gt =
            f3g_io::read_rgb(&images.join(format!("{}_{:08}_gt.png", i.camera, i.frame))).unwrap();
        let pixels = (gt.width * gt.height) as f32;
        let mut mean = [0.0f32; 3];
        for p in gt.data.chunks_exact(3) {
            (0..3).for_each(|c| mean[c] += p[c] / pixels);
        }
        let filled = |colour: [f32; 3]| {
            let mut img = gt.clone();
            img.data
                .chunks_exact_mut(3)
                .for_each(|p| p.copy_from_slice(&colour));
            f3g_nets::metrics::psnr(&img, &gt).unwrap()
        };
        flat += filled(mean).max(filled([1.0; 3]));
    }
    let head = report.mean_head.expect("heads in view").psnr;
    (
        report.mean_body.psnr,
        head,
        flat / report.images.len() as f64,
    )
}

#[test]
fn training_beats_the_untrained_avatar_and_a_flat_colour_baseline_on_held_out_views() {
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("cap");
    capture(&cap);
    let train = |name: &str, steps: [u64; 5]| {
        let run = dir.path().join(name);
        train_to_end(&run, &cap, tiny_body(steps));
        novel_view_psnr(&run)
    };
    let (untrained_body, untrained_head, flat) = train("untrained", [1, 0, 0, 0, 0]);
    let (body, head, _) = train("trained", [20, 140, 0, 0, 0]);
    eprintln!(
        "novel views: trained body {body:.2} / head {head:.2} dB, untrained {untrained_body:.2} / \
         {untrained_head:.2} dB, best flat image {flat:.2} dB"
    );
    assert!(body > untrained_body + 4.0, "{body} vs {untrained_body}");
    assert!(head > untrained_head + 4.0, "{head} vs {untrained_head}");
    assert!(body > flat + 4.0, "{body} vs the flat baseline {flat}");
}

#[test]
fn identical_runs_write_identical_checkpoint_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("cap");
    capture(&cap);
    let checkpoint = |name: &str| {
        let run = dir.path().join(name);
        train_to_end(&run, &cap, tiny([2, 2, 1, 2, 1]));
        let latest = std::fs::read_to_string(run.join("checkpoints/latest")).unwrap();
        run.join("checkpoints").join(latest.trim())
    };
    let a = checkpoint("a");
    // Cross a 2-second step of zip timestamps, so bytes that depend on the time show.
    std::thread::sleep(std::time::Duration::from_millis(2100));
    let b = checkpoint("b");
    let mut names: Vec<String> = std::fs::read_dir(&a)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    // Networks, optimiser states (body, face, discriminator), discriminator, face model.
    assert_eq!(
        names.iter().filter(|n| n.ends_with(".bpk")).count(),
        5,
        "{names:?}"
    );
    for name in &names {
        let (x, y) = (
            std::fs::read(a.join(name)).unwrap(),
            std::fs::read(b.join(name)).unwrap(),
        );
        if name == "state.json" {
            // The one documented difference: the wall-clock seconds the run took.
            let strip = |bytes: &[u8]| {
                let mut v: serde_json::Value = serde_json::from_slice(bytes).unwrap();
                v.as_object_mut().unwrap().remove("seconds");
                v
            };
            assert_eq!(strip(&x), strip(&y));
        } else {
            assert!(x == y, "{name} differs between two identical runs");
        }
    }
}

/// Replaces every float parameter by NaN, as a diverged optimiser would leave them.
/// Scales every weight by 1e30: finite (so the checkpoint loads; NaN weights are refused when
/// loading), but the forward pass overflows.
struct Poison;
impl burn::module::ModuleMapper for Poison {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        param.map(|t| t * 1e30)
    }
}

#[test]
fn a_diverged_run_stops_at_the_first_non_finite_loss_and_keeps_its_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("cap");
    capture(&cap);
    let run = dir.path().join("run");
    let config = tiny([4, 2, 0, 0, 0]);
    let mut t = create(&run, &cap, config.clone()).unwrap();
    t.train(&AtomicBool::new(true), &mut |_| {}).unwrap();
    assert_eq!(t.step(), 1);
    drop(t);
    // Poison the networks of the checkpoint and resume: step 1 meets a NaN loss.
    let ckpt = run.join("checkpoints/step-000000001");
    let nets = TrainedAvatar::load(&run, &Device::flex()).unwrap().nets;
    f3g_nets::checkpoint::save(nets.map(&mut Poison), &ckpt.join("nets.bpk")).unwrap();
    let log_before = std::fs::read_to_string(run.join("log.jsonl")).unwrap();
    let mut t = Trainer::resume(&run, None, &[Device::flex()]).unwrap();
    let e = t.train(&AtomicBool::new(false), &mut |_| {}).unwrap_err();
    let text = e.to_string();
    assert!(
        matches!(e, f3g_avatar::AvatarError::NonFinite { step: 1, .. }),
        "{text}"
    );
    assert!(
        text.contains("pretrain") && text.contains("step-000000001"),
        "{text}"
    );
    // Nothing was written over: the checkpoint and the log are as they were.
    assert_eq!(
        std::fs::read_to_string(run.join("log.jsonl")).unwrap(),
        log_before
    );
    assert!(ckpt.join("state.json").exists());
    assert_eq!(
        std::fs::read_to_string(run.join("checkpoints/latest")).unwrap(),
        "step-000000001"
    );
}

#[test]
fn bad_runs_fail_clearly_and_keep_what_was_written() {
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("cap");
    capture(&cap);
    let run = dir.path().join("run");
    train_to_end(&run, &cap, tiny([1, 1, 0, 0, 0]));
    // A second run into the same folder is refused.
    let e = create(&run, &cap, tiny([1, 1, 0, 0, 0]))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("already holds a run"), "{e}");
    // So is a folder holding someone else's files, which stay as they were.
    let theirs = dir.path().join("theirs");
    std::fs::create_dir(&theirs).unwrap();
    std::fs::write(theirs.join("log.jsonl"), "mine\n").unwrap();
    let e = create(&theirs, &cap, tiny([1, 1, 0, 0, 0]))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("holds files and no run"), "{e}");
    assert_eq!(std::fs::read_dir(&theirs).unwrap().count(), 1);
    assert_eq!(
        std::fs::read_to_string(theirs.join("log.jsonl")).unwrap(),
        "mine\n"
    );
    // A corrupted checkpoint names the file; the files stay as they were.
    let ckpt = run.join("checkpoints").join(
        std::fs::read_to_string(run.join("checkpoints/latest"))
            .unwrap()
            .trim(),
    );
    let nets = ckpt.join("nets.bpk");
    std::fs::write(&nets, b"not a checkpoint").unwrap();
    let e = Trainer::resume(&run, None, &[Device::flex()])
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("nets.bpk"), "{e}");
    assert!(ckpt.join("optim_body.bpk").exists() && run.join("log.jsonl").exists());
    // A capture whose body model is not the run's.
    let info = run.join("run.json");
    let text = std::fs::read_to_string(&info)
        .unwrap()
        .replace("\"model\": \"builtin\"", "\"model\": \"smplx:other.npz\"");
    std::fs::write(&info, text).unwrap();
    let e = Trainer::resume(&run, None, &[Device::flex()])
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("body model") && e.contains("smplx:other.npz"),
        "{e}"
    );
    // A config with an unknown key or a bad value.
    let cfg = dir.path().join("bad.json");
    std::fs::write(&cfg, r#"{"losses": {"l1": -1}}"#).unwrap();
    let e = TrainConfig::from_file(&cfg).unwrap_err().to_string();
    assert!(e.contains("losses.l1"), "{e}");
    let load_error = |path: &std::path::Path| {
        TrainedAvatar::load(path, &Device::flex())
            .err()
            .unwrap()
            .to_string()
    };
    // Not a run at all.
    let e = load_error(&cap);
    assert!(e.contains("not a training run"), "{e}");
    // Nothing there (a mistyped avatar file or run folder).
    let e = load_error(&dir.path().join("avatar.glb"));
    assert!(
        e.contains("avatar.glb") && e.contains("no such file or folder"),
        "{e}"
    );
}

/// Renders a `.ply`-style cloud with the reference CPU renderer (what `f3g render-ply` does).
fn render_cloud(cloud: &f3g_splat::GaussianCloud, camera: &f3g_splat::Camera) -> f3g_io::Image {
    let out = f3g_splat::cpu::render(
        &cloud.slices(),
        camera,
        [1.0f32; 3],
        &f3g_splat::RenderOptions::default(),
    )
    .unwrap();
    f3g_io::Image::from_vec(camera.width as usize, camera.height as usize, 3, out.color).unwrap()
}

#[test]
fn exported_ply_keeps_the_view_dependent_colour_in_either_up_convention() {
    use f3g_avatar::infer::export::{ExportOptions, Up, export_cloud};
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("cap");
    capture(&cap);
    let run = dir.path().join("run");
    train_to_end(&run, &cap, tiny_body([5, 30, 0, 0, 0]));
    let avatar = TrainedAvatar::load(&run, &Device::flex()).unwrap();
    let ds = f3g_data::Dataset::open(&cap, None).unwrap();
    let params = &ds.params[1];
    let export = |degree: usize, up: Up| {
        let options = ExportOptions {
            degree,
            directions: 24,
            up,
            lit: true,
        };
        export_cloud(&avatar, params, false, &options).unwrap()
    };
    let (sh3, fit3) = export(3, Up::Y);
    let (_, fit0) = export(0, Up::Y);
    assert_eq!((sh3.sh_degree, sh3.len()), (3, avatar.gaussian_count()));
    // The colour network does depend on the view: degree 3 follows it better than one colour.
    assert!(fit3.rms < fit0.rms, "{fit3:?} vs {fit0:?}");
    // What a 3DGS viewer shows from a camera behind and to the side (the test captures hold
    // out cameras 0, 7 and 13) is what the avatar renders itself.
    let camera = &ds.cameras[7].camera;
    let own = avatar.render(params, camera, [1.0; 3], false).unwrap();
    let viewer = render_cloud(&sh3, camera);
    let psnr = f3g_nets::metrics::psnr(&viewer, &own).unwrap();
    eprintln!(
        "SH fit RMS: degree 3 {:.4}, degree 0 {:.4}; .ply vs avatar {psnr:.1} dB",
        fit3.rms, fit0.rms
    );
    assert!(psnr > 35.0, "{psnr} dB between the .ply and the avatar");
    // −Y up: the same picture from the camera turned with the scene (x' = R x, R = Rx(π)).
    let (flipped, _) = export(3, Up::NegY);
    for (a, b) in flipped.means.chunks_exact(3).zip(sh3.means.chunks_exact(3)) {
        assert!(
            (a[0] - b[0]).abs() < 1e-5 && (a[1] + b[1]).abs() < 1e-5 && (a[2] + b[2]).abs() < 1e-5
        );
    }
    let mut turned = camera.clone();
    for row in turned.r.iter_mut() {
        row[1] = -row[1];
        row[2] = -row[2];
    }
    let same = f3g_nets::metrics::psnr(&render_cloud(&flipped, &turned), &viewer).unwrap();
    assert!(same > 50.0, "{same} dB");
}

#[test]
fn a_run_bakes_into_an_avatar_file_that_reads_back_and_renders_like_its_networks() {
    use f3g_avatar::infer::avatar_file;
    use f3g_avatar::infer::bake::{BakeOptions, BakedAvatar};
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("cap");
    capture(&cap);
    let run = dir.path().join("run");
    let mut config = tiny([10, 10, 2, 6, 2]);
    config.model.world_shading = true;
    train_to_end(&run, &cap, config);
    let mut avatar = f3g_avatar::infer::TrainedAvatar::load(&run, &Device::flex()).unwrap();
    // A strong light from above and the front (ten steps barely move the neutral one), so
    // that the baked avatar matches its networks below only if it shades as they do.
    let frame = avatar.training_poses().unwrap().last().unwrap().clone();
    let camera =
        f3g_splat::Camera::look_at([0.4, 0.2, 3.0], [0.0; 3], [0.0, 1.0, 0.0], 90.0, 64, 96);
    let unlit = avatar.render(&frame, &camera, [1.0; 3], false).unwrap();
    // `s = 1 + 1.71·y + 1.03·z` for a normal (x, y, z): the neutral light's constant term and
    // coefficients −3.5 on `Y_1 = −C1·y`, 2.1 on `Y_2 = C1·z`, as parameters (the change from
    // the neutral light over the shading's step).
    use f3g_avatar::model::shading::SHADING_STEP;
    let mut light = vec![0.0f32; 27];
    light[3..6].fill(-3.5 / SHADING_STEP);
    light[6..9].fill(2.1 / SHADING_STEP);
    let light = Tensor::<2>::from_data(
        burn::tensor::TensorData::new(light, [9, 3]),
        &Device::flex(),
    );
    avatar.nets.body.shading = Some(Param::from_tensor(light));
    let lit = avatar.render(&frame, &camera, [1.0; 3], false).unwrap();
    let psnr = f3g_nets::metrics::psnr(&unlit, &lit).unwrap();
    println!("the light changes the render: {psnr:.1} dB");
    assert!(psnr < 20.0, "the light changes the render: {psnr} dB");
    // The run keeps its training poses.
    let poses = avatar.training_poses().unwrap();
    assert_eq!(poses.len(), avatar.info.train_frames.len());
    // Degree 3 (not the default 0), so that the file's SH layout is read back too.
    let options = BakeOptions {
        correctives: 3,
        sh_degree: 3,
        directions: 16,
        poses: 4,
        perturbations: 1,
        ..BakeOptions::default()
    };
    let (baked, report) = BakedAvatar::bake(&avatar, &poses, &options).unwrap();
    assert_eq!(baked.len(), avatar.gaussian_count());
    assert_eq!((report.samples, baked.corrective_count()), (8, 3));
    assert!(report.explained_variance > 0.0 && report.explained_variance <= 1.0 + 1e-9);

    // The file reads back as the same avatar.
    let path = dir.path().join("avatar.glb");
    avatar_file::write(&baked, &path, avatar_file::Encoding::Float).unwrap();
    let back = avatar_file::read(&path).unwrap();
    let frame = &poses[poses.len() - 1];
    let (a, b) = (baked.posed(frame).unwrap(), back.posed(frame).unwrap());
    let worst = |x: &[f32], y: &[f32]| {
        x.iter()
            .zip(y)
            .map(|(p, q)| (p - q).abs())
            .fold(0.0f32, f32::max)
    };
    assert!(worst(&a.means, &b.means) < 1e-5);
    assert!(worst(&a.sh, &b.sh) < 1e-5);
    assert!(worst(&a.log_scales, &b.log_scales) < 1e-4);
    assert!(worst(&a.opacity_logits, &b.opacity_logits) < 1e-3);
    assert_eq!(back.expression_names, baked.expression_names);

    // glTF's skinning gives f3g's: the nodes' world transforms times the inverse bind
    // matrices are the identity in the canonical pose the nodes hold.
    let file = f3g_rig::glb::GlbFile::parse(&std::fs::read(&path).unwrap()).unwrap();
    let nodes = file.document["nodes"].as_array().unwrap();
    let joints = baked.rig.skeleton.joints();
    let mut world: Vec<glam::Mat4> = Vec::new();
    for (j, joint) in joints.iter().enumerate() {
        let n = &nodes[j];
        let f = |k: &str| -> Vec<f32> {
            n[k].as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap() as f32)
                .collect()
        };
        let (t, r, s) = (f("translation"), f("rotation"), f("scale"));
        let local = glam::Mat4::from_scale_rotation_translation(
            glam::Vec3::from_slice(&s),
            glam::Quat::from_slice(&r),
            glam::Vec3::from_slice(&t),
        );
        world.push(joint.parent.map_or(local, |p| world[p] * local));
    }
    let ibm_index = file.document["skins"][0]["inverseBindMatrices"]
        .as_u64()
        .unwrap() as usize;
    let ibm = file.floats(ibm_index, 16).unwrap();
    let deviation = world
        .iter()
        .zip(ibm.chunks_exact(16))
        .map(|(w, m)| {
            (*w * glam::Mat4::from_cols_slice(m))
                .to_cols_array()
                .iter()
                .zip(glam::Mat4::IDENTITY.to_cols_array())
                .map(|(x, y)| (x - y).abs())
                .fold(0.0f32, f32::max)
        })
        .fold(0.0f32, f32::max);
    assert!(deviation < 1e-4, "{deviation}");

    assert_eq!(back.shading, baked.shading);
    assert!(baked.shading.is_some());

    // At a training pose the baked avatar looks like its networks.
    let networks = avatar.render(frame, &camera, [1.0; 3], false).unwrap();
    let rendered = back.render(frame, &camera, [1.0; 3]).unwrap();
    let psnr = f3g_nets::metrics::psnr(&networks, &rendered).unwrap();
    println!("baked vs networks: {psnr:.1} dB");
    assert!(psnr > 25.0, "baked vs networks: {psnr} dB");

    // The compressed file is smaller and renders like the float one (its quantisation only),
    // its expressions and light intact.
    let small = dir.path().join("avatar-compressed.glb");
    let size = avatar_file::write(&baked, &small, avatar_file::Encoding::Compressed).unwrap();
    assert!(
        size * 3 < std::fs::metadata(&path).unwrap().len(),
        "{size} bytes"
    );
    let unpacked = avatar_file::read(&small).unwrap();
    assert_eq!(unpacked.expression_names, baked.expression_names);
    assert_eq!(
        unpacked.shading.as_ref().unwrap().coefficients,
        baked.shading.as_ref().unwrap().coefficients
    );
    let compressed = unpacked.render(frame, &camera, [1.0; 3]).unwrap();
    let psnr = f3g_nets::metrics::psnr(&rendered, &compressed).unwrap();
    println!("compressed against float: {psnr:.1} dB, {size} bytes");
    assert!(psnr > 35.0, "compressed vs float: {psnr} dB");

    // Bad files are errors naming them.
    let bytes = std::fs::read(&path).unwrap();
    let truncated = dir.path().join("truncated.glb");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let e = avatar_file::read(&truncated).unwrap_err().to_string();
    assert!(
        e.contains("truncated.glb") && e.contains("truncated"),
        "{e}"
    );
    let foreign = dir.path().join("rig.glb");
    f3g_rig::gltf::write(&baked.rig, &foreign).unwrap();
    let e = avatar_file::read(&foreign).unwrap_err().to_string();
    assert!(
        e.contains("rig.glb") && e.contains("not an f3g avatar"),
        "{e}"
    );
    // A corrective count that disagrees with the morph targets.
    let mut glb = f3g_rig::glb::GlbFile::parse(&bytes).unwrap();
    glb.document["meshes"][0]["primitives"][0]["extensions"]["F3G_pose_correctives"]["count"] =
        serde_json::json!(5);
    let edited = dir.path().join("edited.glb");
    std::fs::write(&edited, glb.to_bytes()).unwrap();
    let e = avatar_file::read(&edited).unwrap_err().to_string();
    assert!(
        e.contains("edited.glb") && e.contains("morph targets"),
        "{e}"
    );
}
