//! `impl ConvBackend for Autodiff<B>`: one graph node per convolution, whose backward computes
//! only the gradients its parents need (LPIPS's frozen weights get none). The weight reaches
//! the node through a gate ([`crate::gate`]): the node queues the weight's gradient
//! ([`ConvBackend::conv2d_weight_grad`]) and the gate launches the pass's queue and
//! registers it.

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::tensor::FloatTensor;
use burn::backend::{AutodiffBackend, Backend};
use burn::tensor::ops::ConvOptions;

use super::ConvBackend;
use crate::gate::{Stash, gate, lock};

/// Saved for the backward: the inner-backend input and weight, the options and the weight
/// gate's stash.
type Saved<B> = (FloatTensor<B>, FloatTensor<B>, ConvOptions<2>, Stash<B, 1>);

/// A convolution's gate launch ([`crate::gate`]): the weight gradients' sums the pass queued.
fn launch_weight_grads<B: ConvBackend>(anchor: FloatTensor<B>) {
    B::conv2d_weight_grads_launch_queued(anchor);
}

#[derive(Debug)]
struct Conv2dBackward;

impl<B: Backend + ConvBackend> Backward<B, 2> for Conv2dBackward {
    type State = Saved<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (x, weight, options, stash) = ops.state;
        let [x_node, gate_node] = ops.parents;
        if gate_node.is_some() {
            let weight_grad =
                B::conv2d_weight_grad(x.clone(), weight.clone(), grad.clone(), options.clone());
            *lock(&stash) = Some([weight_grad]);
        }
        if let Some(node) = x_node {
            grads.register::<B>(node.id, B::conv2d_input_grad(x, weight, grad, options));
        }
    }
}

impl<B: Backend + ConvBackend, C: CheckpointStrategy> ConvBackend for Autodiff<B, C> {
    fn conv2d_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        let (gate, stash) = gate::<B, C, 1>([&weight], launch_weight_grads::<B>);
        let nodes = [x.node(), gate.node()];
        let (x, weight) = (x.into_primitive(), weight.into_primitive());
        match Conv2dBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::conv2d_forward(x.clone(), weight.clone(), options.clone());
                prep.finish((x, weight, options, stash), out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::conv2d_forward(x, weight, options)),
        }
    }

    fn conv2d_input_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::conv2d_input_grad(
            x.into_primitive(),
            weight.into_primitive(),
            grad.into_primitive(),
            options,
        ))
    }

    fn conv2d_weight_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::conv2d_weight_grad(
            x.into_primitive(),
            weight.into_primitive(),
            grad.into_primitive(),
            options,
        ))
    }

    fn conv2d_weight_grads_launch_queued(anchor: FloatTensor<Self>) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::conv2d_weight_grads_launch_queued(
            anchor.into_primitive(),
        ))
    }
}
