//! The input gradient of a strided convolution on `Cube` devices as one GEMM and one col2im,
//! computed in the channels-last layout the rest of the network's backward pass runs in.
//!
//! Burn's implicit GEMM has no strided input gradient, and its transposed convolution (the
//! GEMM + col2im it falls back to) copies the output gradient to its own layout, reshapes the
//! columns with copies and hands back a row-major gradient which CUDA pitches (a blurred map is
//! `2n + 1` wide): the blur's backward, the activation's and the next convolution's each copied
//! it again — about seven launches per strided convolution, where this is two. With `G` the
//! output gradient as `[B·H_out·W_out, C_out]` (a channels-last gradient as it is) and `W` the
//! weight as `[C_out, kh·kw·C_in]` (the layout `fused::modulate` and `fused::scale_weight` write
//! it in), the columns are `G · W` (`[B·H_out·W_out, kh·kw·C_in]`), and [`kernels::col2im`] gives
//! each input value the sum of the columns that read it, written channels-last.

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::Shape;
use burn::tensor::ops::ConvOptions;
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::permute_nchw_to_nhwc;

use crate::cube_grid::one_thread_per_value;
use crate::cube_layout::{empty_in_layout, into_channels_last};

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// `dx[b, y, x, i]` (channels-last, one thread per value): the sum over the taps `(ky, kx)`
    /// that read input pixel `(y, x)` from some output position `(oy, ox)` — `y = oy·sh − ph +
    /// ky·dh` and alike for `x` — of `columns[(b, oy, ox), (ky, kx, i)]`, whose rows are
    /// `row_stride` apart.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn col2im(
        columns: &Tensor<f32>,
        dx: &mut Tensor<f32>,
        row_stride: u32,
        c_in: u32,
        h: u32,
        w: u32,
        h_out: u32,
        w_out: u32,
        // kernel, stride, padding, dilation (rows, then columns)
        kh: u32,
        kw: u32,
        sh: u32,
        sw: u32,
        ph: u32,
        pw: u32,
        dh: u32,
        dw: u32,
    ) {
        let g = ABSOLUTE_POS;
        if g >= dx.len() {
            terminate!();
        }
        let g = g as u32;
        let i = g % c_in;
        let x = (g / c_in) % w;
        let y = (g / (c_in * w)) % h;
        let b = g / (c_in * w * h);
        let mut sum = 0.0f32;
        for ky in 0..kh {
            // `oy·sh = y + ph − ky·dh`, when that is a whole output row.
            let ty = (y + ph) as i32 - (ky * dh) as i32;
            let oy = ty.max(0) as u32 / sh;
            if ty >= 0 && oy * sh == ty as u32 && oy < h_out {
                for kx in 0..kw {
                    let tx = (x + pw) as i32 - (kx * dw) as i32;
                    let ox = tx.max(0) as u32 / sw;
                    if tx >= 0 && ox * sw == tx as u32 && ox < w_out {
                        let row = (b * h_out + oy) * w_out + ox;
                        let column = (ky * kw + kx) * c_in + i;
                        sum += columns[(row * row_stride + column) as usize];
                    }
                }
            }
        }
        dx[g as usize] = sum;
    }
}

/// The input gradient (`[B, C_in, H, W]`, channels-last) of a convolution of an input of
/// `x_shape` with `weight` (groups 1, symmetric padding) given its output gradient `grad`; a
/// gradient or weight in another layout is copied to channels-last first. `None` where a
/// tensor has 2³² values or more (the kernel indexes with 32 bits): the caller runs Burn's.
pub fn strided_input_grad(
    x_shape: Shape,
    weight: FloatTensor<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
    options: &ConvOptions<2>,
) -> Option<FloatTensor<CubeBackend>> {
    let [batch, c_in, h, w] = x_shape.dims();
    let [c_out, _, kh, kw] = weight.shape().dims();
    let [_, _, h_out, w_out] = grad.shape().dims();
    let positions = batch * h_out * w_out;
    let taps = kh * kw * c_in;
    let fits = |values: usize| u32::try_from(values).is_ok();
    // The columns' rows may be pitched up to twice their length.
    if !fits(2 * positions * taps) || !fits(batch * c_in * h * w) {
        return None;
    }
    // `[B, C, H, W]` as the `[B·H·W, C]` matrix of its channels-last storage: a view where it
    // is stored so, else a copy.
    let as_matrix = |t: FloatTensor<CubeBackend>, rows: usize, columns: usize| {
        let nhwc = permute_nchw_to_nhwc(into_channels_last(t));
        CubeBackend::float_reshape(nhwc, Shape::new([rows, columns]))
    };
    let grad = as_matrix(grad, positions, c_out);
    let weight = as_matrix(weight, c_out, taps);
    let mut columns = CubeBackend::float_matmul(grad, weight);
    if columns.meta.strides()[1] != 1 {
        // The kernel reads rows (a matmul writes them; a transposed result is copied).
        columns = into_contiguous(columns);
    }
    let row_stride = columns.meta.strides()[0];
    let dx = empty_in_layout(&columns, [batch, c_in, h, w], true);
    let values = dx.shape().num_elements();
    if values > 0 {
        let u = |v: usize| v as u32;
        let (cubes, cube) = one_thread_per_value(values);
        kernels::col2im::launch(
            &columns.client,
            cubes,
            cube,
            columns.clone().into_tensor_arg(),
            dx.clone().into_tensor_arg(),
            u(row_stride),
            u(c_in),
            u(h),
            u(w),
            u(h_out),
            u(w_out),
            u(kh),
            u(kw),
            u(options.stride[0]),
            u(options.stride[1]),
            u(options.padding[0].0),
            u(options.padding[1].0),
            u(options.dilation[0]),
            u(options.dilation[1]),
        );
    }
    Some(dx)
}
