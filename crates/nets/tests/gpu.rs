//! The networks on a GPU compute what they compute on the CPU: same seed, same weights, same
//! outputs and gradients within float tolerance. On a wgpu device (Mesa lavapipe in CI):
//! `cargo test --release -p f3g-nets --features gpu --test gpu`; on the first CUDA GPU:
//! `F3G_TEST_DEVICE=cuda cargo test --release -p f3g-nets --features cuda --test gpu`.
#![cfg(any(feature = "gpu", feature = "cuda"))]

mod common;

use burn::module::Module;
use burn::tensor::{Device, Tensor};
use common::ramp;
use f3g_nets::{DiscriminatorConfig, Lpips, LpipsNet, StyleUNetConfig};

/// The device under test: wgpu's default adapter, or the first CUDA GPU when
/// `F3G_TEST_DEVICE=cuda` (build with `--features cuda`).
fn test_device() -> Device {
    if std::env::var("F3G_TEST_DEVICE").as_deref() == Ok("cuda") {
        #[cfg(feature = "cuda")]
        return Device::cuda(0usize);
        #[cfg(not(feature = "cuda"))]
        panic!("F3G_TEST_DEVICE=cuda needs the `cuda` feature");
    }
    #[cfg(feature = "gpu")]
    return Device::wgpu(burn::tensor::DeviceKind::DefaultDevice);
    #[cfg(not(feature = "gpu"))]
    panic!("without the `gpu` feature, set F3G_TEST_DEVICE=cuda");
}

/// How much looser than f32 the device under test computes: Burn's CUDA convolutions and
/// matmuls run f32 inputs on TF32 tensor cores (a 10-bit mantissa: the lent H200 gave 7e-4 of
/// the output's scale); wgpu computes in f32.
fn tolerance_factor() -> f32 {
    if std::env::var("F3G_TEST_DEVICE").as_deref() == Ok("cuda") {
        20.0
    } else {
        1.0
    }
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
}

fn assert_close(a: &[f32], b: &[f32], tol: f32, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}");
    let tol = tol * tolerance_factor();
    let scale = b.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-6);
    let worst = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max);
    assert!(
        worst <= tol * scale,
        "{what}: differs by {worst} (scale {scale})"
    );
    assert!(a.iter().all(|v| v.is_finite()), "{what}: non-finite values");
}

/// Loss and the input's gradient of the CPU demo's body network on `device`.
fn body_net(device: &Device) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let device = device.clone().autodiff();
    let config = StyleUNetConfig::cpu_body(3, true);
    let net = config.init(3, &device).unwrap();
    let s = config.input_size;
    let x = ramp([1, 3, s, s], &device).require_grad();
    let view = (
        ramp([1, 1, s, s], &device),
        ramp([1, 1, s, s], &device) * 0.5,
    );
    let y = net.forward(x.clone(), Some(view)).unwrap();
    let front = values(y.front.clone());
    let loss = (y.front.powi_scalar(2).mean() + y.back.mean()).reshape([1]);
    let grads = loss.backward();
    let gx = values(x.grad(&grads).unwrap());
    (front, gx, values(loss))
}

/// On CUDA the input gradient's tolerance is wider than [`tolerance_factor`] makes it: it
/// goes back through every convolution, each on TF32 tensor cores both ways. Measured: rounding
/// the convolutions' inputs to TF32 on the CPU moves it by 0.0244 of its largest value (the
/// output by 6.9e-4); the H200 gave 0.0249 (2026-11-29). On wgpu, in f32, it stays 1e-3.
#[test]
fn the_body_network_matches_the_cpu_on_the_gpu() {
    let gpu = test_device();
    let (front_gpu, grad_gpu, loss_gpu) = body_net(&gpu);
    let (front_cpu, grad_cpu, loss_cpu) = body_net(&Device::flex());
    assert_close(&front_gpu, &front_cpu, 1e-4, "front output");
    assert_close(&loss_gpu, &loss_cpu, 1e-4, "loss");
    let cuda = std::env::var("F3G_TEST_DEVICE").as_deref() == Ok("cuda");
    let gradient_tolerance = if cuda {
        0.05 / tolerance_factor()
    } else {
        1e-3
    };
    assert_close(&grad_gpu, &grad_cpu, gradient_tolerance, "input gradient");
}

#[test]
fn the_discriminator_matches_the_cpu_on_the_gpu() {
    let run = |device: &Device| {
        let config = DiscriminatorConfig::cpu(64);
        let d = config.init(5, device).unwrap();
        values(d.forward(ramp([2, 3, 64, 64], device)).unwrap())
    };
    let gpu = test_device();
    assert_close(
        &run(&gpu),
        &run(&Device::flex()),
        1e-4,
        "discriminator logits",
    );
    assert!(Module::num_params(&DiscriminatorConfig::cpu(64).init(5, &gpu).unwrap()) > 0);
}

/// LPIPS (AlexNet, the training loss) and its gradient: two images in `[0, 1]` whose
/// difference changes sign, through every tap's channel normalisation.
fn lpips(device: &Device, size: usize) -> (Vec<f32>, Vec<f32>) {
    let device = device.clone().autodiff();
    let lpips = Lpips::load(LpipsNet::Alex, &device).unwrap();
    let a = (ramp([1, 3, size, size], &device) + 0.5).require_grad();
    let b = ramp([1, 3, size, size], &device).flip([2]) + 0.5;
    let d = lpips.forward(a.clone(), b).unwrap();
    let grads = d.clone().sum().backward();
    (values(d), values(a.grad(&grads).unwrap()))
}

/// On CUDA the gradient's tolerance is wider than [`tolerance_factor`] makes it: at these
/// sizes LPIPS's input gradient is ill-conditioned (every tap divided by its channel norm), and
/// TF32 convolutions move it a long way. Measured: rounding the convolutions' inputs to TF32 on
/// the CPU moves the gradient by 0.160 of its largest value at 32² and 0.025 at 64²; the H200
/// gave 0.161 at 32² (the distance moves by 4e-4 and 2e-4). PyTorch's default (cuDNN with TF32)
/// computes it the same way.
#[test]
fn lpips_matches_the_cpu_on_the_gpu() {
    let cuda = std::env::var("F3G_TEST_DEVICE").as_deref() == Ok("cuda");
    // 32²: AlexNet's last taps are 1×1 (the tiny test configurations' LPIPS size).
    for (size, cuda_gradient_tolerance) in [(32, 0.25), (64, 0.05)] {
        let (d_gpu, grad_gpu) = lpips(&test_device(), size);
        let (d_cpu, grad_cpu) = lpips(&Device::flex(), size);
        assert_close(&d_gpu, &d_cpu, 1e-4, &format!("LPIPS distance at {size}²"));
        let tolerance = if cuda {
            cuda_gradient_tolerance / tolerance_factor()
        } else {
            1e-3
        };
        assert_close(
            &grad_gpu,
            &grad_cpu,
            tolerance,
            &format!("LPIPS gradient at {size}²"),
        );
    }
}

/// One LPIPS layer, the smallest case of a bug in Burn 0.22.1's fusion (`--features fusion`):
/// a ReLU that runs in place on a convolution's `[N, C, 1, 1]` output nothing else holds, then
/// a channel normalisation. Fused, the reduction's read block took the vector axis from the
/// buffer's NHWC strides, launched no thread, and the division read the features from before
/// the ReLU (negative values where the CPU has zeros) over a norm of left-over memory. Fixed
/// by the vendored `burn-cubecl-fusion` patch (third_party/burn-cubecl-fusion.md); passes
/// unfused. Batches 1 and 4, the norm itself and the sum alone, each checked.
#[test]
fn a_normalisation_after_an_in_place_relu_matches_the_cpu() {
    use burn::tensor::activation::relu;
    use burn::tensor::module::max_pool2d;
    use burn::tensor::ops::{ConvOptions, MaxPoolOptions};
    use f3g_nets::conv::conv2d;
    let features = |batch: usize, device: &Device| {
        let x = ramp([batch, 192, 3, 3], device) + 0.5;
        let x = max_pool2d(x, MaxPoolOptions::new([3, 3]).with_stride([2, 2]));
        let w = ramp([384, 192, 3, 3], device) * 0.05;
        relu(conv2d(
            x,
            w,
            None,
            ConvOptions::new([1, 1], [1, 1], [1, 1], 1),
        ))
    };
    for batch in [1, 4] {
        let normalised = |device: &Device| {
            let r = features(batch, device);
            let norm = r.clone().powf_scalar(2.0).sum_dim(1).sqrt() + 1e-10;
            (values(r / norm.clone()), values(norm))
        };
        let ((gpu, gpu_norm), (cpu, cpu_norm)) =
            (normalised(&test_device()), normalised(&Device::flex()));
        assert!(
            gpu.iter().all(|&v| v >= 0.0),
            "batch {batch}: negative after a ReLU: {gpu:?}"
        );
        assert_close(
            &gpu,
            &cpu,
            1e-4,
            &format!("batch {batch}: normalised features"),
        );
        assert_close(
            &gpu_norm,
            &cpu_norm,
            1e-4,
            &format!("batch {batch}: their norm"),
        );
        let sum = |device: &Device| values(features(batch, device).powf_scalar(2.0).sum_dim(1));
        let (gpu, cpu) = (sum(&test_device()), sum(&Device::flex()));
        assert_close(&gpu, &cpu, 1e-4, &format!("batch {batch}: the sum alone"));
    }
}

