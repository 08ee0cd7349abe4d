//! Gaussian rendering as a Burn operation with a hand-written backward.
//!
//! [`SplatBackend`] is a backend extension: [`SplatBackend::splat_forward`] renders and saves
//! what the backward needs ([`RasterState`]); [`SplatBackend::splat_backward`] turns output
//! gradients into input gradients. `Flex` implements both with the CPU path in
//! [`crate::cpu`], `Cube` (features `gpu` and `cuda`: wgpu and CUDA devices) with the kernels
//! of `crate::cube`; `Autodiff<B>` records one graph node whose backward calls
//! `B::splat_backward`. The saved state is plain tensors (on the device that rendered), so
//! callers never know which backend ran.
//!
//! The forward returns one packed `[H, W, 5]` image (RGB, alpha, depth) so that a single
//! autodiff node carries all differentiable outputs; [`render`] slices it apart.

use std::borrow::Cow;

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::ops::{FloatTensorOps, IntTensorOps};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{AutodiffBackend, Backend, Dispatch, ExtensionType, Flex, backend_extension};
use burn::tensor::{DType, Element, Int, IntDType, Shape, Tensor, TensorData};

use crate::cpu::{self, ForwardOutput, PixelGrads, TileBins};
use crate::cpu::{Projected, ScreenGaussian};
use crate::semantics::{GaussianSlices, RenderOptions, TILE_SIZE};
use crate::{Camera, SplatError};

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

/// A float tensor's values as `f32`, borrowed when already contiguous `f32`.
fn host_f32(t: &FloatTensor<Flex>) -> Cow<'_, [f32]> {
    host(t)
}

fn host<E: Element + bytemuck::Pod>(t: &FloatTensor<Flex>) -> Cow<'_, [E]> {
    match t.as_slice::<E>() {
        Some(s) => Cow::Borrowed(s),
        None => Cow::Owned(
            t.clone()
                .into_data()
                .try_to_vec_as::<E>()
                .expect("every numeric tensor converts to the requested element type"),
        ),
    }
}

fn flex_tensor<E: Element>(values: Vec<E>, shape: &[usize], dtype: DType) -> FloatTensor<Flex> {
    Flex::float_from_data(
        TensorData::new(values, shape.to_vec()).convert_dtype(dtype),
        &Default::default(),
    )
}

fn flex_int<E: Element>(values: Vec<E>, shape: &[usize]) -> IntTensor<Flex> {
    Flex::int_from_data(TensorData::new(values, shape.to_vec()), &Default::default())
}

fn screen_to_floats(projected: &Projected<f32>) -> Vec<f32> {
    projected
        .iter()
        .flat_map(|g| {
            [
                g.mean[0], g.mean[1], g.conic[0], g.conic[1], g.conic[2], g.color[0], g.color[1],
                g.color[2], g.opacity, g.depth,
            ]
        })
        .collect()
}

