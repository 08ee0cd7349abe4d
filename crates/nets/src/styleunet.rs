//! The DualStyleUNet of Animatable Gaussians / F3G-Avatar: one encoder, two StyleGAN2-style
//! decoders (front and back), output in the Haar domain.
//!
//! ```text
//! input [B, in, S, S] ── ConvLayer ↓ ─▶ S/2 ─┬─ (+FromRGB) ─ ConvBlock ↓ ─▶ S/4 … ─▶ middle
//!                                           skips at S/2, S/4, …, middle
//! decoder (×2): x = skip(middle); for r = middle … O/4:
//!     x = comb_r(x ‖ skip_r) → StyledConv ↑ (2r) → StyledConv → [+ view features at S/2]
//!     rgb = ToRGB(x, rgb)   (4·out Haar sub-bands at 2r)
//! output = inverse Haar(rgb): [B, out, O, O], O = S or 2S
//! ```
//!
//! Channels per resolution follow StyleGAN2: `min(max_channels, channel_base · cm / r)`
//! (paper values: base 16384, max 512, so cm 2 gives 512 up to 64², then 256, 128, 64, 32).
//! The style is a constant `1/√d` vector through the learned mapping network, the same for every
//! layer (n_latent collapses to one w); each modulated layer's affine map of w is a range of one
//! linear layer's outputs (StyleGAN2's per-layer maps stacked); noise maps are fixed. The optional
//! view branch (the colour networks) turns a map of `n · v` per side into features added to that
//! side's decoder where its features reach `S/2` (AG adds them at 256² for S = 512).

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::NetsError;
use crate::fused::{
    Modulation, cat_channels, channels_last, downsample2, inverse_haar, modulate_all,
};
use crate::init::Init;
use crate::layers::{
    ConvLayer, EqualConv2d, EqualLinear, LRELU_GAIN, LRELU_SLOPE, Mapping, StyleRanges, StyledConv,
    ToRgb,
};
use crate::resample::resize;

/// Architecture of a [`DualStyleUNet`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StyleUNetConfig {
    /// Side of the input maps (a power of two).
    pub input_size: usize,
    /// Side of each output map: `input_size` or `2 · input_size`.
    pub output_size: usize,
    pub in_channels: usize,
    /// Output channels per side.
    pub out_channels: usize,
    pub channel_multiplier: usize,
    /// `channels(r) = min(max_channels, channel_base · channel_multiplier / r)`.
    pub channel_base: usize,
    pub max_channels: usize,
    pub style_dim: usize,
    /// Depth of the mapping network.
    pub n_mlp: usize,
    /// Resolution of the bottleneck.
    pub middle_size: usize,
    /// Adds the view-direction branch (colour networks).
    pub view_conditioned: bool,
}

/// Largest input or output side of a network (the paper's largest is 1024).
pub const MAX_SIDE: usize = 4096;
/// Largest number of channels per layer or of style dimensions (the paper's: 512).
pub const MAX_CHANNELS: usize = 4096;
/// Largest number of input or output channels of a network.
pub const MAX_IO_CHANNELS: usize = 64;
/// Largest single feature map, bytes.
pub const MAX_ACTIVATION_BYTES: u64 = 4 << 30;

