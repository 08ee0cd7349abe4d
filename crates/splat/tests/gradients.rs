//! Finite-difference checks, in f64, of the analytic backward for every input.
//!
//! The loss is a random weighted sum of colour, alpha and depth, so every output gradient path
//! is exercised. The render has jumps (the 1/255 alpha cut-off, the alpha clamp, early
//! termination): a coordinate is compared only when the
//! reference renderer reports the same discrete decisions at both ±h, i.e. when the loss is
//! smooth there. Skips are counted and must stay rare. Scenes overlap heavily and some have
//! opacities up to 0.999, so occlusion, clamping and early termination are all covered.

mod common;

use common::{Scene, loss_weights, random_scene};
use f3g_splat::cpu::{self, PixelGrads};
use f3g_splat::{RenderOptions, reference};

fn loss(
    s: &Scene,
    w: &(Vec<f64>, Vec<f64>, Vec<f64>),
    options: &RenderOptions,
) -> (f64, reference::Signature) {
    let r = reference::render(&s.slices(), &s.camera, s.background, options);
    let l = r.color.iter().zip(&w.0).map(|(a, b)| a * b).sum::<f64>()
        + r.alpha.iter().zip(&w.1).map(|(a, b)| a * b).sum::<f64>()
        + r.depth.iter().zip(&w.2).map(|(a, b)| a * b).sum::<f64>();
    (l, r.signature)
}

struct Tally {
    compared: usize,
    skipped: usize,
    nonzero: usize,
}

fn check_scene(mut s: Scene, seed: u64, tally: &mut Tally) {
    let options = RenderOptions::default();
    let pixels = (s.camera.width * s.camera.height) as usize;
    let w = loss_weights(seed, pixels);
    let fwd = cpu::render(&s.slices(), &s.camera, s.background, &options).unwrap();
    let grads = cpu::render_backward(
        &s.slices(),
        &s.camera,
        &options,
        &fwd,
        &PixelGrads {
            color: &w.0,
            alpha: &w.1,
            depth: &w.2,
        },
    );
    let analytic: Vec<(&str, Vec<f64>)> = vec![
        ("means", grads.means.clone()),
        ("log_scales", grads.log_scales.clone()),
        ("quats", grads.quats.clone()),
        ("opacity_logits", grads.opacity_logits.clone()),
        ("sh", grads.sh.clone()),
        ("background", grads.background.to_vec()),
    ];
    let h = 1e-6;
    for (field, expected) in analytic {
        for (j, &a) in expected.iter().enumerate() {
            let get = |s: &mut Scene| -> f64 {
                s.fields_mut().into_iter().find(|f| f.0 == field).unwrap().1[j]
            };
            let set = |s: &mut Scene, v: f64| {
                s.fields_mut().into_iter().find(|f| f.0 == field).unwrap().1[j] = v
            };
            let x = get(&mut s);
            set(&mut s, x + h);
            let (lp, sp) = loss(&s, &w, &options);
            set(&mut s, x - h);
            let (lm, sm) = loss(&s, &w, &options);
            set(&mut s, x);
            if sp != sm {
                tally.skipped += 1;
                continue;
            }
            let numeric = (lp - lm) / (2.0 * h);
            let tolerance = 1e-6 + 1e-5 * a.abs().max(numeric.abs());
            assert!(
                (a - numeric).abs() <= tolerance,
                "seed {seed}: d loss / d {field}[{j}]: analytic {a:.9e}, numeric {numeric:.9e}"
            );
            tally.compared += 1;
            if a.abs() > 1e-6 {
                tally.nonzero += 1;
            }
        }
    }
}

#[test]
fn gradients_match_finite_differences_on_random_scenes() {
    let mut tally = Tally {
        compared: 0,
        skipped: 0,
        nonzero: 0,
    };
    for seed in 0..40u64 {
        let degree = (seed % 4) as usize;
        let n = 3 + (seed % 6) as usize;
        let max_opacity = if seed % 3 == 0 { 0.999 } else { 0.9 };
        let s = random_scene(1000 + seed, n, degree, max_opacity, 37, 29);
        check_scene(s, seed, &mut tally);
    }
    eprintln!(
        "compared {} skipped {} nonzero {}",
        tally.compared, tally.skipped, tally.nonzero
    );
    assert!(
        tally.compared > 3000,
        "only {} coordinates compared",
        tally.compared
    );
    assert!(
        tally.nonzero > tally.compared / 2,
        "most gradients should be non-zero ({} of {})",
        tally.nonzero,
        tally.compared
    );
    assert!(
        tally.skipped * 50 < tally.compared,
        "{} skipped of {}",
        tally.skipped,
        tally.compared
    );
}

#[test]
fn gradients_of_a_dense_occluding_stack() {
    // Many nearly co-located Gaussians: strong occlusion and early termination everywhere.
    let mut tally = Tally {
        compared: 0,
        skipped: 0,
        nonzero: 0,
    };
    for seed in 0..4u64 {
        let mut s = random_scene(5000 + seed, 14, 1, 0.995, 24, 20);
        for m in s.means.iter_mut() {
            *m *= 0.15;
        }
        check_scene(s, seed, &mut tally);
    }
    assert!(tally.compared > 500, "only {} compared", tally.compared);
    assert!(
        tally.skipped * 20 < tally.compared,
        "{} skipped of {}",
        tally.skipped,
        tally.compared
    );
}
