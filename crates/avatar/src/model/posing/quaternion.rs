//! The Hamilton product of quaternion rows as one backend op each way.
//!
//! Why: as tensor ops on `[N, 1]` columns ([`quat_mul_as_tensors`]) posing a step's Gaussians'
//! rotations was eight column slices, sixteen products, twelve sums and a concatenation forward
//! and more backward, each a kernel launch on a GPU. Here the product is one pass (a loop on the
//! CPU, a kernel on a GPU, `posing/cube.rs`), and so is each gradient: `q = A ⊗ B` is linear in
//! either factor with the adjoint `∂B = Ā ⊗ g`, `∂A = g ⊗ B̄` (a quaternion's left or right
//! multiplication matrix transposed is its conjugate's), so the backward is the same op with a
//! factor conjugated.
//!
//! Conventions: `[N, 4]` rows `(w, x, y, z)`, not necessarily of unit norm.

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::Tensor;
use f3g_nets::host::{from_values, host_f32};
use rayon::prelude::*;

use super::columns;

/// The Hamilton product `a ⊗ b` of `[N, 4]` quaternions (w, x, y, z): one op
/// ([`QuaternionBackend`]) where the backend has it, [`quat_mul_as_tensors`] elsewhere.
pub fn quat_mul(a: Tensor<2>, b: Tensor<2>) -> Tensor<2> {
    assert_eq!(a.dims(), b.dims(), "quaternion rows pair up");
    assert_eq!(a.dims()[1], 4, "quaternions have four components");
    if has_op(&a) {
        Tensor::from_dispatch(<Dispatch as QuaternionBackend>::quat_mul(
            a.into_dispatch(),
            b.into_dispatch(),
            false,
            false,
        ))
    } else {
        quat_mul_as_tensors(a, b)
    }
}

/// Whether `t`'s backend implements [`QuaternionBackend`] for its rows.
fn has_op(t: &Tensor<2>) -> bool {
    super::op_runs(t, t.shape().num_elements())
}

/// [`quat_mul`] in Burn's tensor ops (the reference the op is tested against, and the path of
/// backends without the op).
pub fn quat_mul_as_tensors(a: Tensor<2>, b: Tensor<2>) -> Tensor<2> {
    let [w1, x1, y1, z1] = columns(&a);
    let [w2, x2, y2, z2] = columns(&b);
    let w = w1.clone() * w2.clone()
        - x1.clone() * x2.clone()
        - y1.clone() * y2.clone()
        - z1.clone() * z2.clone();
    let x = w1.clone() * x2.clone() + x1.clone() * w2.clone() + y1.clone() * z2.clone()
        - z1.clone() * y2.clone();
    let y = w1.clone() * y2.clone() - x1.clone() * z2.clone()
        + y1.clone() * w2.clone()
        + z1.clone() * x2.clone();
    let z = w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2;
    Tensor::cat(vec![w, x, y, z], 1)
}

/// The product as a backend op.
#[backend_extension(
    Autodiff,
    Flex,
    Cube: cfg(any(feature = "gpu", feature = "cuda")),
    Fusion: cfg(all(any(feature = "gpu", feature = "cuda"), feature = "fusion"))
)]
pub trait QuaternionBackend: Backend {
    /// `A ⊗ B` of `[N, 4]` rows, where `A` is `a` or, with `conjugate_a`, its conjugate (`B`
    /// likewise): the product and both its gradients.
    #[fusion(dtype = a, shape = a)]
    fn quat_mul(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        conjugate_a: bool,
        conjugate_b: bool,
    ) -> FloatTensor<Self>;
}

/// One row's product, conjugating either factor as asked (the CPU's loop and the reference of
/// the GPU kernel's arithmetic).
pub(super) fn hamilton(a: [f32; 4], b: [f32; 4], conjugate_a: bool, conjugate_b: bool) -> [f32; 4] {
    let sign = |conjugate: bool| if conjugate { -1.0 } else { 1.0 };
    let (sa, sb) = (sign(conjugate_a), sign(conjugate_b));
    let [w1, x1, y1, z1] = [a[0], sa * a[1], sa * a[2], sa * a[3]];
    let [w2, x2, y2, z2] = [b[0], sb * b[1], sb * b[2], sb * b[3]];
    [
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ]
}

