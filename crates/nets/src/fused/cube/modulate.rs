//! StyleGAN2's modulated weight and its gradients: one cube per output channel, which sums the
//! demodulation's squares (and, backward, its projection) in shared memory; the style's
//! gradient a second kernel, one cube per input channel summing over output channels and taps
//! into the layer's range of the network's style vector (`fused::modulate_all`).
//!
//! A network's layers go together, each kernel taking up to [`MAX_PER_LAUNCH`] layers, a grid
//! layer each: the forward queues each layer (`modulate_queue`) and launches them with the
//! network's styles (`modulate_launch_queued`), the backward likewise
//! (`modulate_grad_queue`, `modulate_grad_launch_queued`, called by the autodiff's gate node,
//! `fused/autodiff.rs`), the queue-and-launch pattern of `crate::adam`'s shared launches. A
//! launch per layer and kernel, and the autodiff's sum of every layer's full-length style
//! gradient, were 714 of a `paper` step's 5 453 launches; they are 18 (issue #47). Every
//! kernel's barriers sit in control flow uniform over the cube (the grid layer picks the
//! branch; per-layer flags only select values), as WGSL requires.
//!
//! The modulated weight (and an equalised convolution's scaled weight, [`scale_weight`]) is
//! written channels-last (`[C_out, kh, kw, C_in]` in memory), the layout
//! Burn's implicit-GEMM convolution reads its weight in, forward and for the input gradient:
//! written row-major, each of those copied it first. Its gradient, which the weight-gradient
//! GEMM hands back channels-last, is read as it comes.

use std::cell::RefCell;

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::CubeDim;
use burn_cubecl::cubecl::prelude::SequenceArg;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;

