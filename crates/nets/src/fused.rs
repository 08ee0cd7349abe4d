//! StyleGAN2's element-wise chains and modulated weights as single passes: one loop on the CPU,
//! one kernel on a GPU.
//!
//! Written with Burn's tensor ops, the bias + leaky ReLU of every layer, the ×2 bilinear
//! up-sampling, the `[1, 3, 3, 1]` blur and the Haar transforms of the output are chains of
//! slices, concatenations, scalings and sums: about ten passes over an activation each way (or,
//! on the small Haar tensors, ten ops' fixed costs), and 40–57 % of a StyleUNet's
//! forward+backward on `Flex` (`f3g bench nets --profile`, "other"). The modulated weight of
//! every styled convolution is another ten small ops forward and twenty backward, each a kernel
//! launch on a GPU. The 2 × 2 down-sampling of the encoder's input pyramid, as Burn's average
//! pooling, compiles a GPU kernel for every pooling and input size. Here each is one backend op
//! with a hand-written backward ([`FusedBackend`]); on `Flex` each forward and backward is one
//! loop over the planes, in parallel, and on unfused `Cube` devices (wgpu, CUDA) one kernel
//! (`cube`). Burn's `fusion` devices keep the tensor-op formulation in
//! [`crate::layers::portable`], which fusion fuses itself; [`runs`] routes.
//!
//! Layouts: `[B, C, H, W]` (row-major on the CPU; on a GPU row-major or channels-last, see
//! `cube`); `bias` `[C]`; a convolution weight `[C_out, C_in, kh, kw]`, its style `[C_in]`.

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::{Device, Tensor};

mod autodiff;
#[cfg(all(any(feature = "gpu", feature = "cuda"), not(feature = "fusion")))]
mod cube;
mod flex;

/// Whether `x` lives on the CPU backend (with or without autodiff).
pub fn on_flex(x: &Tensor<4>) -> bool {
    x.device().without_autodiff() == Device::flex()
}

/// Whether a fused op on `x` runs as one op here: on the CPU, and on unfused `Cube` devices
/// where none of the op's tensors has 2³² values or more (`largest`: the most any of them has,
/// forward or backward), since their kernels index with 32 bits.
pub fn runs(x: &Tensor<4>, largest: usize) -> bool {
    if on_flex(x) {
        return true;
    }
    #[cfg(all(any(feature = "gpu", feature = "cuda"), not(feature = "fusion")))]
    if matches!(
        x.device().without_autodiff().as_dispatch(),
        burn::backend::DispatchDevice::Cube(_)
    ) {
        return u32::try_from(largest.max(x.shape().num_elements())).is_ok();
    }
    let _ = largest;
    false
}

/// `gain · leaky_relu(x + bias, slope)` with a per-channel bias as one op, where [`runs`]:
/// StyleGAN2's fused activation (slope 0.2, gain √2), or a convolution's bias and ReLU (0, 1).
/// `gain` must be positive and `slope` not negative (the backward reads the slope from the
/// output's sign).
pub fn bias_leaky_relu(x: Tensor<4>, bias: Tensor<1>, slope: f64, gain: f32) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as FusedBackend>::bias_leaky_relu(
        x.into_dispatch(),
        bias.into_dispatch(),
        slope as f32,
        gain,
    ))
}

/// Bilinear ×2 up-sampling (`align_corners = false`) as one op, where [`runs`].
pub fn upsample2(x: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as FusedBackend>::upsample2(x.into_dispatch()))
}

/// The mean of each 2 × 2 block, `[B, C, H, W] → [B, C, ⌊H/2⌋, ⌊W/2⌋]` (area halving; for even
/// sizes also bilinear halving with `align_corners = false`), as one op, where [`runs`].
pub fn downsample2(x: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as FusedBackend>::downsample2(x.into_dispatch()))
}

/// The separable `[1, 3, 3, 1] / 8` blur with zero padding `(before, after)` ≤ 3 on both axes as
/// one op, where [`runs`].
pub fn blur(x: Tensor<4>, before: usize, after: usize) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as FusedBackend>::blur(
        x.into_dispatch(),
        before,
        after,
    ))
}

