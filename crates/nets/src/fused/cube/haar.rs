//! Haar analysis and synthesis, each the other's inverse and adjoint, one thread per output
//! value.

use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;

use super::{dims, one_thread_per_output, u32_of};
use crate::cube_layout::{empty_in_layout, readable};

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use crate::fused::cube::position::{analysed, position, strided, synthesised};

    /// `out` (`[B, 4C, h, w]`, channels-last): channel `4c + k` holds sub-band `k ∈ (LL, LH, HL,
    /// HH)` of the 2 × 2 block `(p q / r s)` at `(2y, 2x)` of channel `c` of `x` (`[B, C, 2h,
    /// 2w]`, any strides), `½(p ± q ± r ± s)`.
    #[cube(launch)]
    pub fn haar(x: &Tensor<f32>, out: &mut Tensor<f32>, channels: u32, h: u32, w: u32) {
        let o = ABSOLUTE_POS;
        if o >= out.len() {
            terminate!();
        }
        let at = position(o as u32, 4 * channels, h, w, true);
        let (b, c, band) = (at.batch, at.channel / 4, at.channel % 4);
        let (y, x0) = (2 * at.y, 2 * at.x);
        let p = x[strided(x, b, c, y, x0)];
        let q = x[strided(x, b, c, y, x0 + 1)];
        let r = x[strided(x, b, c, y + 1, x0)];
        let s = x[strided(x, b, c, y + 1, x0 + 1)];
        out[o] = analysed(p, q, r, s, band);
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
        out[o] = synthesised(
            x,
            at.batch,
            at.channel,
            at.y,
            at.x,
            h,
            w,
            4 * channels,
            channels_last,
        );
    }
}

/// One kernel, reading `x` through its strides and writing channels-last whatever its layout:
/// the analysis is the backward of a network's last op, whose output gradient arrives in any
/// layout (a slice of a concatenation's gradient, row-major from a resize), and the ToRGB
/// convolutions' gradients it feeds compute channels-last (their GEMMs would copy anything
/// else, at every decoder level).
pub(super) fn haar(x: FloatTensor<CubeBackend>) -> FloatTensor<CubeBackend> {
    let [batch, channels, height, width] = dims(&x);
    assert!(
        height % 2 == 0 && width % 2 == 0,
        "Haar analysis of even sizes"
    );
    let (h, w) = (height / 2, width / 2);
    let out = empty_in_layout(&x, [batch, 4 * channels, h, w], true);
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
        )
    })
}

/// One kernel, in `x`'s layout.
pub(super) fn inverse_haar(x: FloatTensor<CubeBackend>) -> FloatTensor<CubeBackend> {
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
