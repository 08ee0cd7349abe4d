//! Gaussian rendering as a Burn operation with a hand-written backward.
//!
//! [`SplatBackend`] is a backend extension: [`SplatBackend::splat_forward`] renders and saves
//! what the backward needs ([`RasterState`]); [`SplatBackend::splat_backward`] turns output
//! gradients into input gradients. `Flex` implements both with the CPU path in
//! [`crate::cpu`], `CubeBackend` (features `gpu` and `cuda`: wgpu and CUDA devices) with the
//! kernels of `crate::cube`, and `Fusion<CubeBackend>` (feature `fusion`) by running that
//! eagerly between fused blocks; `Autodiff<B>` records one graph node whose backward calls
//! `B::splat_backward`. The saved state is plain tensors (on the device that rendered), so
//! callers never know which backend ran.
//!
//! The trait and its tensors are here; `flex.rs` implements it with the CPU renderer and
//! `autodiff.rs` records the graph node (as brush keeps its forward and backward glue apart).
//!
//! The forward returns one packed `[H, W, 5]` image (RGB, alpha, depth) so that a single
//! autodiff node carries all differentiable outputs; [`render`] slices it apart.

use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Backend, Dispatch, ExtensionType, backend_extension};
use burn::tensor::{DType, Int, IntDType, Shape, Tensor};

use crate::semantics::RenderOptions;
use crate::{Camera, SplatError};

mod autodiff;
mod flex;
#[cfg(all(feature = "fusion", any(feature = "gpu", feature = "cuda")))]
mod fusion;

/// Number of channels of the packed render: R, G, B, alpha, depth.
pub const PACKED_CHANNELS: usize = 5;
/// Floats per projected Gaussian in [`RasterState::screen`]: mean (2), conic (3), colour (3),
/// opacity, depth.
pub const SCREEN_FLOATS: usize = 10;

/// The differentiable inputs of a render (and, for the backward, their gradients).
#[derive(ExtensionType, Clone, Debug)]
pub struct GaussianTensors<B: Backend> {
    /// `[N, 3]`
    pub means: FloatTensor<B>,
    /// `[N, 3]`
    pub log_scales: FloatTensor<B>,
    /// `[N, 4]`, (w, x, y, z), normalised on use
    pub quats: FloatTensor<B>,
    /// `[N]`
    pub opacity_logits: FloatTensor<B>,
    /// `[N, K, 3]`, K = (degree + 1)²
    pub sh: FloatTensor<B>,
    /// `[3]`
    pub background: FloatTensor<B>,
}

/// What the forward saves for the backward, as tensors so that any backend can hold it.
#[derive(ExtensionType, Clone, Debug)]
pub struct RasterState<B: Backend> {
    /// `[N, SCREEN_FLOATS]` projected Gaussians.
    pub screen: FloatTensor<B>,
    /// `[N, 2]` footprint half-sizes in pixels (x, y), 0 when culled.
    pub radii: IntTensor<B>,
    /// `[tiles + 1]` offsets into `tile_ids`.
    pub tile_offsets: IntTensor<B>,
    /// `[intersections]` Gaussian ids per tile, front to back.
    pub tile_ids: IntTensor<B>,
    /// `[H, W]` final transmittance.
    pub final_transmittance: FloatTensor<B>,
    /// `[H, W]` one past the last contributing list position.
    pub n_contrib: IntTensor<B>,
}

/// Result of [`SplatBackend::splat_forward`].
#[derive(ExtensionType, Clone, Debug)]
pub struct SplatForward<B: Backend> {
    /// `[H, W, 5]`: RGB, alpha, depth.
    pub image: FloatTensor<B>,
    #[extension_type]
    pub state: RasterState<B>,
    /// Set when the inputs were rejected (non-finite values, bad shapes, too many
    /// intersections); the tensors are then empty placeholders and must not be used.
    pub error: Option<SplatError>,
}

