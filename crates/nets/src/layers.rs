//! StyleGAN2 building blocks with the equalised learning rate.
//!
//! Every weight is stored as `N(0, 1)` (divided by the layer's learning-rate multiplier) and
//! scaled at run time by `lr_mul / √fan_in`, as StyleGAN2 does, so that Adam sees parameters
//! of unit scale whatever the layer's width. Layouts are Burn's: images `[B, C, H, W]`, conv
//! weights `[out, in, kh, kw]`, linear weights `[out, in]`.
//!
//! Resampling follows StyleGAN2 in spirit with two documented simplifications:
//! down-sampling convolutions blur with the separable `[1, 3, 3, 1]` filter before a
//! stride-2 convolution (exactly as StyleGAN2); up-sampling is bilinear ×2
//! (`align_corners = false`, the same filter up to border handling) followed by a stride-1
//! convolution instead of a transposed convolution and blur.

use burn::module::{Module, Param};
use burn::tensor::activation::leaky_relu;
use burn::tensor::module::interpolate;
use burn::tensor::ops::{ConvOptions, InterpolateMode, InterpolateOptions};
use burn::tensor::{Device, Tensor, TensorData};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr_free::normal;

use crate::conv::conv2d;
use crate::fused;

/// StyleGAN2's leaky ReLU slope below zero (f64, as Burn's `leaky_relu` takes it).
pub const LRELU_SLOPE: f64 = 0.2;
/// Gain that keeps the variance of leaky ReLU(0.2) activations at one.
pub const LRELU_GAIN: f32 = std::f32::consts::SQRT_2;

/// Deterministic host-side initialisation: the same seed gives the same weights.
pub struct Init {
    rng: ChaCha8Rng,
    pub device: Device,
}

impl Init {
    pub fn new(seed: u64, device: &Device) -> Self {
        Self {
            rng: ChaCha8Rng::seed_from_u64(seed),
            device: device.clone(),
        }
    }

    /// Values drawn from `N(0, std²)`.
    pub fn normal_values(&mut self, count: usize, std: f32) -> Vec<f32> {
        (0..count).map(|_| std * normal(&mut self.rng)).collect()
    }

    /// A trainable tensor drawn from `N(0, std²)`.
    pub fn normal<const D: usize>(&mut self, shape: [usize; D], std: f32) -> Param<Tensor<D>> {
        let values = self.normal_values(shape.iter().product(), std);
        Param::from_data(TensorData::new(values, shape), &self.device)
    }

    /// A trainable tensor filled with `value`.
    pub fn constant<const D: usize>(&mut self, shape: [usize; D], value: f32) -> Param<Tensor<D>> {
        let values = vec![value; shape.iter().product()];
        Param::from_data(TensorData::new(values, shape), &self.device)
    }

    /// A constant (non-persistent) tensor from values.
    pub fn tensor<const D: usize>(&self, values: Vec<f32>, shape: [usize; D]) -> Tensor<D> {
        Tensor::from_data(TensorData::new(values, shape), &self.device)
    }
}

/// Box–Muller standard normal samples without an extra dependency.
mod rand_distr_free {
    use rand::Rng;

    pub fn normal(rng: &mut impl Rng) -> f32 {
        let u1: f64 = rng.random_range(f64::MIN_POSITIVE..1.0);
        let u2: f64 = rng.random();
        ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
    }
}

/// `leaky_relu(x + bias, 0.2) · √2` with a per-channel bias (StyleGAN2's fused activation).
pub fn fused_lrelu(x: Tensor<4>, bias: Tensor<1>) -> Tensor<4> {
    bias_leaky_relu(x, bias, LRELU_SLOPE, LRELU_GAIN)
}

/// `gain · leaky_relu(x + bias, slope)` with a per-channel bias (`gain > 0`, `slope ≥ 0`; a
/// ReLU with 0 and 1): one op where it runs ([`fused::bias_leaky_relu`]),
/// [`portable::bias_leaky_relu`] elsewhere.
pub fn bias_leaky_relu(x: Tensor<4>, bias: Tensor<1>, slope: f64, gain: f32) -> Tensor<4> {
    if fused::runs(&x, 0) {
        fused::bias_leaky_relu(x, bias, slope, gain)
    } else {
        portable::bias_leaky_relu(x, bias, slope, gain)
    }
}

