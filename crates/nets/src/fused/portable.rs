//! The fused ops written with Burn's tensor ops, differentiable on every backend: what `Cube`
//! devices run for tensors of 2³² values or more, and the reference the fused ops are tested
//! against. Each function has the semantics of its namesake in [`crate::fused`].

use burn::tensor::Tensor;
use burn::tensor::activation::{leaky_relu, relu};
use burn::tensor::module::avg_pool2d;
use burn::tensor::ops::AvgPoolOptions;

use super::{DEMODULATION_EPSILON, LPIPS_EPSILON, LinearScales};

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

/// [`bias_leaky_relu`] after StyleGAN2's noise injection: `x + noise · strength` (`noise`
/// `[1, 1, H, W]`, `strength` `[1]`).
pub fn noisy_bias_leaky_relu(
    x: Tensor<4>,
    noise: Tensor<4>,
    strength: Tensor<1>,
    bias: Tensor<1>,
    slope: f64,
    gain: f32,
) -> Tensor<4> {
    bias_leaky_relu(
        x + noise * strength.reshape([1, 1, 1, 1]),
        bias,
        slope,
        gain,
    )
}

/// A linear layer with scaled weight and bias and an optional leaky ReLU (slope 0: Burn's
/// `relu`, as [`bias_leaky_relu`]).
pub fn scaled_linear(
    x: Tensor<2>,
    weight: Tensor<2>,
    bias: Tensor<1>,
    scales: LinearScales,
) -> Tensor<2> {
    let outputs = bias.dims()[0];
    let y = x.matmul((weight * scales.weight_scale).transpose())
        + (bias * scales.bias_scale).reshape([1, outputs]);
    let LinearScales { slope, gain, .. } = scales;
    if slope == 1.0 && gain == 1.0 {
        y
    } else if slope == 0.0 {
        relu(y) * gain
    } else {
        leaky_relu(y, f64::from(slope)) * gain
    }
}

/// StyleGAN2's modulated weight: `weight · styles[first + i] · scale`, then with `demodulate`
/// each output channel divided by `√(Σ w² + 10⁻⁸)`.
pub fn modulate(
    weight: Tensor<4>,
    styles: Tensor<1>,
    first: usize,
    scale: f32,
    demodulate: bool,
) -> Tensor<4> {
    let [c_out, c_in, _, _] = weight.dims();
    let style = styles.narrow(0, first, c_in);
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

/// LPIPS's comparison of one tap ([`crate::fused::lpips_distance`]): each feature map divided
/// by its norm over channels plus 10⁻¹⁰, the squared difference weighted per channel by the
/// head and summed over channels, the mean over pixels. `[B]`.
pub fn lpips_distance(x: Tensor<4>, y: Tensor<4>, weight: Tensor<1>) -> Tensor<1> {
    let [batch, channels, h, w] = x.dims();
    let unit = |f: Tensor<4>| {
        let norm = f.clone().powf_scalar(2.0).sum_dim(1).sqrt() + LPIPS_EPSILON;
        f / norm
    };
    let weighted = (unit(x) - unit(y)).powf_scalar(2.0) * weight.reshape([1, channels, 1, 1]);
    weighted
        .sum_dim(1)
        .reshape([batch, h * w])
        .mean_dim(1)
        .reshape([batch])
}

/// `x + bias + haar(upsample2(inverse_haar(skip)))` ([`crate::fused::to_rgb_output`]).
pub fn to_rgb_output(x: Tensor<4>, bias: Tensor<1>, skip: Tensor<4>) -> Tensor<4> {
    let channels = bias.dims()[0];
    x + bias.reshape([1, channels, 1, 1]) + haar(upsample2(inverse_haar(skip)))
}
