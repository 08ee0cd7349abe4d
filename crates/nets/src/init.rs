//! Deterministic weight initialisation on the host: a ChaCha8 stream seeded with the network's
//! seed, so the same seed gives the same weights on every backend and every machine. The draws
//! define every network's initial weights, and through them the numbers a run reports: the order
//! in which modules draw, and how a draw consumes the stream, are part of the format.

use burn::module::Param;
use burn::tensor::{Device, Tensor, TensorData};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Deterministic host-side initialisation: the same seed gives the same weights.
pub struct Init {
    rng: ChaCha8Rng,
    pub device: Device,
}

impl Init {
    pub fn new(seed: u64, device: &Device) -> Self {
        Self {
            rng: ChaCha8Rng::seed_from_u64(seed),
            device: device.clone(),
        }
    }

    /// Values drawn from `N(0, std²)`.
    pub fn normal_values(&mut self, count: usize, std: f32) -> Vec<f32> {
        (0..count)
            .map(|_| std * standard_normal(&mut self.rng))
            .collect()
    }

    /// A trainable tensor drawn from `N(0, std²)`.
    pub fn normal<const D: usize>(&mut self, shape: [usize; D], std: f32) -> Param<Tensor<D>> {
        let values = self.normal_values(shape.iter().product(), std);
        Param::from_data(TensorData::new(values, shape), &self.device)
    }

    /// A trainable tensor filled with `value`.
    pub fn constant<const D: usize>(&mut self, shape: [usize; D], value: f32) -> Param<Tensor<D>> {
        let values = vec![value; shape.iter().product()];
        Param::from_data(TensorData::new(values, shape), &self.device)
    }

    /// A constant (non-persistent) tensor from values.
    pub fn tensor<const D: usize>(&self, values: Vec<f32>, shape: [usize; D]) -> Tensor<D> {
        Tensor::from_data(TensorData::new(values, shape), &self.device)
    }
}

/// One standard normal sample by Box–Muller: two uniform `f64` draws (the first in
/// `[f64::MIN_POSITIVE, 1)`, so its logarithm is finite), the cosine branch only, rounded to
/// `f32`. Hand-written rather than `rand_distr`'s `StandardNormal`, a ziggurat that consumes
/// the stream differently: weights drawn with it would differ from those of every existing run.
pub fn standard_normal(rng: &mut impl Rng) -> f32 {
    let u1: f64 = rng.random_range(f64::MIN_POSITIVE..1.0);
    let u2: f64 = rng.random();
    ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The first draws of seed 0, bit for bit: a change to how [`standard_normal`] consumes the
    /// stream changes every network's initial weights.
    #[test]
    fn the_draws_of_a_seed_are_pinned() {
        let mut init = Init::new(0, &Device::flex());
        let bits: Vec<u32> = init
            .normal_values(4, 1.0)
            .iter()
            .map(|v| v.to_bits())
            .collect();
        assert_eq!(bits, [3209653765, 1061767946, 3203886062, 1058017179]);
    }
}
