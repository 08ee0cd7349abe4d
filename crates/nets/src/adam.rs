//! Adam as one pass per parameter: Burn's `Adam` (no weight decay, no AMSGrad) with its update
//! computed by one backend op instead of thirteen tensor ops.
//!
//! Burn's `Adam` updates each parameter tensor with about thirteen element-wise ops (the two
//! moments, the bias corrections, the step), each its own kernel launch on a GPU: ≈ 17 000
//! launches of the `paper` preset's ≈ 67 000 per step, and 375 ms of its 3 s on an H200
//! (BENCHMARKS "Where the device time goes"). [`FusedAdam`] computes the same update in one
//! pass over each parameter ([`AdamBackend::adam_update`]: one parallel loop on `Flex`, one kernel
//! on `Cube` devices, fused or not) and keeps Burn's state type ([`AdamState`]), so checkpoints
//! written by either load in the other. Devices without the op run Burn's arithmetic as tensor
//! ops ([`update_as_tensors`]).
//!
//! [`ModuleAdam`] steps a whole module. On `Cube` devices it launches the updates of
//! up to [`MAX_PER_LAUNCH`] parameters per kernel instead of one kernel per parameter (the
//! `paper` step has ≈ 1 200 parameters): each parameter's outputs are allocated as Burn's
//! `ModuleOptimizer` visits it, and written when every parameter has been visited.
//!
//! The arithmetic, in f32 and in Burn's order (so that on the CPU the two agree to the bit):
//! with `t` the step count from 1, `m ← β₁·m + (1−β₁)·g`, `v ← β₂·v + (1−β₂)·g²` (moments start at
//! zero), `c = √(1−β₂ᵗ) / (1−β₁ᵗ)`, `p ← p − lr·(m·c) / (√v + ε·√(1−β₂ᵗ))`.

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::module::Module;
use burn::optim::{
    AdamState, AdaptiveMomentumState, GradientsParams, LearningRate, ModuleOptimizer, Optimizer,
    OptimizerRecord,
};
use burn::tensor::{Device, Tensor};

#[cfg(any(feature = "gpu", feature = "cuda"))]
mod cube;
mod flex;

/// Parameters whose updates share one kernel launch on `Cube` devices (at most: seven bindings
/// each, within the device's limit; on CUDA a device pointer each, 1.8 KB of the 4 KB of kernel
/// parameters CUDA allows before 12.1 and the 32 KB since). The `paper` step's updates took 56
/// launches at 16 and take 28 at 32, compiling as many variants (one per queue length left
/// over); more would save a few launches for larger kernels.
pub const MAX_PER_LAUNCH: usize = 32;

/// The step's scalars, computed once on the host for every element.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamCoefficients {
    pub beta_1: f32,
    /// `1 − β₁` (as Burn rounds it).
    pub one_minus_beta_1: f32,
    pub beta_2: f32,
    /// `1 − β₂`.
    pub one_minus_beta_2: f32,
    /// `√(1−β₂ᵗ) / (1−β₁ᵗ)`: the bias corrections folded into the first moment's scale.
    pub moment_scale: f32,
    /// `ε·√(1−β₂ᵗ)`, added to `√v`.
    pub epsilon: f32,
    /// The learning rate.
    pub learning_rate: f32,
}

/// The Adam update as one backend op.
#[backend_extension(
    Flex,
    Cube: cfg(any(feature = "gpu", feature = "cuda")),
    Fusion: cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))
)]
pub trait AdamBackend: Backend {
    /// `(param, m, v)` after one step with gradient `grad`; all four of one shape.
    #[fusion(meta = |param, _grad, _m, _v, _c| (param.clone(), param.clone(), param.clone()))]
    fn adam_update(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        moment_1: FloatTensor<Self>,
        moment_2: FloatTensor<Self>,
        coefficients: AdamCoefficients,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>);
}

/// Adam without weight decay or AMSGrad, one pass per parameter; Burn's state records.
#[derive(Clone, Copy, Debug)]
pub struct FusedAdam {
    pub beta_1: f32,
    pub beta_2: f32,
    pub epsilon: f32,
}