impl QuaternionBackend for Flex {
    fn quat_mul(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        conjugate_a: bool,
        conjugate_b: bool,
    ) -> FloatTensor<Self> {
        let shape = a.shape().dims::<2>();
        let (a, b) = (host_f32(&a), host_f32(&b));
        let mut out = vec![0.0f32; a.len()];
        out.par_chunks_mut(4)
            .zip(a.par_chunks(4).zip(b.par_chunks(4)))
            .for_each(|(q, (a, b))| {
                let row = |v: &[f32]| [v[0], v[1], v[2], v[3]];
                q.copy_from_slice(&hamilton(row(a), row(b), conjugate_a, conjugate_b));
            });
        from_values(out, shape.to_vec())
    }
}

#[derive(Debug)]
struct QuatMulBackward;

impl<B: Backend + QuaternionBackend> Backward<B, 2> for QuatMulBackward {
    /// Both factors and their conjugation flags.
    type State = (FloatTensor<B>, FloatTensor<B>, bool, bool);

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (a, b, conjugate_a, conjugate_b) = ops.state;
        let [a_node, b_node] = ops.parents;
        // q = A ⊗ B: ∂A = g ⊗ B̄ and ∂B = Ā ⊗ g; a conjugated factor's gradient is the
        // conjugate of its conjugate's, conj(p ⊗ r) = r̄ ⊗ p̄.
        if let Some(node) = a_node {
            let d_a = if conjugate_a {
                B::quat_mul(b.clone(), grad.clone(), conjugate_b, true)
            } else {
                B::quat_mul(grad.clone(), b, false, !conjugate_b)
            };
            grads.register::<B>(node.id, d_a);
        }
        if let Some(node) = b_node {
            let d_b = if conjugate_b {
                B::quat_mul(grad, a, true, conjugate_a)
            } else {
                B::quat_mul(a, grad, !conjugate_a, false)
            };
            grads.register::<B>(node.id, d_b);
        }
    }
}

impl<B: Backend + QuaternionBackend, C: CheckpointStrategy> QuaternionBackend for Autodiff<B, C> {
    fn quat_mul(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        conjugate_a: bool,
        conjugate_b: bool,
    ) -> FloatTensor<Self> {
        let nodes = [a.node(), b.node()];
        let (a, b) = (a.into_primitive(), b.into_primitive());
        let out = B::quat_mul(a.clone(), b.clone(), conjugate_a, conjugate_b);
        match QuatMulBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((a, b, conjugate_a, conjugate_b), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};

    fn rows(n: usize, phase: f32) -> Vec<f32> {
        (0..4 * n)
            .map(|i| (i as f32 * 0.61 + phase).sin())
            .collect()
    }

    fn tensor(values: Vec<f32>, device: &Device) -> Tensor<2> {
        let n = values.len() / 4;
        Tensor::from_data(TensorData::new(values, [n, 4]), device)
    }

    fn values(t: Tensor<2>) -> Vec<f32> {
        crate::model::host_values(t)
    }

    fn assert_close(a: &[f32], b: &[f32], tolerance: f32, what: &str) {
        assert_eq!(a.len(), b.len(), "{what}");
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!((x - y).abs() <= tolerance, "{what}[{i}]: {x} vs {y}");
        }
    }

