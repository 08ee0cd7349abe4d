//! StyleGAN2's element-wise chains and modulated weights, and LPIPS's comparison of a tap, each
//! op choosing its path: one pass where [`runs`] says it can (one loop on the CPU, one kernel on
//! a GPU), elsewhere the same maths in Burn's tensor ops ([`portable`]).
//!
//! Written with Burn's tensor ops, the bias + leaky ReLU of every layer, the ×2 bilinear
//! up-sampling, the `[1, 3, 3, 1]` blur and the Haar transforms of the output are chains of
//! slices, concatenations, scalings and sums: about ten passes over an activation each way (or,
//! on the small Haar tensors, ten ops' fixed costs), and 40–57 % of a StyleUNet's
//! forward+backward on `Flex` (`f3g bench nets --profile`, "other"). The modulated weight of
//! every styled convolution is another ten small ops forward and twenty backward, each a kernel
//! launch on a GPU, and so were the equalised linear layers that make each style (two scalings,
//! a transpose, a matmul and a broadcast add), an equalised convolution's `weight · scale`
//! and the noise injection before a styled convolution's activation. The 2 × 2 down-sampling
//! of the encoder's input pyramid, as Burn's average pooling, compiles a GPU kernel for every
//! pooling and input size. A ToRGB's output (its bias and the previous level's output carried
//! up through three resampling ops) and LPIPS's comparison of a tap (each feature map
//! normalised over channels, the difference weighted by a 1×1 convolution, the mean) were five
//! and about fifteen ops forward, twice as many backward; a decoder level's concatenation was
//! Burn's `cat`, whose row-major output the next convolution copied. Here each is one backend op
//! with a hand-written backward ([`FusedBackend`]); on `Flex` each forward and backward is one
//! loop over the planes, in parallel (`flex`), and on `Cube` devices (wgpu, CUDA) one kernel
//! (`cube`, a file per op). Under Burn's `fusion` each op is a lazy operation of the fusion
//! stream (`#[fusion]` below: its output shape recorded now, the kernel run in turn), so fusion
//! fuses the element-wise chains between them; as Burn's ops ([`portable`]) under fusion the
//! StyleGAN2 blocks regrouped into more launches than these kernels make (BENCHMARKS "Burn's
//! fusion, fixed").
//!
//! Layouts: `[B, C, H, W]` (row-major on the CPU; on a GPU row-major or channels-last, see
//! `cube`); `bias` `[C]`; a convolution weight `[C_out, C_in, kh, kw]`, its style `C_in` values
//! of a network's style vector.

#[cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))]
use burn::backend::fusion::custom::TensorSpec;
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
#[cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))]
use burn::tensor::Shape;
use burn::tensor::{Device, Tensor};

mod autodiff;
#[cfg(any(feature = "gpu", feature = "cuda"))]
mod cube;
mod flex;
pub mod portable;

/// Whether `x` lives on the CPU backend (with or without autodiff).
pub fn on_flex<const D: usize>(x: &Tensor<D>) -> bool {
    x.device().without_autodiff() == Device::flex()
}

/// Whether a fused op on `x` runs as one op here: on the CPU, and on `Cube` devices (fused or
/// not) where none of the op's tensors has 2³² values or more (`largest`: the most any of them
/// has, forward or backward), since their kernels index with 32 bits.
pub fn runs<const D: usize>(x: &Tensor<D>, largest: usize) -> bool {
    if on_flex(x) {
        return true;
    }
    #[cfg(any(feature = "gpu", feature = "cuda"))]
    if matches!(
        x.device().without_autodiff().as_dispatch(),
        burn::backend::DispatchDevice::Cube(_)
    ) {
        return u32::try_from(largest.max(x.shape().num_elements())).is_ok();
    }
    let _ = largest;
    false
}

/// `gain · leaky_relu(x + bias, slope)` with a per-channel bias: StyleGAN2's fused activation
/// (slope 0.2, gain √2), or a convolution's bias and ReLU (0, 1). `gain` must be positive and
/// `slope` not negative (the fused backward reads the slope from the output's sign). One op
/// where it [`runs`], [`portable::bias_leaky_relu`] elsewhere.
pub fn bias_leaky_relu(x: Tensor<4>, bias: Tensor<1>, slope: f64, gain: f32) -> Tensor<4> {
    scaled_bias_leaky_relu(x, 1.0, bias, slope, gain)
}

/// [`bias_leaky_relu`] of `input_scale · x` (`input_scale > 0`): an equalised convolution's
/// weight scale applied in its activation's pass, `leaky_relu(conv(x, s·W) + b) =
/// leaky_relu(s · conv(x, W) + b)`, instead of to the weight by an op of its own each way.
pub fn scaled_bias_leaky_relu(
    x: Tensor<4>,
    input_scale: f32,
    bias: Tensor<1>,
    slope: f64,
    gain: f32,
) -> Tensor<4> {
    if runs(&x, 0) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::bias_leaky_relu(
            x.into_dispatch(),
            input_scale,
            bias.into_dispatch(),
            slope as f32,
            gain,
        ))
    } else if input_scale == 1.0 {
        portable::bias_leaky_relu(x, bias, slope, gain)
    } else {
        portable::bias_leaky_relu(x * input_scale, bias, slope, gain)
    }
}

/// `gain · leaky_relu(x + noise · strength + bias, slope)`: StyleGAN2's noise injection (a
/// fixed `noise` map `[1, 1, H, W]` times a learned `strength` `[1]`) and its fused activation
/// in one op where it [`runs`], [`portable::noisy_bias_leaky_relu`] elsewhere. Why:
/// as a multiply and a broadcast add, with their backward's broadcast sums, the injection cost
/// a styled convolution six launches more on a GPU.
pub fn noisy_bias_leaky_relu(
    x: Tensor<4>,
    noise: Tensor<4>,
    strength: Tensor<1>,
    bias: Tensor<1>,
    slope: f64,
    gain: f32,
) -> Tensor<4> {
    if runs(&x, 0) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::noisy_bias_leaky_relu(
            x.into_dispatch(),
            noise.into_dispatch(),
            strength.into_dispatch(),
            bias.into_dispatch(),
            slope as f32,
            gain,
        ))
    } else {
        portable::noisy_bias_leaky_relu(x, noise, strength, bias, slope, gain)
    }
}