/// Gaussian rasterisation as a backend operation.
#[backend_extension(Autodiff, Flex, Cube: cfg(any(feature = "gpu", feature = "cuda")))]
pub trait SplatBackend: Backend {
    /// Renders `inputs` seen by `camera`.
    fn splat_forward(
        #[extension_type] inputs: GaussianTensors<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> SplatForward<Self>;

    /// Gradients of the inputs given the gradient of the packed `[H, W, 5]` image.
    fn splat_backward(
        #[extension_type] inputs: GaussianTensors<Self>,
        #[extension_type] state: RasterState<Self>,
        grad_image: FloatTensor<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> GaussianTensors<Self>;
}

impl<B: Backend> GaussianTensors<B> {
    /// Every tensor through `f`: the one place that lists the fields, for the backends that
    /// move the inputs or their gradients between backends, dtypes or layouts.
    pub(crate) fn map_tensors<C: Backend>(
        self,
        mut f: impl FnMut(FloatTensor<B>) -> FloatTensor<C>,
    ) -> GaussianTensors<C> {
        GaussianTensors {
            means: f(self.means),
            log_scales: f(self.log_scales),
            quats: f(self.quats),
            opacity_logits: f(self.opacity_logits),
            sh: f(self.sh),
            background: f(self.background),
        }
    }
}

impl<B: Backend> RasterState<B> {
    /// Every float tensor through `float` and every int tensor through `int`.
    pub(crate) fn map_tensors<C: Backend>(
        self,
        mut float: impl FnMut(FloatTensor<B>) -> FloatTensor<C>,
        mut int: impl FnMut(IntTensor<B>) -> IntTensor<C>,
    ) -> RasterState<C> {
        RasterState {
            screen: float(self.screen),
            radii: int(self.radii),
            tile_offsets: int(self.tile_offsets),
            tile_ids: int(self.tile_ids),
            final_transmittance: float(self.final_transmittance),
            n_contrib: int(self.n_contrib),
        }
    }
}

/// What [`SplatBackend::splat_forward`] returns for rejected inputs: the error and empty
/// placeholders, so that a request refused for its size allocates nothing of that size.
pub(crate) fn rejected<B: Backend>(
    error: SplatError,
    device: &<B as burn::backend::BackendTypes>::Device,
    dtype: DType,
) -> SplatForward<B> {
    let float = |shape: Vec<usize>| B::float_zeros(Shape::from(shape), device, dtype.into());
    let int = |shape: Vec<usize>| B::int_zeros(Shape::from(shape), device, IntDType::I32);
    SplatForward {
        image: float(vec![0, 0, PACKED_CHANNELS]),
        state: RasterState {
            screen: float(vec![0, SCREEN_FLOATS]),
            radii: int(vec![0, 2]),
            tile_offsets: int(vec![0]),
            tile_ids: int(vec![0]),
            final_transmittance: float(vec![0, 0]),
            n_contrib: int(vec![0, 0]),
        },
        error: Some(error),
    }
}

/// Gaussians as Burn tensors (any device; gradients flow when the device is autodiff).
#[derive(Clone, Debug)]
pub struct Gaussians {
    /// `[N, 3]` world positions (metres).
    pub means: Tensor<2>,
    /// `[N, 3]` natural-log scales.
    pub log_scales: Tensor<2>,
    /// `[N, 4]` rotations (w, x, y, z), normalised on use.
    pub quats: Tensor<2>,
    /// `[N]` opacity logits.
    pub opacity_logits: Tensor<1>,
    /// `[N, K, 3]` SH coefficients, K = (degree + 1)².
    pub sh: Tensor<3>,
}

impl Gaussians {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.opacity_logits.dims()[0]
    }

    /// True when there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Checks that all shapes agree with `[N,3]`, `[N,3]`, `[N,4]`, `[N]`, `[N,K,3]`.
    pub fn validate_shapes(&self) -> Result<(), SplatError> {
        check_gaussian_shapes(
            self.len(),
            &self.means.dims(),
            &self.log_scales.dims(),
            &self.quats.dims(),
            &self.sh.dims(),
        )
    }
}

/// Checks the shapes of a render's inputs against `[N, 3]` (means, log-scales), `[N, 4]`
/// (quaternions) and `[N, K, 3]` (SH, K = (degree + 1)² for a degree 0..=3), naming the first
/// field that differs. Every backend's op checks through here.
pub(crate) fn check_gaussian_shapes(
    n: usize,
    means: &[usize],
    log_scales: &[usize],
    quats: &[usize],
    sh: &[usize],
) -> Result<(), SplatError> {
    let check = |name: &'static str, got: &[usize], expected: &[usize], text: &str| {
        if got != expected {
            return Err(SplatError::Shape {
                name,
                got: got.to_vec(),
                expected: format!("{text} with N = {n}"),
            });
        }
        Ok(())
    };
    check("means", means, &[n, 3], "[N, 3]")?;
    check("log_scales", log_scales, &[n, 3], "[N, 3]")?;
    check("quats", quats, &[n, 4], "[N, 4]")?;
    let k = sh.get(1).copied().unwrap_or(0);
    check("sh", sh, &[n, k, 3], "[N, K, 3]")?;
    if crate::sh::degree_for(k).is_none() {
        return Err(SplatError::ShDegree { coeffs: k });
    }
    Ok(())
}