fn screen_from_floats(
    values: &[f32],
    radii: &[i32],
    width: usize,
    height: usize,
) -> Projected<f32> {
    values
        .chunks_exact(SCREEN_FLOATS)
        .zip(radii.chunks_exact(2))
        .map(|(v, r)| ScreenGaussian {
            mean: [v[0], v[1]],
            conic: [v[2], v[3], v[4]],
            color: [v[5], v[6], v[7]],
            opacity: v[8],
            depth: v[9],
            radii: [r[0].max(0) as u32, r[1].max(0) as u32],
            pixels: [0; 4],
        })
        .map(|g| g.with_footprint(width, height))
        .collect()
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

impl SplatBackend for Flex {
    fn splat_forward(
        inputs: GaussianTensors<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> SplatForward<Self> {
        let dtype = inputs.means.dtype();
        let (means, log_scales, quats) = (
            host_f32(&inputs.means),
            host_f32(&inputs.log_scales),
            host_f32(&inputs.quats),
        );
        let (opacity_logits, sh) = (host_f32(&inputs.opacity_logits), host_f32(&inputs.sh));
        let background = host_f32(&inputs.background);
        let slices = GaussianSlices {
            means: &means,
            log_scales: &log_scales,
            quats: &quats,
            opacity_logits: &opacity_logits,
            sh: &sh,
        };
        let (w, h) = (camera.width as usize, camera.height as usize);
        let bg = [0, 1, 2].map(|c| background.get(c).copied().unwrap_or(f32::NAN));
        match cpu::render(&slices, &camera, bg, &options) {
            Ok(fwd) => pack_forward(fwd, w, h, dtype),
            Err(error) => rejected(error, &Default::default(), dtype),
        }
    }

    fn splat_backward(
        inputs: GaussianTensors<Self>,
        state: RasterState<Self>,
        grad_image: FloatTensor<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> GaussianTensors<Self> {
        let dtype = inputs.means.dtype();
        let (means, log_scales, quats) = (
            host_f32(&inputs.means),
            host_f32(&inputs.log_scales),
            host_f32(&inputs.quats),
        );
        let (opacity_logits, sh) = (host_f32(&inputs.opacity_logits), host_f32(&inputs.sh));
        let background = host_f32(&inputs.background);
        let slices = GaussianSlices {
            means: &means,
            log_scales: &log_scales,
            quats: &quats,
            opacity_logits: &opacity_logits,
            sh: &sh,
        };
        let (w, h) = (camera.width as usize, camera.height as usize);
        let radii = host::<i32>(&state.radii);
        let bins = TileBins {
            tiles_x: w.div_ceil(TILE_SIZE),
            tiles_y: h.div_ceil(TILE_SIZE),
            offsets: host::<u32>(&state.tile_offsets).into_owned(),
            ids: host::<u32>(&state.tile_ids).into_owned(),
        };
        let fwd = ForwardOutput {
            color: Vec::new(),
            alpha: Vec::new(),
            depth: Vec::new(),
            final_transmittance: host_f32(&state.final_transmittance).into_owned(),
            n_contrib: host::<u32>(&state.n_contrib).into_owned(),
            projected: screen_from_floats(&host_f32(&state.screen), &radii, w, h),
            bins,
            background: [background[0], background[1], background[2]],
            evaluations: 0,
        };
        let packed = host_f32(&grad_image);
        let mut d_color = Vec::with_capacity(w * h * 3);
        let mut d_alpha = Vec::with_capacity(w * h);
        let mut d_depth = Vec::with_capacity(w * h);
        for px in packed.chunks_exact(PACKED_CHANNELS) {
            d_color.extend_from_slice(&px[..3]);
            d_alpha.push(px[3]);
            d_depth.push(px[4]);
        }
        let pixel_grads = PixelGrads {
            color: &d_color,
            alpha: &d_alpha,
            depth: &d_depth,
        };
        let g = cpu::render_backward(&slices, &camera, &options, &fwd, &pixel_grads);
        let n = slices.len();
        let k = slices.sh_coeffs();
        GaussianTensors {
            means: flex_tensor(g.means, &[n, 3], dtype),
            log_scales: flex_tensor(g.log_scales, &[n, 3], dtype),
            quats: flex_tensor(g.quats, &[n, 4], dtype),
            opacity_logits: flex_tensor(g.opacity_logits, &[n], dtype),
            sh: flex_tensor(g.sh, &[n, k, 3], dtype),
            background: flex_tensor(g.background.to_vec(), &[3], dtype),
        }
    }
}

fn pack_forward(fwd: ForwardOutput<f32>, w: usize, h: usize, dtype: DType) -> SplatForward<Flex> {
    let mut image = Vec::with_capacity(w * h * PACKED_CHANNELS);
    for p in 0..w * h {
        image.extend_from_slice(&[
            fwd.color[3 * p],
            fwd.color[3 * p + 1],
            fwd.color[3 * p + 2],
            fwd.alpha[p],
            fwd.depth[p],
        ]);
    }
    let n = fwd.projected.len();
    let radii: Vec<i32> = fwd
        .projected
        .iter()
        .flat_map(|g| g.radii.map(|r| r.min(i32::MAX as u32) as i32))
        .collect();
    let n_isect = fwd.bins.ids.len();
    let n_offsets = fwd.bins.offsets.len();
    SplatForward {
        image: flex_tensor(image, &[h, w, PACKED_CHANNELS], dtype),
        state: RasterState {
            screen: flex_tensor(
                screen_to_floats(&fwd.projected),
                &[n, SCREEN_FLOATS],
                DType::F32,
            ),
            radii: flex_int(radii, &[n, 2]),
            tile_offsets: flex_int(fwd.bins.offsets, &[n_offsets]),
            tile_ids: flex_int(fwd.bins.ids, &[n_isect]),
            final_transmittance: flex_tensor(fwd.final_transmittance, &[h, w], DType::F32),
            n_contrib: flex_int(fwd.n_contrib, &[h, w]),
        },
        error: None,
    }
}

/// Wraps backend-level state tensors as (untracked) autodiff tensors.
fn lift_state<B: Backend, C: CheckpointStrategy>(s: RasterState<B>) -> RasterState<Autodiff<B, C>> {
    RasterState {
        screen: Autodiff::<B, C>::from_inner(s.screen),
        radii: s.radii,
        tile_offsets: s.tile_offsets,
        tile_ids: s.tile_ids,
        final_transmittance: Autodiff::<B, C>::from_inner(s.final_transmittance),
        n_contrib: s.n_contrib,
    }
}

fn lower_state<B: Backend, C: CheckpointStrategy>(
    s: RasterState<Autodiff<B, C>>,
) -> RasterState<B> {
    RasterState {
        screen: s.screen.into_primitive(),
        radii: s.radii,
        tile_offsets: s.tile_offsets,
        tile_ids: s.tile_ids,
        final_transmittance: s.final_transmittance.into_primitive(),
        n_contrib: s.n_contrib,
    }
}

fn lower_inputs<B: Backend, C: CheckpointStrategy>(
    g: GaussianTensors<Autodiff<B, C>>,
) -> GaussianTensors<B> {
    GaussianTensors {
        means: g.means.into_primitive(),
        log_scales: g.log_scales.into_primitive(),
        quats: g.quats.into_primitive(),
        opacity_logits: g.opacity_logits.into_primitive(),
        sh: g.sh.into_primitive(),
        background: g.background.into_primitive(),
    }
}

/// Saved for the backward: the inner-backend inputs, the raster state and the view.
type SavedRender<B> = (GaussianTensors<B>, RasterState<B>, Camera, RenderOptions);

#[derive(Debug)]
struct SplatBackwardOp;

impl<B: Backend + SplatBackend> Backward<B, 6> for SplatBackwardOp {
    type State = SavedRender<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 6>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad_image = grads.consume::<B>(&ops.node);
        let (inputs, state, camera, options) = ops.state;
        let g = B::splat_backward(inputs, state, grad_image, camera, options);
        let per_input = [
            g.means,
            g.log_scales,
            g.quats,
            g.opacity_logits,
            g.sh,
            g.background,
        ];
        for (parent, grad) in ops.parents.into_iter().zip(per_input) {
            if let Some(node) = parent {
                grads.register::<B>(node.id, grad);
            }
        }
    }
}

impl<B: Backend + SplatBackend, C: CheckpointStrategy> SplatBackend for Autodiff<B, C> {
    fn splat_forward(
        inputs: GaussianTensors<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> SplatForward<Self> {
        let nodes = [
            inputs.means.node(),
            inputs.log_scales.node(),
            inputs.quats.node(),
            inputs.opacity_logits.node(),
            inputs.sh.node(),
            inputs.background.node(),
        ];
        let inner = lower_inputs(inputs);
        match SplatBackwardOp
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::splat_forward(inner.clone(), camera.clone(), options);
                let saved = (inner, out.state.clone(), camera, options);
                SplatForward {
                    image: prep.finish(saved, out.image),
                    state: lift_state(out.state),
                    error: out.error,
                }
            }
            OpsKind::UnTracked(prep) => {
                let out = B::splat_forward(inner, camera, options);
                SplatForward {
                    image: prep.finish(out.image),
                    state: lift_state(out.state),
                    error: out.error,
                }
            }
        }
    }

    fn splat_backward(
        inputs: GaussianTensors<Self>,
        state: RasterState<Self>,
        grad_image: FloatTensor<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> GaussianTensors<Self> {
        let g = B::splat_backward(
            lower_inputs(inputs),
            lower_state(state),
            grad_image.into_primitive(),
            camera,
            options,
        );
        GaussianTensors {
            means: Autodiff::<B, C>::from_inner(g.means),
            log_scales: Autodiff::<B, C>::from_inner(g.log_scales),
            quats: Autodiff::<B, C>::from_inner(g.quats),
            opacity_logits: Autodiff::<B, C>::from_inner(g.opacity_logits),
            sh: Autodiff::<B, C>::from_inner(g.sh),
            background: Autodiff::<B, C>::from_inner(g.background),
        }
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
