//! [`SplatBackend`] for Cube devices (wgpu, CUDA): the kernels of this module chained into
//! the op's forward and backward, with the state the backward needs kept on the device.
//!
//! Host round trips: the forward reads back one small tensor — the intersection count, which
//! sizes the tile list, together with a flag that says whether any input is NaN or infinite.
//! Only when that flag is set are the inputs read back, to name the first bad value exactly as
//! the CPU path does. The backward reads nothing back.

use burn::backend::ops::{FloatTensorOps, IntTensorOps};
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, FloatDType, IntDType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::CubeDim;
use burn_cubecl::kernel::into_contiguous;

use super::bin::{TileBins, bin_tiles, depth_order, read_count};
#[cfg(feature = "cuda-source")]
use super::cuda_source::{CudaTarget, KernelSource, tensor};
use super::project::{Projection, project};
use super::project_backward::project_backward;
use super::raster::{Accumulation, rasterize, rasterize_backward};
use super::scan::{MAX_ROW, grid};
use crate::op::{
    GaussianTensors, RasterState, SplatBackend, SplatForward, check_background_shape,
    check_gaussian_shapes, rejected,
};
use crate::semantics::{GaussianSlices, MAX_INTERSECTIONS, RenderOptions, check_finite};
use crate::{Camera, SplatError};

/// Units per cube of the input check.
const UNITS: usize = 256;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// Sets `flag[0]` when any value is NaN or infinite: its exponent bits are all ones.
    /// (On the bits, because WGSL lets a compiler assume floats are never NaN.)
    #[allow(clippy::collapsible_if)]
    #[cube(launch)]
    pub fn flag_non_finite(values: &Tensor<f32>, flag: &mut Tensor<Atomic<i32>>) {
        let i = ABSOLUTE_POS;
        // Nested: `&&` in a kernel evaluates both sides, and the index must be checked first.
        if i < values.len() {
            if f32::to_bits(values[i]) & 0x7f80_0000u32 == 0x7f80_0000u32 {
                flag[0].store(1i32);
            }
        }
    }
}

/// The kernels above as CUDA C, for the offline NVRTC check.
#[cfg(feature = "cuda-source")]
pub(super) fn cuda_kernels(target: &CudaTarget) -> Result<Vec<KernelSource>, String> {
    let (settings, properties, target_properties) = target.settings(CubeDim::new_1d(UNITS as u32));
    Ok(vec![target.source(
        "flag_non_finite",
        kernels::flag_non_finite::FlagNonFinite::new(
            settings,
            properties,
            target_properties,
            tensor(),
            tensor(),
        ),
    )?])
}

/// A contiguous f32 copy of `t` (a no-op for the f32 tensors the trainer makes).
fn f32_contiguous(t: &FloatTensor<CubeBackend>) -> FloatTensor<CubeBackend> {
    let t = if t.dtype == burn::tensor::DType::F32 {
        t.clone()
    } else {
        CubeBackend::float_cast(t.clone(), FloatDType::F32)
    };
    into_contiguous(t)
}

fn f32_inputs(inputs: &GaussianTensors<CubeBackend>) -> GaussianTensors<CubeBackend> {
    inputs.clone().map_tensors(|t| f32_contiguous(&t))
}

fn host(t: &FloatTensor<CubeBackend>) -> Vec<f32> {
    burn::tensor::read_sync(CubeBackend::float_into_data(t.clone()))
        .expect("reading a tensor back from the device")
        .convert::<f32>()
        .try_into_vec::<f32>()
        .expect("f32 values")
}

/// Checks the shapes (metadata only, no device work).
fn check_shapes(inputs: &GaussianTensors<CubeBackend>) -> Result<(), SplatError> {
    check_gaussian_shapes(
        inputs.opacity_logits.meta.shape()[0],
        inputs.means.meta.shape(),
        inputs.log_scales.meta.shape(),
        inputs.quats.meta.shape(),
        inputs.sh.meta.shape(),
    )?;
    check_background_shape(inputs.background.meta.shape())
}

/// The error the CPU path gives for these inputs (called only once the device found a
/// non-finite value, so reading everything back is the rare path).
fn host_error(inputs: &GaussianTensors<CubeBackend>) -> SplatError {
    let (means, log_scales, quats) = (
        host(&inputs.means),
        host(&inputs.log_scales),
        host(&inputs.quats),
    );
    let (opacity_logits, sh) = (host(&inputs.opacity_logits), host(&inputs.sh));
    let slices = GaussianSlices {
        means: &means,
        log_scales: &log_scales,
        quats: &quats,
        opacity_logits: &opacity_logits,
        sh: &sh,
    };
    slices
        .validate()
        .and_then(|()| check_finite("background", &host(&inputs.background)))
        .err()
        .unwrap_or(SplatError::NonFinite {
            name: "inputs",
            index: 0,
            value: f64::NAN,
        })
}

