//! The `f3g` binary on a wgpu device (Mesa lavapipe in CI): `render-ply --device wgpu` gives
//! the CPU's image, `bench splat --device wgpu` measures and writes its JSON, a run trained on
//! the CPU evaluates, animates and exports on wgpu as on the CPU, a missing adapter is an error
//! that lists the ones there are, and the avatar crate's skinning, gathering,
//! quaternion-product and view kernels give the CPU's values. Run with `cargo test --release -p f3g-cli --features
//! gpu --test gpu`.
#![cfg(feature = "gpu")]

mod common;

use std::path::Path;

use burn::tensor::Tensor;
use common::{f3g_in, ok, worst_difference};
use f3g_splat::{Camera, GaussianCloud, ply};

/// A tensor's values on the host, as `f32`.
fn values(t: Tensor<2>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
}

/// A ring of 300 overlapping Gaussians with SH degree 3.
fn scene() -> GaussianCloud {
    let n = 300;
    let mut cloud = GaussianCloud {
        sh_degree: 3,
        ..Default::default()
    };
    for i in 0..n {
        let t = i as f32 / n as f32 * std::f32::consts::TAU;
        cloud
            .means
            .extend([0.5 * t.cos(), 0.4 * t.sin(), 0.1 * (3.0 * t).sin()]);
        cloud
            .log_scales
            .extend([0.06f32.ln(), 0.03f32.ln(), 0.045f32.ln()]);
        cloud.quats.extend([1.0, 0.3 * t.sin(), 0.1, 0.2 * t.cos()]);
        cloud.opacity_logits.push(0.5 + (5.0 * t).sin());
        cloud.sh.extend([1.0, -0.5 + 0.3 * t.cos(), 0.3]);
        cloud
            .sh
            .extend((0..45).map(|j| 0.1 * ((i * 7 + j) as f32).sin()));
    }
    cloud
}

/// `scene.ply` (the ring) and `cam.json` (a `width × height` view of it) in `dir`.
fn write_scene(dir: &Path, width: u32, height: u32) {
    ply::write_ply(&dir.join("scene.ply"), &scene()).unwrap();
    let camera = Camera::look_at(
        [0.3, 0.2, 2.5],
        [0.0; 3],
        [0.0, 1.0, 0.0],
        120.0,
        width,
        height,
    );
    std::fs::write(
        dir.join("cam.json"),
        serde_json::to_string(&camera).unwrap(),
    )
    .unwrap();
}

#[test]
fn render_ply_on_wgpu_gives_the_cpu_image() {
    let dir = tempfile::tempdir().unwrap();
    write_scene(dir.path(), 96, 80);
    let mut images = Vec::new();
    for device in ["cpu", "wgpu"] {
        let (png, npy) = (format!("{device}.png"), format!("{device}.npy"));
        ok(&f3g_in(
            dir.path(),
            &[
                "render-ply",
                "--ply",
                "scene.ply",
                "--camera",
                "cam.json",
                "--out",
                &png,
                "--raw",
                &npy,
                "--device",
                device,
                "--background",
                "0.1,0.2,0.3",
            ],
        ));
        let (shape, raw) = f3g_io::read_npy_f32(&dir.path().join(format!("{device}.npy"))).unwrap();
        assert_eq!(shape, vec![80, 96, 3]);
        images.push(raw);
    }
    let differs = images[0]
        .iter()
        .zip(&images[1])
        .filter(|(a, b)| (*a - *b).abs() > 1e-5 * (1.0 + a.abs()))
        .count();
    assert_eq!(differs, 0, "{differs} values differ by more than 1e-5");
    assert!(
        images[0].iter().any(|&v| v > 0.5),
        "the ring is not in view"
    );
}

