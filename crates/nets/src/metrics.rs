//! Image metrics as the field reports them, and their differentiable losses.
//!
//! - **SSIM** as the paper's evaluation computes it (Animatable Gaussians' `eval/score.py`:
//!   scikit-image's `structural_similarity(..., channel_axis=-1, data_range=1)` with its
//!   defaults): a 7×7 uniform window, sample covariances (`49/48` normalisation),
//!   `C1 = 0.01²`, `C2 = 0.03²`, the map averaged over the pixels at least 3 from the border,
//!   then over channels ([`ssim_skimage`]).
//! - **SSIM** as 3DGS computes it (the training-side convention): an 11-tap Gaussian window
//!   (σ = 1.5) applied separably with zero padding, same constants, the map averaged over all
//!   pixels and channels ([`ssim`], [`ssim_images`]). scikit-image gives the same number on
//!   images zero-padded by 5 pixels with `gaussian_weights=True, use_sample_covariance=False,
//!   data_range=1`.
//! - **PSNR** `= 20 · log10(1 / √MSE)` over all pixels and channels.
//! - **D-SSIM** loss `1 − SSIM`; **L1**.
//!
//! Tensors are `[B, C, H, W]` in `[0, 1]`; host images are [`f3g_io::Image`] `[H, W, C]`.

use burn::tensor::ops::ConvOptions;
use burn::tensor::{Device, Tensor, TensorData};

use crate::NetsError;
use crate::conv::conv2d;
use f3g_io::Image;

const WINDOW: usize = 11;
const SIGMA: f64 = 1.5;
const C1: f32 = 0.01 * 0.01;
const C2: f32 = 0.03 * 0.03;

fn gaussian_taps() -> Vec<f32> {
    let half = (WINDOW / 2) as f64;
    let g: Vec<f64> = (0..WINDOW)
        .map(|i| (-(i as f64 - half).powi(2) / (2.0 * SIGMA * SIGMA)).exp())
        .collect();
    let s: f64 = g.iter().sum();
    g.iter().map(|v| (v / s) as f32).collect()
}

/// Separable Gaussian filtering of every channel with zero padding.
fn filter(x: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let device = x.device();
    let taps = gaussian_taps();
    let horizontal =
        Tensor::<4>::from_data(TensorData::new(taps.clone(), [1, 1, 1, WINDOW]), &device);
    let vertical = Tensor::<4>::from_data(TensorData::new(taps, [1, 1, WINDOW, 1]), &device);
    let p = WINDOW / 2;
    let x = x.reshape([b * c, 1, h, w]);
    let x = conv2d(
        x,
        horizontal,
        None,
        ConvOptions::new([1, 1], [0, p], [1, 1], 1),
    );
    let x = conv2d(
        x,
        vertical,
        None,
        ConvOptions::new([1, 1], [p, 0], [1, 1], 1),
    );
    x.reshape([b, c, h, w])
}

/// SSIM of each image pair: `[B]`.
pub fn ssim(a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
    let [batch, c, h, w] = a.dims();
    let mu1 = filter(a.clone());
    let mu2 = filter(b.clone());
    let mu1_sq = mu1.clone().powf_scalar(2.0);
    let mu2_sq = mu2.clone().powf_scalar(2.0);
    let mu12 = mu1 * mu2;
    let s1 = filter(a.clone().powf_scalar(2.0)) - mu1_sq.clone();
    let s2 = filter(b.clone().powf_scalar(2.0)) - mu2_sq.clone();
    let s12 = filter(a * b) - mu12.clone();
    let map = ((mu12 * 2.0 + C1) * (s12 * 2.0 + C2)) / ((mu1_sq + mu2_sq + C1) * (s1 + s2 + C2));
    map.reshape([batch, c * h * w]).mean_dim(1).reshape([batch])
}

/// The D-SSIM loss `1 − SSIM`, averaged over the batch.
pub fn dssim_loss(a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
    (ssim(a, b) * -1.0 + 1.0).mean()
}

/// Mean absolute error.
pub fn l1_loss(a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
    (a - b).abs().mean()
}

/// PSNR of two host images of the same shape (values in `[0, 1]`); `+∞` when identical.
pub fn psnr(a: &Image, b: &Image) -> Result<f64, NetsError> {
    same_shape(a, b)?;
    let mse = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>()
        / a.data.len() as f64;
    Ok(20.0 * (1.0 / mse.sqrt()).log10())
}

/// SSIM of two host images of the same shape.
pub fn ssim_images(a: &Image, b: &Image) -> Result<f64, NetsError> {
    same_shape(a, b)?;
    let device = Device::flex();
    let value = ssim(image_tensor(a, &device), image_tensor(b, &device));
    Ok(value.into_data().try_into_vec::<f32>().expect("f32")[0] as f64)
}

