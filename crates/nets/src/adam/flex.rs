//! `impl AdamBackend for Flex`: one parallel loop over the parameter's values.

use burn::backend::Flex;
use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use rayon::prelude::*;

use super::{AdamBackend, AdamCoefficients, update_one};
use crate::host::{from_values, host_f32};

/// Values per parallel task: large enough to amortise the task, small enough to split a layer.
const CHUNK: usize = 1 << 14;

impl AdamBackend for Flex {
    fn adam_update(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        moment_1: FloatTensor<Self>,
        moment_2: FloatTensor<Self>,
        c: AdamCoefficients,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let shape = param.shape().to_vec();
        let grad = host_f32(&grad);
        let mut p = host_f32(&param).into_owned();
        let mut m = host_f32(&moment_1).into_owned();
        let mut v = host_f32(&moment_2).into_owned();
        assert!(
            grad.len() == p.len() && m.len() == p.len() && v.len() == p.len(),
            "a parameter, its gradient and its moments have one shape"
        );
        p.par_chunks_mut(CHUNK)
            .zip(m.par_chunks_mut(CHUNK))
            .zip(v.par_chunks_mut(CHUNK))
            .zip(grad.par_chunks(CHUNK))
            .for_each(|(((p, m), v), g)| {
                for (((p, m), v), &g) in p.iter_mut().zip(m).zip(v).zip(g) {
                    update_one(p, g, m, v, &c);
                }
            });
        (
            from_values(p, shape.clone()),
            from_values(m, shape.clone()),
            from_values(v, shape),
        )
    }
}