#[test]
fn bench_splat_on_wgpu_writes_its_measurements() {
    let dir = tempfile::tempdir().unwrap();
    ok(&f3g_in(
        dir.path(),
        &[
            "bench",
            "splat",
            "--device",
            "wgpu",
            "--gaussians",
            "2000",
            "--resolutions",
            "64,96x48",
            "--repeats",
            "1",
            "--json",
            "b.json",
        ],
    ));
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("b.json")).unwrap()).unwrap();
    assert_eq!(doc["device"], "wgpu");
    let cases = doc["cases"].as_array().unwrap();
    assert_eq!(cases.len(), 2);
    assert_eq!(
        (cases[1]["width"].as_u64(), cases[1]["height"].as_u64()),
        (Some(96), Some(48))
    );
    for c in cases {
        assert!(c["forward_backward_ms"].as_f64().unwrap() > 0.0, "{c}");
        assert!(c["evaluations"].as_u64().unwrap() > 0, "{c}");
        assert!(c["intersections"].as_u64().unwrap() > 0, "{c}");
    }
}

#[test]
fn a_missing_adapter_is_an_error_listing_the_adapters() {
    let dir = tempfile::tempdir().unwrap();
    write_scene(dir.path(), 32, 32);
    let out = f3g_in(
        dir.path(),
        &[
            "render-ply",
            "--ply",
            "scene.ply",
            "--camera",
            "cam.json",
            "--out",
            "x.png",
            "--device",
            "wgpu:99",
        ],
    );
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("there is no wgpu:99") && stderr.contains("adapters"),
        "{stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
}

