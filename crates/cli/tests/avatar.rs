//! `f3g train`, `train --resume`, `eval`, `animate` and `export-ply` end to end on a tiny
//! synthetic capture with a tiny configuration file.

mod common;

use common::{f3g_in as f3g, ok, tiny_capture, worst_difference};

#[test]
fn train_resume_evaluate_animate_and_export() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    tiny_capture(d, [2, 2, 1, 2, 1]);
    let out = f3g(
        d,
        &[
            "train",
            "--data",
            "cap",
            "--out",
            "run",
            "--config",
            "tiny.json",
            "--max-steps",
            "3",
        ],
    );
    ok(&out);
    assert!(String::from_utf8_lossy(&out.stdout).contains("stopped at step 3"));
    // Training into the same folder again is refused; resuming finishes the run.
    let again = f3g(
        d,
        &[
            "train",
            "--data",
            "cap",
            "--out",
            "run",
            "--config",
            "tiny.json",
        ],
    );
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("already holds a run"));
    let out = f3g(d, &["train", "--resume", "run"]);
    ok(&out);
    assert!(String::from_utf8_lossy(&out.stdout).contains("finished 8 steps"));
    assert_eq!(
        std::fs::read_to_string(d.join("run/log.jsonl"))
            .unwrap()
            .lines()
            .count(),
        8
    );

    let evaluated = f3g(d, &["eval", "run", "--every", "2", "--lpips", "alex"]);
    ok(&evaluated);
    // The summary gives the head per view class; the held-out frontal camera sees it.
    assert!(String::from_utf8_lossy(&evaluated.stdout).contains("head seen from the front"));
    let metrics: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(d.join("run/eval/novel-view/metrics.json")).unwrap(),
    )
    .unwrap();
    // Eight steps learn little: that training learns is checked in the avatar crate's
    // `training_beats_the_untrained_avatar_and_a_flat_colour_baseline_on_held_out_views`.
    assert!(metrics["mean_body"]["psnr"].as_f64().unwrap().is_finite());
    // The head's SSIM is the mean over the images with the head in view, each the SSIM of the
    // saved head render against its saved ground truth.
    let heads: Vec<(String, f64)> = metrics["images"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|image| !image["head"].is_null())
        .map(|image| {
            let name = format!(
                "{}_{:08}_head",
                image["camera"].as_str().unwrap(),
                image["frame"].as_u64().unwrap()
            );
            (name, image["head"]["ssim"].as_f64().unwrap())
        })
        .collect();
    assert!(!heads.is_empty(), "no head in view: {metrics}");
    let mean = heads.iter().map(|(_, ssim)| ssim).sum::<f64>() / heads.len() as f64;
    let reported = metrics["mean_head"]["ssim"].as_f64().unwrap();
    assert!((reported - mean).abs() < 1e-12, "{reported} ≠ {mean}");
    let images = d.join("run/eval/novel-view/images");
    for (name, ssim) in &heads {
        let png = |suffix: &str| f3g_io::read_rgb(&images.join(format!("{name}{suffix}.png")));
        let recomputed =
            f3g_nets::metrics::ssim_skimage(&png("").unwrap(), &png("_gt").unwrap()).unwrap();
        assert!(
            (recomputed - ssim).abs() < 1e-6,
            "{name}: {recomputed} ≠ {ssim}"
        );
    }
    ok(&f3g(d, &["eval", "run", "--split", "novel-pose"]));

    // A run that trained on a camera its split now holds out is refused, unless the cameras
    // are chosen by hand.
    let info_path = d.join("run/run.json");
    let info = std::fs::read_to_string(&info_path).unwrap();
    let mut older: serde_json::Value = serde_json::from_str(&info).unwrap();
    older["train_cameras"]
        .as_array_mut()
        .unwrap()
        .push(0.into());
    std::fs::write(&info_path, older.to_string()).unwrap();
    let refused = f3g(d, &["eval", "run", "--split", "novel-pose"]);
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("trained on"));
    ok(&f3g(
        d,
        &[
            "eval",
            "run",
            "--split",
            "novel-pose",
            "--cameras",
            "7,13",
            "--out",
            "e713",
        ],
    ));
    std::fs::write(&info_path, info).unwrap();

    ok(&f3g(
        d,
        &[
            "animate",
            "run",
            "--motion",
            "cap/body_params.npz",
            "--out",
            "anim",
            "--export-ply",
            "--export-spz",
            "--size",
            "48x64",
        ],
    ));
    assert!(d.join("anim/animation.gif").exists());
    let frame = f3g_io::read_rgb(&d.join("anim/frames/frame_00004.png")).unwrap();
    assert_eq!((frame.width, frame.height), (48, 64));
    // The video decodes to the frames, in order, at the motion's rate.
    let (video, fps) =
        f3g_avatar::infer::video::read_mp4(&std::fs::read(d.join("anim/animation.mp4")).unwrap())
            .unwrap();
    let frames = std::fs::read_dir(d.join("anim/frames")).unwrap().count();
    assert_eq!(video.len(), frames);
    assert!(fps > 0.0, "{fps}");
    let psnr = f3g_nets::metrics::psnr(&frame, &video[4]).unwrap();
    let other = f3g_nets::metrics::psnr(&frame, &video[0]).unwrap();
    assert!(
        psnr > 30.0 && psnr > other,
        "frame 4 decoded at {psnr:.1} dB (frame 0: {other:.1})"
    );
    // The bottom corners see the floor (a grey of its chequer), or the white background
    // without it.
    let corner = |img: &f3g_io::Image| img.data[3 * (63 * 48)];
    assert!(corner(&frame) < 0.95, "no floor: {}", corner(&frame));
    let cloud = f3g_splat::ply::read_ply(&d.join("anim/ply/frame_00004.ply")).unwrap();
    let spz = f3g_splat::spz::decode(&std::fs::read(d.join("anim/spz/frame_00004.spz")).unwrap())
        .unwrap();
    assert_eq!(spz.len(), cloud.len());

    // The run folder works from anywhere: moved, it animates and exports as before. Into the
    // same folder, an animation removes what the earlier one wrote and this one does not (the
    // `.ply` files, and their emptied folder), and nothing of the user's, even when named like
    // a frame.
    std::fs::create_dir(d.join("moved")).unwrap();
    std::fs::rename(d.join("run"), d.join("moved/run")).unwrap();
    for mine in [
        "frames/frame_00099.png",
        "frames/frame_abc.txt",
        "notes.txt",
    ] {
        std::fs::write(d.join("anim").join(mine), b"mine").unwrap();
    }
    let animate_moved = |out: &str, extra: &[&str]| {
        let mut args = vec![
            "animate",
            "moved/run",
            "--motion",
            "cap/body_params.npz",
            "--out",
            out,
            "--size",
            "48x64",
        ];
        args.extend_from_slice(extra);
        f3g(d, &args)
    };
    ok(&animate_moved("bare", &["--no-floor"]));
    let bare = f3g_io::read_rgb(&d.join("bare/frames/frame_00004.png")).unwrap();
    assert_eq!(corner(&bare), 1.0);
    ok(&animate_moved("anim", &[]));
    assert!(!d.join("anim/ply").exists());
    assert!(d.join("anim/frames/frame_00004.png").exists());
    for mine in [
        "frames/frame_00099.png",
        "frames/frame_abc.txt",
        "notes.txt",
    ] {
        assert_eq!(std::fs::read(d.join("anim").join(mine)).unwrap(), b"mine");
    }
    // A folder of someone else's is refused, and written into only with --overwrite.
    std::fs::create_dir(d.join("mine")).unwrap();
    std::fs::write(d.join("mine/animation.gif"), b"mine").unwrap();
    let refused = animate_moved("mine", &[]);
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("--overwrite"));
    assert_eq!(
        std::fs::read(d.join("mine/animation.gif")).unwrap(),
        b"mine"
    );
    ok(&animate_moved("mine", &["--overwrite"]));
    assert!(d.join("mine/frames/frame_00004.png").exists());
    // A link inside the folder is not followed: the frames folder pointing elsewhere.
    #[cfg(unix)]
    {
        std::fs::create_dir(d.join("elsewhere")).unwrap();
        std::fs::write(d.join("elsewhere/frame_00000.png"), b"precious").unwrap();
        std::fs::remove_dir_all(d.join("mine/frames")).unwrap();
        std::os::unix::fs::symlink(d.join("elsewhere"), d.join("mine/frames")).unwrap();
        let refused = animate_moved("mine", &[]);
        assert!(String::from_utf8_lossy(&refused.stderr).contains("symbolic link"));
        assert_eq!(
            std::fs::read(d.join("elsewhere/frame_00000.png")).unwrap(),
            b"precious"
        );
    }
    std::fs::rename(d.join("moved/run"), d.join("run")).unwrap();

    // Its training poses go out as BVH, and a BVH motion drives it (retargeted by name).
    ok(&f3g(d, &["motion", "export", "run", "--out", "train.bvh"]));
    let out = f3g(
        d,
        &[
            "animate",
            "run",
            "--motion",
            "train.bvh",
            "--out",
            "bvh",
            "--size",
            "48x64",
            "--fps",
            "30",
        ],
    );
    ok(&out);
    assert!(String::from_utf8_lossy(&out.stderr).contains("retargeted by rotations"));
    assert!(d.join("bvh/frames/frame_00000.png").exists());

    // A capture folder is not overwritten by accident.
    let again = f3g(
        d,
        &[
            "synth",
            "--out",
            "cap",
            "--frames",
            "2",
            "--resolution",
            "64",
        ],
    );
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("--overwrite"));

    ok(&f3g(
        d,
        &["export-ply", "run", "--out", "one.ply", "--frame", "4"],
    ));
    let one = f3g_splat::ply::read_ply(&d.join("one.ply")).unwrap();
    assert_eq!(one.len(), cloud.len());
    // Every file has the degree-3 layout the reference 3DGS loader and SIBR expect.
    assert_eq!((one.sh_degree, cloud.sh_degree), (3, 3));
    // The same frame as SPZ: the same Gaussians within SPZ's quantisation (a quarter
    // millimetre), in a smaller file.
    ok(&f3g(
        d,
        &["export-ply", "run", "--out", "one.spz", "--frame", "4"],
    ));
    let spz_bytes = std::fs::read(d.join("one.spz")).unwrap();
    let spz = f3g_splat::spz::decode(&spz_bytes).unwrap();
    assert_eq!(spz.len(), one.len());
    let worst = worst_difference(&one.means, &spz.means);
    assert!(worst <= 1.3e-4, "{worst}");
    assert!(spz_bytes.len() * 5 < std::fs::metadata(d.join("one.ply")).unwrap().len() as usize);
    let out = f3g(
        d,
        &[
            "export-ply",
            "run",
            "--out",
            "down.ply",
            "--frame",
            "4",
            "--sh-degree",
            "1",
            "--up",
            "-y",
        ],
    );
    ok(&out);
    assert!(String::from_utf8_lossy(&out.stdout).contains("SH degree 1 fitted"));
    let down = f3g_splat::ply::read_ply(&d.join("down.ply")).unwrap();
    let mean_y = |c: &f3g_splat::GaussianCloud| {
        c.means.chunks_exact(3).map(|m| m[1] as f64).sum::<f64>() / c.len() as f64
    };
    let (y_down, y_up) = (mean_y(&down), mean_y(&one));
    assert!(
        (y_down + y_up).abs() < 1e-3 && y_up.abs() > 0.1,
        "{y_down} {y_up}"
    );
    let bad = f3g(
        d,
        &["export-ply", "run", "--out", "x.ply", "--sh-degree", "4"],
    );
    assert!(!bad.status.success() && !d.join("x.ply").exists());
    assert!(one.means.iter().all(|v| v.is_finite()));

    // `view --static` does not replace a user's page without --overwrite, and with it keeps
    // what it does not write.
    std::fs::create_dir(d.join("site")).unwrap();
    std::fs::write(d.join("site/index.html"), b"mine").unwrap();
    std::fs::write(d.join("site/notes.txt"), b"mine").unwrap();
    let view = |extra: &[&str]| {
        let mut args = vec!["view", "run", "--static", "site", "--correctives", "0"];
        args.extend_from_slice(extra);
        f3g(d, &args)
    };
    let refused = view(&[]);
    assert!(String::from_utf8_lossy(&refused.stderr).contains("--overwrite"));
    assert_eq!(std::fs::read(d.join("site/index.html")).unwrap(), b"mine");
    ok(&view(&["--overwrite"]));
    assert_ne!(std::fs::read(d.join("site/index.html")).unwrap(), b"mine");
    assert_eq!(std::fs::read(d.join("site/notes.txt")).unwrap(), b"mine");
    // The folder is now the player's: written again without the flag.
    ok(&view(&[]));

    // Clear errors.
    let e = f3g(d, &["eval", "cap"]);
    assert!(!e.status.success());
    assert!(String::from_utf8_lossy(&e.stderr).contains("not a training run"));
    let e = f3g(
        d,
        &["animate", "run", "--motion", "tiny.json", "--out", "x"],
    );
    assert!(!e.status.success());
    assert!(String::from_utf8_lossy(&e.stderr).contains("tiny.json"));
    let e = f3g(
        d,
        &[
            "train",
            "--data",
            "cap",
            "--out",
            "r2",
            "--set",
            "steps.joint=-3",
        ],
    );
    assert!(!e.status.success());
    assert!(String::from_utf8_lossy(&e.stderr).contains("--set"));
}

