//! The Burn operation: same values and gradients as the CPU reference, gradients that reach
//! whatever produced the Gaussians, and clear errors for bad tensors.

mod common;

use burn::tensor::{Device, Tensor, TensorData};
use common::{Scene, random_scene};
use f3g_splat::cpu::{self, PixelGrads};
use f3g_splat::{GaussianCloud, Gaussians, RenderOptions, SplatError, render};

fn cloud_of(s: &Scene) -> GaussianCloud {
    GaussianCloud {
        means: Scene::to_f32(&s.means),
        log_scales: Scene::to_f32(&s.log_scales),
        quats: Scene::to_f32(&s.quats),
        opacity_logits: Scene::to_f32(&s.opacity_logits),
        sh: Scene::to_f32(&s.sh),
        sh_degree: f3g_splat::sh::degree_for(s.sh.len() / (3 * s.len())).unwrap(),
    }
}

fn values<const D: usize>(t: &Tensor<D>) -> Vec<f32> {
    t.to_data().try_into_vec_as::<f32>().unwrap()
}

fn background(s: &Scene, device: &Device) -> Tensor<1> {
    Tensor::from_data(
        TensorData::new(s.background.map(|v| v as f32).to_vec(), [3]),
        device,
    )
}

#[test]
fn forward_and_gradients_equal_the_cpu_reference() {
    let device = Device::flex().autodiff();
    let s = random_scene(11, 40, 2, 0.99, 45, 33);
    let cloud = cloud_of(&s);
    let g = cloud.to_tensors(&device);
    let g = Gaussians {
        means: g.means.require_grad(),
        log_scales: g.log_scales.require_grad(),
        quats: g.quats.require_grad(),
        opacity_logits: g.opacity_logits.require_grad(),
        sh: g.sh.require_grad(),
    };
    let bg = background(&s, &device).require_grad();
    let options = RenderOptions::default();
    let out = render(&g, &s.camera, bg.clone(), &options).unwrap();

    let bg32 = s.background.map(|v| v as f32);
    let reference = cpu::render(&cloud.slices(), &s.camera, bg32, &options).unwrap();
    assert_eq!(values(&out.color), reference.color);
    assert_eq!(values(&out.alpha), reference.alpha);
    assert_eq!(values(&out.depth), reference.depth);
    let radii: Vec<i64> = out.radii.to_data().try_into_vec_as::<i64>().unwrap();
    assert_eq!(
        radii,
        reference
            .projected
            .iter()
            .flat_map(|p| p.radii.map(i64::from))
            .collect::<Vec<_>>()
    );

    let (wc, wa, wd) = common::loss_weights(5, 45 * 33);
    let (wc, wa, wd) = (Scene::to_f32(&wc), Scene::to_f32(&wa), Scene::to_f32(&wd));
    let loss = (out.color
        * Tensor::<3>::from_data(TensorData::new(wc.clone(), [33, 45, 3]), &device))
    .sum()
        + (out.alpha * Tensor::<2>::from_data(TensorData::new(wa.clone(), [33, 45]), &device))
            .sum()
        + (out.depth * Tensor::<2>::from_data(TensorData::new(wd.clone(), [33, 45]), &device))
            .sum();
    let grads = loss.backward();
    let expected = cpu::render_backward(
        &cloud.slices(),
        &s.camera,
        &options,
        &reference,
        &PixelGrads {
            color: &wc,
            alpha: &wa,
            depth: &wd,
        },
    );
    let close = |name: &str, got: Vec<f32>, want: &[f32]| {
        assert_eq!(got.len(), want.len(), "{name}");
        for (i, (a, b)) in got.iter().zip(want).enumerate() {
            assert!(
                (a - b).abs() <= 1e-5 * (1.0 + b.abs()),
                "{name}[{i}]: {a} vs {b}"
            );
        }
        assert!(
            want.iter().any(|v| v.abs() > 1e-4),
            "{name}: gradient should not vanish"
        );
    };
    close(
        "means",
        values(&g.means.grad(&grads).unwrap()),
        &expected.means,
    );
    close(
        "log_scales",
        values(&g.log_scales.grad(&grads).unwrap()),
        &expected.log_scales,
    );
    close(
        "quats",
        values(&g.quats.grad(&grads).unwrap()),
        &expected.quats,
    );
    close(
        "opacity_logits",
        values(&g.opacity_logits.grad(&grads).unwrap()),
        &expected.opacity_logits,
    );
    close("sh", values(&g.sh.grad(&grads).unwrap()), &expected.sh);
    close(
        "background",
        values(&bg.grad(&grads).unwrap()),
        &expected.background,
    );
}

