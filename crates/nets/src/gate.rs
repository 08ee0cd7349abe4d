//! Gates: autodiff nodes that let one launch write the gradients of many ops' parameters.
//!
//! An op whose parameters' gradients are sums (an activation's bias, a convolution's weight
//! summed over its bands) takes its parameters through a gate node instead of directly. The op's
//! node computes its input's gradient at once and leaves the parameters' in the gate's stash,
//! *queued*: allocated, and on a GPU not yet written. The gate's step launches what the backward
//! pass has queued of its kind and then registers the gradients. A gate runs after its op's node
//! (the node's parent) and before its parameters' own steps; the gates of leaf parameters have
//! order 1 and Burn runs a graph's steps from the highest order down, so they run after every
//! op's node of the pass: the first launches every queued sum and the others find the queue
//! empty. A launch per op becomes one or a few per pass (issue #47), with no state across
//! graphs (each gate belongs to its op's graph).

use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use burn::backend::Backend;
use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::tensor::FloatTensor;

/// The gradients of an op's parameters, left by the op's node for its gate to register.
pub(crate) type Stash<B, const N: usize> = Arc<Mutex<Option<[FloatTensor<B>; N]>>>;

/// Writes what is queued of a gate's kind; takes a gradient of the stash (an anchor for the
/// backend's client).
pub(crate) type Launch<B> = fn(FloatTensor<B>);

#[derive(Debug)]
struct GateBackward<const N: usize>;

impl<B: Backend, const N: usize> Backward<B, N> for GateBackward<N> {
    type State = (Stash<B, N>, Launch<B>);

    fn backward(
        self,
        ops: Ops<Self::State, N>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let (stash, launch) = ops.state;
        let Some(gradients) = lock(&stash).take() else {
            return;
        };
        if let Some(first) = gradients.first() {
            launch(first.clone());
        }
        // Registered after the launch: a sum with an earlier gradient reads them.
        for (parent, gradient) in ops.parents.into_iter().zip(gradients) {
            if let Some(node) = parent {
                grads.register::<B>(node.id, gradient);
            }
        }
    }
}

/// The gate of `parameters` and its stash: the first parameter passed through (the op's node
/// takes it as its parent in the parameters' place), untracked (and the stash never filled)
/// where none needs a gradient. `launch` writes the queue the op's node fills.
pub(crate) fn gate<B: Backend, C: CheckpointStrategy, const N: usize>(
    parameters: [&FloatTensor<Autodiff<B, C>>; N],
    launch: Launch<B>,
) -> (FloatTensor<Autodiff<B, C>>, Stash<B, N>) {
    let stash = Arc::new(Mutex::new(None));
    let passed = parameters[0].primitive().clone();
    let gate = match GateBackward::<N>
        .prepare::<C>(parameters.map(|p| p.node()))
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish((stash.clone(), launch), passed),
        OpsKind::UnTracked(prep) => prep.finish(passed),
    };
    (gate, stash)
}

/// A stash's or batch's lock: a panic that poisoned it left nothing half-written that matters
/// here.
pub(crate) fn lock<T>(shared: &Mutex<T>) -> MutexGuard<'_, T> {
    shared.lock().unwrap_or_else(PoisonError::into_inner)
}
