//! The tail of a Haar-domain ToRGB, `x + bias + haar(upsample2(inverse_haar(skip)))` (the first
//! level's `x + bias` alone, `fused::add_channel_bias`), one thread per output value, and the
//! skip's adjoint `haar(upsample2_grad(inverse_haar(grad)))`, one thread per value of the skip's
//! gradient: each value gathers the few it depends on through the three maps (`position.rs`'s Haar
//! and up-sampling arithmetic, which `haar.rs`'s and `upsample.rs`'s kernels use too), instead of
//! three launches and two intermediate maps each way.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::into_contiguous;

use super::{dims, one_thread_per_output, u32_of};
use crate::cube_layout::{empty_in_layout, pixel_stride, readable};

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use crate::fused::cube::position::{
        analysed, position, synthesised, upsample_adjoint_weight, upsample_neighbour,
    };

    /// Pixel `(r, s)` of channel `c` of `upsample2(inverse_haar(skip))` (`4h × 4w`), `skip`
    /// `[B, 4C, h, w]`.
    #[allow(clippy::too_many_arguments)]
    #[cube]
    fn upsampled(
        skip: &Tensor<f32>,
        b: u32,
        c: u32,
        r: u32,
        s: u32,
        h: u32,
        w: u32,
        c4: u32,
        #[comptime] last: bool,
    ) -> f32 {
        let (r0, r1) = (r / 2, upsample_neighbour(r, 2 * h));
        let (s0, s1) = (s / 2, upsample_neighbour(s, 2 * w));
        let near = 0.75f32 * synthesised(skip, b, c, r0, s0, h, w, c4, last)
            + 0.25f32 * synthesised(skip, b, c, r0, s1, h, w, c4, last);
        let far = 0.75f32 * synthesised(skip, b, c, r1, s0, h, w, c4, last)
            + 0.25f32 * synthesised(skip, b, c, r1, s1, h, w, c4, last);
        0.75f32 * near + 0.25f32 * far
    }

    /// `out = x + bias[channel] + haar(upsample2(inverse_haar(skip)))`, or without `has_skip`
    /// `x + bias[channel]`: `out` `[B, 4C, height, width]` gapless in `x`'s layout, `x`
    /// channels-last with `x_pixel` values from one pixel to the next (the channels or more:
    /// CUDA pitches the rows of a convolution's output of 12 channels to 16) or row-major;
    /// `skip` `[B, 4C, height / 2, width / 2]` in its own layout.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn to_rgb_output(
        x: &Tensor<f32>,
        bias: &Tensor<f32>,
        skip: &Tensor<f32>,
        out: &mut Tensor<f32>,
        c4: u32,
        height: u32,
        width: u32,
        x_pixel: u32,
        #[comptime] x_last: bool,
        #[comptime] skip_last: bool,
        #[comptime] has_skip: bool,
    ) {
        let o = ABSOLUTE_POS;
        if o >= out.len() {
            terminate!();
        }
        let at = position(o as u32, c4, height, width, x_last);
        let mut read = o as u32;
        if comptime![x_last] {
            read = (read / c4) * x_pixel + read % c4;
        }
        let mut value = x[read as usize] + bias[at.channel as usize];
        if comptime![has_skip] {
            let (h, w) = (height / 2, width / 2);
            let (b, c, band) = (at.batch, at.channel / 4, at.channel % 4);
            let (r, s) = (2 * at.y, 2 * at.x);
            let p = upsampled(skip, b, c, r, s, h, w, c4, skip_last);
            let q = upsampled(skip, b, c, r, s + 1, h, w, c4, skip_last);
            let rr = upsampled(skip, b, c, r + 1, s, h, w, c4, skip_last);
            let ss = upsampled(skip, b, c, r + 1, s + 1, h, w, c4, skip_last);
            value += analysed(p, q, rr, ss, band);
        }
        out[o] = value;
    }

    /// Pixel `(i, j)` (of `2h × 2w`) of channel `c` of `upsample2_grad(inverse_haar(grad))`,
    /// `grad` `[B, 4C, 2h, 2w]`: the weighted sum of the up to 4 × 4 pixels of the `4h × 4w`
    /// synthesis that read it.
    #[allow(clippy::too_many_arguments)]
    #[cube]
    fn upsampled_adjoint(
        grad: &Tensor<f32>,
        b: u32,
        c: u32,
        i: u32,
        j: u32,
        h: u32,
        w: u32,
        c4: u32,
        #[comptime] last: bool,
    ) -> f32 {
        let mut sum = 0.0f32;
        for ty in 0..4u32 {
            let wy = upsample_adjoint_weight(i, 2 * h, ty);
            if wy != 0.0 {
                let oy = 2 * i + ty - 1;
                let mut along = 0.0f32;
                for tx in 0..4u32 {
                    let wx = upsample_adjoint_weight(j, 2 * w, tx);
                    if wx != 0.0 {
                        let ox = 2 * j + tx - 1;
                        along += wx * synthesised(grad, b, c, oy, ox, 2 * h, 2 * w, c4, last);
                    }
                }
                sum += wy * along;
            }
        }
        sum
    }

    /// `dskip = haar(upsample2_grad(inverse_haar(grad)))`, `[B, 4C, h, w]` in `grad`'s layout:
    /// the adjoint of [`to_rgb_output`]'s skip path (Haar analysis and synthesis are each
    /// other's adjoints).
    #[cube(launch)]
    pub fn to_rgb_skip_grad(
        grad: &Tensor<f32>,
        dskip: &mut Tensor<f32>,
        c4: u32,
        h: u32,
        w: u32,
        #[comptime] last: bool,
    ) {
        let o = ABSOLUTE_POS;
        if o >= dskip.len() {
            terminate!();
        }
        let at = position(o as u32, c4, h, w, last);
        let (b, c, band) = (at.batch, at.channel / 4, at.channel % 4);
        let (i, j) = (2 * at.y, 2 * at.x);
        let p = upsampled_adjoint(grad, b, c, i, j, h, w, c4, last);
        let q = upsampled_adjoint(grad, b, c, i, j + 1, h, w, c4, last);
        let r = upsampled_adjoint(grad, b, c, i + 1, j, h, w, c4, last);
        let s = upsampled_adjoint(grad, b, c, i + 1, j + 1, h, w, c4, last);
        dskip[o] = analysed(p, q, r, s, band);
    }
}

