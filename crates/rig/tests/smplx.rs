//! SMPL-X on a generated model file equals a straightforward independent evaluation (the
//! formulas of the SMPL-X paper, written with plain 4×4 matrices), and bad files are rejected
//! with the file and field named.
// The reference evaluation indexes matrices the way the formulas are written.
#![allow(clippy::needless_range_loop)]

use std::path::Path;

use f3g_io::NpyValues::{F32, I64};
use f3g_rig::smplx::{self, SmplParams};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const J: usize = 55;
const V: usize = 40;
const S: usize = 20;

struct Model {
    template: Vec<f32>,
    shapedirs: Vec<f32>,
    posedirs: Vec<f32>,
    regressor: Vec<f32>,
    weights: Vec<f32>,
    parents: Vec<i64>,
    faces: Vec<i64>,
}

/// A random model with SMPL-X's kinematic tree, ≤ 4 skin influences per vertex and
/// 10 betas + 10 expressions (the v1.0 layout).
fn random_model(seed: u64) -> Model {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut r = |a: f32, b: f32| rng.random_range(a..b);
    let template: Vec<f32> = (0..V * 3).map(|_| r(-0.5, 0.5)).collect();
    let shapedirs: Vec<f32> = (0..V * 3 * S).map(|_| r(-0.02, 0.02)).collect();
    let posedirs: Vec<f32> = (0..V * 3 * 486).map(|_| r(-0.01, 0.01)).collect();
    let mut regressor = vec![0.0f32; J * V];
    let mut weights = vec![0.0f32; V * J];
    let mut rng = ChaCha8Rng::seed_from_u64(seed + 1);
    for j in 0..J {
        // Each joint averages three vertices.
        for _ in 0..3 {
            regressor[j * V + rng.random_range(0..V)] += 1.0 / 3.0;
        }
    }
    for v in 0..V {
        let mut total = 0.0;
        for _ in 0..4 {
            let j = rng.random_range(0..J);
            let w = rng.random_range(0.1..1.0);
            weights[v * J + j] += w;
            total += w;
        }
        for j in 0..J {
            weights[v * J + j] /= total;
        }
    }
    // SMPL-X's kinematic tree.
    let parents = vec![
        -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15, 20,
        25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38, 21, 40, 41, 21, 43, 44, 21, 46, 47,
        21, 49, 50, 21, 52, 53,
    ];
    let faces = (0..V as i64 - 2).flat_map(|i| [i, i + 1, i + 2]).collect();
    Model {
        template,
        shapedirs,
        posedirs,
        regressor,
        weights,
        parents,
        faces,
    }
}

fn write_model(path: &Path, m: &Model) {
    let kintree: Vec<i64> = m.parents.iter().copied().chain(0..J as i64).collect();
    f3g_io::write_npz(
        path,
        &[
            ("v_template", &[V, 3], F32(&m.template)),
            ("shapedirs", &[V, 3, S], F32(&m.shapedirs)),
            ("posedirs", &[V, 3, 486], F32(&m.posedirs)),
            ("J_regressor", &[J, V], F32(&m.regressor)),
            ("weights", &[V, J], F32(&m.weights)),
            ("kintree_table", &[2, J], I64(&kintree)),
            ("f", &[m.faces.len() / 3, 3], I64(&m.faces)),
        ],
    )
    .unwrap();
}

type M4 = [[f64; 4]; 4];

fn mul(a: &M4, b: &M4) -> M4 {
    let mut c = [[0.0; 4]; 4];
    for i in 0..4 {
        for j in 0..4 {
            c[i][j] = (0..4).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    c
}

/// Rodrigues' formula.
fn rodrigues(v: [f64; 3]) -> [[f64; 3]; 3] {
    let theta = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-12);
    let k = [v[0] / theta, v[1] / theta, v[2] / theta];
    let kx = [[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]];
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let kx2: f64 = (0..3).map(|m| kx[i][m] * kx[m][j]).sum();
            r[i][j] = (i == j) as u8 as f64 + theta.sin() * kx[i][j] + (1.0 - theta.cos()) * kx2;
        }
    }
    r
}

