//! The convolution op (`f3g_nets::conv`) against Burn's own convolution on the same CPU device:
//! outputs and every gradient within float tolerance, for the shapes the networks use and for
//! the cases that take Burn's route (groups); its weight gradient against central differences;
//! and a frozen weight gets no weight-gradient computation.

mod central_differences;
mod common;

use std::sync::Mutex;

use burn::tensor::module::conv2d as burn_conv2d;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Device, Tensor, TensorData};
use central_differences::values;
use common::ramp;
use f3g_nets::conv::{conv2d, profile};

/// The profile is process-wide: tests that convolve on the CPU take turns.
static CPU: Mutex<()> = Mutex::new(());

fn assert_close(got: &[f32], expected: &[f32], what: &str) {
    assert_eq!(got.len(), expected.len(), "{what}: lengths");
    let scale = expected.iter().fold(1.0f32, |m, v| m.max(v.abs()));
    for (i, (g, e)) in got.iter().zip(expected).enumerate() {
        assert!(
            (g - e).abs() <= 1e-5 * scale,
            "{what}[{i}]: {g}, Burn's convolution gives {e}"
        );
    }
}

/// A weight that is not a ramp of the input's period.
fn weight(shape: [usize; 4], device: &Device) -> Tensor<4> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n)
        .map(|i| ((i * 31 + 7) % 23) as f32 / 23.0 - 0.4)
        .collect();
    Tensor::from_data(TensorData::new(v, shape), device)
}

/// Output, input gradient, weight gradient and bias gradient of `sum(conv · r)`.
fn run(
    conv: fn(Tensor<4>, Tensor<4>, Option<Tensor<1>>, ConvOptions<2>) -> Tensor<4>,
    x_shape: [usize; 4],
    w_shape: [usize; 4],
    options: &ConvOptions<2>,
) -> [Vec<f32>; 4] {
    let device = Device::flex().autodiff();
    let x = ramp(x_shape, &device).require_grad();
    let w = weight(w_shape, &device).require_grad();
    let b = Tensor::<1>::from_data(
        TensorData::new(
            (0..w_shape[0]).map(|i| i as f32 * 0.1).collect(),
            [w_shape[0]],
        ),
        &device,
    )
    .require_grad();
    let y = conv(x.clone(), w.clone(), Some(b.clone()), options.clone());
    let r = ramp(y.dims(), &device) + 0.25;
    let grads = (y.clone() * r).sum().backward();
    [
        values(y),
        values(x.grad(&grads).unwrap()),
        values(w.grad(&grads).unwrap()),
        values(b.grad(&grads).unwrap()),
    ]
}

fn matches_burn(x_shape: [usize; 4], w_shape: [usize; 4], options: ConvOptions<2>) {
    let _turn = CPU.lock().unwrap_or_else(|e| e.into_inner());
    let ours = run(conv2d, x_shape, w_shape, &options);
    let burns = run(burn_conv2d, x_shape, w_shape, &options);
    for ((got, expected), what) in ours.iter().zip(&burns).zip(["output", "dx", "dW", "db"]) {
        assert_close(
            got,
            expected,
            &format!("{what} of {x_shape:?} ∗ {w_shape:?}"),
        );
    }
}

#[test]
fn the_styleunets_convolution_matches_burns() {
    // A StyledConv at 32 channels, a ToRGB-like 1×1, the stride-2 down-sampling of ConvLayer.
    matches_burn(
        [1, 32, 32, 32],
        [32, 32, 3, 3],
        ConvOptions::new([1, 1], [1, 1], [1, 1], 1),
    );
    matches_burn(
        [1, 32, 16, 16],
        [12, 32, 1, 1],
        ConvOptions::new([1, 1], [0, 0], [1, 1], 1),
    );
    matches_burn(
        [1, 16, 35, 35],
        [32, 16, 3, 3],
        ConvOptions::new([2, 2], [0, 0], [1, 1], 1),
    );
}

#[test]
fn batches_few_channels_and_lpips_first_layer_match_burns() {
    matches_burn(
        [2, 3, 20, 18],
        [5, 3, 3, 3],
        ConvOptions::new([1, 1], [1, 1], [1, 1], 1),
    );
    matches_burn(
        [1, 3, 64, 64],
        [64, 3, 11, 11],
        ConvOptions::new([4, 4], [2, 2], [1, 1], 1),
    );
}

