//! The CPU's fused element-wise ops (`f3g_nets::fused`) against the tensor-op formulation other
//! devices run (`fused::portable`): outputs and gradients within float tolerance for the shapes
//! and paddings the networks use and for edge sizes; each hand-written backward against central
//! differences.

mod central_differences;
mod common;

use burn::tensor::{Device, Tensor, TensorData};
use central_differences::values;
use common::ramp;
use f3g_nets::fused::{self, portable};
use f3g_nets::layers::{LRELU_GAIN, LRELU_SLOPE};

fn assert_close(got: &[f32], expected: &[f32], what: &str) {
    assert_eq!(got.len(), expected.len(), "{what}: lengths");
    for (i, (g, e)) in got.iter().zip(expected).enumerate() {
        assert!(
            (g - e).abs() <= 1e-5 * (1.0 + e.abs()),
            "{what}[{i}]: {g}, the tensor ops give {e}"
        );
    }
}

/// Weights for `sum(op(x) · r)`, so that every output has its own gradient.
fn weights(shape: [usize; 4], device: &Device) -> Tensor<4> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|i| ((i * 31) % 13) as f32 - 6.0).collect();
    Tensor::from_data(TensorData::new(v, shape), device)
}

/// Output and input gradient of `op` on `x`.
fn output_and_grad(op: &dyn Fn(Tensor<4>) -> Tensor<4>, x: Tensor<4>) -> [Vec<f32>; 2] {
    let x = x.require_grad();
    let y = op(x.clone());
    let r = weights(y.dims(), &x.device());
    let grads = (y.clone() * r).sum().backward();
    [values(y), values(x.grad(&grads).unwrap())]
}

fn bias(channels: usize, device: &Device) -> Tensor<1> {
    let v = (0..channels).map(|c| 0.3 - 0.17 * c as f32).collect();
    Tensor::from_data(TensorData::new(v, [channels]), device)
}

#[test]
fn bias_leaky_relu_matches_the_tensor_ops() {
    let device = Device::flex().autodiff();
    // StyleGAN2's activation and a convolution's bias + ReLU, of the input as it is and scaled
    // (an equalised convolution's weight scale, 1/√(9·32)).
    for (slope, gain) in [(LRELU_SLOPE, LRELU_GAIN), (0.0, 1.0)] {
        for input_scale in [1.0, 0.059] {
            for shape in [[1, 3, 5, 7], [2, 4, 1, 1], [2, 32, 16, 16]] {
                let run = |op: &dyn Fn(Tensor<4>, Tensor<1>) -> Tensor<4>| {
                    let b = bias(shape[1], &device).require_grad();
                    let x = ramp(shape, &device).require_grad();
                    let y = op(x.clone(), b.clone());
                    let grads = (y.clone() * weights(shape, &device)).sum().backward();
                    [
                        values(y),
                        values(x.grad(&grads).unwrap()),
                        values(b.grad(&grads).unwrap()),
                    ]
                };
                let ours =
                    run(&|x, b| fused::scaled_bias_leaky_relu(x, input_scale, b, slope, gain));
                let theirs =
                    run(&|x, b| portable::bias_leaky_relu(x * input_scale, b, slope, gain));
                for ((got, expected), what) in ours.iter().zip(&theirs).zip(["y", "dx", "db"]) {
                    let what = format!(
                        "{what} of {shape:?}, input scale {input_scale}, slope {slope}, gain {gain}"
                    );
                    assert_close(got, expected, &what);
                }
            }
        }
    }
}