use super::sum::{SUM_UNITS, one_cube_per_channel_in_layers};
use super::{dims, u32_of};
use crate::cube_grid::{UNITS, items_per_launch, one_thread_per_value};
use crate::cube_layout::{empty_in_layout, readable};
use crate::fused::DEMODULATION_EPSILON;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use super::super::sum::cube_sum;

    /// The buffer offset of value `j = i · taps + k` (input channel `i`, tap `k`) of the output
    /// channel at `base`: `base + j` row-major, `base + k · inputs + i` channels-last.
    #[cube]
    fn offset(base: u32, j: u32, taps: u32, inputs: u32, #[comptime] channels_last: bool) -> u32 {
        let mut at = base + j;
        if comptime![channels_last] {
            at = base + (j % taps) * inputs + j / taps;
        }
        at
    }

    /// The modulated weights of several layers, grid layer `CUBE_POS_Z` for layer `n`
    /// (`weights[n]`, `[C_out, C_in, kh, kw]`, into `outs[n]` channels-last), one cube per
    /// output channel `o` (`CUBE_POS_X`; cubes past the layer's channels write nothing):
    /// `u[o, j] = weight[o, j] · styles[firsts[n] + j / taps] · scales[n]`, times `(Σ_j u² +
    /// epsilon)^(−½)` where `demodulates[n]` is 1 (`j` over the channel's `C_in · taps` values).
    /// Every cube makes the sum of squares whatever its flag, so that the barriers sit in
    /// uniform control flow (the layer is the grid's, `n` a constant of each unrolled branch).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn modulate_many(
        weights: &Sequence<OwnedTensor<f32>>,
        styles: &Tensor<f32>,
        outs: &mut Sequence<OwnedTensor<f32>>,
        firsts: &Sequence<u32>,
        scales: &Sequence<f32>,
        demodulates: &Sequence<u32>,
        epsilon: f32,
        #[comptime] count: usize,
        #[comptime] units: u32,
    ) {
        let layer = CUBE_POS_Z as usize;
        let o = CUBE_POS_X;
        let t = UNIT_POS;
        let mut partial = Shared::<[f32]>::new_slice(comptime![units as usize]);
        #[unroll]
        for n in 0..count {
            if layer == n {
                let weight = weights.index(n);
                let taps = (weight.shape(2) * weight.shape(3)) as u32;
                let inputs = weight.shape(1) as u32;
                let per_output = inputs * taps;
                let mut terms = 0u32;
                if o < weight.shape(0) as u32 {
                    terms = per_output;
                }
                let first = *firsts.index(n);
                let scale = *scales.index(n);
                let base = o * per_output;
                let mut sum = 0.0f32;
                let mut j = t;
                while j < terms {
                    let u =
                        weight[(base + j) as usize] * styles[(first + j / taps) as usize] * scale;
                    sum += u * u;
                    j += units;
                }
                partial[t as usize] = sum;
                cube_sum(&mut partial, units);
                let mut d = 1.0f32;
                if *demodulates.index(n) == 1 {
                    d = 1.0 / f32::sqrt(partial[0] + epsilon);
                }
                let out = outs.index_mut(n);
                let mut j = t;
                while j < terms {
                    let u =
                        weight[(base + j) as usize] * styles[(first + j / taps) as usize] * scale;
                    out[offset(base, j, taps, inputs, true) as usize] = u * d;
                    j += units;
                }
            }
        }
    }

    /// [`offset`] with the layout a runtime flag (1: channels-last).
    #[cube]
    fn offset_in(base: u32, j: u32, taps: u32, inputs: u32, channels_last: u32) -> u32 {
        let mut at = base + j;
        if channels_last == 1 {
            at = base + (j % taps) * inputs + j / taps;
        }
        at
    }

    /// The backward of [`modulate_many`], grid layer `CUBE_POS_Z` for layer `n`, one cube per
    /// output channel: `d_weights[n]` and `terms[n] = ∂u · weight · scale`, whose sums over
    /// output channels and taps are the style's gradient ([`style_grad_many`]); `grads[n]`
    /// row-major or, where `grads_last[n]` is 1, channels-last. The demodulation's sums are made
    /// for every layer (uniform barriers, as in [`modulate_many`]).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn modulate_grad_many(
        weights: &Sequence<OwnedTensor<f32>>,
        grads: &Sequence<OwnedTensor<f32>>,
        styles: &Tensor<f32>,
        d_weights: &mut Sequence<OwnedTensor<f32>>,
        terms: &mut Sequence<OwnedTensor<f32>>,
        firsts: &Sequence<u32>,
        scales: &Sequence<f32>,
        demodulates: &Sequence<u32>,
        grads_last: &Sequence<u32>,
        epsilon: f32,
        #[comptime] count: usize,
        #[comptime] units: u32,
    ) {
        let layer = CUBE_POS_Z as usize;
        let o = CUBE_POS_X;
        let t = UNIT_POS;
        let mut squares = Shared::<[f32]>::new_slice(comptime![units as usize]);
        let mut projections = Shared::<[f32]>::new_slice(comptime![units as usize]);
        #[unroll]
        for n in 0..count {
            if layer == n {
                let weight = weights.index(n);
                let grad = grads.index(n);
                let taps = (weight.shape(2) * weight.shape(3)) as u32;
                let inputs = weight.shape(1) as u32;
                let per_output = inputs * taps;
                let mut values = 0u32;
                if o < weight.shape(0) as u32 {
                    values = per_output;
                }
                let first = *firsts.index(n);
                let scale = *scales.index(n);
                let last = *grads_last.index(n);
                let base = o * per_output;
                let mut uu = 0.0f32;
                let mut gu = 0.0f32;
                let mut j = t;
                while j < values {
                    let u =
                        weight[(base + j) as usize] * styles[(first + j / taps) as usize] * scale;
                    uu += u * u;
                    gu += grad[offset_in(base, j, taps, inputs, last) as usize] * u;
                    j += units;
                }
                squares[t as usize] = uu;
                projections[t as usize] = gu;
                cube_sum(&mut squares, units);
                cube_sum(&mut projections, units);
                let mut d = 1.0f32;
                let mut projection = 0.0f32;
                if *demodulates.index(n) == 1 {
                    d = 1.0 / f32::sqrt(squares[0] + epsilon);
                    projection = projections[0] * d * d;
                }
                let mut j = t;
                while j < values {
                    let s = styles[(first + j / taps) as usize];
                    let w = weight[(base + j) as usize];
                    let u = w * s * scale;
                    let g = grad[offset_in(base, j, taps, inputs, last) as usize];
                    let d_u = d * (g - u * projection);
                    d_weights.index_mut(n)[(base + j) as usize] = d_u * s * scale;
                    terms.index_mut(n)[(base + j) as usize] = d_u * w * scale;
                    j += units;
                }
            }
        }
    }

    /// `out = weight · scale` with `out` channels-last, one thread per weight value (`j` its
    /// row-major offset).
    #[cube(launch)]
    pub fn scale_weight(
        weight: &Tensor<f32>,
        out: &mut Tensor<f32>,
        per_output: u32,
        taps: u32,
        scale: f32,
    ) {
        let j = ABSOLUTE_POS as u32;
        if j >= weight.len() as u32 {
            terminate!();
        }
        let base = (j / per_output) * per_output;
        let inputs = per_output / taps;
        out[offset(base, j % per_output, taps, inputs, true) as usize] = weight[j as usize] * scale;
    }

    /// `d_weight = grad · scale`, row-major, from `grad` row-major or, with `grad_last`,
    /// channels-last; one thread per value.
    #[cube(launch)]
    pub fn scale_weight_grad(
        grad: &Tensor<f32>,
        d_weight: &mut Tensor<f32>,
        per_output: u32,
        taps: u32,
        scale: f32,
        #[comptime] grad_last: bool,
    ) {
        let j = ABSOLUTE_POS as u32;
        if j >= d_weight.len() as u32 {
            terminate!();
        }
        let base = (j / per_output) * per_output;
        let inputs = per_output / taps;
        d_weight[j as usize] =
            grad[offset(base, j % per_output, taps, inputs, grad_last) as usize] * scale;
    }

    /// `d_styles[firsts[n] + i] = Σ_{o, k} terms[n][o, i·taps + k]`, grid layer `CUBE_POS_Z`
    /// for layer `n`, one cube per input channel `i` (`CUBE_POS_X`; cubes past the layer's
    /// inputs write nothing), its units striding over the `(o, k)` pairs.
    #[cube(launch)]
    pub fn style_grad_many(
        terms: &Sequence<OwnedTensor<f32>>,
        d_styles: &mut Tensor<f32>,
        firsts: &Sequence<u32>,
        #[comptime] count: usize,
        #[comptime] units: u32,
    ) {
        let layer = CUBE_POS_Z as usize;
        let i = CUBE_POS_X;
        let t = UNIT_POS;
        let mut partial = Shared::<[f32]>::new_slice(comptime![units as usize]);
        #[unroll]
        for n in 0..count {
            if layer == n {
                let layer_terms = terms.index(n);
                let outputs = layer_terms.shape(0) as u32;
                let inputs = layer_terms.shape(1) as u32;
                let taps = (layer_terms.shape(2) * layer_terms.shape(3)) as u32;
                let per_output = inputs * taps;
                let mut pairs = 0u32;
                if i < inputs {
                    pairs = outputs * taps;
                }
                let mut sum = 0.0f32;
                let mut p = t;
                while p < pairs {
                    sum += layer_terms[((p / taps) * per_output + i * taps + p % taps) as usize];
                    p += units;
                }
                partial[t as usize] = sum;
                cube_sum(&mut partial, units);
                if t == 0 && i < inputs {
                    d_styles[(*firsts.index(n) + i) as usize] = partial[0];
                }
            }
        }
    }
}