/// StyleGAN2's modulated weight: input channel `i` of `weight` scaled by `style[i] · scale`,
/// each output channel then divided by its norm if `demodulate`: one op where it runs
/// ([`fused::modulate`]), [`portable::modulate`] elsewhere.
pub fn modulate(weight: Tensor<4>, style: Tensor<1>, scale: f32, demodulate: bool) -> Tensor<4> {
    if fused::runs(&weight, 0) {
        fused::modulate(weight, style, scale, demodulate)
    } else {
        portable::modulate(weight, style, scale, demodulate)
    }
}

/// Bilinear resize (`align_corners = false`); doubling goes through [`upsample2`] and halving
/// even sizes through [`downsample2`] (there bilinear samples midway between two pixels: the
/// 2 × 2 mean). On the CPU (Flex) other sizes use Burn's `interpolate`; on other devices
/// [`resize_separable`], because Burn 0.22's CubeCL backends (CUDA, wgpu) have no backward for
/// bilinear interpolation.
pub fn resize(x: Tensor<4>, height: usize, width: usize) -> Tensor<4> {
    let [_, _, h, w] = x.dims();
    if [height, width] == [2 * h, 2 * w] {
        return upsample2(x);
    }
    if h % 2 == 0 && w % 2 == 0 && [height, width] == [h / 2, w / 2] {
        return downsample2(x);
    }
    if !fused::on_flex(&x) {
        return resize_separable(x, height, width);
    }
    let mut options = InterpolateOptions::new(InterpolateMode::Bilinear);
    options.align_corners = false;
    options.output_size = Some([height, width]);
    interpolate(x, options)
}

/// Bilinear resize (`align_corners = false`, no antialiasing: PyTorch's and Burn's semantics)
/// as two matrix products with the interpolation weights of each axis — differentiable on
/// every backend.
pub fn resize_separable(x: Tensor<4>, height: usize, width: usize) -> Tensor<4> {
    let [n, c, h, w] = x.dims();
    let device = x.device();
    // Along x: [n·c·h, w] · [w, width].
    let y = x
        .reshape([n * c * h, w])
        .matmul(bilinear_weights(w, width, &device).transpose());
    // Along y: [n·c·width, h] · [h, height].
    let y = y
        .reshape([n * c, h, width])
        .swap_dims(1, 2)
        .reshape([n * c * width, h])
        .matmul(bilinear_weights(h, height, &device).transpose());
    y.reshape([n * c, width, height])
        .swap_dims(1, 2)
        .reshape([n, c, height, width])
}

/// `[to, from]`: row `o` holds the weights of the source samples that output `o` blends
/// (source coordinate `(o + ½)·from/to − ½`, clamped at 0; the upper neighbour clamped to the
/// last sample).
fn bilinear_weights(from: usize, to: usize, device: &Device) -> Tensor<2> {
    let mut weights = vec![0f32; to * from];
    let scale = from as f64 / to as f64;
    for o in 0..to {
        let source = ((o as f64 + 0.5) * scale - 0.5).max(0.0);
        let lower = (source.floor() as usize).min(from - 1);
        let upper = (lower + 1).min(from - 1);
        let t = (source - lower as f64) as f32;
        weights[o * from + lower] += 1.0 - t;
        weights[o * from + upper] += t;
    }
    Tensor::from_data(TensorData::new(weights, [to, from]), device)
}

/// Bilinear up-sampling by 2 (`align_corners = false`): one op where it runs
/// ([`fused::upsample2`]), [`portable::upsample2`] elsewhere.
pub fn upsample2(x: Tensor<4>) -> Tensor<4> {
    if fused::runs(&x, 4 * x.shape().num_elements()) {
        fused::upsample2(x)
    } else {
        portable::upsample2(x)
    }
}

/// The mean of each 2 × 2 block, `[B, C, H, W] → [B, C, ⌊H/2⌋, ⌊W/2⌋]`: one op where it runs
/// ([`fused::downsample2`]), [`portable::downsample2`] elsewhere.
pub fn downsample2(x: Tensor<4>) -> Tensor<4> {
    if fused::runs(&x, 0) {
        fused::downsample2(x)
    } else {
        portable::downsample2(x)
    }
}

