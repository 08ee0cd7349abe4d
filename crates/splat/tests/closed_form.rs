//! Renders with known answers, and inputs that must be rejected.

mod common;

use common::random_scene;
use f3g_splat::cpu;
use f3g_splat::semantics::GaussianSlices;
use f3g_splat::sh::SH_C0;
use f3g_splat::{Camera, RenderOptions, SplatError};

fn origin_camera(width: u32, height: u32, focal: f64) -> Camera {
    Camera {
        k: [
            [focal, 0.0, width as f64 / 2.0],
            [0.0, focal, height as f64 / 2.0],
            [0.0, 0.0, 1.0],
        ],
        r: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        t: [0.0; 3],
        width,
        height,
        near: 0.01,
        far: 100.0,
    }
}

struct One {
    means: Vec<f64>,
    log_scales: Vec<f64>,
    quats: Vec<f64>,
    opacity_logits: Vec<f64>,
    sh: Vec<f64>,
}

impl One {
    fn new(mean: [f64; 3], scale: f64, opacity: f64, color: [f64; 3]) -> Self {
        Self {
            means: mean.to_vec(),
            log_scales: vec![scale.ln(); 3],
            quats: vec![1.0, 0.0, 0.0, 0.0],
            opacity_logits: vec![(opacity / (1.0 - opacity)).ln()],
            sh: color.iter().map(|c| (c - 0.5) / SH_C0).collect(),
        }
    }

    fn slices(&self) -> GaussianSlices<'_, f64> {
        GaussianSlices {
            means: &self.means,
            log_scales: &self.log_scales,
            quats: &self.quats,
            opacity_logits: &self.opacity_logits,
            sh: &self.sh,
        }
    }
}

#[test]
fn one_isotropic_gaussian_gives_the_analytic_image() {
    let cam = origin_camera(64, 48, 100.0);
    let (x, y, z, s, o) = (0.013, -0.007, 2.0, 0.04, 0.8);
    let color = [0.9, 0.4, 0.1];
    let bg = [0.2, 0.3, 1.0];
    let g = One::new([x, y, z], s, o, color);
    let out = cpu::render(&g.slices(), &cam, bg, &RenderOptions::default()).unwrap();

    // EWA: Σ₂ᴅ = s² J Jᵀ + 0.3 I with J the perspective Jacobian at the mean.
    let (f, s2) = (100.0, s * s);
    let j = [
        [f / z, 0.0, -f * x / (z * z)],
        [0.0, f / z, -f * y / (z * z)],
    ];
    let cxx = s2 * (j[0][0] * j[0][0] + j[0][2] * j[0][2]) + 0.3;
    let cxy = s2 * (j[0][2] * j[1][2]);
    let cyy = s2 * (j[1][1] * j[1][1] + j[1][2] * j[1][2]) + 0.3;
    let det = cxx * cyy - cxy * cxy;
    let (mu, mv) = (f * x / z + 32.0, f * y / z + 24.0);
    // gsplat's opacity-aware extent: the box where o·exp(−½m²) ≥ 1/255.
    let k = (2.0 * (255.0 * o).ln()).sqrt();
    assert_eq!(
        out.projected[0].radii,
        [
            (k * cxx.sqrt()).ceil() as u32,
            (k * cyy.sqrt()).ceil() as u32
        ]
    );

    let mut covered = 0;
    for row in 0..48 {
        for col in 0..64 {
            let (dx, dy) = (col as f64 + 0.5 - mu, row as f64 + 0.5 - mv);
            let power = -0.5 * (cyy * dx * dx - 2.0 * cxy * dx * dy + cxx * dy * dy) / det;
            let mut a = (o * power.exp()).min(0.99);
            // Every pixel where the Gaussian reaches 1/255 counts, however far out.
            if a < 1.0 / 255.0 {
                a = 0.0;
            } else {
                covered += 1;
            }
            let p = row * 64 + col;
            for c in 0..3 {
                let expected = a * color[c] + (1.0 - a) * bg[c];
                assert!(
                    (out.color[3 * p + c] - expected).abs() < 1e-12,
                    "pixel ({col},{row}) channel {c}"
                );
            }
            assert!((out.alpha[p] - a).abs() < 1e-12);
            assert!((out.depth[p] - a * z).abs() < 1e-12);
        }
    }
    assert!(
        covered > 100,
        "the Gaussian should cover a disc of pixels, covered {covered}"
    );
}