/// The convolution op and both its gradients, one shape per algorithm the GPU path picks
/// (`f3g_nets::conv`, `src/conv/cube.rs`): stride 1 (implicit GEMMs where the device has matrix
/// units), stride 2 with a row and a column the convolution drops (the input gradient as
/// matmul + col2im), stride 2 with padding (the view branch's 4×4), stride 4 with two rows
/// and columns dropped (AlexNet's first layer), 1×1, and maps of 3×3 and 1×1 pixels smaller
/// than their padded kernels; the loss weights every output differently.
#[test]
fn the_convolution_and_its_gradients_match_the_cpu_for_every_stride() {
    use burn::tensor::ops::ConvOptions;
    use f3g_nets::conv::conv2d;
    // (batch, in, out, size, kernel, stride, padding)
    let cases = [
        (2, 8, 16, 12, 3, 1, 1),
        (1, 16, 8, 14, 3, 2, 0),
        (1, 4, 8, 16, 4, 2, 1),
        (1, 3, 16, 37, 11, 4, 2),
        (2, 32, 16, 9, 1, 1, 0),
        // AlexNet's deep layers at LPIPS 32²: 3×3 and 1×1 feature maps, padded.
        (1, 64, 96, 3, 5, 1, 2),
        (1, 96, 64, 1, 3, 1, 1),
        // Few channels over many positions: the weight gradient in bands (`conv::bands`), the
        // second with bands across the batch and a last band padded.
        (1, 4, 8, 64, 3, 1, 1),
        (2, 3, 8, 66, 3, 2, 1),
    ];
    let run = |device: &Device, (b, cin, cout, size, k, stride, pad): (_, _, _, _, _, _, _)| {
        let device = device.clone().autodiff();
        let x = ramp([b, cin, size, size], &device).require_grad();
        let w = (ramp([cout, cin, k, k], &device) * 0.3).require_grad();
        let options = ConvOptions::new([stride; 2], [pad; 2], [1, 1], 1);
        let y = conv2d(x.clone(), w.clone(), None, options);
        let weights = ramp(y.dims(), &device);
        let grads = (y.clone() * weights).sum().backward();
        (
            values(y),
            values(x.grad(&grads).unwrap()),
            values(w.grad(&grads).unwrap()),
        )
    };
    for case in cases {
        let (y_gpu, gx_gpu, gw_gpu) = run(&test_device(), case);
        let (y_cpu, gx_cpu, gw_cpu) = run(&Device::flex(), case);
        assert_close(&y_gpu, &y_cpu, 1e-4, &format!("output of {case:?}"));
        assert_close(
            &gx_gpu,
            &gx_cpu,
            1e-4,
            &format!("input gradient of {case:?}"),
        );
        assert_close(
            &gw_gpu,
            &gw_cpu,
            1e-4,
            &format!("weight gradient of {case:?}"),
        );
    }
}

/// The test device as the CubeCL device its kernels run on.
fn cube_device() -> burn_cubecl::CubeDevice {
    match test_device().as_dispatch() {
        burn::backend::DispatchDevice::Cube(d) => d.clone(),
        #[allow(unreachable_patterns)]
        _ => unreachable!("wgpu and CUDA devices are cubecl devices"),
    }
}

/// Row-major `[B, C, H, W]` values on `device`, stored row-major or channels-last (a permuted
/// view of `[B, H, W, C]`, as Burn's convolutions leave their outputs and input gradients).
fn upload(
    values: &[f32],
    [b, c, h, w]: [usize; 4],
    channels_last: bool,
    device: &burn_cubecl::CubeDevice,
) -> <burn_cubecl::CubeBackend as burn::backend::BackendTypes>::FloatTensorPrimitive {
    use burn::backend::ops::FloatTensorOps;
    use burn::tensor::TensorData;
    use burn_cubecl::CubeBackend;
    if !channels_last {
        let data = TensorData::new(values.to_vec(), [b, c, h, w]);
        return CubeBackend::float_from_data(data, device);
    }
    let mut nhwc = vec![0.0f32; values.len()];
    for (i, &v) in values.iter().enumerate() {
        let (x, y, ch, n) = (i % w, (i / w) % h, (i / (w * h)) % c, i / (w * h * c));
        nhwc[((n * h + y) * w + x) * c + ch] = v;
    }
    let data = TensorData::new(nhwc, [b, h, w, c]);
    CubeBackend::float_permute(CubeBackend::float_from_data(data, device), &[0, 3, 1, 2])
}

/// `fused::channels_last` stores a row-major tensor channels-last (the strides of a permuted
/// `[B, H, W, C]`) with the same values, and leaves a channels-last one as it is.
#[test]
fn channels_last_stores_the_same_values_channels_last() {
    use burn::backend::ops::FloatTensorOps;
    use burn_cubecl::CubeBackend;
    use f3g_nets::fused::FusedBackend;
    let device = cube_device();
    let shape = [2, 3, 5, 4];
    let values: Vec<f32> = (0..120).map(|i| (i as f32 * 0.37).sin()).collect();
    let read = |t| {
        let data = burn::tensor::read_sync(CubeBackend::float_into_data(t)).unwrap();
        data.convert::<f32>().try_to_vec::<f32>().unwrap()
    };
    for stored_last in [false, true] {
        let out = CubeBackend::to_channels_last(upload(&values, shape, stored_last, &device));
        assert_eq!(
            out.meta.strides()[..],
            [60, 1, 12, 3],
            "stored last: {stored_last}"
        );
        assert_eq!(read(out), values, "stored last: {stored_last}");
    }
}

/// The input gradient of strided convolutions as a GEMM and a col2im (`conv::strided`): strides
/// 2 and 3, padding, dilation, a 4×4 kernel, the blurred `2n + 1` sides the down-sampling layers
/// see, a batch of two — from output gradients and weights in either layout (channels-last, as
/// the activations' backward and `fused::scale_weight` leave them) — against Burn's on the CPU.
#[test]
fn the_strided_input_gradient_matches_the_cpu_from_either_layout() {
    use burn::backend::ops::{FloatTensorOps, ModuleOps};
    use burn::tensor::TensorData;
    use burn::tensor::ops::ConvOptions;
    use burn_cubecl::CubeBackend;
    use f3g_nets::conv::strided::strided_input_grad;
    type Flex = burn::backend::Flex;
    let device = cube_device();
    let ramp_values = |n: usize, phase: f32| -> Vec<f32> {
        (0..n).map(|i| (i as f32 * 0.37 + phase).sin()).collect()
    };
    // (batch, in, out, size, kernel, stride, padding, dilation)
    let cases = [
        (1, 8, 16, 17, 3, 2, 0, 1),
        (2, 3, 5, 9, 4, 2, 1, 1),
        (1, 4, 6, 13, 3, 3, 1, 2),
        (1, 2, 3, 1, 3, 2, 1, 1),
    ];
    for case @ (b, cin, cout, size, k, stride, pad, dil) in cases {
        let options = ConvOptions::new([stride; 2], [pad; 2], [dil; 2], 1);
        let out = (size + 2 * pad - dil * (k - 1) - 1) / stride + 1;
        let (x_shape, g_shape, w_shape) =
            ([b, cin, size, size], [b, cout, out, out], [cout, cin, k, k]);
        let g = ramp_values(g_shape.iter().product(), 0.7);
        let w = ramp_values(w_shape.iter().product(), 0.2);
        let flex = Default::default();
        let cpu = Flex::conv2d_x_backward(
            Flex::float_zeros(x_shape.into(), &flex, burn::tensor::DType::F32.into()),
            Flex::float_from_data(TensorData::new(w.clone(), w_shape), &flex),
            Flex::float_from_data(TensorData::new(g.clone(), g_shape), &flex),
            options.clone(),
        );
        let read =
            |data: burn::tensor::TensorData| data.convert::<f32>().try_to_vec::<f32>().unwrap();
        let cpu = read(burn::tensor::read_sync(Flex::float_into_data(cpu)).unwrap());
        for (g_last, w_last) in [(false, false), (true, true), (true, false), (false, true)] {
            let cube = strided_input_grad(
                x_shape.into(),
                upload(&w, w_shape, w_last, &device),
                upload(&g, g_shape, g_last, &device),
                &options,
            )
            .expect("small tensors");
            let cube = read(burn::tensor::read_sync(CubeBackend::float_into_data(cube)).unwrap());
            let layouts = format!("channels-last gradient {g_last}, weight {w_last}");
            // The matmul runs on TF32 tensor cores on CUDA.
            assert_close(&cube, &cpu, 3e-4, &format!("{case:?}, {layouts}"));
        }
    }
}