#[test]
fn grouped_convolutions_take_burns_route_and_match() {
    matches_burn(
        [1, 6, 12, 12],
        [6, 2, 3, 3],
        ConvOptions::new([1, 1], [1, 1], [1, 1], 3),
    );
}

#[test]
fn both_gradients_match_central_differences() {
    let _turn = CPU.lock().unwrap_or_else(|e| e.into_inner());
    let device = Device::flex().autodiff();
    // Strided (dx through col2im) and stride 1 (dx as the convolution with the flipped kernel).
    for options in [
        ConvOptions::new([2, 1], [1, 0], [1, 2], 1),
        ConvOptions::new([1, 1], [1, 2], [1, 1], 1),
    ] {
        let x0 = ramp([2, 2, 7, 8], &device);
        let w0 = weight([3, 2, 3, 2], &device);
        let loss = |x: Tensor<4>, w: Tensor<4>| {
            let y = conv2d(x, w, None, options.clone());
            let r = ramp(y.dims(), &device) + 0.3;
            (y.clone() * y * r).sum()
        };
        let what = format!("stride {:?}", options.stride);
        central_differences::check(
            &|w| loss(x0.clone(), w),
            w0.clone(),
            1e-2,
            &format!("dW, {what}"),
        );
        central_differences::check(
            &|x| loss(x, w0.clone()),
            x0.clone(),
            1e-2,
            &format!("dx, {what}"),
        );
    }
}

#[test]
fn a_frozen_weight_gets_no_weight_gradient_and_the_profile_sees_each_phase() {
    let _turn = CPU.lock().unwrap_or_else(|e| e.into_inner());
    let device = Device::flex().autodiff();
    let options = ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
    let phases = |train_weight: bool| {
        let x = ramp([1, 4, 9, 9], &device).require_grad();
        let mut w = weight([5, 4, 3, 3], &device);
        if train_weight {
            w = w.require_grad();
        }
        profile::start();
        let _ = conv2d(x, w, None, options.clone()).sum().backward();
        let records = profile::finish();
        assert!(
            records
                .iter()
                .all(|r| r.output == [1, 5, 9, 9] && r.flops() > 0.0)
        );
        records.into_iter().map(|r| r.phase).collect::<Vec<_>>()
    };
    use profile::Phase::{Forward, InputGrad, WeightGrad};
    assert_eq!(phases(false), [Forward, InputGrad]);
    assert_eq!(phases(true), [Forward, WeightGrad, InputGrad]);
}

/// The weights reach the convolution's node through a gate that registers their gradients
/// after the pass's queued sums are written (`conv/autodiff.rs`): a chain of four convolutions
/// against Burn's, with a weight shared by two of them, one made by other ops (whose own step
/// takes the gate's gradient on) and a frozen one.
#[test]
fn the_weight_gates_give_every_weight_its_gradient() {
    let _turn = CPU.lock().unwrap_or_else(|e| e.into_inner());
    type Conv = fn(Tensor<4>, Tensor<4>, Option<Tensor<1>>, ConvOptions<2>) -> Tensor<4>;
    let run = |conv: Conv| {
        let device = Device::flex().autodiff();
        let options = ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
        let x = ramp([2, 3, 9, 8], &device).require_grad();
        let shared = weight([3, 3, 3, 3], &device).require_grad();
        let root = weight([3, 3, 3, 3], &device).flip([0]).require_grad();
        let frozen = weight([3, 3, 3, 3], &device).flip([1]);
        let y = conv(x.clone(), shared.clone(), None, options.clone());
        let y = conv(y, root.clone() * 1.5 - 0.1, None, options.clone());
        let y = conv(y, shared.clone(), None, options.clone());
        let y = conv(y, frozen, None, options);
        let r = ramp(y.dims(), &device) + 0.25;
        let grads = (y.clone() * r).sum().backward();
        [
            values(y),
            values(x.grad(&grads).unwrap()),
            values(shared.grad(&grads).unwrap()),
            values(root.grad(&grads).unwrap()),
        ]
    };
    let (ours, burns) = (run(conv2d), run(burn_conv2d));
    for ((got, expected), what) in ours.iter().zip(&burns).zip(["y", "dx", "dshared", "droot"]) {
        assert_close(got, expected, &format!("{what} through the gates"));
    }
}