impl FusedAdam {
    /// The optimiser of a whole module.
    pub fn init(self) -> ModuleAdam {
        ModuleAdam {
            inner: ModuleOptimizer::from(self),
        }
    }

    /// The scalars of step `time` (from 1) at learning rate `lr`, as Burn computes them.
    pub fn coefficients(&self, time: usize, lr: LearningRate) -> AdamCoefficients {
        let time = time as i32;
        let bias_correction_2 = (1.0 - self.beta_2.powi(time)).sqrt();
        AdamCoefficients {
            beta_1: self.beta_1,
            one_minus_beta_1: 1.0 - self.beta_1,
            beta_2: self.beta_2,
            one_minus_beta_2: 1.0 - self.beta_2,
            moment_scale: bias_correction_2 / (1.0 - self.beta_1.powi(time)),
            epsilon: self.epsilon * bias_correction_2,
            learning_rate: lr as f32,
        }
    }
}

impl Optimizer for FusedAdam {
    type State<const D: usize> = AdamState<D>;

    fn step<const D: usize>(
        &self,
        lr: LearningRate,
        tensor: Tensor<D>,
        grad: Tensor<D>,
        state: Option<Self::State<D>>,
    ) -> (Tensor<D>, Option<Self::State<D>>) {
        let (moment_1, moment_2, time) = match state {
            Some(state) => (
                state.momentum.moment_1,
                state.momentum.moment_2,
                state.momentum.time,
            ),
            None => (grad.zeros_like(), grad.zeros_like(), 0),
        };
        let time = time + 1;
        let coefficients = self.coefficients(time, lr);
        #[cfg(any(feature = "gpu", feature = "cuda"))]
        if cube::deferring(&tensor.device()) {
            let (tensor, moment_1, moment_2) =
                cube::defer(tensor, grad, moment_1, moment_2, coefficients);
            let momentum = AdaptiveMomentumState::new(time, moment_1, moment_2);
            return (tensor, Some(AdamState::new(momentum)));
        }
        let (tensor, moment_1, moment_2) = if has_the_op(&tensor.device()) {
            let (p, m, v) = <Dispatch as AdamBackend>::adam_update(
                tensor.into_dispatch(),
                grad.into_dispatch(),
                moment_1.into_dispatch(),
                moment_2.into_dispatch(),
                coefficients,
            );
            (
                Tensor::from_dispatch(p),
                Tensor::from_dispatch(m),
                Tensor::from_dispatch(v),
            )
        } else {
            update_as_tensors(tensor, grad, moment_1, moment_2, coefficients)
        };
        let momentum = AdaptiveMomentumState::new(time, moment_1, moment_2);
        (tensor, Some(AdamState::new(momentum)))
    }

    fn to_device<const D: usize>(mut state: Self::State<D>, device: &Device) -> Self::State<D> {
        state.momentum = state.momentum.to_device(device);
        state
    }
}

/// Adam over a whole module: Burn's [`ModuleOptimizer`] stepping [`FusedAdam`] (so its
/// per-parameter states and records are Burn's, and checkpoints load either way), with the
/// updates of `Cube` devices launched [`MAX_PER_LAUNCH`] parameters at a time.
#[derive(Clone)]
pub struct ModuleAdam {
    inner: ModuleOptimizer,
}

impl ModuleAdam {
    /// Updates `module`'s parameters with `grads` at learning rate `lr`.
    pub fn step<M: Module>(&mut self, lr: LearningRate, module: M, grads: GradientsParams) -> M {
        #[cfg(any(feature = "gpu", feature = "cuda"))]
        {
            cube::batched(|| self.inner.step(lr, module, grads))
        }
        #[cfg(not(any(feature = "gpu", feature = "cuda")))]
        {
            self.inner.step(lr, module, grads)
        }
    }

    /// The moments and step counts of every parameter (Burn's `ModuleOptimizer` record).
    pub fn to_record(&self) -> OptimizerRecord {
        self.inner.to_record()
    }