/// One test, so that lavapipe compiles the kernels of each command once: training on wgpu
/// follows the CPU run and resumes on the CPU; the CPU-trained run evaluates, animates and
/// exports on wgpu as on the CPU.
#[test]
fn a_run_trains_evaluates_animates_and_exports_on_wgpu_as_on_the_cpu() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    ok(&f3g_in(
        d,
        &[
            "synth",
            "--out",
            "cap",
            "--frames",
            "4",
            "--resolution",
            "96",
        ],
    ));
    // One step of every stage.
    std::fs::write(
        d.join("tiny.json"),
        common::tiny_config([1, 1, 1, 1, 1], ""),
    )
    .unwrap();
    let train = ["train", "--data", "cap", "--config", "tiny.json", "--out"];
    ok(&f3g_in(
        d,
        &[&train[..], &["cpu", "--device", "cpu"]].concat(),
    ));
    // Three steps on wgpu (through the face model's construction), the rest on the CPU.
    ok(&f3g_in(
        d,
        &[
            &train[..],
            &["mixed", "--device", "wgpu", "--max-steps", "3"],
        ]
        .concat(),
    ));
    let written_on = |step: &str| {
        let state = d.join("mixed/checkpoints").join(step).join("state.json");
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(state).unwrap()).unwrap();
        v["device"].as_str().unwrap().to_string()
    };
    assert!(written_on("step-000000003").contains("Cube"));
    // The step bench counts the kernels a cold step launches (each compiled then): the
    // networks' convolutions, the splat op's 13 kernels (fewer: one SH degree), LPIPS, Adam.
    ok(&f3g_in(
        d,
        &[
            "bench",
            "train",
            "--device",
            "wgpu",
            "--data",
            "cap",
            "--config",
            "tiny.json",
            "--steps",
            "1",
            "--warmup",
            "1",
            "--json",
            "bench.json",
        ],
    ));
    let bench: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("bench.json")).unwrap()).unwrap();
    let kernels = bench["warmup_kernels"].as_u64().unwrap();
    assert!((20..5000).contains(&kernels), "{bench}");
    ok(&f3g_in(
        d,
        &["train", "--resume", "mixed", "--device", "cpu"],
    ));
    assert!(written_on("step-000000005").contains("Flex"));
    let (cpu, mixed) = (
        common::losses(&d.join("cpu")),
        common::losses(&d.join("mixed")),
    );
    assert_eq!((cpu.len(), mixed.len()), (5, 5));
    // Same initialisation (seeded on the host), same samples: the same losses to float
    // rounding, step after step (LPIPS and adversarial terms included).
    for (&(step, c), &(_, m)) in cpu.iter().zip(&mixed) {
        assert!(
            (c - m).abs() <= 2e-3 * c.abs().max(1e-3),
            "step {step}: cpu {c} vs wgpu then cpu {m}"
        );
    }

    let mut metrics = Vec::new();
    for device in ["cpu", "wgpu"] {
        let out = format!("eval-{device}");
        ok(&f3g_in(
            d,
            &[
                "eval",
                "cpu",
                "--every",
                "2",
                "--out",
                &out,
                "--device",
                device,
                // Small LPIPS squares: lavapipe runs AlexNet on the CPU's threads, and at the
                // protocol's 512² and 256² this one command took 4.7 of the test's 5.7 min.
                "--lpips-size",
                "64",
                "--face-size",
                "64",
            ],
        ));
        let m: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(d.join(&out).join("metrics.json")).unwrap(),
        )
        .unwrap();
        metrics.push(m);
        ok(&f3g_in(
            d,
            &[
                "animate",
                "cpu",
                "--motion",
                "cap/body_params.npz",
                "--out",
                &format!("anim-{device}"),
                "--size",
                "48x64",
                // The devices' renders compared, not the floor's depth test where the soles
                // touch it (a pixel there may go either way on float rounding).
                "--no-floor",
                "--device",
                device,
            ],
        ));
        ok(&f3g_in(
            d,
            &[
                "export-ply",
                "cpu",
                "--out",
                &format!("{device}.ply"),
                "--frame",
                "1",
                // Each direction of the SH fit is a forward pass of the networks (97 by
                // default, 36 s on lavapipe); degree 1 needs four.
                "--sh-degree",
                "1",
                "--directions",
                "4",
                "--device",
                device,
            ],
        ));
    }
    // Metrics of the same checkpoint: the renders differ by float rounding only.
    for key in ["mean_body", "mean_head"] {
        for (metric, tolerance) in [("psnr", 0.05), ("lpips", 1e-3)] {
            let (a, b) = (
                metrics[0][key][metric].as_f64().unwrap(),
                metrics[1][key][metric].as_f64().unwrap(),
            );
            assert!(
                (a - b).abs() < tolerance,
                "{key} {metric}: cpu {a} vs wgpu {b}"
            );
        }
    }
    // Animation frames: at most a few levels of 8 bits apart.
    for frame in ["frame_00000.png", "frame_00003.png"] {
        let a = f3g_io::read_rgb(&d.join("anim-cpu/frames").join(frame)).unwrap();
        let b = f3g_io::read_rgb(&d.join("anim-wgpu/frames").join(frame)).unwrap();
        let worst = worst_difference(&a.data, &b.data);
        assert!(worst <= 3.0 / 255.0, "{frame}: differs by {worst}");
    }
    // The exported Gaussians.
    let a = ply::read_ply(&d.join("cpu.ply")).unwrap();
    let b = ply::read_ply(&d.join("wgpu.ply")).unwrap();
    assert_eq!(a.len(), b.len());
    let worst = worst_difference(&a.means, &b.means);
    assert!(worst < 1e-4, "means differ by {worst}");
    let worst = worst_difference(&a.sh, &b.sh);
    assert!(worst < 1e-3, "SH coefficients differ by {worst}");
}

