//! `impl ConvBackend for CubeBackend` (wgpu, CUDA without fusion): Burn's convolution kernels,
//! with the algorithm chosen here instead of by Burn's default.
//!
//! Without `autotune`, Burn 0.22.1 runs a convolution and both its gradients with its *direct*
//! kernels (`ConvStrategy::Direct`: one thread per output element, no tiling, no matrix
//! units); on an H200 that made the paper-sized networks 10–37× slower than PyTorch
//! (BENCHMARKS "GPU: an H200"). Here, on a device with matrix units (CMMA), the output and the
//! weight gradient run as implicit GEMMs (`ConvStrategy::ImplicitGemm`; on CUDA, f32 as TF32 on
//! tensor cores, as cuDNN does by default), the input gradient as an implicit GEMM at stride 1
//! and as the transposed convolution's matmul + col2im at other strides (the implicit GEMM has
//! no strided input gradient). On a device without matrix units (Mesa lavapipe), where Burn's
//! setup declines, and for grouped or asymmetrically padded convolutions, the direct kernels run
//! as before. A weight gradient whose implicit GEMM would have too few tiles for its long
//! reduction (few channels at a high resolution) runs split into bands of positions instead,
//! on any device ([`super::bands`]). With Burn's `autotune` on, its tuner chooses among all of
//! these and more, so this choice steps aside.

use burn::backend::TensorMetadata;
use burn::backend::ops::ModuleOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::ops::{ConvOptions, ConvTransposeOptions};
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::conv::{
    ConvStrategy, ConvTranspose2dStrategy, conv_data_backward, conv_forward, conv_transpose2d,
    conv_weight_backward,
};

use super::ConvBackend;
use super::bands::weight_grad_split;

/// Whether to pick the algorithm here: Burn's default is `Direct` unless its `autotune` is on.
fn choose_here(options: &ConvOptions<2>) -> bool {
    let symmetric = options.padding.iter().all(|(begin, end)| begin == end);
    symmetric && options.groups == 1 && matches!(ConvStrategy::default(), ConvStrategy::Direct)
}

/// Whether `t`'s device has matrix units (CMMA) at all. Without them Burn's implicit GEMM
/// declines every problem, but only after copying the input and the weight to NHWC: asking it
/// anyway would add those copies to every convolution before the direct kernel runs.
fn has_matrix_units(t: &FloatTensor<CubeBackend>) -> bool {
    !t.client.properties().features.matmul.cmma.is_empty()
}

impl ConvBackend for CubeBackend {
    fn conv2d_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        if choose_here(&options)
            && has_matrix_units(&x)
            && let Ok(out) = conv_forward::<2>(
                x.clone(),
                weight.clone(),
                None,
                options.clone(),
                ConvStrategy::ImplicitGemm,
            )
        {
            return out;
        }
        <Self as ModuleOps<Self>>::conv2d(x, weight, None, options)
    }

    fn conv2d_input_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        if choose_here(&options) {
            let unit_stride = options.stride.iter().all(|&s| s == 1);
            // The strided path is a plain matmul: it runs on any device.
            let fast = if !unit_stride {
                Some(conv_transpose2d(
                    grad.clone(),
                    weight.clone(),
                    None,
                    transpose_options(&x, &grad, &weight, &options),
                    ConvTranspose2dStrategy::Gemm,
                ))
            } else if has_matrix_units(&x) {
                Some(conv_data_backward(
                    grad.clone(),
                    weight.clone(),
                    x.shape(),
                    options.clone(),
                    ConvStrategy::ImplicitGemm,
                ))
            } else {
                None
            };
            if let Some(Ok(input_grad)) = fast {
                return input_grad;
            }
        }
        <Self as ModuleOps<Self>>::conv2d_x_backward(x, weight, grad, options)
    }

    fn conv2d_weight_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        if choose_here(&options) {
            if let Some(weight_grad) =
                weight_grad_split(x.clone(), grad.clone(), weight.shape(), &options)
            {
                return weight_grad;
            }
            if has_matrix_units(&x)
                && let Ok(weight_grad) = conv_weight_backward::<2>(
                    x.clone(),
                    grad.clone(),
                    weight.shape(),
                    options.clone(),
                    ConvStrategy::ImplicitGemm,
                )
            {
                return weight_grad;
            }
        }
        <Self as ModuleOps<Self>>::conv2d_weight_backward(x, weight, grad, options)
    }
}

/// The transposed convolution whose output is the input gradient of a (symmetric) `options`
/// convolution of `x`: `padding_out` restores the rows and columns a strided convolution drops.
fn transpose_options(
    x: &FloatTensor<CubeBackend>,
    grad: &FloatTensor<CubeBackend>,
    weight: &FloatTensor<CubeBackend>,
    options: &ConvOptions<2>,
) -> ConvTransposeOptions<2> {
    let (x, grad, weight) = (x.shape(), grad.shape(), weight.shape());
    let padding = options.padding.map(|(begin, _)| begin);
    let padding_out = std::array::from_fn(|i| {
        let covered =
            (grad[2 + i] - 1) * options.stride[i] + options.dilation[i] * (weight[2 + i] - 1) + 1;
        (x[2 + i] + 2 * padding[i]).saturating_sub(covered)
    });
    ConvTransposeOptions::new(
        options.stride,
        padding,
        padding_out,
        options.dilation,
        options.groups,
    )
}
