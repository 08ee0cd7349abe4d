//! Bias + leaky ReLU (StyleGAN2's activation; LPIPS's bias + ReLU with slope 0): the forward and
//! the input gradient one kernel each, the bias gradient Burn's reductions, the noise strength's
//! a kernel of partial sums and Burn's reduction of them.

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::Shape;
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::{permute_nchw_to_nhwc, permute_nhwc_to_nchw};

use super::{dims, one_thread_per_output, u32_of};
use crate::cube_grid::{UNITS, one_thread_per_value};
use crate::cube_layout::{channels_last, empty_in_layout, readable};

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use super::super::sum::{cube_index, cube_sum};

    /// `out = gain · (x + bias[c])`, times `slope` where that is not positive; `c` is the
    /// channel of the value at buffer offset `i` (`(i / channel_stride) % channels`: `x` and `out`
    /// share one gapless layout).
    #[cube(launch)]
    pub fn bias_leaky_relu(
        x: &Tensor<f32>,
        bias: &Tensor<f32>,
        out: &mut Tensor<f32>,
        channel_stride: u32,
        channels: u32,
        gain: f32,
        slope: f32,
    ) {
        let i = ABSOLUTE_POS;
        if i >= out.len() {
            terminate!();
        }
        let c = (i as u32 / channel_stride) % channels;
        let pre = x[i] + bias[c as usize];
        let mut value = pre;
        if pre <= 0.0 {
            value = slope * pre;
        }
        out[i] = gain * value;
    }

    /// [`bias_leaky_relu`] with `noise[p] · strength[0]` added, `p` the pixel of the value at
    /// buffer offset `i` (`(i / pixel_stride) % pixels`).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn noisy_bias_leaky_relu(
        x: &Tensor<f32>,
        noise: &Tensor<f32>,
        strength: &Tensor<f32>,
        bias: &Tensor<f32>,
        out: &mut Tensor<f32>,
        channel_stride: u32,
        channels: u32,
        pixel_stride: u32,
        pixels: u32,
        gain: f32,
        slope: f32,
    ) {
        let i = ABSOLUTE_POS;
        if i >= out.len() {
            terminate!();
        }
        let c = (i as u32 / channel_stride) % channels;
        let p = (i as u32 / pixel_stride) % pixels;
        let pre = x[i] + noise[p as usize] * strength[0] + bias[c as usize];
        let mut value = pre;
        if pre <= 0.0 {
            value = slope * pre;
        }
        out[i] = gain * value;
    }

    /// `partials[k]`: over cube `k`'s pixels `p` ([`cube_index`], `units` pixels a cube), the
    /// sum of `noise[p] · Σ_{b, c} grad[b, c, p]` (`grad` row-major or, with `channels_last`,
    /// channels-last): a thread per pixel, then a pairwise sum in shared memory. Every unit
    /// reaches its barriers: units past the pixels add zero, cubes past the partials write
    /// nothing.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn noise_partials(
        grad: &Tensor<f32>,
        noise: &Tensor<f32>,
        partials: &mut Tensor<f32>,
        pixels: u32,
        batch: u32,
        channels: u32,
        #[comptime] channels_last: bool,
        #[comptime] units: u32,
    ) {
        let k = cube_index();
        let p = k * units + UNIT_POS;
        let mut sum = 0.0f32;
        if p < pixels {
            for b in 0..batch {
                for c in 0..channels {
                    let mut at = (b * channels + c) * pixels + p;
                    if comptime![channels_last] {
                        at = (b * pixels + p) * channels + c;
                    }
                    sum += grad[at as usize];
                }
            }
            sum *= noise[p as usize];
        }
        let mut partial = Shared::<[f32]>::new_slice(comptime![units as usize]);
        partial[UNIT_POS as usize] = sum;
        cube_sum(&mut partial, units);
        if UNIT_POS == 0 && (k as usize) < partials.len() {
            partials[k as usize] = partial[0];
        }
    }

    /// `dx = grad · gain · (1 where the output is positive, else slope)`, buffer offset by buffer
    /// offset (the three share one gapless layout); with slope 0 a selection, as `fused::flex`'s
    /// `leaky_relu_grad`, so that a non-finite gradient where the output is zero does not pass.
    #[cube(launch)]
    pub fn bias_leaky_relu_grad(
        output: &Tensor<f32>,
        grad: &Tensor<f32>,
        dx: &mut Tensor<f32>,
        gain: f32,
        slope: f32,
    ) {
        let i = ABSOLUTE_POS;
        if i >= dx.len() {
            terminate!();
        }
        let mut value = 0.0f32;
        if output[i] > 0.0 {
            value = gain * grad[i];
        } else if slope != 0.0 {
            value = gain * slope * grad[i];
        }
        dx[i] = value;
    }
}