/// Checks that a background has shape `[3]`.
pub(crate) fn check_background_shape(shape: &[usize]) -> Result<(), SplatError> {
    if shape != [3] {
        return Err(SplatError::Shape {
            name: "background",
            got: shape.to_vec(),
            expected: "[3]".into(),
        });
    }
    Ok(())
}

/// A rendered image and per-Gaussian statistics.
#[derive(Clone, Debug)]
pub struct Rendered {
    /// `[H, W, 3]` RGB with the background composited.
    pub color: Tensor<3>,
    /// `[H, W]` accumulated opacity `1 − T_final`.
    pub alpha: Tensor<2>,
    /// `[H, W]` alpha-weighted camera-space depth `Σ zᵢ αᵢ Tᵢ`.
    pub depth: Tensor<2>,
    /// `[N, 2]` footprint half-sizes in pixels (x, y), 0 for culled Gaussians.
    pub radii: Tensor<2, Int>,
}

/// Renders `gaussians` from `camera` over `background` (`[3]`), differentiably.
pub fn render(
    gaussians: &Gaussians,
    camera: &Camera,
    background: Tensor<1>,
    options: &RenderOptions,
) -> Result<Rendered, SplatError> {
    camera.validate()?;
    options.validate()?;
    gaussians.validate_shapes()?;
    check_background_shape(&background.dims())?;
    let inputs = GaussianTensors {
        means: gaussians.means.clone().into_dispatch(),
        log_scales: gaussians.log_scales.clone().into_dispatch(),
        quats: gaussians.quats.clone().into_dispatch(),
        opacity_logits: gaussians.opacity_logits.clone().into_dispatch(),
        sh: gaussians.sh.clone().into_dispatch(),
        background: background.into_dispatch(),
    };
    let out = <Dispatch as SplatBackend>::splat_forward(inputs, camera.clone(), *options);
    if let Some(error) = out.error {
        return Err(error);
    }
    let image = Tensor::<3>::from_dispatch(out.image);
    let (h, w) = (camera.height as usize, camera.width as usize);
    Ok(Rendered {
        color: image.clone().slice([0..h, 0..w, 0..3]),
        alpha: image.clone().slice([0..h, 0..w, 3..4]).reshape([h, w]),
        depth: image.slice([0..h, 0..w, 4..5]).reshape([h, w]),
        radii: Tensor::<2, Int>::from_dispatch(out.state.radii),
    })
}