/// Bilinear ×2 up-sampling (`align_corners = false`): one op where it [`runs`],
/// [`portable::upsample2`] elsewhere.
pub fn upsample2(x: Tensor<4>) -> Tensor<4> {
    if runs(&x, 4 * x.shape().num_elements()) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::upsample2(x.into_dispatch()))
    } else {
        portable::upsample2(x)
    }
}

/// The mean of each 2 × 2 block, `[B, C, H, W] → [B, C, ⌊H/2⌋, ⌊W/2⌋]` (area halving; for even
/// sizes also bilinear halving with `align_corners = false`): one op where it [`runs`],
/// [`portable::downsample2`] elsewhere.
pub fn downsample2(x: Tensor<4>) -> Tensor<4> {
    if runs(&x, 0) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::downsample2(x.into_dispatch()))
    } else {
        portable::downsample2(x)
    }
}

/// The separable `[1, 3, 3, 1] / 8` blur of StyleGAN2, with zero padding `(before, after)` on
/// both axes (the output grows by `before + after − 3`): one op where it [`runs`] and the
/// padding is at most 3, [`portable::blur`] elsewhere.
pub fn blur(x: Tensor<4>, before: usize, after: usize) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let grown = |n: usize| n + before + after;
    if before <= 3 && after <= 3 && runs(&x, b * c * grown(h) * grown(w)) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::blur(
            x.into_dispatch(),
            before,
            after,
        ))
    } else {
        portable::blur(x, before, after)
    }
}

/// Orthonormal 2-D Haar analysis: `[B, C, 2H, 2W] → [B, 4C, H, W]`, channel `4c + k` holding
/// sub-band `k ∈ (LL, LH, HL, HH)` of channel `c`: one op where it [`runs`],
/// [`portable::haar`] elsewhere.
pub fn haar(x: Tensor<4>) -> Tensor<4> {
    if runs(&x, 0) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::haar(x.into_dispatch()))
    } else {
        portable::haar(x)
    }
}

/// `x` stored as a GPU's convolutions read it, channels-last (a copy unless it is so already);
/// elsewhere as it is. The values, and the gradient, are unchanged. Why: a network's input
/// arrives row-major, and its encoder convolves it and its 2 × 2 means (which keep its layout)
/// at every level: Burn's implicit GEMM copied each of them to channels-last, a launch per
/// level and network (36 a `paper` step), where this is one per network. (The output's
/// gradient needs no such op: the Haar analysis, its backward, writes channels-last itself.)
pub fn channels_last(x: Tensor<4>) -> Tensor<4> {
    if runs(&x, 0) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::to_channels_last(
            x.into_dispatch(),
        ))
    } else {
        x
    }
}

/// The inverse of [`haar`], `[B, 4C, H, W] → [B, C, 2H, 2W]`: one op where it [`runs`],
/// [`portable::inverse_haar`] elsewhere.
pub fn inverse_haar(x: Tensor<4>) -> Tensor<4> {
    if runs(&x, 0) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::inverse_haar(x.into_dispatch()))
    } else {
        portable::inverse_haar(x)
    }
}

/// `x + bias + haar(upsample2(inverse_haar(skip)))`: the output of a Haar-domain ToRGB
/// ([`crate::layers::ToRgb`]), its `x` (`[B, 4C, H, W]`) plus a bias per sub-band channel (`[4C]`)
/// plus the previous level's output `skip` (`[B, 4C, H/2, W/2]`) carried up as an image. One op
/// where it [`runs`] (one kernel each way; `x`'s gradient is the output's, passed on without a
/// launch), those ops and a broadcast add elsewhere.
///
/// Why one op: as three resampling ops and two adds it was five launches forward and six back
/// per decoder level, on maps of few channels where each launch's fixed cost is its time.
pub fn to_rgb_output(x: Tensor<4>, bias: Tensor<1>, skip: Tensor<4>) -> Tensor<4> {
    if runs(&x, 0) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::to_rgb_output(
            x.into_dispatch(),
            bias.into_dispatch(),
            skip.into_dispatch(),
        ))
    } else {
        portable::to_rgb_output(x, bias, skip)
    }
}

/// `x + bias` with one bias per channel (`x` `[B, C, H, W]`, `bias` `[C]`): the first ToRGB's
/// output, which has no previous level's to carry up. One op where it [`runs`] (one kernel
/// forward; backward, `x`'s gradient passed on and the bias's [`FusedBackend::channel_sum`]), a
/// broadcast add elsewhere. Why: on a GPU the op reads the convolution's 12-channel output in
/// the pitched layout CUDA gives it, where the add's output, pitched alike, was copied by the
/// next level's [`to_rgb_output`].
pub fn add_channel_bias(x: Tensor<4>, bias: Tensor<1>) -> Tensor<4> {
    if runs(&x, 0) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::add_channel_bias(
            x.into_dispatch(),
            bias.into_dispatch(),
        ))
    } else {
        let channels = bias.dims()[0];
        x + bias.reshape([1, channels, 1, 1])
    }
}

