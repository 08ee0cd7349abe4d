//! `impl FusedBackend for Flex`: each op one loop over the `[B·C]` planes of row-major f32 data,
//! planes in parallel, in f32 (the networks' only float type); LPIPS's comparison walks the
//! channels over blocks of pixels, blocks in parallel, and a ToRGB's output composes the
//! resampling ops.

use std::borrow::Cow;
use std::cell::RefCell;
use std::ops::Range;

use burn::backend::Flex;
use burn::backend::TensorMetadata;
use burn::backend::ops::{FloatTensorOps, ModuleOps};
use burn::backend::tensor::FloatTensor;
use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
use burn::tensor::{FloatDType, Shape};
use rayon::prelude::*;

use super::{
    DEMODULATION_EPSILON, FusedBackend, LPIPS_EPSILON, LinearScales, blurred_side,
    separate_bias_leaky_relu_grads,
};
use crate::host::{from_values, host_f32};

/// The blur's taps.
const TAPS: [f32; 4] = [1.0 / 8.0, 3.0 / 8.0, 3.0 / 8.0, 1.0 / 8.0];

thread_local! {
    /// The styles' gradient of the layers `modulate_grad_queue` saw on this thread since the
    /// last `modulate_grad_launch_queued`.
    static STYLE_GRADIENT: RefCell<Option<FloatTensor<Flex>>> = const { RefCell::new(None) };
}

impl FusedBackend for Flex {
    fn bias_leaky_relu(
        x: FloatTensor<Self>,
        input_scale: f32,
        bias: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self> {
        let shape = dims(&x);
        let plane = shape[2] * shape[3];
        let (bias, channels) = (host_f32(&bias), shape[1]);
        assert_eq!(bias.len(), channels, "one bias per channel");
        let mut out = host_f32(&x).into_owned();
        out.par_chunks_mut(plane.max(1))
            .enumerate()
            .for_each(|(index, values)| {
                let b = bias[index % channels];
                for v in values {
                    let pre = input_scale * *v + b;
                    *v = gain * if pre > 0.0 { pre } else { slope * pre };
                }
            });
        from_values(out, shape.to_vec())
    }

    fn bias_leaky_relu_grad(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self> {
        let shape = dims(&grad);
        let output = host_f32(&output);
        let mut dx = host_f32(&grad).into_owned();
        assert_eq!(output.len(), dx.len(), "output and gradient shapes");
        dx.par_chunks_mut(1 << 14)
            .zip(output.par_chunks(1 << 14))
            .for_each(|(dx, y)| {
                for (d, &y) in dx.iter_mut().zip(y) {
                    *d = leaky_relu_grad(*d, y, slope, gain);
                }
            });
        from_values(dx, shape.to_vec())
    }

    fn noisy_bias_leaky_relu(
        x: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        strength: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self> {
        let shape = dims(&x);
        let plane = shape[2] * shape[3];
        let (noise, strength) = (host_f32(&noise), host_f32(&strength));
        assert_eq!(noise.len(), plane, "one noise value per pixel");
        let strength = strength[0];
        let (bias, channels) = (host_f32(&bias), shape[1]);
        assert_eq!(bias.len(), channels, "one bias per channel");
        let mut out = host_f32(&x).into_owned();
        out.par_chunks_mut(plane.max(1))
            .enumerate()
            .for_each(|(index, values)| {
                let b = bias[index % channels];
                for (v, &n) in values.iter_mut().zip(noise.iter()) {
                    let pre = *v + n * strength + b;
                    *v = gain * if pre > 0.0 { pre } else { slope * pre };
                }
            });
        from_values(out, shape.to_vec())
    }

    fn noise_strength_grad(grad: FloatTensor<Self>, noise: FloatTensor<Self>) -> FloatTensor<Self> {
        let [_, _, height, width] = dims(&grad);
        let plane = height * width;
        let (grad, noise) = (host_f32(&grad), host_f32(&noise));
        assert_eq!(noise.len(), plane, "one noise value per pixel");
        let sum: f64 = if plane == 0 {
            0.0
        } else {
            grad.par_chunks(plane)
                .map(|g| {
                    g.iter()
                        .zip(noise.iter())
                        .map(|(&g, &n)| f64::from(g) * f64::from(n))
                        .sum::<f64>()
                })
                .sum()
        };
        from_values(vec![sum as f32], vec![1])
    }

    fn bias_leaky_relu_backward_queue(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        input_scale: f32,
        slope: f32,
        gain: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        separate_bias_leaky_relu_grads::<Self>(output, grad, input_scale, slope, gain)
    }

    fn noisy_bias_leaky_relu_backward_queue(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let (dx, d_bias) = separate_bias_leaky_relu_grads::<Self>(output, grad, 1.0, slope, gain);
        let d_strength = Self::noise_strength_grad(dx.clone(), noise);
        (dx, d_bias, d_strength)
    }

    /// Nothing is queued on the CPU: the gradients are computed at once.
    fn bias_grads_launch_queued(anchor: FloatTensor<Self>) -> FloatTensor<Self> {
        anchor
    }

    fn channel_sum(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, height, width] = dims(&x);
        let plane = height * width;
        let values = host_f32(&x);
        let per_plane: Vec<f64> = if plane == 0 {
            vec![0.0; batch * channels]
        } else {
            values
                .par_chunks(plane)
                .map(|p| p.iter().map(|&v| f64::from(v)).sum())
                .collect()
        };
        let sums = (0..channels)
            .map(|c| (0..batch).map(|b| per_plane[b * channels + c]).sum::<f64>() as f32)
            .collect();
        from_values(sums, vec![channels])
    }

    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, height, width] = dims(&x);
        let x = host_f32(&x);
        let mut out = vec![0.0f32; 4 * x.len()];
        if height * width > 0 {
            out.par_chunks_mut(4 * height * width)
                .zip(x.par_chunks(height * width))
                .for_each(|(out, plane)| {
                    let mut rows = vec![0.0f32; 2 * plane.len()];
                    upsample_axis(plane, height, width, 1, &mut rows);
                    upsample_axis(&rows, 1, height, 2 * width, out);
                });
        }
        from_values(out, vec![batch, channels, 2 * height, 2 * width])
    }