/// The most layers one launch of [`kernels::modulate_many`] (or of the gradients' kernels)
/// takes: a network's (a `paper` body StyleUNet has 36 modulated layers, a face one 24); fewer
/// where the device binds fewer tensors per kernel.
const MAX_PER_LAUNCH: usize = 48;

/// A modulated layer as the kernels read it: its weight made row-major and its place in the
/// network's styles.
struct Layer {
    weight: FloatTensor<CubeBackend>,
    first: usize,
    scale: f32,
    demodulate: bool,
}

impl Layer {
    /// `styles` checked to hold the layer's range.
    fn new(
        weight: FloatTensor<CubeBackend>,
        styles: &FloatTensor<CubeBackend>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> Self {
        check_styles(styles, first, dims(&weight)[1]);
        Self {
            weight: into_contiguous(weight),
            first,
            scale,
            demodulate,
        }
    }

    fn shape(&self) -> [usize; 4] {
        dims(&self.weight)
    }

    /// Whether `count` styles hold the layer's range: a queued layer they do not (left by a
    /// caller that panicked before its launch; nothing reads its outputs) is dropped.
    fn fits(&self, count: usize) -> bool {
        self.first + self.shape()[1] <= count
    }
}

/// The per-layer scalars of one launch: where each layer's styles begin, its scale and whether
/// it demodulates.
struct Scalars {
    firsts: SequenceArg<u32>,
    scales: SequenceArg<f32>,
    demodulates: SequenceArg<u32>,
}

impl Scalars {
    fn of<'a>(layers: impl Iterator<Item = &'a Layer>) -> Self {
        let mut scalars = Self {
            firsts: SequenceArg::new(),
            scales: SequenceArg::new(),
            demodulates: SequenceArg::new(),
        };
        for layer in layers {
            scalars.firsts.push(u32_of(layer.first));
            scalars.scales.push(layer.scale);
            scalars.demodulates.push(u32::from(layer.demodulate));
        }
        scalars
    }
}

