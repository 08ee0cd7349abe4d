//! Inputs shared by the network tests.

use burn::tensor::{Device, Tensor, TensorData};

/// A deterministic, non-constant input in `[-0.5, 0.5)`.
pub fn ramp(shape: [usize; 4], device: &Device) -> Tensor<4> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n)
        .map(|i| ((i * 7919) % 97) as f32 / 97.0 - 0.5)
        .collect();
    Tensor::from_data(TensorData::new(v, shape), device)
}