/// The skinning kernel of GPU devices (`f3g_avatar::model::posing`'s `cube`) against
/// the CPU's loop: the built-in human's vertices under a pose with bent joints (two to eight
/// influences each), turned as a whole by nothing and by 170° about each axis so that each of
/// Shepperd's four pivots is taken; every output (blend, nearest rotation, quaternion) within
/// float rounding.
#[test]
fn skinning_on_the_gpu_matches_the_cpu() {
    use burn::tensor::Device;
    use f3g_avatar::model::posing::{Skinning, Taps, affine_tensor};
    use glam::{Affine3A, Quat};
    let human = f3g_rig::builtin::load().unwrap();
    let rig = &human.rig;
    let mut params = rig.zero_params();
    for (i, p) in params.pose.iter_mut().enumerate() {
        *p = 0.4 * ((i * 37 % 11) as f32 / 11.0 - 0.5);
    }
    let posed = rig.pose(&params).unwrap();
    let gpu = Device::wgpu(burn::tensor::DeviceKind::DefaultDevice);
    let half_turn = 170f32.to_radians();
    for turn in [
        Quat::IDENTITY,
        Quat::from_rotation_x(half_turn),
        Quat::from_rotation_y(half_turn),
        Quat::from_rotation_z(half_turn),
    ] {
        let joints: Vec<Affine3A> = posed
            .skinning
            .iter()
            .map(|a| Affine3A::from_quat(turn) * *a)
            .collect();
        let run = |device: &Device| {
            let skin = Taps::skin(&rig.skin, device);
            let s = Skinning::new(&affine_tensor(&joints, device), &skin);
            let n = s.translation.dims()[0];
            vec![
                values(s.linear.reshape([n, 9])),
                values(s.translation),
                values(s.quaternion),
                values(s.rotation.reshape([n, 9])),
            ]
        };
        let (got, expected) = (run(&gpu), run(&Device::flex()));
        let names = ["linear", "translation", "quaternion", "rotation"];
        for (what, (g, e)) in names.iter().zip(got.iter().zip(&expected)) {
            assert_eq!(g.len(), e.len(), "{what}");
            let worst = worst_difference(g, e);
            assert!(worst < 2e-5, "{what} under {turn:?} differs by {worst}");
        }
    }
}

/// The view maps' values on GPU devices (`f3g_avatar::model::posing::view_cosines`: one kernel
/// for posed normals and `n · v`) against Burn's tensor ops on the CPU: the built-in human's
/// vertices skinned under a bent pose, seen from a camera, without view noise and with noise
/// read from the middle of a larger tensor (as training slices each part's rows out of one).
#[test]
fn the_view_values_on_the_gpu_match_the_cpu() {
    use burn::tensor::{Device, TensorData};
    use f3g_avatar::model::posing::{
        Skinning, Taps, affine_tensor, view_cosines, view_cosines_as_tensors,
    };
    let human = f3g_rig::builtin::load().unwrap();
    let rig = &human.rig;
    let mut params = rig.zero_params();
    for (i, p) in params.pose.iter_mut().enumerate() {
        *p = 0.4 * ((i * 37 % 11) as f32 / 11.0 - 0.5);
    }
    let joints = rig.pose(&params).unwrap().skinning;
    let n = rig.skin.len();
    let ramp = |rows: usize, phase: f32, scale: f32| -> Vec<f32> {
        (0..3 * rows)
            .map(|i| scale * (i as f32 * 0.37 + phase).sin())
            .collect()
    };
    type ViewFn = fn(
        &Skinning,
        &Tensor<2>,
        &Tensor<2>,
        &Tensor<2>,
        Option<Tensor<2>>,
    ) -> (Tensor<2>, Tensor<2>);
    let run = |device: Device, op: ViewFn, noisy: bool| {
        let tensor = |v: Vec<f32>, rows: usize| {
            Tensor::<2>::from_data(TensorData::new(v, [rows, 3]), &device)
        };
        let skinning = Skinning::new(
            &affine_tensor(&joints, &device),
            &Taps::skin(&rig.skin, &device),
        );
        let canonical = tensor(ramp(n, 0.2, 0.9), n);
        let normals = tensor(ramp(n, 1.7, 1.0), n);
        let centre = Tensor::<2>::from_data(TensorData::new(vec![0.3, 1.2, 3.5], [1, 3]), &device);
        let noise = noisy.then(|| tensor(ramp(n + 20, 2.9, 0.1), n + 20).slice([7..7 + n, 0..3]));
        let (posed_normals, cosines) = op(&skinning, &canonical, &normals, &centre, noise);
        [values(posed_normals), values(cosines)]
    };
    for noisy in [false, true] {
        let gpu = run(
            Device::wgpu(burn::tensor::DeviceKind::DefaultDevice),
            view_cosines,
            noisy,
        );
        let cpu = run(Device::flex(), view_cosines_as_tensors, noisy);
        for ((g, c), what) in gpu.iter().zip(&cpu).zip(["normals", "cosines"]) {
            assert_eq!(g.len(), c.len(), "{what}");
            let worst = worst_difference(g, c);
            assert!(worst < 1e-5, "{what} (noise: {noisy}) differs by {worst}");
        }
    }
}