/// `[first; second]` along the channels: `first` `[B, C₁, H, W]` and `second` `[B, C₂, H, W]`
/// into `[B, C₁ + C₂, H, W]`, a decoder level's input from the level below and the encoder's
/// skip. One op where it [`runs`] (one kernel each way; on a GPU the output channels-last if
/// either input is, the layout the next convolution reads), Burn's `cat` elsewhere.
///
/// Why one op: Burn's `cat` writes a row-major output one input at a time (two launches), which
/// the convolution after it copied to channels-last (a third), and its backward's two channel
/// slices of a channels-last gradient were copied again by the ops that read them.
pub fn cat_channels(first: Tensor<4>, second: Tensor<4>) -> Tensor<4> {
    let ([b, _, h, w], [b2, _, h2, w2]) = (first.dims(), second.dims());
    assert_eq!(
        [b, h, w],
        [b2, h2, w2],
        "concatenated maps share batch and size"
    );
    let total = first.shape().num_elements() + second.shape().num_elements();
    if runs(&first, total) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::cat_channels(
            first.into_dispatch(),
            second.into_dispatch(),
        ))
    } else {
        Tensor::cat(vec![first, second], 1)
    }
}

/// One modulated convolution layer of a network, for [`modulate_all`]: its weight
/// (`[C_out, C_in, kh, kw]`), where its styles begin in the network's style vector, its scale
/// and whether it demodulates.
#[derive(Clone, Debug)]
pub struct Modulation {
    pub weight: Tensor<4>,
    pub first: usize,
    pub scale: f32,
    pub demodulate: bool,
}

/// StyleGAN2's modulated convolution weight of every layer in `layers`: each input channel `i`
/// of a layer's `weight` scaled by `styles[first + i] · scale`, then, with `demodulate`, each
/// output channel divided by its norm `√(Σ w² + 10⁻⁸)`. `styles` holds every modulated layer's
/// style of a network: one linear layer makes them all ([`crate::DualStyleUNet`]), and on a GPU
/// one launch modulates every layer's weight and, backward, two launches give every weight's
/// and the styles' gradients (a node per layer and a gate node for the batch, `fused/autodiff`:
/// three launches per layer and the ≈ 30 sums of its styles' gradients were 714 of a `paper`
/// step's launches). One op per layer where it [`runs`] (`styles`' device),
/// [`portable::modulate`] elsewhere.
pub fn modulate_all(layers: Vec<Modulation>, styles: Tensor<1>) -> Vec<Tensor<4>> {
    if !runs(&styles, 0) {
        return layers
            .into_iter()
            .map(|l| portable::modulate(l.weight, styles.clone(), l.first, l.scale, l.demodulate))
            .collect();
    }
    let weights = layers
        .into_iter()
        .map(|l| {
            Tensor::from_dispatch(<Dispatch as FusedBackend>::modulate_queue(
                l.weight.into_dispatch(),
                styles.clone().into_dispatch(),
                l.first,
                l.scale,
                l.demodulate,
            ))
        })
        .collect();
    <Dispatch as FusedBackend>::modulate_launch_queued(styles.into_dispatch());
    weights
}

/// [`modulate_all`] of one layer.
pub fn modulate(
    weight: Tensor<4>,
    styles: Tensor<1>,
    first: usize,
    scale: f32,
    demodulate: bool,
) -> Tensor<4> {
    let layer = Modulation {
        weight,
        first,
        scale,
        demodulate,
    };
    modulate_all(vec![layer], styles)
        .pop()
        .expect("one layer in, one weight out")
}

/// `weight · scale` for a convolution weight `[C_out, C_in, kh, kw]` (an equalised
/// convolution's): one op where it [`runs`], Burn's scaling elsewhere. On `Cube` devices
/// the result is stored channels-last, the layout Burn's implicit-GEMM convolution
/// reads its weight in: stored row-major, as Burn's scaling leaves it, it was copied before the
/// convolution and again before its input gradient.
pub fn scale_weight(weight: Tensor<4>, scale: f32) -> Tensor<4> {
    if runs(&weight, 0) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::scale_weight(
            weight.into_dispatch(),
            scale,
        ))
    } else {
        weight * scale
    }
}

/// The scalars of [`scaled_linear`]: `gain · leaky_relu(x · (weight · weight_scale)ᵀ + bias ·
/// bias_scale, slope)`; slope 1 and gain 1 leave the affine map alone ([`LinearScales::affine`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinearScales {
    pub weight_scale: f32,
    pub bias_scale: f32,
    /// Leaky ReLU's slope below zero, not negative (the backward reads it from the output's
    /// sign, as [`bias_leaky_relu`]'s).
    pub slope: f32,
    /// Positive.
    pub gain: f32,
}

impl LinearScales {
    /// No activation.
    pub fn affine(weight_scale: f32, bias_scale: f32) -> Self {
        Self {
            weight_scale,
            bias_scale,
            slope: 1.0,
            gain: 1.0,
        }
    }
}

/// A linear layer with scaled weight and bias and an optional leaky ReLU ([`LinearScales`]):
/// `x` `[B, in]`, `weight` `[out, in]`, `bias` `[out]` → `[B, out]`. One op where it [`runs`],
/// [`portable::scaled_linear`] elsewhere.
///
/// Why one op: the StyleUNets' modulations are such layers on one style vector, two of them per
/// styled convolution; as Burn's ops (two scalings, a transpose, a matmul, a broadcast add,
/// and their backwards) they were one in eight of a `paper` step's kernel launches on a GPU.
pub fn scaled_linear(
    x: Tensor<2>,
    weight: Tensor<2>,
    bias: Tensor<1>,
    scales: LinearScales,
) -> Tensor<2> {
    let largest = weight.shape().num_elements() + x.shape().num_elements() + bias.dims()[0];
    if runs(&x, largest) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::scaled_linear(
            x.into_dispatch(),
            weight.into_dispatch(),
            bias.into_dispatch(),
            scales,
        ))
    } else {
        portable::scaled_linear(x, weight, bias, scales)
    }
}

