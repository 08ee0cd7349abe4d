//! Shared test scenes and loss weights (the renderer they are checked against is
//! `f3g_splat::reference`).
#![allow(dead_code)]

use f3g_splat::semantics::GaussianSlices;
use f3g_splat::{Camera, sh};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Owned scene parameters in `f64`.
#[derive(Clone, Debug)]
pub struct Scene {
    pub means: Vec<f64>,
    pub log_scales: Vec<f64>,
    pub quats: Vec<f64>,
    pub opacity_logits: Vec<f64>,
    pub sh: Vec<f64>,
    pub background: [f64; 3],
    pub camera: Camera,
}

impl Scene {
    pub fn slices(&self) -> GaussianSlices<'_, f64> {
        GaussianSlices {
            means: &self.means,
            log_scales: &self.log_scales,
            quats: &self.quats,
            opacity_logits: &self.opacity_logits,
            sh: &self.sh,
        }
    }

    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    pub fn to_f32(v: &[f64]) -> Vec<f32> {
        v.iter().map(|&x| x as f32).collect()
    }

    /// All parameters as mutable slices, with their names, for finite differences.
    pub fn fields_mut(&mut self) -> Vec<(&'static str, &mut [f64])> {
        vec![
            ("means", &mut self.means[..]),
            ("log_scales", &mut self.log_scales[..]),
            ("quats", &mut self.quats[..]),
            ("opacity_logits", &mut self.opacity_logits[..]),
            ("sh", &mut self.sh[..]),
            ("background", &mut self.background[..]),
        ]
    }
}

/// A camera looking at the origin from +z·distance with an off-centre principal point and a
/// small odd-sized image (several partial tiles).
pub fn test_camera(rng: &mut ChaCha8Rng, width: u32, height: u32) -> Camera {
    let eye = [
        rng.random_range(-0.3..0.3),
        rng.random_range(-0.3..0.3),
        3.0,
    ];
    let mut cam = Camera::look_at(
        eye,
        [0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        rng.random_range(60.0..90.0),
        width,
        height,
    );
    cam.k[0][2] += rng.random_range(-3.0..3.0);
    cam.k[1][2] += rng.random_range(-3.0..3.0);
    cam.k[1][1] *= rng.random_range(0.9..1.1);
    cam
}

/// `n` Gaussians clustered in front of the camera so that many overlap and occlude each
/// other. `max_opacity` above 0.99 exercises the alpha clamp and early termination.
pub fn random_scene(
    seed: u64,
    n: usize,
    degree: usize,
    max_opacity: f64,
    width: u32,
    height: u32,
) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let camera = test_camera(&mut rng, width, height);
    let k = sh::num_coeffs(degree);
    let mut s = Scene {
        means: Vec::new(),
        log_scales: Vec::new(),
        quats: Vec::new(),
        opacity_logits: Vec::new(),
        sh: Vec::new(),
        background: [
            rng.random_range(0.0..1.0),
            rng.random_range(0.0..1.0),
            rng.random_range(0.0..1.0),
        ],
        camera,
    };
    for _ in 0..n {
        s.means.extend([
            rng.random_range(-0.5..0.5),
            rng.random_range(-0.4..0.4),
            rng.random_range(-0.5..0.5),
        ]);
        s.log_scales
            .extend((0..3).map(|_| rng.random_range(0.02f64..0.12).ln()));
        s.quats.extend((0..4).map(|_| rng.random_range(-1.0..1.0)));
        let o: f64 = rng.random_range(0.15..max_opacity);
        s.opacity_logits.push((o / (1.0 - o)).ln());
        for j in 0..k {
            for _ in 0..3 {
                // A positive DC term keeps colours away from the clamp at zero.
                s.sh.push(if j == 0 {
                    rng.random_range(0.3..1.5)
                } else {
                    rng.random_range(-0.15..0.15)
                });
            }
        }
    }
    s
}

/// Random per-pixel loss weights for colour, alpha and depth.
pub fn loss_weights(seed: u64, pixels: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed);
    (
        (0..3 * pixels)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect(),
        (0..pixels).map(|_| rng.random_range(-1.0..1.0)).collect(),
        (0..pixels).map(|_| rng.random_range(-0.3..0.3)).collect(),
    )
}

/// 8 200 Gaussians that each cover all 262 144 tiles of an 8192² image: 2.15 × 10⁹ pairs, past
/// what 32-bit tile offsets can index.
pub fn overflowing_scene() -> (f3g_splat::GaussianCloud, Camera) {
    let n = 8_200;
    let cloud = f3g_splat::GaussianCloud {
        means: vec![0.0; 3 * n],
        log_scales: vec![5f32.ln(); 3 * n],
        quats: [1.0, 0.0, 0.0, 0.0].repeat(n),
        opacity_logits: vec![5.0; n],
        sh: vec![0.5; 3 * n],
        sh_degree: 0,
    };
    let camera = f3g_splat::Camera::look_at(
        [0.0, 0.0, 3.0],
        [0.0; 3],
        [0.0, 1.0, 0.0],
        4000.0,
        8192,
        8192,
    );
    (cloud, camera)
}
