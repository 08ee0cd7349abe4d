//! `impl FusedBackend for Autodiff<B>`: one graph node per fused op, whose backward calls the
//! inner backend's gradient op; the backward ops themselves are not differentiated again.

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::tensor::FloatTensor;
use burn::backend::{AutodiffBackend, Backend, TensorMetadata};

use super::{FusedBackend, LinearScales};

#[derive(Debug)]
struct BiasLeakyReluBackward;

impl<B: Backend + FusedBackend> Backward<B, 2> for BiasLeakyReluBackward {
    /// The op's output (its sign gives the slope), the input scale, the slope and the gain.
    type State = (FloatTensor<B>, f32, f32, f32);

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (output, input_scale, slope, gain) = ops.state;
        let [x_node, bias_node] = ops.parents;
        let dx = match bias_node {
            Some(node) => {
                let (dx, d_bias) =
                    B::bias_leaky_relu_backward(output, grad, input_scale, slope, gain);
                grads.register::<B>(node.id, d_bias);
                dx
            }
            None => B::bias_leaky_relu_grad(output, grad, slope, gain * input_scale),
        };
        if let Some(node) = x_node {
            grads.register::<B>(node.id, dx);
        }
    }
}

#[derive(Debug)]
struct NoisyBiasLeakyReluBackward;

impl<B: Backend + FusedBackend> Backward<B, 4> for NoisyBiasLeakyReluBackward {
    /// The op's output (its sign gives the slope), the noise, the strength, the slope and the
    /// gain.
    type State = (FloatTensor<B>, FloatTensor<B>, FloatTensor<B>, f32, f32);

    fn backward(
        self,
        ops: Ops<Self::State, 4>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (output, noise, strength, slope, gain) = ops.state;
        let [x_node, noise_node, strength_node, bias_node] = ops.parents;
        // The networks learn both: one pass for the three gradients.
        let (pre_activation, d_bias, d_strength) =
            B::noisy_bias_leaky_relu_backward(output, grad, noise, slope, gain);
        if let Some(node) = bias_node {
            grads.register::<B>(node.id, d_bias);
        }
        if let Some(node) = strength_node {
            grads.register::<B>(node.id, d_strength);
        }
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

#[derive(Debug)]
struct Downsample2Backward;

impl<B: Backend + FusedBackend> Backward<B, 1> for Downsample2Backward {
    /// The input's height and width.
    type State = (usize, usize);

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (height, width) = ops.state;
        if let [Some(node)] = ops.parents {
            grads.register::<B>(node.id, B::downsample2_grad(grad, height, width));
        }
    }
}

#[derive(Debug)]
struct BlurBackward;

impl<B: Backend + FusedBackend> Backward<B, 1> for BlurBackward {
    /// The forward's padding `(before, after)`.
    type State = (usize, usize);

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (before, after) = ops.state;
        if let [Some(node)] = ops.parents {
            grads.register::<B>(node.id, B::blur(grad, 3 - before, 3 - after));
        }
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
        let nodes = [x.node(), bias.node()];
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
            OpsKind::Tracked(prep) => prep.finish((out.clone(), input_scale, slope, gain), out),
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
        let nodes = [x.node(), noise.node(), strength.node(), bias.node()];
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
            OpsKind::Tracked(prep) => prep.finish((out.clone(), noise, strength, slope, gain), out),
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

    fn bias_leaky_relu_backward(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        input_scale: f32,
        slope: f32,
        gain: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let (dx, d_bias) = B::bias_leaky_relu_backward(
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

    fn noisy_bias_leaky_relu_backward(
        output: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        slope: f32,
        gain: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let (dx, d_bias, d_strength) = B::noisy_bias_leaky_relu_backward(
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
        match Downsample2Backward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((height, width), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    fn downsample2_grad(grad: FloatTensor<Self>, height: usize, width: usize) -> FloatTensor<Self> {
        Autodiff::<B, C>::from_inner(B::downsample2_grad(grad.into_primitive(), height, width))
    }

    fn blur(x: FloatTensor<Self>, before: usize, after: usize) -> FloatTensor<Self> {
        let nodes = [x.node()];
        let out = B::blur(x.into_primitive(), before, after);
        match BlurBackward.prepare::<C>(nodes).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish((before, after), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    fn haar(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let nodes = [x.node()];
        HaarBackward { inverse: false }
            .prepare::<C>(nodes)
            .compute_bound()
            .stateless(B::haar(x.into_primitive()))
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

    fn modulate(
        weight: FloatTensor<Self>,
        styles: FloatTensor<Self>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> FloatTensor<Self> {
        let nodes = [weight.node(), styles.node()];
        let (weight, styles) = (weight.into_primitive(), styles.into_primitive());
        let out = B::modulate(weight.clone(), styles.clone(), first, scale, demodulate);
        match ModulateBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((weight, styles, first, scale, demodulate), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
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