/// The SMPL-X forward pass as in the paper: shape, pose correctives, joint regression,
/// rigid chain, relative transforms, blend.
fn reference(
    m: &Model,
    betas: &[f64],
    expression: &[f64],
    pose: &[f64],
    transl: [f64; 3],
) -> Vec<[f64; 3]> {
    let mut shaped: Vec<[f64; 3]> = (0..V)
        .map(|v| [0, 1, 2].map(|c| m.template[v * 3 + c] as f64))
        .collect();
    for v in 0..V {
        for c in 0..3 {
            for (s, b) in betas.iter().enumerate() {
                shaped[v][c] += b * m.shapedirs[(v * 3 + c) * S + s] as f64;
            }
            for (e, x) in expression.iter().enumerate() {
                shaped[v][c] += x * m.shapedirs[(v * 3 + c) * S + 10 + e] as f64;
            }
        }
    }
    let joints: Vec<[f64; 3]> = (0..J)
        .map(|j| {
            [0, 1, 2].map(|c| {
                (0..V)
                    .map(|v| m.regressor[j * V + v] as f64 * shaped[v][c])
                    .sum()
            })
        })
        .collect();
    let rots: Vec<[[f64; 3]; 3]> = (0..J)
        .map(|j| rodrigues([pose[3 * j], pose[3 * j + 1], pose[3 * j + 2]]))
        .collect();
    let mut feature = Vec::new();
    for r in &rots[1..] {
        for i in 0..3 {
            for k in 0..3 {
                feature.push(r[i][k] - (i == k) as u8 as f64);
            }
        }
    }
    let mut posed = shaped.clone();
    for v in 0..V {
        for c in 0..3 {
            posed[v][c] += feature
                .iter()
                .enumerate()
                .map(|(f, x)| x * m.posedirs[(v * 3 + c) * 486 + f] as f64)
                .sum::<f64>();
        }
    }
    let mut world: Vec<M4> = Vec::new();
    for j in 0..J {
        let rel = if j == 0 {
            joints[0]
        } else {
            [0, 1, 2].map(|c| joints[j][c] - joints[m.parents[j] as usize][c])
        };
        let mut local = [[0.0; 4]; 4];
        for i in 0..3 {
            local[i][..3].copy_from_slice(&rots[j][i]);
            local[i][3] = rel[i];
        }
        local[3][3] = 1.0;
        world.push(if j == 0 {
            local
        } else {
            mul(&world[m.parents[j] as usize], &local)
        });
    }
    let relative: Vec<M4> = (0..J)
        .map(|j| {
            let mut t = [[0.0; 4]; 4];
            for i in 0..4 {
                t[i][i] = 1.0;
            }
            for i in 0..3 {
                t[i][3] = -joints[j][i];
            }
            mul(&world[j], &t)
        })
        .collect();
    (0..V)
        .map(|v| {
            let mut out = [0.0; 3];
            for j in 0..J {
                let w = m.weights[v * J + j] as f64;
                for i in 0..3 {
                    out[i] += w
                        * ((0..3).map(|k| relative[j][i][k] * posed[v][k]).sum::<f64>()
                            + relative[j][i][3]);
                }
            }
            [out[0] + transl[0], out[1] + transl[1], out[2] + transl[2]]
        })
        .collect()
}