/// The separable `[1, 3, 3, 1] / 8` blur of StyleGAN2, with zero padding `(before, after)` on
/// both axes (the output grows by `before + after − 3`): one op where it runs
/// ([`fused::blur`]), [`portable::blur`] elsewhere.
pub fn blur(x: Tensor<4>, before: usize, after: usize) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let grown = |n: usize| n + before + after;
    if before <= 3 && after <= 3 && fused::runs(&x, b * c * grown(h) * grown(w)) {
        fused::blur(x, before, after)
    } else {
        portable::blur(x, before, after)
    }
}

/// The element-wise chains written with Burn's tensor ops, differentiable on every backend:
/// what devices with Burn's `fusion` run, and the reference the fused ops ([`fused`]) are
/// tested against.
pub mod portable {
    use burn::tensor::Tensor;
    use burn::tensor::activation::{leaky_relu, relu};
    use burn::tensor::module::avg_pool2d;
    use burn::tensor::ops::AvgPoolOptions;

    use crate::fused::DEMODULATION_EPSILON;

    /// `gain · leaky_relu(x + bias, slope)` with a per-channel bias; with slope 0 Burn's `relu`,
    /// whose backward selects (a non-finite gradient where the output is zero does not pass;
    /// `leaky_relu`'s multiplies it by the slope, and `∞ · 0` is NaN).
    pub fn bias_leaky_relu(x: Tensor<4>, bias: Tensor<1>, slope: f64, gain: f32) -> Tensor<4> {
        let c = bias.dims()[0];
        let pre = x + bias.reshape([1, c, 1, 1]);
        if slope == 0.0 {
            relu(pre) * gain
        } else {
            leaky_relu(pre, slope) * gain
        }
    }

    /// StyleGAN2's modulated weight: `weight · style[i] · scale`, then with `demodulate` each
    /// output channel divided by `√(Σ w² + 10⁻⁸)`.
    pub fn modulate(
        weight: Tensor<4>,
        style: Tensor<1>,
        scale: f32,
        demodulate: bool,
    ) -> Tensor<4> {
        let [c_out, c_in, _, _] = weight.dims();
        let w = weight * style.reshape([1, c_in, 1, 1]) * scale;
        if !demodulate {
            return w;
        }
        let squares = w.clone().powf_scalar(2.0).sum_dim(1).sum_dim(2).sum_dim(3);
        let d = (squares + DEMODULATION_EPSILON).sqrt().recip();
        w * d.reshape([c_out, 1, 1, 1])
    }

    /// Bilinear up-sampling by 2 (`align_corners = false`), written with slices, sums and a
    /// reshape rather than `interpolate`, because Burn 0.22's CubeCL backends (CUDA, wgpu) have no
    /// backward for bilinear interpolation. Per axis: `out[2i] = ¾ x[i] + ¼ x[i−1]`,
    /// `out[2i+1] = ¾ x[i] + ¼ x[i+1]`, with the edge sample repeated at the borders — exactly
    /// bilinear interpolation at the source coordinates `i ∓ ¼`.
    pub fn upsample2(x: Tensor<4>) -> Tensor<4> {
        let x = upsample2_axis(x, 3);
        upsample2_axis(x, 2)
    }

    fn upsample2_axis(x: Tensor<4>, axis: usize) -> Tensor<4> {
        let dims = x.dims();
        let n = dims[axis];
        let slice = |from: usize, to: usize| x.clone().narrow(axis, from, to - from);
        let (previous, next) = if n == 1 {
            (x.clone(), x.clone())
        } else {
            (
                Tensor::cat(vec![slice(0, 1), slice(0, n - 1)], axis),
                Tensor::cat(vec![slice(1, n), slice(n - 1, n)], axis),
            )
        };
        let centre = x.clone() * 0.75;
        let even = centre.clone() + previous * 0.25;
        let odd = centre + next * 0.25;
        let mut out = dims;
        out[axis] = 2 * n;
        Tensor::stack::<5>(vec![even, odd], axis + 1).reshape(out)
    }

