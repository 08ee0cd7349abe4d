//! [`SplatBackend`] for Burn's `fusion` feature (`Cube` is then `Fusion<CubeBackend>`): the
//! op runs eagerly on the unfused backend between fused blocks.
//!
//! Why eager, not a lazy custom operation: the forward's output shapes depend on the data —
//! the tile list is as long as the intersection count, which only a readback knows — and the
//! forward reads back anyway (the count and the input check). So both directions flush the
//! streams their inputs are on, call `CubeBackend`'s implementation on the resolved tensors,
//! and hand the results to the fusion client as fresh tensors, as Burn's own
//! `float_from_data` does. Fusion carries on around the op; the op itself is never fused.

use burn::backend::TensorMetadata;
use burn::backend::fusion::stream::StreamId;
use burn::backend::fusion::{Client, Fusion, FusionBackend, FusionHandle, FusionTensor, NoOp};
use burn::backend::ir::{BackendIr, InitOperationIr, OperationIr, OperationOutput};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;

use super::{GaussianTensors, RasterState, SplatBackend, SplatForward};
use crate::{Camera, RenderOptions};

type Runtime = <CubeBackend as FusionBackend>::FusionRuntime;

/// The unfused tensor behind a fused float tensor, once every queued operation on its stream
/// has run.
fn float(t: FusionTensor<Runtime>) -> FloatTensor<CubeBackend> {
    t.client.clone().resolve_tensor_float::<CubeBackend>(t)
}

fn int(t: FusionTensor<Runtime>) -> IntTensor<CubeBackend> {
    t.client.clone().resolve_tensor_int::<CubeBackend>(t)
}

/// An unfused tensor handed to the fusion client as a new tensor on the current stream.
fn register(
    client: &Client<Runtime>,
    shape: Shape,
    dtype: DType,
    handle: FusionHandle<Runtime>,
) -> FusionTensor<Runtime> {
    let desc = InitOperationIr::create(shape, dtype, || client.register_tensor_handle(handle));
    client
        .register(
            StreamId::current(),
            OperationIr::Init(desc),
            NoOp::<CubeBackend>::new(),
        )
        .output()
}

fn fused_float(client: &Client<Runtime>, t: FloatTensor<CubeBackend>) -> FusionTensor<Runtime> {
    let (shape, dtype) = (t.shape(), t.dtype());
    register(client, shape, dtype, CubeBackend::float_tensor_handle(t))
}

fn fused_int(client: &Client<Runtime>, t: IntTensor<CubeBackend>) -> FusionTensor<Runtime> {
    let (shape, dtype) = (t.shape(), t.dtype());
    register(client, shape, dtype, CubeBackend::int_tensor_handle(t))
}

impl SplatBackend for Fusion<CubeBackend> {
    fn splat_forward(
        inputs: GaussianTensors<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> SplatForward<Self> {
        let client = inputs.means.client.clone();
        let out = CubeBackend::splat_forward(inputs.map_tensors(float), camera, options);
        SplatForward {
            image: fused_float(&client, out.image),
            state: out
                .state
                .map_tensors(|t| fused_float(&client, t), |t| fused_int(&client, t)),
            error: out.error,
        }
    }

    fn splat_backward(
        inputs: GaussianTensors<Self>,
        state: RasterState<Self>,
        grad_image: FloatTensor<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> GaussianTensors<Self> {
        let client = inputs.means.client.clone();
        CubeBackend::splat_backward(
            inputs.map_tensors(float),
            state.map_tensors(float, int),
            float(grad_image),
            camera,
            options,
        )
        .map_tensors(|t| fused_float(&client, t))
    }
}
