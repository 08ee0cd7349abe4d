//! The CPU renderer and the reference against gsplat 1.5.3 itself: golden renders made on a
//! CUDA GPU by `tools/gsplat_golden.py` (scenes with SH degree 0–3, occlusion, the 0.999 alpha
//! clamp and early stop, Gaussians across the image and tile borders, an off-centre principal
//! point, a near plane through the cloud).
//!
//! gsplat computes in f32 with `--use_fast_math`, so images agree to about 1e-6, not bit for
//! bit; radii may differ by one pixel where `⌈k σ⌉` lands on an integer. gsplat also keeps
//! Gaussians whose box overlaps the image without holding a pixel centre (they draw nothing);
//! we cull those, so radii are compared where both are visible.

use std::path::{Path, PathBuf};

use f3g_io::Npz;
use f3g_splat::cpu;
use f3g_splat::semantics::GaussianSlices;
use f3g_splat::{Camera, RenderOptions, reference};

fn golden_files() -> Vec<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/gsplat");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "npz"))
        .collect();
    files.sort();
    files
}

fn matrix(v: &[f32]) -> [[f64; 3]; 3] {
    std::array::from_fn(|r| std::array::from_fn(|c| v[3 * r + c] as f64))
}

#[test]
fn cpu_and_reference_match_gsplat() {
    let files = golden_files();
    assert_eq!(files.len(), 4, "expected the four golden scenes");
    let mut visible_total = 0;
    for path in files {
        let mut npz = Npz::open(&path).unwrap();
        let mut f = |name: &str| npz.f32(name).unwrap().1;
        let (means, log_scales, quats) = (f("means"), f("log_scales"), f("quats"));
        let (opacity_logits, sh, background) = (f("opacity_logits"), f("sh"), f("background"));
        let (k, r, t) = (f("k"), f("r"), f("t"));
        let (near, far) = (f("near")[0] as f64, f("far")[0] as f64);
        let (color, alpha, depth) = (f("color"), f("alpha"), f("depth"));
        let size = npz.i64("size").unwrap().1;
        let radii = npz.i64("radii").unwrap().1;
        let camera = Camera {
            k: matrix(&k),
            r: matrix(&r),
            t: [t[0] as f64, t[1] as f64, t[2] as f64],
            width: size[0] as u32,
            height: size[1] as u32,
            near,
            far,
        };
        let g = GaussianSlices {
            means: &means,
            log_scales: &log_scales,
            quats: &quats,
            opacity_logits: &opacity_logits,
            sh: &sh,
        };
        let bg = [background[0], background[1], background[2]];
        let options = RenderOptions { alpha_max: 0.999 };
        let fwd = cpu::render(&g, &camera, bg, &options).unwrap();
        let spec = reference::render(&g, &camera, bg, &options);
        let name = path.file_name().unwrap().to_string_lossy();
        for (what, ours, theirs, tol) in [
            ("colour", &fwd.color, &color, 5e-6),
            ("alpha", &fwd.alpha, &alpha, 5e-6),
            ("depth", &fwd.depth, &depth, 2e-5),
            ("reference colour", &spec.color, &color, 5e-6),
        ] {
            let worst = ours
                .iter()
                .zip(theirs.iter())
                .map(|(a, b)| (a - b).abs())
                .fold(0f32, f32::max);
            println!("{name}: {what} max |Δ| = {worst:.2e}");
            assert!(worst < tol, "{name}: {what} differs from gsplat by {worst}");
        }
        let mut visible = 0;
        let mut off_by_one = 0;
        for (i, p) in fwd.projected.iter().enumerate() {
            let theirs = [radii[2 * i], radii[2 * i + 1]];
            if !p.is_visible() {
                continue;
            }
            visible += 1;
            assert!(
                theirs != [0, 0],
                "{name}: Gaussian {i} is culled by gsplat only"
            );
            for axis in 0..2 {
                let d = (p.radii[axis] as i64 - theirs[axis]).abs();
                assert!(
                    d <= 1,
                    "{name}: Gaussian {i} radius {axis}: {p:?} vs {theirs:?}"
                );
                off_by_one += d as usize;
            }
        }
        println!("{name}: {visible} visible, {off_by_one} radii off by one");
        assert!(
            off_by_one * 50 <= visible,
            "{name}: {off_by_one} radii off by one"
        );
        visible_total += visible;
    }
    assert!(visible_total > 300, "{visible_total}");
}