    fn upsample2_grad(grad: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, height2, width2] = dims(&grad);
        let (height, width) = (height2 / 2, width2 / 2);
        let grad = host_f32(&grad);
        let mut dx = vec![0.0f32; grad.len() / 4];
        if height * width > 0 {
            dx.par_chunks_mut(height * width)
                .zip(grad.par_chunks(4 * height * width))
                .for_each(|(dx, plane)| {
                    let mut rows = vec![0.0f32; 2 * dx.len()];
                    upsample_axis_adjoint(plane, 1, height, 2 * width, &mut rows);
                    upsample_axis_adjoint(&rows, height, width, 1, dx);
                });
        }
        from_values(dx, vec![batch, channels, height, width])
    }

    fn downsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, height, width] = dims(&x);
        let (h, w) = (height / 2, width / 2);
        let x = host_f32(&x);
        let mut out = vec![0.0f32; batch * channels * h * w];
        if h * w > 0 {
            out.par_chunks_mut(h * w)
                .zip(x.par_chunks(height * width))
                .for_each(|(out, plane)| {
                    for (i, row) in out.chunks_mut(w).enumerate() {
                        let (top, bottom) =
                            (&plane[2 * i * width..], &plane[(2 * i + 1) * width..]);
                        for (j, o) in row.iter_mut().enumerate() {
                            let (p, q) = (top[2 * j], top[2 * j + 1]);
                            let (r, s) = (bottom[2 * j], bottom[2 * j + 1]);
                            *o = 0.25 * (p + q + r + s);
                        }
                    }
                });
        }
        from_values(out, vec![batch, channels, h, w])
    }

    fn downsample2_grad(grad: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self> {
        let [batch, channels, h, w] = dims(&grad);
        assert_eq!(
            [h, w],
            [height / 2, width / 2],
            "the gradient of a 2 × 2 mean"
        );
        let grad = host_f32(&grad);
        let mut dx = vec![0.0f32; batch * channels * height * width];
        if h * w > 0 {
            dx.par_chunks_mut(height * width)
                .zip(grad.par_chunks(h * w))
                .for_each(|(dx, plane)| {
                    for (y, row) in dx.chunks_mut(width).take(2 * h).enumerate() {
                        for (x, d) in row[..2 * w].iter_mut().enumerate() {
                            *d = 0.25 * plane[(y / 2) * w + x / 2];
                        }
                    }
                });
        }
        from_values(dx, vec![batch, channels, height, width])
    }

    /// Burn's bilinear interpolation, as the CPU resized before this op existed.
    fn resize(x: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self> {
        <Self as ModuleOps<Self>>::interpolate(x, [height, width], bilinear())
    }

    fn resize_grad(grad: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self> {
        let [batch, channels, out_height, out_width] = dims(&grad);
        // Burn's backward reads only the input's shape.
        let input = Self::float_empty(
            Shape::new([batch, channels, height, width]),
            &grad.device(),
            FloatDType::F32,
        );
        <Self as ModuleOps<Self>>::interpolate_backward(
            input,
            grad,
            [out_height, out_width],
            bilinear(),
        )
    }

    fn blur(x: FloatTensor<Self>, before: usize, after: usize) -> FloatTensor<Self> {
        let [batch, channels, height, width] = dims(&x);
        assert!(before <= 3 && after <= 3, "blur padding at most 3");
        let grown = |n: usize| blurred_side(n, before, after);
        let (out_h, out_w) = (grown(height), grown(width));
        let x = host_f32(&x);
        let mut out = vec![0.0f32; batch * channels * out_h * out_w];
        if out_h * out_w > 0 {
            out.par_chunks_mut(out_h * out_w)
                .zip(x.par_chunks(height * width))
                .for_each(|(out, plane)| {
                    let mut rows = vec![0.0f32; height * out_w];
                    blur_axis(plane, height, width, 1, before, &mut rows);
                    blur_axis(&rows, 1, height, out_w, before, out);
                });
        }
        from_values(out, vec![batch, channels, out_h, out_w])
    }

    fn haar(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, height, width] = dims(&x);
        assert!(
            height % 2 == 0 && width % 2 == 0,
            "Haar analysis of even sizes"
        );
        let (h, w) = (height / 2, width / 2);
        let x = host_f32(&x);
        let mut out = vec![0.0f32; x.len()];
        if h * w > 0 {
            // One input plane → its four sub-band planes, which are contiguous.
            out.par_chunks_mut(4 * h * w)
                .zip(x.par_chunks(4 * h * w))
                .for_each(|(bands, plane)| {
                    let (ll, rest) = bands.split_at_mut(h * w);
                    let (lh, rest) = rest.split_at_mut(h * w);
                    let (hl, hh) = rest.split_at_mut(h * w);
                    for i in 0..h {
                        let (top, bottom) =
                            (&plane[2 * i * width..], &plane[(2 * i + 1) * width..]);
                        for j in 0..w {
                            let (p, q) = (top[2 * j], top[2 * j + 1]);
                            let (r, s) = (bottom[2 * j], bottom[2 * j + 1]);
                            let o = i * w + j;
                            ll[o] = 0.5 * (p + q + r + s);
                            lh[o] = 0.5 * (p + q - r - s);
                            hl[o] = 0.5 * (p - q + r - s);
                            hh[o] = 0.5 * (p - q - r + s);
                        }
                    }
                });
        }
        from_values(out, vec![batch, 4 * channels, h, w])
    }

    /// The CPU's kernels read row-major tensors: nothing to change.
    fn to_channels_last(x: FloatTensor<Self>) -> FloatTensor<Self> {
        x
    }

    fn inverse_haar(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels4, h, w] = dims(&x);
        assert!(
            channels4 % 4 == 0,
            "Haar synthesis of four sub-bands per channel"
        );
        let x = host_f32(&x);
        let mut out = vec![0.0f32; x.len()];
        if h * w > 0 {
            out.par_chunks_mut(4 * h * w)
                .zip(x.par_chunks(4 * h * w))
                .for_each(|(plane, bands)| {
                    let (ll, rest) = bands.split_at(h * w);
                    let (lh, rest) = rest.split_at(h * w);
                    let (hl, hh) = rest.split_at(h * w);
                    for i in 0..h {
                        let (top, bottom) =
                            plane[2 * i * 2 * w..(2 * i + 2) * 2 * w].split_at_mut(2 * w);
                        for j in 0..w {
                            let o = i * w + j;
                            let (a, b, c, d) = (ll[o], lh[o], hl[o], hh[o]);
                            top[2 * j] = 0.5 * (a + b + c + d);
                            top[2 * j + 1] = 0.5 * (a + b - c - d);
                            bottom[2 * j] = 0.5 * (a - b + c - d);
                            bottom[2 * j + 1] = 0.5 * (a - b - c + d);
                        }
                    }
                });
        }
        from_values(out, vec![batch, channels4 / 4, 2 * h, 2 * w])
    }

    fn to_rgb_output(
        x: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        skip: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let shape = dims(&x);
        let plane = shape[2] * shape[3];
        let carried = Self::haar(Self::upsample2(Self::inverse_haar(skip)));
        assert_eq!(
            dims(&carried),
            shape,
            "the skip carried up is the size of x"
        );
        let (bias, channels) = (host_f32(&bias), shape[1]);
        assert_eq!(bias.len(), channels, "one bias per sub-band channel");
        let x = host_f32(&x);
        let mut out = host_f32(&carried).into_owned();
        out.par_chunks_mut(plane.max(1))
            .zip(x.par_chunks(plane.max(1)))
            .enumerate()
            .for_each(|(index, (out, x))| {
                let b = bias[index % channels];
                for (o, &x) in out.iter_mut().zip(x) {
                    *o += x + b;
                }
            });
        from_values(out, shape.to_vec())
    }

    fn to_rgb_skip_grad(grad: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::haar(Self::upsample2_grad(Self::inverse_haar(grad)))
    }

    fn add_channel_bias(x: FloatTensor<Self>, bias: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::bias_leaky_relu(x, 1.0, bias, 1.0, 1.0)
    }

    fn cat_channels(first: FloatTensor<Self>, second: FloatTensor<Self>) -> FloatTensor<Self> {
        let ([batch, c1, height, width], [_, c2, ..]) = (dims(&first), dims(&second));
        let plane = height * width;
        let (first, second) = (host_f32(&first), host_f32(&second));
        let (n1, n2) = (c1 * plane, c2 * plane);
        let mut out = vec![0.0f32; first.len() + second.len()];
        if n1 + n2 > 0 {
            out.par_chunks_mut(n1 + n2)
                .enumerate()
                .for_each(|(b, item)| {
                    item[..n1].copy_from_slice(&first[b * n1..(b + 1) * n1]);
                    item[n1..].copy_from_slice(&second[b * n2..(b + 1) * n2]);
                });
        }
        from_values(out, vec![batch, c1 + c2, height, width])
    }

    fn split_channels(
        grad: FloatTensor<Self>,
        first: usize,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let [batch, channels, height, width] = dims(&grad);
        assert!(
            first <= channels,
            "the first part's channels are the gradient's"
        );
        let plane = height * width;
        let (n1, n2) = (first * plane, (channels - first) * plane);
        let grad = host_f32(&grad);
        let mut parts = (vec![0.0f32; batch * n1], vec![0.0f32; batch * n2]);
        for (b, item) in grad.chunks(n1 + n2).take(batch).enumerate() {
            parts.0[b * n1..(b + 1) * n1].copy_from_slice(&item[..n1]);
            parts.1[b * n2..(b + 1) * n2].copy_from_slice(&item[n1..]);
        }
        (
            from_values(parts.0, vec![batch, first, height, width]),
            from_values(parts.1, vec![batch, channels - first, height, width]),
        )
    }

    /// Computed now: the CPU has no launches to save.
    fn modulate_queue(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> FloatTensor<Self> {
        let shape = dims(&weight);
        let per_output = shape[1] * shape[2] * shape[3];
        let taps = shape[2] * shape[3];
        let styles = host_f32(&styles);
        let style = layer_styles(&styles, first, shape[1]);
        let mut out = host_f32(&weight).into_owned();
        out.par_chunks_mut(per_output.max(1)).for_each(|u| {
            for (j, v) in u.iter_mut().enumerate() {
                *v = *v * style[j / taps] * scale;
            }
            if demodulate {
                let d = demodulation(u);
                u.iter_mut().for_each(|v| *v *= d);
            }
        });
        from_values(out, shape.to_vec())
    }

    fn modulate_launch_queued(styles: FloatTensor<Self>) -> FloatTensor<Self> {
        styles
    }

    fn modulate_grad(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let shape = dims(&weight);
        let (c_in, taps) = (shape[1], shape[2] * shape[3]);
        let per_output = (c_in * taps).max(1);
        let (weight, styles, grad) = (host_f32(&weight), host_f32(&styles), host_f32(&grad));
        let style = layer_styles(&styles, first, c_in);
        assert_eq!(weight.len(), grad.len(), "weight and gradient shapes");
        let mut d_weight = vec![0.0f32; weight.len()];
        // Per output channel: ∂weight, and its share of ∂style.
        let style_shares: Vec<Vec<f64>> = d_weight
            .par_chunks_mut(per_output)
            .zip(weight.par_chunks(per_output))
            .zip(grad.par_chunks(per_output))
            .map(|((d_weight, weight), grad)| {
                let u: Vec<f32> = weight
                    .iter()
                    .enumerate()
                    .map(|(j, &w)| w * style[j / taps] * scale)
                    .collect();
                let (d, projection) = if demodulate {
                    let g_dot_u: f64 = grad
                        .iter()
                        .zip(&u)
                        .map(|(&g, &u)| f64::from(g) * f64::from(u))
                        .sum();
                    let d = demodulation(&u);
                    (d, (g_dot_u as f32) * d * d)
                } else {
                    (1.0, 0.0)
                };
                let mut share = vec![0.0f64; c_in];
                for (j, ((dw, &g), &u)) in d_weight.iter_mut().zip(grad).zip(&u).enumerate() {
                    let d_u = d * (g - u * projection);
                    *dw = d_u * style[j / taps] * scale;
                    share[j / taps] += f64::from(d_u * weight[j] * scale);
                }
                share
            })
            .collect();
        let mut d_styles = vec![0.0f32; styles.len()];
        for (i, d) in d_styles[first..first + c_in].iter_mut().enumerate() {
            *d = style_shares.iter().map(|share| share[i]).sum::<f64>() as f32;
        }
        (
            from_values(d_weight, shape.to_vec()),
            from_values(d_styles, vec![styles.len()]),
        )
    }

    /// Computed now; the styles' gradient is summed on this thread until the launch.
    fn modulate_grad_queue(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> FloatTensor<Self> {
        let (d_weight, d_styles) =
            Self::modulate_grad(weight, styles, grad, first, scale, demodulate);
        STYLE_GRADIENT.with(|sum| {
            let mut sum = sum.borrow_mut();
            *sum = Some(match sum.take() {
                Some(s) => Self::float_add(s, d_styles),
                None => d_styles,
            });
        });
        d_weight
    }

    fn modulate_grad_launch_queued(styles: FloatTensor<Self>) -> FloatTensor<Self> {
        let shape = styles.shape();
        STYLE_GRADIENT
            .with(|sum| sum.borrow_mut().take())
            .filter(|sum| sum.shape() == shape)
            .unwrap_or_else(|| Self::float_zeros(shape, &styles.device(), styles.dtype().into()))
    }

    fn scale_weight(weight: FloatTensor<Self>, scale: f32) -> FloatTensor<Self> {
        Flex::float_mul_scalar(weight, scale.into())
    }

    fn scale_weight_grad(grad: FloatTensor<Self>, scale: f32) -> FloatTensor<Self> {
        Flex::float_mul_scalar(grad, scale.into())
    }

    fn scaled_linear(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        scales: LinearScales,
    ) -> FloatTensor<Self> {
        let (batch, inputs, outputs) = linear_dims(&x, &weight);
        let (x, weight, bias) = (host_f32(&x), host_f32(&weight), host_f32(&bias));
        assert_eq!(bias.len(), outputs, "one bias per output");
        let mut out = vec![0.0f32; batch * outputs];
        out.par_iter_mut()
            .with_min_len(64)
            .enumerate()
            .for_each(|(k, y)| {
                let (b, o) = (k / outputs, k % outputs);
                let row = &x[b * inputs..(b + 1) * inputs];
                let w = &weight[o * inputs..(o + 1) * inputs];
                let dot = row.iter().zip(w).fold(0.0f32, |sum, (a, b)| sum + a * b);
                let pre = dot * scales.weight_scale + bias[o] * scales.bias_scale;
                *y = scales.gain * if pre > 0.0 { pre } else { scales.slope * pre };
            });
        from_values(out, vec![batch, outputs])
    }

    fn scaled_linear_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        scales: LinearScales,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let (batch, inputs, outputs) = linear_dims(&x, &weight);
        let (x, weight) = (host_f32(&x), host_f32(&weight));
        let (output, grad) = (host_f32(&output), host_f32(&grad));
        assert_eq!(grad.len(), batch * outputs, "gradient shape");
        assert_eq!(output.len(), grad.len(), "output and gradient shapes");
        // The gradient before the activation, `[B, out]`.
        let g: Vec<f32> = grad
            .iter()
            .zip(output.iter())
            .map(|(&d, &y)| leaky_relu_grad(d, y, scales.slope, scales.gain))
            .collect();
        let at = |b: usize, o: usize| g[b * outputs + o];
        // Each sum runs in the order of the GPU kernel's (`fused::cube`'s `scaled_linear_grad`).
        let mut d_weight = vec![0.0f32; outputs * inputs];
        d_weight
            .par_iter_mut()
            .with_min_len(256)
            .enumerate()
            .for_each(|(t, d)| {
                let (o, i) = (t / inputs, t % inputs);
                let sum = (0..batch).fold(0.0f32, |sum, b| sum + at(b, o) * x[b * inputs + i]);
                *d = sum * scales.weight_scale;
            });
        let mut d_x = vec![0.0f32; batch * inputs];
        d_x.par_iter_mut()
            .with_min_len(64)
            .enumerate()
            .for_each(|(t, d)| {
                let (b, i) = (t / inputs, t % inputs);
                let sum =
                    (0..outputs).fold(0.0f32, |sum, o| sum + at(b, o) * weight[o * inputs + i]);
                *d = sum * scales.weight_scale;
            });
        let d_bias = (0..outputs)
            .map(|o| (0..batch).fold(0.0f32, |sum, b| sum + at(b, o)) * scales.bias_scale)
            .collect();
        (
            from_values(d_x, vec![batch, inputs]),
            from_values(d_weight, vec![outputs, inputs]),
            from_values(d_bias, vec![outputs]),
        )
    }

    fn lpips_distance(
        x: FloatTensor<Self>,
        y: FloatTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let features = LpipsFeatures::new(&x, &y, &weight);
        let plane = features.plane;
        let distances = (0..features.batch)
            .map(|b| {
                let sum: f64 = (0..plane.div_ceil(PIXEL_BLOCK))
                    .into_par_iter()
                    .map(|block| {
                        let pixels = block * PIXEL_BLOCK..((block + 1) * PIXEL_BLOCK).min(plane);
                        let norms = features.norms(b, pixels.clone());
                        let mut d = vec![0.0f32; pixels.len()];
                        for c in 0..features.channels {
                            let (xc, yc) = features.channel(b, c, pixels.clone());
                            for (((d, &x), &y), n) in d.iter_mut().zip(xc).zip(yc).zip(&norms) {
                                let diff = x * n.inv_x - y * n.inv_y;
                                *d += features.weight[c] * diff * diff;
                            }
                        }
                        d.iter().map(|&v| f64::from(v)).sum::<f64>()
                    })
                    .sum();
                (sum / plane as f64) as f32
            })
            .collect();
        from_values(distances, vec![features.batch])
    }

    fn lpips_distance_grad(
        x: FloatTensor<Self>,
        y: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let shape = dims(&x);
        let features = LpipsFeatures::new(&x, &y, &weight);
        let (plane, channels) = (features.plane, features.channels);
        let grad = host_f32(&grad);
        assert_eq!(grad.len(), features.batch, "one gradient per distance");
        let mut dx = vec![0.0f32; features.x.len()];
        for (b, dx) in dx.chunks_mut((channels * plane).max(1)).enumerate() {
            let scale = grad[b] / plane as f32;
            // Per pixel, the norms' inverses and `k = Σ_c u_c x_c / (n² ‖x‖)`.
            let pixels: Vec<(PixelNorms, f32)> = (0..plane.div_ceil(PIXEL_BLOCK))
                .into_par_iter()
                .flat_map_iter(|block| {
                    let pixels = block * PIXEL_BLOCK..((block + 1) * PIXEL_BLOCK).min(plane);
                    let norms = features.norms(b, pixels.clone());
                    let mut dot = vec![0.0f32; pixels.len()];
                    for c in 0..channels {
                        let (xc, yc) = features.channel(b, c, pixels.clone());
                        let w2 = 2.0 * features.weight[c] * scale;
                        for (((dot, &x), &y), n) in dot.iter_mut().zip(xc).zip(yc).zip(&norms) {
                            *dot += w2 * (x * n.inv_x - y * n.inv_y) * x;
                        }
                    }
                    norms.into_iter().zip(dot).map(|(n, dot)| {
                        let k = if n.norm_x > 0.0 {
                            dot * n.inv_x * n.inv_x / n.norm_x
                        } else {
                            0.0
                        };
                        (n, k)
                    })
                })
                .collect();
            dx.par_chunks_mut(plane.max(1))
                .enumerate()
                .for_each(|(c, dx)| {
                    let (xc, yc) = features.channel(b, c, 0..plane);
                    let w2 = 2.0 * features.weight[c] * scale;
                    for (((dx, &x), &y), (n, k)) in dx.iter_mut().zip(xc).zip(yc).zip(&pixels) {
                        let u = w2 * (x * n.inv_x - y * n.inv_y);
                        *dx = u * n.inv_x - x * k;
                    }
                });
        }
        from_values(dx, shape.to_vec())
    }
}

/// Pixels per task of the LPIPS comparison: each task walks the channels over its block.
const PIXEL_BLOCK: usize = 1024;

/// The inputs of [`FusedBackend::lpips_distance`] as host values, row-major `[B, C, H·W]`.
struct LpipsFeatures<'a> {
    x: Cow<'a, [f32]>,
    y: Cow<'a, [f32]>,
    weight: Cow<'a, [f32]>,
    batch: usize,
    channels: usize,
    plane: usize,
}