/// A queued modulation: the layer and its output (allocated channels-last, written by the
/// launch).
struct Queued {
    layer: Layer,
    out: FloatTensor<CubeBackend>,
}

thread_local! {
    /// Modulations queued by [`modulate_queue`], launched by [`modulate_launch_queued`].
    static QUEUE: RefCell<Vec<Queued>> = const { RefCell::new(Vec::new()) };
}

/// Queues the modulation of `weight` on this thread and returns its output, allocated now and
/// written by [`modulate_launch_queued`] (one stream per device: before any later kernel reads
/// it). `styles` is checked to hold the layer's range; the launch's styles are used.
pub(super) fn modulate_queue(
    weight: FloatTensor<CubeBackend>,
    styles: &FloatTensor<CubeBackend>,
    first: usize,
    scale: f32,
    demodulate: bool,
) -> FloatTensor<CubeBackend> {
    let layer = Layer::new(weight, styles, first, scale, demodulate);
    let out = empty_in_layout(&layer.weight, layer.shape(), true);
    if per_output_channel(layer.shape()).is_some() {
        let queued = Queued {
            layer,
            out: out.clone(),
        };
        QUEUE.with(|q| q.borrow_mut().push(queued));
    }
    out
}

/// Launches the modulations queued on this thread with `styles`, [`MAX_PER_LAUNCH`] layers at
/// most per kernel, one grid layer each (queued layers `styles` does not hold are dropped,
/// [`Layer::fits`]).
pub(super) fn modulate_launch_queued(styles: FloatTensor<CubeBackend>) -> FloatTensor<CubeBackend> {
    let [count] = styles.shape().dims();
    let queue: Vec<Queued> = QUEUE.with(|q| std::mem::take(&mut *q.borrow_mut()));
    let queue: Vec<Queued> = queue.into_iter().filter(|q| q.layer.fits(count)).collect();
    if queue.is_empty() {
        return styles;
    }
    let contiguous = into_contiguous(styles.clone());
    let client = contiguous.client.clone();
    for chunk in queue.chunks(items_per_launch(&client, 2, 1, MAX_PER_LAUNCH)) {
        let (mut weights, mut outs) = (SequenceArg::new(), SequenceArg::new());
        for q in chunk {
            weights.push(q.layer.weight.clone().into_tensor_arg());
            outs.push(q.out.clone().into_tensor_arg());
        }
        let scalars = Scalars::of(chunk.iter().map(|q| &q.layer));
        let most_outputs = chunk.iter().map(|q| q.layer.shape()[0]).max().unwrap_or(0);
        kernels::modulate_many::launch(
            &client,
            one_cube_per_channel_in_layers(most_outputs, "output", chunk.len()),
            CubeDim::new_1d(UNITS),
            weights,
            contiguous.clone().into_tensor_arg(),
            outs,
            scalars.firsts,
            scalars.scales,
            scalars.demodulates,
            DEMODULATION_EPSILON,
            chunk.len(),
            UNITS,
        );
    }
    styles
}

/// A queued gradient of a modulated weight: the layer, the output gradient as [`readable`] gives
/// it (and whether that is channels-last), the weight's gradient and the style terms (allocated
/// row-major, written by the launch).
struct QueuedGrad {
    layer: Layer,
    grad: FloatTensor<CubeBackend>,
    grad_last: bool,
    d_weight: FloatTensor<CubeBackend>,
    terms: FloatTensor<CubeBackend>,
}

