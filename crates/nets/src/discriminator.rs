//! The StyleGAN2 residual discriminator, its non-saturating losses and R1 regularisation.
//!
//! ```text
//! image [B, 3, R, R] → ConvLayer 1×1 → ResBlock ↓ … → 4×4 → minibatch stddev (+1 channel)
//!   → ConvLayer 3×3 → flatten → EqualLinear (lrelu) → EqualLinear → score [B, 1]
//! ```
//!
//! Channels per resolution follow [`StyleUNetConfig::channels`](crate::StyleUNetConfig).
//!
//! **R1 without double back-propagation.** R1 is `γ/2 · E‖∇ₓD(x)‖²` on real images; its gradient
//! with respect to D's weights needs a second derivative, which Burn's autodiff does not provide.
//! [`r1_penalty`] uses the unbiased directional estimate `‖g‖² = E_u[(g·u)²]` for
//! `u ~ N(0, I)` with the directional derivative taken by a central finite difference,
//! `g·u ≈ (D(x + εu) − D(x − εu)) / 2ε`, which first-order autodiff differentiates exactly.

use burn::module::Module;
use burn::tensor::activation::softplus;
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use crate::NetsError;
use crate::init::Init;
use crate::layers::{ConvLayer, EqualLinear};

/// Architecture of a [`Discriminator`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiscriminatorConfig {
    /// Side of the input images (a power of two ≥ 8).
    pub resolution: usize,
    pub channel_multiplier: usize,
    pub channel_base: usize,
    pub max_channels: usize,
    /// Group size of the minibatch standard deviation.
    pub stddev_group: usize,
}

impl DiscriminatorConfig {
    /// StyleGAN2's discriminator at `resolution` (base 16384, max 512 channels, cm 2).
    pub fn paper(resolution: usize) -> Self {
        Self {
            resolution,
            channel_multiplier: 2,
            channel_base: 16384,
            max_channels: 512,
            stddev_group: 4,
        }
    }

    /// A small discriminator for the CPU preset (at most 64 channels).
    pub fn cpu(resolution: usize) -> Self {
        Self {
            resolution,
            channel_multiplier: 1,
            channel_base: 1024,
            max_channels: 64,
            stddev_group: 4,
        }
    }

    pub fn channels(&self, r: usize) -> usize {
        (self.channel_base * self.channel_multiplier / r).clamp(1, self.max_channels)
    }

    pub fn validate(&self) -> Result<(), NetsError> {
        if self.resolution < 8 || !self.resolution.is_power_of_two() {
            return Err(NetsError::config(
                "resolution",
                format!("{} is not a power of two ≥ 8", self.resolution),
            ));
        }
        for (field, v) in [
            ("channel_multiplier", self.channel_multiplier),
            ("channel_base", self.channel_base),
            ("max_channels", self.max_channels),
            ("stddev_group", self.stddev_group),
        ] {
            if v == 0 {
                return Err(NetsError::config(field, "must be at least 1"));
            }
        }
        use crate::styleunet::{MAX_CHANNELS, MAX_SIDE, check_sizes};
        check_sizes(&[
            ("resolution", self.resolution, MAX_SIDE),
            ("channel_multiplier", self.channel_multiplier, 64),
            ("channel_base", self.channel_base, 1 << 24),
            ("max_channels", self.max_channels, MAX_CHANNELS),
            ("stddev_group", self.stddev_group, 64),
        ])?;
        Ok(())
    }

    pub fn init(&self, seed: u64, device: &Device) -> Result<Discriminator, NetsError> {
        self.validate()?;
        let mut init = Init::new(seed, device);
        let ch = |r| self.channels(r);
        let mut blocks = Vec::new();
        let mut r = self.resolution;
        while r > 4 {
            blocks.push(ResBlock {
                conv1: ConvLayer::new(&mut init, [ch(r), ch(r)], 3, false, true),
                conv2: ConvLayer::new(&mut init, [ch(r), ch(r / 2)], 3, true, true),
                skip: ConvLayer::new(&mut init, [ch(r), ch(r / 2)], 1, true, false),
            });
            r /= 2;
        }
        Ok(Discriminator {
            from_rgb: ConvLayer::new(&mut init, [3, ch(self.resolution)], 1, false, true),
            blocks,
            final_conv: ConvLayer::new(&mut init, [ch(4) + 1, ch(4)], 3, false, true),
            final_linear: EqualLinear::new(&mut init, [ch(4) * 16, ch(4)], 0.0, 1.0, true),
            score: EqualLinear::new(&mut init, [ch(4), 1], 0.0, 1.0, false),
            resolution: self.resolution,
            stddev_group: self.stddev_group,
        })
    }
}