/// Orthonormal 2-D Haar analysis `[B, C, 2H, 2W] → [B, 4C, H, W]` as one op, where [`runs`].
pub fn haar(x: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as FusedBackend>::haar(x.into_dispatch()))
}

/// The inverse of [`haar`] as one op, where [`runs`].
pub fn inverse_haar(x: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as FusedBackend>::inverse_haar(x.into_dispatch()))
}

/// StyleGAN2's modulated convolution weight as one op, where [`runs`] (`weight`'s device): each
/// input channel `i` of `weight` (`[C_out, C_in, kh, kw]`) scaled by `style[i] · scale`, then,
/// with `demodulate`, each output channel divided by its norm `√(Σ w² + 10⁻⁸)`.
pub fn modulate(weight: Tensor<4>, style: Tensor<1>, scale: f32, demodulate: bool) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as FusedBackend>::modulate(
        weight.into_dispatch(),
        style.into_dispatch(),
        scale,
        demodulate,
    ))
}

/// The fused ops and the backward passes their autodiff nodes call.
#[backend_extension(
    Autodiff,
    Flex,
    Cube: cfg(all(any(feature = "gpu", feature = "cuda"), not(feature = "fusion")))
)]
pub trait FusedBackend: Backend {
    /// `gain · leaky_relu(x + bias, slope)` (`gain > 0`, `slope ≥ 0`).
    fn bias_leaky_relu(
        x: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self>;

    /// The gradient of `x + bias` from the op's `output` and the output gradient `grad`
    /// (`grad · gain`, times `slope` where the output is not positive; with slope 0 there zero,
    /// whatever `grad` holds, as ReLU's backward selects: `∞ · 0` would be NaN).
    fn bias_leaky_relu_grad(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self>;

    /// `[C]`: the sum of `x` over batch and pixels per channel (the bias gradient).
    fn channel_sum(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// `[B, C, H, W] → [B, C, 2H, 2W]`, bilinear.
    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// The adjoint of [`FusedBackend::upsample2`]: `[B, C, 2H, 2W] → [B, C, H, W]`.
    fn upsample2_grad(grad: FloatTensor<Self>) -> FloatTensor<Self>;

    /// `[B, C, H, W] → [B, C, ⌊H/2⌋, ⌊W/2⌋]`: the mean of each 2 × 2 block (an odd last row or
    /// column is left out).
    fn downsample2(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// The adjoint of [`FusedBackend::downsample2`] for an input of `height × width`: each value
    /// a quarter of its block's gradient, zero on a left-out row or column.
    fn downsample2_grad(grad: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self>;

    /// The blur: each axis grows by `before + after − 3`. Its adjoint is the blur with padding
    /// `(3 − before, 3 − after)` (the taps are symmetric).
    fn blur(x: FloatTensor<Self>, before: usize, after: usize) -> FloatTensor<Self>;

    /// Haar analysis: channel `4c + k` holds sub-band `k ∈ (LL, LH, HL, HH)` of channel `c`. The
    /// transform is orthonormal, so its adjoint is [`FusedBackend::inverse_haar`].
    fn haar(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// Haar synthesis, the inverse (and adjoint) of [`FusedBackend::haar`].
    fn inverse_haar(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// The modulated weight ([`modulate`]): `u = weight · style[i] · scale`, and with
    /// `demodulate` `u · d` where `d = (Σ_{i,taps} u² + 10⁻⁸)^(−½)` per output channel.
    fn modulate(
        weight: FloatTensor<Self>,
        style: FloatTensor<Self>,
        scale: f32,
        demodulate: bool,
    ) -> FloatTensor<Self>;

    /// The gradients of `weight` and `style` given the output gradient `grad`. With
    /// demodulation, the gradient of `u` is `d · (g − u · d² · Σ g·u)` (sums per output channel);
    /// then `∂weight = ∂u · style[i] · scale` and `∂style[i] = Σ_{o,taps} ∂u · weight · scale`.
    fn modulate_grad(
        weight: FloatTensor<Self>,
        style: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        scale: f32,
        demodulate: bool,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);
}

/// The demodulation's `10⁻⁸` under the square root (StyleGAN2's).
pub const DEMODULATION_EPSILON: f32 = 1e-8;
