//! Central-difference checks of hand-written backwards, shared by the tests of the backend ops.

use burn::tensor::{Tensor, TensorData};

pub fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec::<f32>().unwrap()
}

/// The analytic gradient of `loss` at `x0` against central differences of step `eps`, element
/// by element (relative tolerance 2·10⁻³).
pub fn check(loss: &dyn Fn(Tensor<4>) -> Tensor<1>, x0: Tensor<4>, eps: f32, what: &str) {
    let device = x0.device();
    let x = x0.clone().require_grad();
    let analytic = values(x.grad(&loss(x.clone()).backward()).unwrap());
    let base = values(x0.clone());
    for (i, &a) in analytic.iter().enumerate() {
        let at = |delta: f32| {
            let mut shifted = base.clone();
            shifted[i] += delta;
            let x = Tensor::<4>::from_data(TensorData::new(shifted, x0.dims()), &device);
            f64::from(loss(x).into_scalar::<f32>())
        };
        let numeric = ((at(eps) - at(-eps)) / (2.0 * f64::from(eps))) as f32;
        assert!(
            (a - numeric).abs() <= 2e-3 * (1.0 + numeric.abs()),
            "{what}[{i}]: {a}, central differences give {numeric}"
        );
    }
}