    /// Resumes from a record of [`Self::to_record`] or of Burn's `Adam`.
    pub fn load_record(self, record: OptimizerRecord) -> Self {
        Self {
            inner: self.inner.load_record(record),
        }
    }
}

/// Whether `device` runs [`AdamBackend`] (the optimiser's tensors never carry autodiff).
fn has_the_op(device: &Device) -> bool {
    #[cfg(any(feature = "gpu", feature = "cuda"))]
    if matches!(device.as_dispatch(), burn::backend::DispatchDevice::Cube(_)) {
        return true;
    }
    *device == Device::flex()
}

/// The update as Burn's `Adam` computes it, one tensor op at a time.
pub fn update_as_tensors<const D: usize>(
    param: Tensor<D>,
    grad: Tensor<D>,
    moment_1: Tensor<D>,
    moment_2: Tensor<D>,
    c: AdamCoefficients,
) -> (Tensor<D>, Tensor<D>, Tensor<D>) {
    let moment_1 = moment_1
        .mul_scalar(c.beta_1)
        .add(grad.clone().mul_scalar(c.one_minus_beta_1));
    let moment_2 = moment_2
        .mul_scalar(c.beta_2)
        .add(grad.square().mul_scalar(c.one_minus_beta_2));
    let step = moment_1
        .clone()
        .mul_scalar(c.moment_scale)
        .div(moment_2.clone().sqrt().add_scalar(c.epsilon));
    (param - step.mul_scalar(c.learning_rate), moment_1, moment_2)
}

