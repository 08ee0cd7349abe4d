//! The GPU kernels (`f3g_splat::cube`) against the CPU path, on a wgpu device (Mesa lavapipe
//! in CI; `cargo test --release -p f3g-splat --features gpu --test gpu`).
//!
//! Projection: every Gaussian of random scenes (SH degrees 0–3, Gaussians behind the near
//! plane, across the image border, off-screen, nearly transparent) gets the CPU's screen
//! values to 1e-5 relative, the same radii and tile counts (a radius may differ by one where
//! `k√Σ₂ᴅ` lies within 1e-4 of a whole number: f32 rounding in a different order), and the
//! same culling.
#![cfg(feature = "gpu")]

mod common;

use burn::backend::ops::{FloatTensorOps, IntTensorOps};
use burn::backend::{Cube, DispatchDevice};
use burn::tensor::{DeviceKind, TensorData};
use f3g_splat::cpu::{self, GaussianSlices, TILE_SIZE};
use f3g_splat::cube;
use f3g_splat::op::GaussianTensors;

type CubeDevice = <Cube as burn::backend::BackendTypes>::Device;

fn device() -> CubeDevice {
    match burn::tensor::Device::wgpu(DeviceKind::DefaultDevice).as_dispatch() {
        DispatchDevice::Cube(d) => d.clone(),
        #[allow(unreachable_patterns)]
        _ => unreachable!("a wgpu device is a cubecl device"),
    }
}

fn upload(
    v: &[f32],
    shape: &[usize],
    device: &CubeDevice,
) -> burn::backend::tensor::FloatTensor<Cube> {
    Cube::float_from_data(TensorData::new(v.to_vec(), shape.to_vec()), device)
}

fn floats(t: burn::backend::tensor::FloatTensor<Cube>) -> Vec<f32> {
    let data = burn::tensor::read_sync(Cube::float_into_data(t)).unwrap();
    data.try_into_vec::<f32>().unwrap()
}

fn ints(t: burn::backend::tensor::IntTensor<Cube>) -> Vec<i32> {
    let data = burn::tensor::read_sync(Cube::int_into_data(t)).unwrap();
    data.convert::<i32>().try_into_vec::<i32>().unwrap()
}

/// A scene in f32 with some Gaussians moved behind the camera, off-screen or made faint.
fn scene(seed: u64, n: usize, degree: usize) -> common::Scene {
    let mut s = common::random_scene(seed, n, degree, 0.999, 61, 47);
    for i in 0..n {
        match i % 7 {
            0 => s.means[3 * i + 2] = 3.5, // behind the camera (it looks along −z from z = 3)
            1 => s.means[3 * i] += 2.5,    // off-screen or across the border
            2 => s.opacity_logits[i] = -6.5, // below 1/255: culled
            _ => {}
        }
    }
    s
}

#[test]
fn projection_matches_the_cpu() {
    let device = device();
    for (seed, degree) in [(1, 0), (2, 1), (3, 2), (4, 3), (5, 3)] {
        let s = scene(seed, 300, degree);
        let f = |v: &[f64]| common::Scene::to_f32(v);
        let (means, log_scales, quats, opacity, sh) = (
            f(&s.means),
            f(&s.log_scales),
            f(&s.quats),
            f(&s.opacity_logits),
            f(&s.sh),
        );
        let n = s.len();
        let k = sh.len() / (3 * n);
        let expected = cpu::project(
            &GaussianSlices {
                means: &means,
                log_scales: &log_scales,
                quats: &quats,
                opacity_logits: &opacity,
                sh: &sh,
            },
            &s.camera,
        );
        let inputs = GaussianTensors::<Cube> {
            means: upload(&means, &[n, 3], &device),
            log_scales: upload(&log_scales, &[n, 3], &device),
            quats: upload(&quats, &[n, 4], &device),
            opacity_logits: upload(&opacity, &[n], &device),
            sh: upload(&sh, &[n, k, 3], &device),
            background: upload(&[0.0; 3], &[3], &device),
        };
        let got = cube::project(&inputs, &s.camera);
        let (screen, radii, tiles) = (floats(got.screen), ints(got.radii), ints(got.tiles));
        let mut visible = 0;
        for (i, e) in expected.iter().enumerate() {
            let r = [radii[2 * i] as u32, radii[2 * i + 1] as u32];
            assert_eq!(
                e.is_visible(),
                r != [0, 0],
                "seed {seed}, Gaussian {i}: culling differs ({e:?} vs radii {r:?})"
            );
            if !e.is_visible() {
                assert!(screen[10 * i..10 * i + 10].iter().all(|&v| v == 0.0));
                assert_eq!(tiles[i], 0);
                continue;
            }
            visible += 1;
            let want = [
                e.mean[0], e.mean[1], e.conic[0], e.conic[1], e.conic[2], e.color[0], e.color[1],
                e.color[2], e.opacity, e.depth,
            ];
            for (j, (&g, &w)) in screen[10 * i..10 * i + 10].iter().zip(&want).enumerate() {
                assert!(
                    (g - w).abs() <= 1e-5 * w.abs().max(1.0),
                    "seed {seed}, Gaussian {i}, screen[{j}]: {g} vs {w}"
                );
            }
            for (axis, (&g, &w)) in r.iter().zip(&e.radii).enumerate() {
                assert!(
                    g.abs_diff(w) <= 1,
                    "seed {seed}, Gaussian {i}, radius {axis}: {g} vs {w}"
                );
            }
            if r == e.radii {
                let [x0, x1, y0, y1] = e.pixels.map(|v| v as usize);
                let t = TILE_SIZE;
                let want_tiles = ((x1 - 1) / t - x0 / t + 1) * ((y1 - 1) / t - y0 / t + 1);
                assert_eq!(tiles[i] as usize, want_tiles, "seed {seed}, Gaussian {i}");
            }
        }
        assert!(
            visible > n / 3,
            "seed {seed}: only {visible} of {n} visible"
        );
        assert!(visible < n, "seed {seed}: nothing was culled");
    }
}

#[test]
fn an_empty_scene_projects_to_nothing() {
    let device = device();
    let s = scene(9, 1, 0);
    let inputs = GaussianTensors::<Cube> {
        means: upload(&[], &[0, 3], &device),
        log_scales: upload(&[], &[0, 3], &device),
        quats: upload(&[], &[0, 4], &device),
        opacity_logits: upload(&[], &[0], &device),
        sh: upload(&[], &[0, 1, 3], &device),
        background: upload(&[0.0; 3], &[3], &device),
    };
    let got = cube::project(&inputs, &s.camera);
    assert!(floats(got.screen).is_empty());
}

#[test]
fn exclusive_scan_matches_a_running_sum() {
    let device = device();
    // Several block sizes: one partial block, exactly one, many (a second level), and enough
    // for a third level of block totals (256² < 70 000).
    for n in [1usize, 5, 256, 257, 1000, 70_000] {
        let values: Vec<i32> = (0..n).map(|i| ((i * 7919) % 13) as i32).collect();
        let t = Cube::int_from_data(TensorData::new(values.clone(), [n]), &device);
        let got = ints(cube::exclusive_scan(t));
        let mut sum = 0;
        let want: Vec<i32> = values
            .iter()
            .map(|&v| {
                let before = sum;
                sum += v;
                before
            })
            .collect();
        assert_eq!(got, want, "n = {n}");
    }
}
