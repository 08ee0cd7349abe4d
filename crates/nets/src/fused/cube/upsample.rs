//! Bilinear ×2 up-sampling and its adjoint, one thread per output value.

use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;

use super::{dims, one_thread_per_output, u32_of};
use crate::cube_layout::{empty_in_layout, readable};

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use crate::fused::cube::position::{
        offset, position, upsample_adjoint_weight, upsample_neighbour,
    };

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
}

/// One kernel, in `x`'s layout.
pub(super) fn upsample2(x: FloatTensor<CubeBackend>) -> FloatTensor<CubeBackend> {
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

/// One kernel, in `grad`'s layout.
pub(super) fn upsample2_grad(grad: FloatTensor<CubeBackend>) -> FloatTensor<CubeBackend> {
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