/// One pixel's feature norms over channels: `‖x‖` and the inverses of `‖x‖ + ε`, `‖y‖ + ε`.
struct PixelNorms {
    norm_x: f32,
    inv_x: f32,
    inv_y: f32,
}

impl<'a> LpipsFeatures<'a> {
    fn new(
        x: &'a FloatTensor<Flex>,
        y: &'a FloatTensor<Flex>,
        weight: &'a FloatTensor<Flex>,
    ) -> Self {
        let [batch, channels, h, w] = dims(x);
        assert_eq!(
            dims(y),
            [batch, channels, h, w],
            "LPIPS compares features of one shape"
        );
        let weight = host_f32(weight);
        assert_eq!(weight.len(), channels, "one head weight per channel");
        Self {
            x: host_f32(x),
            y: host_f32(y),
            weight,
            batch,
            channels,
            plane: h * w,
        }
    }

    /// Channel `c` of batch item `b` over `pixels`, of `x` and of `y`.
    fn channel(&self, b: usize, c: usize, pixels: Range<usize>) -> (&[f32], &[f32]) {
        let start = (b * self.channels + c) * self.plane;
        (
            &self.x[start + pixels.start..start + pixels.end],
            &self.y[start + pixels.start..start + pixels.end],
        )
    }

    /// The norms over channels at each of `pixels` of batch item `b`, summed channel by
    /// channel in f32 (as the GPU kernel sums them).
    fn norms(&self, b: usize, pixels: Range<usize>) -> Vec<PixelNorms> {
        let (mut sx, mut sy) = (vec![0.0f32; pixels.len()], vec![0.0f32; pixels.len()]);
        for c in 0..self.channels {
            let (xc, yc) = self.channel(b, c, pixels.clone());
            for (((sx, sy), &x), &y) in sx.iter_mut().zip(sy.iter_mut()).zip(xc).zip(yc) {
                *sx += x * x;
                *sy += y * y;
            }
        }
        sx.into_iter()
            .zip(sy)
            .map(|(sx, sy)| {
                let norm_x = sx.sqrt();
                PixelNorms {
                    norm_x,
                    inv_x: 1.0 / (norm_x + LPIPS_EPSILON),
                    inv_y: 1.0 / (sy.sqrt() + LPIPS_EPSILON),
                }
            })
            .collect()
    }
}