/// The banded weight gradient with bands of every kind: one band per launch, several per launch
/// with a short last launch, bands crossing batch items, a strided dilated kernel, padding,
/// bands that divide the positions (a channels-last gradient then read as it is) — from
/// row-major and channels-last inputs and gradients — against Burn's own weight gradient
/// on the CPU (`conv2d_weight_backward`).
#[test]
fn the_weight_gradient_in_bands_matches_the_cpu() {
    use burn::backend::ops::{FloatTensorOps, ModuleOps};
    use burn::tensor::TensorData;
    use burn::tensor::ops::ConvOptions;
    use burn_cubecl::CubeBackend;
    use f3g_nets::conv::bands::{BandSum, Bands, launch_queued_band_sums, weight_grad_in_bands};
    type Flex = burn::backend::Flex;
    let device = cube_device();
    let read = |data: burn::tensor::TensorData| data.convert::<f32>().try_to_vec::<f32>().unwrap();
    let mut queued = Vec::new();
    let ramp_values = |n: usize, phase: f32| -> Vec<f32> {
        (0..n).map(|i| (i as f32 * 0.37 + phase).sin()).collect()
    };
    // (batch, in, out, size, kernel, stride, padding, dilation, band, bands per launch)
    let cases = [
        (1, 3, 5, 20, 3, 1, 1, 1, 64, 1),
        (2, 4, 6, 17, 3, 2, 1, 1, 96, 3),
        (3, 2, 7, 15, 5, 1, 2, 2, 32, 4),
        (1, 5, 3, 16, 1, 1, 0, 1, 50, 2),
        // Bands that divide the positions: a channels-last gradient's rows are read as they
        // are, one band per launch and two per launch.
        (1, 3, 5, 16, 3, 1, 1, 1, 64, 1),
        (2, 4, 6, 16, 3, 2, 1, 1, 32, 2),
    ];
    for case @ (b, cin, cout, size, k, stride, pad, dil, band, per_launch) in cases {
        let options = ConvOptions::new([stride; 2], [pad; 2], [dil; 2], 1);
        let out = (size + 2 * pad - dil * (k - 1) - 1) / stride + 1;
        let x_shape = [b, cin, size, size];
        let g_shape = [b, cout, out, out];
        let w_shape = [cout, cin, k, k];
        let x = ramp_values(x_shape.iter().product(), 0.1);
        let g = ramp_values(g_shape.iter().product(), 0.7);
        let w = vec![0.0f32; w_shape.iter().product()];
        let flex = Default::default();
        let cpu = Flex::conv2d_weight_backward(
            Flex::float_from_data(TensorData::new(x.clone(), x_shape), &flex),
            Flex::float_from_data(TensorData::new(w, w_shape), &flex),
            Flex::float_from_data(TensorData::new(g.clone(), g_shape), &flex),
            options.clone(),
        );
        let cpu = read(burn::tensor::read_sync(Flex::float_into_data(cpu)).unwrap());
        let upload = |values: &[f32], shape, last| upload(values, shape, last, &device);
        for (x_last, g_last) in [(false, false), (true, true), (true, false), (false, true)] {
            let split = |bands_per_launch, sum| {
                let bands = Bands {
                    band,
                    bands_per_launch,
                };
                let (x, g) = (upload(&x, x_shape, x_last), upload(&g, g_shape, g_last));
                weight_grad_in_bands(x, g, w_shape.into(), &options, bands, sum)
                    .expect("small tensors are split")
            };
            let cube = split(per_launch, BandSum::Now);
            let cube = read(burn::tensor::read_sync(CubeBackend::float_into_data(cube)).unwrap());
            // The bands' GEMM runs on TF32 tensor cores on CUDA: 3.7e-3 of the scale on an H100
            // for the second case (sums of ~160 products with cancellation); a wrong index would
            // be off by the scale itself.
            let label = format!("{case:?}, channels-last input {x_last}, gradient {g_last}");
            assert_close(&cube, &cpu, 3e-4, &label);
            // All bands in one GEMM, their sum queued: written by the one launch below.
            queued.push((split(usize::MAX, BandSum::Queued), cpu.clone(), label));
        }
    }
    // 24 sums of 15 to 350 values over 2 to 22 bands, of row-major and channels-last
    // products, in one launch (chunked where the device binds fewer tensors).
    launch_queued_band_sums();
    for (cube, cpu, label) in queued {
        let cube = read(burn::tensor::read_sync(CubeBackend::float_into_data(cube)).unwrap());
        assert_close(&cube, &cpu, 3e-4, &format!("queued: {label}"));
    }
}

/// A chain of convolutions large enough for their weight gradients to run in bands (a 64² map
/// of 4 channels: four bands of 1 024 positions), so that each weight's sum over its bands is
/// queued and written by its gate's launch (`conv/autodiff.rs`): a weight shared by two
/// convolutions, one made by other ops and a frozen one, on the device under test against the
/// CPU.
#[test]
fn the_queued_weight_gradients_match_the_cpu() {
    use burn::tensor::ops::ConvOptions;
    use f3g_nets::conv::conv2d;
    let run = |device: &Device| {
        let device = device.clone().autodiff();
        let options = || ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
        let x = ramp([1, 4, 64, 64], &device).require_grad();
        let shared = ramp([4, 4, 3, 3], &device).require_grad();
        let root = ramp([4, 4, 3, 3], &device).flip([0]).require_grad();
        let frozen = ramp([4, 4, 3, 3], &device).flip([1]);
        let y = conv2d(x.clone(), shared.clone(), None, options());
        let y = conv2d(y, root.clone() * 1.5 - 0.1, None, options());
        let y = conv2d(y, shared.clone(), None, options());
        let y = conv2d(y, frozen, None, options());
        let grads = (y.clone() * (ramp(y.dims(), &device) + 0.25))
            .sum()
            .backward();
        [
            values(x.grad(&grads).unwrap()),
            values(shared.grad(&grads).unwrap()),
            values(root.grad(&grads).unwrap()),
        ]
    };
    let (gpu, cpu) = (run(&test_device()), run(&Device::flex()));
    for ((got, expected), what) in gpu.iter().zip(&cpu).zip(["dx", "dshared", "droot"]) {
        assert_close(got, expected, 1e-4, what);
    }
}

/// `F3G_CONV_GEMM`'s values: one routine for every pass, one per pass, and what is refused.
#[test]
fn conv_gemm_names_read_as_cubek_routines() {
    use burn_cubecl::kernel::conv::{AcceleratedTileKind, ConvAlgorithm};
    use f3g_nets::conv::gemm_choices;
    let tma = Some((ConvAlgorithm::SimpleAsyncTma, AcceleratedTileKind::Cmma));
    assert_eq!(gemm_choices("simple_async_tma_cmma"), Ok([tma; 3]));
    assert_eq!(gemm_choices(""), Ok([None; 3]));
    let mma = Some((ConvAlgorithm::SimpleSyncCyclic, AcceleratedTileKind::Mma));
    let tilewise = Some((ConvAlgorithm::SimpleSyncTilewise, AcceleratedTileKind::Cmma));
    assert_eq!(
        gemm_choices("forward:simple_sync_cyclic_mma,weight:simple_sync_tilewise_cmma"),
        Ok([mma, None, tilewise])
    );
    let e = gemm_choices("simple_sync_cyclic").unwrap_err();
    assert!(e.contains("not a routine"), "{e}");
    let e = gemm_choices("backward:simple_sync_cyclic_mma").unwrap_err();
    assert!(e.contains("no pass \"backward\""), "{e}");
}

