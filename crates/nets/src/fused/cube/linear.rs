//! A linear layer with scaled weight and bias and an optional leaky ReLU, for the few rows of a
//! style vector or a discriminator's head, where a tiled matmul's launches and layout copies
//! cost more than its arithmetic saves. Each dot product is a cube's ([`super::sum`]): the
//! forward one cube per output value; the three gradients one launch, whose first cubes compute
//! the weight's and the bias's gradient a thread per value (a sum over the batch, a row or
//! two) and whose last cubes the input's, a cube per value (a sum over the outputs). No atomics.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;

use super::sum::{SUM_UNITS, one_cube_per_value};
use super::u32_of;
use crate::fused::LinearScales;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use super::super::bias_leaky_relu::kernels::activation_grad;
    use super::super::sum::{cube_index, cube_sum};

    /// `out[b, o] = gain · leaky_relu(Σ_i x[b, i] · weight[o, i] · weight_scale + bias[o] ·
    /// bias_scale, slope)`, one cube per output value `k = b · outputs + o` ([`cube_index`];
    /// cubes past the `values` write nothing), its units striding over `i` (row-major tensors).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn scaled_linear(
        x: &Tensor<f32>,
        weight: &Tensor<f32>,
        bias: &Tensor<f32>,
        out: &mut Tensor<f32>,
        values: u32,
        inputs: u32,
        outputs: u32,
        weight_scale: f32,
        bias_scale: f32,
        slope: f32,
        gain: f32,
        #[comptime] units: u32,
    ) {
        let t = UNIT_POS;
        let k = cube_index();
        let b = k / outputs;
        let o = k % outputs;
        let mut partial = Shared::<[f32]>::new_slice(comptime![units as usize]);
        let mut dot = 0.0f32;
        if k < values {
            let mut i = t;
            while i < inputs {
                dot += x[(b * inputs + i) as usize] * weight[(o * inputs + i) as usize];
                i += units;
            }
        }
        partial[t as usize] = dot;
        cube_sum(&mut partial, units);
        if t == 0 && k < values {
            let pre = partial[0] * weight_scale + bias[o as usize] * bias_scale;
            let mut value = pre;
            if pre <= 0.0 {
                value = slope * pre;
            }
            out[k as usize] = gain * value;
        }
    }

    /// The three gradients. The first `elementwise` cubes ([`cube_index`]) a thread `t` per
    /// value: `d_weight[t]` for `t < out·in`, then `d_bias[t − out·in]` for the next `out`,
    /// each a sum over the batch. The cubes after them one per value `u` of `d_x` (`B·in`
    /// of them; further cubes write nothing), its units striding over the outputs. Each term
    /// is the activation's gradient times the other factor; every unit reaches the cube sum.
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
        elementwise: u32,
        batch: u32,
        inputs: u32,
        outputs: u32,
        weight_scale: f32,
        bias_scale: f32,
        slope: f32,
        gain: f32,
        #[comptime] units: u32,
    ) {
        let c = cube_index();
        let weights = outputs * inputs;
        let mut partial = Shared::<[f32]>::new_slice(comptime![units as usize]);
        let mut term = 0.0f32;
        let mut u = 0u32;
        if c >= elementwise {
            u = c - elementwise;
        }
        if c < elementwise {
            let t = c * units + UNIT_POS;
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
            } else if t < weights + outputs {
                let o = t - weights;
                let mut sum = 0.0f32;
                for b in 0..batch {
                    let at = (b * outputs + o) as usize;
                    sum += activation_grad(grad[at], output[at], slope, gain);
                }
                d_bias[o as usize] = sum * bias_scale;
            }
        } else if u < batch * inputs {
            let b = u / inputs;
            let i = u % inputs;
            let mut o = UNIT_POS;
            while o < outputs {
                let at = (b * outputs + o) as usize;
                let g = activation_grad(grad[at], output[at], slope, gain);
                term += g * weight[(o * inputs + i) as usize];
                o += units;
            }
        }
        partial[UNIT_POS as usize] = term;
        cube_sum(&mut partial, units);
        if UNIT_POS == 0 && c >= elementwise && u < batch * inputs {
            d_x[u as usize] = partial[0] * weight_scale;
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
        let (cubes, cube) = one_cube_per_value(values);
        kernels::scaled_linear::launch(
            &x.client,
            cubes,
            cube,
            x.clone().into_tensor_arg(),
            weight.into_tensor_arg(),
            bias.into_tensor_arg(),
            out.clone().into_tensor_arg(),
            u32_of(values),
            u32_of(inputs),
            u32_of(outputs),
            scales.weight_scale,
            scales.bias_scale,
            scales.slope,
            scales.gain,
            SUM_UNITS,
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
    let elementwise = (outputs * inputs + outputs).div_ceil(SUM_UNITS as usize);
    let cubes = elementwise + batch * inputs;
    u32_of(cubes * SUM_UNITS as usize);
    if outputs * inputs + batch * inputs + outputs > 0 {
        let (cubes, cube) = one_cube_per_value(cubes);
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
            u32_of(elementwise),
            u32_of(batch),
            u32_of(inputs),
            u32_of(outputs),
            scales.weight_scale,
            scales.bias_scale,
            scales.slope,
            scales.gain,
            SUM_UNITS,
        );
    }
    (d_x, d_weight, d_bias)
}