#[test]
fn data_parallel_training_and_the_training_step_bench() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    tiny_capture(d, [1, 1, 0, 0, 0]);
    let train = |devices: &str, out: &str| {
        f3g(
            d,
            &[
                "train",
                "--data",
                "cap",
                "--out",
                out,
                "--config",
                "tiny.json",
                "--devices",
                devices,
            ],
        )
    };
    ok(&train("cpu,cpu", "dp"));
    let state: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(d.join("dp/checkpoints/step-000000002/state.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(state["replicas"], 2, "{state}");
    assert_eq!(state["device"].as_str().unwrap().split(',').count(), 2);
    let e = train("cpu,gpu", "x");
    assert!(!e.status.success());
    assert!(String::from_utf8_lossy(&e.stderr).contains("unknown device `gpu`"));

    // The step bench: every phase timed (the discriminator's too: the paper's adversarial
    // loss, which the `cpu` preset leaves out), the phases add up to the step.
    ok(&f3g(
        d,
        &[
            "bench",
            "train",
            "--data",
            "cap",
            "--steps",
            "1",
            "--warmup",
            "1",
            "--set",
            "adversarial=true",
            "--json",
            "bench.json",
        ],
    ));
    let bench: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("bench.json")).unwrap()).unwrap();
    let phases = bench["phases"]["phases"].as_array().unwrap();
    let ms = |name: &str| {
        phases.iter().find(|p| p[0] == name).unwrap()[1]
            .as_f64()
            .unwrap()
    };
    assert_eq!(phases.len(), 10);
    for phase in ["networks", "render", "lpips", "backward", "discriminator"] {
        assert!(ms(phase) > 0.0, "{phase}: {bench}");
    }
    let sum: f64 = phases.iter().map(|p| p[1].as_f64().unwrap()).sum();
    let step = bench["step_ms"].as_f64().unwrap();
    assert!(sum <= step * 1.001 && sum > 0.9 * step, "{sum} vs {step}");
    // The CPU launches no CubeCL kernels (counted on GPUs: tests/gpu.rs).
    assert!(bench["warmup_kernels"].is_null(), "{bench}");
    // Without the phases' synchronisations: whole steps, no phases. F3G_PHASE_TRACE gets each
    // step's start and each phase's end, in the order they ran (the phase profile's marks).
    let trace = d.join("phases.trace");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_f3g"))
        .args([
            "bench", "train", "--data", "cap", "--steps", "1", "--warmup", "1",
        ])
        .args([
            "--set",
            "adversarial=true",
            "--unsynced",
            "--json",
            "unsynced.json",
        ])
        .env("F3G_PHASE_TRACE", &trace)
        .current_dir(d)
        .output()
        .unwrap();
    ok(&out);
    let unsynced: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("unsynced.json")).unwrap()).unwrap();
    assert!(unsynced["phases"].is_null(), "{unsynced}");
    assert!(unsynced["step_ms"].as_f64().unwrap() > 0.0, "{unsynced}");
    let marks = std::fs::read_to_string(&trace).unwrap();
    assert!(marks.is_empty(), "an unsynced bench marks nothing: {marks}");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_f3g"))
        .args([
            "bench", "train", "--data", "cap", "--steps", "1", "--warmup", "1",
        ])
        .args(["--set", "adversarial=true"])
        .env("F3G_PHASE_TRACE", &trace)
        .current_dir(d)
        .output()
        .unwrap();
    ok(&out);
    let marks = std::fs::read_to_string(&trace).unwrap();
    let lines: Vec<&str> = marks.lines().collect();
    assert_eq!(
        lines.iter().filter(|l| **l == "P start").count(),
        2,
        "{marks}"
    );
    assert_eq!(lines[..2], ["P start", "P data"], "{marks}");
    assert_eq!(lines.last(), Some(&"P discriminator"), "{marks}");
    for phase in ["networks", "render", "lpips", "backward", "optimiser"] {
        assert!(marks.contains(&format!("P {phase}\n")), "{phase}: {marks}");
    }
    let e = f3g(
        d,
        &["bench", "train", "--data", "cap", "--set", "steps.joint=0"],
    );
    assert!(!e.status.success());
    assert!(String::from_utf8_lossy(&e.stderr).contains("no Joint steps"));
}