/// LPIPS normalises its ReLU features by `√(Σ_c x²)`, whose gradient is infinite where every
/// channel is zero: ReLU's backward must stop it there (Burn's and PyTorch's select; a product
/// with the slope 0 would give NaN and, one day, NaN weights).
#[test]
fn relus_backward_does_not_pass_an_infinite_gradient() {
    let device = Device::flex().autodiff();
    let shape = [1, 3, 4, 5];
    let run = |op: fn(Tensor<4>, Tensor<1>, f64, f32) -> Tensor<4>| {
        let x = ramp(shape, &device).require_grad();
        let y = op(x.clone(), Tensor::zeros([3], &device), 0.0, 1.0);
        let grads = y.sqrt().sum().backward();
        values(x.grad(&grads).unwrap())
    };
    let (ours, theirs) = (run(fused::bias_leaky_relu), run(portable::bias_leaky_relu));
    let x = values(ramp(shape, &device));
    assert!(x.iter().any(|&v| v < 0.0), "the ramp has values ReLU cuts");
    for ((&v, g), e) in x.iter().zip(&ours).zip(&theirs) {
        assert!(
            g.is_finite() && *g == *e,
            "dx at {v}: {g}, the tensor ops give {e}"
        );
        assert_eq!(v <= 0.0, *g == 0.0, "dx at {v}: {g}");
    }
}

#[test]
fn upsample2_matches_the_tensor_ops() {
    let device = Device::flex().autodiff();
    for shape in [[1, 1, 1, 1], [2, 3, 1, 4], [1, 2, 5, 3], [1, 12, 16, 16]] {
        let ours = output_and_grad(&fused::upsample2, ramp(shape, &device));
        let theirs = output_and_grad(&portable::upsample2, ramp(shape, &device));
        assert_close(&ours[0], &theirs[0], &format!("y of {shape:?}"));
        assert_close(&ours[1], &theirs[1], &format!("dx of {shape:?}"));
    }
}

#[test]
fn downsample2_matches_the_tensor_ops() {
    let device = Device::flex().autodiff();
    for shape in [[1, 1, 2, 2], [2, 3, 5, 7], [1, 2, 3, 2], [1, 12, 16, 16]] {
        let ours = output_and_grad(&fused::downsample2, ramp(shape, &device));
        let theirs = output_and_grad(&portable::downsample2, ramp(shape, &device));
        assert_close(&ours[0], &theirs[0], &format!("y of {shape:?}"));
        assert_close(&ours[1], &theirs[1], &format!("dx of {shape:?}"));
    }
}

#[test]
fn blur_matches_the_tensor_ops_for_every_padding() {
    let device = Device::flex().autodiff();
    for shape in [[1, 2, 8, 8], [2, 3, 5, 9], [1, 1, 1, 2]] {
        for (before, after) in [(2, 2), (2, 1), (1, 2), (3, 0), (0, 3), (3, 3), (1, 1)] {
            if shape[2] + before + after < 4 || shape[3] + before + after < 4 {
                continue;
            }
            let ours = output_and_grad(&|x| fused::blur(x, before, after), ramp(shape, &device));
            let theirs =
                output_and_grad(&|x| portable::blur(x, before, after), ramp(shape, &device));
            let what = format!("{shape:?} padded ({before}, {after})");
            assert_close(&ours[0], &theirs[0], &format!("y of {what}"));
            assert_close(&ours[1], &theirs[1], &format!("dx of {what}"));
        }
    }
}

#[test]
fn haar_and_its_inverse_match_the_tensor_ops() {
    let device = Device::flex().autodiff();
    for shape in [[1, 1, 2, 2], [2, 3, 4, 6], [1, 3, 16, 16]] {
        let ours = output_and_grad(&fused::haar, ramp(shape, &device));
        let theirs = output_and_grad(&portable::haar, ramp(shape, &device));
        assert_close(&ours[0], &theirs[0], &format!("haar y of {shape:?}"));
        assert_close(&ours[1], &theirs[1], &format!("haar dx of {shape:?}"));
        let bands = [shape[0], 4 * shape[1], shape[2] / 2, shape[3] / 2];
        let ours = output_and_grad(&fused::inverse_haar, ramp(bands, &device));
        let theirs = output_and_grad(&portable::inverse_haar, ramp(bands, &device));
        assert_close(&ours[0], &theirs[0], &format!("inverse y of {bands:?}"));
        assert_close(&ours[1], &theirs[1], &format!("inverse dx of {bands:?}"));
    }
}