/// The split chosen for the layers it is for, and not for the others.
#[test]
fn weight_gradients_are_split_where_the_tiles_are_few() {
    use f3g_nets::conv::bands::{Bands, MAX_COLUMN_VALUES};
    // A 32 → 32 3×3 layer at 1024²: 5 tiles for a million positions.
    let plan = Bands::plan(1 << 20, 32, 288).expect("split");
    assert!(
        plan.band >= 1024 && plan.band.is_multiple_of(32),
        "{plan:?}"
    );
    let bands = (1usize << 20).div_ceil(plan.band);
    assert!(bands * 5 >= 1024, "{plan:?}: {bands} bands");
    assert!(
        (1usize << 20).is_multiple_of(plan.band),
        "{plan:?}: bands that divide"
    );
    assert!(plan.bands_per_launch * 288 * plan.band <= MAX_COLUMN_VALUES);
    // 512 → 512 at 32²: many tiles, a short reduction.
    assert_eq!(Bands::plan(1024, 512, 4608), None);
    // Enough tiles already: 1024 → 1024 3×3 at 64².
    assert_eq!(Bands::plan(4096, 1024, 9216), None);
}

/// Adam's one-pass update on the device: three steps equal the CPU's (whose update is Burn's
/// `Adam` to the bit, `adam::tests`).
#[test]
fn adam_in_one_pass_matches_the_cpu() {
    use burn::optim::Optimizer;
    use f3g_nets::adam::FusedAdam;
    let adam = FusedAdam {
        beta_1: 0.9,
        beta_2: 0.999,
        epsilon: 1e-8,
    };
    let run = |device: &Device| {
        let mut p = ramp([1, 1, 7, 1001], device);
        let mut state = None;
        for step in 0..3 {
            let grad = (ramp([1, 1, 7, 1001], device) * (step as f32 + 1.0)).sin() * 1e-3;
            (p, state) = adam.step(1e-2, p, grad, state);
        }
        let state = state.unwrap().momentum;
        [values(p), values(state.moment_1), values(state.moment_2)]
    };
    let gpu = run(&test_device());
    let cpu = run(&Device::flex());
    for (what, (g, c)) in ["parameter", "first moment", "second moment"]
        .iter()
        .zip(gpu.iter().zip(&cpu))
    {
        assert_close(g, c, 1e-5, what);
    }
}

/// [`f3g_nets::adam::ModuleAdam`] on the device launches the updates of up to `MAX_PER_LAUNCH`
/// parameters per kernel (one grid layer each, sorted by size): three steps of a module with
/// more parameters than two launches hold, of many sizes, equal the CPU's one-by-one updates.
/// Convolution weights among them get channels-last gradients (as the implicit GEMM hands
/// them back) for two steps, which the update keeps the weight and its moments in, then a
/// row-major one.
#[test]
fn adam_over_a_module_in_shared_launches_matches_the_cpu() {
    use burn::module::Param;
    use burn::optim::GradientsParams;
    use f3g_nets::adam::{FusedAdam, MAX_PER_LAUNCH};

    #[derive(Module, Debug)]
    struct Many {
        rows: Vec<Param<Tensor<4>>>,
        weights: Vec<Param<Tensor<4>>>,
    }
    let sizes: Vec<usize> = (0..2 * MAX_PER_LAUNCH + 5)
        .map(|i| 1 + (i * i * 37) % 3001 + if i == 7 { 90_000 } else { 0 })
        .collect();
    let weight_shapes = [[5, 3, 3, 3], [8, 6, 3, 3], [4, 16, 1, 1], [2, 1, 4, 4]];
    let run = |device: &Device| {
        let device = device.clone().autodiff();
        let mut many = Many {
            rows: sizes
                .iter()
                .map(|&n| Param::from_tensor(ramp([1, 1, 1, n], &device)))
                .collect(),
            weights: weight_shapes
                .iter()
                .map(|&shape| Param::from_tensor(ramp(shape, &device)))
                .collect(),
        };
        let mut adam = FusedAdam {
            beta_1: 0.9,
            beta_2: 0.999,
            epsilon: 1e-8,
        }
        .init();
        for step in 0..3 {
            let rows = many
                .rows
                .iter()
                .enumerate()
                .map(|(i, p)| (p.val() * (step + i % 5) as f32).sin().sum());
            // The gradient of a permuted view is the permuted gradient: `[O, kh, kw, I]`
            // row-major, a channels-last `[O, I, kh, kw]`.
            let weights = many.weights.iter().map(|p| {
                let w = p.val() * (step + 2) as f32;
                if step < 2 {
                    w.permute([0, 2, 3, 1]).sin().sum()
                } else {
                    w.sin().sum()
                }
            });
            let loss = rows.chain(weights).reduce(|a, b| a + b).unwrap();
            let grads = GradientsParams::from_grads(loss.backward(), &many);
            many = adam.step(1e-2, many, grads);
        }
        many.rows
            .iter()
            .chain(&many.weights)
            .flat_map(|p| values(p.val().inner()))
            .collect::<Vec<_>>()
    };
    let gpu = run(&test_device());
    let cpu = run(&Device::flex());
    assert_close(&gpu, &cpu, 1e-5, "parameters");
}

/// Reductions with few outputs over long axes — a bias gradient (autodiff sums `[B, C, H, W]`
/// over `B·H·W` in one folded axis), a loss's mean, a sum along rows — against the CPU: on
/// GPUs they run the cube and plane routines of the patched `burn-cubecl`
/// (`third_party/burn-cubecl.md`) instead of one thread per output.
#[test]
fn long_reductions_with_few_outputs_match_the_cpu() {
    let run = |device: &Device| {
        let device = device.clone().autodiff();
        let x = ramp([2, 6, 160, 150], &device);
        let bias = Tensor::<1>::zeros([6], &device).require_grad();
        let y = x.clone() + bias.clone().reshape([1, 6, 1, 1]);
        let grads = (y * x.clone()).sum().backward();
        let bias_grad = values(bias.grad(&grads).unwrap());
        let mean = values(x.clone().mean().reshape([1]));
        let rows = values(x.clone().reshape([300, 960]).sum_dim(1));
        let columns = values(x.reshape([24, 12000]).mean_dim(1));
        [bias_grad, mean, rows, columns]
    };
    let gpu = run(&test_device());
    let cpu = run(&Device::flex());
    for (what, (g, c)) in ["bias gradient", "mean", "row sums", "row means"]
        .iter()
        .zip(gpu.iter().zip(&cpu))
    {
        assert_close(g, c, 1e-4, what);
    }
}