/// One kernel, in `x`'s layout.
pub(super) fn bias_leaky_relu(
    x: FloatTensor<CubeBackend>,
    bias: FloatTensor<CubeBackend>,
    slope: f32,
    gain: f32,
) -> FloatTensor<CubeBackend> {
    let shape = dims(&x);
    assert_eq!(bias.shape().dims::<1>(), [shape[1]], "one bias per channel");
    let bias = into_contiguous(bias);
    let (x, last) = readable(x);
    let channel_stride = if last { 1 } else { shape[2] * shape[3] };
    let out = empty_in_layout(&x, shape, last);
    one_thread_per_output(out, &x, |cubes, cube, out| {
        kernels::bias_leaky_relu::launch(
            &x.client,
            cubes,
            cube,
            x.clone().into_tensor_arg(),
            bias.into_tensor_arg(),
            out.into_tensor_arg(),
            u32_of(channel_stride).max(1),
            u32_of(shape[1]).max(1),
            gain,
            slope,
        )
    })
}

/// One kernel, in `x`'s layout.
pub(super) fn noisy_bias_leaky_relu(
    x: FloatTensor<CubeBackend>,
    noise: FloatTensor<CubeBackend>,
    strength: FloatTensor<CubeBackend>,
    bias: FloatTensor<CubeBackend>,
    slope: f32,
    gain: f32,
) -> FloatTensor<CubeBackend> {
    let shape = dims(&x);
    let pixels = shape[2] * shape[3];
    assert_eq!(bias.shape().dims::<1>(), [shape[1]], "one bias per channel");
    assert_eq!(
        noise.shape().num_elements(),
        pixels,
        "one noise value per pixel"
    );
    assert_eq!(strength.shape().num_elements(), 1, "one noise strength");
    let [noise, strength, bias] = [noise, strength, bias].map(into_contiguous);
    let (x, last) = readable(x);
    let (channel_stride, pixel_stride) = if last { (1, shape[1]) } else { (pixels, 1) };
    let out = empty_in_layout(&x, shape, last);
    one_thread_per_output(out, &x, |cubes, cube, out| {
        kernels::noisy_bias_leaky_relu::launch(
            &x.client,
            cubes,
            cube,
            x.clone().into_tensor_arg(),
            noise.into_tensor_arg(),
            strength.into_tensor_arg(),
            bias.into_tensor_arg(),
            out.into_tensor_arg(),
            u32_of(channel_stride).max(1),
            u32_of(shape[1]).max(1),
            u32_of(pixel_stride).max(1),
            u32_of(pixels).max(1),
            gain,
            slope,
        )
    })
}