#[test]
fn every_backward_matches_central_differences() {
    let device = Device::flex().autodiff();
    // A loss that is not linear in the output, so that the gradient depends on where it is taken.
    let squared = |y: Tensor<4>| {
        let r = weights(y.dims(), &y.device()) * 0.1 + 0.05;
        (y.clone() * y * r).sum()
    };
    let x0 = ramp([2, 3, 4, 5], &device);
    // Pre-activations stay away from leaky ReLU's kink at zero: ramp values are odd multiples
    // of 1/194 and the bias whole multiples of 1/97, so every x + b is at least 1/194 from
    // zero, beyond the step.
    let kink_free = 4e-3;
    let b = Tensor::<1>::from_data(
        TensorData::new(vec![29.0 / 97.0, 0.0, -13.0 / 97.0], [3]),
        &device,
    );
    central_differences::check(
        &|x| {
            squared(fused::bias_leaky_relu(
                x,
                b.clone(),
                LRELU_SLOPE,
                LRELU_GAIN,
            ))
        },
        x0.clone(),
        kink_free,
        "dx of bias_leaky_relu",
    );
    let bias_loss = |b: Tensor<4>| {
        squared(fused::bias_leaky_relu(
            x0.clone(),
            b.reshape([3]),
            LRELU_SLOPE,
            LRELU_GAIN,
        ))
    };
    central_differences::check(
        &bias_loss,
        b.clone().reshape([1, 3, 1, 1]),
        kink_free,
        "db of bias_leaky_relu",
    );
    // With the input scaled by 2 the kink is as far from every scaled x + b.
    let scaled = |x: Tensor<4>, b: Tensor<1>| {
        squared(fused::scaled_bias_leaky_relu(
            x,
            2.0,
            b,
            LRELU_SLOPE,
            LRELU_GAIN,
        ))
    };
    central_differences::check(
        &|x| scaled(x, b.clone() * 2.0),
        x0.clone(),
        kink_free / 2.0,
        "dx of scaled_bias_leaky_relu",
    );
    central_differences::check(
        &|b: Tensor<4>| scaled(x0.clone(), b.reshape([3]) * 2.0),
        b.reshape([1, 3, 1, 1]),
        kink_free,
        "db of scaled_bias_leaky_relu",
    );
    central_differences::check(
        &|x| squared(fused::upsample2(x)),
        x0.clone(),
        1e-2,
        "upsample2",
    );
    central_differences::check(
        &|x| squared(fused::downsample2(x)),
        x0.clone(),
        1e-2,
        "downsample2",
    );
    let even = ramp([2, 3, 4, 6], &device);
    central_differences::check(&|x| squared(fused::haar(x)), even, 1e-2, "haar");
    let bands = ramp([1, 8, 2, 3], &device);
    central_differences::check(
        &|x| squared(fused::inverse_haar(x)),
        bands,
        1e-2,
        "inverse_haar",
    );
    // Bilinear resizing to sizes neither double nor half (its own op): enlarging and shrinking.
    for (height, width) in [(7, 9), (3, 2)] {
        central_differences::check(
            &|x| squared(f3g_nets::resample::resize(x, height, width)),
            x0.clone(),
            1e-2,
            &format!("resize to {height} × {width}"),
        );
    }
    for (before, after) in [(2, 2), (3, 0), (1, 3)] {
        central_differences::check(
            &|x| squared(fused::blur(x, before, after)),
            x0.clone(),
            1e-2,
            &format!("blur ({before}, {after})"),
        );
    }
}

/// A modulated weight's op: weight, the network's styles, where the layer's begin, scale,
/// whether to demodulate.
type Modulation = fn(Tensor<4>, Tensor<1>, usize, f32, bool) -> Tensor<4>;

/// The modulated weight's output and the gradients of weight and styles of `sum(op(w, s) · r)`,
/// the layer's styles from `first` on in a vector with `more` after them.
fn modulated(
    op: Modulation,
    shape: [usize; 4],
    [first, more]: [usize; 2],
    demodulate: bool,
) -> [Vec<f32>; 3] {
    let device = Device::flex().autodiff();
    let weight = ramp(shape, &device).require_grad();
    let styles = bias(first + shape[1] + more, &device).require_grad();
    let y = op(weight.clone(), styles.clone(), first, 0.37, demodulate);
    let grads = (y.clone() * weights(shape, &device)).sum().backward();
    [
        values(y),
        values(weight.grad(&grads).unwrap()),
        values(styles.grad(&grads).unwrap()),
    ]
}

