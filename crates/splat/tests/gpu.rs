//! The GPU kernels (`f3g_splat::cube`) and the op on a GPU against the CPU path: on a wgpu
//! device (Mesa lavapipe in CI; `cargo test --release -p f3g-splat --features gpu --test
//! gpu`) or, with `F3G_TEST_DEVICE=cuda` and `--features cuda`, on the first CUDA GPU.
//!
//! Projection: every Gaussian of random scenes (SH degrees 0–3, Gaussians behind the near
//! plane, across the image border, off-screen, nearly transparent) gets the CPU's screen
//! values to 1e-5 relative, the same radii and tile counts (a radius may differ by one where
//! `k√Σ₂ᴅ` lies within 1e-4 of a whole number: f32 rounding in a different order), and the
//! same culling; where all radii agree, the tile bins equal the CPU's entry for entry. The
//! whole op (forward and gradients) equals the CPU op; every way of summing the backward's
//! gradients that the device supports gives the same sums.
#![cfg(any(feature = "gpu", feature = "cuda"))]

mod common;

use burn::backend::DispatchDevice;
use burn::backend::ops::{FloatTensorOps, IntTensorOps};
use burn::tensor::TensorData;
use burn_cubecl::CubeBackend;
use f3g_splat::cpu;
use f3g_splat::cube;
use f3g_splat::op::GaussianTensors;
use f3g_splat::semantics::{GaussianSlices, TILE_SIZE};

type CubeDevice = <CubeBackend as burn::backend::BackendTypes>::Device;

/// The device under test: wgpu's default adapter (lavapipe in CI), or the first CUDA GPU
/// when `F3G_TEST_DEVICE=cuda` (build with `--features cuda`).
fn test_device() -> burn::tensor::Device {
    if std::env::var("F3G_TEST_DEVICE").as_deref() == Ok("cuda") {
        #[cfg(feature = "cuda")]
        return burn::tensor::Device::cuda(0usize);
        #[cfg(not(feature = "cuda"))]
        panic!("F3G_TEST_DEVICE=cuda needs the `cuda` feature");
    }
    #[cfg(feature = "gpu")]
    return burn::tensor::Device::wgpu(burn::tensor::DeviceKind::DefaultDevice);
    #[cfg(not(feature = "gpu"))]
    panic!("without the `gpu` feature, set F3G_TEST_DEVICE=cuda");
}

fn device() -> CubeDevice {
    match test_device().as_dispatch() {
        DispatchDevice::Cube(d) => d.clone(),
        #[allow(unreachable_patterns)]
        _ => unreachable!("wgpu and CUDA devices are cubecl devices"),
    }
}

fn upload(
    v: &[f32],
    shape: &[usize],
    device: &CubeDevice,
) -> burn::backend::tensor::FloatTensor<CubeBackend> {
    CubeBackend::float_from_data(TensorData::new(v.to_vec(), shape.to_vec()), device)
}

fn floats(t: burn::backend::tensor::FloatTensor<CubeBackend>) -> Vec<f32> {
    let data = burn::tensor::read_sync(CubeBackend::float_into_data(t)).unwrap();
    data.try_into_vec::<f32>().unwrap()
}