/// StyleGAN2's element-wise chains and modulated weights as single kernels (`fused`, `Cube`
/// devices, with or without Burn's `fusion`) against the CPU's single loops, forward and
/// backward, for the shapes and paddings the networks use, edge sizes, and an up-sampling of
/// more cubes than one grid row holds.
#[test]
fn the_fused_ops_match_the_cpu() {
    use f3g_nets::fused;
    /// A ramp of `shape` (`[B, C, H, W]`), stored row-major or channels-last (a permuted view,
    /// as Burn's convolutions leave their outputs on a GPU).
    fn laid_out(shape: [usize; 4], device: &Device, channels_last: bool) -> Tensor<4> {
        let [b, c, h, w] = shape;
        if channels_last {
            ramp([b, h, w, c], device).permute([0, 3, 1, 2])
        } else {
            ramp(shape, device)
        }
    }
    /// Output and input gradient of `op` on `x` (the gradient of `sum(op(x) · r)`, with
    /// weights `r` in the layout `r_last` says that give every output its own).
    fn output_and_grad(
        op: &dyn Fn(Tensor<4>) -> Tensor<4>,
        x: Tensor<4>,
        r_last: bool,
    ) -> [Vec<f32>; 2] {
        let x = x.require_grad();
        let y = op(x.clone());
        let r = (laid_out(y.dims(), &x.device(), r_last) * 37.0).sin();
        let grads = (y.clone() * r).sum().backward();
        [values(y), values(x.grad(&grads).unwrap())]
    }
    // Every pairing of the input's layout and the output gradient's.
    const LAYOUTS: [(bool, bool); 4] = [(false, false), (true, true), (true, false), (false, true)];
    let gpu = test_device().autodiff();
    let cpu = Device::flex().autodiff();
    let compare = |op: &dyn Fn(Tensor<4>) -> Tensor<4>, shape: [usize; 4], what: &str| {
        for (x_last, r_last) in LAYOUTS {
            let x = laid_out(shape, &gpu, x_last);
            assert!(
                fused::runs(&x, 0),
                "{what}: the fused op runs on the device"
            );
            let got = output_and_grad(op, x, r_last);
            let expected = output_and_grad(op, laid_out(shape, &cpu, x_last), r_last);
            let what = format!("{what} {shape:?}, channels-last input {x_last}, gradient {r_last}");
            assert_close(&got[0], &expected[0], 1e-5, &format!("{what}: output"));
            assert_close(&got[1], &expected[1], 1e-5, &format!("{what}: gradient"));
        }
    };
    // The bias's gradient of a long map over few channels, summed in segments and then over
    // them (`channel_sum`), from either layout; a batch of two row-major.
    // Channels-last over a power-of-two channel count, the input gradient and each cube's share
    // of the bias's come from one pass (`bias_leaky_relu_grads`): over many cubes, the last
    // one short, and with a cube of 1 024 units.
    for (shape, x_last, r_last) in [
        ([1, 3, 256, 256], false, false),
        ([1, 3, 256, 256], true, true),
        ([2, 3, 256, 256], false, true),
        ([2, 16, 100, 30], true, true),
        ([1, 1024, 3, 5], true, true),
    ] {
        let run = |device: &Device| {
            let x = laid_out(shape, device, x_last);
            let v = (0..shape[1]).map(|c| 0.3 - 0.2 * (c % 3) as f32).collect();
            let b = Tensor::<1>::from_data(burn::tensor::TensorData::new(v, [shape[1]]), device)
                .require_grad();
            let y = fused::bias_leaky_relu(x, b.clone(), 0.2, 1.5);
            let r = (laid_out(shape, device, r_last) * 37.0).sin();
            values(b.grad(&(y * r).sum().backward()).unwrap())
        };
        let what = format!("bias gradient {shape:?}, channels-last {x_last}/{r_last}");
        assert_close(&run(&gpu), &run(&cpu), 1e-4, &what);
    }
    // 40 × 30: the noise strength's gradient summed over several cubes of pixels, the last
    // one partly past them; from a channels-last map of 8, 512 or 4 channels, the three
    // gradients from one pass over the batch's positions, cubes of 256 and 512 units and a
    // thousand cubes.
    for shape in [
        [1, 1, 1, 1],
        [2, 3, 5, 7],
        [1, 32, 16, 16],
        [2, 3, 40, 30],
        [2, 8, 40, 30],
        [1, 512, 6, 5],
        [1, 4, 256, 256],
    ] {
        let channels = shape[1];
        let bias = |device: &Device| {
            let v = (0..channels).map(|c| 0.3 - 0.17 * c as f32).collect();
            Tensor::<1>::from_data(burn::tensor::TensorData::new(v, [channels]), device)
        };
        // The bias's gradient too: the op's second parent. StyleGAN2's activation, and bias +
        // ReLU on the second pairing; the input scaled (an equalised convolution's weight
        // scale) on the second and fourth.
        for (pairing, (x_last, r_last)) in LAYOUTS.into_iter().enumerate() {
            let (slope, gain) = if pairing == 1 { (0.0, 1.0) } else { (0.2, 1.5) };
            let input_scale = [1.0, 0.37, 1.0, 0.059][pairing];
            let run = |device: &Device| {
                let x = laid_out(shape, device, x_last).require_grad();
                let b = bias(device).require_grad();
                let y =
                    fused::scaled_bias_leaky_relu(x.clone(), input_scale, b.clone(), slope, gain);
                let r = (laid_out(shape, device, r_last) * 37.0).sin();
                let grads = (y.clone() * r).sum().backward();
                [
                    values(y),
                    values(x.grad(&grads).unwrap()),
                    values(b.grad(&grads).unwrap()),
                ]
            };
            let (got, expected) = (run(&gpu), run(&cpu));
            for (what, (g, e)) in ["output", "dx", "bias gradient"]
                .iter()
                .zip(got.iter().zip(&expected))
            {
                let layouts = format!("channels-last input {x_last}, gradient {r_last}");
                assert_close(
                    g,
                    e,
                    1e-5,
                    &format!(
                        "bias_leaky_relu {shape:?} ({input_scale}, {slope}, {gain}), {layouts}: \
                         {what}"
                    ),
                );
            }
        }
        compare(&fused::upsample2, shape, "upsample2");
        // A styled convolution's noise injection and activation in one op: the gradients of
        // input, strength and bias too, from either layout.
        for (x_last, r_last) in LAYOUTS {
            let [_, _, h, w] = shape;
            let run = |device: &Device| {
                let x = laid_out(shape, device, x_last).require_grad();
                let noise = ramp([1, 1, h, w], device).flip([3]) * 2.0;
                let strength = Tensor::<1>::from_data(
                    burn::tensor::TensorData::new(vec![0.37f32], [1]),
                    device,
                )
                .require_grad();
                let b = bias(device).require_grad();
                let y = fused::noisy_bias_leaky_relu(
                    x.clone(),
                    noise,
                    strength.clone(),
                    b.clone(),
                    0.2,
                    1.5,
                );
                let r = (laid_out(shape, device, r_last) * 37.0).sin();
                let grads = (y.clone() * r).sum().backward();
                [
                    values(y),
                    values(x.grad(&grads).unwrap()),
                    values(strength.grad(&grads).unwrap()),
                    values(b.grad(&grads).unwrap()),
                ]
            };
            let (got, expected) = (run(&gpu), run(&cpu));
            for (what, (g, e)) in ["output", "dx", "strength gradient", "bias gradient"]
                .iter()
                .zip(got.iter().zip(&expected))
            {
                let layouts = format!("channels-last input {x_last}, gradient {r_last}");
                assert_close(
                    g,
                    e,
                    1e-5,
                    &format!("noisy_bias_leaky_relu {shape:?}, {layouts}: {what}"),
                );
            }
        }
    }
    // ReLU's backward stops an infinite gradient where the output is zero (LPIPS's √Σx²).
    let relu_sqrt = |x: Tensor<4>| {
        let c = x.dims()[1];
        fused::bias_leaky_relu(x.clone(), Tensor::zeros([c], &x.device()), 0.0, 1.0).sqrt()
    };
    compare(&relu_sqrt, [1, 3, 4, 5], "bias + ReLU under a square root");
    compare(&fused::upsample2, [1, 2, 1, 9], "upsample2");
    for shape in [[2, 3, 5, 7], [1, 32, 16, 16], [1, 2, 2, 9]] {
        compare(&fused::downsample2, shape, "downsample2");
    }
    // Bilinear resizing to sizes neither double nor half (one kernel each way): enlarging by
    // non-integer factors (a sample read by up to 7 outputs along an axis), shrinking (a
    // crop to LPIPS's side), the same size, one sample, one output.
    for (shape, height, width) in [
        ([1, 3, 7, 5], 19, 12),
        ([2, 3, 40, 30], 17, 23),
        ([1, 32, 16, 16], 16, 16),
        ([1, 2, 1, 1], 4, 3),
        ([1, 1, 9, 6], 1, 1),
        ([1, 4, 64, 48], 150, 7),
    ] {
        let resize = |x| f3g_nets::resample::resize(x, height, width);
        compare(&resize, shape, &format!("resize to {height} × {width}"));
    }
    // Strided views read as they are: resizing a slice, and the gradients of a resize and of a
    // 2 × 2 mean arriving as slices of a concatenation's gradient (offset into its buffer).
    let beside = |y: Tensor<4>| {
        let [b, c, h, _] = y.dims();
        Tensor::cat(vec![ramp([b, c, h, 3], &y.device()), y], 3)
    };
    let sliced = |x: Tensor<4>| {
        let [b, c, h, w] = x.dims();
        f3g_nets::resample::resize(x.slice([0..b, 0..c, 1..h, 2..w]), 11, 6)
    };
    compare(&sliced, [2, 3, 9, 8], "resize of a slice");
    let resized = |x| beside(f3g_nets::resample::resize(x, 13, 5));
    compare(&resized, [1, 4, 6, 9], "resize, its gradient a slice");
    let halved = |x| beside(fused::downsample2(x));
    compare(&halved, [2, 3, 10, 7], "downsample2, its gradient a slice");
    // A network's last op: the Haar analysis of its output's gradient, here a slice.
    let synthesised = |x| beside(fused::inverse_haar(x));
    compare(
        &synthesised,
        [1, 8, 5, 6],
        "inverse_haar, its gradient a slice",
    );
    // 4 · 2 100² outputs: 68 907 cubes of 256, past one grid row of 65 535.
    compare(&fused::upsample2, [1, 1, 2100, 2100], "upsample2");
    for shape in [[1, 2, 8, 8], [2, 3, 5, 9], [1, 1, 1, 2]] {
        for (before, after) in [(2, 2), (2, 1), (1, 2), (3, 0), (0, 3), (3, 3), (1, 1)] {
            if shape[2] + before + after >= 4 && shape[3] + before + after >= 4 {
                let blur = |x| fused::blur(x, before, after);
                compare(&blur, shape, &format!("blur ({before}, {after})"));
            }
        }
    }
    // The modulated weight, both gradients: a 3×3 layer of the paper's widths (4 608 values per
    // output channel, 18 per cube unit), a 1×1 ToRGB, and fewer values than a cube has units;
    // the output gradient row-major, and channels-last as the weight-gradient GEMM gives it;
    // the layer's styles alone or a range of a longer vector (zeros in more than one cube).
    let style_vector =
        |device: &Device, count: usize| ramp([1, 1, 1, count], device).reshape([count]) * 3.0 + 1.0;
    for (shape, demodulate, r_last, [first, more]) in [
        ([16, 512, 3, 3], true, false, [0, 0]),
        ([16, 512, 3, 3], true, true, [300, 40]),
        ([12, 64, 1, 1], false, false, [7, 600]),
        ([3, 5, 3, 3], true, true, [0, 3]),
        ([3, 5, 3, 3], false, true, [2, 0]),
    ] {
        let run = |device: &Device| {
            let weight = ramp(shape, device).require_grad();
            let style = style_vector(device, first + shape[1] + more).require_grad();
            let y = fused::modulate(weight.clone(), style.clone(), first, 0.05, demodulate);
            let r = (laid_out(shape, device, r_last) * 37.0).sin();
            let grads = (y.clone() * r).sum().backward();
            [
                values(y),
                values(weight.grad(&grads).unwrap()),
                values(style.grad(&grads).unwrap()),
            ]
        };
        let (got, expected) = (run(&gpu), run(&cpu));
        for (what, (g, e)) in ["output", "weight gradient", "style gradient"]
            .iter()
            .zip(got.iter().zip(&expected))
        {
            assert_close(
                g,
                e,
                1e-5,
                &format!(
                    "modulate {shape:?}, styles {first} + {more} ({demodulate}, gradient \
                     channels-last {r_last}): {what}"
                ),
            );
        }
    }
    // A network's layers modulated together (one launch, or a few where the adapter binds few
    // tensors): shapes of 3 to 16 output channels side by side (cubes past a layer's channels
    // write nothing), demodulated or not, each from its own range of one style vector.
    {
        let layers = [
            ([16, 64, 3, 3], true),
            ([12, 16, 1, 1], false),
            ([3, 5, 3, 3], true),
            ([7, 9, 3, 3], false),
        ];
        let run = |device: &Device| {
            let count = layers.iter().map(|(shape, _)| shape[1]).sum::<usize>() + 5;
            let style = style_vector(device, count).require_grad();
            let mut first = 5;
            let mut weights = Vec::new();
            let mut modulations = Vec::new();
            for (shape, demodulate) in layers {
                let weight = ramp(shape, device).require_grad();
                weights.push(weight.clone());
                modulations.push(fused::Modulation {
                    weight,
                    first,
                    scale: 0.05,
                    demodulate,
                });
                first += shape[1];
            }
            let ys = fused::modulate_all(modulations, style.clone());
            let loss = ys
                .iter()
                .map(|y| (y.clone() * (y.clone() * 37.0).sin()).sum())
                .reduce(|a, b| a + b)
                .unwrap();
            let grads = loss.backward();
            let mut all: Vec<Vec<f32>> = ys.into_iter().map(values).collect();
            all.extend(weights.iter().map(|w| values(w.grad(&grads).unwrap())));
            all.push(values(style.grad(&grads).unwrap()));
            all
        };
        let (got, expected) = (run(&gpu), run(&cpu));
        assert_eq!(got.len(), 2 * layers.len() + 1);
        for (k, (g, e)) in got.iter().zip(&expected).enumerate() {
            assert_close(g, e, 1e-5, &format!("modulate_all, value set {k}"));
        }
    }
    // The backward op itself with a channels-last gradient (Burn's weight-gradient GEMMs hand
    // theirs back so; the autodiff runs above may not reach that layout).
    {
        use burn::backend::Dispatch;
        use f3g_nets::fused::FusedBackend;
        let shape = [6, 7, 3, 3];
        let grads = |device: &Device| {
            let weight = ramp(shape, device);
            let style = style_vector(device, shape[1] + 4);
            let grad = (laid_out(shape, device, true) * 37.0).sin();
            let (d_weight, d_style) = <Dispatch as FusedBackend>::modulate_grad(
                weight.into_dispatch(),
                style.into_dispatch(),
                grad.into_dispatch(),
                4,
                0.05,
                true,
            );
            [
                values(Tensor::<4>::from_dispatch(d_weight)),
                values(Tensor::<1>::from_dispatch(d_style)),
            ]
        };
        let expected = grads(&Device::flex());
        let got = grads(&test_device());
        assert_close(
            &got[0],
            &expected[0],
            1e-5,
            "modulate_grad, channels-last: weight",
        );
        assert_close(
            &got[1],
            &expected[1],
            1e-5,
            "modulate_grad, channels-last: style",
        );
        // An equalised convolution's scaled weight, its gradient from either layout.
        for (shape, grad_last) in [
            ([6, 7, 3, 3], false),
            ([6, 7, 3, 3], true),
            ([5, 3, 1, 1], true),
        ] {
            let scaled = |device: &Device| {
                let weight = ramp(shape, device).require_grad();
                let y = fused::scale_weight(weight.clone(), 0.3);
                let r = (laid_out(shape, device, grad_last) * 37.0).sin();
                let grads = (y.clone() * r).sum().backward();
                [values(y), values(weight.grad(&grads).unwrap())]
            };
            let (got, expected) = (scaled(&gpu), scaled(&cpu));
            let what = format!("scale_weight {shape:?}, gradient channels-last {grad_last}");
            assert_close(&got[0], &expected[0], 1e-6, &format!("{what}: output"));
            assert_close(&got[1], &expected[1], 1e-6, &format!("{what}: gradient"));
            let direct = |device: &Device| {
                let grad = (laid_out(shape, device, grad_last) * 37.0).sin();
                let d = <Dispatch as FusedBackend>::scale_weight_grad(grad.into_dispatch(), 0.3);
                values(Tensor::<4>::from_dispatch(d))
            };
            let (got, expected) = (direct(&test_device()), direct(&Device::flex()));
            assert_close(&got, &expected, 1e-6, &format!("{what}: the backward op"));
        }
    }
    // The activations' backward ops themselves with a channels-last output and gradient (the
    // autodiff runs above may hand the gradient in another layout): the one-pass kernel with
    // the input scaled, and for the noisy form the strength's gradient too, the bias's and the
    // strength's sums over many cubes queued for all three shapes (six tables of 1 to 512
    // columns and 1 to 1 024 rows) and written by one `bias_grads_launch_queued` (chunked where
    // the adapter binds few tensors); a single cube (the 30 positions) queues nothing.
    {
        use burn::backend::Dispatch;
        use f3g_nets::fused::FusedBackend;
        let shapes = [[2, 8, 40, 30], [1, 4, 256, 256], [1, 512, 6, 5]];
        let run = |device: &Device| {
            let queued: Vec<_> = shapes
                .iter()
                .map(|&shape| {
                    let [_, _, h, w] = shape;
                    let output = (laid_out(shape, device, true) * 3.0).sin();
                    let grad = (laid_out(shape, device, true) * 37.0).sin();
                    let noise = ramp([1, 1, h, w], device).flip([3]) * 2.0;
                    let noisy = <Dispatch as FusedBackend>::noisy_bias_leaky_relu_backward_queue(
                        output.clone().into_dispatch(),
                        grad.clone().into_dispatch(),
                        noise.into_dispatch(),
                        0.2,
                        1.5,
                    );
                    let scaled = <Dispatch as FusedBackend>::bias_leaky_relu_backward_queue(
                        output.into_dispatch(),
                        grad.into_dispatch(),
                        0.37,
                        0.2,
                        1.5,
                    );
                    (noisy, scaled)
                })
                .collect();
            let ((_, first, _), _) = &queued[0];
            <Dispatch as FusedBackend>::bias_grads_launch_queued(first.clone());
            queued
                .into_iter()
                .map(|((dx, d_bias, d_strength), (scaled_dx, scaled_bias))| {
                    [
                        values(Tensor::<4>::from_dispatch(dx)),
                        values(Tensor::<1>::from_dispatch(d_bias)),
                        values(Tensor::<1>::from_dispatch(d_strength)),
                        values(Tensor::<4>::from_dispatch(scaled_dx)),
                        values(Tensor::<1>::from_dispatch(scaled_bias)),
                    ]
                })
                .collect::<Vec<_>>()
        };
        let (got, expected) = (run(&test_device()), run(&Device::flex()));
        let parts = [
            "noisy: dx",
            "noisy: bias gradient",
            "noisy: strength gradient",
            "scaled: dx",
            "scaled: bias gradient",
        ];
        for (shape, (got, expected)) in shapes.iter().zip(got.iter().zip(&expected)) {
            for (what, (g, e)) in parts.iter().zip(got.iter().zip(expected)) {
                // The strength's gradient is ≈ 1 from 262 144 products of sines that cancel:
                // f32 shares against the CPU's f64 sum differ by ≈ 2·10⁻⁵ of it.
                let tolerance = if what.contains("strength") {
                    1e-4
                } else {
                    1e-5
                };
                let what = format!("activation backward {shape:?}, {what}");
                assert_close(g, e, tolerance, &what);
            }
        }
    }
    // The scaled linear layer, its three gradients: a modulation of the paper's widths (a style
    // vector of 512 to 256 input channels), a mapping layer's leaky ReLU on a few rows, a ReLU.
    for ([batch, inputs, outputs], scales) in [
        ([1, 512, 256], fused::LinearScales::affine(0.044, 1.0)),
        (
            [3, 33, 7],
            fused::LinearScales {
                weight_scale: 0.03,
                bias_scale: 0.01,
                slope: 0.2,
                gain: std::f32::consts::SQRT_2,
            },
        ),
        (
            [2, 5, 3],
            fused::LinearScales {
                weight_scale: 0.7,
                bias_scale: 2.0,
                slope: 0.0,
                gain: 1.5,
            },
        ),
    ] {
        let matrix = |rows: usize, columns: usize, device: &Device| {
            ramp([1, 1, rows, columns], device).reshape([rows, columns])
        };
        let run = |device: &Device| {
            let x = (matrix(batch, inputs, device) * 3.0).require_grad();
            let weight = matrix(outputs, inputs, device).flip([1]).require_grad();
            let bias = (matrix(1, outputs, device).reshape([outputs]) + 0.1).require_grad();
            let y = fused::scaled_linear(x.clone(), weight.clone(), bias.clone(), scales);
            let r = (matrix(batch, outputs, device) * 37.0).sin();
            let grads = (y.clone() * r).sum().backward();
            [
                values(y),
                values(x.grad(&grads).unwrap()),
                values(weight.grad(&grads).unwrap()),
                values(bias.grad(&grads).unwrap()),
            ]
        };
        let (got, expected) = (run(&gpu), run(&cpu));
        for (what, (g, e)) in ["output", "dx", "weight gradient", "bias gradient"]
            .iter()
            .zip(got.iter().zip(&expected))
        {
            let dims = [batch, inputs, outputs];
            assert_close(g, e, 1e-5, &format!("scaled_linear {dims:?}: {what}"));
        }
    }
    for shape in [[1, 1, 2, 2], [2, 3, 4, 6], [1, 3, 16, 16]] {
        compare(&fused::haar, shape, "haar");
        let bands = [shape[0], 4 * shape[1], shape[2] / 2, shape[3] / 2];
        compare(&fused::inverse_haar, bands, "inverse_haar");
    }
    // A ToRGB's output: x, the previous level's bands carried up and a bias, the gradients of
    // all three; x (and the output gradient) and the skip in every pairing of layouts, from a
    // skip of one pixel (every up-sampling tap an edge) to one of 8 × 6.
    for [b, c4, h, w] in [[1, 4, 1, 1], [2, 12, 3, 2], [1, 8, 8, 6]] {
        for (x_last, skip_last) in LAYOUTS {
            let big = [b, c4, 2 * h, 2 * w];
            let run = |device: &Device| {
                let x = laid_out(big, device, x_last).require_grad();
                let skip = (laid_out([b, c4, h, w], device, skip_last) * 3.0).require_grad();
                let v = (0..c4).map(|c| 0.2 - 0.07 * c as f32).collect();
                let bias = Tensor::<1>::from_data(burn::tensor::TensorData::new(v, [c4]), device)
                    .require_grad();
                let y = fused::to_rgb_output(x.clone(), bias.clone(), skip.clone());
                let r = (laid_out(big, device, x_last) * 37.0).sin();
                let grads = (y.clone() * r).sum().backward();
                [
                    values(y),
                    values(x.grad(&grads).unwrap()),
                    values(bias.grad(&grads).unwrap()),
                    values(skip.grad(&grads).unwrap()),
                ]
            };
            let (got, expected) = (run(&gpu), run(&cpu));
            for (what, (g, e)) in ["output", "dx", "bias gradient", "skip gradient"]
                .iter()
                .zip(got.iter().zip(&expected))
            {
                let what = format!(
                    "to_rgb_output {big:?}, channels-last x {x_last}, skip {skip_last}: {what}"
                );
                assert_close(g, e, 1e-5, &what);
            }
        }
    }
    // The first ToRGB's bias, from either layout.
    for shape in [[1, 12, 8, 8], [2, 3, 5, 7]] {
        let channels = shape[1];
        let add_bias = |x: Tensor<4>| {
            let v = (0..channels).map(|c| 0.2 - 0.07 * c as f32).collect();
            let bias =
                Tensor::<1>::from_data(burn::tensor::TensorData::new(v, [channels]), &x.device());
            fused::add_channel_bias(x, bias)
        };
        compare(&add_bias, shape, "add_channel_bias");
    }
    // A decoder level's concatenation: each input and the output gradient in every layout, the
    // gradients of both inputs; a single channel on one side and a batch of two.
    for ([b, c1, c2, h, w], r_last) in [
        ([1, 8, 8, 4, 4], true),
        ([2, 3, 5, 3, 2], false),
        ([1, 1, 6, 5, 3], true),
    ] {
        for (first_last, second_last) in LAYOUTS {
            let run = |device: &Device| {
                let first = laid_out([b, c1, h, w], device, first_last).require_grad();
                let second = (laid_out([b, c2, h, w], device, second_last) * 3.0).require_grad();
                let y = fused::cat_channels(first.clone(), second.clone());
                let r = (laid_out([b, c1 + c2, h, w], device, r_last) * 37.0).sin();
                let grads = (y.clone() * r).sum().backward();
                [
                    values(y),
                    values(first.grad(&grads).unwrap()),
                    values(second.grad(&grads).unwrap()),
                ]
            };
            let (got, expected) = (run(&gpu), run(&cpu));
            for (what, (g, e)) in ["output", "first's gradient", "second's gradient"]
                .iter()
                .zip(got.iter().zip(&expected))
            {
                let what = format!(
                    "cat_channels {:?}, channels-last {first_last}/{second_last}/{r_last}: {what}",
                    [b, c1, c2, h, w]
                );
                assert_close(g, e, 1e-6, &what);
            }
        }
    }
}

