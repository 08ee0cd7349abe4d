//! The GPU kernels (`f3g_splat::cube`) against the CPU path, on a wgpu device (Mesa lavapipe
//! in CI; `cargo test --release -p f3g-splat --features gpu --test gpu`).
//!
//! Projection: every Gaussian of random scenes (SH degrees 0–3, Gaussians behind the near
//! plane, across the image border, off-screen, nearly transparent) gets the CPU's screen
//! values to 1e-5 relative, the same radii and tile counts (a radius may differ by one where
//! `k√Σ₂ᴅ` lies within 1e-4 of a whole number: f32 rounding in a different order), and the
//! same culling; each Gaussian's run of the (unsorted) intersection list holds its tiles.
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
        let (screen, radii, tiles) = (
            floats(got.screen.clone()),
            ints(got.radii.clone()),
            ints(got.tiles.clone()),
        );
        let inter = cube::intersect(&got, s.camera.width);
        let (tile_of, gaussian_of, offsets) = (
            ints(inter.tile_of),
            ints(inter.gaussian_of),
            ints(inter.offsets),
        );
        assert_eq!(inter.count, tiles.iter().sum::<i32>() as usize);
        let tiles_x = (s.camera.width as usize).div_ceil(TILE_SIZE);
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
                // Its run of the intersection list: its tiles row by row, and its own id.
                let want: Vec<i32> = (y0 / t..=(y1 - 1) / t)
                    .flat_map(|ty| {
                        (x0 / t..=(x1 - 1) / t).map(move |tx| (ty * tiles_x + tx) as i32)
                    })
                    .collect();
                let start = offsets[i] as usize;
                let run = start..start + want.len();
                assert_eq!(tile_of[run.clone()], want[..], "seed {seed}, Gaussian {i}");
                assert!(gaussian_of[run].iter().all(|&g| g == i as i32));
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
        let (scanned, total) = cube::exclusive_scan(t);
        let got = ints(scanned);
        assert_eq!(ints(total), [values.iter().sum::<i32>()], "n = {n}");
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

#[test]
fn radix_sort_is_stable_and_sorts_by_the_low_bits() {
    let device = device();
    for (n, bits) in [
        (1usize, 4u32),
        (37, 8),
        (1024, 12),
        (1025, 32),
        (5000, 20),
        (70_000, 32),
    ] {
        // Keys with many repeats (so stability matters) and bits above `bits` that the sort
        // must ignore; values are the original positions. (Below 2³¹: the upload goes
        // through Cube's i32.)
        let keys: Vec<u32> = (0..n as u64)
            .map(|i| ((i * 2_654_435_761) % 4_294_967_291) as u32 % 97 * 22_111_479)
            .collect();
        let mask = if bits == 32 {
            u32::MAX
        } else {
            (1 << bits) - 1
        };
        let values: Vec<i32> = (0..n as i32).collect();
        let k = Cube::int_from_data(TensorData::new(keys.clone(), [n]), &device);
        let k = Cube::int_cast(k, burn::tensor::IntDType::U32);
        let v = Cube::int_from_data(TensorData::new(values, [n]), &device);
        let (sk, sv) = cube::sort_pairs(k, v, bits);
        let got_values = ints(sv);
        let got_keys: Vec<u32> = {
            let data = burn::tensor::read_sync(Cube::int_into_data(sk)).unwrap();
            data.convert::<u32>().try_into_vec::<u32>().unwrap()
        };
        let mut want: Vec<(u32, i32)> = keys
            .iter()
            .enumerate()
            .map(|(i, &k)| (k, i as i32))
            .collect();
        want.sort_by_key(|&(k, _)| k & mask); // std's sort is stable
        assert_eq!(
            got_values,
            want.iter().map(|p| p.1).collect::<Vec<_>>(),
            "n = {n}, bits = {bits}"
        );
        assert_eq!(
            got_keys,
            want.iter().map(|p| p.0).collect::<Vec<_>>(),
            "n = {n}, bits = {bits}"
        );
    }
}