#[test]
fn matches_an_independent_evaluation() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("SMPLX_TEST.npz");
    for seed in 0..4 {
        let m = random_model(seed);
        write_model(&path, &m);
        let rig = smplx::load(&path, 10, 10).unwrap();
        // Checked on its copy through a rig file (linear correctives, the joint model).
        let copy = dir.path().join("rig.npz");
        f3g_rig::file::write(&rig, &copy).unwrap();
        let rig = f3g_rig::file::read(&copy).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(100 + seed);
        let mut params = rig.zero_params();
        params
            .pose
            .iter_mut()
            .for_each(|p| *p = rng.random_range(-0.6..0.6));
        params
            .identity
            .iter_mut()
            .for_each(|p| *p = rng.random_range(-2.0..2.0));
        params
            .expression
            .iter_mut()
            .for_each(|p| *p = rng.random_range(-2.0..2.0));
        let posed = rig.pose(&params).unwrap();
        let f64s = |v: &[f32]| v.iter().map(|&x| x as f64).collect::<Vec<_>>();
        let n = params.pose.len();
        let transl = [n - 3, n - 2, n - 1].map(|i| params.pose[i] as f64);
        let expected = reference(
            &m,
            &f64s(&params.identity),
            &f64s(&params.expression),
            &f64s(&params.pose[..n - 3]),
            transl,
        );
        for (got, want) in posed.vertices.iter().zip(&expected) {
            for c in 0..3 {
                assert!(
                    (got[c] as f64 - want[c]).abs() < 2e-5,
                    "seed {seed}: {got:?} vs {want:?}"
                );
            }
        }
    }
}

#[test]
fn params_round_trip_and_frames() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("smpl_params.npz");
    let n = 3;
    let ramp = |w: usize| (0..n * w).map(|i| i as f32 * 0.01).collect::<Vec<_>>();
    let p = SmplParams {
        frames: n,
        betas: ramp(10)[..10].to_vec(),
        global_orient: ramp(3),
        transl: ramp(3),
        jaw_pose: ramp(3),
        leye_pose: ramp(3),
        reye_pose: ramp(3),
        body_pose: ramp(63),
        left_hand_pose: ramp(45),
        right_hand_pose: ramp(45),
        expression: ramp(10),
    };
    smplx::write_params(&path, &p).unwrap();
    let back = smplx::read_params(&path).unwrap();
    assert_eq!(back, p);
    assert_eq!(back.pose(1).len(), 168);
    assert_eq!(back.pose(1)[0], p.global_orient[3]);
    assert_eq!(back.pose(2)[165..], p.transl[6..9]);
}

#[test]
fn bad_files_name_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("model.npz");
    let m = random_model(9);
    write_model(&model, &m);
    // Drop a key.
    f3g_io::write_npz(&model, &[("v_template", &[V, 3], F32(&m.template))]).unwrap();
    let e = smplx::load(&model, 10, 10).unwrap_err().to_string();
    assert!(
        e.contains("model.npz") && e.contains("missing array `shapedirs`"),
        "{e}"
    );
    // NaN in the weights.
    let mut bad = random_model(9);
    bad.weights[17] = f32::NAN;
    write_model(&model, &bad);
    let e = smplx::load(&model, 10, 10).unwrap_err().to_string();
    assert!(e.contains("`weights`") && e.contains("non-finite"), "{e}");
    // Too many betas for the shape space.
    write_model(&model, &random_model(9));
    let e = smplx::load(&model, 11, 10).unwrap_err().to_string();
    assert!(e.contains("`shapedirs`") && e.contains("11 betas"), "{e}");

    let params = dir.path().join("smpl_params.npz");
    f3g_io::write_npz(
        &params,
        &[
            ("betas", &[1, 10], F32(&[0.0; 10])),
            ("transl", &[2, 3], F32(&[0.0; 6])),
            ("global_orient", &[2, 3], F32(&[0.0; 6])),
            ("body_pose", &[2, 60], F32(&[0.0; 120])),
        ],
    )
    .unwrap();
    let e = smplx::read_params(&params).unwrap_err().to_string();
    assert!(
        e.contains("smpl_params.npz") && e.contains("`body_pose`") && e.contains("[2, 60]"),
        "{e}"
    );
    let mut pose = vec![0.0f32; 126];
    pose[70] = f32::NAN;
    f3g_io::write_npz(
        &params,
        &[
            ("betas", &[1, 10], F32(&[0.0; 10])),
            ("transl", &[2, 3], F32(&[0.0; 6])),
            ("global_orient", &[2, 3], F32(&[0.0; 6])),
            ("body_pose", &[2, 63], F32(&pose)),
        ],
    )
    .unwrap();
    let e = smplx::read_params(&params).unwrap_err().to_string();
    assert!(e.contains("`body_pose`") && e.contains("non-finite"), "{e}");
}