impl QueuedGrad {
    fn new(
        weight: FloatTensor<CubeBackend>,
        styles: &FloatTensor<CubeBackend>,
        grad: FloatTensor<CubeBackend>,
        first: usize,
        scale: f32,
        demodulate: bool,
    ) -> Self {
        let layer = Layer::new(weight, styles, first, scale, demodulate);
        let shape = layer.shape();
        assert_eq!(dims(&grad), shape, "weight and gradient shapes");
        let (grad, grad_last) = readable(grad);
        Self {
            d_weight: empty_in_layout(&layer.weight, shape, false),
            terms: empty_in_layout(&layer.weight, shape, false),
            layer,
            grad,
            grad_last,
        }
    }
}

thread_local! {
    /// Gradients queued by [`modulate_grad_queue`], launched by [`modulate_grad_launch_queued`].
    static GRAD_QUEUE: RefCell<Vec<QueuedGrad>> = const { RefCell::new(Vec::new()) };
}

/// One layer's gradients now: [`launch_grads`] of it alone (the styles' gradient zero outside
/// its range).
pub(super) fn modulate_grad(
    weight: FloatTensor<CubeBackend>,
    styles: FloatTensor<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
    first: usize,
    scale: f32,
    demodulate: bool,
) -> (FloatTensor<CubeBackend>, FloatTensor<CubeBackend>) {
    let layer = QueuedGrad::new(weight, &styles, grad, first, scale, demodulate);
    let d_weight = layer.d_weight.clone();
    (d_weight, launch_grads(vec![layer], styles))
}

/// Queues a layer's gradients on this thread and returns the weight's, allocated now and
/// written by [`modulate_grad_launch_queued`].
pub(super) fn modulate_grad_queue(
    weight: FloatTensor<CubeBackend>,
    styles: &FloatTensor<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
    first: usize,
    scale: f32,
    demodulate: bool,
) -> FloatTensor<CubeBackend> {
    let layer = QueuedGrad::new(weight, styles, grad, first, scale, demodulate);
    let d_weight = layer.d_weight.clone();
    GRAD_QUEUE.with(|q| q.borrow_mut().push(layer));
    d_weight
}

/// Launches the gradients queued on this thread with `styles` and returns the styles' gradient
/// (queued layers `styles` does not hold are dropped, [`Layer::fits`]).
pub(super) fn modulate_grad_launch_queued(
    styles: FloatTensor<CubeBackend>,
) -> FloatTensor<CubeBackend> {
    let [count] = styles.shape().dims();
    let queue: Vec<QueuedGrad> = GRAD_QUEUE.with(|q| std::mem::take(&mut *q.borrow_mut()));
    let queue = queue.into_iter().filter(|q| q.layer.fits(count)).collect();
    launch_grads(queue, styles)
}

