//! Bilinear resizing of `[B, C, H, W]` tensors (`align_corners = false`, no antialiasing:
//! PyTorch's and Burn's semantics) to any size, differentiable on every backend.

use burn::backend::Dispatch;
use burn::tensor::{Device, Tensor, TensorData};

use crate::fused::{self, FusedBackend, downsample2, upsample2};

/// Bilinear resize (`align_corners = false`); doubling goes through [`upsample2`] and halving
/// even sizes through [`downsample2`] (there bilinear samples midway between two pixels: the
/// 2 × 2 mean), other sizes through one op where it [`fused::runs`] (Burn's `interpolate` on
/// the CPU; on other devices one kernel each way, since Burn 0.22's CubeCL backends have no
/// backward for bilinear interpolation) and [`resize_separable`] elsewhere. An empty input or
/// output gives zeros.
pub fn resize(x: Tensor<4>, height: usize, width: usize) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    if [height, width] == [2 * h, 2 * w] {
        return upsample2(x);
    }
    if h % 2 == 0 && w % 2 == 0 && [height, width] == [h / 2, w / 2] {
        return downsample2(x);
    }
    if h * w == 0 || height * width == 0 {
        return Tensor::zeros([b, c, height, width], &x.device());
    }
    if fused::runs(&x, b * c * height * width) {
        return Tensor::from_dispatch(<Dispatch as FusedBackend>::resize(
            x.into_dispatch(),
            height,
            width,
        ));
    }
    resize_separable(x, height, width)
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

#[cfg(test)]
mod tests {
    use burn::tensor::module::interpolate;
    use burn::tensor::ops::{InterpolateMode, InterpolateOptions};

    use super::*;
    use crate::fused::portable;

    fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().try_into_vec::<f32>().unwrap()
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
            let (theirs, theirs_grad) = run(&|x| {
                let mut options = InterpolateOptions::new(InterpolateMode::Bilinear);
                options.align_corners = false;
                options.output_size = Some([to_h, to_w]);
                interpolate(x, options)
            });
            // The portable path, and `resize`'s op with its graph node.
            for (ours, ours_grad) in [
                run(&|x| resize_separable(x, to_h, to_w)),
                run(&|x| resize(x, to_h, to_w)),
            ] {
                assert_eq!(ours.len(), theirs.len());
                assert_eq!(ours_grad.len(), theirs_grad.len());
                for (a, b) in ours
                    .iter()
                    .zip(&theirs)
                    .chain(ours_grad.iter().zip(&theirs_grad))
                {
                    assert!((a - b).abs() < 1e-5, "{h}×{w} → {to_h}×{to_w}: {a} vs {b}");
                }
            }
        }
    }
}
