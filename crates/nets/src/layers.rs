//! StyleGAN2 building blocks with the equalised learning rate: the network modules the
//! StyleUNets and the discriminator are built of. The ops they call are [`crate::fused`]'s
//! (each choosing a fused pass or Burn's tensor ops) and [`crate::conv`]'s; their weights are
//! drawn by [`crate::init`].
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
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Device, Tensor, TensorData};

use crate::conv::conv2d;
use crate::fused::{
    LinearScales, Modulation, add_channel_bias, blur, noisy_bias_leaky_relu, scale_weight,
    scaled_bias_leaky_relu, scaled_linear, to_rgb_output, upsample2,
};
use crate::init::Init;

/// [`crate::resample::resize`], at the path `f3g-avatar` imports it from.
pub use crate::resample::resize;

/// StyleGAN2's leaky ReLU slope below zero (f64, as Burn's `leaky_relu` takes it).
pub const LRELU_SLOPE: f64 = 0.2;
/// Gain that keeps the variance of leaky ReLU(0.2) activations at one.
pub const LRELU_GAIN: f32 = std::f32::consts::SQRT_2;

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
            scale_weight(self.weight.val(), self.scale),
            self.bias.as_ref().map(Param::val),
            self.options(),
        )
    }

    /// `gain · leaky_relu(conv(x) + bias, slope)` with an activation `bias` (this layer's own
    /// is not added), computed as `gain · leaky_relu(scale · conv(x, weight) + bias, slope)`:
    /// the equalised scale is applied in the activation's pass ([`scaled_bias_leaky_relu`]),
    /// so the weight is convolved as stored — on a GPU no launch scales it, and none scales
    /// its gradient back.
    pub fn forward_activated(
        &self,
        x: Tensor<4>,
        bias: Tensor<1>,
        slope: f64,
        gain: f32,
    ) -> Tensor<4> {
        let y = conv2d(x, self.weight.val(), None, self.options());
        scaled_bias_leaky_relu(y, self.scale, bias, slope, gain)
    }

    /// The convolution, then `leaky_relu(·, slope)` with the bias added in the activation's
    /// single pass ([`Self::forward_activated`]).
    pub fn forward_leaky_relu(&self, x: Tensor<4>, slope: f64) -> Tensor<4> {
        match &self.bias {
            Some(bias) => self.forward_activated(x, bias.val(), slope, 1.0),
            None => leaky_relu(self.forward(x), slope),
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

    /// `[B, in] → [B, out]`, one op ([`scaled_linear`]).
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let scales = if self.activate {
            LinearScales {
                weight_scale: self.scale,
                bias_scale: self.lr_mul,
                slope: LRELU_SLOPE as f32,
                gain: LRELU_GAIN,
            }
        } else {
            LinearScales::affine(self.scale, self.lr_mul)
        };
        scaled_linear(x, self.weight.val(), self.bias.val(), scales)
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
        match &self.activation_bias {
            Some(b) => self
                .conv
                .forward_activated(x, b.val(), LRELU_SLOPE, LRELU_GAIN),
            None => self.conv.forward(x),
        }
    }
}

/// Hands out each modulated layer's range of its network's style vector, in the order the
/// layers are built: the network makes every style with one linear layer of `total` outputs
/// ([`crate::DualStyleUNet`]).
#[derive(Debug, Default)]
pub struct StyleRanges {
    total: usize,
}

impl StyleRanges {
    /// The first of `inputs` fresh styles.
    fn take(&mut self, inputs: usize) -> usize {
        let first = self.total;
        self.total += inputs;
        first
    }

    /// Styles handed out so far.
    pub fn total(&self) -> usize {
        self.total
    }
}

/// A convolution whose weights are scaled per input channel by a style and, optionally,
/// demodulated per output channel (StyleGAN2). Its styles are `C_in` values of its network's
/// style vector from `first` on ([`StyleRanges`]), one vector shared by the whole batch (the
/// StyleUNets use a constant style), so the modulated weights are computed once.
#[derive(Module, Debug)]
pub struct ModulatedConv2d {
    pub weight: Param<Tensor<4>>,
    first: usize,
    scale: f32,
    demodulate: bool,
    upsample: bool,
}