    /// `x` with `before` zero rows and columns before and `after` after, on the device: Burn's
    /// `pad` fills its output on the host and uploads it on an autodiff device (`Autodiff` has
    /// no `float_full` of its own, and the default builds `TensorData::full`) — on a GPU a
    /// host allocation and a copy over the bus of every padded activation, each step (a fifth
    /// of a `paper` step's host time on the offline CUDA driver).
    fn zero_pad(x: Tensor<4>, before: usize, after: usize) -> Tensor<4> {
        if before == 0 && after == 0 {
            return x;
        }
        let [b, c, h, w] = x.dims();
        let grown = before + after;
        Tensor::zeros([b, c, h + grown, w + grown], &x.device())
            .slice_assign([0..b, 0..c, before..before + h, before..before + w], x)
    }

    /// The mean of each 2 × 2 block (Burn's average pooling).
    pub fn downsample2(x: Tensor<4>) -> Tensor<4> {
        avg_pool2d(x, AvgPoolOptions::new([2, 2]))
    }

    /// The separable `[1, 3, 3, 1] / 8` blur of StyleGAN2, with zero padding `(before, after)` on
    /// both axes (the output grows by `before + after − 3`).
    pub fn blur(x: Tensor<4>, before: usize, after: usize) -> Tensor<4> {
        const TAPS: [f32; 4] = [1.0 / 8.0, 3.0 / 8.0, 3.0 / 8.0, 1.0 / 8.0];
        let x = zero_pad(x, before, after);
        let [b, c, h, w] = x.dims();
        let (oh, ow) = (h - 3, w - 3);
        let rows = TAPS
            .iter()
            .enumerate()
            .map(|(k, &t)| x.clone().slice([0..b, 0..c, 0..h, k..k + ow]) * t)
            .reduce(|a, v| a + v)
            .expect("four taps");
        TAPS.iter()
            .enumerate()
            .map(|(k, &t)| rows.clone().slice([0..b, 0..c, k..k + oh, 0..ow]) * t)
            .reduce(|a, v| a + v)
            .expect("four taps")
    }

    /// Orthonormal 2-D Haar analysis: `[B, C, 2H, 2W] → [B, 4C, H, W]`, channel `4c + k` holding
    /// sub-band `k ∈ (LL, LH, HL, HH)` of channel `c`.
    pub fn haar(x: Tensor<4>) -> Tensor<4> {
        let [b, c, h2, w2] = x.dims();
        let (h, w) = (h2 / 2, w2 / 2);
        let x = x.reshape([b, c, h, 2, w, 2]);
        let tap = |i: usize, j: usize| {
            x.clone()
                .slice([0..b, 0..c, 0..h, i..i + 1, 0..w, j..j + 1])
                .reshape([b, c, 1, h, w])
        };
        let (p, q, r, s) = (tap(0, 0), tap(0, 1), tap(1, 0), tap(1, 1));
        let ll = (p.clone() + q.clone() + r.clone() + s.clone()) * 0.5;
        let lh = (p.clone() + q.clone() - r.clone() - s.clone()) * 0.5;
        let hl = (p.clone() - q.clone() + r.clone() - s.clone()) * 0.5;
        let hh = (p - q - r + s) * 0.5;
        Tensor::cat(vec![ll, lh, hl, hh], 2).reshape([b, 4 * c, h, w])
    }

    /// The inverse of [`haar`]: `[B, 4C, H, W] → [B, C, 2H, 2W]`.
    pub fn inverse_haar(x: Tensor<4>) -> Tensor<4> {
        let [b, c4, h, w] = x.dims();
        let c = c4 / 4;
        let x = x.reshape([b, c, 4, h, w]);
        let band = |k: usize| x.clone().slice([0..b, 0..c, k..k + 1, 0..h, 0..w]);
        let (ll, lh, hl, hh) = (band(0), band(1), band(2), band(3));
        let p = (ll.clone() + lh.clone() + hl.clone() + hh.clone()) * 0.5;
        let q = (ll.clone() + lh.clone() - hl.clone() - hh.clone()) * 0.5;
        let r = (ll.clone() - lh.clone() + hl.clone() - hh.clone()) * 0.5;
        let s = (ll - lh - hl + hh) * 0.5;
        // [B, C, 1, H, W] each → [B, C, H, 2 (i), W, 2 (j)].
        let row = |a: Tensor<5>, bb: Tensor<5>| {
            Tensor::cat(
                vec![a.reshape([b, c, h, w, 1]), bb.reshape([b, c, h, w, 1])],
                4,
            )
        };
        let top = row(p, q).reshape([b, c, h, 1, w, 2]);
        let bottom = row(r, s).reshape([b, c, h, 1, w, 2]);
        Tensor::cat(vec![top, bottom], 3).reshape([b, c, 2 * h, 2 * w])
    }
}