#[test]
fn zero_opacity_gives_the_background() {
    let cam = origin_camera(40, 30, 50.0);
    let mut g = One::new([0.0, 0.0, 2.0], 0.1, 0.5, [1.0, 0.0, 0.0]);
    g.opacity_logits = vec![-40.0];
    let bg = [0.25, 0.5, 0.75];
    let out = cpu::render(&g.slices(), &cam, bg, &RenderOptions::default()).unwrap();
    for px in out.color.chunks(3) {
        assert_eq!(px, bg);
    }
    assert!(out.alpha.iter().all(|&a| a == 0.0));
}

#[test]
fn gaussians_behind_the_camera_or_before_near_contribute_nothing() {
    let cam = origin_camera(40, 30, 50.0);
    let bg = [0.1, 0.2, 0.3];
    for z in [-2.0, -0.001, 0.005] {
        let g = One::new([0.0, 0.0, z], 0.5, 0.9, [1.0, 1.0, 1.0]);
        let out = cpu::render(&g.slices(), &cam, bg, &RenderOptions::default()).unwrap();
        assert_eq!(out.projected[0].radii, [0, 0], "z = {z}");
        assert!(out.color.chunks(3).all(|px| px == bg), "z = {z}");
        assert_eq!(out.bins.num_intersections(), 0);
    }
}

#[test]
fn an_empty_scene_renders_the_background() {
    let cam = origin_camera(17, 5, 50.0);
    let g = GaussianSlices::<f64> {
        means: &[],
        log_scales: &[],
        quats: &[],
        opacity_logits: &[],
        sh: &[],
    };
    let out = cpu::render(&g, &cam, [0.5, 0.5, 0.5], &RenderOptions::default()).unwrap();
    assert_eq!(out.color, vec![0.5; 17 * 5 * 3]);
}

#[test]
fn bad_inputs_are_rejected_with_the_field_named() {
    let s = random_scene(3, 4, 1, 0.9, 32, 32);
    let opts = RenderOptions::default();
    let render = |s: &common::Scene| cpu::render(&s.slices(), &s.camera, s.background, &opts);
    assert!(render(&s).is_ok());

    let mut bad = s.clone();
    bad.means[5] = f64::NAN;
    match render(&bad) {
        Err(SplatError::NonFinite {
            name: "means",
            index: 5,
            ..
        }) => {}
        other => panic!("expected a NaN error for means, got {other:?}"),
    }
    let mut bad = s.clone();
    bad.sh[2] = f64::INFINITY;
    assert!(render(&bad).unwrap_err().to_string().contains("`sh`"));
    let mut bad = s.clone();
    bad.opacity_logits[0] = f64::NEG_INFINITY;
    assert!(
        render(&bad)
            .unwrap_err()
            .to_string()
            .contains("opacity_logits")
    );
    let mut bad = s.clone();
    bad.background[1] = f64::NAN;
    assert!(render(&bad).unwrap_err().to_string().contains("background"));

    let mut bad = s.clone();
    bad.quats.pop();
    assert!(render(&bad).unwrap_err().to_string().contains("`quats`"));
    let mut bad = s.clone();
    bad.sh.truncate(3 * 4 * 2);
    assert!(matches!(
        render(&bad),
        Err(SplatError::Shape { name: "sh", .. }) | Err(SplatError::ShDegree { .. })
    ));

    let mut bad = s.clone();
    bad.camera.t[0] = f64::INFINITY;
    assert!(matches!(render(&bad), Err(SplatError::Camera(_))));
    let mut bad = s.clone();
    bad.camera.r = [[0.0; 3]; 3];
    assert!(
        render(&bad)
            .unwrap_err()
            .to_string()
            .contains("orthonormal")
    );
    let mut bad = s.clone();
    bad.camera.k[1][1] = 0.0;
    assert!(render(&bad).unwrap_err().to_string().contains("focal"));
    let mut bad = s.clone();
    bad.camera.height = 0;
    assert!(render(&bad).unwrap_err().to_string().contains("empty"));

    let bad_opts = RenderOptions { alpha_max: 1.0 };
    assert!(
        cpu::render(&s.slices(), &s.camera, s.background, &bad_opts)
            .unwrap_err()
            .to_string()
            .contains("alpha_max")
    );
}
