//! The `[1, 3, 3, 1] / 8` blur with zero padding, one thread per output value; its adjoint is
//! the blur with the complementary padding (`fused::autodiff`).

use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;

use super::{dims, one_thread_per_output, u32_of};
use crate::cube_layout::{empty_in_layout, readable};
use crate::fused::blurred_side;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use crate::fused::cube::position::{offset, position};

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
}

/// One kernel, in `x`'s layout.
pub(super) fn blur(
    x: FloatTensor<CubeBackend>,
    before: usize,
    after: usize,
) -> FloatTensor<CubeBackend> {
    let [batch, channels, h, w] = dims(&x);
    assert!(before <= 3 && after <= 3, "blur padding at most 3");
    let grown = |n: usize| blurred_side(n, before, after);
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