impl ModulatedConv2d {
    pub fn new(
        init: &mut Init,
        channels: [usize; 2],
        kernel: usize,
        styles: &mut StyleRanges,
        demodulate: bool,
        upsample: bool,
    ) -> Self {
        let [cin, cout] = channels;
        Self {
            weight: init.normal([cout, cin, kernel, kernel], 1.0),
            first: styles.take(cin),
            scale: 1.0 / ((cin * kernel * kernel) as f32).sqrt(),
            demodulate,
            upsample,
        }
    }

    /// The layer's part of its network's [`crate::fused::modulate_all`].
    pub fn modulation(&self) -> Modulation {
        Modulation {
            weight: self.weight.val(),
            first: self.first,
            scale: self.scale,
            demodulate: self.demodulate,
        }
    }

    /// `x`: `[B, in, H, W]`, `weight`: this layer's modulated weight (from
    /// [`Self::modulation`]).
    pub fn forward(&self, x: Tensor<4>, weight: Tensor<4>) -> Tensor<4> {
        let k = weight.dims()[2];
        let x = if self.upsample { upsample2(x) } else { x };
        conv2d(
            x,
            weight,
            None,
            ConvOptions::new([1, 1], [k / 2, k / 2], [1, 1], 1),
        )
    }
}

/// Fixed per-pixel noise (StyleGAN2 with `randomize_noise = False`) times a learned strength
/// that starts at zero. The noise map is a parameter without gradient so that checkpoints keep
/// it. [`StyledConv`] adds it in its activation's pass ([`noisy_bias_leaky_relu`]).
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
}

