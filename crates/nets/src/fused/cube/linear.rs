//! A linear layer with scaled weight and bias and an optional leaky ReLU: the forward one thread
//! per output value, the three gradients one launch with a thread per value of each (a dot
//! product each, no atomics). Meant for the few rows of a style vector or a discriminator's
//! head, where a tiled matmul's launches and layout copies cost more than its arithmetic saves.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;

use super::u32_of;
use crate::cube_grid::one_thread_per_value;
use crate::fused::LinearScales;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// The activation's gradient, as `bias_leaky_relu_grad`'s: with slope 0 a selection.
    #[cube]
    fn activation_grad(grad: f32, output: f32, slope: f32, gain: f32) -> f32 {
        let mut value = 0.0f32;
        if output > 0.0 {
            value = gain * grad;
        } else if slope != 0.0 {
            value = gain * slope * grad;
        }
        value
    }

    /// `out[b, o] = gain · leaky_relu(Σ_i x[b, i] · weight[o, i] · weight_scale + bias[o] ·
    /// bias_scale, slope)`, one thread per output value (row-major tensors).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn scaled_linear(
        x: &Tensor<f32>,
        weight: &Tensor<f32>,
        bias: &Tensor<f32>,
        out: &mut Tensor<f32>,
        inputs: u32,
        outputs: u32,
        weight_scale: f32,
        bias_scale: f32,
        slope: f32,
        gain: f32,
    ) {
        let k = ABSOLUTE_POS;
        if k >= out.len() {
            terminate!();
        }
        let b = k as u32 / outputs;
        let o = k as u32 % outputs;
        let mut dot = 0.0f32;
        for i in 0..inputs {
            dot += x[(b * inputs + i) as usize] * weight[(o * inputs + i) as usize];
        }
        let pre = dot * weight_scale + bias[o as usize] * bias_scale;
        let mut value = pre;
        if pre <= 0.0 {
            value = slope * pre;
        }
        out[k] = gain * value;
    }

    /// The three gradients, thread `t` computing `d_weight[t]` for `t < out·in`, then
    /// `d_x[t − out·in]` for the next `B·in`, then `d_bias[t − out·in − B·in]` for the last
    /// `out`: each a sum over the batch or the outputs of the activation's gradient times the
    /// other factor, in the order `fused::flex` sums.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn scaled_linear_grad(
        x: &Tensor<f32>,
        weight: &Tensor<f32>,
        output: &Tensor<f32>,
        grad: &Tensor<f32>,
        d_x: &mut Tensor<f32>,
        d_weight: &mut Tensor<f32>,
        d_bias: &mut Tensor<f32>,
        batch: u32,
        inputs: u32,
        outputs: u32,
        weight_scale: f32,
        bias_scale: f32,
        slope: f32,
        gain: f32,
    ) {
        let t = ABSOLUTE_POS as u32;
        let weights = outputs * inputs;
        let xs = batch * inputs;
        if t < weights {
            let o = t / inputs;
            let i = t % inputs;
            let mut sum = 0.0f32;
            for b in 0..batch {
                let at = (b * outputs + o) as usize;
                let g = activation_grad(grad[at], output[at], slope, gain);
                sum += g * x[(b * inputs + i) as usize];
            }
            d_weight[t as usize] = sum * weight_scale;
        } else if t < weights + xs {
            let u = t - weights;
            let b = u / inputs;
            let i = u % inputs;
            let mut sum = 0.0f32;
            for o in 0..outputs {
                let at = (b * outputs + o) as usize;
                let g = activation_grad(grad[at], output[at], slope, gain);
                sum += g * weight[(o * inputs + i) as usize];
            }
            d_x[u as usize] = sum * weight_scale;
        } else if t < weights + xs + outputs {
            let o = t - weights - xs;
            let mut sum = 0.0f32;
            for b in 0..batch {
                let at = (b * outputs + o) as usize;
                sum += activation_grad(grad[at], output[at], slope, gain);
            }
            d_bias[o as usize] = sum * bias_scale;
        }
    }
}

/// `(batch, inputs, outputs)` of an input `[B, in]` and a weight `[out, in]`.
fn linear_dims(
    x: &FloatTensor<CubeBackend>,
    weight: &FloatTensor<CubeBackend>,
) -> (usize, usize, usize) {
    let [batch, inputs] = x.shape().dims();
    let [outputs, weight_inputs] = weight.shape().dims();
    assert_eq!(weight_inputs, inputs, "the weight's inputs are the input's");
    (batch, inputs, outputs)
}

fn empty(like: &FloatTensor<CubeBackend>, shape: Vec<usize>) -> FloatTensor<CubeBackend> {
    empty_device_contiguous_dtype(
        like.client.clone(),
        like.device.clone(),
        Shape::from(shape),
        DType::F32,
    )
}

/// One kernel on the inputs made row-major.
pub(super) fn scaled_linear(
    x: FloatTensor<CubeBackend>,
    weight: FloatTensor<CubeBackend>,
    bias: FloatTensor<CubeBackend>,
    scales: LinearScales,
) -> FloatTensor<CubeBackend> {
    let (batch, inputs, outputs) = linear_dims(&x, &weight);
    assert_eq!(bias.shape().dims::<1>(), [outputs], "one bias per output");
    let [x, weight, bias] = [x, weight, bias].map(into_contiguous);
    let out = empty(&x, vec![batch, outputs]);
    let values = batch * outputs;
    if values > 0 {
        let (cubes, cube) = one_thread_per_value(values);
        kernels::scaled_linear::launch(
            &x.client,
            cubes,
            cube,
            x.clone().into_tensor_arg(),
            weight.into_tensor_arg(),
            bias.into_tensor_arg(),
            out.clone().into_tensor_arg(),
            u32_of(inputs),
            u32_of(outputs),
            scales.weight_scale,
            scales.bias_scale,
            scales.slope,
            scales.gain,
        );
    }
    out
}

/// One kernel for the three gradients, on the inputs made row-major.
pub(super) fn scaled_linear_grad(
    x: FloatTensor<CubeBackend>,
    weight: FloatTensor<CubeBackend>,
    output: FloatTensor<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
    scales: LinearScales,
) -> (
    FloatTensor<CubeBackend>,
    FloatTensor<CubeBackend>,
    FloatTensor<CubeBackend>,
) {
    let (batch, inputs, outputs) = linear_dims(&x, &weight);
    assert_eq!(grad.shape().dims::<2>(), [batch, outputs], "gradient shape");
    let [x, weight, output, grad] = [x, weight, output, grad].map(into_contiguous);
    let d_x = empty(&x, vec![batch, inputs]);
    let d_weight = empty(&x, vec![outputs, inputs]);
    let d_bias = empty(&x, vec![outputs]);
    let threads = u32_of(outputs * inputs + batch * inputs + outputs);
    if threads > 0 {
        let (cubes, cube) = one_thread_per_value(threads as usize);
        kernels::scaled_linear_grad::launch(
            &x.client,
            cubes,
            cube,
            x.clone().into_tensor_arg(),
            weight.into_tensor_arg(),
            output.into_tensor_arg(),
            grad.into_tensor_arg(),
            d_x.clone().into_tensor_arg(),
            d_weight.clone().into_tensor_arg(),
            d_bias.clone().into_tensor_arg(),
            u32_of(batch),
            u32_of(inputs),
            u32_of(outputs),
            scales.weight_scale,
            scales.bias_scale,
            scales.slope,
            scales.gain,
        );
    }
    (d_x, d_weight, d_bias)
}
