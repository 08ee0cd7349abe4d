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
        let inner = inputs.map_tensors(|t| t.into_primitive());
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
                    // The state is saved as plain, untracked tensors.
                    state: out.state.map_tensors(Autodiff::<B, C>::from_inner, |t| t),
                    error: out.error,
                }
            }
            OpsKind::UnTracked(prep) => {
                let out = B::splat_forward(inner, camera, options);
                SplatForward {
                    image: prep.finish(out.image),
                    state: out.state.map_tensors(Autodiff::<B, C>::from_inner, |t| t),
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
        B::splat_backward(
            inputs.map_tensors(|t| t.into_primitive()),
            state.map_tensors(|t| t.into_primitive(), |t| t),
            grad_image.into_primitive(),
            camera,
            options,
        )
        .map_tensors(Autodiff::<B, C>::from_inner)
    }
}