#[test]
fn modulation_matches_the_tensor_ops() {
    for shape in [[4, 3, 3, 3], [12, 8, 1, 1], [1, 1, 1, 1], [3, 300, 3, 3]] {
        for range in [[0, 0], [5, 2]] {
            for demodulate in [true, false] {
                let ours = modulated(fused::modulate, shape, range, demodulate);
                let theirs = modulated(portable::modulate, shape, range, demodulate);
                for ((got, expected), what) in ours.iter().zip(&theirs).zip(["y", "dw", "ds"]) {
                    assert_close(
                        got,
                        expected,
                        &format!("{what} of {shape:?}, styles {range:?} ({demodulate})"),
                    );
                }
            }
        }
    }
}

/// A network's layers modulated together ([`fused::modulate_all`]: one node per layer and a
/// gate computing their gradients together) against each layer through the tensor ops: a leaf
/// weight (a parameter, batched), a weight made by another op (its gradient computed by its
/// own node, the styles' share through the gate), an untracked weight (the styles' gradient
/// only), and the styles detached (each layer its own node).
#[test]
fn modulating_layers_together_matches_one_at_a_time() {
    let device = Device::flex().autodiff();
    let shapes = [[4, 3, 3, 3], [12, 8, 1, 1], [5, 2, 3, 3]];
    for styles_tracked in [true, false] {
        let run = |together: bool| {
            let styles = bias(2 + 3 + 8 + 2 + 4, &device);
            let styles = if styles_tracked {
                styles.require_grad()
            } else {
                styles
            };
            let leaf = ramp(shapes[0], &device).require_grad();
            let source = ramp(shapes[1], &device).require_grad();
            let layers = [
                (leaf.clone(), 2, true),
                (source.clone() * 1.5 - 0.25, 5, false),
                (ramp(shapes[2], &device), 13, true),
            ];
            let ys: Vec<Tensor<4>> = if together {
                let modulations = layers
                    .iter()
                    .map(|(weight, first, demodulate)| fused::Modulation {
                        weight: weight.clone(),
                        first: *first,
                        scale: 0.37,
                        demodulate: *demodulate,
                    })
                    .collect();
                fused::modulate_all(modulations, styles.clone())
            } else {
                layers
                    .iter()
                    .map(|(weight, first, demodulate)| {
                        portable::modulate(
                            weight.clone(),
                            styles.clone(),
                            *first,
                            0.37,
                            *demodulate,
                        )
                    })
                    .collect()
            };
            let loss = ys
                .iter()
                .map(|y| (y.clone() * weights(y.dims(), &device)).sum())
                .reduce(|a, b| a + b)
                .unwrap();
            let grads = loss.backward();
            let mut all: Vec<Vec<f32>> = ys.into_iter().map(values).collect();
            all.push(values(leaf.grad(&grads).unwrap()));
            all.push(values(source.grad(&grads).unwrap()));
            if styles_tracked {
                all.push(values(styles.grad(&grads).unwrap()));
            }
            all
        };
        let (ours, theirs) = (run(true), run(false));
        assert_eq!(ours.len(), theirs.len());
        for (k, (got, expected)) in ours.iter().zip(&theirs).enumerate() {
            assert_close(
                got,
                expected,
                &format!("value set {k} (styles tracked: {styles_tracked})"),
            );
        }
    }
}

