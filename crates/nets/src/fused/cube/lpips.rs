//! LPIPS's comparison of one tap: a thread per pixel walks the channels — the norms of both
//! feature maps, then the weighted squared difference (forward) or the gradient's channel sum
//! and then each channel's gradient (backward) — so each map is read once a pass and nothing
//! `[B, C, H, W]`-sized is written but the gradient. The forward's per-pixel terms are averaged
//! per batch item by Burn's reduction (one launch more). Each map in either of
//! `crate::cube_layout`'s layouts; the gradient is written in `x`'s. The arithmetic follows
//! `fused::flex` term by term.

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::Shape;
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::into_contiguous;

use super::{dims, u32_of};
use crate::cube_grid::one_thread_per_value;
use crate::cube_layout::{empty_in_layout, readable};
use crate::fused::LPIPS_EPSILON;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use crate::fused::cube::position::offset;

    /// One pixel's feature norms over channels.
    #[derive(CubeType)]
    struct Norms {
        /// `1 / (‖x‖ + ε)`.
        inv_x: f32,
        /// `1 / (‖y‖ + ε)`.
        inv_y: f32,
        /// `‖x‖`.
        norm_x: f32,
    }

    /// The norms over the channels at pixel `p` of batch item `b`.
    #[allow(clippy::too_many_arguments)]
    #[cube]
    fn norms(
        x: &Tensor<f32>,
        y: &Tensor<f32>,
        b: u32,
        p: u32,
        channels: u32,
        plane: u32,
        epsilon: f32,
        #[comptime] x_last: bool,
        #[comptime] y_last: bool,
    ) -> Norms {
        let mut sx = 0.0f32;
        let mut sy = 0.0f32;
        for c in 0..channels {
            let xv = x[offset(b, c, 0, p, channels, 1, plane, x_last)];
            let yv = y[offset(b, c, 0, p, channels, 1, plane, y_last)];
            sx += xv * xv;
            sy += yv * yv;
        }
        let norm_x = f32::sqrt(sx);
        Norms {
            inv_x: 1.0f32 / (norm_x + epsilon),
            inv_y: 1.0f32 / (f32::sqrt(sy) + epsilon),
            norm_x,
        }
    }

    /// `out[b · plane + p] = Σ_c weight[c] · (x_c / (‖x‖ + ε) − y_c / (‖y‖ + ε))²`, one thread per
    /// pixel `(b, p)`.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn lpips_pixels(
        x: &Tensor<f32>,
        y: &Tensor<f32>,
        weight: &Tensor<f32>,
        out: &mut Tensor<f32>,
        channels: u32,
        plane: u32,
        epsilon: f32,
        #[comptime] x_last: bool,
        #[comptime] y_last: bool,
    ) {
        let q = ABSOLUTE_POS;
        if q >= out.len() {
            terminate!();
        }
        let (b, p) = (q as u32 / plane, q as u32 % plane);
        let n = norms(x, y, b, p, channels, plane, epsilon, x_last, y_last);
        let mut d = 0.0f32;
        for c in 0..channels {
            let xv = x[offset(b, c, 0, p, channels, 1, plane, x_last)];
            let yv = y[offset(b, c, 0, p, channels, 1, plane, y_last)];
            let diff = xv * n.inv_x - yv * n.inv_y;
            d += weight[c as usize] * diff * diff;
        }
        out[q] = d;
    }

    /// `dx` (`x`'s layout) from the distances' gradient `grad` (`[B]`), one thread per pixel
    /// `(b, p)` of the `pixels`: `u_c = 2 · weight[c] · (x̂_c − ŷ_c) · grad[b] / plane`,
    /// `dx_j = u_j / n − x_j · Σ_c u_c x_c / (n² ‖x‖)` (the second term 0 where `‖x‖` is 0).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn lpips_grad(
        x: &Tensor<f32>,
        y: &Tensor<f32>,
        weight: &Tensor<f32>,
        grad: &Tensor<f32>,
        dx: &mut Tensor<f32>,
        pixels: u32,
        channels: u32,
        plane: u32,
        epsilon: f32,
        #[comptime] x_last: bool,
        #[comptime] y_last: bool,
    ) {
        let q = ABSOLUTE_POS as u32;
        if q >= pixels {
            terminate!();
        }
        let (b, p) = (q / plane, q % plane);
        let n = norms(x, y, b, p, channels, plane, epsilon, x_last, y_last);
        let scale = grad[b as usize] / f32::cast_from(plane);
        let mut dot = 0.0f32;
        for c in 0..channels {
            let xv = x[offset(b, c, 0, p, channels, 1, plane, x_last)];
            let yv = y[offset(b, c, 0, p, channels, 1, plane, y_last)];
            dot += 2.0f32 * weight[c as usize] * scale * (xv * n.inv_x - yv * n.inv_y) * xv;
        }
        let mut k = 0.0f32;
        if n.norm_x > 0.0f32 {
            k = dot * n.inv_x * n.inv_x / n.norm_x;
        }
        for c in 0..channels {
            let at = offset(b, c, 0, p, channels, 1, plane, x_last);
            let xv = x[at];
            let yv = y[offset(b, c, 0, p, channels, 1, plane, y_last)];
            let u = 2.0f32 * weight[c as usize] * scale * (xv * n.inv_x - yv * n.inv_y);
            dx[at] = u * n.inv_x - xv * k;
        }
    }
}