/// One element of the update, for the CPU loop (the kernel spells out the same).
#[inline(always)]
pub(crate) fn update_one(p: &mut f32, g: f32, m: &mut f32, v: &mut f32, c: &AdamCoefficients) {
    *m = *m * c.beta_1 + g * c.one_minus_beta_1;
    *v = *v * c.beta_2 + g * g * c.one_minus_beta_2;
    *p -= *m * c.moment_scale / (v.sqrt() + c.epsilon) * c.learning_rate;
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::{Module, Param};
    use burn::optim::{AdamConfig, GradientsParams};
    use burn::tensor::TensorData;

    fn wave(shape: [usize; 2], phase: f32, device: &Device) -> Tensor<2> {
        let n = shape[0] * shape[1];
        let values: Vec<f32> = (0..n)
            .map(|i| (i as f32 * 0.013 + phase).sin() * (1.0 + (i % 7) as f32))
            .collect();
        Tensor::from_data(TensorData::new(values, shape), device)
    }

    fn bits<const D: usize>(t: &Tensor<D>) -> Vec<u32> {
        let values = t.clone().into_data().try_to_vec::<f32>().unwrap();
        values.iter().map(|v| v.to_bits()).collect()
    }

    /// Several chunks of the parallel loop, moments from zero, five steps with new gradients:
    /// the parameter and both moments equal Burn's `Adam`'s to the bit, for both beta settings
    /// the avatar uses.
    #[test]
    fn one_pass_equals_burns_adam_to_the_bit() {
        let device = Device::flex();
        for (beta_1, beta_2, epsilon) in [(0.9, 0.999, 1e-8), (0.0, 0.99, 1e-5)] {
            let burns = AdamConfig::new()
                .with_beta_1(beta_1)
                .with_beta_2(beta_2)
                .with_epsilon(epsilon)
                .build();
            let fused = FusedAdam {
                beta_1,
                beta_2,
                epsilon,
            };
            let shape = [3, 20_001];
            let (mut p_burn, mut p_fused) = (wave(shape, 0.3, &device), wave(shape, 0.3, &device));
            let (mut s_burn, mut s_fused) = (None, None);
            for step in 0..5 {
                let grad = wave(shape, step as f32, &device) * 1e-3;
                let lr = 1e-2 / (step + 1) as f64;
                (p_burn, s_burn) = burns.step(lr, p_burn, grad.clone(), s_burn);
                (p_fused, s_fused) = fused.step(lr, p_fused, grad, s_fused);
            }
            let (burn_state, fused_state) = (s_burn.unwrap().momentum, s_fused.unwrap().momentum);
            assert_eq!(bits(&p_fused), bits(&p_burn), "parameter");
            assert_eq!(bits(&fused_state.moment_1), bits(&burn_state.moment_1));
            assert_eq!(bits(&fused_state.moment_2), bits(&burn_state.moment_2));
            assert_eq!(fused_state.time, 5);
        }
    }

    /// The tensor-op formulation (devices without the op) computes what the op does.
    #[test]
    fn the_tensor_formulation_equals_the_op() {
        let device = Device::flex();
        let shape = [5, 999];
        let c = FusedAdam {
            beta_1: 0.9,
            beta_2: 0.999,
            epsilon: 1e-8,
        }
        .coefficients(3, 5e-3);
        let [p, g, m] = [0.1, 0.2, 0.3].map(|phase| wave(shape, phase, &device));
        let v = wave(shape, 0.4, &device).abs();
        let by_tensors = update_as_tensors(p.clone(), g.clone(), m.clone(), v.clone(), c);
        let (p, m, v) = <Dispatch as AdamBackend>::adam_update(
            p.into_dispatch(),
            g.into_dispatch(),
            m.into_dispatch(),
            v.into_dispatch(),
            c,
        );
        let by_op: [Tensor<2>; 3] = [p, m, v].map(Tensor::from_dispatch);
        assert_eq!(bits(&by_op[0]), bits(&by_tensors.0));
        assert_eq!(bits(&by_op[1]), bits(&by_tensors.1));
        assert_eq!(bits(&by_op[2]), bits(&by_tensors.2));
    }

    #[derive(Module, Debug)]
    struct Pair {
        a: Param<Tensor<2>>,
        b: Param<Tensor<1>>,
    }

    /// An optimiser state saved by Burn's `Adam` resumes in [`FusedAdam`] (and back): two steps
    /// with one, its record through bytes, a third with the other equals three with Burn's.
    #[test]
    fn states_load_across_burns_adam_and_this_one() {
        let device = Device::flex().autodiff();
        let pair = || Pair {
            a: Param::from_tensor(wave([4, 6], 0.5, &device)),
            b: Param::from_tensor(wave([1, 6], 0.9, &device).reshape([6])),
        };
        let grads = |pair: &Pair, step: usize| {
            let target = wave([4, 6], step as f32, &device);
            let loss = (pair.a.val() * pair.b.val().reshape([1, 6]) - target)
                .powi_scalar(2)
                .sum();
            GradientsParams::from_grads(loss.backward(), pair)
        };
        let burns = || AdamConfig::new().with_epsilon(1e-8).init();
        let fused = || {
            FusedAdam {
                beta_1: 0.9,
                beta_2: 0.999,
                epsilon: 1e-8,
            }
            .init()
        };
        let (mut reference, mut optim) = (pair(), burns());
        for step in 0..3 {
            let g = grads(&reference, step);
            reference = optim.step(1e-2, reference, g);
        }
        for burns_first in [true, false] {
            let mut resumed = pair();
            let record = if burns_first {
                let mut optim = burns();
                for step in 0..2 {
                    let g = grads(&resumed, step);
                    resumed = optim.step(1e-2, resumed, g);
                }
                optim.to_record()
            } else {
                let mut optim = fused();
                for step in 0..2 {
                    let g = grads(&resumed, step);
                    resumed = optim.step(1e-2, resumed, g);
                }
                optim.to_record()
            };
            let record = OptimizerRecord::from_bytes(record.into_bytes().unwrap()).unwrap();
            let g = grads(&resumed, 2);
            resumed = if burns_first {
                fused().load_record(record).step(1e-2, resumed, g)
            } else {
                burns().load_record(record).step(1e-2, resumed, g)
            };
            let close = |x: Tensor<2>, y: Tensor<2>| {
                let d = (x - y).abs().max().into_scalar::<f32>();
                assert!(d < 1e-6, "differs by {d}");
            };
            close(resumed.a.val().inner(), reference.a.val().inner());
            close(
                resumed.b.val().inner().reshape([1, 6]),
                reference.b.val().inner().reshape([1, 6]),
            );
        }
    }
}
