//! `impl AdamBackend for CubeBackend` (wgpu, CUDA without fusion): one kernel per parameter.
//! Inputs are read row-major after `into_contiguous`; outputs are allocated contiguous (CUDA
//! pitches Burn's ordinary allocations: `f3g_splat::cube`'s module doc).

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn::tensor::DType;
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;

use super::{AdamBackend, AdamCoefficients};
use crate::cube_grid::one_thread_per_value;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// One element of `super::super::update_one`, at `ABSOLUTE_POS`.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn adam_update(
        param: &Tensor<f32>,
        grad: &Tensor<f32>,
        moment_1: &Tensor<f32>,
        moment_2: &Tensor<f32>,
        param_out: &mut Tensor<f32>,
        moment_1_out: &mut Tensor<f32>,
        moment_2_out: &mut Tensor<f32>,
        beta_1: f32,
        one_minus_beta_1: f32,
        beta_2: f32,
        one_minus_beta_2: f32,
        moment_scale: f32,
        epsilon: f32,
        learning_rate: f32,
    ) {
        let i = ABSOLUTE_POS;
        if i >= param.len() {
            terminate!();
        }
        let g = grad[i];
        let m = moment_1[i] * beta_1 + g * one_minus_beta_1;
        let v = moment_2[i] * beta_2 + g * g * one_minus_beta_2;
        moment_1_out[i] = m;
        moment_2_out[i] = v;
        param_out[i] = param[i] - m * moment_scale / (f32::sqrt(v) + epsilon) * learning_rate;
    }
}

impl AdamBackend for CubeBackend {
    fn adam_update(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        moment_1: FloatTensor<Self>,
        moment_2: FloatTensor<Self>,
        c: AdamCoefficients,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let shape = param.shape();
        let n = shape.num_elements();
        let [param, grad, moment_1, moment_2] =
            [param, grad, moment_1, moment_2].map(into_contiguous);
        let (client, device) = (param.client.clone(), param.device.clone());
        let empty = || {
            empty_device_contiguous_dtype(client.clone(), device.clone(), shape.clone(), DType::F32)
        };
        let (param_out, m_out, v_out) = (empty(), empty(), empty());
        if n > 0 {
            let (cubes, cube) = one_thread_per_value(n);
            kernels::adam_update::launch(
                &client,
                cubes,
                cube,
                param.into_tensor_arg(),
                grad.into_tensor_arg(),
                moment_1.into_tensor_arg(),
                moment_2.into_tensor_arg(),
                param_out.clone().into_tensor_arg(),
                m_out.clone().into_tensor_arg(),
                v_out.clone().into_tensor_arg(),
                c.beta_1,
                c.one_minus_beta_1,
                c.beta_2,
                c.one_minus_beta_2,
                c.moment_scale,
                c.epsilon,
                c.learning_rate,
            );
        }
        (param_out, m_out, v_out)
    }
}