    /// The op and its gradients (both factors tracked, then only the second, as posing tracks
    /// it) equal the tensor ops' on the CPU, for rows of any norm.
    #[test]
    fn the_product_and_its_gradients_equal_the_tensor_ops() {
        let device = Device::flex().autodiff();
        let (av, bv, gv) = (rows(37, 0.2), rows(37, 1.3), rows(37, 2.9));
        for a_tracked in [true, false] {
            let run = |op: fn(Tensor<2>, Tensor<2>) -> Tensor<2>| {
                let a = tensor(av.clone(), &device);
                let a = if a_tracked { a.require_grad() } else { a };
                let b = tensor(bv.clone(), &device).require_grad();
                let q = op(a.clone(), b.clone());
                let loss = (q.clone() * tensor(gv.clone(), &device)).sum();
                let grads = loss.backward();
                let d_a = a.grad(&grads).map(values);
                let d_b = values(b.grad(&grads).expect("b is tracked"));
                (values(q), d_a, d_b)
            };
            let (q, d_a, d_b) = run(quat_mul);
            let (q_ref, d_a_ref, d_b_ref) = run(quat_mul_as_tensors);
            assert!(has_op(&tensor(av.clone(), &device)), "the CPU has the op");
            assert_close(&q, &q_ref, 1e-6, "product");
            assert_close(&d_b, &d_b_ref, 1e-6, "b's gradient");
            assert_eq!(d_a.is_some(), a_tracked);
            if let (Some(d_a), Some(d_a_ref)) = (d_a, d_a_ref) {
                assert_close(&d_a, &d_a_ref, 1e-6, "a's gradient");
            }
        }
    }

    /// Every conjugation the backward uses: `hamilton` with a flag equals the product with that
    /// factor conjugated by hand, and the op's gradients of a conjugated product match central
    /// differences (the backward's conjugated branches are reached only this way).
    #[test]
    fn conjugated_products_and_their_gradients_match_central_differences() {
        let conj = |q: [f32; 4]| [q[0], -q[1], -q[2], -q[3]];
        let (a, b) = ([0.3, -0.8, 0.5, 0.1], [-0.4, 0.2, 0.9, -0.6]);
        for (ca, cb) in [(false, false), (true, false), (false, true), (true, true)] {
            let by_hand = hamilton(
                if ca { conj(a) } else { a },
                if cb { conj(b) } else { b },
                false,
                false,
            );
            assert_eq!(hamilton(a, b, ca, cb), by_hand, "flags {ca} {cb}");
        }
        let device = Device::flex().autodiff();
        let (av, bv, gv) = (rows(3, 0.4), rows(3, 1.1), rows(3, 2.2));
        let loss_of = |av: &[f32], bv: &[f32], ca: bool, cb: bool| -> f64 {
            let q = <Flex as QuaternionBackend>::quat_mul(
                from_values(av.to_vec(), vec![3, 4]),
                from_values(bv.to_vec(), vec![3, 4]),
                ca,
                cb,
            );
            host_f32(&q)
                .iter()
                .zip(&gv)
                .map(|(q, g)| (*q as f64) * (*g as f64))
                .sum()
        };
        for (ca, cb) in [(true, false), (false, true), (true, true)] {
            let a = tensor(av.clone(), &device).require_grad();
            let b = tensor(bv.clone(), &device).require_grad();
            let q = Tensor::from_dispatch(<Dispatch as QuaternionBackend>::quat_mul(
                a.clone().into_dispatch(),
                b.clone().into_dispatch(),
                ca,
                cb,
            ));
            let grads = (q * tensor(gv.clone(), &device)).sum().backward();
            let analytic = [
                values(a.grad(&grads).unwrap()),
                values(b.grad(&grads).unwrap()),
            ];
            let h = 1e-3f32;
            for (which, analytic) in analytic.iter().enumerate() {
                for i in 0..12 {
                    let (mut plus, mut minus) =
                        ([av.clone(), bv.clone()], [av.clone(), bv.clone()]);
                    plus[which][i] += h;
                    minus[which][i] -= h;
                    let numeric = (loss_of(&plus[0], &plus[1], ca, cb)
                        - loss_of(&minus[0], &minus[1], ca, cb))
                        / (2.0 * h as f64);
                    assert!(
                        (numeric as f32 - analytic[i]).abs() < 1e-3,
                        "flags {ca} {cb}, factor {which}, value {i}: {numeric} vs {}",
                        analytic[i]
                    );
                }
            }
        }
    }
}
