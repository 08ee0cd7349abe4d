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
use burn::tensor::{Device, Tensor};
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
        self.forward_parts(images, 1)
    }

    /// Scores `parts` batches stacked along the batch axis (`B` divisible by `parts`) in one
    /// pass, each part's minibatch standard deviation its own: the scores a forward per part
    /// gives, in one set of launches on a GPU instead of one per part (each layer is a launch
    /// or more whatever the batch).
    pub fn forward_parts(&self, images: Tensor<4>, parts: usize) -> Result<Tensor<2>, NetsError> {
        let [b, c, h, w] = images.dims();
        if [c, h, w] != [3, self.resolution, self.resolution] {
            return Err(NetsError::Input(format!(
                "discriminator input is [{b}, {c}, {h}, {w}], expected [B, 3, {r}, {r}]",
                r = self.resolution
            )));
        }
        if parts == 0 || !b.is_multiple_of(parts) {
            return Err(NetsError::Input(format!(
                "a discriminator batch of {b} cannot be split into {parts} equal parts"
            )));
        }
        let mut x = self.from_rgb.forward(images * 2.0 - 1.0);
        for block in &self.blocks {
            let y = block.conv2.forward(block.conv1.forward(x.clone()));
            x = (y + block.skip.forward(x)) / std::f32::consts::SQRT_2;
        }
        let x = self
            .final_conv
            .forward(minibatch_stddev(x, self.stddev_group, parts));
        let [b, c, h, w] = x.dims();
        let x = self.final_linear.forward(x.reshape([b, c * h * w]));
        Ok(self.score.forward(x))
    }
}

/// Appends the mean standard deviation over groups of each of the batch's `parts` (stacked
/// along the batch axis) as one feature map.
fn minibatch_stddev(x: Tensor<4>, group: usize, parts: usize) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let per_part = b / parts;
    let g = group.min(per_part);
    let g = (1..=g)
        .rev()
        .find(|g| per_part.is_multiple_of(*g))
        .unwrap_or(1);
    let columns = per_part / g;
    let y = x.clone().reshape([parts, g, columns, c * h * w]);
    let centred = y.clone() - y.mean_dim(1);
    let std = (centred.powf_scalar(2.0).mean_dim(1) + 1e-8).sqrt(); // [parts, 1, columns, chw]
    // Sample `(j, k)` of a part (group row j, column k) gets its column's mean.
    let per_sample = std.mean_dim(3).repeat_dim(1, g).reshape([b, 1, 1, 1]);
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
    let mut init = Init::new(seed, &real.device());
    let mut total: Option<Tensor<1>> = None;
    for _ in 0..samples.max(1) {
        let u = r1_direction(&mut init, &real);
        let plus = d.forward(real.clone() + u.clone() * epsilon)?;
        let minus = d.forward(real.clone() - u * epsilon)?;
        let term = r1_term(plus, minus, epsilon);
        total = Some(match total {
            Some(t) => t + term,
            None => term,
        });
    }
    Ok(total.expect("at least one sample") * (gamma / 2.0 / samples.max(1) as f32))
}

/// A direction `u ~ N(0, I)` the shape of `real`.
fn r1_direction(init: &mut Init, real: &Tensor<4>) -> Tensor<4> {
    let dims = real.dims();
    let values = init.normal_values(dims.iter().product(), 1.0);
    init.tensor(values, dims)
}

/// `mean(((D(x + εu) − D(x − εu)) / 2ε)²)`: one direction's estimate of `‖∇ₓD(x)‖²`.
fn r1_term(plus: Tensor<2>, minus: Tensor<2>, epsilon: f32) -> Tensor<1> {
    ((plus - minus) / (2.0 * epsilon)).powf_scalar(2.0).mean()
}

/// [`r1_penalty`]'s settings for [`discriminator_step_loss`] (one direction).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct R1 {
    /// `γ` (times the lazy regularisation's interval, where the caller applies it every few
    /// steps).
    pub gamma: f32,
    pub epsilon: f32,
    pub seed: u64,
}

/// The discriminator's step loss: [`discriminator_loss`] on `real` and `fake` (`[B, 3, R,
/// R]` each) and, with `r1`, [`r1_penalty`] on `real` with one direction — every image scored
/// in one forward ([`Discriminator::forward_parts`]: two parts, four with R1), where a forward
/// per part was two to four times the discriminator's launches on a GPU.
pub fn discriminator_step_loss(
    d: &Discriminator,
    real: Tensor<4>,
    fake: Tensor<4>,
    r1: Option<R1>,
) -> Result<Tensor<1>, NetsError> {
    let b = real.dims()[0];
    if fake.dims() != real.dims() {
        return Err(NetsError::Input(format!(
            "real images {:?} and fake images {:?} differ in shape",
            real.dims(),
            fake.dims()
        )));
    }
    let mut images = vec![real.clone(), fake];
    if let Some(r1) = r1 {
        let u = r1_direction(&mut Init::new(r1.seed, &real.device()), &real);
        images.push(real.clone() + u.clone() * r1.epsilon);
        images.push(real - u * r1.epsilon);
    }
    let parts = images.len();
    let scores = d.forward_parts(Tensor::cat(images, 0), parts)?;
    let part = |k: usize| scores.clone().narrow(0, k * b, b);
    let loss = discriminator_loss(part(0), part(1));
    Ok(match r1 {
        Some(r1) => loss + r1_term(part(2), part(3), r1.epsilon) * (r1.gamma / 2.0),
        None => loss,
    })
}