/// `(batch, inputs, outputs)` of a linear layer's input `[B, in]` and weight `[out, in]`.
fn linear_dims(x: &FloatTensor<Flex>, weight: &FloatTensor<Flex>) -> (usize, usize, usize) {
    let [batch, inputs] = x.shape().dims();
    let [outputs, weight_inputs] = weight.shape().dims();
    assert_eq!(weight_inputs, inputs, "the weight's inputs are the input's");
    (batch, inputs, outputs)
}

/// A layer's `inputs` styles, from `first` on in a network's `styles`.
fn layer_styles(styles: &[f32], first: usize, inputs: usize) -> &[f32] {
    assert!(
        first + inputs <= styles.len(),
        "styles {first}..{} of {}",
        first + inputs,
        styles.len()
    );
    &styles[first..first + inputs]
}

/// `(Σ u² + 10⁻⁸)^(−½)` over one output channel's modulated weights.
fn demodulation(u: &[f32]) -> f32 {
    let sum: f64 = u.iter().map(|&v| f64::from(v) * f64::from(v)).sum();
    1.0 / (sum as f32 + DEMODULATION_EPSILON).sqrt()
}

/// One value of [`FusedBackend::bias_leaky_relu_grad`]: with slope 0 (a ReLU) a selection, not a
/// product, so that a gradient that is infinite or NaN where the output is zero does not pass
/// (`∞ · 0` is NaN), as in Burn's and PyTorch's ReLU.
fn leaky_relu_grad(grad: f32, output: f32, slope: f32, gain: f32) -> f32 {
    if output > 0.0 {
        gain * grad
    } else if slope == 0.0 {
        0.0
    } else {
        gain * slope * grad
    }
}

