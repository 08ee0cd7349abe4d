//! `impl FusedBackend for Autodiff<B>`: one graph node per fused op, whose backward calls the
//! inner backend's gradient op; the backward ops themselves are not differentiated again.

use std::any::Any;
use std::cell::RefCell;
use std::sync::{Arc, Mutex};

use burn::backend::autodiff::{
    Autodiff, NodeId,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, NodeGuard, Ops, OpsKind},
};
use burn::backend::tensor::FloatTensor;
use burn::backend::{AutodiffBackend, Backend, TensorMetadata};

use super::{FusedBackend, LinearScales};
use crate::gate::{Stash, gate, lock};

/// An activation's gate launch ([`crate::gate`]): the bias and noise-strength sums the pass
/// queued (`FusedBackend::bias_leaky_relu_backward_queue`).
fn launch_bias_sums<B: FusedBackend>(anchor: FloatTensor<B>) {
    B::bias_grads_launch_queued(anchor);
}

#[derive(Debug)]
struct BiasLeakyReluBackward;

impl<B: Backend + FusedBackend> Backward<B, 2> for BiasLeakyReluBackward {
    /// The op's output (its sign gives the slope), the input scale, the slope, the gain and
    /// the bias gate's stash.
    type State = (FloatTensor<B>, f32, f32, f32, Stash<B, 1>);

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (output, input_scale, slope, gain, stash) = ops.state;
        let [x_node, gate_node] = ops.parents;
        let dx = if gate_node.is_some() {
            let (dx, d_bias) =
                B::bias_leaky_relu_backward_queue(output, grad, input_scale, slope, gain);
            *lock(&stash) = Some([d_bias]);
            dx
        } else {
            B::bias_leaky_relu_grad(output, grad, slope, gain * input_scale)
        };
        if let Some(node) = x_node {
            grads.register::<B>(node.id, dx);
        }
    }
}

#[derive(Debug)]
struct NoisyBiasLeakyReluBackward;

impl<B: Backend + FusedBackend> Backward<B, 3> for NoisyBiasLeakyReluBackward {
    /// The op's output (its sign gives the slope), the noise, the strength, the slope, the gain
    /// and the gate's stash (bias, strength).
    type State = (
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        f32,
        f32,
        Stash<B, 2>,
    );

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (output, noise, strength, slope, gain, stash) = ops.state;
        let [x_node, noise_node, gate_node] = ops.parents;
        let pre_activation = if gate_node.is_some() {
            // The networks learn both: one pass for the three gradients.
            let (pre_activation, d_bias, d_strength) =
                B::noisy_bias_leaky_relu_backward_queue(output, grad, noise, slope, gain);
            *lock(&stash) = Some([d_bias, d_strength]);
            pre_activation
        } else {
            B::bias_leaky_relu_grad(output, grad, slope, gain)
        };
        if let Some(node) = noise_node {
            // The fixed noise maps never ask for it; any other caller gets it exactly.
            let per_pixel = B::float_sum_dim(B::float_sum_dim(pre_activation.clone(), 0), 1);
            let d_noise = B::float_mul(
                per_pixel,
                B::float_reshape(strength, burn::tensor::Shape::new([1, 1, 1, 1])),
            );
            grads.register::<B>(node.id, d_noise);
        }
        if let Some(node) = x_node {
            grads.register::<B>(node.id, pre_activation);
        }
    }
}

/// An op that changes only how values are stored: the gradient passes through.
#[derive(Debug)]
struct PassThroughBackward;

impl<B: Backend + FusedBackend> Backward<B, 1> for PassThroughBackward {
    type State = ();

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        if let [Some(node)] = ops.parents {
            grads.register::<B>(node.id, grad);
        }
    }
}

#[derive(Debug)]
struct Upsample2Backward;

impl<B: Backend + FusedBackend> Backward<B, 1> for Upsample2Backward {
    type State = ();

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        if let [Some(node)] = ops.parents {
            grads.register::<B>(node.id, B::upsample2_grad(grad));
        }
    }
}

/// The backward of a one-input op whose adjoint is an op of the gradient and two sizes kept
/// from the forward (the 2 × 2 mean's and the resize's: the input's height and width; the
/// blur's: the padding that undoes the forward's).
struct AdjointBackward<B: Backend> {
    adjoint: fn(FloatTensor<B>, usize, usize) -> FloatTensor<B>,
}

impl<B: Backend> std::fmt::Debug for AdjointBackward<B> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("AdjointBackward")
    }
}