#[test]
fn gradients_reach_the_network_that_produced_the_gaussians() {
    // Gaussians predicted by a linear map from per-Gaussian features: the render's gradient
    // must reach the weights, and equal the chain rule through the CPU reference.
    let device = Device::flex().autodiff();
    let s = random_scene(12, 25, 0, 0.9, 40, 30);
    let cloud = cloud_of(&s);
    let base = cloud.to_tensors(&device);
    let n = cloud.len();
    let features = Tensor::<2>::from_data(
        TensorData::new(
            (0..n * 4)
                .map(|i| ((i * 37 % 11) as f32 / 11.0) - 0.5)
                .collect::<Vec<_>>(),
            [n, 4],
        ),
        &device,
    );
    let weight = Tensor::<2>::from_data(TensorData::new(vec![0.01f32; 4 * 3], [4, 3]), &device)
        .require_grad();
    let means = base.means.clone() + features.clone().matmul(weight.clone());
    let g = Gaussians {
        means: means.clone(),
        ..base
    };
    let out = render(
        &g,
        &s.camera,
        background(&s, &device),
        &RenderOptions::default(),
    )
    .unwrap();
    let grads = out.color.sum().backward();
    let d_weight = values(&weight.grad(&grads).expect("the weights receive a gradient"));

    let host_means = values(&means);
    let mut moved = cloud.clone();
    moved.means = host_means;
    let reference = cpu::render(
        &moved.slices(),
        &s.camera,
        s.background.map(|v| v as f32),
        &RenderOptions::default(),
    )
    .unwrap();
    let ones = vec![1f32; 40 * 30 * 3];
    let zeros = vec![0f32; 40 * 30];
    let d = cpu::render_backward(
        &moved.slices(),
        &s.camera,
        &RenderOptions::default(),
        &reference,
        &PixelGrads {
            color: &ones,
            alpha: &zeros,
            depth: &zeros,
        },
    );
    let f = values(&features);
    for a in 0..4 {
        for b in 0..3 {
            let want: f32 = (0..n).map(|i| f[4 * i + a] * d.means[3 * i + b]).sum();
            let got = d_weight[3 * a + b];
            assert!(
                (got - want).abs() <= 1e-4 * (1.0 + want.abs()),
                "dW[{a}][{b}]: {got} vs {want}"
            );
        }
    }
}

#[test]
fn gradient_descent_on_colours_fits_a_target_render() {
    let device = Device::flex().autodiff();
    let s = random_scene(13, 30, 1, 0.95, 32, 32);
    let cloud = cloud_of(&s);
    let mut target_cloud = cloud.clone();
    target_cloud
        .sh
        .iter_mut()
        .step_by(3)
        .for_each(|v| *v += 0.8);
    let bg = background(&s, &device);
    let target = render(
        &target_cloud.to_tensors(&device),
        &s.camera,
        bg.clone(),
        &RenderOptions::default(),
    )
    .unwrap()
    .color
    .detach();
    let g = cloud.to_tensors(&device);
    let mut sh = g.sh.clone().require_grad();
    let mut losses = Vec::new();
    for _ in 0..30 {
        let current = Gaussians {
            sh: sh.clone(),
            ..g.clone()
        };
        let out = render(&current, &s.camera, bg.clone(), &RenderOptions::default()).unwrap();
        let loss = (out.color - target.clone()).powf_scalar(2.0).mean();
        losses.push(values(&loss.clone().reshape([1]))[0]);
        let grads = loss.backward();
        let step = sh.grad(&grads).unwrap() * 80.0;
        sh = (sh - step).detach().require_grad();
    }
    assert!(
        losses[29] < 0.05 * losses[0],
        "loss went from {} to {}",
        losses[0],
        losses[29]
    );
}