/// The taps' gather on GPU devices (`f3g_avatar::model::posing::Taps::apply` for inputs that
/// need no gradient: one kernel) against Burn's tensor ops on the CPU: rows of one to four
/// taps (the short ones padded), five channels, more values than one cube holds; and on an
/// autodiff device, as training calls it.
#[test]
fn the_taps_gather_on_the_gpu_matches_the_cpu() {
    use burn::tensor::{Device, TensorData};
    use f3g_avatar::model::posing::Taps;
    let (sources, rows, channels) = (300, 1000, 5);
    let lists: Vec<Vec<(usize, f32)>> = (0..rows)
        .map(|i| {
            (0..1 + i % 4)
                .map(|k| ((i * 7 + k * 131) % sources, 0.3 + 0.1 * k as f32))
                .collect()
        })
        .collect();
    let x: Vec<f32> = (0..sources * channels)
        .map(|i| (i as f32 * 0.29).sin())
        .collect();
    let gather = |device: &Device, on_gpu: bool| {
        let taps = Taps::new(lists.iter().map(Vec::as_slice), device);
        let x = Tensor::<2>::from_data(TensorData::new(x.clone(), [sources, channels]), device);
        let out = if on_gpu {
            taps.apply(x)
        } else {
            taps.apply_as_tensors(x)
        };
        assert_eq!(out.dims(), [rows, channels]);
        values(out)
    };
    let expected = gather(&Device::flex(), false);
    let gpu = Device::wgpu(burn::tensor::DeviceKind::DefaultDevice);
    for device in [gpu.clone(), gpu.autodiff()] {
        let worst = worst_difference(&gather(&device, true), &expected);
        assert!(worst < 1e-6, "differs by {worst} on {device:?}");
    }
}

/// The rotations' Hamilton product on GPU devices (`f3g_avatar::model::posing::quat_mul`: one
/// kernel forward, one per factor backward, the latter with a factor conjugated) against Burn's
/// tensor ops on the CPU: the product and both factors' gradients, over more rows than one cube
/// holds.
#[test]
fn the_quaternion_product_on_the_gpu_matches_the_cpu() {
    use burn::tensor::{Device, TensorData};
    use f3g_avatar::model::posing::{quat_mul, quat_mul_as_tensors};
    let n = 1000;
    let ramp = |phase: f32| -> Vec<f32> {
        (0..4 * n)
            .map(|i| (i as f32 * 0.37 + phase).sin())
            .collect()
    };
    let run = |device: Device, op: fn(Tensor<2>, Tensor<2>) -> Tensor<2>| {
        let device = device.autodiff();
        let tensor = |v: Vec<f32>| Tensor::<2>::from_data(TensorData::new(v, [n, 4]), &device);
        let a = tensor(ramp(0.1)).require_grad();
        let b = tensor(ramp(0.9)).require_grad();
        let q = op(a.clone(), b.clone());
        let grads = (q.clone() * tensor(ramp(2.3))).sum().backward();
        [
            values(q),
            values(a.grad(&grads).unwrap()),
            values(b.grad(&grads).unwrap()),
        ]
    };
    let gpu = run(
        Device::wgpu(burn::tensor::DeviceKind::DefaultDevice),
        quat_mul,
    );
    let cpu = run(Device::flex(), quat_mul_as_tensors);
    for ((g, c), what) in gpu
        .iter()
        .zip(&cpu)
        .zip(["product", "a's gradient", "b's gradient"])
    {
        assert_eq!(g.len(), c.len(), "{what}");
        let worst = worst_difference(g, c);
        assert!(worst < 1e-5, "{what} differs by {worst}");
    }
}