/// A ToRGB's 12-channel convolution output as CUDA allocates it (channels-last, each pixel's
/// row pitched to 16 values), read by the two ToRGB ops without a copy: the same sums as from
/// the gapless map on the CPU. Built by hand on the device (wgpu does not pitch), with the
/// pitch's 4 values per pixel set far off so that a kernel that read them would fail.
#[test]
fn the_to_rgb_ops_read_a_pitched_map() {
    use burn::backend::Flex;
    use burn::backend::ops::FloatTensorOps;
    use burn::tensor::TensorData;
    use burn_cubecl::CubeBackend;
    use f3g_nets::fused::FusedBackend;

    let device = cube_device();
    let [b, c4, pitch, h, w] = [2, 12, 16, 6, 4];
    let value = |n: usize, c: usize, y: usize, x: usize| {
        (((n * 7 + c) * 13 + y * 5 + x * 3) % 29) as f32 / 29.0 - 0.5
    };
    let mut pitched = vec![1.0e6f32; b * h * w * pitch];
    let mut gapless = vec![0.0f32; b * c4 * h * w];
    for n in 0..b {
        for c in 0..c4 {
            for y in 0..h {
                for x in 0..w {
                    pitched[((n * h + y) * w + x) * pitch + c] = value(n, c, y, x);
                    gapless[((n * c4 + c) * h + y) * w + x] = value(n, c, y, x);
                }
            }
        }
    }
    let bias: Vec<f32> = (0..c4).map(|c| 0.1 * c as f32 - 0.4).collect();
    let skip: Vec<f32> = (0..b * c4 * h * w / 4)
        .map(|i| (i % 11) as f32 / 11.0)
        .collect();
    let skip_shape = [b, c4, h / 2, w / 2];

    let mut x = CubeBackend::float_from_data(TensorData::new(pitched, [b, h, w, pitch]), &device);
    x.meta.shape_mut()[3] = c4;
    let x = CubeBackend::float_permute(x, &[0, 3, 1, 2]);
    let on_gpu = |t: TensorData| CubeBackend::float_from_data(t, &device);
    let read = |t: <CubeBackend as burn::backend::BackendTypes>::FloatTensorPrimitive| {
        let data = burn::tensor::read_sync(CubeBackend::float_into_data(t)).unwrap();
        data.convert::<f32>().try_to_vec::<f32>().unwrap()
    };
    let flex = Default::default();
    let on_cpu = |t: TensorData| Flex::float_from_data(t, &flex);
    let read_cpu = |t: <Flex as burn::backend::BackendTypes>::FloatTensorPrimitive| {
        let data = burn::tensor::read_sync(Flex::float_into_data(t)).unwrap();
        data.convert::<f32>().try_to_vec::<f32>().unwrap()
    };
    let gapless_x = || on_cpu(TensorData::new(gapless.clone(), [b, c4, h, w]));

    let got = read(CubeBackend::add_channel_bias(
        x.clone(),
        on_gpu(TensorData::new(bias.clone(), [c4])),
    ));
    let expected = read_cpu(Flex::add_channel_bias(
        gapless_x(),
        on_cpu(TensorData::new(bias.clone(), [c4])),
    ));
    assert_close(&got, &expected, 1e-6, "add_channel_bias of a pitched map");

    let got = read(CubeBackend::to_rgb_output(
        x,
        on_gpu(TensorData::new(bias.clone(), [c4])),
        on_gpu(TensorData::new(skip.clone(), skip_shape)),
    ));
    let expected = read_cpu(Flex::to_rgb_output(
        gapless_x(),
        on_cpu(TensorData::new(bias, [c4])),
        on_cpu(TensorData::new(skip, skip_shape)),
    ));
    assert_close(&got, &expected, 1e-5, "to_rgb_output of a pitched map");
}

