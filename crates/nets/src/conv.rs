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
//! GEMMs on matrix units where the device has them) unless Burn's `autotune` or `fusion` is on,
//! where Burn's own choice stands. `Autodiff` records one node whose backward
//! asks the inner backend for each gradient a parent needs. Layouts are Burn's: `x`
//! `[B, C_in, H, W]`, `weight` `[C_out, C_in / groups, kh, kw]`.

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::Tensor;
use burn::tensor::ops::ConvOptions;

mod autodiff;
#[cfg(all(any(feature = "gpu", feature = "cuda"), not(feature = "fusion")))]
pub mod bands;
#[cfg(all(any(feature = "gpu", feature = "cuda"), not(feature = "fusion")))]
mod cube;
#[cfg(all(any(feature = "gpu", feature = "cuda"), not(feature = "fusion")))]
pub use cube::{GemmChoice, gemm_choices};
mod flex;
pub mod profile;

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
#[backend_extension(Autodiff, Flex, Cube: cfg(any(feature = "gpu", feature = "cuda")))]
pub trait ConvBackend: Backend {
    /// `conv2d(x, weight)` without bias: `[B, C_out, H_out, W_out]`.
    fn conv2d_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self>;

    /// The gradient of the input given the output gradient `grad`.
    fn conv2d_input_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self>;

    /// The gradient of the weight given the output gradient `grad`.
    fn conv2d_weight_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self>;
}

/// Burn's kernels with Burn's choice of algorithm on fused wgpu and CUDA devices (the tensors
/// are the fusion engine's; unfused devices: [`cube`]).
#[cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))]
impl ConvBackend for burn::backend::Cube {
    fn conv2d_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        <Self as burn::backend::ops::ModuleOps<Self>>::conv2d(x, weight, None, options)
    }

    fn conv2d_input_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        <Self as burn::backend::ops::ModuleOps<Self>>::conv2d_x_backward(x, weight, grad, options)
    }

    fn conv2d_weight_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        <Self as burn::backend::ops::ModuleOps<Self>>::conv2d_weight_backward(
            x, weight, grad, options,
        )
    }
}
