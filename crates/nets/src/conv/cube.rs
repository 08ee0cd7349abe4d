//! `impl ConvBackend for CubeBackend` (wgpu, CUDA, fused or not): Burn's convolution kernels,
//! with the algorithm chosen here instead of by Burn's default.
//!
//! Without `autotune`, Burn 0.22.1 runs a convolution and both its gradients with its *direct*
//! kernels (`ConvStrategy::Direct`: one thread per output element, no tiling, no matrix
//! units); on an H200 that made the paper-sized networks 10–37× slower than PyTorch
//! (BENCHMARKS "GPU: an H200"). Here, on a device with matrix units (CMMA), the output and the
//! weight gradient run as implicit GEMMs (`ConvStrategy::ImplicitGemm`; on CUDA, f32 as TF32 on
//! tensor cores, as cuDNN does by default), the input gradient as an implicit GEMM at stride 1
//! and at other strides as a matmul and our col2im, channels-last ([`super::strided`]; the
//! implicit GEMM has no strided input gradient). On a device without matrix units (Mesa lavapipe), where Burn's
//! setup declines, and for grouped or asymmetrically padded convolutions, the direct kernels run
//! as before. A weight gradient whose implicit GEMM would have too few tiles for its long
//! reduction (few channels at a high resolution) runs split into bands of positions instead,
//! on any device ([`super::bands`]). `F3G_CONV_GEMM` runs another of CubeK's implicit-GEMM
//! routines instead of the default, to measure them one by one ([`gemm_choices`]). With
//! Burn's `autotune` on, its tuner chooses among all of these and more, so this choice steps
//! aside.

use burn::backend::TensorMetadata;
use burn::backend::ops::ModuleOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::ops::ConvOptions;
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::conv::{
    AcceleratedTileKind, ConvAlgorithm, ConvStrategy, conv_data_backward, conv_forward,
    conv_weight_backward,
};
use std::sync::{Mutex, OnceLock};

use super::ConvBackend;
use super::bands::{launch_queued_band_sums, weight_grad_split};
use super::strided::strided_input_grad;

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

/// Which pass of a convolution an implicit GEMM computes.
#[derive(Clone, Copy)]
enum Pass {
    Forward = 0,
    InputGrad = 1,
    WeightGrad = 2,
}

const PASS_NAMES: [&str; 3] = ["forward", "input", "weight"];

/// The implicit GEMM's routine for `pass`: Burn's `ImplicitGemm` (CubeK's synchronous cyclic
/// routine on CMMA) unless `F3G_CONV_GEMM` names another ([`gemm_choices`]). What it cannot
/// read is said once and the default runs.
fn gemm_strategy(pass: Pass) -> Option<ConvStrategy> {
    static CHOICES: OnceLock<[GemmChoice; 3]> = OnceLock::new();
    let choices = CHOICES.get_or_init(|| {
        let value = std::env::var("F3G_CONV_GEMM").unwrap_or_default();
        gemm_choices(&value).unwrap_or_else(|e| {
            eprintln!("F3G_CONV_GEMM={value}: {e}; the default runs");
            [None; 3]
        })
    });
    choices[pass as usize].map(|(algorithm, tile_kind)| ConvStrategy::ImplicitGemmWith {
        algorithm,
        tile_kind,
    })
}

/// A routine and its tile matmul; `None`: Burn's `ImplicitGemm`.
pub type GemmChoice = Option<(ConvAlgorithm, AcceleratedTileKind)>;

/// The routine of each pass (forward, input gradient, weight gradient) named by an
/// `F3G_CONV_GEMM` value: `<routine>_<cmma|mma>` (e.g. `simple_async_tma_cmma`) for every
/// pass, or per pass `forward:<name>,input:<name>,weight:<name>`, as CubeK names them (the
/// variants Burn's autotuner chooses among, to measure one at a time); empty for the default.
pub fn gemm_choices(value: &str) -> Result<[GemmChoice; 3], String> {
    let mut choices = [None; 3];
    for part in value.split(',').filter(|p| !p.is_empty()) {
        let (passes, name) = match part.split_once(':') {
            Some((pass, name)) => match PASS_NAMES.iter().position(|&p| p == pass) {
                Some(i) => (i..i + 1, name),
                None => return Err(format!("no pass {pass:?} (forward, input, weight)")),
            },
            None => (0..3, part),
        };
        let found = ALGORITHMS.iter().find_map(|&algorithm| {
            [AcceleratedTileKind::Cmma, AcceleratedTileKind::Mma]
                .into_iter()
                .find(|tile| format!("{algorithm}_{tile}") == name)
                .map(|tile| (algorithm, tile))
        });
        let Some(found) = found else {
            return Err(format!(
                "{name:?} is not a routine (e.g. simple_sync_cyclic_mma)"
            ));
        };
        for i in passes {
            choices[i] = Some(found);
        }
    }
    Ok(choices)
}