impl<B: Backend> Backward<B, 1> for AdjointBackward<B> {
    /// The adjoint's two sizes.
    type State = (usize, usize);

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (a, b) = ops.state;
        if let [Some(node)] = ops.parents {
            grads.register::<B>(node.id, (self.adjoint)(grad, a, b));
        }
    }
}

/// `out`, computed from the tensor of `nodes`, on the graph with [`AdjointBackward`].
fn with_adjoint<B: Backend, C: CheckpointStrategy>(
    nodes: [NodeGuard; 1],
    out: FloatTensor<B>,
    adjoint: fn(FloatTensor<B>, usize, usize) -> FloatTensor<B>,
    sizes: (usize, usize),
) -> FloatTensor<Autodiff<B, C>> {
    let backward = AdjointBackward { adjoint };
    match backward.prepare::<C>(nodes).compute_bound().stateful() {
        OpsKind::Tracked(prep) => prep.finish(sizes, out),
        OpsKind::UnTracked(prep) => prep.finish(out),
    }
}

/// Haar analysis (`inverse: false`) or synthesis: orthonormal, so each one's backward is the
/// other.
#[derive(Debug)]
struct HaarBackward {
    inverse: bool,
}

impl<B: Backend + FusedBackend> Backward<B, 1> for HaarBackward {
    type State = ();

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        if let [Some(node)] = ops.parents {
            let dx = if self.inverse {
                // A network's last op: its output's gradient arrives in any layout; on a GPU the
                // analysis writes it channels-last, as the ToRGBs' convolutions read it.
                B::haar(grad)
            } else {
                B::inverse_haar(grad)
            };
            grads.register::<B>(node.id, dx);
        }
    }
}

#[derive(Debug)]
struct ToRgbOutputBackward;

impl<B: Backend + FusedBackend> Backward<B, 3> for ToRgbOutputBackward {
    type State = ();

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let [x_node, bias_node, skip_node] = ops.parents;
        if let Some(node) = skip_node {
            grads.register::<B>(node.id, B::to_rgb_skip_grad(grad.clone()));
        }
        if let Some(node) = bias_node {
            grads.register::<B>(node.id, B::channel_sum(grad.clone()));
        }
        if let Some(node) = x_node {
            grads.register::<B>(node.id, grad);
        }
    }
}

#[derive(Debug)]
struct AddChannelBiasBackward;

impl<B: Backend + FusedBackend> Backward<B, 2> for AddChannelBiasBackward {
    type State = ();

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let [x_node, bias_node] = ops.parents;
        if let Some(node) = bias_node {
            grads.register::<B>(node.id, B::channel_sum(grad.clone()));
        }
        if let Some(node) = x_node {
            grads.register::<B>(node.id, grad);
        }
    }
}

#[derive(Debug)]
struct CatChannelsBackward;

impl<B: Backend + FusedBackend> Backward<B, 2> for CatChannelsBackward {
    /// The first input's channels.
    type State = usize;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (first, second) = B::split_channels(grad, ops.state);
        let [first_node, second_node] = ops.parents;
        if let Some(node) = first_node {
            grads.register::<B>(node.id, first);
        }
        if let Some(node) = second_node {
            grads.register::<B>(node.id, second);
        }
    }
}

#[derive(Debug)]
struct ModulateBackward;

impl<B: Backend + FusedBackend> Backward<B, 2> for ModulateBackward {
    /// The weight and the styles, where the layer's begin, the scale and whether the op
    /// demodulates.
    type State = (FloatTensor<B>, FloatTensor<B>, usize, f32, bool);

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (weight, styles, first, scale, demodulate) = ops.state;
        let (d_weight, d_style) = B::modulate_grad(weight, styles, grad, first, scale, demodulate);
        let [weight_node, style_node] = ops.parents;
        if let Some(node) = weight_node {
            grads.register::<B>(node.id, d_weight);
        }
        if let Some(node) = style_node {
            grads.register::<B>(node.id, d_style);
        }
    }
}

