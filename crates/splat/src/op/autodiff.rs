//! `impl SplatBackend for Autodiff<B>`: one graph node per render, whose backward calls
//! `B::splat_backward` with the state the forward saved.

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::tensor::FloatTensor;
use burn::backend::{AutodiffBackend, Backend};

use super::{GaussianTensors, RasterState, SplatBackend, SplatForward};
use crate::Camera;
use crate::semantics::RenderOptions;

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