/// One kernel, in `x`'s layout (gapless); with no `skip`, `x + bias` alone.
pub(super) fn to_rgb_output(
    x: FloatTensor<CubeBackend>,
    bias: FloatTensor<CubeBackend>,
    skip: Option<FloatTensor<CubeBackend>>,
) -> FloatTensor<CubeBackend> {
    let shape = dims(&x);
    let [batch, c4, height, width] = shape;
    if let Some(skip) = &skip {
        assert_eq!(
            dims(skip),
            [batch, c4, height / 2, width / 2],
            "the skip is at half the size, in as many sub-bands"
        );
        assert!(
            c4 % 4 == 0 && height % 2 == 0 && width % 2 == 0,
            "four sub-bands per channel, even sizes"
        );
    }
    assert_eq!(bias.shape().dims::<1>(), [c4], "one bias per channel");
    let bias = into_contiguous(bias);
    let (x, x_last, x_pixel) = match pixel_stride(&x) {
        Some(pixel) => (x, true, pixel),
        None => (into_contiguous(x), false, c4),
    };
    // The kernel indexes `x`'s buffer, gaps included, with 32 bits.
    u32_of(batch * height * width * x_pixel);
    let has_skip = skip.is_some();
    let (skip, skip_last) = match skip {
        Some(skip) => readable(skip),
        // Never read: the kernel takes a tensor all the same.
        None => (x.clone(), false),
    };
    let out = empty_in_layout(&x, shape, x_last);
    one_thread_per_output(out, &x, |cubes, cube, out| {
        kernels::to_rgb_output::launch(
            &x.client,
            cubes,
            cube,
            x.clone().into_tensor_arg(),
            bias.into_tensor_arg(),
            skip.into_tensor_arg(),
            out.into_tensor_arg(),
            u32_of(c4),
            u32_of(height),
            u32_of(width),
            u32_of(x_pixel),
            x_last,
            skip_last,
            has_skip,
        )
    })
}

/// One kernel, in `grad`'s layout.
pub(super) fn to_rgb_skip_grad(grad: FloatTensor<CubeBackend>) -> FloatTensor<CubeBackend> {
    let [batch, c4, height, width] = dims(&grad);
    assert!(
        c4 % 4 == 0 && height % 2 == 0 && width % 2 == 0,
        "four sub-bands per channel, even sizes"
    );
    let (h, w) = (height / 2, width / 2);
    let (grad, last) = readable(grad);
    let dskip = empty_in_layout(&grad, [batch, c4, h, w], last);
    one_thread_per_output(dskip, &grad, |cubes, cube, dskip| {
        kernels::to_rgb_skip_grad::launch(
            &grad.client,
            cubes,
            cube,
            grad.clone().into_tensor_arg(),
            dskip.into_tensor_arg(),
            u32_of(c4),
            u32_of(h),
            u32_of(w),
            last,
        )
    })
}