/// The layers of one [`FusedBackend::modulate_launch_queued`] batch (a network's modulated
/// convolutions, `fused::modulate_all`), whose gradients are computed together: each layer's
/// node ([`ModulateLayerBackward`]) leaves its output's gradient here, and the batch's gate
/// node ([`ModulationGateBackward`]), between the styles and every layer, computes them all in
/// one queue and launch. The gate runs after every layer's node (Burn runs a graph's steps from
/// the highest order down, and each layer's order is above the gate's) and before the styles'
/// node, so the styles get one gradient where the autodiff summed one per layer (on a GPU a
/// layer's three launches and a network's ≈ 30 sums became three launches per network;
/// issue #47).
struct ModulationBatch<B: Backend> {
    styles: FloatTensor<B>,
    layers: Vec<BatchedLayer<B>>,
    /// Whether a layer computed its gradients at once and registered its styles' share on the
    /// gate ([`ModulateLayerBackward`]).
    gate_has_gradient: bool,
}

/// A layer of a [`ModulationBatch`]: its weight and place in the styles, and once its node's
/// backward has run, its output's gradient and its weight's node.
struct BatchedLayer<B: Backend> {
    weight: FloatTensor<B>,
    first: usize,
    scale: f32,
    demodulate: bool,
    pending: Option<(FloatTensor<B>, Option<NodeId>)>,
}

type SharedBatch<B> = Arc<Mutex<ModulationBatch<B>>>;

impl<B: Backend> std::fmt::Debug for ModulationBatch<B> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ModulationBatch")
            .field("layers", &self.layers.len())
            .field("gate_has_gradient", &self.gate_has_gradient)
            .finish()
    }
}

/// The batch being queued on this thread: the styles' node, the gate and the batch.
struct OpenBatch<B: Backend, C: CheckpointStrategy> {
    styles: NodeId,
    gate: Gate<B, C>,
    batch: SharedBatch<B>,
}

/// A batch's gate tensor (the styles, passed through its node).
type Gate<B, C> = FloatTensor<Autodiff<B, C>>;

thread_local! {
    /// An `OpenBatch<B, C>` from the first `modulate_queue` of tracked styles until
    /// `modulate_launch_queued`.
    static OPEN_BATCH: RefCell<Option<Box<dyn Any>>> = const { RefCell::new(None) };
}

/// The gate and batch of `styles`' layers: the open batch if it belongs to `styles`, else a new
/// one; `None` where `styles` needs no gradient (each layer then gets its own node).
fn open_batch<B: FusedBackend, C: CheckpointStrategy>(
    styles: &Gate<B, C>,
) -> Option<(Gate<B, C>, SharedBatch<B>)> {
    OPEN_BATCH.with(|open| {
        let mut open = open.borrow_mut();
        if let Some(current) = open
            .as_ref()
            .and_then(|b| b.downcast_ref::<OpenBatch<B, C>>())
            .filter(|b| b.styles == styles.id())
        {
            return Some((current.gate.clone(), current.batch.clone()));
        }
        let batch = Arc::new(Mutex::new(ModulationBatch {
            styles: styles.primitive().clone(),
            layers: Vec::new(),
            gate_has_gradient: false,
        }));
        let gate = match ModulationGateBackward
            .prepare::<C>([styles.node()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(batch.clone(), styles.primitive().clone()),
            OpsKind::UnTracked(_) => {
                *open = None;
                return None;
            }
        };
        *open = Some(Box::new(OpenBatch::<B, C> {
            styles: styles.id(),
            gate: gate.clone(),
            batch: batch.clone(),
        }));
        Some((gate, batch))
    })
}

/// A batched layer's node: parents the weight and the batch's gate.
#[derive(Debug)]
struct ModulateLayerBackward;

impl<B: Backend + FusedBackend> Backward<B, 2> for ModulateLayerBackward {
    /// The batch and the layer's index in it.
    type State = (SharedBatch<B>, usize);

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (batch, index) = ops.state;
        let mut batch = lock(&batch);
        let [weight_node, gate_node] = ops.parents;
        match weight_node {
            // A weight made by other ops (order above 0) may have its own step run before the
            // gate's: its gradient is computed and registered now, the styles' share on the gate.
            Some(node) if node.order > 0 => {
                let layer = &batch.layers[index];
                let (d_weight, d_styles) = B::modulate_grad(
                    layer.weight.clone(),
                    batch.styles.clone(),
                    grad,
                    layer.first,
                    layer.scale,
                    layer.demodulate,
                );
                grads.register::<B>(node.id, d_weight);
                if let Some(gate) = gate_node {
                    grads.register::<B>(gate.id, d_styles);
                    batch.gate_has_gradient = true;
                }
            }
            weight_node => batch.layers[index].pending = Some((grad, weight_node.map(|n| n.id))),
        }
    }
}

/// A batch's gate: the styles passed through, its backward the batch's gradients.
#[derive(Debug)]
struct ModulationGateBackward;

