//! The mean of each 2 × 2 block and its adjoint, one thread per output value.

use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;

use super::{dims, one_thread_per_output, u32_of};
use crate::cube_layout::{empty_in_layout, pixel_stride, readable};

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use crate::fused::cube::position::{offset, position, strided};

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

    /// `dx` (`[B, C, height, width]`, channels-last with `channels_last`), the adjoint of
    /// [`downsample2`]: a quarter of the gradient (`[B, C, h, w]`, any strides) of the block a
    /// value falls in, zero outside the blocks.
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
            value = 0.25 * grad[strided(grad, at.batch, at.channel, y, x)];
        }
        dx[i] = value;
    }
}

/// One kernel, in `x`'s layout.
pub(super) fn downsample2(x: FloatTensor<CubeBackend>) -> FloatTensor<CubeBackend> {
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

/// One kernel, reading `grad` through its strides (a pitched gradient as it is); `dx`
/// channels-last where `grad` is.
pub(super) fn downsample2_grad(
    grad: FloatTensor<CubeBackend>,
    height: usize,
    width: usize,
) -> FloatTensor<CubeBackend> {
    let [batch, channels, h, w] = dims(&grad);
    assert_eq!(
        [h, w],
        [height / 2, width / 2],
        "the gradient of a 2 × 2 mean"
    );
    let last = pixel_stride(&grad).is_some();
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
