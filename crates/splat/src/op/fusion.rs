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

fn unfused(t: GaussianTensors<Fusion<CubeBackend>>) -> GaussianTensors<CubeBackend> {
    GaussianTensors {
        means: float(t.means),
        log_scales: float(t.log_scales),
        quats: float(t.quats),
        opacity_logits: float(t.opacity_logits),
        sh: float(t.sh),
        background: float(t.background),
    }
}

fn fused(
    client: &Client<Runtime>,
    t: GaussianTensors<CubeBackend>,
) -> GaussianTensors<Fusion<CubeBackend>> {
    GaussianTensors {
        means: fused_float(client, t.means),
        log_scales: fused_float(client, t.log_scales),
        quats: fused_float(client, t.quats),
        opacity_logits: fused_float(client, t.opacity_logits),
        sh: fused_float(client, t.sh),
        background: fused_float(client, t.background),
    }
}

impl SplatBackend for Fusion<CubeBackend> {
    fn splat_forward(
        inputs: GaussianTensors<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> SplatForward<Self> {
        let client = inputs.means.client.clone();
        let out = CubeBackend::splat_forward(unfused(inputs), camera, options);
        let state = out.state;
        SplatForward {
            image: fused_float(&client, out.image),
            state: RasterState {
                screen: fused_float(&client, state.screen),
                radii: fused_int(&client, state.radii),
                tile_offsets: fused_int(&client, state.tile_offsets),
                tile_ids: fused_int(&client, state.tile_ids),
                final_transmittance: fused_float(&client, state.final_transmittance),
                n_contrib: fused_int(&client, state.n_contrib),
            },
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
        let state = RasterState {
            screen: float(state.screen),
            radii: int(state.radii),
            tile_offsets: int(state.tile_offsets),
            tile_ids: int(state.tile_ids),
            final_transmittance: float(state.final_transmittance),
            n_contrib: int(state.n_contrib),
        };
        let grads =
            CubeBackend::splat_backward(unfused(inputs), state, float(grad_image), camera, options);
        fused(&client, grads)
    }
}