/// A convolution with equalised learning rate.
#[derive(Module, Debug)]
pub struct EqualConv2d {
    pub weight: Param<Tensor<4>>,
    pub bias: Option<Param<Tensor<1>>>,
    scale: f32,
    stride: usize,
    padding: usize,
}

impl EqualConv2d {
    pub fn new(
        init: &mut Init,
        channels: [usize; 2],
        kernel: usize,
        stride: usize,
        padding: usize,
        bias: bool,
    ) -> Self {
        let [cin, cout] = channels;
        Self {
            weight: init.normal([cout, cin, kernel, kernel], 1.0),
            bias: bias.then(|| init.constant([cout], 0.0)),
            scale: 1.0 / ((cin * kernel * kernel) as f32).sqrt(),
            stride,
            padding,
        }
    }

    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        conv2d(
            x,
            self.weight.val() * self.scale,
            self.bias.as_ref().map(Param::val),
            self.options(),
        )
    }

    /// The convolution, then `leaky_relu(·, slope)` with the bias added in the activation's
    /// single pass ([`bias_leaky_relu`]).
    pub fn forward_leaky_relu(&self, x: Tensor<4>, slope: f64) -> Tensor<4> {
        let y = conv2d(x, self.weight.val() * self.scale, None, self.options());
        match &self.bias {
            Some(bias) => bias_leaky_relu(y, bias.val(), slope, 1.0),
            None => leaky_relu(y, slope),
        }
    }

    fn options(&self) -> ConvOptions<2> {
        ConvOptions::new([self.stride; 2], [self.padding; 2], [1, 1], 1)
    }
}

/// A linear layer with equalised learning rate and an optional fused leaky ReLU.
#[derive(Module, Debug)]
pub struct EqualLinear {
    pub weight: Param<Tensor<2>>,
    pub bias: Param<Tensor<1>>,
    scale: f32,
    lr_mul: f32,
    activate: bool,
}

impl EqualLinear {
    pub fn new(
        init: &mut Init,
        channels: [usize; 2],
        bias_init: f32,
        lr_mul: f32,
        activate: bool,
    ) -> Self {
        let [cin, cout] = channels;
        Self {
            weight: init.normal([cout, cin], 1.0 / lr_mul),
            bias: init.constant([cout], bias_init / lr_mul),
            scale: lr_mul / (cin as f32).sqrt(),
            lr_mul,
            activate,
        }
    }

    /// `[B, in] → [B, out]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let cout = self.bias.dims()[0];
        let y = x.matmul((self.weight.val() * self.scale).transpose())
            + (self.bias.val() * self.lr_mul).reshape([1, cout]);
        if self.activate {
            leaky_relu(y, LRELU_SLOPE) * LRELU_GAIN
        } else {
            y
        }
    }
}

/// StyleGAN2's `ConvLayer`: optional blur + stride-2 down-sampling, an equalised convolution,
/// and optionally the fused leaky ReLU.
#[derive(Module, Debug)]
pub struct ConvLayer {
    pub conv: EqualConv2d,
    pub activation_bias: Option<Param<Tensor<1>>>,
    downsample: bool,
    kernel: usize,
}

impl ConvLayer {
    pub fn new(
        init: &mut Init,
        channels: [usize; 2],
        kernel: usize,
        downsample: bool,
        activate: bool,
    ) -> Self {
        let (stride, padding) = if downsample { (2, 0) } else { (1, kernel / 2) };
        Self {
            conv: EqualConv2d::new(init, channels, kernel, stride, padding, !activate),
            activation_bias: activate.then(|| init.constant([channels[1]], 0.0)),
            downsample,
            kernel,
        }
    }

    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let x = if self.downsample {
            // Pad so that blur + stride-2 convolution halves the size exactly.
            let p = 2 + self.kernel - 1;
            blur(x, p.div_ceil(2), p / 2)
        } else {
            x
        };
        let y = self.conv.forward(x);
        match &self.activation_bias {
            Some(b) => fused_lrelu(y, b.val()),
            None => y,
        }
    }
}

