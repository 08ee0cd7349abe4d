//! `impl FusedBackend for CubeBackend` (wgpu, CUDA without fusion): each op one kernel, one
//! thread per output value, gathering its few inputs (no atomics, so the backward passes are
//! deterministic).
//!
//! Written with Burn's tensor ops ([`crate::layers::portable`]) these chains are slices,
//! concatenations, scalings and sums: a `paper` step launched ≈ 57 000 kernels, 35 000 of them
//! element-wise, `SliceAssign` or leaky ReLU's `MaskWhere` (BENCHMARKS "Where the device time
//! goes now"), and its host work per launch bounds the step on an H100. Indices are 32-bit: the
//! callers route tensors of 2³² values or more to the portable ops (`fused::available`). Inputs
//! are read row-major after `into_contiguous`; outputs are allocated contiguous (CUDA pitches
//! Burn's ordinary allocations: `f3g_splat::cube`'s module doc). The arithmetic follows
//! `fused::flex` term by term.

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::{CubeCount, CubeDim};
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;

use super::FusedBackend;
use crate::cube_grid::one_thread_per_value;
use crate::layers::LRELU_GAIN;

/// Leaky ReLU's slope below zero.
const SLOPE: f32 = 0.2;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// `out = gain · (x + bias[c])`, times `slope` where that is not positive; `c` is the
    /// channel of value `i` (`(i / plane) % channels`).
    #[cube(launch)]
    pub fn bias_leaky_relu(
        x: &Tensor<f32>,
        bias: &Tensor<f32>,
        out: &mut Tensor<f32>,
        plane: u32,
        channels: u32,
        gain: f32,
        slope: f32,
    ) {
        let i = ABSOLUTE_POS;
        if i >= out.len() {
            terminate!();
        }
        let c = (i as u32 / plane) % channels;
        let pre = x[i] + bias[c as usize];
        let mut value = pre;
        if pre <= 0.0 {
            value = slope * pre;
        }
        out[i] = gain * value;
    }

    /// `dx = grad · gain · (1 where the output is positive, else slope)`.
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
        let mut factor = gain;
        if output[i] <= 0.0 {
            factor = gain * slope;
        }
        dx[i] = grad[i] * factor;
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

    /// `out[p, oy, ox]` (`[planes, 2h, 2w]`) from `x` (`[planes, h, w]`): bilinear along the
    /// row, then along the column.
    #[cube(launch)]
    pub fn upsample2(x: &Tensor<f32>, out: &mut Tensor<f32>, h: u32, w: u32) {
        let i = ABSOLUTE_POS;
        if i >= out.len() {
            terminate!();
        }
        let i = i as u32;
        let ox = i % (2 * w);
        let oy = (i / (2 * w)) % (2 * h);
        let base = (i / (4 * h * w)) * h * w;
        let (x0, x1) = (ox / 2, upsample_neighbour(ox, w));
        let (y0, y1) = (oy / 2, upsample_neighbour(oy, h));
        let row0 = base + y0 * w;
        let row1 = base + y1 * w;
        let near = 0.75 * x[(row0 + x0) as usize] + 0.25 * x[(row0 + x1) as usize];
        let far = 0.75 * x[(row1 + x0) as usize] + 0.25 * x[(row1 + x1) as usize];
        out[i as usize] = 0.75 * near + 0.25 * far;
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

    /// `dx[p, y, x]` (`[planes, h, w]`), the adjoint of [`upsample2`]: the weighted sum of the
    /// up to 4 × 4 outputs of `grad` (`[planes, 2h, 2w]`) that read sample `(y, x)`.
    #[cube(launch)]
    pub fn upsample2_grad(grad: &Tensor<f32>, dx: &mut Tensor<f32>, h: u32, w: u32) {
        let i = ABSOLUTE_POS;
        if i >= dx.len() {
            terminate!();
        }
        let i = i as u32;
        let x = i % w;
        let y = (i / w) % h;
        let base = (i / (h * w)) * 4 * h * w;
        let mut sum = 0.0f32;
        for ty in 0..4u32 {
            let wy = upsample_adjoint_weight(y, h, ty);
            if wy != 0.0 {
                let row = base + (2 * y + ty - 1) * 2 * w;
                let mut along = 0.0f32;
                for tx in 0..4u32 {
                    let wx = upsample_adjoint_weight(x, w, tx);
                    if wx != 0.0 {
                        along += wx * grad[(row + 2 * x + tx - 1) as usize];
                    }
                }
                sum += wy * along;
            }
        }
        dx[i as usize] = sum;
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

    /// `out[p, oy, ox]` (`[planes, out_h, out_w]`) = `Σ taps[ky] · taps[kx] · x[p, oy + ky −
    /// before, ox + kx − before]` over the taps inside `x` (`[planes, h, w]`; zero padding).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn blur(
        x: &Tensor<f32>,
        out: &mut Tensor<f32>,
        h: u32,
        w: u32,
        out_h: u32,
        out_w: u32,
        before: u32,
    ) {
        let i = ABSOLUTE_POS;
        if i >= out.len() {
            terminate!();
        }
        let i = i as u32;
        let ox = i % out_w;
        let oy = (i / out_w) % out_h;
        let base = (i / (out_h * out_w)) * h * w;
        let mut sum = 0.0f32;
        for ky in 0..4u32 {
            let iy = (oy + ky) as i32 - before as i32;
            if iy >= 0 && iy < h as i32 {
                let row = base + iy as u32 * w;
                let mut along = 0.0f32;
                for kx in 0..4u32 {
                    let ix = (ox + kx) as i32 - before as i32;
                    if ix >= 0 && ix < w as i32 {
                        along += blur_tap(kx) * x[(row + ix as u32) as usize];
                    }
                }
                sum += blur_tap(ky) * along;
            }
        }
        out[i as usize] = sum;
    }

    /// `out[p, k, i, j]` (`[planes, 4, h, w]`): sub-band `k ∈ (LL, LH, HL, HH)` of the 2 × 2
    /// block `(p q / r s)` at `(2i, 2j)` of `x` (`[planes, 2h, 2w]`), `½(p ± q ± r ± s)`.
    #[cube(launch)]
    pub fn haar(x: &Tensor<f32>, out: &mut Tensor<f32>, h: u32, w: u32) {
        let o = ABSOLUTE_POS;
        if o >= out.len() {
            terminate!();
        }
        let o = o as u32;
        let j = o % w;
        let i = (o / w) % h;
        let band = (o / (h * w)) % 4;
        let top = (o / (4 * h * w)) * 4 * h * w + 2 * i * 2 * w + 2 * j;
        let bottom = top + 2 * w;
        let (p, q) = (x[top as usize], x[(top + 1) as usize]);
        let (r, s) = (x[bottom as usize], x[(bottom + 1) as usize]);
        // LH negates the bottom row, HL the right column, HH both (s twice).
        let mut sign_q = 1.0f32;
        if band >= 2 {
            sign_q = -1.0f32;
        }
        let mut sign_r = 1.0f32;
        if band % 2 == 1 {
            sign_r = -1.0f32;
        }
        out[o as usize] = 0.5 * (p + sign_q * q + sign_r * r + sign_q * sign_r * s);
    }

    /// `out[p, y, x]` (`[planes, 2h, 2w]`) from the four sub-bands `(a, b, c, d)` of `x`
    /// (`[planes, 4, h, w]`) at `(y / 2, x / 2)`: `½(a ± b ± c ± d)`, the inverse of [`haar`].
    #[cube(launch)]
    pub fn inverse_haar(x: &Tensor<f32>, out: &mut Tensor<f32>, h: u32, w: u32) {
        let o = ABSOLUTE_POS;
        if o >= out.len() {
            terminate!();
        }
        let o = o as u32;
        let xx = o % (2 * w);
        let yy = (o / (2 * w)) % (2 * h);
        let band = (o / (4 * h * w)) * 4 * h * w + (yy / 2) * w + xx / 2;
        let (a, b) = (x[band as usize], x[(band + h * w) as usize]);
        let (c, d) = (
            x[(band + 2 * h * w) as usize],
            x[(band + 3 * h * w) as usize],
        );
        // The bottom row negates LH, the right column HL, the corner both (HH twice).
        let mut sign_b = 1.0f32;
        if yy % 2 == 1 {
            sign_b = -1.0f32;
        }
        let mut sign_c = 1.0f32;
        if xx % 2 == 1 {
            sign_c = -1.0f32;
        }
        out[o as usize] = 0.5 * (a + sign_b * b + sign_c * c + sign_b * sign_c * d);
    }
}

