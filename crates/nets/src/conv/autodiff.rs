//! `impl ConvBackend for Autodiff<B>`: one graph node per convolution, whose backward computes
//! only the gradients its parents need (LPIPS's frozen weights get none).

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

/// Saved for the backward: the inner-backend input and weight, and the options.
type Saved<B> = (FloatTensor<B>, FloatTensor<B>, ConvOptions<2>);

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
        let (x, weight, options) = ops.state;
        let [x_node, weight_node] = ops.parents;
        if let Some(node) = weight_node {
            let weight_grad =
                B::conv2d_weight_grad(x.clone(), weight.clone(), grad.clone(), options.clone());
            grads.register::<B>(node.id, weight_grad);
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
        let nodes = [x.node(), weight.node()];
        let (x, weight) = (x.into_primitive(), weight.into_primitive());
        match Conv2dBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::conv2d_forward(x.clone(), weight.clone(), options.clone());
                prep.finish((x, weight, options), out)
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
}