fn ints(t: burn::backend::tensor::IntTensor<CubeBackend>) -> Vec<i32> {
    let data = burn::tensor::read_sync(CubeBackend::int_into_data(t)).unwrap();
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
fn projection_and_bins_match_the_cpu() {
    let device = device();
    let mut binned = 0;
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
        let inputs = GaussianTensors::<CubeBackend> {
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
        let depth = cube::depth_order(&got);
        let count = depth.count();
        assert_eq!(count, tiles.iter().sum::<i32>() as usize);
        let bins = cube::bin_tiles(&got, &depth, count, s.camera.width, s.camera.height);
        let (offsets, ids) = (ints(bins.offsets), ints(bins.ids));
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
        // Where the footprints agree, so do the bins: tile by tile, front to back.
        if (0..n).all(|i| [radii[2 * i] as u32, radii[2 * i + 1] as u32] == expected[i].radii) {
            let want = cpu::bin_tiles(&expected, s.camera.width as usize, s.camera.height as usize);
            let as_i32 = |v: &[u32]| v.iter().map(|&x| x as i32).collect::<Vec<_>>();
            assert_eq!(offsets, as_i32(&want.offsets), "seed {seed}: tile offsets");
            assert_eq!(ids, as_i32(&want.ids), "seed {seed}: tile lists");
            binned += 1;
        }
        assert!(
            visible > n / 3,
            "seed {seed}: only {visible} of {n} visible"
        );
        assert!(visible < n, "seed {seed}: nothing was culled");
    }
    assert!(binned >= 3, "only {binned} scenes had identical footprints");
}

#[test]
fn an_empty_scene_projects_to_nothing() {
    let device = device();
    let s = scene(9, 1, 0);
    let inputs = GaussianTensors::<CubeBackend> {
        means: upload(&[], &[0, 3], &device),
        log_scales: upload(&[], &[0, 3], &device),
        quats: upload(&[], &[0, 4], &device),
        opacity_logits: upload(&[], &[0], &device),
        sh: upload(&[], &[0, 1, 3], &device),
        background: upload(&[0.0; 3], &[3], &device),
    };
    let got = cube::project(&inputs, &s.camera);
    assert!(floats(got.screen.clone()).is_empty());
    let depth = cube::depth_order(&got);
    assert_eq!(depth.count(), 0);
    let bins = cube::bin_tiles(&got, &depth, 0, s.camera.width, s.camera.height);
    assert!(ints(bins.offsets).iter().all(|&o| o == 0));
}

#[test]
fn exclusive_scan_matches_a_running_sum() {
    let device = device();
    // Several block sizes: one partial block, exactly one, many (a second level), and enough
    // for a third level of block totals (256² < 70 000).
    for n in [1usize, 5, 256, 257, 1000, 70_000] {
        let values: Vec<i32> = (0..n).map(|i| ((i * 7919) % 13) as i32).collect();
        let t = CubeBackend::int_from_data(TensorData::new(values.clone(), [n]), &device);
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
    for (n, bits) in [
        (1usize, 4u32),
        (37, 8),
        (1024, 12),
        (1025, 32),
        (5000, 20),
        (70_000, 32),
    ] {
        check_sort(n, bits, None);
    }
}

/// Past 65 535 cubes the grid has more than one row and its last row runs past the work: the
/// kernels must ignore those cubes (the histogram kernel once wrote their zeros into the next
/// bin's counts, corrupting the sort above ~67 M pairs). Grids of 3 cubes per row make the
/// same shape from 10 blocks, and 7 per row make the scan recurse over several rows too.
#[test]
fn sort_and_scan_ignore_the_cubes_past_the_work_of_a_multi_row_grid() {
    for (n, bits, row) in [(10 * 1024, 12u32, 3usize), (9_000, 32, 7), (70_000, 16, 5)] {
        check_sort(n, bits, Some(row));
    }
    let device = device();
    for (n, row) in [(2_500usize, 3usize), (70_000, 4)] {
        let values: Vec<i32> = (0..n).map(|i| ((i * 31) % 7) as i32).collect();
        let t = CubeBackend::int_from_data(TensorData::new(values.clone(), [n]), &device);
        let (scanned, total) = cube::exclusive_scan_in_rows(t, row);
        assert_eq!(
            ints(total),
            [values.iter().sum::<i32>()],
            "n = {n}, row = {row}"
        );
        let got = ints(scanned);
        let mut sum = 0;
        for (i, v) in values.iter().enumerate() {
            assert_eq!(got[i], sum, "n = {n}, row = {row}, at {i}");
            sum += v;
        }
    }
}

/// Sorts `n` keys with many repeats by their low `bits` bits (on grids of `row` cubes per row
/// when given) and checks the order and its stability against std's stable sort.
fn check_sort(n: usize, bits: u32, row: Option<usize>) {
    let device = device();
    // Keys with many repeats (so stability matters) and bits above `bits` that the sort must
    // ignore; values are the original positions. (Below 2³¹: the upload goes through Cube's
    // i32.)
    let keys: Vec<u32> = (0..n as u64)
        .map(|i| ((i * 2_654_435_761) % 4_294_967_291) as u32 % 97 * 22_111_479)
        .collect();
    let mask = if bits == 32 {
        u32::MAX
    } else {
        (1 << bits) - 1
    };
    let values: Vec<i32> = (0..n as i32).collect();
    let k = CubeBackend::int_from_data(TensorData::new(keys.clone(), [n]), &device);
    let k = CubeBackend::int_cast(k, burn::tensor::IntDType::U32);
    let v = CubeBackend::int_from_data(TensorData::new(values, [n]), &device);
    let (sk, sv) = match row {
        Some(row) => cube::sort_pairs_in_rows(k, v, bits, row),
        None => cube::sort_pairs(k, v, bits),
    };
    let got_values = ints(sv);
    let got_keys: Vec<u32> = {
        let data = burn::tensor::read_sync(CubeBackend::int_into_data(sk)).unwrap();
        data.convert::<u32>().try_into_vec::<u32>().unwrap()
    };
    let mut want: Vec<(u32, i32)> = keys
        .iter()
        .enumerate()
        .map(|(i, &k)| (k, i as i32))
        .collect();
    want.sort_by_key(|&(k, _)| k & mask); // std's sort is stable
    assert_eq!(got_values.len(), n);
    // The first pair out of place, not 10⁴ numbers.
    let wrong = (0..n).find(|&i| (got_keys[i], got_values[i]) != want[i]);
    assert!(
        wrong.is_none(),
        "n = {n}, bits = {bits}, row = {row:?}: from slot {}, {} pairs out of place",
        wrong.unwrap_or(0),
        (0..n)
            .filter(|&i| (got_keys[i], got_values[i]) != want[i])
            .count()
    );
}

/// A render and its gradients (loss = Σ weights · outputs) on `device`.
struct Rendered {
    color: Vec<f32>,
    alpha: Vec<f32>,
    depth: Vec<f32>,
    grads: Vec<(&'static str, Vec<f32>)>,
}

fn render_with_grads(s: &common::Scene, device: &burn::tensor::Device) -> Rendered {
    use burn::tensor::Tensor;
    let cloud = f3g_splat::GaussianCloud {
        means: common::Scene::to_f32(&s.means),
        log_scales: common::Scene::to_f32(&s.log_scales),
        quats: common::Scene::to_f32(&s.quats),
        opacity_logits: common::Scene::to_f32(&s.opacity_logits),
        sh: common::Scene::to_f32(&s.sh),
        sh_degree: f3g_splat::sh::degree_for(s.sh.len() / (3 * s.len())).unwrap(),
    };
    let g = cloud.to_tensors(device);
    let g = f3g_splat::Gaussians {
        means: g.means.require_grad(),
        log_scales: g.log_scales.require_grad(),
        quats: g.quats.require_grad(),
        opacity_logits: g.opacity_logits.require_grad(),
        sh: g.sh.require_grad(),
    };
    let bg = Tensor::<1>::from_data(
        TensorData::new(s.background.map(|v| v as f32).to_vec(), [3]),
        device,
    )
    .require_grad();
    let out = f3g_splat::render(&g, &s.camera, bg.clone(), &Default::default()).unwrap();
    let (w, h) = (s.camera.width as usize, s.camera.height as usize);
    let (wc, wa, wd) = common::loss_weights(5, w * h);
    let weights = |v: &[f64], shape: Vec<usize>| {
        Tensor::<3>::from_data(TensorData::new(common::Scene::to_f32(v), shape), device)
    };
    let loss = (out.color.clone() * weights(&wc, vec![h, w, 3])).sum()
        + (out.alpha.clone().reshape([h, w, 1]) * weights(&wa, vec![h, w, 1])).sum()
        + (out.depth.clone().reshape([h, w, 1]) * weights(&wd, vec![h, w, 1])).sum();
    let grads = loss.backward();
    let v = |t: Tensor<3>| t.to_data().convert::<f32>().try_into_vec::<f32>().unwrap();
    let flat = |t: Tensor<2>| t.to_data().convert::<f32>().try_into_vec::<f32>().unwrap();
    let one = |t: Tensor<1>| t.to_data().convert::<f32>().try_into_vec::<f32>().unwrap();
    Rendered {
        color: v(out.color),
        alpha: flat(out.alpha),
        depth: flat(out.depth),
        grads: vec![
            ("means", flat(g.means.grad(&grads).unwrap())),
            ("log_scales", flat(g.log_scales.grad(&grads).unwrap())),
            ("quats", flat(g.quats.grad(&grads).unwrap())),
            (
                "opacity_logits",
                one(g.opacity_logits.grad(&grads).unwrap()),
            ),
            ("sh", v(g.sh.grad(&grads).unwrap())),
            ("background", one(bg.grad(&grads).unwrap())),
        ],
    }
}

/// The whole op on wgpu against the CPU op: images to 1e-5, gradients to 1e-4 of the largest
/// one of their kind (atomics sum tiles in any order).
fn assert_op_matches_the_cpu(name: &str, s: &common::Scene) {
    let gpu = render_with_grads(s, &test_device().autodiff());
    let cpu = render_with_grads(s, &burn::tensor::Device::flex().autodiff());
    for (what, got, want) in [
        ("colour", &gpu.color, &cpu.color),
        ("alpha", &gpu.alpha, &cpu.alpha),
        ("depth", &gpu.depth, &cpu.depth),
    ] {
        assert_eq!(got.len(), want.len());
        for (i, (a, b)) in got.iter().zip(want.iter()).enumerate() {
            assert!(
                (a - b).abs() <= 1e-5 * (1.0 + b.abs()),
                "{name}: {what}[{i}]: {a} vs {b}"
            );
        }
    }
    for ((field, got), (_, want)) in gpu.grads.iter().zip(&cpu.grads) {
        let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
        assert!(scale > 1e-6, "{name}: the {field} gradient vanished");
        for (i, (a, b)) in got.iter().zip(want).enumerate() {
            assert!(
                (a - b).abs() <= 1e-4 * scale,
                "{name}: ∂L/∂{field}[{i}]: {a} vs {b} (largest {scale})"
            );
        }
    }
}

#[test]
fn the_op_matches_the_cpu_on_random_scenes() {
    for (seed, degree) in [(21, 0), (22, 1), (23, 2), (24, 3)] {
        assert_op_matches_the_cpu(&format!("seed {seed}"), &scene(seed, 200, degree));
    }
}

#[test]
fn the_op_matches_the_cpu_with_more_gaussians_per_tile_than_one_batch() {
    // 700 small Gaussians packed around the image centre: the central tiles list several
    // batches of 256.
    let mut s = common::random_scene(31, 700, 1, 0.6, 40, 36);
    for v in s.means.iter_mut() {
        *v *= 0.15;
    }
    for v in s.log_scales.iter_mut() {
        *v -= 0.5;
    }
    let f = common::Scene::to_f32;
    let (means, log_scales, quats) = (f(&s.means), f(&s.log_scales), f(&s.quats));
    let (opacity_logits, sh) = (f(&s.opacity_logits), f(&s.sh));
    let slices = GaussianSlices {
        means: &means,
        log_scales: &log_scales,
        quats: &quats,
        opacity_logits: &opacity_logits,
        sh: &sh,
    };
    let bins = cpu::bin_tiles(&cpu::project(&slices, &s.camera), 40, 36);
    let longest = bins.offsets.windows(2).map(|w| w[1] - w[0]).max().unwrap();
    assert!(
        longest > 2 * 256,
        "the longest tile list has {longest} entries"
    );
    assert_op_matches_the_cpu("dense", &s);
}

#[test]
fn the_op_matches_the_cpu_where_every_pixel_stops_early() {
    // Large, nearly opaque Gaussians in front of many others: every pixel of the inner tiles
    // reaches the transmittance floor before the end of its list.
    let mut s = common::random_scene(32, 150, 2, 0.99, 33, 33);
    for i in 0..60 {
        s.means[3 * i] *= 0.2;
        s.means[3 * i + 1] *= 0.2;
        s.means[3 * i + 2] = 0.8;
        for (a, v) in [0.0, -0.3, -0.5].into_iter().enumerate() {
            s.log_scales[3 * i + a] = v;
        }
        s.opacity_logits[i] = 6.0;
    }
    // Check the premise on the CPU: every pixel of the tile at the image centre saturates and
    // stops before the end of the tile's list.
    let f = common::Scene::to_f32;
    let (means, log_scales, quats) = (f(&s.means), f(&s.log_scales), f(&s.quats));
    let (opacity_logits, sh) = (f(&s.opacity_logits), f(&s.sh));
    let slices = GaussianSlices {
        means: &means,
        log_scales: &log_scales,
        quats: &quats,
        opacity_logits: &opacity_logits,
        sh: &sh,
    };
    let fwd = cpu::render(&slices, &s.camera, [0.0; 3], &Default::default()).unwrap();
    let tile = fwd.bins.tiles_x + 1;
    let listed = fwd.bins.offsets[tile + 1] - fwd.bins.offsets[tile];
    for y in TILE_SIZE..2 * TILE_SIZE {
        for x in TILE_SIZE..2 * TILE_SIZE {
            let p = y * s.camera.width as usize + x;
            assert!(
                fwd.final_transmittance[p] < 0.02,
                "pixel ({x}, {y}) is not saturated: T = {}, last {} of {listed}",
                fwd.final_transmittance[p],
                fwd.n_contrib[p]
            );
            assert!(
                fwd.n_contrib[p] < listed,
                "pixel ({x}, {y}) did not stop early"
            );
        }
    }
    assert_op_matches_the_cpu("saturated", &s);
}

#[test]
fn a_non_finite_input_gets_the_cpu_error() {
    let mut s = scene(41, 50, 1);
    s.log_scales[3 * 17 + 1] = f64::NAN;
    let cloud = f3g_splat::GaussianCloud {
        means: common::Scene::to_f32(&s.means),
        log_scales: common::Scene::to_f32(&s.log_scales),
        quats: common::Scene::to_f32(&s.quats),
        opacity_logits: common::Scene::to_f32(&s.opacity_logits),
        sh: common::Scene::to_f32(&s.sh),
        sh_degree: 1,
    };
    let device = test_device();
    let g = cloud.to_tensors(&device);
    let bg = burn::tensor::Tensor::<1>::zeros([3], &device);
    let err = f3g_splat::render(&g, &s.camera, bg, &Default::default()).unwrap_err();
    assert_eq!(
        err.to_string(),
        f3g_splat::SplatError::NonFinite {
            name: "log_scales",
            index: 3 * 17 + 1,
            value: f64::NAN
        }
        .to_string()
    );
}

#[test]
fn every_accumulation_the_device_has_gives_the_same_gradients() {
    let device = device();
    let s = scene(51, 300, 2);
    let f = |v: &[f64]| common::Scene::to_f32(v);
    let n = s.len();
    let k = s.sh.len() / (3 * n);
    let inputs = GaussianTensors::<CubeBackend> {
        means: upload(&f(&s.means), &[n, 3], &device),
        log_scales: upload(&f(&s.log_scales), &[n, 3], &device),
        quats: upload(&f(&s.quats), &[n, 4], &device),
        opacity_logits: upload(&f(&s.opacity_logits), &[n], &device),
        sh: upload(&f(&s.sh), &[n, k, 3], &device),
        background: upload(&[0.2, 0.5, 0.9], &[3], &device),
    };
    let (w, h) = (s.camera.width, s.camera.height);
    let projection = cube::project(&inputs, &s.camera);
    let depth = cube::depth_order(&projection);
    let bins = cube::bin_tiles(&projection, &depth, depth.count(), w, h);
    let raster = cube::rasterize(
        &projection.screen,
        &projection.radii,
        &bins,
        &inputs.background,
        w,
        h,
        0.99,
    );
    let (wc, _, _) = common::loss_weights(3, (w * h) as usize);
    let grad_image: Vec<f32> = (0..(w * h) as usize)
        .flat_map(|p| [wc[3 * p], wc[3 * p + 1], wc[3 * p + 2], 0.3, -0.1].map(|v| v as f32))
        .collect();
    let grad_image = upload(&grad_image, &[h as usize, w as usize, 5], &device);
    let best = cube::Accumulation::best(&projection.screen.client);
    let mut variants = vec![cube::Accumulation {
        float_atomics: false,
        planes: false,
    }];
    if best.float_atomics {
        variants.push(cube::Accumulation {
            float_atomics: true,
            planes: false,
        });
    }
    if best.planes {
        variants.push(cube::Accumulation {
            float_atomics: best.float_atomics,
            planes: true,
        });
    }
    let sums: Vec<Vec<f32>> = variants
        .iter()
        .map(|&accumulation| {
            let (screen_grads, _) = cube::rasterize_backward(
                &projection.screen,
                &projection.radii,
                &bins,
                &inputs.background,
                &raster.final_transmittance,
                &raster.n_contrib,
                &grad_image,
                w,
                h,
                0.99,
                accumulation,
            );
            floats(screen_grads)
        })
        .collect();
    let scale = sums[0].iter().fold(0f32, |m, v| m.max(v.abs()));
    assert!(scale > 1e-3, "the gradients vanished");
    for (variant, got) in variants.iter().zip(&sums).skip(1) {
        for (i, (a, b)) in got.iter().zip(&sums[0]).enumerate() {
            assert!(
                (a - b).abs() <= 1e-5 * scale,
                "{variant:?}: gradient {i}: {a} vs {b} (compare-and-swap, no planes)"
            );
        }
    }
    eprintln!("accumulations compared: {variants:?}");
}

#[test]
fn too_many_intersections_is_an_error_on_the_gpu_too() {
    // 2.15 × 10⁹ pairs: they wrap the i32 scan.
    let (cloud, camera) = common::overflowing_scene();
    let device = test_device();
    let bg = burn::tensor::Tensor::<1>::zeros([3], &device);
    let err = f3g_splat::render(&cloud.to_tensors(&device), &camera, bg, &Default::default())
        .unwrap_err();
    match err {
        f3g_splat::SplatError::Intersections { count, limit } => {
            assert_eq!(limit, i32::MAX as u64);
            // Counted in f32 in units of 1024: close to the exact 8 200 · 262 144.
            let exact = 8_200u64 * 262_144;
            assert!(count.abs_diff(exact) < exact / 1000, "{count} vs {exact}");
        }
        other => panic!("expected Intersections, got {other}"),
    }
}