/// A contiguous f32 tensor of `dims` on `like`'s device.
fn empty_like(like: &FloatTensor<CubeBackend>, dims: [usize; 4]) -> FloatTensor<CubeBackend> {
    empty_device_contiguous_dtype(
        like.client.clone(),
        like.device.clone(),
        Shape::new(dims),
        DType::F32,
    )
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
    fn bias_leaky_relu(x: FloatTensor<Self>, bias: FloatTensor<Self>) -> FloatTensor<Self> {
        let shape = dims(&x);
        assert_eq!(bias.shape().dims::<1>(), [shape[1]], "one bias per channel");
        let (x, bias) = (into_contiguous(x), into_contiguous(bias));
        let out = empty_like(&x, shape);
        one_thread_per_output(out, &x, |cubes, cube, out| {
            kernels::bias_leaky_relu::launch(
                &x.client,
                cubes,
                cube,
                x.clone().into_tensor_arg(),
                bias.into_tensor_arg(),
                out.into_tensor_arg(),
                u32_of(shape[2] * shape[3]).max(1),
                u32_of(shape[1]).max(1),
                LRELU_GAIN,
                SLOPE,
            )
        })
    }

    fn bias_leaky_relu_grad(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let shape = dims(&grad);
        assert_eq!(dims(&output), shape, "output and gradient shapes");
        let (output, grad) = (into_contiguous(output), into_contiguous(grad));
        let dx = empty_like(&grad, shape);
        one_thread_per_output(dx, &grad, |cubes, cube, dx| {
            kernels::bias_leaky_relu_grad::launch(
                &grad.client,
                cubes,
                cube,
                output.into_tensor_arg(),
                grad.clone().into_tensor_arg(),
                dx.into_tensor_arg(),
                LRELU_GAIN,
                SLOPE,
            )
        })
    }

    /// Burn's reductions (the patched `burn-cubecl` picks a plane per channel for the long
    /// axis), the batch summed only where there is more than one.
    fn channel_sum(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, height, width] = dims(&x);
        let planes = Self::float_reshape(x, Shape::new([batch, channels, height * width]));
        let mut sums = Self::float_sum_dim(planes, 2);
        if batch > 1 {
            sums = Self::float_sum_dim(sums, 0);
        }
        Self::float_reshape(sums, Shape::new([channels]))
    }

    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, h, w] = dims(&x);
        let x = into_contiguous(x);
        let out = empty_like(&x, [batch, channels, 2 * h, 2 * w]);
        one_thread_per_output(out, &x, |cubes, cube, out| {
            kernels::upsample2::launch(
                &x.client,
                cubes,
                cube,
                x.clone().into_tensor_arg(),
                out.into_tensor_arg(),
                u32_of(h),
                u32_of(w),
            )
        })
    }

    fn upsample2_grad(grad: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels, h2, w2] = dims(&grad);
        let (h, w) = (h2 / 2, w2 / 2);
        let grad = into_contiguous(grad);
        let dx = empty_like(&grad, [batch, channels, h, w]);
        one_thread_per_output(dx, &grad, |cubes, cube, dx| {
            kernels::upsample2_grad::launch(
                &grad.client,
                cubes,
                cube,
                grad.clone().into_tensor_arg(),
                dx.into_tensor_arg(),
                u32_of(h),
                u32_of(w),
            )
        })
    }

    fn blur(x: FloatTensor<Self>, before: usize, after: usize) -> FloatTensor<Self> {
        let [batch, channels, h, w] = dims(&x);
        assert!(before <= 3 && after <= 3, "blur padding at most 3");
        let grown = |n: usize| (n + before + after).saturating_sub(3);
        let (out_h, out_w) = (grown(h), grown(w));
        let x = into_contiguous(x);
        let out = empty_like(&x, [batch, channels, out_h, out_w]);
        one_thread_per_output(out, &x, |cubes, cube, out| {
            kernels::blur::launch(
                &x.client,
                cubes,
                cube,
                x.clone().into_tensor_arg(),
                out.into_tensor_arg(),
                u32_of(h),
                u32_of(w),
                u32_of(out_h),
                u32_of(out_w),
                u32_of(before),
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
        let x = into_contiguous(x);
        let out = empty_like(&x, [batch, 4 * channels, h, w]);
        one_thread_per_output(out, &x, |cubes, cube, out| {
            kernels::haar::launch(
                &x.client,
                cubes,
                cube,
                x.clone().into_tensor_arg(),
                out.into_tensor_arg(),
                u32_of(h),
                u32_of(w),
            )
        })
    }

    fn inverse_haar(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let [batch, channels4, h, w] = dims(&x);
        assert!(
            channels4 % 4 == 0,
            "Haar synthesis of four sub-bands per channel"
        );
        let x = into_contiguous(x);
        let out = empty_like(&x, [batch, channels4 / 4, 2 * h, 2 * w]);
        one_thread_per_output(out, &x, |cubes, cube, out| {
            kernels::inverse_haar::launch(
                &x.client,
                cubes,
                cube,
                x.clone().into_tensor_arg(),
                out.into_tensor_arg(),
                u32_of(h),
                u32_of(w),
            )
        })
    }
}