/// A convolution whose weights are scaled per input channel by a style vector and, optionally,
/// demodulated per output channel (StyleGAN2). The style is one vector shared by the whole
/// batch (the StyleUNets use a constant style), so the modulated weights are computed once.
#[derive(Module, Debug)]
pub struct ModulatedConv2d {
    pub weight: Param<Tensor<4>>,
    pub modulation: EqualLinear,
    scale: f32,
    demodulate: bool,
    upsample: bool,
}

impl ModulatedConv2d {
    pub fn new(
        init: &mut Init,
        channels: [usize; 2],
        kernel: usize,
        style_dim: usize,
        demodulate: bool,
        upsample: bool,
    ) -> Self {
        let [cin, cout] = channels;
        Self {
            weight: init.normal([cout, cin, kernel, kernel], 1.0),
            modulation: EqualLinear::new(init, [style_dim, cin], 1.0, 1.0, false),
            scale: 1.0 / ((cin * kernel * kernel) as f32).sqrt(),
            demodulate,
            upsample,
        }
    }

    /// `x`: `[B, in, H, W]`, `style`: `[1, style_dim]`.
    pub fn forward(&self, x: Tensor<4>, style: Tensor<2>) -> Tensor<4> {
        let [_, cin, k, _] = self.weight.dims();
        let s = self.modulation.forward(style).reshape([cin]);
        let w = modulate(self.weight.val(), s, self.scale, self.demodulate);
        let x = if self.upsample { upsample2(x) } else { x };
        conv2d(
            x,
            w,
            None,
            ConvOptions::new([1, 1], [k / 2, k / 2], [1, 1], 1),
        )
    }
}

/// Fixed per-pixel noise (StyleGAN2 with `randomize_noise = False`) times a learned strength
/// that starts at zero. The noise map is a parameter without gradient so that checkpoints keep
/// it.
#[derive(Module, Debug)]
pub struct NoiseInjection {
    pub strength: Param<Tensor<1>>,
    pub noise: Param<Tensor<4>>,
}

impl NoiseInjection {
    pub fn new(init: &mut Init, size: usize) -> Self {
        Self {
            strength: init.constant([1], 0.0),
            noise: init.normal([1, 1, size, size], 1.0).set_require_grad(false),
        }
    }

    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        x + self.noise.val() * self.strength.val().reshape([1, 1, 1, 1])
    }
}

/// Modulated 3×3 convolution (optionally up-sampling), noise, fused leaky ReLU.
#[derive(Module, Debug)]
pub struct StyledConv {
    pub conv: ModulatedConv2d,
    pub noise: NoiseInjection,
    pub bias: Param<Tensor<1>>,
}

impl StyledConv {
    pub fn new(
        init: &mut Init,
        channels: [usize; 2],
        style_dim: usize,
        upsample: bool,
        out_size: usize,
    ) -> Self {
        Self {
            conv: ModulatedConv2d::new(init, channels, 3, style_dim, true, upsample),
            noise: NoiseInjection::new(init, out_size),
            bias: init.constant([channels[1]], 0.0),
        }
    }

    pub fn forward(&self, x: Tensor<4>, style: Tensor<2>) -> Tensor<4> {
        fused_lrelu(
            self.noise.forward(self.conv.forward(x, style)),
            self.bias.val(),
        )
    }
}

/// Orthonormal 2-D Haar analysis: `[B, C, 2H, 2W] → [B, 4C, H, W]`, channel `4c + k` holding
/// sub-band `k ∈ (LL, LH, HL, HH)` of channel `c`: one op where it runs ([`fused::haar`]),
/// [`portable::haar`] elsewhere.
pub fn haar(x: Tensor<4>) -> Tensor<4> {
    if fused::runs(&x, 0) {
        fused::haar(x)
    } else {
        portable::haar(x)
    }
}

/// The inverse of [`haar`]: `[B, 4C, H, W] → [B, C, 2H, 2W]`.
pub fn inverse_haar(x: Tensor<4>) -> Tensor<4> {
    if fused::runs(&x, 0) {
        fused::inverse_haar(x)
    } else {
        portable::inverse_haar(x)
    }
}

/// StyleGAN2's `ToRGB` in the Haar domain: a modulated 1×1 convolution without demodulation to
/// `4 · out` sub-band channels plus a bias, adding the previous level's output carried up as
/// inverse Haar → ×2 up-sampling → Haar.
#[derive(Module, Debug)]
pub struct ToRgb {
    pub conv: ModulatedConv2d,
    pub bias: Param<Tensor<1>>,
}