/// Modulated 3×3 convolution (optionally up-sampling), then noise, bias and leaky ReLU in one op.
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
        styles: &mut StyleRanges,
        upsample: bool,
        out_size: usize,
    ) -> Self {
        Self {
            conv: ModulatedConv2d::new(init, channels, 3, styles, true, upsample),
            noise: NoiseInjection::new(init, out_size),
            bias: init.constant([channels[1]], 0.0),
        }
    }

    /// `weight`: the modulated weight of [`Self::conv`].
    pub fn forward(&self, x: Tensor<4>, weight: Tensor<4>) -> Tensor<4> {
        noisy_bias_leaky_relu(
            self.conv.forward(x, weight),
            self.noise.noise.val(),
            self.noise.strength.val(),
            self.bias.val(),
            LRELU_SLOPE,
            LRELU_GAIN,
        )
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
    pub fn new(
        init: &mut Init,
        in_channels: usize,
        out_channels: usize,
        styles: &mut StyleRanges,
    ) -> Self {
        Self {
            conv: ModulatedConv2d::new(
                init,
                [in_channels, 4 * out_channels],
                1,
                styles,
                false,
                false,
            ),
            bias: init.constant([4 * out_channels], 0.0),
        }
    }

    /// `weight`: the modulated weight of [`Self::conv`].
    pub fn forward(&self, x: Tensor<4>, weight: Tensor<4>, skip: Option<Tensor<4>>) -> Tensor<4> {
        let out = self.conv.forward(x, weight);
        match skip {
            Some(s) => to_rgb_output(out, self.bias.val(), s),
            None => add_channel_bias(out, self.bias.val()),
        }
    }
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

    /// `w` `[1, dim]` for the constant input `z = 1/√dim` (the StyleUNets' style). The pixel
    /// norm of a constant, `z / √(mean(z²) + 10⁻⁸)`, is computed on the host in f32: on a GPU
    /// the fill and the norm were seven launches per network and step.
    pub fn constant_style(&self, dim: usize, device: &Device) -> Tensor<2> {
        let z = 1.0 / (dim as f32).sqrt();
        let normed = z / (z * z + 1e-8).sqrt();
        let z = Tensor::<2>::from_data(TensorData::new(vec![normed; dim], [1, dim]), device);
        self.layers.iter().fold(z, |x, layer| layer.forward(x))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().try_into_vec::<f32>().unwrap()
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

    /// The equalised scale applied in the activation's pass equals the scaled weight convolved
    /// (StyleGAN2's formulation): output and the input's, weight's and bias's gradients, with
    /// and without the blur + stride-2 down-sampling.
    #[test]
    fn an_activated_layer_equals_its_scaled_weight_convolved() {
        let device = Device::flex().autodiff();
        for downsample in [false, true] {
            let mut init = Init::new(11, &device);
            let layer = ConvLayer::new(&mut init, [3, 5], 3, downsample, true);
            let bias_values = init.normal_values(5, 0.3);
            let layer = ConvLayer {
                activation_bias: Some(Param::from_tensor(init.tensor(bias_values, [5]))),
                ..layer
            };
            let x_values = init.normal_values(2 * 3 * 8 * 8, 1.0);
            let run = |reference: bool| {
                let x = init.tensor(x_values.clone(), [2, 3, 8, 8]).require_grad();
                let y = if reference {
                    let x = if downsample {
                        blur(x.clone(), 2, 2)
                    } else {
                        x.clone()
                    };
                    let w = scale_weight(layer.conv.weight.val(), layer.conv.scale);
                    let y = conv2d(x, w, None, layer.conv.options());
                    let bias = layer.activation_bias.as_ref().unwrap().val();
                    crate::fused::bias_leaky_relu(y, bias, LRELU_SLOPE, LRELU_GAIN)
                } else {
                    layer.forward(x.clone())
                };
                let n = y.shape().num_elements();
                let r = (0..n).map(|i| ((i * 7) % 11) as f32 - 5.0).collect();
                let r = init.tensor(r, y.dims());
                let grads = (y.clone() * r).sum().backward();
                [
                    values(y),
                    values(x.grad(&grads).unwrap()),
                    values(layer.conv.weight.val().grad(&grads).unwrap()),
                    values(
                        layer
                            .activation_bias
                            .as_ref()
                            .unwrap()
                            .val()
                            .grad(&grads)
                            .unwrap(),
                    ),
                ]
            };
            let (ours, reference) = (run(false), run(true));
            for (what, (got, expected)) in ["y", "dx", "dw", "db"]
                .iter()
                .zip(ours.iter().zip(&reference))
            {
                assert_eq!(got.len(), expected.len());
                for (g, e) in got.iter().zip(expected) {
                    assert!(
                        (g - e).abs() <= 1e-4 * (1.0 + e.abs()),
                        "{what} (down-sampling {downsample}): {g}, the scaled weight gives {e}"
                    );
                }
            }
        }
    }

    #[test]
    fn demodulation_normalises_output_channels() {
        // With demodulation, each output channel's effective weights have unit norm: the
        // responses to a unit impulse in every input channel, squared and summed, give one per
        // output channel, whatever the style.
        let device = Device::flex();
        let mut init = Init::new(5, &device);
        // The layer's styles from the third on of a vector of eight.
        let mut styles = StyleRanges::default();
        styles.take(2);
        let conv = ModulatedConv2d::new(&mut init, [4, 3], 3, &mut styles, true, false);
        let style_values = init.normal_values(8, 3.0);
        let style = init.tensor(style_values, [8]);
        let mut energy = [0.0f32; 3];
        for c in 0..4 {
            let mut x = vec![0.0f32; 4 * 9 * 9];
            x[c * 81 + 4 * 9 + 4] = 1.0;
            let weight = crate::fused::modulate_all(vec![conv.modulation()], style.clone());
            let y = values(conv.forward(init.tensor(x, [1, 4, 9, 9]), weight[0].clone()));
            for (o, e) in energy.iter_mut().enumerate() {
                *e += y[o * 81..(o + 1) * 81].iter().map(|v| v * v).sum::<f32>();
            }
        }
        for e in energy {
            assert!((e - 1.0).abs() < 1e-4, "{e}");
        }
    }
}