/// Bilinear interpolation with `align_corners = false` (PyTorch's default).
fn bilinear() -> InterpolateOptions {
    let mut options = InterpolateOptions::new(InterpolateMode::Bilinear);
    options.align_corners = false;
    options
}

fn dims(t: &FloatTensor<Flex>) -> [usize; 4] {
    t.shape().dims()
}

/// Bilinear ×2 along one axis of `lines` blocks of `n` samples, each sample `inner` contiguous
/// values (`inner` = 1: along rows; the row length: along columns): output sample `2i` is
/// `¾ x[i] + ¼ x[i − 1]`, `2i + 1` is `¾ x[i] + ¼ x[i + 1]`, the edge sample repeated.
fn upsample_axis(x: &[f32], lines: usize, n: usize, inner: usize, out: &mut [f32]) {
    for line in 0..lines {
        let source = &x[line * n * inner..(line + 1) * n * inner];
        let target = &mut out[2 * line * n * inner..2 * (line + 1) * n * inner];
        let sample = |i: usize| &source[i * inner..(i + 1) * inner];
        for i in 0..n {
            let (centre, previous, next) = (sample(i), sample(i.saturating_sub(1)), {
                sample((i + 1).min(n - 1))
            });
            let (even, odd) = target[2 * i * inner..(2 * i + 2) * inner].split_at_mut(inner);
            for t in 0..inner {
                even[t] = 0.75 * centre[t] + 0.25 * previous[t];
                odd[t] = 0.75 * centre[t] + 0.25 * next[t];
            }
        }
    }
}