/// [`kernels::modulate_grad_many`] for `layers`, then [`kernels::style_grad_many`]'s sums into
/// each layer's range of the styles' gradient: zero-filled first unless the ranges cover the
/// styles exactly (a network's layers do), [`MAX_PER_LAUNCH`] layers at most per launch.
fn launch_grads(
    layers: Vec<QueuedGrad>,
    styles: FloatTensor<CubeBackend>,
) -> FloatTensor<CubeBackend> {
    let [count] = styles.shape().dims();
    let styles = into_contiguous(styles);
    let layers: Vec<QueuedGrad> = layers
        .into_iter()
        .filter(|q| per_output_channel(q.layer.shape()).is_some())
        .collect();
    let mut ranges: Vec<[usize; 2]> = layers
        .iter()
        .map(|q| [q.layer.first, q.layer.first + q.layer.shape()[1]])
        .collect();
    ranges.sort_unstable();
    let covered = ranges
        .iter()
        .try_fold(0, |end, &[a, b]| (a == end).then_some(b))
        == Some(count);
    let d_styles = if covered {
        empty_device_contiguous_dtype(
            styles.client.clone(),
            styles.device.clone(),
            Shape::new([count]),
            DType::F32,
        )
    } else {
        CubeBackend::float_zeros(Shape::new([count]), &styles.device, DType::F32.into())
    };
    if layers.is_empty() {
        return d_styles;
    }
    let client = styles.client.clone();
    for chunk in layers.chunks(items_per_launch(&client, 4, 1, MAX_PER_LAUNCH)) {
        let [mut weights, mut grads, mut d_weights, mut terms] =
            [(); 4].map(|_| SequenceArg::new());
        let mut grads_last = SequenceArg::new();
        for q in chunk {
            weights.push(q.layer.weight.clone().into_tensor_arg());
            grads.push(q.grad.clone().into_tensor_arg());
            d_weights.push(q.d_weight.clone().into_tensor_arg());
            terms.push(q.terms.clone().into_tensor_arg());
            grads_last.push(u32::from(q.grad_last));
        }
        let scalars = Scalars::of(chunk.iter().map(|q| &q.layer));
        let most_outputs = chunk.iter().map(|q| q.layer.shape()[0]).max().unwrap_or(0);
        kernels::modulate_grad_many::launch(
            &client,
            one_cube_per_channel_in_layers(most_outputs, "output", chunk.len()),
            CubeDim::new_1d(UNITS),
            weights,
            grads,
            styles.clone().into_tensor_arg(),
            d_weights,
            terms,
            scalars.firsts,
            scalars.scales,
            scalars.demodulates,
            grads_last,
            DEMODULATION_EPSILON,
            chunk.len(),
            UNITS,
        );
    }
    for chunk in layers.chunks(items_per_launch(&client, 1, 1, MAX_PER_LAUNCH)) {
        let (mut terms, mut firsts) = (SequenceArg::new(), SequenceArg::new());
        for q in chunk {
            terms.push(q.terms.clone().into_tensor_arg());
            firsts.push(u32_of(q.layer.first));
        }
        let most_inputs = chunk.iter().map(|q| q.layer.shape()[1]).max().unwrap_or(0);
        kernels::style_grad_many::launch(
            &client,
            one_cube_per_channel_in_layers(most_inputs, "input", chunk.len()),
            CubeDim::new_1d(SUM_UNITS),
            terms,
            d_styles.clone().into_tensor_arg(),
            firsts,
            chunk.len(),
            SUM_UNITS,
        );
    }
    d_styles
}

/// The number of `styles`, checked to hold `inputs` from `first` on.
fn check_styles(styles: &FloatTensor<CubeBackend>, first: usize, inputs: usize) -> usize {
    let [count] = styles.shape().dims();
    assert!(
        first + inputs <= count,
        "styles {first}..{} of {count}",
        first + inputs
    );
    count
}

/// One thread per value, the output channels-last.
pub(super) fn scale_weight(
    weight: FloatTensor<CubeBackend>,
    scale: f32,
) -> FloatTensor<CubeBackend> {
    let shape = dims(&weight);
    let weight = into_contiguous(weight);
    let out = empty_in_layout(&weight, shape, true);
    if let Some((per_output, taps)) = per_output_channel(shape) {
        let (cubes, cube) = one_thread_per_value(weight.shape().num_elements());
        kernels::scale_weight::launch(
            &weight.client,
            cubes,
            cube,
            weight.clone().into_tensor_arg(),
            out.clone().into_tensor_arg(),
            per_output,
            taps,
            scale,
        );
    }
    out
}

/// One thread per value, from the gradient as it comes if channels-last, into a row-major
/// gradient.
pub(super) fn scale_weight_grad(
    grad: FloatTensor<CubeBackend>,
    scale: f32,
) -> FloatTensor<CubeBackend> {
    let shape = dims(&grad);
    let (grad, grad_last) = readable(grad);
    let d_weight = empty_in_layout(&grad, shape, false);
    if let Some((per_output, taps)) = per_output_channel(shape) {
        let (cubes, cube) = one_thread_per_value(grad.shape().num_elements());
        kernels::scale_weight_grad::launch(
            &grad.client,
            cubes,
            cube,
            grad.clone().into_tensor_arg(),
            d_weight.clone().into_tensor_arg(),
            per_output,
            taps,
            scale,
            grad_last,
        );
    }
    d_weight
}

/// The values per output channel and the taps per input channel of a weight of `shape`, as
/// kernel arguments (its values checked to be indexable with 32 bits); `None` for a weight
/// without values.
fn per_output_channel(shape: [usize; 4]) -> Option<(u32, u32)> {
    let [c_out, c_in, kh, kw] = shape;
    let per_output = c_in * kh * kw;
    if c_out * per_output == 0 {
        return None;
    }
    u32_of(c_out * per_output);
    Some((u32_of(per_output), u32_of(kh * kw)))
}