/// LPIPS's comparison of one tap (`fused::lpips_distance`): distances and both maps'
/// gradients, each map row-major or channels-last (as the VGG's ReLUs leave them on a GPU), a
/// batch of two with one pixel of `x` zero in each item (where the op's gradient is its
/// one-sided derivative), at AlexNet's narrowest tap and a VGG-like width.
#[test]
fn the_lpips_comparison_matches_the_cpu() {
    use f3g_nets::fused;
    fn laid_out(shape: [usize; 4], device: &Device, channels_last: bool, flip: bool) -> Tensor<4> {
        let [b, c, h, w] = shape;
        let mut t = if channels_last {
            ramp([b, h, w, c], device).permute([0, 3, 1, 2])
        } else {
            ramp(shape, device)
        };
        if flip {
            t = t.flip([1]);
        }
        // ReLU features, and pixel (0, 0) of x zero in every channel.
        let t = burn::tensor::activation::relu(t + 0.2);
        if flip {
            t
        } else {
            t.slice_fill([0..b, 0..c, 0..1, 0..1], 0.0)
        }
    }
    let (gpu, cpu) = (test_device().autodiff(), Device::flex().autodiff());
    for shape in [[2, 64, 9, 7], [2, 256, 4, 4]] {
        let c = shape[1];
        for (x_last, y_last) in [(false, false), (true, true), (true, false), (false, true)] {
            let run = |device: &Device| {
                let x = laid_out(shape, device, x_last, false).require_grad();
                let y = laid_out(shape, device, y_last, true).require_grad();
                let head: Vec<f32> = (0..c).map(|k| 0.01 + 0.3 * ((k * 13) % 7) as f32).collect();
                let head = Tensor::<1>::from_data(burn::tensor::TensorData::new(head, [c]), device);
                let d = fused::lpips_distance(x.clone(), y.clone(), head);
                let weights = Tensor::<1>::from_data(
                    burn::tensor::TensorData::new(vec![1.0f32, -2.0], [2]),
                    device,
                );
                let grads = (d.clone() * weights).sum().backward();
                [
                    values(d),
                    values(x.grad(&grads).unwrap()),
                    values(y.grad(&grads).unwrap()),
                ]
            };
            let (got, expected) = (run(&gpu), run(&cpu));
            let plane = shape[2] * shape[3];
            // x's zero pixels apart: their gradient is ~10¹⁰ times the others'.
            let part = |v: &[f32], zero: bool| -> Vec<f32> {
                v.iter()
                    .enumerate()
                    .filter(|(i, _)| (i % plane == 0) == zero)
                    .map(|(_, &v)| v)
                    .collect()
            };
            let layouts = format!("{shape:?}, channels-last x {x_last}, y {y_last}");
            assert_close(&got[0], &expected[0], 1e-5, &format!("{layouts}: distance"));
            for zero in [false, true] {
                let what = format!("{layouts}: x gradient (zero pixel {zero})");
                assert_close(&part(&got[1], zero), &part(&expected[1], zero), 1e-5, &what);
            }
            assert_close(
                &got[2],
                &expected[2],
                1e-5,
                &format!("{layouts}: y gradient"),
            );
        }
    }
}

