//! Light fixed in the world (`world_shading`): every Gaussian's colour is its albedo (what the
//! networks predict) times a smooth function of its posed surface normal in world space,
//! `s_c(n) = Σ_k a_kc · Y_k(n)`, the 9 real spherical harmonics of degree ≤ 2 (3DGS's basis
//! and signs, [`f3g_splat::sh::basis`]) with one learnt coefficient per basis function and
//! colour channel — the irradiance of distant light on a diffuse surface, which degree 2
//! approximates to a few per cent (Ramamoorthi and Hanrahan 2001).
//!
//! Why: a studio's light (and the synthetic capture's) stays where it is while the person
//! moves, so the same patch of skin is brighter facing the light than facing away. Networks
//! conditioned on the pose learn that shading only for poses training showed; a limb raised as
//! no training frame had it keeps the brightness of its training poses (BENCHMARKS, "Where the
//! blotches under new motions come from"). With the shading term the networks need only
//! learn the albedo, and the light follows the normal into any pose.
//!
//! Conventions: normals are the template's surface normals turned by each Gaussian's
//! skinning rotation (body, then face Gaussians); the coefficients are `[9, 3]` row-major
//! (basis function, channel); the neutral light is `a_00 = 1 / Y_0`, every other zero, so
//! `s ≡ 1`. The shading multiplies the degree-0 colour `0.5 + Y_0 · f_dc`; in a baked avatar
//! the higher SH bands (the view-dependent part) are added unshaded.

use burn::module::Param;
use burn::tensor::{Device, Tensor, TensorData};

use f3g_splat::sh;

/// Basis functions of the shading (SH degree ≤ 2).
pub const SHADING_BASIS: usize = 9;

/// Step-size multiplier of the shading's coefficients relative to the networks' `lr`: Adam
/// moves each parameter by about `lr` per step, and the coefficients need to move by O(1)
/// within a demo's few hundred steps. Screened 3, 10, 30 (BENCHMARKS, "The light fixed in the
/// world"): 30 beats 10 on the head by +0.27 dB and −0.006 LPIPS over three seeds, 3 is worse.
pub const SHADING_STEP: f32 = 30.0;

/// The neutral light: `[9, 3]` coefficients with `s(n) = 1` for every normal.
pub fn neutral_coefficients() -> [f32; SHADING_BASIS * 3] {
    let mut a = [0.0; SHADING_BASIS * 3];
    a[..3].fill(1.0 / sh::SH_C0 as f32);
    a
}

/// The learnable parameters of the shading: `[9, 3]`, zero at the start (the neutral light).
pub fn initial_parameters(device: &Device) -> Param<Tensor<2>> {
    Param::from_tensor(Tensor::zeros([SHADING_BASIS, 3], device))
}

/// The coefficients `[9, 3]` the parameters stand for.
pub fn coefficients(parameters: &Param<Tensor<2>>) -> Tensor<2> {
    let p = parameters.val();
    let neutral = Tensor::<2>::from_data(
        TensorData::new(neutral_coefficients().to_vec(), [SHADING_BASIS, 3]),
        &p.device(),
    );
    neutral + p * SHADING_STEP
}

/// The shading `[N, 3]` (per Gaussian and channel) of unit normals `[N, 3]` under `[9, 3]`
/// coefficients.
pub fn shade(coefficients: Tensor<2>, normals: &Tensor<2>) -> Tensor<2> {
    basis(normals).matmul(coefficients)
}

/// The degree ≤ 2 SH basis `[N, 9]` of unit vectors `[N, 3]`, as [`sh::basis`] computes it.
fn basis(v: &Tensor<2>) -> Tensor<2> {
    let n = v.dims()[0];
    let column = |k: usize| v.clone().slice([0..n, k..k + 1]);
    let (x, y, z) = (column(0), column(1), column(2));
    let (xx, yy, zz) = (
        x.clone() * x.clone(),
        y.clone() * y.clone(),
        z.clone() * z.clone(),
    );
    let c1 = sh::SH_C1 as f32;
    let c2 = sh::SH_C2.map(|c| c as f32);
    Tensor::cat(
        vec![
            Tensor::ones([n, 1], &v.device()) * sh::SH_C0 as f32,
            y.clone() * -c1,
            z.clone() * c1,
            x.clone() * -c1,
            x.clone() * y.clone() * c2[0],
            y * z.clone() * c2[1],
            (zz * 2.0 - xx.clone() - yy.clone()) * c2[2],
            x * z * c2[3],
            (xx - yy) * c2[4],
        ],
        1,
    )
}

/// [`shade`] for one unit normal on the host, with coefficients as [`neutral_coefficients`]
/// lays them out.
pub fn shade_host(coefficients: &[f32], normal: [f32; 3]) -> [f32; 3] {
    let mut y = [0.0f32; 16];
    sh::basis(SHADING_BASIS, normal, &mut y);
    std::array::from_fn(|c| {
        (0..SHADING_BASIS)
            .map(|k| y[k] * coefficients[3 * k + c])
            .sum()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::host_values;

    fn tensor(values: Vec<f32>, shape: [usize; 2]) -> Tensor<2> {
        Tensor::from_data(TensorData::new(values, shape), &Device::flex())
    }

    /// The tensor basis is 3DGS's: the shading of random normals under random coefficients
    /// equals the host's, which uses `sh::basis`.
    #[test]
    fn the_tensor_shading_equals_the_host_shading() {
        let mut state = 7u64;
        let mut random = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        };
        let normals: Vec<[f32; 3]> = (0..50)
            .map(|_| {
                let v = [random(), random(), random()];
                let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
                v.map(|c| c / l)
            })
            .collect();
        let a: Vec<f32> = (0..SHADING_BASIS * 3).map(|_| random()).collect();
        let got = host_values(shade(
            tensor(a.clone(), [SHADING_BASIS, 3]),
            &tensor(normals.concat(), [normals.len(), 3]),
        ));
        for (i, n) in normals.iter().enumerate() {
            let want = shade_host(&a, *n);
            for c in 0..3 {
                assert!(
                    (got[3 * i + c] - want[c]).abs() < 1e-5,
                    "normal {i} channel {c}: {} against {}",
                    got[3 * i + c],
                    want[c]
                );
            }
        }
    }

    /// Zero parameters are the neutral light, and a light from +Y brightens normals facing up
    /// more than normals facing down.
    #[test]
    fn the_neutral_light_is_one_and_a_light_from_above_lights_the_top() {
        let device = Device::flex();
        let neutral = coefficients(&initial_parameters(&device));
        let normals = tensor(vec![0.0, 1.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0], [3, 3]);
        let s = host_values(shade(neutral, &normals));
        assert!(s.iter().all(|v| (v - 1.0).abs() < 1e-6), "{s:?}");
        // Y_1 = −C1·y: a negative coefficient on it lights +Y.
        let mut a = neutral_coefficients();
        a[3..6].fill(-0.5);
        let s = host_values(shade(tensor(a.to_vec(), [SHADING_BASIS, 3]), &normals));
        assert!(
            s[0] > 1.2 && s[3] < 0.8 && (s[6] - 1.0).abs() < 1e-6,
            "{s:?}"
        );
    }
}
