//! `impl FusedBackend for CubeBackend` (wgpu, CUDA without fusion): each op one kernel, one
//! thread per output value, gathering its few inputs (no atomics, so the backward passes are
//! deterministic).
//!
//! Written with Burn's tensor ops ([`crate::layers::portable`]) these chains are slices,
//! concatenations, scalings and sums: a `paper` step launched ≈ 57 000 kernels, 35 000 of them
//! element-wise, `SliceAssign` or leaky ReLU's `MaskWhere` (BENCHMARKS "Where the device time
//! goes now"), and its host work per launch bounds the step on an H100. Indices are 32-bit: the
//! callers route tensors of 2³² values or more to the portable ops (`fused::runs`).
//!
//! Layouts: every op reads and writes either of `crate::cube_layout`'s two and keeps its input's
//! (anything else is made row-major first), so the activation after a convolution goes through
//! bias + leaky ReLU, blur or up-sampling into the next convolution in the channels-last layout
//! the convolutions compute in, without copies to row-major and back. The arithmetic follows
//! `fused::flex` term by term.

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::{CubeCount, CubeDim};
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;
use burn_cubecl::ops::{permute_nchw_to_nhwc, permute_nhwc_to_nchw};

use super::{DEMODULATION_EPSILON, FusedBackend};
use crate::cube_grid::{UNITS, one_thread_per_value};
use crate::cube_layout::{channels_last, empty_in_layout, readable};

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

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

    /// The sample `2i ∓ 1`'s neighbour along an axis of `n` samples: output `o` of the ×2
    /// up-sampling blends sample `o / 2` (¾) with this one (¼), the edge repeated.
    #[cube]
    fn upsample_neighbour(o: u32, n: u32) -> u32 {
        let i = o / 2;
        let mut neighbour = i;
        if o % 2 == 1 {
            if i + 1 < n {
                neighbour = i + 1;
            }
        } else if i > 0 {
            neighbour = i - 1;
        }
        neighbour
    }

    /// Where a value sits in a `[B, C, H, W]` tensor.
    #[derive(CubeType)]
    struct Position {
        batch: u32,
        channel: u32,
        y: u32,
        x: u32,
    }

    /// The position of buffer offset `i` in a gapless `[B, channels, h, w]` tensor, stored
    /// row-major or, with `channels_last`, as `[B, h, w, channels]`.
    #[cube]
    fn position(
        i: u32,
        channels: u32,
        h: u32,
        w: u32,
        #[comptime] channels_last: bool,
    ) -> Position {
        if comptime![channels_last] {
            Position {
                batch: i / (channels * w * h),
                channel: i % channels,
                y: (i / (channels * w)) % h,
                x: (i / channels) % w,
            }
        } else {
            Position {
                batch: i / (w * h * channels),
                channel: (i / (w * h)) % channels,
                y: (i / w) % h,
                x: i % w,
            }
        }
    }

    /// The buffer offset of `(batch, channel, y, x)` in the tensor [`position`] describes.
    #[allow(clippy::too_many_arguments)]
    #[cube]
    fn offset(
        batch: u32,
        channel: u32,
        y: u32,
        x: u32,
        channels: u32,
        h: u32,
        w: u32,
        #[comptime] channels_last: bool,
    ) -> usize {
        let mut o = ((batch * channels + channel) * h + y) * w + x;
        if comptime![channels_last] {
            o = ((batch * h + y) * w + x) * channels + channel;
        }
        o as usize
    }

    /// `out` (`[B, C, 2h, 2w]`) from `x` (`[B, C, h, w]`), both in one layout: bilinear along
    /// the row, then along the column.
    #[cube(launch)]
    pub fn upsample2(
        x: &Tensor<f32>,
        out: &mut Tensor<f32>,
        channels: u32,
        h: u32,
        w: u32,
        #[comptime] channels_last: bool,
    ) {
        let i = ABSOLUTE_POS;
        if i >= out.len() {
            terminate!();
        }
        let p = position(i as u32, channels, 2 * h, 2 * w, channels_last);
        let (x0, x1) = (p.x / 2, upsample_neighbour(p.x, w));
        let (y0, y1) = (p.y / 2, upsample_neighbour(p.y, h));
        let (b, c) = (p.batch, p.channel);
        let near = 0.75 * x[offset(b, c, y0, x0, channels, h, w, channels_last)]
            + 0.25 * x[offset(b, c, y0, x1, channels, h, w, channels_last)];
        let far = 0.75 * x[offset(b, c, y1, x0, channels, h, w, channels_last)]
            + 0.25 * x[offset(b, c, y1, x1, channels, h, w, channels_last)];
        out[i] = 0.75 * near + 0.25 * far;
    }

    /// The weight with which output `2i + tap − 1` of the ×2 up-sampling (along an axis of `n`
    /// samples) reads sample `i`: ¼ from the odd output before and the even one after, ¾ from
    /// its own two, the edge outputs reading their edge sample twice.
    #[cube]
    fn upsample_adjoint_weight(i: u32, n: u32, tap: u32) -> f32 {
        let mut weight = 0.0f32;
        if tap == 0 {
            if i > 0 {
                weight = 0.25;
            }
        } else if tap == 1 {
            weight = 0.75;
            if i == 0 {
                weight = 1.0;
            }
        } else if tap == 2 {
            weight = 0.75;
            if i + 1 == n {
                weight = 1.0;
            }
        } else if i + 1 < n {
            weight = 0.25;
        }
        weight
    }

    /// `dx` (`[B, C, h, w]`), the adjoint of [`upsample2`]: the weighted sum of the up to 4 × 4
    /// outputs of `grad` (`[B, C, 2h, 2w]`, the same layout) that read sample `(y, x)`.
    #[cube(launch)]
    pub fn upsample2_grad(
        grad: &Tensor<f32>,
        dx: &mut Tensor<f32>,
        channels: u32,
        h: u32,
        w: u32,
        #[comptime] channels_last: bool,
    ) {
        let i = ABSOLUTE_POS;
        if i >= dx.len() {
            terminate!();
        }
        let p = position(i as u32, channels, h, w, channels_last);
        let mut sum = 0.0f32;
        for ty in 0..4u32 {
            let wy = upsample_adjoint_weight(p.y, h, ty);
            if wy != 0.0 {
                let oy = 2 * p.y + ty - 1;
                let mut along = 0.0f32;
                for tx in 0..4u32 {
                    let wx = upsample_adjoint_weight(p.x, w, tx);
                    if wx != 0.0 {
                        let ox = 2 * p.x + tx - 1;
                        let at = offset(
                            p.batch,
                            p.channel,
                            oy,
                            ox,
                            channels,
                            2 * h,
                            2 * w,
                            channels_last,
                        );
                        along += wx * grad[at];
                    }
                }
                sum += wy * along;
            }
        }
        dx[i] = sum;
    }

    /// `out` (`[B, C, h, w]`) from `x` (`[B, C, height, width]`, the same layout, `h = ⌊height / 2⌋`,
    /// `w = ⌊width / 2⌋`): the mean of each 2 × 2 block.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn downsample2(
        x: &Tensor<f32>,
        out: &mut Tensor<f32>,
        channels: u32,
        height: u32,
        width: u32,
        h: u32,
        w: u32,
        #[comptime] channels_last: bool,
    ) {
        let i = ABSOLUTE_POS;
        if i >= out.len() {
            terminate!();
        }
        let at = position(i as u32, channels, h, w, channels_last);
        let (b, c, y, x0) = (at.batch, at.channel, 2 * at.y, 2 * at.x);
        let p = x[offset(b, c, y, x0, channels, height, width, channels_last)];
        let q = x[offset(b, c, y, x0 + 1, channels, height, width, channels_last)];
        let r = x[offset(b, c, y + 1, x0, channels, height, width, channels_last)];
        let s = x[offset(b, c, y + 1, x0 + 1, channels, height, width, channels_last)];
        out[i] = 0.25 * (p + q + r + s);
    }

    /// `dx` (`[B, C, height, width]`), the adjoint of [`downsample2`]: a quarter of the gradient
    /// (`[B, C, h, w]`, the same layout) of the block a value falls in, zero outside the blocks.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn downsample2_grad(
        grad: &Tensor<f32>,
        dx: &mut Tensor<f32>,
        channels: u32,
        height: u32,
        width: u32,
        h: u32,
        w: u32,
        #[comptime] channels_last: bool,
    ) {
        let i = ABSOLUTE_POS;
        if i >= dx.len() {
            terminate!();
        }
        let at = position(i as u32, channels, height, width, channels_last);
        let (y, x) = (at.y / 2, at.x / 2);
        let mut value = 0.0f32;
        if y < h && x < w {
            let o = offset(at.batch, at.channel, y, x, channels, h, w, channels_last);
            value = 0.25 * grad[o];
        }
        dx[i] = value;
    }

    /// Tap `k` of the `[1, 3, 3, 1] / 8` filter.
    #[cube]
    fn blur_tap(k: u32) -> f32 {
        let mut tap = 0.375f32;
        if k == 0 || k == 3 {
            tap = 0.125;
        }
        tap
    }

    /// `out` (`[B, C, out_h, out_w]`) = `Σ taps[ky] · taps[kx] · x[b, c, oy + ky − before, ox + kx
    /// − before]` over the taps inside `x` (`[B, C, h, w]`, the same layout; zero padding).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn blur(
        x: &Tensor<f32>,
        out: &mut Tensor<f32>,
        channels: u32,
        h: u32,
        w: u32,
        out_h: u32,
        out_w: u32,
        before: u32,
        #[comptime] channels_last: bool,
    ) {
        let i = ABSOLUTE_POS;
        if i >= out.len() {
            terminate!();
        }
        let p = position(i as u32, channels, out_h, out_w, channels_last);
        let mut sum = 0.0f32;
        for ky in 0..4u32 {
            let iy = (p.y + ky) as i32 - before as i32;
            if iy >= 0 && iy < h as i32 {
                let mut along = 0.0f32;
                for kx in 0..4u32 {
                    let ix = (p.x + kx) as i32 - before as i32;
                    if ix >= 0 && ix < w as i32 {
                        let at = offset(
                            p.batch,
                            p.channel,
                            iy as u32,
                            ix as u32,
                            channels,
                            h,
                            w,
                            channels_last,
                        );
                        along += blur_tap(kx) * x[at];
                    }
                }
                sum += blur_tap(ky) * along;
            }
        }
        out[i] = sum;
    }

    /// `out` (`[B, 4C, h, w]`): channel `4c + k` holds sub-band `k ∈ (LL, LH, HL, HH)` of the
    /// 2 × 2 block `(p q / r s)` at `(2y, 2x)` of channel `c` of `x` (`[B, C, 2h, 2w]`, the same
    /// layout), `½(p ± q ± r ± s)`.
    #[cube(launch)]
    pub fn haar(
        x: &Tensor<f32>,
        out: &mut Tensor<f32>,
        channels: u32,
        h: u32,
        w: u32,
        #[comptime] channels_last: bool,
    ) {
        let o = ABSOLUTE_POS;
        if o >= out.len() {
            terminate!();
        }
        let at = position(o as u32, 4 * channels, h, w, channels_last);
        let (b, c, band) = (at.batch, at.channel / 4, at.channel % 4);
        let (y, x0) = (2 * at.y, 2 * at.x);
        let (h2, w2) = (2 * h, 2 * w);
        let p = x[offset(b, c, y, x0, channels, h2, w2, channels_last)];
        let q = x[offset(b, c, y, x0 + 1, channels, h2, w2, channels_last)];
        let r = x[offset(b, c, y + 1, x0, channels, h2, w2, channels_last)];
        let s = x[offset(b, c, y + 1, x0 + 1, channels, h2, w2, channels_last)];
        // LH negates the bottom row, HL the right column, HH both (s twice).
        let mut sign_q = 1.0f32;
        if band >= 2 {
            sign_q = -1.0f32;
        }
        let mut sign_r = 1.0f32;
        if band % 2 == 1 {
            sign_r = -1.0f32;
        }
        out[o] = 0.5 * (p + sign_q * q + sign_r * r + sign_q * sign_r * s);
    }

    /// `out` (`[B, C, 2h, 2w]`) from the four sub-bands `(a, b, c, d)` of `x` (`[B, 4C, h, w]`,
    /// the same layout) at `(y / 2, x / 2)`: `½(a ± b ± c ± d)`, the inverse of [`haar`].
    #[cube(launch)]
    pub fn inverse_haar(
        x: &Tensor<f32>,
        out: &mut Tensor<f32>,
        channels: u32,
        h: u32,
        w: u32,
        #[comptime] channels_last: bool,
    ) {
        let o = ABSOLUTE_POS;
        if o >= out.len() {
            terminate!();
        }
        let at = position(o as u32, channels, 2 * h, 2 * w, channels_last);
        let (batch, first) = (at.batch, 4 * at.channel);
        let (y, x0) = (at.y / 2, at.x / 2);
        let c4 = 4 * channels;
        let a = x[offset(batch, first, y, x0, c4, h, w, channels_last)];
        let b = x[offset(batch, first + 1, y, x0, c4, h, w, channels_last)];
        let c = x[offset(batch, first + 2, y, x0, c4, h, w, channels_last)];
        let d = x[offset(batch, first + 3, y, x0, c4, h, w, channels_last)];
        // The bottom row negates LH, the right column HL, the corner both (HH twice).
        let mut sign_b = 1.0f32;
        if at.y % 2 == 1 {
            sign_b = -1.0f32;
        }
        let mut sign_c = 1.0f32;
        if at.x % 2 == 1 {
            sign_c = -1.0f32;
        }
        out[o] = 0.5 * (a + sign_b * b + sign_c * c + sign_b * sign_c * d);
    }

    /// Sums `partial` (one value per unit, `units` a power of two) into `partial[0]`, pairwise
    /// with doubling strides; every unit must call it.
    #[cube]
    fn cube_sum(partial: &mut Shared<[f32]>, #[comptime] units: u32) {
        let t = UNIT_POS;
        sync_cube();
        let mut stride = 1u32;
        while stride < units {
            if t & (2 * stride - 1) == 0 {
                partial[t as usize] += partial[(t + stride) as usize];
            }
            sync_cube();
            stride *= 2;
        }
    }

    /// One cube per output channel `o` (`CUBE_POS_X`): `out[o, j] = weight[o, j] · style[j /
    /// taps] · scale`, times `(Σ_j (weight · style · scale)² + epsilon)^(−½)` if `demodulate`
    /// (`j` over the channel's `per_output` values).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn modulate(
        weight: &Tensor<f32>,
        style: &Tensor<f32>,
        out: &mut Tensor<f32>,
        per_output: u32,
        taps: u32,
        scale: f32,
        epsilon: f32,
        #[comptime] demodulate: bool,
        #[comptime] units: u32,
    ) {
        let t = UNIT_POS;
        let base = CUBE_POS_X * per_output;
        let mut partial = Shared::<[f32]>::new_slice(comptime![units as usize]);
        let mut d = 1.0f32;
        if comptime![demodulate] {
            let mut sum = 0.0f32;
            let mut j = t;
            while j < per_output {
                let u = weight[(base + j) as usize] * style[(j / taps) as usize] * scale;
                sum += u * u;
                j += units;
            }
            partial[t as usize] = sum;
            cube_sum(&mut partial, units);
            d = 1.0 / f32::sqrt(partial[0] + epsilon);
        }
        let mut j = t;
        while j < per_output {
            let u = weight[(base + j) as usize] * style[(j / taps) as usize] * scale;
            out[(base + j) as usize] = u * d;
            j += units;
        }
    }

    /// The backward of [`modulate`], one cube per output channel: `d_weight` and
    /// `terms = ∂u · weight · scale`, whose sums over output channels and taps are the style's
    /// gradient ([`style_grad`]).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn modulate_grad(
        weight: &Tensor<f32>,
        style: &Tensor<f32>,
        grad: &Tensor<f32>,
        d_weight: &mut Tensor<f32>,
        terms: &mut Tensor<f32>,
        per_output: u32,
        taps: u32,
        scale: f32,
        epsilon: f32,
        #[comptime] demodulate: bool,
        #[comptime] units: u32,
    ) {
        let t = UNIT_POS;
        let base = CUBE_POS_X * per_output;
        let mut squares = Shared::<[f32]>::new_slice(comptime![units as usize]);
        let mut projections = Shared::<[f32]>::new_slice(comptime![units as usize]);
        let mut d = 1.0f32;
        let mut projection = 0.0f32;
        if comptime![demodulate] {
            let mut uu = 0.0f32;
            let mut gu = 0.0f32;
            let mut j = t;
            while j < per_output {
                let u = weight[(base + j) as usize] * style[(j / taps) as usize] * scale;
                uu += u * u;
                gu += grad[(base + j) as usize] * u;
                j += units;
            }
            squares[t as usize] = uu;
            projections[t as usize] = gu;
            cube_sum(&mut squares, units);
            cube_sum(&mut projections, units);
            d = 1.0 / f32::sqrt(squares[0] + epsilon);
            projection = projections[0] * d * d;
        }
        let mut j = t;
        while j < per_output {
            let s = style[(j / taps) as usize];
            let w = weight[(base + j) as usize];
            let u = w * s * scale;
            let d_u = d * (grad[(base + j) as usize] - u * projection);
            d_weight[(base + j) as usize] = d_u * s * scale;
            terms[(base + j) as usize] = d_u * w * scale;
            j += units;
        }
    }

    /// `d_style[i] = Σ_{o, k} terms[o, i·taps + k]`, one thread per input channel.
    #[cube(launch)]
    pub fn style_grad(
        terms: &Tensor<f32>,
        d_style: &mut Tensor<f32>,
        outputs: u32,
        per_output: u32,
        taps: u32,
    ) {
        let i = ABSOLUTE_POS;
        if i >= d_style.len() {
            terminate!();
        }
        let first = i as u32 * taps;
        let mut sum = 0.0f32;
        for o in 0..outputs {
            for k in 0..taps {
                sum += terms[(o * per_output + first + k) as usize];
            }
        }
        d_style[i] = sum;
    }
}

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
        bias: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self> {
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

    /// In the gradient's layout; the output is copied to it where the two differ.
    fn bias_leaky_relu_grad(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self> {
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
    /// where there is more than one, the batch.
    fn channel_sum(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, height, width] = dims(&x);
        if channels_last(&x) {
            let rows = Self::float_reshape(
                permute_nchw_to_nhwc(x),
                Shape::new([batch * height * width, channels]),
            );
            return Self::float_reshape(Self::float_sum_dim(rows, 0), Shape::new([channels]));
        }
        let planes = Self::float_reshape(x, Shape::new([batch, channels, height * width]));
        let mut sums = Self::float_sum_dim(planes, 2);
        if batch > 1 {
            sums = Self::float_sum_dim(sums, 0);
        }
        Self::float_reshape(sums, Shape::new([channels]))
    }

    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, h, w] = dims(&x);
        let (x, last) = readable(x);
        let out = empty_in_layout(&x, [batch, channels, 2 * h, 2 * w], last);
        one_thread_per_output(out, &x, |cubes, cube, out| {
            kernels::upsample2::launch(
                &x.client,
                cubes,
                cube,
                x.clone().into_tensor_arg(),
                out.into_tensor_arg(),
                u32_of(channels),
                u32_of(h),
                u32_of(w),
                last,
            )
        })
    }

    fn upsample2_grad(grad: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, h2, w2] = dims(&grad);
        let (h, w) = (h2 / 2, w2 / 2);
        let (grad, last) = readable(grad);
        let dx = empty_in_layout(&grad, [batch, channels, h, w], last);
        one_thread_per_output(dx, &grad, |cubes, cube, dx| {
            kernels::upsample2_grad::launch(
                &grad.client,
                cubes,
                cube,
                grad.clone().into_tensor_arg(),
                dx.into_tensor_arg(),
                u32_of(channels),
                u32_of(h),
                u32_of(w),
                last,
            )
        })
    }

    fn downsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, height, width] = dims(&x);
        let (h, w) = (height / 2, width / 2);
        let (x, last) = readable(x);
        let out = empty_in_layout(&x, [batch, channels, h, w], last);
        one_thread_per_output(out, &x, |cubes, cube, out| {
            kernels::downsample2::launch(
                &x.client,
                cubes,
                cube,
                x.clone().into_tensor_arg(),
                out.into_tensor_arg(),
                u32_of(channels),
                u32_of(height),
                u32_of(width),
                u32_of(h),
                u32_of(w),
                last,
            )
        })
    }

    fn downsample2_grad(grad: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self> {
        let [batch, channels, h, w] = dims(&grad);
        assert_eq!(
            [h, w],
            [height / 2, width / 2],
            "the gradient of a 2 × 2 mean"
        );
        let (grad, last) = readable(grad);
        let dx = empty_in_layout(&grad, [batch, channels, height, width], last);
        one_thread_per_output(dx, &grad, |cubes, cube, dx| {
            kernels::downsample2_grad::launch(
                &grad.client,
                cubes,
                cube,
                grad.clone().into_tensor_arg(),
                dx.into_tensor_arg(),
                u32_of(channels),
                u32_of(height),
                u32_of(width),
                u32_of(h),
                u32_of(w),
                last,
            )
        })
    }

    fn blur(x: FloatTensor<Self>, before: usize, after: usize) -> FloatTensor<Self> {
        let [batch, channels, h, w] = dims(&x);
        assert!(before <= 3 && after <= 3, "blur padding at most 3");
        let grown = |n: usize| (n + before + after).saturating_sub(3);
        let (out_h, out_w) = (grown(h), grown(w));
        let (x, last) = readable(x);
        let out = empty_in_layout(&x, [batch, channels, out_h, out_w], last);
        one_thread_per_output(out, &x, |cubes, cube, out| {
            kernels::blur::launch(
                &x.client,
                cubes,
                cube,
                x.clone().into_tensor_arg(),
                out.into_tensor_arg(),
                u32_of(channels),
                u32_of(h),
                u32_of(w),
                u32_of(out_h),
                u32_of(out_w),
                u32_of(before),
                last,
            )
        })
    }

    fn haar(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, height, width] = dims(&x);
        assert!(
            height % 2 == 0 && width % 2 == 0,
            "Haar analysis of even sizes"
        );
        let (h, w) = (height / 2, width / 2);
        let (x, last) = readable(x);
        let out = empty_in_layout(&x, [batch, 4 * channels, h, w], last);
        one_thread_per_output(out, &x, |cubes, cube, out| {
            kernels::haar::launch(
                &x.client,
                cubes,
                cube,
                x.clone().into_tensor_arg(),
                out.into_tensor_arg(),
                u32_of(channels),
                u32_of(h),
                u32_of(w),
                last,
            )
        })
    }

    fn inverse_haar(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels4, h, w] = dims(&x);
        assert!(
            channels4 % 4 == 0,
            "Haar synthesis of four sub-bands per channel"
        );
        let (x, last) = readable(x);
        let out = empty_in_layout(&x, [batch, channels4 / 4, 2 * h, 2 * w], last);
        one_thread_per_output(out, &x, |cubes, cube, out| {
            kernels::inverse_haar::launch(
                &x.client,
                cubes,
                cube,
                x.clone().into_tensor_arg(),
                out.into_tensor_arg(),
                u32_of(channels4 / 4),
                u32_of(h),
                u32_of(w),
                last,
            )
        })
    }

    fn modulate(
        weight: FloatTensor<Self>,
        style: FloatTensor<Self>,
        scale: f32,
        demodulate: bool,
    ) -> FloatTensor<Self> {
        let shape = dims(&weight);
        assert_eq!(
            style.shape().dims::<1>(),
            [shape[1]],
            "one style value per input"
        );
        let (weight, style) = (into_contiguous(weight), into_contiguous(style));
        let out = empty_in_layout(&weight, shape, false);
        if let Some((cubes, cube, per_output, taps)) = per_output_channel(shape) {
            kernels::modulate::launch(
                &weight.client,
                cubes,
                cube,
                weight.clone().into_tensor_arg(),
                style.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                per_output,
                taps,
                scale,
                DEMODULATION_EPSILON,
                demodulate,
                UNITS,
            );
        }
        out
    }

    fn modulate_grad(
        weight: FloatTensor<Self>,
        style: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        scale: f32,
        demodulate: bool,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let shape = dims(&weight);
        assert_eq!(dims(&grad), shape, "weight and gradient shapes");
        let [weight, style, grad] = [weight, style, grad].map(into_contiguous);
        let d_weight = empty_in_layout(&weight, shape, false);
        let terms = empty_in_layout(&weight, shape, false);
        let d_style = empty_device_contiguous_dtype(
            weight.client.clone(),
            weight.device.clone(),
            Shape::new([shape[1]]),
            DType::F32,
        );
        let Some((cubes, cube, per_output, taps)) = per_output_channel(shape) else {
            // A weight without values: no style value has any effect.
            let zeros =
                Self::float_zeros(Shape::new([shape[1]]), &weight.device, DType::F32.into());
            return (d_weight, zeros);
        };
        kernels::modulate_grad::launch(
            &weight.client,
            cubes,
            cube,
            weight.clone().into_tensor_arg(),
            style.into_tensor_arg(),
            grad.into_tensor_arg(),
            d_weight.clone().into_tensor_arg(),
            terms.clone().into_tensor_arg(),
            per_output,
            taps,
            scale,
            DEMODULATION_EPSILON,
            demodulate,
            UNITS,
        );
        let (cubes, cube) = one_thread_per_value(shape[1]);
        kernels::style_grad::launch(
            &weight.client,
            cubes,
            cube,
            terms.into_tensor_arg(),
            d_style.clone().into_tensor_arg(),
            u32_of(shape[0]),
            per_output,
            taps,
        );
        (d_weight, d_style)
    }
}

/// The launch of [`kernels::modulate`] and its gradient for a weight of `shape`: one cube of
/// [`UNITS`] per output channel, the values per output channel and the taps per input channel
/// as kernel arguments; `None` for a weight without values.
fn per_output_channel(shape: [usize; 4]) -> Option<(CubeCount, CubeDim, u32, u32)> {
    let [c_out, c_in, kh, kw] = shape;
    let per_output = c_in * kh * kw;
    if c_out * per_output == 0 {
        return None;
    }
    u32_of(c_out * per_output);
    let cubes = u32::try_from(c_out)
        .ok()
        .filter(|&c| c <= 65_535)
        .expect("at most 65 535 output channels");
    Some((
        CubeCount::Static(cubes, 1, 1),
        CubeDim::new_1d(UNITS),
        u32_of(per_output),
        u32_of(kh * kw),
    ))
}
