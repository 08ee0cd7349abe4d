//! Adam on `CubeBackend` (wgpu, CUDA; under `fusion` as lazy ops): one kernel,
//! `adam_update_many`, updates up to [`MAX_PER_LAUNCH`] parameters, one grid layer each — one
//! parameter for `impl AdamBackend`, a queue of them for the batched path of
//! [`super::ModuleAdam`] ([`AdamManyBackend`]). Inputs are read row-major after
//! `into_contiguous`; outputs are allocated contiguous (CUDA pitches Burn's ordinary
//! allocations: `f3g_splat::cube`'s module doc).
//!
//! Batching: while [`batched`] runs a module's step on this thread, [`defer`] gives each
//! parameter freshly allocated outputs (its new value and moments, which Burn's optimiser
//! stores as usual) and queues the update; [`batched`] launches the queue when every parameter
//! has been visited, before anything can read the outputs (one stream per device: the launches
//! run before any later kernel that reads them).

use std::cell::RefCell;

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, DispatchDevice, TensorMetadata, backend_extension};
use burn::tensor::{DType, Device, Tensor};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::client::Client;
use burn_cubecl::cubecl::prelude::SequenceArg;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;
use burn_cubecl::tensor::CubeTensor;

use super::{AdamBackend, AdamCoefficients, MAX_PER_LAUNCH};
use crate::cube_grid::{items_per_launch, one_thread_per_value_in_layers};
use crate::cube_layout::{empty_in_layout, into_channels_last, pixel_stride};

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// `super::super::update_one` for several parameters: layer `CUBE_POS_Z` of the grid
    /// updates parameter `t`, whose `(param, grad, m, v)` are `inputs[4t..4t + 4]` and new
    /// `(param, m, v)` `outputs[3t..3t + 3]`.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn adam_update_many(
        inputs: &Sequence<OwnedTensor<f32>>,
        outputs: &mut Sequence<OwnedTensor<f32>>,
        beta_1: f32,
        one_minus_beta_1: f32,
        beta_2: f32,
        one_minus_beta_2: f32,
        moment_scale: f32,
        epsilon: f32,
        learning_rate: f32,
        #[comptime] count: usize,
    ) {
        let layer = CUBE_POS_Z as usize;
        let i = ((CUBE_POS_Y * CUBE_COUNT_X + CUBE_POS_X) * CUBE_DIM_X + UNIT_POS_X) as usize;
        #[unroll]
        for t in 0..count {
            if layer == t {
                let param = inputs.index(4 * t);
                if i < param.len() {
                    let g = inputs.index(4 * t + 1)[i];
                    let m = inputs.index(4 * t + 2)[i] * beta_1 + g * one_minus_beta_1;
                    let v = inputs.index(4 * t + 3)[i] * beta_2 + g * g * one_minus_beta_2;
                    let p = param[i] - m * moment_scale / (f32::sqrt(v) + epsilon) * learning_rate;
                    outputs.index_mut(3 * t)[i] = p;
                    outputs.index_mut(3 * t + 1)[i] = m;
                    outputs.index_mut(3 * t + 2)[i] = v;
                }
            }
        }
    }
}

impl AdamBackend for CubeBackend {
    fn adam_update(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        moment_1: FloatTensor<Self>,
        moment_2: FloatTensor<Self>,
        c: AdamCoefficients,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let update = Queued::new(param, grad, moment_1, moment_2, c);
        launch(&update.tensors[0].client, std::slice::from_ref(&update), c);
        update.outputs()
    }
}

/// The batched update's two halves as backend ops (`Cube` devices only). Under Burn's `fusion`
/// both run on the fusion stream's thread in the order they were recorded, so the queue is
/// that thread's.
#[backend_extension(
    Cube,
    Fusion: cfg(feature = "fusion")
)]
pub trait AdamManyBackend: Backend {
    /// Queues the update of one parameter on this thread and returns its new value and
    /// moments: allocated now, written by [`Self::adam_launch_queued`].
    #[fusion(meta = |param, _grad, _m, _v, _c| (param.clone(), param.clone(), param.clone()))]
    fn adam_queue(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        moment_1: FloatTensor<Self>,
        moment_2: FloatTensor<Self>,
        coefficients: AdamCoefficients,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>);