const ALGORITHMS: [ConvAlgorithm; 9] = [
    ConvAlgorithm::SimpleSyncCyclic,
    ConvAlgorithm::SimpleSyncStrided,
    ConvAlgorithm::SimpleSyncTilewise,
    ConvAlgorithm::SimpleAsyncCyclic,
    ConvAlgorithm::SimpleAsyncStrided,
    ConvAlgorithm::SimpleAsyncTma,
    ConvAlgorithm::SpecializedAsyncCyclic,
    ConvAlgorithm::SpecializedAsyncStrided,
    ConvAlgorithm::SpecializedTma,
];

/// Runs `pass` with the chosen routine, then with Burn's default implicit GEMM where it declines.
fn with_gemm<T, E: std::fmt::Debug>(
    which: Pass,
    pass: impl Fn(ConvStrategy) -> Result<T, E>,
) -> Result<T, E> {
    if let Some(strategy) = gemm_strategy(which) {
        match pass(strategy) {
            Ok(out) => return Ok(out),
            Err(err) => {
                // Once per pass and reason: a network meets the same refusal at every layer.
                static SAID: Mutex<Vec<String>> = Mutex::new(Vec::new());
                let said = format!("{} pass: {err:?}", PASS_NAMES[which as usize]);
                let mut seen = SAID.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
                if !seen.contains(&said) {
                    eprintln!("F3G_CONV_GEMM declined a {said}");
                    seen.push(said);
                }
            }
        }
    }
    pass(ConvStrategy::ImplicitGemm)
}

impl ConvBackend for CubeBackend {
    fn conv2d_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        if choose_here(&options)
            && has_matrix_units(&x)
            && let Ok(out) = with_gemm(Pass::Forward, |strategy| {
                conv_forward::<2>(x.clone(), weight.clone(), None, options.clone(), strategy)
            })
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
            // The strided path is a plain matmul and a col2im: it runs on any device.
            let fast = if !unit_stride {
                strided_input_grad(x.shape(), weight.clone(), grad.clone(), &options).map(Ok)
            } else if has_matrix_units(&x) {
                Some(with_gemm(Pass::InputGrad, |strategy| {
                    conv_data_backward(
                        grad.clone(),
                        weight.clone(),
                        x.shape(),
                        options.clone(),
                        strategy,
                    )
                }))
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
        weight_grad(x, weight, grad, options)
    }

    fn conv2d_weight_grads_launch_queued(anchor: FloatTensor<Self>) -> FloatTensor<Self> {
        launch_queued_band_sums();
        anchor
    }
}

/// The weight gradient: in bands where [`weight_grad_split`] splits it (their sum queued), else
/// as an implicit GEMM on matrix units, else Burn's direct kernel.
fn weight_grad(
    x: FloatTensor<CubeBackend>,
    weight: FloatTensor<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
    options: ConvOptions<2>,
) -> FloatTensor<CubeBackend> {
    if choose_here(&options) {
        if let Some(weight_grad) =
            weight_grad_split(x.clone(), grad.clone(), weight.shape(), &options)
        {
            return weight_grad;
        }
        if has_matrix_units(&x)
            && let Ok(weight_grad) = with_gemm(Pass::WeightGrad, |strategy| {
                conv_weight_backward::<2>(
                    x.clone(),
                    grad.clone(),
                    weight.shape(),
                    options.clone(),
                    strategy,
                )
            })
        {
            return weight_grad;
        }
    }
    <CubeBackend as ModuleOps<CubeBackend>>::conv2d_weight_backward(x, weight, grad, options)
}
