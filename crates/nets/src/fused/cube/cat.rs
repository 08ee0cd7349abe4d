//! Concatenation along the channels and its adjoint, the split of a gradient: one thread per
//! value of the concatenation, forward and backward.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;

use super::{dims, one_thread_per_output, u32_of};
use crate::cube_grid::one_thread_per_value;
use crate::cube_layout::{empty_in_layout, readable};

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use crate::fused::cube::position::{offset, position};

    /// `out` (`[B, C₁ + C₂, H, W]`, channels-last with `out_last`) from `first` and `second`,
    /// each read in its own layout.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn cat_channels(
        first: &Tensor<f32>,
        second: &Tensor<f32>,
        out: &mut Tensor<f32>,
        c1: u32,
        c2: u32,
        h: u32,
        w: u32,
        #[comptime] first_last: bool,
        #[comptime] second_last: bool,
        #[comptime] out_last: bool,
    ) {
        let i = ABSOLUTE_POS;
        if i >= out.len() {
            terminate!();
        }
        let p = position(i as u32, c1 + c2, h, w, out_last);
        if p.channel < c1 {
            out[i] = first[offset(p.batch, p.channel, p.y, p.x, c1, h, w, first_last)];
        } else {
            let c = p.channel - c1;
            out[i] = second[offset(p.batch, c, p.y, p.x, c2, h, w, second_last)];
        }
    }

    /// `first` and `second` (`[B, C₁, H, W]`, `[B, C₂, H, W]`) from `grad` (`[B, C₁ + C₂, H,
    /// W]`), all three in one layout.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn split_channels(
        grad: &Tensor<f32>,
        first: &mut Tensor<f32>,
        second: &mut Tensor<f32>,
        c1: u32,
        c2: u32,
        h: u32,
        w: u32,
        #[comptime] last: bool,
    ) {
        let i = ABSOLUTE_POS;
        if i >= grad.len() {
            terminate!();
        }
        let p = position(i as u32, c1 + c2, h, w, last);
        if p.channel < c1 {
            first[offset(p.batch, p.channel, p.y, p.x, c1, h, w, last)] = grad[i];
        } else {
            let c = p.channel - c1;
            second[offset(p.batch, c, p.y, p.x, c2, h, w, last)] = grad[i];
        }
    }
}

/// One kernel; the output channels-last if either input is.
pub(super) fn cat_channels(
    first: FloatTensor<CubeBackend>,
    second: FloatTensor<CubeBackend>,
) -> FloatTensor<CubeBackend> {
    let ([batch, c1, h, w], [b2, c2, h2, w2]) = (dims(&first), dims(&second));
    assert_eq!([batch, h, w], [b2, h2, w2], "maps of one batch and size");
    let ((first, first_last), (second, second_last)) = (readable(first), readable(second));
    let out_last = first_last || second_last;
    let out = empty_in_layout(&first, [batch, c1 + c2, h, w], out_last);
    one_thread_per_output(out, &first, |cubes, cube, out| {
        kernels::cat_channels::launch(
            &first.client,
            cubes,
            cube,
            first.clone().into_tensor_arg(),
            second.into_tensor_arg(),
            out.into_tensor_arg(),
            u32_of(c1),
            u32_of(c2),
            u32_of(h),
            u32_of(w),
            first_last,
            second_last,
            out_last,
        )
    })
}

/// One kernel, both parts in `grad`'s layout.
pub(super) fn split_channels(
    grad: FloatTensor<CubeBackend>,
    c1: usize,
) -> (FloatTensor<CubeBackend>, FloatTensor<CubeBackend>) {
    let [batch, channels, h, w] = dims(&grad);
    assert!(
        c1 <= channels,
        "the first part's channels are the gradient's"
    );
    let c2 = channels - c1;
    let (grad, last) = readable(grad);
    let first = empty_in_layout(&grad, [batch, c1, h, w], last);
    let second = empty_in_layout(&grad, [batch, c2, h, w], last);
    let n = u32_of(grad.shape().num_elements());
    if n > 0 {
        let (cubes, cube) = one_thread_per_value(n as usize);
        kernels::split_channels::launch(
            &grad.client,
            cubes,
            cube,
            grad.clone().into_tensor_arg(),
            first.clone().into_tensor_arg(),
            second.clone().into_tensor_arg(),
            u32_of(c1),
            u32_of(c2),
            u32_of(h),
            u32_of(w),
            last,
        );
    }
    (first, second)
}