/// LPIPS's comparison of one tap: per batch item, the mean over pixels of
/// `Σ_c weight[c] · (x̂_c − ŷ_c)²`, where `x̂ = x / (‖x‖ + 10⁻¹⁰)` is `x` (`[B, C, H, W]`)
/// unit-normalised over channels at each pixel, as `lpips` 0.1.4 normalises, and `ŷ` the same
/// of `y` (the shape of `x`); `weight` `[C]` is the tap's linear head, a constant (no gradient
/// flows to it). `[B]`. One op where it [`runs`] (one pass over `x` and `y` each way),
/// [`portable::lpips_distance`] elsewhere. Where `x` is zero at a pixel, the tensor ops'
/// gradient is NaN (their square root has no derivative at zero); the op's is the
/// normalisation's one-sided derivative there, `u / 10⁻¹⁰` ([`FusedBackend::lpips_distance_grad`]).
///
/// Why one op: as Burn's ops the normalisations, the difference, the head as a 1×1 convolution
/// and the mean were about 15 launches and passes over the features forward and 20 backward per
/// tap, and the taps of LPIPS VGG are the largest feature maps of a `paper` step after the body
/// network's.
pub fn lpips_distance(x: Tensor<4>, y: Tensor<4>, weight: Tensor<1>) -> Tensor<1> {
    assert_eq!(x.dims(), y.dims(), "LPIPS compares features of one shape");
    assert_eq!(weight.dims(), [x.dims()[1]], "one head weight per channel");
    if runs(&x, 0) {
        Tensor::from_dispatch(<Dispatch as FusedBackend>::lpips_distance(
            x.into_dispatch(),
            y.into_dispatch(),
            weight.detach().into_dispatch(),
        ))
    } else {
        portable::lpips_distance(x, y, weight.detach())
    }
}

