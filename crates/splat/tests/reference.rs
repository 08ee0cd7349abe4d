//! The fast CPU renderer equals the readable reference (`f3g_splat::reference`, gsplat 1.5.3's
//! semantics), and the projection equals an independent formulation (perspective Jacobian by
//! finite differences, covariance by rotating the scaled axes with quaternion sandwich
//! products, radii from the opacity-aware extent).

mod common;

use common::{Scene, random_scene};
use f3g_splat::cpu;
use f3g_splat::semantics::GaussianSlices;
use f3g_splat::{RenderOptions, reference};

fn max_abs_diff<T: Copy + Into<f64>>(a: &[T], b: &[T]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| ((*x).into() - (*y).into()).abs())
        .fold(0.0, f64::max)
}

#[test]
fn cpu_equals_the_reference_f64() {
    for seed in 0..12 {
        let degree = (seed % 4) as usize;
        let max_opacity = if seed % 2 == 0 { 0.95 } else { 0.999 };
        let s = random_scene(seed, 60, degree, max_opacity, 83, 61);
        let options = RenderOptions::default();
        let fwd = cpu::render(&s.slices(), &s.camera, s.background, &options).unwrap();
        let reference = reference::render(&s.slices(), &s.camera, s.background, &options);
        assert!(
            max_abs_diff(&fwd.color, &reference.color) < 1e-12,
            "seed {seed}: colour differs"
        );
        assert!(
            max_abs_diff(&fwd.alpha, &reference.alpha) < 1e-12,
            "seed {seed}: alpha differs"
        );
        assert!(
            max_abs_diff(&fwd.depth, &reference.depth) < 1e-12,
            "seed {seed}: depth differs"
        );
        assert!(
            fwd.alpha.iter().any(|&a| a > 0.5),
            "seed {seed}: the scene should cover pixels"
        );
    }
}

#[test]
fn cpu_equals_the_reference_f32_with_gsplat_clamp() {
    let mut stopped_early = 0;
    for seed in 100..106 {
        let s = random_scene(seed, 150, 3, 0.999, 97, 70);
        let options = RenderOptions { alpha_max: 0.999 };
        let means = Scene::to_f32(&s.means);
        let log_scales = Scene::to_f32(&s.log_scales);
        let quats = Scene::to_f32(&s.quats);
        let opacity_logits = Scene::to_f32(&s.opacity_logits);
        let sh = Scene::to_f32(&s.sh);
        let g = GaussianSlices {
            means: &means,
            log_scales: &log_scales,
            quats: &quats,
            opacity_logits: &opacity_logits,
            sh: &sh,
        };
        let bg = s.background.map(|v| v as f32);
        let fwd = cpu::render(&g, &s.camera, bg, &options).unwrap();
        let reference = reference::render(&g, &s.camera, bg, &options);
        assert!(
            max_abs_diff(&fwd.color, &reference.color) < 1e-6,
            "seed {seed}"
        );
        assert!(
            max_abs_diff(&fwd.alpha, &reference.alpha) < 1e-6,
            "seed {seed}"
        );
        assert!(
            max_abs_diff(&fwd.depth, &reference.depth) < 1e-5,
            "seed {seed}"
        );
        stopped_early += reference
            .signature
            .pixels
            .iter()
            .filter(|(_, stop)| stop.is_some())
            .count();
    }
    // Some pixels must have terminated early for the comparison to cover that path.
    assert!(
        stopped_early > 20,
        "only {stopped_early} pixels stopped early"
    );
}

/// Rotates `v` by unit quaternion `q` (w, x, y, z) as `q v q*`.
fn rotate(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    let [w, x, y, z] = q;
    let mul = |a: [f64; 4], b: [f64; 4]| {
        [
            a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
            a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
            a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
            a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
        ]
    };
    let r = mul(mul([w, x, y, z], [0.0, v[0], v[1], v[2]]), [w, -x, -y, -z]);
    [r[1], r[2], r[3]]
}