/// Checks `(field, value, limit)` triples: a value above its limit is an error naming the field
/// (sizes from config files are checked before anything is allocated).
pub(crate) fn check_sizes(fields: &[(&'static str, usize, usize)]) -> Result<(), NetsError> {
    for &(field, value, limit) in fields {
        if value > limit {
            return Err(NetsError::config(
                field,
                format!("{value} is larger than the limit {limit}"),
            ));
        }
    }
    Ok(())
}

impl StyleUNetConfig {
    /// The paper's body network: 512 → 1024, cm 2, style 512, n_mlp 2.
    pub fn paper_body(out_channels: usize, view_conditioned: bool) -> Self {
        Self {
            input_size: 512,
            output_size: 1024,
            in_channels: 3,
            out_channels,
            channel_multiplier: 2,
            channel_base: 16384,
            max_channels: 512,
            style_dim: 512,
            n_mlp: 2,
            middle_size: 8,
            view_conditioned,
        }
    }

    /// The paper's face network (its full model, Table 4): 256 → 256, cm 1, style 256, n_mlp 4.
    pub fn paper_face(out_channels: usize, view_conditioned: bool) -> Self {
        Self {
            input_size: 256,
            output_size: 256,
            channel_multiplier: 1,
            style_dim: 256,
            n_mlp: 4,
            ..Self::paper_body(out_channels, view_conditioned)
        }
    }

    /// The CPU body network of the demo: 64 → 128, at most 32 channels (with the learnable
    /// canonical attributes carrying the per-texel detail, wider networks measured no better).
    pub fn cpu_body(out_channels: usize, view_conditioned: bool) -> Self {
        Self {
            input_size: 64,
            output_size: 128,
            in_channels: 3,
            out_channels,
            channel_multiplier: 1,
            channel_base: 1024,
            max_channels: 32,
            style_dim: 64,
            n_mlp: 2,
            middle_size: 8,
            view_conditioned,
        }
    }

    /// The CPU face network of the demo: 32 → 32, at most 64 channels, n_mlp 4.
    pub fn cpu_face(out_channels: usize, view_conditioned: bool) -> Self {
        Self {
            input_size: 32,
            output_size: 32,
            max_channels: 64,
            middle_size: 4,
            n_mlp: 4,
            ..Self::cpu_body(out_channels, view_conditioned)
        }
    }

    /// Channels of the features at resolution `r`.
    pub fn channels(&self, r: usize) -> usize {
        (self.channel_base * self.channel_multiplier / r).clamp(1, self.max_channels)
    }

    /// Checks every field, naming the first bad one.
    pub fn validate(&self) -> Result<(), NetsError> {
        let pow2 = |v: usize| v >= 4 && v.is_power_of_two();
        if !pow2(self.input_size) {
            return Err(NetsError::config(
                "input_size",
                format!("{} is not a power of two ≥ 4", self.input_size),
            ));
        }
        if self.output_size != self.input_size && self.output_size != 2 * self.input_size {
            return Err(NetsError::config(
                "output_size",
                format!(
                    "{} must equal input_size ({}) or twice it",
                    self.output_size, self.input_size
                ),
            ));
        }
        if !pow2(self.middle_size) || self.middle_size > self.output_size / 4 {
            return Err(NetsError::config(
                "middle_size",
                format!(
                    "{} must be a power of two in [4, output_size / 4 = {}]",
                    self.middle_size,
                    self.output_size / 4
                ),
            ));
        }
        if self.middle_size > self.input_size / 4 {
            return Err(NetsError::config(
                "middle_size",
                format!("{} exceeds input_size / 4", self.middle_size),
            ));
        }
        for (field, v) in [
            ("in_channels", self.in_channels),
            ("out_channels", self.out_channels),
            ("channel_multiplier", self.channel_multiplier),
            ("channel_base", self.channel_base),
            ("max_channels", self.max_channels),
            ("style_dim", self.style_dim),
        ] {
            if v == 0 {
                return Err(NetsError::config(field, "must be at least 1"));
            }
        }
        if self.n_mlp > 16 {
            return Err(NetsError::config("n_mlp", "more than 16 layers"));
        }
        check_sizes(&[
            ("input_size", self.input_size, MAX_SIDE),
            ("in_channels", self.in_channels, MAX_IO_CHANNELS),
            ("out_channels", self.out_channels, MAX_IO_CHANNELS),
            ("channel_multiplier", self.channel_multiplier, 64),
            ("channel_base", self.channel_base, 1 << 24),
            ("max_channels", self.max_channels, MAX_CHANNELS),
            ("style_dim", self.style_dim, MAX_CHANNELS),
        ])?;
        // The largest feature map (at the output) must fit: the bound is generous for a
        // 24 GiB machine and far above the paper's 128 MiB.
        let r = self.output_size;
        let bytes = (r * r * self.channels(r)) as u64 * 4;
        if bytes > MAX_ACTIVATION_BYTES {
            return Err(NetsError::config(
                "output_size",
                format!(
                    "a {r}² feature map of {} channels needs {:.1} GiB, more than the {} GiB \
                     a network may use",
                    self.channels(r),
                    bytes as f64 / (1u64 << 30) as f64,
                    MAX_ACTIVATION_BYTES >> 30
                ),
            ));
        }
        Ok(())
    }

    /// Builds the network with weights drawn from `seed`.
    pub fn init(&self, seed: u64, device: &Device) -> Result<DualStyleUNet, NetsError> {
        self.validate()?;
        let mut init = Init::new(seed, device);
        let s = self.input_size;
        let ch = |r| self.channels(r);
        let conv_in = ConvLayer::new(&mut init, [self.in_channels, ch(s / 2)], 3, true, true);
        let mut from_rgb = Vec::new();
        let mut encoder = Vec::new();
        let mut r = s / 2;
        while r > self.middle_size {
            from_rgb.push(FromRgb {
                conv: EqualConv2d::new(&mut init, [self.in_channels, ch(r)], 1, 1, 0, false),
                bias: init.constant([ch(r)], 0.0),
            });
            encoder.push(ConvBlock {
                conv1: ConvLayer::new(&mut init, [ch(r), ch(r)], 3, false, true),
                conv2: ConvLayer::new(&mut init, [ch(r), ch(r / 2)], 3, true, true),
            });
            r /= 2;
        }
        let mut styles = StyleRanges::default();
        let front = Decoder::new(&mut init, self, &mut styles);
        let back = Decoder::new(&mut init, self, &mut styles);
        let view = self.view_conditioned.then(|| {
            let c = ch(s / 2);
            ViewBranch {
                conv1: EqualConv2d::new(&mut init, [1, (c / 2).max(1)], 4, 2, 1, true),
                conv2: EqualConv2d::new(&mut init, [(c / 2).max(1), c], 4, 2, 1, true),
            }
        });
        let style_dim = self.style_dim;
        Ok(DualStyleUNet {
            mapping: Mapping::new(&mut init, style_dim, self.n_mlp, 0.01),
            styles: EqualLinear::new(&mut init, [style_dim, styles.total()], 1.0, 1.0, false),
            conv_in,
            from_rgb,
            encoder,
            front,
            back,
            view,
            config_json: serde_json::to_string(self).expect("serialisable config"),
        })
    }
}

/// Adds the area-downsampled raw input to the encoder features.
#[derive(Module, Debug)]
pub struct FromRgb {
    pub conv: EqualConv2d,
    pub bias: Param<Tensor<1>>,
}

/// Two 3×3 convolutions, the second halving the resolution.
#[derive(Module, Debug)]
pub struct ConvBlock {
    pub conv1: ConvLayer,
    pub conv2: ConvLayer,
}

/// One decoder level.
#[derive(Module, Debug)]
pub struct DecoderBlock {
    pub comb: ConvLayer,
    pub up: StyledConv,
    pub conv: StyledConv,
    pub to_rgb: ToRgb,
}

/// A decoder: levels from the bottleneck to `output_size / 2`.
#[derive(Module, Debug)]
pub struct Decoder {
    pub blocks: Vec<DecoderBlock>,
}

impl Decoder {
    fn new(init: &mut Init, c: &StyleUNetConfig, styles: &mut StyleRanges) -> Self {
        let ch = |r| c.channels(r);
        let mut blocks = Vec::new();
        let mut r = c.middle_size;
        while r <= c.output_size / 4 {
            let comb_in = if r == c.middle_size { ch(r) } else { 2 * ch(r) };
            blocks.push(DecoderBlock {
                comb: ConvLayer::new(init, [comb_in, ch(r)], 3, false, true),
                up: StyledConv::new(init, [ch(r), ch(2 * r)], styles, true, 2 * r),
                conv: StyledConv::new(init, [ch(2 * r), ch(2 * r)], styles, false, 2 * r),
                to_rgb: ToRgb::new(init, ch(2 * r), c.out_channels, styles),
            });
            r *= 2;
        }
        Self { blocks }
    }

    /// Its modulated layers in the order [`Self::forward`] takes their weights.
    fn modulations(&self) -> impl Iterator<Item = Modulation> + '_ {
        self.blocks.iter().flat_map(|block| {
            [&block.up.conv, &block.conv.conv, &block.to_rgb.conv].map(|conv| conv.modulation())
        })
    }

    /// `weights`: the modulated weights of [`Self::modulations`], in order.
    fn forward(
        &self,
        skips: &[Tensor<4>],
        weights: &mut impl Iterator<Item = Tensor<4>>,
        view: Option<Tensor<4>>,
        view_level: usize,
    ) -> Tensor<4> {
        let mut weight = || weights.next().expect("a modulated weight per layer");
        // skips[k] is at resolution middle · 2^(levels − 1 − k)… stored from large to small.
        let mut x = skips.last().expect("at least one skip").clone();
        let mut rgb = None;
        let mut view = view;
        for (level, block) in self.blocks.iter().enumerate() {
            if level > 0 {
                let skip = skips[skips.len() - 1 - level].clone();
                x = cat_channels(x, skip);
            }
            x = block.comb.forward(x);
            x = block.up.forward(x, weight());
            x = block.conv.forward(x, weight());
            if level == view_level
                && let Some(v) = view.take()
            {
                x = x + v;
            }
            rgb = Some(block.to_rgb.forward(x.clone(), weight(), rgb));
        }
        inverse_haar(rgb.expect("at least one decoder block"))
    }
}

/// The view-direction branch: `n · v` map → two stride-2 4×4 convolutions.
#[derive(Module, Debug)]
pub struct ViewBranch {
    pub conv1: EqualConv2d,
    pub conv2: EqualConv2d,
}

/// The DualStyleUNet.
#[derive(Module, Debug)]
pub struct DualStyleUNet {
    pub mapping: Mapping,
    /// Every modulated layer's style from the mapping's output, one linear layer for all
    /// (each layer reads its range, [`StyleRanges`]): StyleGAN2's per-layer affine maps
    /// stacked, so that a GPU makes them in one launch each way instead of one per layer.
    pub styles: EqualLinear,
    pub conv_in: ConvLayer,
    pub from_rgb: Vec<FromRgb>,
    pub encoder: Vec<ConvBlock>,
    pub front: Decoder,
    pub back: Decoder,
    pub view: Option<ViewBranch>,
    /// The configuration it was built from, so checkpoints can be checked against it.
    config_json: String,
}

/// Front and back outputs, each `[B, out_channels, O, O]`.
#[derive(Clone, Debug)]
pub struct DualOutput {
    pub front: Tensor<4>,
    pub back: Tensor<4>,
}

impl DualStyleUNet {
    /// The configuration the network was built with.
    pub fn config(&self) -> StyleUNetConfig {
        serde_json::from_str(&self.config_json).expect("written by init")
    }

    /// The constant style through the mapping network ([`Mapping::constant_style`]) and every
    /// layer's affine map: `[total]` ([`StyleRanges`]).
    fn style_vector(&self, device: &Device) -> Tensor<1> {
        let dim = self.styles.weight.dims()[1];
        let styles = self
            .styles
            .forward(self.mapping.constant_style(dim, device));
        let total = styles.dims()[1];
        styles.reshape([total])
    }

    /// Runs the network. `input`: `[B, in, S, S]`; `view`: `(front, back)` maps of `n · v`,
    /// each `[B, 1, S, S]`, required exactly when the network is view-conditioned.
    pub fn forward(
        &self,
        input: Tensor<4>,
        view: Option<(Tensor<4>, Tensor<4>)>,
    ) -> Result<DualOutput, NetsError> {
        let c = self.config();
        let [b, cin, h, w] = input.dims();
        if [cin, h, w] != [c.in_channels, c.input_size, c.input_size] {
            return Err(NetsError::Input(format!(
                "StyleUNet input is [{b}, {cin}, {h}, {w}], expected [B, {}, {}, {}]",
                c.in_channels, c.input_size, c.input_size
            )));
        }
        if view.is_some() != self.view.is_some() {
            return Err(NetsError::Input(if self.view.is_some() {
                "this StyleUNet is view-conditioned: give the n·v maps".into()
            } else {
                "this StyleUNet takes no view maps".into()
            }));
        }
        let device = input.device();
        let layers = self.front.modulations().chain(self.back.modulations());
        let mut weights = modulate_all(layers.collect(), self.style_vector(&device)).into_iter();
        let input = channels_last(input);
        let mut skips = Vec::new();
        let mut x = self.conv_in.forward(input.clone());
        // The input at each encoder level's size, each level the 2 × 2 mean of the one above.
        let mut small = input.clone();
        for (rgb, block) in self.from_rgb.iter().zip(&self.encoder) {
            small = downsample2(small);
            x = x + rgb.conv.forward_activated(
                small.clone(),
                rgb.bias.val(),
                LRELU_SLOPE,
                LRELU_GAIN,
            );
            skips.push(x.clone());
            x = block.conv1.forward(x);
            x = block.conv2.forward(x);
        }
        skips.push(x);
        // The decoder level whose output is at S/2.
        let view_level = (c.input_size / 2 / c.middle_size).trailing_zeros() as usize - 1;
        let (vf, vb) = match (&self.view, view) {
            (Some(branch), Some((f, bk))) => {
                let feat = |m: Tensor<4>| -> Result<Tensor<4>, NetsError> {
                    let [mb, mc, mh, mw] = m.dims();
                    if [mb, mc, mh, mw] != [b, 1, c.input_size, c.input_size] {
                        return Err(NetsError::Input(format!(
                            "view map is [{mb}, {mc}, {mh}, {mw}], expected [{b}, 1, {}, {}]",
                            c.input_size, c.input_size
                        )));
                    }
                    let y = branch.conv1.forward_leaky_relu(m, LRELU_SLOPE);
                    let y = branch.conv2.forward(y);
                    Ok(resize(y, c.input_size / 2, c.input_size / 2))
                };
                (Some(feat(f)?), Some(feat(bk)?))
            }
            _ => (None, None),
        };
        Ok(DualOutput {
            front: self.front.forward(&skips, &mut weights, vf, view_level),
            back: self.back.forward(&skips, &mut weights, vb, view_level),
        })
    }
}