#[test]
fn bad_tensors_give_errors_not_panics() {
    let device = Device::flex();
    let s = random_scene(14, 6, 1, 0.9, 20, 20);
    let cloud = cloud_of(&s);
    let bg = background(&s, &device);
    let opts = RenderOptions::default();
    let ok = cloud.to_tensors(&device);
    assert!(render(&ok, &s.camera, bg.clone(), &opts).is_ok());

    let mut nan = cloud.clone();
    nan.log_scales[7] = f32::NAN;
    match render(&nan.to_tensors(&device), &s.camera, bg.clone(), &opts) {
        Err(SplatError::NonFinite {
            name: "log_scales",
            index: 7,
            ..
        }) => {}
        other => panic!("expected a NaN error, got {other:?}"),
    }
    let wrong_means = Gaussians {
        means: ok.means.clone().slice([0..6, 0..2]),
        ..ok.clone()
    };
    let e = render(&wrong_means, &s.camera, bg.clone(), &opts)
        .unwrap_err()
        .to_string();
    assert!(e.contains("means") && e.contains("[6, 2]"), "{e}");
    let wrong_count = Gaussians {
        quats: ok.quats.clone().slice([0..5, 0..4]),
        ..ok.clone()
    };
    assert!(
        render(&wrong_count, &s.camera, bg.clone(), &opts)
            .unwrap_err()
            .to_string()
            .contains("quats")
    );
    let wrong_sh = Gaussians {
        sh: Tensor::zeros([6, 5, 3], &device),
        ..ok.clone()
    };
    assert!(matches!(
        render(&wrong_sh, &s.camera, bg.clone(), &opts),
        Err(SplatError::ShDegree { coeffs: 5 })
    ));
    let bad_bg = Tensor::<1>::zeros([4], &device);
    assert!(
        render(&ok, &s.camera, bad_bg, &opts)
            .unwrap_err()
            .to_string()
            .contains("background")
    );
    let mut cam = s.camera.clone();
    cam.width = 0;
    assert!(matches!(
        render(&ok, &cam, bg, &opts),
        Err(SplatError::Camera(_))
    ));
}

#[test]
fn slices_of_a_larger_tensor_render_like_contiguous_ones() {
    // Non-contiguous inputs (a transposed view) are read correctly.
    let device = Device::flex();
    let s = random_scene(15, 10, 0, 0.9, 24, 24);
    let cloud = cloud_of(&s);
    let g = cloud.to_tensors(&device);
    let transposed = Gaussians {
        means: g.means.clone().transpose().transpose(),
        ..g.clone()
    };
    let bg = background(&s, &device);
    let a = render(&g, &s.camera, bg.clone(), &RenderOptions::default()).unwrap();
    let b = render(&transposed, &s.camera, bg, &RenderOptions::default()).unwrap();
    assert_eq!(values(&a.color), values(&b.color));
}

#[test]
fn too_many_intersections_is_an_error_not_a_wrapped_count() {
    let (cloud, camera) = common::overflowing_scene();
    let device = Device::flex();
    let bg = Tensor::<1>::zeros([3], &device);
    let err = render(
        &cloud.to_tensors(&device),
        &camera,
        bg,
        &RenderOptions::default(),
    )
    .unwrap_err();
    assert_eq!(
        err,
        SplatError::Intersections {
            count: 8_200 * 262_144,
            limit: i32::MAX as u64
        }
    );
    assert!(err.to_string().contains("render a smaller image"), "{err}");
}