#[test]
fn projection_matches_an_independent_formulation() {
    for seed in 200..210 {
        let s = random_scene(seed, 40, 0, 0.9, 120, 90);
        let projected = cpu::project(&s.slices(), &s.camera);
        let cam = &s.camera;
        let to_pixels = |x: [f64; 3]| cam.project(x).unwrap().0;
        let mut checked = 0;
        for (i, p) in projected.iter().enumerate() {
            if !p.is_visible() {
                continue;
            }
            let mean = [s.means[3 * i], s.means[3 * i + 1], s.means[3 * i + 2]];
            let (uv, depth) = cam.project(mean).unwrap();
            assert!((uv[0] - p.mean[0]).abs() < 1e-9 && (uv[1] - p.mean[1]).abs() < 1e-9);
            assert!((depth - p.depth).abs() < 1e-12);
            // Σ₂ᴅ = Σ_a (J s_a r_a)(J s_a r_a)ᵀ with r_a the rotated axes and J by differences.
            let qn = {
                let q = &s.quats[4 * i..4 * i + 4];
                let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
                [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
            };
            let mut cov = [0.3, 0.0, 0.3];
            for a in 0..3 {
                let mut e = [0.0; 3];
                e[a] = s.log_scales[3 * i + a].exp();
                let axis = rotate(qn, e);
                let h = 1e-6;
                let plus = to_pixels([
                    mean[0] + h * axis[0],
                    mean[1] + h * axis[1],
                    mean[2] + h * axis[2],
                ]);
                let minus = to_pixels([
                    mean[0] - h * axis[0],
                    mean[1] - h * axis[1],
                    mean[2] - h * axis[2],
                ]);
                let j = [
                    (plus[0] - minus[0]) / (2.0 * h),
                    (plus[1] - minus[1]) / (2.0 * h),
                ];
                cov[0] += j[0] * j[0];
                cov[1] += j[0] * j[1];
                cov[2] += j[1] * j[1];
            }
            let det = cov[0] * cov[2] - cov[1] * cov[1];
            let conic = [cov[2] / det, -cov[1] / det, cov[0] / det];
            for c in 0..3 {
                let rel = (conic[c] - p.conic[c]).abs() / conic[0].abs().max(conic[2].abs());
                assert!(
                    rel < 1e-6,
                    "seed {seed} gaussian {i} conic[{c}]: {} vs {}",
                    p.conic[c],
                    conic[c]
                );
            }
            let o = 1.0 / (1.0 + (-s.opacity_logits[i]).exp());
            let k = (2.0 * (255.0 * o).ln()).sqrt().min(3.33);
            assert_eq!(
                p.radii,
                [
                    (k * cov[0].sqrt()).ceil() as u32,
                    (k * cov[2].sqrt()).ceil() as u32
                ],
                "seed {seed} gaussian {i}"
            );
            checked += 1;
        }
        assert!(checked > 10, "seed {seed}: only {checked} visible");
    }
}

#[test]
fn far_off_screen_gaussians_use_the_clamped_jacobian() {
    // A Gaussian far to the side of a narrow camera: its Jacobian is taken at the clamped
    // position (1.3× the half field of view), which keeps its footprint bounded.
    let mut s = random_scene(7, 1, 0, 0.9, 64, 64);
    s.camera = f3g_splat::Camera::look_at([0.0, 0.0, 3.0], [0.0; 3], [0.0, 1.0, 0.0], 64.0, 64, 64);
    s.means = vec![2.0, 0.0, 0.0];
    s.log_scales = vec![(1.0f64).ln(); 3];
    s.quats = vec![1.0, 0.0, 0.0, 0.0];
    let p = cpu::project(&s.slices(), &s.camera)[0];
    // With unit scales the horizontal variance is fx²/z²·(1 + (tx/z)²) + 0.3, where the
    // unclamped tx/z would be 2/3 and the clamped one is (W − cx)/fx + 0.3·W/(2 fx) = 0.65.
    let (fx, z) = (64.0f64, 3.0f64);
    let expected_var = fx * fx / (z * z) * (1.0 + 0.65f64 * 0.65) + 0.3;
    let var_x = p.conic[2] / (p.conic[0] * p.conic[2] - p.conic[1] * p.conic[1]);
    assert!(
        (var_x - expected_var).abs() < 1e-9,
        "{var_x} vs {expected_var}"
    );
}

#[test]
fn cpu_equals_the_reference_on_empty_near_plane_and_border_scenes() {
    let options = RenderOptions::default();
    let check = |s: &Scene, what: &str| {
        let fwd = cpu::render(&s.slices(), &s.camera, s.background, &options).unwrap();
        let reference = reference::render(&s.slices(), &s.camera, s.background, &options);
        for (name, a, b) in [
            ("colour", &fwd.color, &reference.color),
            ("alpha", &fwd.alpha, &reference.alpha),
            ("depth", &fwd.depth, &reference.depth),
        ] {
            let d = max_abs_diff(a, b);
            assert!(d < 1e-12, "{what}: {name} differs by {d}");
        }
        let radii: Vec<[u32; 2]> = fwd.projected.iter().map(|p| p.radii).collect();
        assert_eq!(radii, reference.signature.radii, "{what}: radii");
        reference
    };

    let mut empty = random_scene(1, 0, 2, 0.9, 50, 37);
    let r = check(&empty, "empty scene");
    assert!(r.color.chunks(3).all(|px| px == empty.background));
    empty.background = [0.0; 3];
    check(&empty, "empty scene, black background");

    // The camera sits at z = 3 looking at the origin; a near plane at 2.9 cuts through the
    // cluster, so some Gaussians straddle it and some lie just in front of it.
    let mut near = random_scene(2, 80, 1, 0.95, 61, 45);
    near.camera.near = 2.9;
    let r = check(&near, "near plane");
    let culled = r.projected.iter().filter(|p| p.is_none()).count();
    assert!(
        culled > 10 && culled < 70,
        "{culled} of 80 culled by the near plane"
    );

    // Spread the means far wider than the view: many Gaussians cross the image border, some
    // are centred outside it and still reach in.
    let mut border = random_scene(3, 120, 3, 0.999, 53, 41);
    for m in border.means.chunks_exact_mut(3) {
        m[0] *= 3.0;
        m[1] *= 3.0;
    }
    let r = check(&border, "image border");
    let (w, h) = (53.0, 41.0);
    let outside_but_drawn = r
        .projected
        .iter()
        .flatten()
        .filter(|p| p.mean[0] < 0.0 || p.mean[0] > w || p.mean[1] < 0.0 || p.mean[1] > h)
        .count();
    assert!(
        outside_but_drawn > 3,
        "only {outside_but_drawn} off-centre Gaussians reach in"
    );
}

/// The footprint box loses nothing: outside it every pixel centre has α < 1/255 — the
/// property that makes the image independent of boxes and tiles (gsplat's opacity-aware
/// extent; the old 3σ square of the largest eigenvalue dropped pixels with α up to ~1 %).
#[test]
fn no_pixel_outside_the_box_reaches_one_in_255() {
    let mut checked = 0;
    for seed in 300..340 {
        let s = random_scene(seed, 30, 0, 1.0 - 1e-9, 96, 80);
        for p in cpu::project(&s.slices(), &s.camera)
            .iter()
            .filter(|p| p.is_visible())
        {
            let [rx, ry] = p.radii.map(f64::from);
            for row in 0..80 {
                for col in 0..96 {
                    let (dx, dy) = (col as f64 + 0.5 - p.mean[0], row as f64 + 0.5 - p.mean[1]);
                    if dx.abs() <= rx && dy.abs() <= ry {
                        continue;
                    }
                    let sigma =
                        0.5 * (p.conic[0] * dx * dx + p.conic[2] * dy * dy) + p.conic[1] * dx * dy;
                    let alpha = p.opacity * (-sigma).exp();
                    assert!(
                        alpha < 1.0 / 255.0,
                        "seed {seed}: α = {alpha} at ({dx}, {dy})"
                    );
                    checked += 1;
                }
            }
        }
    }
    assert!(checked > 100_000, "{checked}");
}