/// Two launches: the products with the noise summed per cube of pixels, then those partial
/// sums by Burn's reduction (a pass over a few thousand values; before, the products were
/// written per pixel and summed by Burn's `sum`, which fills its output first: three launches).
pub(super) fn noise_strength_grad(
    grad: FloatTensor<CubeBackend>,
    noise: FloatTensor<CubeBackend>,
) -> FloatTensor<CubeBackend> {
    let [batch, channels, height, width] = dims(&grad);
    let pixels = height * width;
    assert_eq!(
        noise.shape().num_elements(),
        pixels,
        "one noise value per pixel"
    );
    u32_of(grad.shape().num_elements());
    let noise = into_contiguous(noise);
    let (grad, last) = readable(grad);
    let cubes = pixels.div_ceil(UNITS as usize).max(1);
    let partials = empty_in_layout(&grad, [1, 1, 1, cubes], false);
    let (grid, cube) = one_thread_per_value(pixels);
    kernels::noise_partials::launch(
        &grad.client,
        grid,
        cube,
        grad.clone().into_tensor_arg(),
        noise.into_tensor_arg(),
        partials.clone().into_tensor_arg(),
        u32_of(pixels),
        u32_of(batch),
        u32_of(channels),
        last,
        UNITS,
    );
    let partials = CubeBackend::float_reshape(partials, Shape::new([cubes]));
    CubeBackend::float_sum_dim(partials, 0)
}

/// In the gradient's layout; the output is copied to it where the two differ.
pub(super) fn bias_leaky_relu_grad(
    output: FloatTensor<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
    slope: f32,
    gain: f32,
) -> FloatTensor<CubeBackend> {
    let shape = dims(&grad);
    assert_eq!(dims(&output), shape, "output and gradient shapes");
    let (grad, last) = readable(grad);
    let output = match (channels_last(&output), last) {
        (true, true) => output,
        (_, false) => into_contiguous(output),
        (false, true) => permute_nhwc_to_nchw(into_contiguous(permute_nchw_to_nhwc(output))),
    };
    let dx = empty_in_layout(&grad, shape, last);
    one_thread_per_output(dx, &grad, |cubes, cube, dx| {
        kernels::bias_leaky_relu_grad::launch(
            &grad.client,
            cubes,
            cube,
            output.into_tensor_arg(),
            grad.clone().into_tensor_arg(),
            dx.into_tensor_arg(),
            gain,
            slope,
        )
    })
}

/// Burn's reductions (the patched `burn-cubecl` picks a plane per channel for the long
/// axis): one over the positions of a channels-last `x`, else over each plane and then,
/// where there is more than one, the batch. A long sum over few channels goes in two stages,
/// over [`segments`] of the positions and then over the segments: a plane per channel alone
/// kept a few of the GPU's multiprocessors busy, 0.58 ms a sum on an H200 for a 1024² map of
/// 32 channels (BENCHMARKS, "GPU: an H200 lent on 2026-11-29").
pub(super) fn channel_sum(x: FloatTensor<CubeBackend>) -> FloatTensor<CubeBackend> {
    let [batch, channels, height, width] = dims(&x);
    let positions = batch * height * width;
    if channels_last(&x) {
        let parts = segments(positions, channels);
        let rows = CubeBackend::float_reshape(
            permute_nchw_to_nhwc(x),
            Shape::new([parts, positions / parts, channels]),
        );
        let mut sums = CubeBackend::float_sum_dim(rows, 1);
        if parts > 1 {
            sums = CubeBackend::float_sum_dim(sums, 0);
        }
        return CubeBackend::float_reshape(sums, Shape::new([channels]));
    }
    let plane = height * width;
    let parts = segments(plane, channels * batch);
    let planes = CubeBackend::float_reshape(x, Shape::new([batch, channels, parts, plane / parts]));
    let mut sums = CubeBackend::float_sum_dim(planes, 3);
    if parts > 1 {
        sums = CubeBackend::float_sum_dim(sums, 2);
    }
    if batch > 1 {
        sums = CubeBackend::float_sum_dim(sums, 0);
    }
    CubeBackend::float_reshape(sums, Shape::new([channels]))
}

/// Into how many equal segments to cut `positions` terms of each of `sums` sums: 1 unless the
/// sums are long (2¹⁶ terms or more) and few (under 256); then by halving while the
/// segments' sums number under 1 024 and each keeps 4 096 terms or more.
fn segments(positions: usize, sums: usize) -> usize {
    let mut parts = 1;
    if positions >= 1 << 16 && sums < 256 {
        while sums * parts < 1024
            && positions.is_multiple_of(2 * parts)
            && positions / (2 * parts) >= 4096
        {
            parts *= 2;
        }
    }
    parts
}