impl<B: Backend + FusedBackend> Backward<B, 1> for ModulationGateBackward {
    type State = SharedBatch<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let mut batch = lock(&ops.state);
        let styles = batch.styles.clone();
        let mut weight_grads = Vec::new();
        let mut queued = false;
        for layer in &mut batch.layers {
            if let Some((grad, weight_node)) = layer.pending.take() {
                let d_weight = B::modulate_grad_queue(
                    layer.weight.clone(),
                    styles.clone(),
                    grad,
                    layer.first,
                    layer.scale,
                    layer.demodulate,
                );
                weight_grads.extend(weight_node.map(|id| (id, d_weight)));
                queued = true;
            }
        }
        let mut d_styles = queued.then(|| B::modulate_grad_launch_queued(styles));
        // Registered after the launch: a sum with an earlier gradient reads them.
        for (id, d_weight) in weight_grads {
            grads.register::<B>(id, d_weight);
        }
        if batch.gate_has_gradient {
            let at_once = grads.consume::<B>(&ops.node);
            d_styles = Some(match d_styles {
                Some(d) => B::float_add(d, at_once),
                None => at_once,
            });
        }
        if let ([Some(node)], Some(d_styles)) = (ops.parents, d_styles) {
            grads.register::<B>(node.id, d_styles);
        }
    }
}

#[derive(Debug)]
struct ScaleWeightBackward;

impl<B: Backend + FusedBackend> Backward<B, 1> for ScaleWeightBackward {
    /// The scale.
    type State = f32;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        if let [Some(node)] = ops.parents {
            grads.register::<B>(node.id, B::scale_weight_grad(grad, ops.state));
        }
    }
}

#[derive(Debug)]
struct LinearBackward;

impl<B: Backend + FusedBackend> Backward<B, 3> for LinearBackward {
    /// The input, the weight, the op's output (its sign gives the activation's slope) and the
    /// scalars.
    type State = (FloatTensor<B>, FloatTensor<B>, FloatTensor<B>, LinearScales);

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (x, weight, output, scales) = ops.state;
        let (d_x, d_weight, d_bias) = B::scaled_linear_grad(x, weight, output, grad, scales);
        let [x_node, weight_node, bias_node] = ops.parents;
        for (node, d) in [(x_node, d_x), (weight_node, d_weight), (bias_node, d_bias)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, d);
            }
        }
    }
}

#[derive(Debug)]
struct LpipsDistanceBackward;

impl<B: Backend + FusedBackend> Backward<B, 2> for LpipsDistanceBackward {
    /// The two feature maps and the head's weights (a constant).
    type State = (FloatTensor<B>, FloatTensor<B>, FloatTensor<B>);

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (x, y, weight) = ops.state;
        let [x_node, y_node] = ops.parents;
        if let Some(node) = y_node {
            let d_y = B::lpips_distance_grad(y.clone(), x.clone(), weight.clone(), grad.clone());
            grads.register::<B>(node.id, d_y);
        }
        if let Some(node) = x_node {
            grads.register::<B>(node.id, B::lpips_distance_grad(x, y, weight, grad));
        }
    }
}

impl<B: Backend + FusedBackend, C: CheckpointStrategy> FusedBackend for Autodiff<B, C> {
    fn bias_leaky_relu(
        x: FloatTensor<Self>,
        input_scale: f32,
        bias: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self> {
        let (gate, stash) = gate::<B, C, 1>([&bias], launch_bias_sums::<B>);
        let nodes = [x.node(), gate.node()];
        let out = B::bias_leaky_relu(
            x.into_primitive(),
            input_scale,
            bias.into_primitive(),
            slope,
            gain,
        );
        match BiasLeakyReluBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                prep.finish((out.clone(), input_scale, slope, gain, stash), out)
            }
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    fn noisy_bias_leaky_relu(
        x: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        strength: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self> {
        let (gate, stash) = gate::<B, C, 2>([&bias, &strength], launch_bias_sums::<B>);
        let nodes = [x.node(), noise.node(), gate.node()];
        let (noise, strength) = (noise.into_primitive(), strength.into_primitive());
        let out = B::noisy_bias_leaky_relu(
            x.into_primitive(),
            noise.clone(),
            strength.clone(),
            bias.into_primitive(),
            slope,
            gain,
        );
        match NoisyBiasLeakyReluBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                prep.finish((out.clone(), noise, strength, slope, gain, stash), out)
            }
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    fn noise_strength_grad(grad: FloatTensor<Self>, noise: FloatTensor<Self>) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::noise_strength_grad(
            grad.into_primitive(),
            noise.into_primitive(),
        ))
    }

