//! `impl FusedBackend for CubeBackend` (wgpu, CUDA; under `fusion` run by its lazy op): one
//! kernel per op, one thread per output value, gathering its few inputs (no atomics, so the
//! backward passes are deterministic).
//!
//! Written with Burn's tensor ops ([`crate::fused::portable`]) these chains are slices,
//! concatenations, scalings and sums: a `paper` step launched ≈ 57 000 kernels, 35 000 of them
//! element-wise, `SliceAssign` or leaky ReLU's `MaskWhere` (BENCHMARKS "Where the device time
//! goes now"), and its host work per launch bounds the step on an H100. Indices are 32-bit: the
//! callers route tensors of 2³² values or more to the portable ops (`fused::runs`).
//!
//! Layouts: every op reads and writes either of `crate::cube_layout`'s two and keeps its input's
//! (anything else is made row-major first; the resize, the 2 × 2 mean's adjoint and the Haar
//! analysis read any strides, the analysis writing channels-last always), so the activation
//! after a convolution goes through bias + leaky ReLU, blur or up-sampling into the next
//! convolution in the channels-last layout the convolutions compute in, without copies to
//! row-major and back. Convolution weights (`modulate`, `scale_weight`) are written
//! channels-last whatever their input's layout, as the implicit GEMM reads them; the linear
//! layer's `[B, in]` tensors are row-major. The arithmetic follows `fused::flex` term by term.
//!
//! One file per op and its backward, the kernels (`mod kernels`) beside their launches;
//! `position` holds the index arithmetic of the layouts, which the resampling kernels share.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::{CubeCount, CubeDim};

use super::{FusedBackend, LinearScales, separate_bias_leaky_relu_grads};
use crate::cube_grid::one_thread_per_value;
use crate::cube_layout::into_channels_last;

mod bias_leaky_relu;
mod blur;
mod cat;
mod downsample;
mod haar;
mod linear;
mod lpips;
mod modulate;
mod position;
mod resize;
mod sum;
mod to_rgb;
mod upsample;

fn dims(t: &FloatTensor<CubeBackend>) -> [usize; 4] {
    t.shape().dims()
}

/// A size as a kernel's 32-bit argument.
fn u32_of(values: usize) -> u32 {
    u32::try_from(values).expect("fused ops index fewer than 2^32 values (fused::runs)")
}

/// Runs `launch` with one thread per value of `out` unless it is empty, and returns `out`;
/// `input` is the op's input, whose values the kernel indexes too.
fn one_thread_per_output(
    out: FloatTensor<CubeBackend>,
    input: &FloatTensor<CubeBackend>,
    launch: impl FnOnce(CubeCount, CubeDim, FloatTensor<CubeBackend>),
) -> FloatTensor<CubeBackend> {
    let n = out.shape().num_elements();
    u32_of(n.max(input.shape().num_elements()));
    if n > 0 {
        let (cubes, cube) = one_thread_per_value(n);
        launch(cubes, cube, out.clone());
    }
    out
}