/// `F3G_MAX_MEMORY` caps the memory budget: each large allocation of training, evaluation and
/// export is refused before it happens, with the flag or key to change.
#[test]
fn a_memory_budget_too_small_is_an_error_naming_what_to_change() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    tiny_capture(d, [1, 0, 0, 0, 0]);
    let capped = |cap: &str, args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_f3g"))
            .args(args)
            .current_dir(d)
            .env("F3G_MAX_MEMORY", cap)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{args:?} ran under {cap}");
        String::from_utf8_lossy(&out.stderr).to_string()
    };
    let train = [
        "train",
        "--data",
        "cap",
        "--out",
        "run",
        "--config",
        "tiny.json",
    ];
    let e = capped("1000", &train);
    assert!(
        e.contains("pose PCA") && e.contains("F3G_MAX_MEMORY=1000"),
        "{e}"
    );
    std::fs::remove_dir_all(d.join("run")).unwrap();
    let e = capped("1M", &train);
    assert!(e.contains("`cache_bytes`"), "{e}");
    std::fs::remove_dir_all(d.join("run")).unwrap();
    ok(&f3g(d, &train));
    let e = capped("1M", &["eval", "run"]);
    assert!(e.contains("--scale 1"), "{e}");
    let e = capped("100K", &["export-ply", "run", "--out", "a.ply"]);
    assert!(
        e.contains("--directions") && !d.join("a.ply").exists(),
        "{e}"
    );
    let e = capped("lots", &["export-ply", "run", "--out", "a.ply"]);
    assert!(e.contains("is not a size"), "{e}");
}