#[test]
fn the_modulations_backward_matches_central_differences() {
    let device = Device::flex().autodiff();
    let squared = |y: Tensor<4>| {
        let r = weights(y.dims(), &y.device()) * 0.1 + 0.05;
        (y.clone() * y * r).sum()
    };
    let weight = ramp([3, 4, 3, 3], &device);
    // The layer's four styles are the second to fifth of six.
    let styles = bias(6, &device);
    for demodulate in [true, false] {
        central_differences::check(
            &|w| squared(fused::modulate(w, styles.clone(), 1, 0.37, demodulate)),
            weight.clone(),
            1e-2,
            &format!("weight gradient ({demodulate})"),
        );
        central_differences::check(
            &|s| {
                squared(fused::modulate(
                    weight.clone(),
                    s.reshape([6]),
                    1,
                    0.37,
                    demodulate,
                ))
            },
            styles.clone().reshape([1, 6, 1, 1]),
            1e-2,
            &format!("style gradient ({demodulate})"),
        );
    }
}

/// A `[rows, columns]` input of distinct values in `[-0.5, 0.5)`.
fn matrix(rows: usize, columns: usize, device: &Device) -> Tensor<2> {
    ramp([1, 1, rows, columns], device).reshape([rows, columns])
}

/// The scalars of a linear layer: an equalised modulation (no activation), the mapping
/// network's layers (StyleGAN2's leaky ReLU) and a ReLU.
const LINEAR_SCALES: [fused::LinearScales; 3] = [
    fused::LinearScales {
        weight_scale: 0.125,
        bias_scale: 1.0,
        slope: 1.0,
        gain: 1.0,
    },
    fused::LinearScales {
        weight_scale: 0.03,
        bias_scale: 0.01,
        slope: 0.2,
        gain: std::f32::consts::SQRT_2,
    },
    fused::LinearScales {
        weight_scale: 0.7,
        bias_scale: 2.0,
        slope: 0.0,
        gain: 1.5,
    },
];

/// The output and the gradients of `x`, `weight` and `bias` of `sum(op(x, w, b) · r)`.
fn linear_run(
    op: fn(Tensor<2>, Tensor<2>, Tensor<1>, fused::LinearScales) -> Tensor<2>,
    [batch, inputs, outputs]: [usize; 3],
    scales: fused::LinearScales,
) -> [Vec<f32>; 4] {
    let device = Device::flex().autodiff();
    let x = (matrix(batch, inputs, &device) * 3.0).require_grad();
    let weight = matrix(outputs, inputs, &device).flip([1]).require_grad();
    let bias = bias(outputs, &device).require_grad();
    let y = op(x.clone(), weight.clone(), bias.clone(), scales);
    let r = weights([1, 1, batch, outputs], &device).reshape([batch, outputs]);
    let grads = (y.clone() * r).sum().backward();
    [
        values(y),
        values(x.grad(&grads).unwrap()),
        values(weight.grad(&grads).unwrap()),
        values(bias.grad(&grads).unwrap()),
    ]
}

#[test]
fn linear_matches_the_tensor_ops() {
    // A style vector through a modulation of the paper's width, a discriminator head's few
    // rows, and the smallest layer.
    for dims in [[1, 512, 64], [3, 17, 4], [2, 1, 1]] {
        for scales in LINEAR_SCALES {
            let ours = linear_run(fused::scaled_linear, dims, scales);
            let theirs = linear_run(portable::scaled_linear, dims, scales);
            for ((got, expected), what) in ours.iter().zip(&theirs).zip(["y", "dx", "dw", "db"]) {
                assert_close(got, expected, &format!("{what} of {dims:?}, {scales:?}"));
            }
        }
    }
}