/// The adjoint of [`upsample_axis`]: `grad` has `2n` samples per line, `dx` gets `n`.
fn upsample_axis_adjoint(grad: &[f32], lines: usize, n: usize, inner: usize, dx: &mut [f32]) {
    for line in 0..lines {
        let source = &grad[2 * line * n * inner..2 * (line + 1) * n * inner];
        let target = &mut dx[line * n * inner..(line + 1) * n * inner];
        target.fill(0.0);
        for i in 0..n {
            let even = &source[2 * i * inner..(2 * i + 1) * inner];
            let odd = &source[(2 * i + 1) * inner..(2 * i + 2) * inner];
            let (previous, next) = (i.saturating_sub(1), (i + 1).min(n - 1));
            for t in 0..inner {
                target[i * inner + t] += 0.75 * (even[t] + odd[t]);
                target[previous * inner + t] += 0.25 * even[t];
                target[next * inner + t] += 0.25 * odd[t];
            }
        }
    }
}

/// The `[1, 3, 3, 1] / 8` filter along one axis of `lines` blocks of `n` samples (each `inner`
/// contiguous values), zero-padded by `before` (and by `after`, implied by `out`'s length):
/// `out[o] = Σ_k taps[k] · x[o + k − before]`. Outputs whose four taps all fall inside form one
/// contiguous span in `out` and in each shifted `x`, summed as four zipped slices (which
/// vectorise whatever `inner` is); the at most three outputs at each end check their taps.
fn blur_axis(x: &[f32], lines: usize, n: usize, inner: usize, before: usize, out: &mut [f32]) {
    let out_n = out.len() / (lines * inner).max(1);
    // Outputs o with 0 ≤ o − before and o + 3 − before < n.
    let interior = before.min(out_n)
        ..(n + before)
            .saturating_sub(3)
            .clamp(before.min(out_n), out_n);
    for line in 0..lines {
        let source = &x[line * n * inner..(line + 1) * n * inner];
        let target = &mut out[line * out_n * inner..(line + 1) * out_n * inner];
        let span = interior.len() * inner;
        if span > 0 {
            let start = (interior.start - before) * inner;
            let shifted = |k: usize| &source[start + k * inner..start + k * inner + span];
            let [t0, t1, t2, t3] = TAPS;
            let values = target[interior.start * inner..interior.end * inner].iter_mut();
            for ((((v, a), b), c), d) in values
                .zip(shifted(0))
                .zip(shifted(1))
                .zip(shifted(2))
                .zip(shifted(3))
            {
                *v = t0 * a + t1 * b + t2 * c + t3 * d;
            }
        }
        for o in (0..interior.start).chain(interior.end..out_n) {
            let value = &mut target[o * inner..(o + 1) * inner];
            value.fill(0.0);
            for (k, tap) in TAPS.iter().enumerate() {
                let Some(i) = (o + k).checked_sub(before).filter(|&i| i < n) else {
                    continue;
                };
                for (v, s) in value.iter_mut().zip(&source[i * inner..(i + 1) * inner]) {
                    *v += tap * s;
                }
            }
        }
    }
}
