//! StyleGAN2's element-wise chains as single passes on the CPU.
//!
//! Written with Burn's tensor ops, the bias + leaky ReLU of every layer, the ×2 bilinear
//! up-sampling, the `[1, 3, 3, 1]` blur and the Haar transforms of the output are chains of
//! slices, concatenations, scalings and sums: about ten passes over an activation each way (or,
//! on the small Haar tensors, ten ops' fixed costs), and 40–57 % of a StyleUNet's
//! forward+backward on `Flex` (`f3g bench nets --profile`, "other"). Here each is one backend op
//! with a hand-written backward ([`FusedBackend`]); on `Flex` each forward and backward is one
//! loop over the planes, in parallel. Other devices keep the tensor-op formulation in
//! [`crate::layers::portable`] (the extension is listed for `Flex` only; [`on_flex`] routes).
//!
//! Layouts: `[B, C, H, W]` row-major; `bias` `[C]`.

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::{Device, Tensor};

mod autodiff;
mod flex;

/// Whether `x` lives on the CPU backend (with or without autodiff), where the fused ops run.
pub fn on_flex(x: &Tensor<4>) -> bool {
    x.device().without_autodiff() == Device::flex()
}

/// `leaky_relu(x + bias, 0.2) · √2` (StyleGAN2's fused activation) as one op; `x` on `Flex`.
pub fn bias_leaky_relu(x: Tensor<4>, bias: Tensor<1>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as FusedBackend>::bias_leaky_relu(
        x.into_dispatch(),
        bias.into_dispatch(),
    ))
}

/// Bilinear ×2 up-sampling (`align_corners = false`) as one op; `x` on `Flex`.
pub fn upsample2(x: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as FusedBackend>::upsample2(x.into_dispatch()))
}

/// The separable `[1, 3, 3, 1] / 8` blur with zero padding `(before, after)` ≤ 3 on both axes as
/// one op; `x` on `Flex`.
pub fn blur(x: Tensor<4>, before: usize, after: usize) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as FusedBackend>::blur(
        x.into_dispatch(),
        before,
        after,
    ))
}

/// Orthonormal 2-D Haar analysis `[B, C, 2H, 2W] → [B, 4C, H, W]` as one op; `x` on `Flex`.
pub fn haar(x: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as FusedBackend>::haar(x.into_dispatch()))
}

/// The inverse of [`haar`] as one op; `x` on `Flex`.
pub fn inverse_haar(x: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as FusedBackend>::inverse_haar(x.into_dispatch()))
}

/// The fused ops and the backward passes their autodiff nodes call.
#[backend_extension(Autodiff, Flex)]
pub trait FusedBackend: Backend {
    /// `leaky_relu(x + bias, 0.2) · √2`.
    fn bias_leaky_relu(x: FloatTensor<Self>, bias: FloatTensor<Self>) -> FloatTensor<Self>;

    /// The gradient of `x + bias` from the op's `output` and the output gradient `grad`
    /// (`grad · √2 · slope`, the slope read from the output's sign).
    fn bias_leaky_relu_grad(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self>;

    /// `[C]`: the sum of `x` over batch and pixels per channel (the bias gradient).
    fn channel_sum(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// `[B, C, H, W] → [B, C, 2H, 2W]`, bilinear.
    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// The adjoint of [`FusedBackend::upsample2`]: `[B, C, 2H, 2W] → [B, C, H, W]`.
    fn upsample2_grad(grad: FloatTensor<Self>) -> FloatTensor<Self>;

    /// The blur: each axis grows by `before + after − 3`. Its adjoint is the blur with padding
    /// `(3 − before, 3 − after)` (the taps are symmetric).
    fn blur(x: FloatTensor<Self>, before: usize, after: usize) -> FloatTensor<Self>;

    /// Haar analysis: channel `4c + k` holds sub-band `k ∈ (LL, LH, HL, HH)` of channel `c`. The
    /// transform is orthonormal, so its adjoint is [`FusedBackend::inverse_haar`].
    fn haar(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// Haar synthesis, the inverse (and adjoint) of [`FusedBackend::haar`].
    fn inverse_haar(x: FloatTensor<Self>) -> FloatTensor<Self>;
}