    fn bias_leaky_relu_grad(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::bias_leaky_relu_grad(
            output.into_primitive(),
            grad.into_primitive(),
            slope,
            gain,
        ))
    }

    fn channel_sum(x: FloatTensor<Self>) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::channel_sum(x.into_primitive()))
    }

    fn bias_leaky_relu_backward_queue(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        input_scale: f32,
        slope: f32,
        gain: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let (dx, d_bias) = B::bias_leaky_relu_backward_queue(
            output.into_primitive(),
            grad.into_primitive(),
            input_scale,
            slope,
            gain,
        );
        (
            Autodiff::<B, C>::from_inner(dx),
            Autodiff::<B, C>::from_inner(d_bias),
        )
    }

    fn noisy_bias_leaky_relu_backward_queue(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let (dx, d_bias, d_strength) = B::noisy_bias_leaky_relu_backward_queue(
            output.into_primitive(),
            grad.into_primitive(),
            noise.into_primitive(),
            slope,
            gain,
        );
        (
            Autodiff::<B, C>::from_inner(dx),
            Autodiff::<B, C>::from_inner(d_bias),
            Autodiff::<B, C>::from_inner(d_strength),
        )
    }

    fn bias_grads_launch_queued(anchor: FloatTensor<Self>) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::bias_grads_launch_queued(anchor.into_primitive()))
    }

    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let nodes = [x.node()];
        Upsample2Backward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateless(B::upsample2(x.into_primitive()))
    }

    fn upsample2_grad(grad: FloatTensor<Self>) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::upsample2_grad(grad.into_primitive()))
    }

    fn downsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let nodes = [x.node()];
        let [.., height, width] = x.shape().dims::<4>();
        let out = B::downsample2(x.into_primitive());
        with_adjoint::<B, C>(nodes, out, B::downsample2_grad, (height, width))
    }

    fn downsample2_grad(grad: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::downsample2_grad(grad.into_primitive(), height, width))
    }

    fn resize(x: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self> {
        let nodes = [x.node()];
        let [.., h, w] = x.shape().dims::<4>();
        let out = B::resize(x.into_primitive(), height, width);
        with_adjoint::<B, C>(nodes, out, B::resize_grad, (h, w))
    }

    fn resize_grad(grad: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::resize_grad(grad.into_primitive(), height, width))
    }

    fn blur(x: FloatTensor<Self>, before: usize, after: usize) -> FloatTensor<Self> {
        let nodes = [x.node()];
        let out = B::blur(x.into_primitive(), before, after);
        // The blur's adjoint is the blur padded by what the forward's padding leaves of 3.
        with_adjoint::<B, C>(nodes, out, B::blur, (3 - before, 3 - after))
    }

    fn haar(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let nodes = [x.node()];
        HaarBackward { inverse: false }
            .prepare::<C>(nodes)
            .compute_bound()
            .stateless(B::haar(x.into_primitive()))
    }

    fn to_channels_last(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let nodes = [x.node()];
        PassThroughBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateless(B::to_channels_last(x.into_primitive()))
    }

    fn inverse_haar(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let nodes = [x.node()];
        HaarBackward { inverse: true }
            .prepare::<C>(nodes)
            .compute_bound()
            .stateless(B::inverse_haar(x.into_primitive()))
    }

    fn to_rgb_output(
        x: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        skip: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let nodes = [x.node(), bias.node(), skip.node()];
        ToRgbOutputBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateless(B::to_rgb_output(
                x.into_primitive(),
                bias.into_primitive(),
                skip.into_primitive(),
            ))
    }

    fn to_rgb_skip_grad(grad: FloatTensor<Self>) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::to_rgb_skip_grad(grad.into_primitive()))
    }

    fn add_channel_bias(x: FloatTensor<Self>, bias: FloatTensor<Self>) -> FloatTensor<Self> {
        let nodes = [x.node(), bias.node()];
        AddChannelBiasBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateless(B::add_channel_bias(
                x.into_primitive(),
                bias.into_primitive(),
            ))
    }

    fn cat_channels(first: FloatTensor<Self>, second: FloatTensor<Self>) -> FloatTensor<Self> {
        let channels = first.shape().dims::<4>()[1];
        let nodes = [first.node(), second.node()];
        let out = B::cat_channels(first.into_primitive(), second.into_primitive());
        match CatChannelsBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(channels, out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    fn split_channels(
        grad: FloatTensor<Self>,
        first: usize,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let (a, b) = B::split_channels(grad.into_primitive(), first);
        (
            Autodiff::<B, C>::from_inner(a),
            Autodiff::<B, C>::from_inner(b),
        )
    }

    fn modulate_queue(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> FloatTensor<Self> {
        if let Some((gate, batch)) = open_batch::<B, C>(&styles) {
            let nodes = [weight.node(), gate.node()];
            let weight = weight.into_primitive();
            let out = B::modulate_queue(
                weight.clone(),
                gate.into_primitive(),
                first,
                scale,
                demodulate,
            );
            let index = {
                let mut open = lock(&batch);
                open.layers.push(BatchedLayer {
                    weight,
                    first,
                    scale,
                    demodulate,
                    pending: None,
                });
                open.layers.len() - 1
            };
            return match ModulateLayerBackward
                .prepare::<C>(nodes)
                .compute_bound()
                .stateful()
            {
                OpsKind::Tracked(prep) => prep.finish((batch, index), out),
                OpsKind::UnTracked(prep) => prep.finish(out),
            };
        }
        let nodes = [weight.node(), styles.node()];
        let (weight, styles) = (weight.into_primitive(), styles.into_primitive());
        let out = B::modulate_queue(weight.clone(), styles.clone(), first, scale, demodulate);
        match ModulateBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((weight, styles, first, scale, demodulate), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    fn modulate_launch_queued(styles: FloatTensor<Self>) -> FloatTensor<Self> {
        OPEN_BATCH.with(|open| open.borrow_mut().take());
        Autodiff::<B, C>::from_inner(B::modulate_launch_queued(styles.into_primitive()))
    }

    fn modulate_grad(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let (d_weight, d_style) = B::modulate_grad(
            weight.into_primitive(),
            styles.into_primitive(),
            grad.into_primitive(),
            first,
            scale,
            demodulate,
        );
        (
            Autodiff::<B, C>::from_inner(d_weight),
            Autodiff::<B, C>::from_inner(d_style),
        )
    }

    fn modulate_grad_queue(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::modulate_grad_queue(
            weight.into_primitive(),
            styles.into_primitive(),
            grad.into_primitive(),
            first,
            scale,
            demodulate,
        ))
    }

    fn modulate_grad_launch_queued(styles: FloatTensor<Self>) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::modulate_grad_launch_queued(styles.into_primitive()))
    }

    fn scale_weight(weight: FloatTensor<Self>, scale: f32) -> FloatTensor<Self> {
        let nodes = [weight.node()];
        let out = B::scale_weight(weight.into_primitive(), scale);
        match ScaleWeightBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(scale, out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    fn scale_weight_grad(grad: FloatTensor<Self>, scale: f32) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::scale_weight_grad(grad.into_primitive(), scale))
    }

    fn scaled_linear(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        scales: LinearScales,
    ) -> FloatTensor<Self> {
        let nodes = [x.node(), weight.node(), bias.node()];
        let (x, weight) = (x.into_primitive(), weight.into_primitive());
        let out = B::scaled_linear(x.clone(), weight.clone(), bias.into_primitive(), scales);
        match LinearBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((x, weight, out.clone(), scales), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    fn scaled_linear_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        scales: LinearScales,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let (d_x, d_weight, d_bias) = B::scaled_linear_grad(
            x.into_primitive(),
            weight.into_primitive(),
            output.into_primitive(),
            grad.into_primitive(),
            scales,
        );
        (
            Autodiff::<B, C>::from_inner(d_x),
            Autodiff::<B, C>::from_inner(d_weight),
            Autodiff::<B, C>::from_inner(d_bias),
        )
    }

    fn lpips_distance(
        x: FloatTensor<Self>,
        y: FloatTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let nodes = [x.node(), y.node()];
        let (x, y, weight) = (
            x.into_primitive(),
            y.into_primitive(),
            weight.into_primitive(),
        );
        let out = B::lpips_distance(x.clone(), y.clone(), weight.clone());
        match LpipsDistanceBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((x, y, weight), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    fn lpips_distance_grad(
        x: FloatTensor<Self>,
        y: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::lpips_distance_grad(
            x.into_primitive(),
            y.into_primitive(),
            weight.into_primitive(),
            grad.into_primitive(),
        ))
    }
}