/// A gradient through a channels-last view of one channel: `x` `[1, 1, 1, 1]` repeated to
/// 2 × 2, times `sin(37 · v)` for a `[1, 2, 2, 1]` ramp `v` permuted to `[1, 1, 2, 2]`. Under
/// Burn 0.22.1's published `fusion` `x`'s gradient came out −2.41 against −1.247: the fused
/// block wrote `r = sin(37 · v)` in place wrongly, its aliased input read at vector size 1 in a
/// block of width 2 (the second change of the vendored `burn-cubecl-fusion`,
/// third_party/burn-cubecl-fusion.md). Found by `the_fused_ops_match_the_cpu`, whose layout
/// pairings meet it; this is its smallest case. Unfused builds run it too.
#[test]
fn a_gradient_through_a_permuted_view_matches_the_cpu() {
    let run = |device: &Device| {
        let x = ramp([1, 1, 1, 1], device).require_grad();
        let y = x.clone().repeat_dim(2, 2).repeat_dim(3, 2);
        let r = (ramp([1, 2, 2, 1], device).permute([0, 3, 1, 2]) * 37.0).sin();
        let grads = (y * r).sum().backward();
        values(x.grad(&grads).unwrap())
    };
    let (gpu, cpu) = (test_device().autodiff(), Device::flex().autodiff());
    assert_close(&run(&gpu), &run(&cpu), 1e-5, "x's gradient");
}
