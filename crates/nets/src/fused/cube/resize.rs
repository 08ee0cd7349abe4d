//! Bilinear resizing to any size (`align_corners = false`) and its adjoint, one thread per
//! output value: the forward blends its four taps, the adjoint sums, for each input value, the
//! outputs whose taps include it (a short range along each axis, found from the same tap
//! arithmetic as the forward's, so the two agree to the weight). Gathered, not scattered: no
//! atomics, deterministic. The input is read through its strides (a slice of a concatenation's
//! gradient as it is); the output is channels-last where the input is (pitched or not), else
//! row-major.

use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;

use super::{dims, one_thread_per_output, u32_of};
use crate::cube_layout::{empty_in_layout, pixel_stride};

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use crate::fused::cube::position::{position, strided};

    /// Output `o`'s taps along an axis of `n` samples resized with `ratio = n / outputs`: the
    /// lower sample, the upper one and the upper's weight. The source coordinate
    /// `(o + ½)·ratio − ½` is clamped at 0 and the upper sample at the last (Burn's and
    /// PyTorch's bilinear).
    #[cube]
    fn taps(o: u32, ratio: f32, n: u32) -> (u32, u32, f32) {
        let source = f32::max((f32::cast_from(o) + 0.5f32) * ratio - 0.5f32, 0.0f32);
        let lower = u32::min(u32::cast_from(f32::floor(source)), n - 1);
        let mut upper = lower + 1;
        if upper > n - 1 {
            upper = n - 1;
        }
        (lower, upper, source - f32::cast_from(lower))
    }

    /// The weight with which output `o` reads sample `i` (both taps may be `i` at the edge).
    #[cube]
    fn weight(o: u32, i: u32, ratio: f32, n: u32) -> f32 {
        let (lower, upper, t) = taps(o, ratio, n);
        let mut w = 0.0f32;
        if lower == i {
            w += 1.0f32 - t;
        }
        if upper == i {
            w += t;
        }
        w
    }

    /// The outputs (of `outputs`) that may read sample `i` of `n`, as `first..=last`: those
    /// whose source coordinate lies in `[i − 1, i + 1)`, widened by one each side against
    /// rounding (a wider range only adds zero weights), the first and last sample taking
    /// every output clamped onto them.
    #[cube]
    fn readers(i: u32, ratio: f32, n: u32, outputs: u32) -> (u32, u32) {
        let fi = f32::cast_from(i);
        let mut first = 0u32;
        if i > 0 {
            let from = f32::floor((fi - 0.5f32) / ratio - 0.5f32) - 1.0f32;
            first = u32::cast_from(f32::max(from, 0.0f32));
        }
        let mut last = outputs - 1;
        if i + 1 < n {
            let to = f32::ceil((fi + 1.5f32) / ratio - 0.5f32) + 1.0f32;
            last = u32::min(u32::cast_from(f32::max(to, 0.0f32)), outputs - 1);
        }
        (first, last)
    }

    /// `out` (`[B, C, height, width]`, channels-last with `channels_last`) from `x`
    /// (`[B, C, h, w]`, any strides).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn resize(
        x: &Tensor<f32>,
        out: &mut Tensor<f32>,
        channels: u32,
        h: u32,
        w: u32,
        height: u32,
        width: u32,
        ratio_y: f32,
        ratio_x: f32,
        #[comptime] channels_last: bool,
    ) {
        let i = ABSOLUTE_POS;
        if i >= out.len() {
            terminate!();
        }
        let p = position(i as u32, channels, height, width, channels_last);
        let (y0, y1, ty) = taps(p.y, ratio_y, h);
        let (x0, x1, tx) = taps(p.x, ratio_x, w);
        let (b, c) = (p.batch, p.channel);
        let top = (1.0f32 - tx) * x[strided(x, b, c, y0, x0)] + tx * x[strided(x, b, c, y0, x1)];
        let bottom = (1.0f32 - tx) * x[strided(x, b, c, y1, x0)] + tx * x[strided(x, b, c, y1, x1)];
        out[i] = (1.0f32 - ty) * top + ty * bottom;
    }

    /// `dx` (`[B, C, h, w]`, channels-last with `channels_last`), the adjoint of [`resize`]: for
    /// each input value the weighted sum of the outputs of `grad` (`[B, C, height, width]`, any
    /// strides) that read it.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn resize_grad(
        grad: &Tensor<f32>,
        dx: &mut Tensor<f32>,
        channels: u32,
        h: u32,
        w: u32,
        height: u32,
        width: u32,
        ratio_y: f32,
        ratio_x: f32,
        #[comptime] channels_last: bool,
    ) {
        let i = ABSOLUTE_POS;
        if i >= dx.len() {
            terminate!();
        }
        let p = position(i as u32, channels, h, w, channels_last);
        let (first_y, last_y) = readers(p.y, ratio_y, h, height);
        let (first_x, last_x) = readers(p.x, ratio_x, w, width);
        let mut sum = 0.0f32;
        for oy in first_y..last_y + 1 {
            let wy = weight(oy, p.y, ratio_y, h);
            if wy != 0.0f32 {
                let mut along = 0.0f32;
                for ox in first_x..last_x + 1 {
                    let wx = weight(ox, p.x, ratio_x, w);
                    if wx != 0.0f32 {
                        along += wx * grad[strided(grad, p.batch, p.channel, oy, ox)];
                    }
                }
                sum += wy * along;
            }
        }
        dx[i] = sum;
    }
}

/// `n / outputs` as the kernels' f32 ratio.
fn ratio(n: usize, outputs: usize) -> f32 {
    (n as f64 / outputs as f64) as f32
}

/// One kernel; the output channels-last where `x` is.
pub(super) fn resize(
    x: FloatTensor<CubeBackend>,
    height: usize,
    width: usize,
) -> FloatTensor<CubeBackend> {
    let [batch, channels, h, w] = dims(&x);
    let last = pixel_stride(&x).is_some();
    let out = empty_in_layout(&x, [batch, channels, height, width], last);
    one_thread_per_output(out, &x, |cubes, cube, out| {
        kernels::resize::launch(
            &x.client,
            cubes,
            cube,
            x.clone().into_tensor_arg(),
            out.into_tensor_arg(),
            u32_of(channels),
            u32_of(h),
            u32_of(w),
            u32_of(height),
            u32_of(width),
            ratio(h, height),
            ratio(w, width),
            last,
        )
    })
}

/// One kernel; `dx` (of the input's size `h × w`) channels-last where `grad` is.
pub(super) fn resize_grad(
    grad: FloatTensor<CubeBackend>,
    h: usize,
    w: usize,
) -> FloatTensor<CubeBackend> {
    let [batch, channels, height, width] = dims(&grad);
    let last = pixel_stride(&grad).is_some();
    let dx = empty_in_layout(&grad, [batch, channels, h, w], last);
    one_thread_per_output(dx, &grad, |cubes, cube, dx| {
        kernels::resize_grad::launch(
            &grad.client,
            cubes,
            cube,
            grad.clone().into_tensor_arg(),
            dx.into_tensor_arg(),
            u32_of(channels),
            u32_of(h),
            u32_of(w),
            u32_of(height),
            u32_of(width),
            ratio(h, height),
            ratio(w, width),
            last,
        )
    })
}