#[test]
fn the_linear_layers_backward_matches_central_differences() {
    let device = Device::flex().autodiff();
    let squared = |y: Tensor<2>| {
        let [rows, columns] = y.dims();
        let r = weights([1, 1, rows, columns], &y.device()).reshape([rows, columns]) * 0.1 + 0.05;
        (y.clone() * y * r).sum()
    };
    let (batch, inputs, outputs) = (2, 5, 3);
    let x = matrix(batch, inputs, &device) * 3.0;
    let weight = matrix(outputs, inputs, &device).flip([1]);
    let b = bias(outputs, &device);
    // The affine map and StyleGAN2's leaky ReLU; no pre-activation lies within the step's
    // reach of the kink (checked below), so the differences see one slope.
    for scales in &LINEAR_SCALES[..2] {
        let pre = portable::scaled_linear(
            x.clone(),
            weight.clone(),
            b.clone(),
            fused::LinearScales::affine(scales.weight_scale, scales.bias_scale),
        );
        let nearest = values(pre).iter().fold(f32::MAX, |m, v| m.min(v.abs()));
        let eps = 1e-3;
        // A step moves a pre-activation by at most eps times its largest factor (|x| ≤ 1.5,
        // |w| ≤ 0.5, one bias).
        let reach = eps * (scales.weight_scale * 1.5).max(scales.bias_scale);
        assert!(
            nearest > 10.0 * reach,
            "a pre-activation {nearest} near the kink"
        );
        let what = |name: &str| format!("{name} of linear ({scales:?})");
        central_differences::check(
            &|x4| {
                let x = x4.reshape([batch, inputs]);
                squared(fused::scaled_linear(x, weight.clone(), b.clone(), *scales))
            },
            x.clone().reshape([1, 1, batch, inputs]),
            eps,
            &what("dx"),
        );
        central_differences::check(
            &|w4| {
                let w = w4.reshape([outputs, inputs]);
                squared(fused::scaled_linear(x.clone(), w, b.clone(), *scales))
            },
            weight.clone().reshape([1, 1, outputs, inputs]),
            eps,
            &what("dw"),
        );
        central_differences::check(
            &|b4| {
                let b = b4.reshape([outputs]);
                squared(fused::scaled_linear(x.clone(), weight.clone(), b, *scales))
            },
            b.clone().reshape([1, 1, 1, outputs]),
            eps,
            &what("db"),
        );
    }
}

#[test]
fn scale_weight_matches_the_tensor_ops_and_central_differences() {
    let device = Device::flex().autodiff();
    let shape = [4, 3, 3, 3];
    let run = |op: &dyn Fn(Tensor<4>) -> Tensor<4>| {
        let w = ramp(shape, &device).require_grad();
        let y = op(w.clone());
        let grads = (y.clone() * weights(shape, &device)).sum().backward();
        [values(y), values(w.grad(&grads).unwrap())]
    };
    let ours = run(&|w| fused::scale_weight(w, 0.19));
    let theirs = run(&|w| w * 0.19);
    for ((got, expected), what) in ours.iter().zip(&theirs).zip(["y", "dw"]) {
        assert_close(got, expected, &format!("{what} of scale_weight"));
    }
    let squared = |y: Tensor<4>| {
        let r = weights(y.dims(), &y.device()) * 0.1 + 0.05;
        (y.clone() * y * r).sum()
    };
    central_differences::check(
        &|w| squared(fused::scale_weight(w, 0.19)),
        ramp(shape, &device),
        1e-2,
        "dw of scale_weight",
    );
}

/// `fused::noisy_bias_leaky_relu`'s signature: input, noise, strength, bias, slope, gain.
type NoisyOp = fn(Tensor<4>, Tensor<4>, Tensor<1>, Tensor<1>, f64, f32) -> Tensor<4>;