impl SplatBackend for CubeBackend {
    fn splat_forward(
        inputs: GaussianTensors<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> SplatForward<Self> {
        let device = inputs.means.device.clone();
        let checked = camera
            .validate()
            .map_err(SplatError::from)
            .and_then(|()| options.validate())
            .and_then(|()| check_shapes(&inputs));
        if let Err(error) = checked {
            return rejected(error, &device, DType::F32);
        }
        let inputs = f32_inputs(&inputs);
        let client = inputs.means.client.clone();
        let flag = CubeBackend::int_zeros(Shape::new([1]), &device, IntDType::I32);
        for t in [
            &inputs.means,
            &inputs.log_scales,
            &inputs.quats,
            &inputs.opacity_logits,
            &inputs.sh,
            &inputs.background,
        ] {
            let len = t.meta.shape().num_elements();
            if len > 0 {
                kernels::flag_non_finite::launch(
                    &client,
                    grid(len.div_ceil(UNITS), MAX_ROW),
                    CubeDim::new_1d(UNITS as u32),
                    t.clone().into_tensor_arg(),
                    flag.clone().into_tensor_arg(),
                );
            }
        }
        let projection: Projection = project(&inputs, &camera);
        let depth = depth_order(&projection);
        // The render's one readback: the input check, the intersection count and the same
        // count summed in f32 in units of 1024 (the i32 scan wraps past i32::MAX; this does not).
        let read = if depth.total.meta.shape()[0] == 0 {
            // No Gaussians: nothing to count, but the background must still be finite.
            vec![read_count(flag)[0], 0, 0]
        } else {
            let coarse = CubeBackend::float_into_int(
                CubeBackend::float_div_scalar(
                    CubeBackend::float_sum(CubeBackend::int_into_float(
                        projection.tiles.clone(),
                        FloatDType::F32,
                    )),
                    1024.0f64.into(),
                ),
                IntDType::I32,
            );
            read_count(CubeBackend::int_cat(
                vec![flag, depth.total.clone(), coarse],
                0,
            ))
        };
        if read[0] != 0 {
            return rejected(host_error(&inputs), &device, DType::F32);
        }
        let coarse = read[2] as u64 * 1024;
        // f32 rounding of the sum is far below the 2²⁵ margin.
        if coarse + (1 << 25) > MAX_INTERSECTIONS {
            let error = SplatError::Intersections {
                count: coarse.max(read[1] as u64),
                limit: MAX_INTERSECTIONS,
            };
            return rejected(error, &device, DType::F32);
        }
        let bins = bin_tiles(&projection, &depth, read[1], camera.width, camera.height);
        let raster = rasterize(
            &projection.screen,
            &projection.radii,
            &bins,
            &inputs.background,
            camera.width,
            camera.height,
            options.alpha_max,
        );
        SplatForward {
            image: raster.image,
            state: RasterState {
                screen: projection.screen,
                radii: projection.radii,
                tile_offsets: bins.offsets,
                tile_ids: bins.ids,
                final_transmittance: raster.final_transmittance,
                n_contrib: raster.n_contrib,
            },
            error: None,
        }
    }

    fn splat_backward(
        inputs: GaussianTensors<Self>,
        state: RasterState<Self>,
        grad_image: FloatTensor<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> GaussianTensors<Self> {
        let dtype = inputs.means.dtype;
        let inputs = f32_inputs(&inputs);
        let count = state.tile_ids.meta.shape()[0];
        let bins = TileBins {
            offsets: state.tile_offsets,
            ids: state.tile_ids,
            count,
        };
        let (screen_grads, background) = rasterize_backward(
            &state.screen,
            &state.radii,
            &bins,
            &inputs.background,
            &state.final_transmittance,
            &state.n_contrib,
            &f32_contiguous(&grad_image),
            camera.width,
            camera.height,
            options.alpha_max,
            Accumulation::best(&inputs.means.client),
        );
        let mut grads =
            project_backward(&inputs, &camera, &state.screen, &state.radii, &screen_grads);
        grads.background = background;
        if dtype == burn::tensor::DType::F32 {
            return grads;
        }
        grads.map_tensors(|t| CubeBackend::float_cast(t, dtype.into()))
    }
}