impl ToRgb {
    pub fn new(init: &mut Init, in_channels: usize, out_channels: usize, style_dim: usize) -> Self {
        Self {
            conv: ModulatedConv2d::new(
                init,
                [in_channels, 4 * out_channels],
                1,
                style_dim,
                false,
                false,
            ),
            bias: init.constant([4 * out_channels], 0.0),
        }
    }

    pub fn forward(&self, x: Tensor<4>, style: Tensor<2>, skip: Option<Tensor<4>>) -> Tensor<4> {
        let c = self.bias.dims()[0];
        let out = self.conv.forward(x, style) + self.bias.val().reshape([1, c, 1, 1]);
        match skip {
            Some(s) => out + haar(upsample2(inverse_haar(s))),
            None => out,
        }
    }
}

/// `x / √(mean(x²) + 1e-8)` over the feature axis.
pub fn pixel_norm(x: Tensor<2>) -> Tensor<2> {
    let ms = x.clone().powf_scalar(2.0).mean_dim(1);
    x / (ms + 1e-8).sqrt()
}

/// The mapping network: pixel norm then `n_mlp` equalised linear layers with fused leaky
/// ReLU and learning-rate multiplier `lr_mul`.
#[derive(Module, Debug)]
pub struct Mapping {
    pub layers: Vec<EqualLinear>,
}

impl Mapping {
    pub fn new(init: &mut Init, style_dim: usize, n_mlp: usize, lr_mul: f32) -> Self {
        Self {
            layers: (0..n_mlp)
                .map(|_| EqualLinear::new(init, [style_dim, style_dim], 0.0, lr_mul, true))
                .collect(),
        }
    }