/// The noise injection and activation of a styled convolution as one op: output and the
/// gradients of input, noise, strength and bias against Burn's ops, and central differences.
#[test]
fn the_noisy_activation_matches_the_tensor_ops_and_central_differences() {
    let device = Device::flex().autodiff();
    let shape = [2, 3, 4, 5];
    let noise = || ramp([1, 1, 4, 5], &device).flip([3]) * 2.0;
    let strength = || Tensor::<1>::from_data(TensorData::new(vec![0.37f32], [1]), &device);
    for (slope, gain) in [(LRELU_SLOPE, LRELU_GAIN), (0.0, 1.0)] {
        let run = |op: NoisyOp| {
            let x = ramp(shape, &device).require_grad();
            let (n, s) = (noise().require_grad(), strength().require_grad());
            let b = bias(3, &device).require_grad();
            let y = op(x.clone(), n.clone(), s.clone(), b.clone(), slope, gain);
            let grads = (y.clone() * weights(shape, &device)).sum().backward();
            [
                values(y),
                values(x.grad(&grads).unwrap()),
                values(n.grad(&grads).unwrap()),
                values(s.grad(&grads).unwrap()),
                values(b.grad(&grads).unwrap()),
            ]
        };
        let ours = run(fused::noisy_bias_leaky_relu);
        let theirs = run(portable::noisy_bias_leaky_relu);
        let names = ["y", "dx", "dnoise", "dstrength", "dbias"];
        for ((got, expected), what) in ours.iter().zip(&theirs).zip(names) {
            assert_close(
                got,
                expected,
                &format!("{what} of the noisy activation ({slope})"),
            );
        }
    }
    // Away from the kink: the strength's small step moves a pre-activation by at most
    // 2e-3 · max|noise| ≈ 2e-3, and none lies that close to zero (checked).
    let squared = |y: Tensor<4>| {
        let r = weights(y.dims(), &y.device()) * 0.1 + 0.05;
        (y.clone() * y * r).sum()
    };
    // The offset keeps every pre-activation at least 0.013 from zero.
    let x = ramp(shape, &device) + 0.145;
    let pre = x.clone() + noise() * 0.37 + bias(3, &device).reshape([1, 3, 1, 1]);
    let nearest = values(pre).iter().fold(f32::MAX, |m, v| m.min(v.abs()));
    assert!(nearest > 4e-3, "a pre-activation {nearest} near the kink");
    central_differences::check(
        &|s4| {
            let s = s4.reshape([1]);
            squared(fused::noisy_bias_leaky_relu(
                x.clone(),
                noise(),
                s,
                bias(3, &device),
                LRELU_SLOPE,
                LRELU_GAIN,
            ))
        },
        strength().reshape([1, 1, 1, 1]),
        2e-3,
        "dstrength of the noisy activation",
    );
}

/// The activations' parameters get their gradients from gate nodes that run after every
/// activation of the pass (`fused/autodiff.rs`): a chain of four activations against Burn's
/// ops, with a bias shared by two of them, a bias and a strength made by other ops (whose own
/// steps take the gate's gradient on), a strength left untracked, and an untracked bias.
#[test]
fn the_activations_gates_give_every_parameter_its_gradient() {
    let device = Device::flex().autodiff();
    let shape = [2, 3, 4, 5];
    type Plain = fn(Tensor<4>, Tensor<1>, f64, f32) -> Tensor<4>;
    let run = |noisy: NoisyOp, plain: Plain| {
        let x = ramp(shape, &device).require_grad();
        let noise = ramp([1, 1, 4, 5], &device).flip([3]) * 2.0;
        let shared = bias(3, &device).require_grad();
        let root = bias(3, &device).flip([0]).require_grad();
        let strength =
            Tensor::<1>::from_data(TensorData::new(vec![0.37f32], [1]), &device).require_grad();
        let y = noisy(
            x.clone(),
            noise.clone(),
            strength.clone(),
            shared.clone(),
            LRELU_SLOPE,
            LRELU_GAIN,
        );
        let y = plain(y, root.clone() * 1.5 - 0.1, LRELU_SLOPE, LRELU_GAIN);
        let y = noisy(
            y,
            noise.clone(),
            strength.clone() * 2.0,
            shared.clone(),
            0.0,
            1.0,
        );
        let y = noisy(y, noise, strength.clone().detach(), root.clone(), 0.2, 1.0);
        let y = plain(y, bias(3, &device) * 0.5, LRELU_SLOPE, LRELU_GAIN);
        let grads = (y.clone() * weights(shape, &device)).sum().backward();
        [
            values(y),
            values(x.grad(&grads).unwrap()),
            values(shared.grad(&grads).unwrap()),
            values(root.grad(&grads).unwrap()),
            values(strength.grad(&grads).unwrap()),
        ]
    };
    let ours = run(fused::noisy_bias_leaky_relu, fused::bias_leaky_relu);
    let theirs = run(portable::noisy_bias_leaky_relu, portable::bias_leaky_relu);
    let names = ["y", "dx", "dshared", "droot", "dstrength"];
    for ((got, expected), what) in ours.iter().zip(&theirs).zip(names) {
        assert_close(got, expected, &format!("{what} through the gates"));
    }
}
