//! Bias + leaky ReLU (StyleGAN2's activation; LPIPS's bias + ReLU with slope 0): the forward and
//! the input gradient one kernel each, the bias gradient Burn's reductions, the noise strength's
//! a kernel of partial sums and Burn's reduction of them — or, for a channels-last gradient of
//! a power-of-two channel count (the networks' own), the three gradients from one kernel that
//! also sums each cube's share of the last two; the sums of those shares are queued on the
//! thread and made for every activation of a backward pass together (`launch_queued_sums`,
//! called by the autodiff's gate nodes, `fused/autodiff.rs`).

use std::cell::RefCell;

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::CubeDim;
use burn_cubecl::cubecl::prelude::SequenceArg;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;
use burn_cubecl::ops::permute_nchw_to_nhwc;

use super::sum::{SUM_UNITS, one_cube_per_channel_in_layers};
use super::{dims, one_thread_per_output, u32_of};
use crate::cube_grid::{UNITS, cubes_in_rows, items_per_launch, one_thread_per_value};
use crate::cube_layout::{channels_last, empty_in_layout, into_channels_last, readable};

/// The kernels; `activation_grad` is shared with the linear layer's (`linear.rs`).
pub(super) mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use super::super::sum::{cube_index, cube_sum};

    /// The activation's gradient at one value: `grad · gain`, times `slope` where the output
    /// is not positive; with slope 0 a selection, as `fused::flex`'s `leaky_relu_grad`, so that
    /// a non-finite gradient where the output is zero does not pass.
    #[cube]
    pub(in crate::fused::cube) fn activation_grad(
        grad: f32,
        output: f32,
        slope: f32,
        gain: f32,
    ) -> f32 {
        let mut value = 0.0f32;
        if output > 0.0 {
            value = gain * grad;
        } else if slope != 0.0 {
            value = gain * slope * grad;
        }
        value
    }

    /// `out = gain · (input_scale · x + bias[c])`, times `slope` where that is not positive; `c` is
    /// the channel of the value at buffer offset `i` (`(i / channel_stride) % channels`: `x` and
    /// `out` share one gapless layout).
    #[cube(launch)]
    pub fn bias_leaky_relu(
        x: &Tensor<f32>,
        bias: &Tensor<f32>,
        out: &mut Tensor<f32>,
        channel_stride: u32,
        channels: u32,
        input_scale: f32,
        gain: f32,
        slope: f32,
    ) {
        let i = ABSOLUTE_POS;
        if i >= out.len() {
            terminate!();
        }
        let c = (i as u32 / channel_stride) % channels;
        let pre = input_scale * x[i] + bias[c as usize];
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

    /// [`bias_leaky_relu_grad`] on channels-last `[positions, channels]` values (`channels` a power
    /// of two dividing `units`), times `input_scale` in `dx`, with each cube's sums for the bias
    /// gradient and, if `noisy`, the noise strength's: cube `k` ([`cube_index`]) takes positions
    /// `k·block..(k + 1)·block`, unit `t` channel `t % channels` of every `units / channels`-th of
    /// them; `bias_partials[k, c]` is the sum of the block's pre-activation gradients `dx[·, c] /
    /// input_scale`, `noise_partials[k]` that of `dx · noise[position % pixels]` (the noisy form's
    /// scale is 1). The units holding one channel are then summed pairwise in shared memory. Every
    /// unit reaches every barrier; cubes past the blocks write nothing.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn bias_leaky_relu_grads(
        output: &Tensor<f32>,
        grad: &Tensor<f32>,
        noise: &Tensor<f32>,
        dx: &mut Tensor<f32>,
        bias_partials: &mut Tensor<f32>,
        noise_partials: &mut Tensor<f32>,
        positions: u32,
        pixels: u32,
        channels: u32,
        block: u32,
        blocks: u32,
        input_scale: f32,
        gain: f32,
        slope: f32,
        #[comptime] noisy: bool,
        #[comptime] units: u32,
    ) {
        let k = cube_index();
        let t = UNIT_POS;
        let c = t % channels;
        let lanes = units / channels;
        let first = k * block;
        let mut end = first + block;
        if end > positions {
            end = positions;
        }
        let mut bias_sum = 0.0f32;
        let mut noise_sum = 0.0f32;
        let mut p = first + t / channels;
        while p < end {
            let at = (p * channels + c) as usize;
            let g = activation_grad(grad[at], output[at], slope, gain);
            dx[at] = input_scale * g;
            bias_sum += g;
            if comptime![noisy] {
                noise_sum += g * noise[(p % pixels) as usize];
            }
            p += lanes;
        }
        let mut partial = Shared::<[f32]>::new_slice(comptime![units as usize]);
        partial[t as usize] = bias_sum;
        sync_cube();
        // Pairwise with doubling strides from the channel count: unit `t` ends holding the sum
        // of the units `t + j · channels`.
        let mut stride = channels;
        while stride < units {
            if t % (2 * stride) < stride {
                partial[t as usize] += partial[(t + stride) as usize];
            }
            sync_cube();
            stride *= 2;
        }
        if t < channels && k < blocks {
            bias_partials[(k * channels + t) as usize] = partial[t as usize];
        }
        if comptime![noisy] {
            let mut products = Shared::<[f32]>::new_slice(comptime![units as usize]);
            products[t as usize] = noise_sum;
            cube_sum(&mut products, units);
            if t == 0 && k < blocks {
                noise_partials[k as usize] = products[0];
            }
        }
    }

    /// The column sums of several `[rows, values]` tables of cubes' shares
    /// (of [`bias_leaky_relu_grads`]), grid layer `CUBE_POS_Z` for table `n` (`shares[n]` into
    /// `sums[n]`, both gapless), one cube per column (`CUBE_POS_X`; cubes past the table's
    /// columns add nothing and write nothing), its units striding over the rows. The barriers
    /// sit in control flow uniform over the cube (the grid layer picks the branch).
    #[cube(launch)]
    pub fn sum_columns_many(
        shares: &Sequence<OwnedTensor<f32>>,
        sums: &mut Sequence<OwnedTensor<f32>>,
        #[comptime] count: usize,
        #[comptime] units: u32,
    ) {
        let table = CUBE_POS_Z as usize;
        let k = CUBE_POS_X;
        let t = UNIT_POS;
        let mut partial = Shared::<[f32]>::new_slice(comptime![units as usize]);
        #[unroll]
        for n in 0..count {
            if table == n {
                let share = shares.index(n);
                let values = share.shape(1) as u32;
                let mut rows = 0u32;
                if k < values {
                    rows = share.shape(0) as u32;
                }
                let mut sum = 0.0f32;
                let mut r = t;
                while r < rows {
                    sum += share[(r * values + k) as usize];
                    r += units;
                }
                partial[t as usize] = sum;
                cube_sum(&mut partial, units);
                if t == 0 && k < values {
                    let out = sums.index_mut(n);
                    out[k as usize] = partial[0];
                }
            }
        }
    }

    /// `dx` = [`activation_grad`], buffer offset by buffer offset (the three share one gapless
    /// layout).
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
        dx[i] = activation_grad(grad[i], output[i], slope, gain);
    }
}

