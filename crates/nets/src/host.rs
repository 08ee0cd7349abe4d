//! Flex tensors as host slices and back, for the CPU implementations of the backend ops (this
//! crate's and `f3g-avatar`'s).

use std::borrow::Cow;

use burn::backend::Flex;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::TensorData;

/// A tensor's values as f32, borrowed when already contiguous f32.
pub fn host_f32(t: &FloatTensor<Flex>) -> Cow<'_, [f32]> {
    match t.as_slice::<f32>() {
        Some(values) => Cow::Borrowed(values),
        None => Cow::Owned(
            t.clone()
                .into_data()
                .convert::<f32>()
                .try_into_vec::<f32>()
                .expect("a float tensor converts to f32 values"),
        ),
    }
}

/// A Flex tensor of `shape` holding `values`.
pub fn from_values(values: Vec<f32>, shape: Vec<usize>) -> FloatTensor<Flex> {
    Flex::float_from_data(TensorData::new(values, shape), &Default::default())
}