/// A residual down-sampling block: `(conv2(conv1(x)) + skip(x)) / √2`.
#[derive(Module, Debug)]
pub struct ResBlock {
    pub conv1: ConvLayer,
    pub conv2: ConvLayer,
    pub skip: ConvLayer,
}

/// The discriminator.
#[derive(Module, Debug)]
pub struct Discriminator {
    pub from_rgb: ConvLayer,
    pub blocks: Vec<ResBlock>,
    pub final_conv: ConvLayer,
    pub final_linear: EqualLinear,
    pub score: EqualLinear,
    resolution: usize,
    stddev_group: usize,
}

impl Discriminator {
    /// Side of the images it scores.
    pub fn resolution(&self) -> usize {
        self.resolution
    }

    /// Scores images `[B, 3, R, R]` in `[0, 1]` (mapped to `[-1, 1]` inside): `[B, 1]` logits.
    pub fn forward(&self, images: Tensor<4>) -> Result<Tensor<2>, NetsError> {
        let [b, c, h, w] = images.dims();
        if [c, h, w] != [3, self.resolution, self.resolution] {
            return Err(NetsError::Input(format!(
                "discriminator input is [{b}, {c}, {h}, {w}], expected [B, 3, {r}, {r}]",
                r = self.resolution
            )));
        }
        let mut x = self.from_rgb.forward(images * 2.0 - 1.0);
        for block in &self.blocks {
            let y = block.conv2.forward(block.conv1.forward(x.clone()));
            x = (y + block.skip.forward(x)) / std::f32::consts::SQRT_2;
        }
        let x = self
            .final_conv
            .forward(minibatch_stddev(x, self.stddev_group));
        let [b, c, h, w] = x.dims();
        let x = self.final_linear.forward(x.reshape([b, c * h * w]));
        Ok(self.score.forward(x))
    }
}

/// Appends the mean standard deviation over groups of the batch as one feature map.
fn minibatch_stddev(x: Tensor<4>, group: usize) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let g = group.min(b);
    let g = (1..=g).rev().find(|g| b % g == 0).unwrap_or(1);
    let y = x.clone().reshape([g, b / g, c, h, w]);
    let centred = y.clone() - y.mean_dim(0);
    let std = (centred.powf_scalar(2.0).mean_dim(0) + 1e-8).sqrt(); // [1, b/g, c, h, w]
    let feature = std
        .reshape([b / g, c * h * w])
        .mean_dim(1)
        .reshape([1, b / g, 1, 1]);
    // Sample i belongs to group column i mod (b/g).
    let per_sample = Tensor::cat(vec![feature; g], 0).reshape([b, 1, 1, 1]);
    let map = per_sample * Tensor::<4>::ones([b, 1, h, w], &x.device());
    Tensor::cat(vec![x, map], 1)
}

/// Generator loss `softplus(−D(fake))`, averaged.
pub fn generator_loss(fake_scores: Tensor<2>) -> Tensor<1> {
    softplus(-fake_scores, 1.0).mean()
}

/// Discriminator loss `softplus(D(fake)) + softplus(−D(real))`, averaged.
pub fn discriminator_loss(real_scores: Tensor<2>, fake_scores: Tensor<2>) -> Tensor<1> {
    softplus(fake_scores, 1.0).mean() + softplus(-real_scores, 1.0).mean()
}

/// The R1 penalty `γ/2 · ‖∇ₓD(x)‖²` on real images, estimated with `samples` random
/// directions and central differences of step `epsilon` (module docs); differentiable in the
/// discriminator's weights. `seed` picks the directions.
pub fn r1_penalty(
    d: &Discriminator,
    real: Tensor<4>,
    gamma: f32,
    samples: usize,
    epsilon: f32,
    seed: u64,
) -> Result<Tensor<1>, NetsError> {
    let dims = real.dims();
    let device = real.device();
    let mut init = Init::new(seed, &device);
    let mut total: Option<Tensor<1>> = None;
    for _ in 0..samples.max(1) {
        let u = Tensor::<4>::from_data(
            TensorData::new(init.normal_values(dims.iter().product(), 1.0), dims),
            &device,
        );
        let plus = d.forward(real.clone() + u.clone() * epsilon)?;
        let minus = d.forward(real.clone() - u * epsilon)?;
        let directional = (plus - minus) / (2.0 * epsilon);
        let term = directional.powf_scalar(2.0).mean();
        total = Some(match total {
            Some(t) => t + term,
            None => term,
        });
    }
    Ok(total.expect("at least one sample") * (gamma / 2.0 / samples.max(1) as f32))
}