    pub fn forward(&self, z: Tensor<2>) -> Tensor<2> {
        self.layers
            .iter()
            .fold(pixel_norm(z), |x, layer| layer.forward(x))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn halving_equals_bilinear_interpolation_and_area_pooling() {
        use burn::tensor::module::avg_pool2d;
        use burn::tensor::ops::AvgPoolOptions;
        let device = Device::flex().autodiff();
        // Output and input gradient of `op` on a `[2, 3, h, w]` ramp.
        let run = |op: &dyn Fn(Tensor<4>) -> Tensor<4>, h: usize, w: usize| {
            let n = 2 * 3 * h * w;
            let v: Vec<f32> = (0..n)
                .map(|i| ((i * 7919) % 97) as f32 / 97.0 - 0.5)
                .collect();
            let x = Tensor::<4>::from_data(TensorData::new(v, [2, 3, h, w]), &device);
            let x = x.require_grad();
            let y = op(x.clone());
            let r: Vec<f32> = (0..y.shape().num_elements())
                .map(|i| ((i * 31) % 13) as f32 - 6.0)
                .collect();
            let r = Tensor::<4>::from_data(TensorData::new(r, y.dims()), &device);
            let grads = (y.clone() * r).sum().backward();
            [values(y), values(x.grad(&grads).unwrap())]
        };
        let assert_same = |ours: [Vec<f32>; 2], theirs: [Vec<f32>; 2], what: &str| {
            for (ours, theirs) in ours.iter().zip(&theirs) {
                assert_eq!(ours.len(), theirs.len(), "{what}");
                for (a, b) in ours.iter().zip(theirs) {
                    assert!((a - b).abs() < 1e-5, "{what}: {a} vs {b}");
                }
            }
        };
        // Even sizes: `resize` to half is bilinear interpolation.
        for [h, w] in [[2, 2], [4, 6], [8, 8]] {
            let bilinear = |x: Tensor<4>| {
                let mut options = InterpolateOptions::new(InterpolateMode::Bilinear);
                options.align_corners = false;
                options.output_size = Some([h / 2, w / 2]);
                interpolate(x, options)
            };
            let theirs = run(&bilinear, h, w);
            let what = format!("{h}×{w} halved");
            assert_same(
                run(&|x| resize(x, h / 2, w / 2), h, w),
                theirs.clone(),
                &what,
            );
            assert_same(run(&portable::downsample2, h, w), theirs, &what);
        }
        // Any size: the 2 × 2 mean is average pooling, and halving twice pools 4 × 4.
        let pool = |k: usize| move |x: Tensor<4>| avg_pool2d(x, AvgPoolOptions::new([k, k]));
        for [h, w] in [[5, 7], [9, 13], [1, 4]] {
            let what = format!("{h}×{w}");
            assert_same(run(&downsample2, h, w), run(&pool(2), h, w), &what);
            if h >= 4 && w >= 4 {
                let twice = |x| downsample2(downsample2(x));
                assert_same(run(&twice, h, w), run(&pool(4), h, w), &what);
            }
        }
    }

    #[test]
    fn separable_resize_equals_interpolate_forward_and_backward() {
        let device = Device::flex().autodiff();
        for (h, w, to_h, to_w) in [(5, 7, 9, 4), (8, 8, 3, 13), (16, 12, 16, 12), (1, 3, 4, 6)] {
            let v: Vec<f32> = (0..2 * 3 * h * w)
                .map(|i| ((i * 7919) % 97) as f32 / 97.0 - 0.5)
                .collect();
            let x = Tensor::<4>::from_data(TensorData::new(v, [2, 3, h, w]), &device);
            let weights: Vec<f32> = (0..2 * 3 * to_h * to_w)
                .map(|i| ((i * 31) % 13) as f32 - 6.0)
                .collect();
            let weights =
                Tensor::<4>::from_data(TensorData::new(weights, [2, 3, to_h, to_w]), &device);
            let run = |up: &dyn Fn(Tensor<4>) -> Tensor<4>| {
                let x = x.clone().require_grad();
                let y = up(x.clone());
                let grads = (y.clone() * weights.clone()).sum().backward();
                (values(y), values(x.grad(&grads).unwrap()))
            };
            let (ours, ours_grad) = run(&|x| resize_separable(x, to_h, to_w));
            let (theirs, theirs_grad) = run(&|x| {
                let mut options = InterpolateOptions::new(InterpolateMode::Bilinear);
                options.align_corners = false;
                options.output_size = Some([to_h, to_w]);
                interpolate(x, options)
            });
            assert_eq!(ours.len(), theirs.len());
            for (a, b) in ours
                .iter()
                .zip(&theirs)
                .chain(ours_grad.iter().zip(&theirs_grad))
            {
                assert!((a - b).abs() < 1e-5, "{h}×{w} → {to_h}×{to_w}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn blur_preserves_constants_inside_and_halves_with_stride() {
        let device = Device::flex();
        let init = Init::new(0, &device);
        let x = init.tensor(vec![1.0; 64], [1, 1, 8, 8]);
        let y = blur(x, 2, 1);
        assert_eq!(y.dims(), [1, 1, 8, 8]);
        let v = values(y);
        // Interior pixels see the full kernel, which sums to one.
        assert!((v[3 * 8 + 3] - 1.0).abs() < 1e-6);
        let mut init = Init::new(3, &device);
        let layer = ConvLayer::new(&mut init, [1, 4], 3, true, true);
        let out = layer.forward(init.tensor(vec![0.5; 64], [1, 1, 8, 8]));
        assert_eq!(out.dims(), [1, 4, 4, 4]);
    }

    #[test]
    fn demodulation_normalises_output_channels() {
        // With demodulation, each output channel's effective weights have unit norm: the
        // responses to a unit impulse in every input channel, squared and summed, give one per
        // output channel, whatever the style.
        let device = Device::flex();
        let mut init = Init::new(5, &device);
        let conv = ModulatedConv2d::new(&mut init, [4, 3], 3, 8, true, false);
        let style_values = init.normal_values(8, 3.0);
        let style = init.tensor(style_values, [1, 8]);
        let mut energy = [0.0f32; 3];
        for c in 0..4 {
            let mut x = vec![0.0f32; 4 * 9 * 9];
            x[c * 81 + 4 * 9 + 4] = 1.0;
            let y = values(conv.forward(init.tensor(x, [1, 4, 9, 9]), style.clone()));
            for (o, e) in energy.iter_mut().enumerate() {
                *e += y[o * 81..(o + 1) * 81].iter().map(|v| v * v).sum::<f32>();
            }
        }
        for e in energy {
            assert!((e - 1.0).abs() < 1e-4, "{e}");
        }
    }
}