    /// Launches the updates queued on this thread, [`MAX_PER_LAUNCH`] parameters at most per
    /// kernel; `route` (any tensor of the device) selects the backend and is returned.
    #[fusion(dtype = route, shape = route)]
    fn adam_launch_queued(route: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// A queued update: `(param, grad, m, v)`, then the outputs `(param, m, v)`.
struct Queued {
    tensors: [CubeTensor; 7],
    coefficients: AdamCoefficients,
}

impl Queued {
    /// The update of one parameter, its outputs allocated (gapless) and not yet written, every
    /// tensor in the gradient's layout: channels-last for a convolution weight, whose gradient
    /// the implicit GEMM hands back so, row-major otherwise. Why: a weight kept channels-last
    /// is read by the next forward and input gradient as it is, where a row-major one was
    /// copied before each (the update reads and writes by buffer offset, so one layout for
    /// all is all it needs). A parameter changes layout once, at its first update.
    fn new(
        param: CubeTensor,
        grad: CubeTensor,
        moment_1: CubeTensor,
        moment_2: CubeTensor,
        coefficients: AdamCoefficients,
    ) -> Self {
        let shape = param.shape();
        // A gradient of few input channels comes back pitched (CUDA pads a row of 3 values to
        // 4): made gapless channels-last all the same, for the forward's sake.
        let last = shape.num_dims() == 4 && pixel_stride(&grad).is_some();
        let arranged = |t: CubeTensor| {
            if last {
                into_channels_last(t)
            } else {
                into_contiguous(t)
            }
        };
        let [param, grad, moment_1, moment_2] = [param, grad, moment_1, moment_2].map(arranged);
        let empty = || {
            if last {
                empty_in_layout(&param, shape.dims(), true)
            } else {
                empty_device_contiguous_dtype(
                    param.client.clone(),
                    param.device.clone(),
                    shape.clone(),
                    DType::F32,
                )
            }
        };
        let (p, m, v) = (empty(), empty(), empty());
        Self {
            tensors: [param, grad, moment_1, moment_2, p, m, v],
            coefficients,
        }
    }

    /// The new value and moments.
    fn outputs(&self) -> (CubeTensor, CubeTensor, CubeTensor) {
        let [.., p, m, v] = &self.tensors;
        (p.clone(), m.clone(), v.clone())
    }
}

thread_local! {
    /// Updates queued by `adam_queue`, launched by `adam_launch_queued`.
    static QUEUE: RefCell<Vec<Queued>> = const { RefCell::new(Vec::new()) };
    /// While [`batched`] runs on this thread: `Some`, with one of the queued updates' outputs
    /// once there is one (the route of the launch).
    static BATCH: RefCell<Option<Option<FloatTensor<Dispatch>>>> = const { RefCell::new(None) };
}

/// Runs `step` (one module's optimiser step) with the updates of `Cube` devices queued, then
/// launches them, several parameters per kernel. Not re-entrant (one module at a time).
pub(super) fn batched<T>(step: impl FnOnce() -> T) -> T {
    /// Stops queueing however `step` ends, and launches the queue unless it is unwinding (a
    /// launch that panicked then would abort; a later step launches the leftovers, whose outputs
    /// nothing reads).
    struct Launch;
    impl Drop for Launch {
        fn drop(&mut self) {
            let route = BATCH.with(|b| b.borrow_mut().take()).flatten();
            if let Some(route) = route.filter(|_| !std::thread::panicking()) {
                <Dispatch as AdamManyBackend>::adam_launch_queued(route);
            }
        }
    }
    BATCH.with(|b| *b.borrow_mut() = Some(None));
    let _launch = Launch;
    step()
}

/// Whether [`defer`] queues updates on `device` now.
pub(super) fn deferring(device: &Device) -> bool {
    matches!(device.as_dispatch(), DispatchDevice::Cube(_)) && BATCH.with(|b| b.borrow().is_some())
}

/// Queues the update of one parameter (see [`deferring`]) and returns its outputs, written
/// when [`batched`] ends.
pub(super) fn defer<const D: usize>(
    param: Tensor<D>,
    grad: Tensor<D>,
    moment_1: Tensor<D>,
    moment_2: Tensor<D>,
    coefficients: AdamCoefficients,
) -> (Tensor<D>, Tensor<D>, Tensor<D>) {
    let (p, m, v) = <Dispatch as AdamManyBackend>::adam_queue(
        param.into_dispatch(),
        grad.into_dispatch(),
        moment_1.into_dispatch(),
        moment_2.into_dispatch(),
        coefficients,
    );
    BATCH.with(|b| {
        if let Some(route) = b.borrow_mut().as_mut() {
            route.get_or_insert_with(|| v.clone());
        }
    });
    (
        Tensor::from_dispatch(p),
        Tensor::from_dispatch(m),
        Tensor::from_dispatch(v),
    )
}

impl AdamManyBackend for CubeBackend {
    fn adam_queue(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        moment_1: FloatTensor<Self>,
        moment_2: FloatTensor<Self>,
        coefficients: AdamCoefficients,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let update = Queued::new(param, grad, moment_1, moment_2, coefficients);
        let outputs = update.outputs();
        QUEUE.with(|q| q.borrow_mut().push(update));
        outputs
    }

    fn adam_launch_queued(route: FloatTensor<Self>) -> FloatTensor<Self> {
        let mut queue = QUEUE.with(|q| std::mem::take(&mut *q.borrow_mut()));
        let client = route.client.clone();
        let per_launch = items_per_launch(&client, 7, 0, MAX_PER_LAUNCH);
        // Neighbours in size share a grid with little to spare; a launch shares one step's
        // coefficients (every parameter's moments are as old, except after a stage adds a
        // network).
        queue.sort_by_key(|q| q.tensors[0].shape().num_elements());
        while let Some(first) = queue.first() {
            let c = first.coefficients;
            let (same, rest): (Vec<_>, Vec<_>) =
                queue.into_iter().partition(|q| q.coefficients == c);
            for chunk in same.chunks(per_launch) {
                launch(&client, chunk, c);
            }
            queue = rest;
        }
        route
    }
}

/// One kernel for the updates of `chunk`, one grid layer each.
fn launch(client: &Client, chunk: &[Queued], c: AdamCoefficients) {
    let longest = chunk
        .iter()
        .map(|q| q.tensors[0].shape().num_elements())
        .max()
        .unwrap_or(0);
    if longest == 0 {
        return;
    }
    let (mut inputs, mut outputs) = (SequenceArg::new(), SequenceArg::new());
    for q in chunk {
        for input in &q.tensors[..4] {
            inputs.push(input.clone().into_tensor_arg());
        }
        for output in &q.tensors[4..] {
            outputs.push(output.clone().into_tensor_arg());
        }
    }
    let (cubes, cube) = one_thread_per_value_in_layers(longest, chunk.len());
    kernels::adam_update_many::launch(
        client,
        cubes,
        cube,
        inputs,
        outputs,
        c.beta_1,
        c.one_minus_beta_1,
        c.beta_2,
        c.one_minus_beta_2,
        c.moment_scale,
        c.epsilon,
        c.learning_rate,
        chunk.len(),
    );
}
