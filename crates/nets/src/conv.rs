//! 2-D convolution as a backend operation, so that the CPU computes it and both its gradients
//! as im2col + GEMM on NCHW data instead of Burn's generic route.
//!
//! Burn 0.22's `Flex` converts every convolution's input to NHWC and back and tiles 512 output
//! positions at a time, computes the input gradient as a transposed convolution, and derives the
//! weight gradient as another convolution: the input with batch and channels swapped, convolved
//! with the output gradient as a kernel the size of the output (`burn-backend`
//! `conv2d_weight_grad_no_groups`), one narrow GEMM per input channel. Here ([`flex`]), with `X̂`
//! the im2col of the input (one column per output position) and `W` the weight as
//! `[C_out, C_in·kh·kw]`: the output is `W · X̂`, the input gradient the convolution of the output
//! gradient with the flipped kernel (stride 1) or `col2im(Wᵀ · G)`, and the weight gradient
//! `Σ G · X̂ᵀ`, each one well-shaped GEMM per tile of output positions.
//!
//! `Cube` devices use Burn's kernels for all three, with the algorithm chosen in [`cube`] (implicit
//! GEMMs on matrix units where the device has them; a strided input gradient as a GEMM and
//! [`strided`]'s col2im, a long weight gradient in [`bands`]) unless Burn's `autotune` is on,
//! where Burn's own choice stands; under Burn's `fusion` each is a lazy operation of the fusion stream.
//! `Autodiff` records one node whose backward asks the inner backend for each gradient a parent
//! needs. Layouts are Burn's: `x` `[B, C_in, H, W]`, `weight` `[C_out, C_in / groups, kh, kw]`.

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
#[cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))]
use burn::tensor::Shape;
use burn::tensor::Tensor;
use burn::tensor::ops::ConvOptions;

mod autodiff;
#[cfg(any(feature = "gpu", feature = "cuda"))]
pub mod bands;
#[cfg(any(feature = "gpu", feature = "cuda"))]
mod cube;
#[cfg(any(feature = "gpu", feature = "cuda"))]
pub use cube::{GemmChoice, gemm_choices};
mod flex;
pub mod profile;
#[cfg(any(feature = "gpu", feature = "cuda"))]
pub mod strided;

/// A 2-D convolution whose gradients the backend computes ([`ConvBackend`]); `bias` (`[C_out]`)
/// is added by broadcasting.
pub fn conv2d(
    x: Tensor<4>,
    weight: Tensor<4>,
    bias: Option<Tensor<1>>,
    options: ConvOptions<2>,
) -> Tensor<4> {
    let channels = weight.dims()[0];
    let out = Tensor::<4>::from_dispatch(<Dispatch as ConvBackend>::conv2d_forward(
        x.into_dispatch(),
        weight.into_dispatch(),
        options,
    ));
    match bias {
        Some(bias) => out + bias.reshape([1, channels, 1, 1]),
        None => out,
    }
}

/// The convolution and its two gradients as backend operations.
#[backend_extension(
    Autodiff,
    Flex,
    Cube: cfg(any(feature = "gpu", feature = "cuda")),
    Fusion: cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))
)]
pub trait ConvBackend: Backend {
    /// `conv2d(x, weight)` without bias: `[B, C_out, H_out, W_out]`.
    #[fusion(dtype = x, shape = output_shape(x, weight, options))]
    fn conv2d_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self>;

    /// The gradient of the input given the output gradient `grad`.
    #[fusion(dtype = x, shape = x)]
    fn conv2d_input_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self>;

    /// The gradient of the weight given the output gradient `grad`, possibly queued: allocated
    /// now but written only by [`ConvBackend::conv2d_weight_grads_launch_queued`], which the
    /// caller runs before anything reads it. Why: on a GPU a weight gradient split into bands
    /// ends in a sum over the bands, and the sums of every convolution of a backward pass run in
    /// one or a few launches ([`bands`]); the CPU computes it at once.
    #[fusion(dtype = weight, shape = weight)]
    fn conv2d_weight_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self>;

    /// Writes the weight gradients queued on this thread by
    /// [`ConvBackend::conv2d_weight_grad`]; returns `anchor` (a tensor for the op to take,
    /// as a lazy operation of Burn's fusion).
    #[fusion(dtype = anchor, shape = anchor)]
    fn conv2d_weight_grads_launch_queued(anchor: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// The output side along spatial `axis` (0: height, 1: width) of a convolution of an input side
/// `input` with a kernel side `kernel`; `None` when the stride is zero or the kernel's reach is
/// longer than the padded input.
pub(crate) fn output_side(
    input: usize,
    kernel: usize,
    options: &ConvOptions<2>,
    axis: usize,
) -> Option<usize> {
    let (before, after) = options.padding[axis];
    let span = options.dilation[axis] * kernel.checked_sub(1)? + 1;
    let padded = input + before + after;
    (padded >= span && options.stride[axis] > 0).then(|| (padded - span) / options.stride[axis] + 1)
}

/// The output shape of [`ConvBackend::conv2d_forward`] (Burn's `fusion` records each op's output
/// shape before running it; a side [`output_side`] has none of is empty).
#[cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))]
fn output_shape(x: &Shape, weight: &Shape, options: &ConvOptions<2>) -> Shape {
    let side = |axis: usize| output_side(x[2 + axis], weight[2 + axis], options, axis).unwrap_or(0);
    Shape::new([x[0], weight[0], side(0), side(1)])
}