/// Side of scikit-image's default SSIM window.
const SKIMAGE_WINDOW: usize = 7;

/// SSIM of two host images exactly as scikit-image's `structural_similarity(a, b,
/// channel_axis=-1, data_range=1)` computes it (in `f64`; see the module docs). Images need at
/// least 7 pixels per side.
pub fn ssim_skimage(a: &Image, b: &Image) -> Result<f64, NetsError> {
    same_shape(a, b)?;
    let (w, h, c) = (a.width, a.height, a.channels);
    let k = SKIMAGE_WINDOW;
    if w < k || h < k {
        return Err(NetsError::Input(format!(
            "SSIM needs images of at least {k}×{k} pixels, got {w}×{h}"
        )));
    }
    let np = (k * k) as f64;
    let cov_norm = np / (np - 1.0);
    let (c1, c2) = (0.01f64 * 0.01, 0.03f64 * 0.03);
    // Window sums from summed-area tables of x, y, x², y², xy.
    let table = |f: &dyn Fn(f64, f64) -> f64, ch: usize| {
        let mut t = vec![0.0f64; (w + 1) * (h + 1)];
        for y in 0..h {
            let mut row = 0.0;
            for x in 0..w {
                let p = (y * w + x) * c + ch;
                row += f(a.data[p] as f64, b.data[p] as f64);
                t[(y + 1) * (w + 1) + x + 1] = t[y * (w + 1) + x + 1] + row;
            }
        }
        t
    };
    let window = |t: &[f64], x: usize, y: usize| {
        let at = |xx: usize, yy: usize| t[yy * (w + 1) + xx];
        (at(x + k, y + k) - at(x, y + k) - at(x + k, y) + at(x, y)) / np
    };
    let mut total = 0.0;
    for ch in 0..c {
        let sx = table(&|x, _| x, ch);
        let sy = table(&|_, y| y, ch);
        let sxx = table(&|x, _| x * x, ch);
        let syy = table(&|_, y| y * y, ch);
        let sxy = table(&|x, y| x * y, ch);
        let mut sum = 0.0;
        for y in 0..=h - k {
            for x in 0..=w - k {
                let (ux, uy) = (window(&sx, x, y), window(&sy, x, y));
                let vx = cov_norm * (window(&sxx, x, y) - ux * ux);
                let vy = cov_norm * (window(&syy, x, y) - uy * uy);
                let vxy = cov_norm * (window(&sxy, x, y) - ux * uy);
                sum += ((2.0 * ux * uy + c1) * (2.0 * vxy + c2))
                    / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
            }
        }
        total += sum / ((w - k + 1) * (h - k + 1)) as f64;
    }
    Ok(total / c as f64)
}

/// A host image `[H, W, C]` as a `[1, C, H, W]` tensor.
pub fn image_tensor(img: &Image, device: &Device) -> Tensor<4> {
    into_image_tensor(img.clone(), device)
}

/// [`image_tensor`] of an image the caller gives up: its pixels become the tensor's data
/// without a copy. A full-resolution training view is 38 MB (1536 × 2048 RGB); a copy that
/// size is a fresh mapping that the kernel zeroes page by page, for every sample (13 % of the
/// CPU samples of an offline `paper` bench's last fifth on 2 cores, BENCHMARKS.md).
pub fn into_image_tensor(img: Image, device: &Device) -> Tensor<4> {
    let shape = [img.height, img.width, img.channels];
    Tensor::<3>::from_data(TensorData::new(img.data, shape), device)
        .permute([2, 0, 1])
        .unsqueeze()
}

fn same_shape(a: &Image, b: &Image) -> Result<(), NetsError> {
    if (a.width, a.height, a.channels) != (b.width, b.height, b.channels) {
        return Err(NetsError::Input(format!(
            "images differ in size: {}×{}×{} and {}×{}×{}",
            a.width, a.height, a.channels, b.width, b.height, b.channels
        )));
    }
    if a.data.iter().chain(&b.data).any(|v| !v.is_finite()) {
        return Err(NetsError::Input("an image has non-finite values".into()));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_images_score_perfectly() {
        let img =
            Image::from_vec(20, 16, 3, (0..960).map(|i| (i % 7) as f32 / 7.0).collect()).unwrap();
        assert!(psnr(&img, &img).unwrap().is_infinite());
        assert!((ssim_images(&img, &img).unwrap() - 1.0).abs() < 1e-5);
    }

    #[test]
    fn psnr_of_a_constant_offset() {
        let a = Image::filled(8, 8, 3, 0.5);
        let b = Image::filled(8, 8, 3, 0.6);
        assert!((psnr(&a, &b).unwrap() - 20.0).abs() < 1e-4);
        assert!(psnr(&a, &Image::filled(8, 9, 3, 0.5)).is_err());
    }
}