impl FusedBackend for CubeBackend {
    fn bias_leaky_relu(
        x: FloatTensor<Self>,
        input_scale: f32,
        bias: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self> {
        bias_leaky_relu::bias_leaky_relu(x, input_scale, bias, slope, gain)
    }

    fn bias_leaky_relu_grad(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self> {
        bias_leaky_relu::bias_leaky_relu_grad(output, grad, slope, gain)
    }

    fn noisy_bias_leaky_relu(
        x: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        strength: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self> {
        bias_leaky_relu::noisy_bias_leaky_relu(x, noise, strength, bias, slope, gain)
    }

    fn noise_strength_grad(grad: FloatTensor<Self>, noise: FloatTensor<Self>) -> FloatTensor<Self> {
        bias_leaky_relu::noise_strength_grad(grad, noise)
    }

    fn channel_sum(x: FloatTensor<Self>) -> FloatTensor<Self> {
        bias_leaky_relu::channel_sum(x)
    }

    fn bias_leaky_relu_backward_queue(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        input_scale: f32,
        slope: f32,
        gain: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        match bias_leaky_relu::gradients(&output, &grad, None, input_scale, slope, gain) {
            Some((dx, d_bias, _)) => (dx, d_bias),
            None => separate_bias_leaky_relu_grads::<Self>(output, grad, input_scale, slope, gain),
        }
    }

    fn noisy_bias_leaky_relu_backward_queue(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        match bias_leaky_relu::gradients(&output, &grad, Some(&noise), 1.0, slope, gain) {
            Some((dx, d_bias, Some(d_strength))) => (dx, d_bias, d_strength),
            _ => {
                let (dx, d_bias) =
                    separate_bias_leaky_relu_grads::<Self>(output, grad, 1.0, slope, gain);
                let d_strength = bias_leaky_relu::noise_strength_grad(dx.clone(), noise);
                (dx, d_bias, d_strength)
            }
        }
    }

    fn bias_grads_launch_queued(anchor: FloatTensor<Self>) -> FloatTensor<Self> {
        bias_leaky_relu::launch_queued_sums();
        anchor
    }

    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        upsample::upsample2(x)
    }

    fn upsample2_grad(grad: FloatTensor<Self>) -> FloatTensor<Self> {
        upsample::upsample2_grad(grad)
    }

    fn downsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        downsample::downsample2(x)
    }

    fn downsample2_grad(grad: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self> {
        downsample::downsample2_grad(grad, height, width)
    }

    fn resize(x: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self> {
        resize::resize(x, height, width)
    }

    fn resize_grad(grad: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self> {
        resize::resize_grad(grad, height, width)
    }

    fn blur(x: FloatTensor<Self>, before: usize, after: usize) -> FloatTensor<Self> {
        blur::blur(x, before, after)
    }

    fn haar(x: FloatTensor<Self>) -> FloatTensor<Self> {
        haar::haar(x)
    }

    fn inverse_haar(x: FloatTensor<Self>) -> FloatTensor<Self> {
        haar::inverse_haar(x)
    }

    fn to_channels_last(x: FloatTensor<Self>) -> FloatTensor<Self> {
        into_channels_last(x)
    }

    fn to_rgb_output(
        x: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        skip: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        to_rgb::to_rgb_output(x, bias, Some(skip))
    }

    fn to_rgb_skip_grad(grad: FloatTensor<Self>) -> FloatTensor<Self> {
        to_rgb::to_rgb_skip_grad(grad)
    }

    fn add_channel_bias(x: FloatTensor<Self>, bias: FloatTensor<Self>) -> FloatTensor<Self> {
        to_rgb::to_rgb_output(x, bias, None)
    }

    fn cat_channels(first: FloatTensor<Self>, second: FloatTensor<Self>) -> FloatTensor<Self> {
        cat::cat_channels(first, second)
    }

    fn split_channels(
        grad: FloatTensor<Self>,
        first: usize,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        cat::split_channels(grad, first)
    }

    fn modulate_queue(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> FloatTensor<Self> {
        modulate::modulate_queue(weight, &styles, first, scale, demodulate)
    }

    fn modulate_launch_queued(styles: FloatTensor<Self>) -> FloatTensor<Self> {
        modulate::modulate_launch_queued(styles)
    }

    fn modulate_grad(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        modulate::modulate_grad(weight, styles, grad, first, scale, demodulate)
    }

    fn modulate_grad_queue(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> FloatTensor<Self> {
        modulate::modulate_grad_queue(weight, &styles, grad, first, scale, demodulate)
    }

    fn modulate_grad_launch_queued(styles: FloatTensor<Self>) -> FloatTensor<Self> {
        modulate::modulate_grad_launch_queued(styles)
    }

    fn scale_weight(weight: FloatTensor<Self>, scale: f32) -> FloatTensor<Self> {
        modulate::scale_weight(weight, scale)
    }

    fn scale_weight_grad(grad: FloatTensor<Self>, scale: f32) -> FloatTensor<Self> {
        modulate::scale_weight_grad(grad, scale)
    }

    fn scaled_linear(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        scales: LinearScales,
    ) -> FloatTensor<Self> {
        linear::scaled_linear(x, weight, bias, scales)
    }

    fn scaled_linear_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        scales: LinearScales,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        linear::scaled_linear_grad(x, weight, output, grad, scales)
    }

    fn lpips_distance(
        x: FloatTensor<Self>,
        y: FloatTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        lpips::lpips_distance(x, y, weight)
    }

    fn lpips_distance_grad(
        x: FloatTensor<Self>,
        y: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        lpips::lpips_distance_grad(x, y, weight, grad)
    }
}