/// One kernel, in `x`'s layout.
pub(super) fn bias_leaky_relu(
    x: FloatTensor<CubeBackend>,
    input_scale: f32,
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
            input_scale,
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
    let output = if last {
        into_channels_last(output)
    } else {
        into_contiguous(output)
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

/// The most units a cube of [`kernels::bias_leaky_relu_grads`] has: a channel count up to this
/// (a power of two) is one channel per unit or fewer.
const MAX_GRAD_UNITS: usize = 1024;
/// Positions per cube of [`kernels::bias_leaky_relu_grads`], at fewest: a cube's sums end in
/// a few values, summed again ([`launch_queued_sums`]).
const MIN_BLOCK: usize = 64;
/// Cubes [`kernels::bias_leaky_relu_grads`] aims for, about eight per multiprocessor of an
/// H100/H200, as the banded weight gradient does.
const TARGET_BLOCKS: usize = 1024;

/// The input gradient of [`bias_leaky_relu`] (or its noisy form, `input_scale` 1) with the bias's
/// gradient and, given the `noise`, the strength's, from one pass over a channels-last `grad` and
/// `output` ([`kernels::bias_leaky_relu_grads`]); the sums of the cubes' shares, which are the
/// bias's and the strength's gradients, are queued ([`launch_queued_sums`] writes them), so
/// that the backward pass sums every activation's shares in a launch or two where each took
/// one (issue #47). `None` where the pass does not apply (another layout, a channel count that
/// is not a power of two up to 1 024, 2³² values or more): the caller runs the separate ops.
#[allow(clippy::type_complexity)]
pub(super) fn gradients(
    output: &FloatTensor<CubeBackend>,
    grad: &FloatTensor<CubeBackend>,
    noise: Option<&FloatTensor<CubeBackend>>,
    input_scale: f32,
    slope: f32,
    gain: f32,
) -> Option<(
    FloatTensor<CubeBackend>,
    FloatTensor<CubeBackend>,
    Option<FloatTensor<CubeBackend>>,
)> {
    let shape @ [batch, channels, height, width] = dims(grad);
    let (pixels, positions) = (height * width, batch * height * width);
    let fits = u32::try_from(grad.shape().num_elements()).is_ok();
    if dims(output) != shape
        || !channels_last(grad)
        || !channels_last(output)
        || !channels.is_power_of_two()
        || channels > MAX_GRAD_UNITS
        || positions == 0
        || !fits
    {
        return None;
    }
    if let Some(noise) = noise {
        assert_eq!(
            noise.shape().num_elements(),
            pixels,
            "one noise value per pixel"
        );
    }
    let units = channels.max(UNITS as usize);
    let lanes = units / channels;
    let block = positions
        .div_ceil(TARGET_BLOCKS)
        .max(MIN_BLOCK)
        .next_multiple_of(lanes);
    let blocks = positions.div_ceil(block);
    let noise = noise.map(|n| into_contiguous(n.clone()));
    let dx = empty_in_layout(grad, shape, true);
    let bias_partials = empty_in_layout(grad, [1, 1, blocks, channels], false);
    let noise_partials = empty_in_layout(grad, [1, 1, 1, blocks], false);
    let u = |v: usize| v as u32;
    kernels::bias_leaky_relu_grads::launch(
        &grad.client,
        cubes_in_rows(blocks),
        CubeDim::new_1d(u(units)),
        output.clone().into_tensor_arg(),
        grad.clone().into_tensor_arg(),
        // Never read without noise: the kernel takes a tensor all the same.
        noise
            .clone()
            .unwrap_or_else(|| grad.clone())
            .into_tensor_arg(),
        dx.clone().into_tensor_arg(),
        bias_partials.clone().into_tensor_arg(),
        noise_partials.clone().into_tensor_arg(),
        u(positions),
        u(pixels).max(1),
        u(channels),
        u(block),
        u(blocks),
        input_scale,
        gain,
        slope,
        noise.is_some(),
        u(units),
    );
    // The sums over the cubes' shares: the shares themselves for a single cube, else queued
    // for `launch_queued_sums`.
    let summed = |shares: FloatTensor<CubeBackend>, values: usize| {
        let table = CubeBackend::float_reshape(shares, Shape::new([blocks, values]));
        if blocks == 1 {
            CubeBackend::float_reshape(table, Shape::new([values]))
        } else {
            queue_sum(table)
        }
    };
    let d_bias = summed(bias_partials, channels);
    let d_strength = noise.is_some().then(|| summed(noise_partials, 1));
    Some((dx, d_bias, d_strength))
}

/// A column sum queued by [`gradients`]: a gapless `[rows, values]` table of cubes' shares
/// and its `[values]` sums, allocated and not yet written.
struct QueuedSum {
    shares: FloatTensor<CubeBackend>,
    sums: FloatTensor<CubeBackend>,
}

thread_local! {
    /// Sums queued by [`gradients`], launched by [`launch_queued_sums`].
    static SUM_QUEUE: RefCell<Vec<QueuedSum>> = const { RefCell::new(Vec::new()) };
}

/// Queues the column sums of `shares` on this thread and returns them, allocated now and
/// written by [`launch_queued_sums`] (one stream per device: before any later kernel reads
/// them).
fn queue_sum(shares: FloatTensor<CubeBackend>) -> FloatTensor<CubeBackend> {
    let [_, values] = shares.shape().dims();
    let sums = CubeBackend::float_reshape(
        empty_in_layout(&shares, [1, 1, 1, values], false),
        Shape::new([values]),
    );
    let queued = QueuedSum {
        shares,
        sums: sums.clone(),
    };
    SUM_QUEUE.with(|q| q.borrow_mut().push(queued));
    sums
}

/// The most tables one launch of [`kernels::sum_columns_many`] sums (a `paper` step's backward
/// passes queue about 390, nine launches); fewer where the device binds fewer tensors per
/// kernel.
const MAX_SUMS_PER_LAUNCH: usize = 48;

/// Launches the sums queued on this thread ([`kernels::sum_columns_many`], up to
/// [`MAX_SUMS_PER_LAUNCH`] tables a launch, a grid layer each). Every launch binds the same
/// number of tables, a short last one made up with fillers (a one-value sum of an unwritten
/// value): the number is a compile-time constant of the kernel and the queue's length varies,
/// so each length would be another kernel to compile (three in a `paper` step, where one will
/// do), as for the bands' sums (`conv::bands::launch_queued_band_sums`).
pub(super) fn launch_queued_sums() {
    let queue: Vec<QueuedSum> = SUM_QUEUE.with(|q| std::mem::take(&mut *q.borrow_mut()));
    let Some(first) = queue.first() else {
        return;
    };
    let (client, device) = (first.shares.client.clone(), first.shares.device.clone());
    let empty = |shape: Shape| {
        empty_device_contiguous_dtype(client.clone(), device.clone(), shape, DType::F32)
    };
    let filler = QueuedSum {
        shares: empty(Shape::new([1, 1])),
        sums: empty(Shape::new([1])),
    };
    let count = items_per_launch(&client, 2, 0, MAX_SUMS_PER_LAUNCH);
    for chunk in queue.chunks(count) {
        let (mut shares, mut sums) = (SequenceArg::new(), SequenceArg::new());
        let fillers = std::iter::repeat_n(&filler, count - chunk.len());
        for q in chunk.iter().chain(fillers) {
            shares.push(q.shares.clone().into_tensor_arg());
            sums.push(q.sums.clone().into_tensor_arg());
        }
        let most_values = chunk
            .iter()
            .map(|q| q.sums.shape().num_elements())
            .max()
            .unwrap_or(0);
        kernels::sum_columns_many::launch(
            &client,
            one_cube_per_channel_in_layers(most_values, "bias", count),
            CubeDim::new_1d(SUM_UNITS),
            shares,
            sums,
            count,
            SUM_UNITS,
        );
    }
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