/// The fused ops and the backward passes their autodiff nodes call.
#[backend_extension(
    Autodiff,
    Flex,
    Cube: cfg(any(feature = "gpu", feature = "cuda")),
    Fusion: cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))
)]
pub trait FusedBackend: Backend {
    /// `gain · leaky_relu(input_scale · x + bias, slope)` (`gain > 0`, `input_scale > 0`,
    /// `slope ≥ 0`).
    #[fusion(dtype = x, shape = x)]
    fn bias_leaky_relu(
        x: FloatTensor<Self>,
        input_scale: f32,
        bias: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self>;

    /// The gradient of `x + bias` from the op's `output` and the output gradient `grad`
    /// (`grad · gain`, times `slope` where the output is not positive; with slope 0 there zero,
    /// whatever `grad` holds, as ReLU's backward selects: `∞ · 0` would be NaN).
    #[fusion(dtype = output, shape = output)]
    fn bias_leaky_relu_grad(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self>;

    /// [`noisy_bias_leaky_relu`]; its backward is [`FusedBackend::bias_leaky_relu_grad`]'s, with
    /// the strength's gradient from [`FusedBackend::noise_strength_grad`].
    #[fusion(dtype = x, shape = x)]
    fn noisy_bias_leaky_relu(
        x: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        strength: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self>;

    /// `[1]`: `Σ_{b, c, h, w} grad[b, c, h, w] · noise[h, w]` for `noise` `[1, 1, H, W]` (the
    /// noise strength's gradient from the pre-activation's).
    #[fusion(dtype = grad, shape = Shape::new([1]))]
    fn noise_strength_grad(grad: FloatTensor<Self>, noise: FloatTensor<Self>) -> FloatTensor<Self>;

    /// `[C]`: the sum of `x` over batch and pixels per channel (the bias gradient).
    #[fusion(dtype = x, shape = Shape::new([x[1]]))]
    fn channel_sum(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// The backward of [`FusedBackend::bias_leaky_relu`] for a learned bias: the input's
    /// gradient (`input_scale ·` the pre-activation's, [`FusedBackend::bias_leaky_relu_grad`]
    /// with the gain times `input_scale`) and the bias's (the pre-activation's,
    /// [`FusedBackend::channel_sum`]). The bias's gradient may be queued: allocated now and
    /// written by [`FusedBackend::bias_grads_launch_queued`], which the caller runs before
    /// anything reads it. Why: on a GPU one kernel writes the input's gradient and each cube's
    /// share of the bias's, where the two ops read the gradient twice in two or three launches,
    /// and the shares of every activation of a backward pass are summed in one launch.
    #[fusion(meta = |output, _grad, _input_scale, _slope, _gain| {
        (output.clone(), TensorSpec::new(Shape::new([output.shape[1]]), output.dtype))
    })]
    fn bias_leaky_relu_backward_queue(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        input_scale: f32,
        slope: f32,
        gain: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);

    /// [`FusedBackend::bias_leaky_relu_backward_queue`] for [`noisy_bias_leaky_relu`], with the
    /// noise strength's gradient ([`FusedBackend::noise_strength_grad`]) from the same pass,
    /// queued like the bias's.
    #[fusion(meta = |output, _grad, _noise, _slope, _gain| {
        let vector = |n: usize| TensorSpec::new(Shape::new([n]), output.dtype);
        (output.clone(), vector(output.shape[1]), vector(1))
    })]
    fn noisy_bias_leaky_relu_backward_queue(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>);

    /// Writes the bias and noise strength gradients queued on this thread by the two ops above;
    /// returns `anchor` (a tensor for the op to take, as a lazy operation of Burn's fusion).
    #[fusion(dtype = anchor, shape = anchor)]
    fn bias_grads_launch_queued(anchor: FloatTensor<Self>) -> FloatTensor<Self>;

    /// `[B, C, H, W] → [B, C, 2H, 2W]`, bilinear.
    #[fusion(dtype = x, shape = scaled(x, 2, 1))]
    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// The adjoint of [`FusedBackend::upsample2`]: `[B, C, 2H, 2W] → [B, C, H, W]`.
    #[fusion(dtype = grad, shape = scaled(grad, 1, 2))]
    fn upsample2_grad(grad: FloatTensor<Self>) -> FloatTensor<Self>;

    /// `[B, C, H, W] → [B, C, ⌊H/2⌋, ⌊W/2⌋]`: the mean of each 2 × 2 block (an odd last row or
    /// column is left out).
    #[fusion(dtype = x, shape = scaled(x, 1, 2))]
    fn downsample2(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// The adjoint of [`FusedBackend::downsample2`] for an input of `height × width`: each value
    /// a quarter of its block's gradient, zero on a left-out row or column.
    #[fusion(dtype = grad, shape = Shape::new([grad[0], grad[1], *height, *width]))]
    fn downsample2_grad(grad: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self>;

    /// `[B, C, h, w] → [B, C, height, width]`, bilinear (`align_corners = false`; every side
    /// above zero).
    #[fusion(dtype = x, shape = Shape::new([x[0], x[1], *height, *width]))]
    fn resize(x: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self>;

    /// The adjoint of [`FusedBackend::resize`] for an input of `height × width`.
    #[fusion(dtype = grad, shape = Shape::new([grad[0], grad[1], *height, *width]))]
    fn resize_grad(grad: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self>;

    /// The blur: each axis grows by `before + after − 3`. Its adjoint is the blur with padding
    /// `(3 − before, 3 − after)` (the taps are symmetric).
    #[fusion(dtype = x, shape = blurred(x, *before, *after))]
    fn blur(x: FloatTensor<Self>, before: usize, after: usize) -> FloatTensor<Self>;

    /// Haar analysis: channel `4c + k` holds sub-band `k ∈ (LL, LH, HL, HH)` of channel `c`. The
    /// transform is orthonormal, so its adjoint is [`FusedBackend::inverse_haar`].
    #[fusion(dtype = x, shape = Shape::new([x[0], 4 * x[1], x[2] / 2, x[3] / 2]))]
    fn haar(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// [`channels_last`]: the same values, on `Cube` devices stored channels-last.
    #[fusion(dtype = x, shape = x)]
    fn to_channels_last(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// Haar synthesis, the inverse (and adjoint) of [`FusedBackend::haar`].
    #[fusion(dtype = x, shape = Shape::new([x[0], x[1] / 4, 2 * x[2], 2 * x[3]]))]
    fn inverse_haar(x: FloatTensor<Self>) -> FloatTensor<Self>;

    /// [`to_rgb_output`]: `x + bias + haar(upsample2(inverse_haar(skip)))`.
    #[fusion(dtype = x, shape = x)]
    fn to_rgb_output(
        x: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        skip: FloatTensor<Self>,
    ) -> FloatTensor<Self>;

    /// The adjoint of [`to_rgb_output`]'s skip path, `haar(upsample2_grad(inverse_haar(grad)))`:
    /// `[B, 4C, 2H, 2W] → [B, 4C, H, W]`.
    #[fusion(dtype = grad, shape = scaled(grad, 1, 2))]
    fn to_rgb_skip_grad(grad: FloatTensor<Self>) -> FloatTensor<Self>;

    /// [`add_channel_bias`].
    #[fusion(dtype = x, shape = x)]
    fn add_channel_bias(x: FloatTensor<Self>, bias: FloatTensor<Self>) -> FloatTensor<Self>;

    /// [`cat_channels`].
    #[fusion(dtype = first, shape = Shape::new([first[0], first[1] + second[1], first[2], first[3]]))]
    fn cat_channels(first: FloatTensor<Self>, second: FloatTensor<Self>) -> FloatTensor<Self>;

    /// The gradient `[B, C, H, W]` of [`cat_channels`] cut into its first `first` channels' and
    /// the rest's, each in `grad`'s layout.
    #[fusion(meta = |grad, first| {
        let part = |c: usize| {
            let [b, _, h, w] = grad.shape.dims::<4>();
            TensorSpec::new(Shape::new([b, c, h, w]), grad.dtype)
        };
        (part(*first), part(grad.shape[1] - *first))
    })]
    fn split_channels(
        grad: FloatTensor<Self>,
        first: usize,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);

    /// The modulated weight ([`modulate`]): `u = weight · styles[first + i] · scale`, and with
    /// `demodulate` `u · d` where `d = (Σ_{i,taps} u² + 10⁻⁸)^(−½)` per output channel. Queued
    /// on this thread where the backend launches kernels: the output is allocated now and
    /// written by [`FusedBackend::modulate_launch_queued`], which the caller runs before
    /// anything reads it, with the same `styles` ([`modulate_all`]).
    #[fusion(dtype = weight, shape = weight)]
    fn modulate_queue(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> FloatTensor<Self>;

    /// Computes the modulations queued on this thread from `styles`, which it returns.
    #[fusion(dtype = styles, shape = styles)]
    fn modulate_launch_queued(styles: FloatTensor<Self>) -> FloatTensor<Self>;

    /// The gradients of `weight` and `styles` given the output gradient `grad`. With
    /// demodulation, the gradient of `u` is `d · (g − u · d² · Σ g·u)` (sums per output channel);
    /// then `∂weight = ∂u · styles[first + i] · scale` and `∂styles[first + i] = Σ_{o,taps} ∂u ·
    /// weight · scale`, the styles' gradient zero outside the layer's range.
    #[fusion(meta = |weight, styles, _grad, _first, _scale, _demodulate| {
        (weight.clone(), styles.clone())
    })]
    fn modulate_grad(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);

    /// [`FusedBackend::modulate_grad`]'s weight gradient, queued on this thread where the backend
    /// launches kernels: allocated now, written by [`FusedBackend::modulate_grad_launch_queued`]
    /// (with the same `styles`), which also sums the styles' gradient of every queued layer.
    #[fusion(dtype = weight, shape = weight)]
    fn modulate_grad_queue(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> FloatTensor<Self>;

    /// Computes the gradients queued on this thread and returns the styles' gradient: each
    /// queued layer's sums in its range, zero outside them.
    #[fusion(dtype = styles, shape = styles)]
    fn modulate_grad_launch_queued(styles: FloatTensor<Self>) -> FloatTensor<Self>;

    /// [`scale_weight`]: `weight · scale`, in the layout the backend's convolutions read.
    #[fusion(dtype = weight, shape = weight)]
    fn scale_weight(weight: FloatTensor<Self>, scale: f32) -> FloatTensor<Self>;

    /// The gradient of [`FusedBackend::scale_weight`]'s input: `grad · scale`, row-major (the
    /// weight's layout).
    #[fusion(dtype = grad, shape = grad)]
    fn scale_weight_grad(grad: FloatTensor<Self>, scale: f32) -> FloatTensor<Self>;

    /// [`scaled_linear`]: `[B, in] → [B, out]`.
    #[fusion(dtype = x, shape = Shape::new([x[0], bias[0]]))]
    fn scaled_linear(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        scales: LinearScales,
    ) -> FloatTensor<Self>;

    /// The gradients of `x`, `weight` and `bias` from the op's `output` and the output gradient
    /// `grad`: with `g` the activation's gradient (as [`FusedBackend::bias_leaky_relu_grad`]'s),
    /// `∂x = weight_scale · g · weight`, `∂weight = weight_scale · gᵀ · x` and
    /// `∂bias = bias_scale · Σ_batch g`.
    #[fusion(meta = |x, weight, output, _grad, _scales| {
        let bias = TensorSpec::new(Shape::new([output.shape[1]]), output.dtype);
        (x.clone(), weight.clone(), bias)
    })]
    fn scaled_linear_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        scales: LinearScales,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>);

    /// [`lpips_distance`]: `[B]`.
    #[fusion(dtype = x, shape = Shape::new([x[0]]))]
    fn lpips_distance(
        x: FloatTensor<Self>,
        y: FloatTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self>;

    /// The gradient of `x` given the distances' gradient `grad` (`[B]`): with `n = ‖x‖ + 10⁻¹⁰`,
    /// `u_c = 2 · weight[c] · (x̂_c − ŷ_c) · grad[b] / (H·W)`, it is
    /// `u_j / n − x_j · Σ_c u_c x_c / (n² ‖x‖)` at each pixel, `u_j / n` where `‖x‖` is zero.
    /// (`y`'s is the same with the two swapped: the distance is symmetric.)
    #[fusion(dtype = x, shape = x)]
    fn lpips_distance_grad(
        x: FloatTensor<Self>,
        y: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// The activation's input and bias gradients as the separate ops give them
/// ([`FusedBackend::bias_leaky_relu_grad`], then its [`FusedBackend::channel_sum`], divided by
/// `input_scale` on the `[C]` sums): the CPU's backward, and a GPU's where its one-pass kernel
/// does not apply.
fn separate_bias_leaky_relu_grads<B: FusedBackend>(
    output: FloatTensor<B>,
    grad: FloatTensor<B>,
    input_scale: f32,
    slope: f32,
    gain: f32,
) -> (FloatTensor<B>, FloatTensor<B>) {
    let dx = B::bias_leaky_relu_grad(output, grad, slope, gain * input_scale);
    let sums = B::channel_sum(dx.clone());
    let d_bias = if input_scale == 1.0 {
        sums
    } else {
        B::float_div_scalar(sums, input_scale.into())
    };
    (dx, d_bias)
}

/// `[B, C, H, W]` with each side times `times` and divided by `by` (Burn's `fusion` records
/// each op's output shape before running it).
#[cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))]
fn scaled(x: &Shape, times: usize, by: usize) -> Shape {
    Shape::new([x[0], x[1], x[2] * times / by, x[3] * times / by])
}

/// The shape of [`FusedBackend::blur`]'s output.
#[cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))]
fn blurred(x: &Shape, before: usize, after: usize) -> Shape {
    let side = |n: usize| blurred_side(n, before, after);
    Shape::new([x[0], x[1], side(x[2]), side(x[3])])
}

/// A side of [`FusedBackend::blur`]'s output for an input side `n`: `n + before + after − 3`,
/// at least 0 (every backend and fusion's recorded shape agree on it).
pub(crate) fn blurred_side(n: usize, before: usize, after: usize) -> usize {
    (n + before + after).saturating_sub(3)
}

/// The demodulation's `10⁻⁸` under the square root (StyleGAN2's).
pub const DEMODULATION_EPSILON: f32 = 1e-8;

/// What LPIPS adds to a feature's norm before dividing by it (`lpips` 0.1.4's
/// `normalize_tensor`).
pub const LPIPS_EPSILON: f32 = 1e-10;

#[cfg(test)]
mod tests {
    use burn::tensor::module::interpolate;
    use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
    use burn::tensor::{Device, TensorData};

    use super::*;
    use crate::init::Init;

    fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().try_into_vec::<f32>().unwrap()
    }

    #[test]
    fn haar_is_orthonormal_and_inverted_exactly() {
        let device = Device::flex();
        let init = Init::new(1, &device);
        let x = init.tensor(init_values(2 * 3 * 8 * 6), [2, 3, 8, 6]);
        let y = haar(x.clone());
        assert_eq!(y.dims(), [2, 12, 4, 3]);
        // Orthonormal: the energy is preserved.
        let e = |t: Tensor<4>| values(t.powf_scalar(2.0).sum())[0];
        assert!((e(x.clone()) - e(y.clone())).abs() < 1e-3);
        let back = inverse_haar(y);
        for (a, b) in values(x).iter().zip(values(back)) {
            assert!((a - b).abs() < 1e-5);
        }
        // A constant image has only the LL band, equal to 2× the value.
        let c = init.tensor(vec![0.25; 16], [1, 1, 4, 4]);
        let bands = values(haar(c));
        assert!(bands[..4].iter().all(|&v| (v - 0.5).abs() < 1e-6));
        assert!(bands[4..].iter().all(|&v| v.abs() < 1e-6));

        fn init_values(n: usize) -> Vec<f32> {
            (0..n).map(|i| ((i * 37) % 11) as f32 - 5.0).collect()
        }
    }

    #[test]
    fn upsample2_equals_bilinear_interpolation_forward_and_backward() {
        let device = Device::flex().autodiff();
        for [h, w] in [[1, 1], [1, 5], [4, 3], [7, 8]] {
            let n = 2 * 3 * h * w;
            let v: Vec<f32> = (0..n)
                .map(|i| ((i * 7919) % 97) as f32 / 97.0 - 0.5)
                .collect();
            let x = Tensor::<4>::from_data(TensorData::new(v, [2, 3, h, w]), &device);
            let weights: Vec<f32> = (0..4 * n).map(|i| ((i * 31) % 13) as f32 - 6.0).collect();
            let weights =
                Tensor::<4>::from_data(TensorData::new(weights, [2, 3, 2 * h, 2 * w]), &device);
            let run = |up: &dyn Fn(Tensor<4>) -> Tensor<4>| {
                let x = x.clone().require_grad();
                let y = up(x.clone());
                let grads = (y.clone() * weights.clone()).sum().backward();
                (values(y), values(x.grad(&grads).unwrap()))
            };
            let (theirs, theirs_grad) = run(&|x| {
                let mut options = InterpolateOptions::new(InterpolateMode::Bilinear);
                options.align_corners = false;
                options.output_size = Some([2 * h, 2 * w]);
                interpolate(x, options)
            });
            // The CPU's fused op and the tensor-op formulation of other devices.
            for up in [upsample2 as fn(Tensor<4>) -> Tensor<4>, portable::upsample2] {
                let (ours, ours_grad) = run(&up);
                for (a, b) in ours
                    .iter()
                    .zip(&theirs)
                    .chain(ours_grad.iter().zip(&theirs_grad))
                {
                    assert!((a - b).abs() < 1e-5, "{h}×{w}: {a} vs {b}");
                }
            }
        }
    }

    /// LPIPS's comparison of one tap as one op: its distances and both gradients equal the
    /// tensor-op formulation's, and its gradient equals central differences of the distance,
    /// also at a pixel where `x` is zero (where the tensor ops' square root has no derivative).
    #[test]
    fn lpips_distance_matches_the_tensor_ops_and_finite_differences() {
        let device = Device::flex().autodiff();
        let [b, c, h, w] = [2, 5, 3, 4];
        let n = b * c * h * w;
        let ramp = |seed: usize| -> Vec<f32> {
            (0..n)
                .map(|i| (((i * 7919 + seed * 31) % 97) as f32 / 97.0 - 0.3).max(0.0))
                .collect()
        };
        let (xv, yv) = (ramp(1), ramp(2));
        let head: Vec<f32> = (0..c).map(|k| 0.1 + 0.05 * k as f32).collect();
        let weights: Vec<f32> = vec![1.5, -0.75];
        let tensor =
            |v: &[f32]| Tensor::<4>::from_data(TensorData::new(v.to_vec(), [b, c, h, w]), &device);
        let run = |op: &dyn Fn(Tensor<4>, Tensor<4>, Tensor<1>) -> Tensor<1>, xv: &[f32]| {
            let (x, y) = (tensor(xv).require_grad(), tensor(&yv).require_grad());
            let head = Tensor::<1>::from_data(TensorData::new(head.clone(), [c]), &device);
            let weights = Tensor::<1>::from_data(TensorData::new(weights.clone(), [b]), &device);
            let d = op(x.clone(), y.clone(), head);
            let grads = (d.clone() * weights).sum().backward();
            [
                values(d),
                values(x.grad(&grads).unwrap()),
                values(y.grad(&grads).unwrap()),
            ]
        };
        let ours = run(&lpips_distance, &xv);
        let theirs = run(&portable::lpips_distance, &xv);
        for (what, (a, e)) in ["distance", "x gradient", "y gradient"]
            .iter()
            .zip(ours.iter().zip(&theirs))
        {
            let scale = e.iter().fold(0f32, |m, v| m.max(v.abs()));
            for (a, e) in a.iter().zip(e) {
                assert!((a - e).abs() <= 1e-5 * scale, "{what}: {a} vs {e}");
            }
        }
        // x zero at one pixel of each batch item: the tensor ops' square root has no
        // derivative there (NaN); the op gives the normalisation's one-sided derivative there
        // (finite) and, everywhere else, central differences of the distance.
        let mut zeroed = xv.clone();
        for bb in 0..b {
            for cc in 0..c {
                zeroed[(bb * c + cc) * h * w + 5] = 0.0;
            }
        }
        let [_, grad, _] = run(&lpips_distance, &zeroed);
        let loss = |v: &[f32]| {
            let head = Tensor::<1>::from_data(TensorData::new(head.clone(), [c]), &device);
            let d = values(lpips_distance(tensor(v), tensor(&yv), head));
            d.iter()
                .zip(&weights)
                .map(|(d, w)| f64::from(d * w))
                .sum::<f64>()
        };
        let step = 1e-3f32;
        for i in 0..n {
            assert!(grad[i].is_finite(), "value {i}: {}", grad[i]);
            if i % (h * w) == 5 {
                continue;
            }
            let (mut plus, mut minus) = (zeroed.clone(), zeroed.clone());
            plus[i] += step;
            minus[i] -= step;
            let numeric = (loss(&plus) - loss(&minus)) / f64::from(2.0 * step);
            assert!(
                (f64::from(grad[i]) - numeric).abs() <= 2e-3 * (1.0 + numeric.abs()),
                "value {i}: analytic {} vs numeric {numeric}",
                grad[i]
            );
        }
    }

    /// The ToRGB output op equals its composition of Burn's ops (`portable`): output and the
    /// gradients of `x`, the bias and the skip, from a skip of one pixel (every tap an edge)
    /// up to one of 4 × 3.
    #[test]
    fn to_rgb_output_matches_the_tensor_ops() {
        let device = Device::flex().autodiff();
        for [b, c4, h, w] in [[1, 4, 1, 1], [2, 8, 2, 3], [1, 12, 4, 3]] {
            let ramp = |n: usize, k: usize| -> Vec<f32> {
                (0..n)
                    .map(|i| ((i * 7919 + k * 131) % 97) as f32 / 97.0 - 0.5)
                    .collect()
            };
            let big = [b, c4, 2 * h, 2 * w];
            let run = |op: &dyn Fn(Tensor<4>, Tensor<1>, Tensor<4>) -> Tensor<4>| {
                let x = Tensor::<4>::from_data(
                    TensorData::new(ramp(b * c4 * 4 * h * w, 1), big),
                    &device,
                )
                .require_grad();
                let bias = Tensor::<1>::from_data(TensorData::new(ramp(c4, 2), [c4]), &device)
                    .require_grad();
                let skip = Tensor::<4>::from_data(
                    TensorData::new(ramp(b * c4 * h * w, 3), [b, c4, h, w]),
                    &device,
                )
                .require_grad();
                let r = Tensor::<4>::from_data(
                    TensorData::new(ramp(b * c4 * 4 * h * w, 4), big),
                    &device,
                );
                let y = op(x.clone(), bias.clone(), skip.clone());
                let grads = (y.clone() * r).sum().backward();
                [
                    values(y),
                    values(x.grad(&grads).unwrap()),
                    values(bias.grad(&grads).unwrap()),
                    values(skip.grad(&grads).unwrap()),
                ]
            };
            let (ours, theirs) = (run(&to_rgb_output), run(&portable::to_rgb_output));
            for (what, (a, e)) in ["output", "x gradient", "bias gradient", "skip gradient"]
                .iter()
                .zip(ours.iter().zip(&theirs))
            {
                assert_eq!(a.len(), e.len(), "{what}");
                for (a, e) in a.iter().zip(e) {
                    assert!((a - e).abs() < 1e-5, "{b}×{c4}×{h}×{w} {what}: {a} vs {e}");
                }
            }
        }
    }

    #[test]
    fn cat_channels_and_the_channel_bias_match_the_tensor_ops() {
        let device = Device::flex().autodiff();
        let ramp = |n: usize, k: usize| -> Vec<f32> {
            (0..n)
                .map(|i| ((i * 7919 + k * 131) % 97) as f32 / 97.0 - 0.5)
                .collect()
        };
        let tensor = |shape: [usize; 4], k: usize| {
            let n = shape.iter().product();
            Tensor::<4>::from_data(TensorData::new(ramp(n, k), shape), &device).require_grad()
        };
        let close = |what: &str, a: Vec<f32>, e: Vec<f32>| {
            assert_eq!(a.len(), e.len(), "{what}");
            for (a, e) in a.iter().zip(&e) {
                assert!((a - e).abs() < 1e-6, "{what}: {a} vs {e}");
            }
        };
        for [b, c1, c2, h, w] in [
            [1, 1, 1, 1, 1],
            [2, 3, 5, 4, 3],
            [3, 4, 0, 2, 2],
            [1, 0, 2, 3, 1],
        ] {
            let run = |op: &dyn Fn(Tensor<4>, Tensor<4>) -> Tensor<4>| {
                let (first, second) = (tensor([b, c1, h, w], 1), tensor([b, c2, h, w], 2));
                let y = op(first.clone(), second.clone());
                let r = Tensor::<4>::from_data(
                    TensorData::new(ramp(b * (c1 + c2) * h * w, 3), [b, c1 + c2, h, w]),
                    &device,
                );
                let grads = (y.clone() * r).sum().backward();
                let grad = |t: &Tensor<4>| t.grad(&grads).map(values).unwrap_or_default();
                [values(y), grad(&first), grad(&second)]
            };
            let ours = run(&cat_channels);
            let theirs = run(&|a, b| Tensor::cat(vec![a, b], 1));
            for (what, (a, e)) in ["cat", "first's gradient", "second's gradient"]
                .iter()
                .zip(ours.into_iter().zip(theirs))
            {
                close(&format!("{b}×({c1}+{c2})×{h}×{w} {what}"), a, e);
            }
        }
        for [b, c, h, w] in [[1, 1, 1, 1], [2, 12, 3, 5]] {
            let run = |op: &dyn Fn(Tensor<4>, Tensor<1>) -> Tensor<4>| {
                let x = tensor([b, c, h, w], 4);
                let bias = Tensor::<1>::from_data(TensorData::new(ramp(c, 5), [c]), &device)
                    .require_grad();
                let r = Tensor::<4>::from_data(
                    TensorData::new(ramp(b * c * h * w, 6), [b, c, h, w]),
                    &device,
                );
                let y = op(x.clone(), bias.clone());
                let grads = (y.clone() * r).sum().backward();
                [
                    values(y),
                    values(x.grad(&grads).unwrap()),
                    values(bias.grad(&grads).unwrap()),
                ]
            };
            let ours = run(&add_channel_bias);
            let theirs = run(&|x, bias| x + bias.reshape([1, c, 1, 1]));
            for (what, (a, e)) in ["x + bias", "x's gradient", "the bias's gradient"]
                .iter()
                .zip(ours.into_iter().zip(theirs))
            {
                close(&format!("{b}×{c}×{h}×{w} {what}"), a, e);
            }
        }
    }
}