/// The per-pixel terms in one kernel, their mean per batch item in Burn's reduction.
pub(super) fn lpips_distance(
    x: FloatTensor<CubeBackend>,
    y: FloatTensor<CubeBackend>,
    weight: FloatTensor<CubeBackend>,
) -> FloatTensor<CubeBackend> {
    let [batch, channels, h, w] = dims(&x);
    assert_eq!(
        dims(&y),
        [batch, channels, h, w],
        "LPIPS compares features of one shape"
    );
    assert_eq!(
        weight.shape().dims::<1>(),
        [channels],
        "one head weight per channel"
    );
    let plane = h * w;
    u32_of(x.shape().num_elements());
    let weight = into_contiguous(weight);
    let ((x, x_last), (y, y_last)) = (readable(x), readable(y));
    let terms = empty_in_layout(&x, [batch, 1, 1, plane], false);
    if batch * plane > 0 {
        let (cubes, cube) = one_thread_per_value(batch * plane);
        kernels::lpips_pixels::launch(
            &x.client,
            cubes,
            cube,
            x.clone().into_tensor_arg(),
            y.into_tensor_arg(),
            weight.into_tensor_arg(),
            terms.clone().into_tensor_arg(),
            u32_of(channels),
            u32_of(plane).max(1),
            LPIPS_EPSILON,
            x_last,
            y_last,
        );
    }
    let terms = CubeBackend::float_reshape(terms, Shape::new([batch, plane]));
    CubeBackend::float_reshape(CubeBackend::float_mean_dim(terms, 1), Shape::new([batch]))
}

/// One kernel, the gradient in `x`'s layout.
pub(super) fn lpips_distance_grad(
    x: FloatTensor<CubeBackend>,
    y: FloatTensor<CubeBackend>,
    weight: FloatTensor<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
) -> FloatTensor<CubeBackend> {
    let shape = dims(&x);
    let [batch, channels, h, w] = shape;
    assert_eq!(dims(&y), shape, "LPIPS compares features of one shape");
    assert_eq!(
        grad.shape().dims::<1>(),
        [batch],
        "one gradient per distance"
    );
    let pixels = batch * h * w;
    u32_of(x.shape().num_elements());
    let (weight, grad) = (into_contiguous(weight), into_contiguous(grad));
    let ((x, x_last), (y, y_last)) = (readable(x), readable(y));
    let dx = empty_in_layout(&x, shape, x_last);
    if pixels > 0 {
        let (cubes, cube) = one_thread_per_value(pixels);
        kernels::lpips_grad::launch(
            &x.client,
            cubes,
            cube,
            x.clone().into_tensor_arg(),
            y.into_tensor_arg(),
            weight.into_tensor_arg(),
            grad.into_tensor_arg(),
            dx.clone().into_tensor_arg(),
            u32_of(pixels),
            u32_of(channels),
            u32_of(h * w),
            LPIPS_EPSILON,
            x_last,
            y_last,
        );
    }
    dx
}
