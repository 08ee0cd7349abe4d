//! The synthetic capture's choreography for the built-in human (`f3g synth`), in the built-in
//! human's own parameter names, which only this crate knows: from a still A-pose-like first
//! frame, easing in over four frames, in-place walking, arm swings, torso and head turns, jaw
//! opening and closing, blinks, smiles and brow raises with seeded phases; the last 20 % of
//! the frames switch to poses the first 80 % never show (arms raised, a wider stance, a head
//! tilt), the synthetic novel-pose split. Parameters a model lacks are left at zero.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::rig::{Rig, RigParams};

/// Sets a named parameter (pose, identity or expression) if the model has it.
fn set(rig: &Rig, p: &mut RigParams, name: &str, value: f32) {
    if let Some(i) = rig.pose_param_names().iter().position(|n| n == name) {
        p.pose[i] = value;
    } else if let Some(i) = rig.expression.names.iter().position(|n| n == name) {
        p.expression[i] = value;
    } else if let Some(i) = rig.identity.names.iter().position(|n| n == name) {
        p.identity[i] = value;
    }
}

/// The shape (identity parameters) of the person `seed` draws, which every frame of
/// [`motion`] with that seed carries: another motion performed by the same person
/// (`f3g synth --motion`) takes it, so that an avatar trained on one capture is compared with
/// itself, not with a differently built body, on the other.
pub fn identity(rig: &Rig, seed: u64) -> Vec<f32> {
    motion(rig, 1, seed).swap_remove(0).identity
}

/// The synthetic capture's motion: `frames` frames at 15 fps from `seed` (module docs).
pub fn motion(rig: &Rig, frames: usize, seed: u64) -> Vec<RigParams> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x3071);
    let phase: Vec<f32> = (0..16)
        .map(|_| rng.random_range(0.0..std::f32::consts::TAU))
        .collect();
    let gender = rng.random_range(-0.3..0.3);
    let weight = rng.random_range(0.0..0.3);
    let blink_period = rng.random_range(20..28);
    let novel_from = (frames * 4).div_ceil(5);
    let fps = 15.0;
    (0..frames)
        .map(|f| {
            let t = f as f32 / fps;
            // The sequence starts still, in an A-pose-like frame (as captures usually do, and
            // what `f3g template reconstruct` carves best), and eases into the motion.
            let ease = (f as f32 / 4.0).min(1.0);
            let s =
                |freq: f32, k: usize| ease * (std::f32::consts::TAU * freq * t + phase[k]).sin();
            let mut p = rig.zero_params();
            set(rig, &mut p, "gender", gender);
            set(rig, &mut p, "weight", weight);
            let novel = f >= novel_from;
            // Body.
            set(rig, &mut p, "root_ry", 0.5 * s(0.07, 0));
            set(rig, &mut p, "root_ty", 0.01 * s(0.9, 1));
            set(rig, &mut p, "spine03_ry", 0.15 * s(0.25, 2));
            set(rig, &mut p, "spine02_rz", 0.06 * s(0.2, 3));
            let stride = 0.3 * s(0.45, 4);
            set(rig, &mut p, "upperleg01.L_rx", -stride);
            set(rig, &mut p, "upperleg01.R_rx", stride);
            set(rig, &mut p, "lowerleg01.L_rx", 0.3 * stride.max(0.0) + 0.05);
            set(
                rig,
                &mut p,
                "lowerleg01.R_rx",
                0.3 * (-stride).max(0.0) + 0.05,
            );
            let (arm_l, arm_r) = if novel {
                (1.1 + 0.2 * s(0.3, 5), -1.0 - 0.2 * s(0.35, 6))
            } else {
                (0.35 + 0.25 * s(0.3, 5), -0.35 - 0.25 * s(0.35, 6))
            };
            set(rig, &mut p, "upperarm01.L_rz", arm_l);
            set(rig, &mut p, "upperarm01.R_rz", arm_r);
            set(rig, &mut p, "upperarm01.L_rx", 0.3 * s(0.45, 4));
            set(rig, &mut p, "upperarm01.R_rx", -0.3 * s(0.45, 4));
            let elbow = 0.45 * ease + 0.35 * s(0.4, 7);
            set(rig, &mut p, "lowerarm01.L_rx", -elbow * 0.7);
            set(rig, &mut p, "lowerarm01.L_ry", elbow * 0.7);
            set(rig, &mut p, "lowerarm01.R_rx", -elbow * 0.7);
            set(rig, &mut p, "lowerarm01.R_ry", -elbow * 0.7);
            if novel {
                set(rig, &mut p, "upperleg01.L_rz", 0.2);
                set(rig, &mut p, "upperleg01.R_rz", -0.2);
                set(rig, &mut p, "head_rz", 0.2);
            }
            set(rig, &mut p, "head_ry", 0.45 * s(0.15, 8));
            set(rig, &mut p, "head_rx", 0.12 * s(0.22, 9));
            // Face: jaw, blinks, smiles, brows.
            let jaw = (0.3 * s(0.35, 10)).max(0.0);
            set(rig, &mut p, "jaw_rx", jaw);
            set(rig, &mut p, "mouth-open", 2.0 * jaw);
            let blink = match f % blink_period {
                0 | 2 => 0.6,
                1 => 1.0,
                _ => 0.0,
            };
            set(rig, &mut p, "eye-left-closure", blink);
            set(rig, &mut p, "eye-right-closure", blink);
            set(
                rig,
                &mut p,
                "mouth-corner-puller",
                (0.9 * s(0.12, 11)).max(0.0),
            );
            let brows = (0.8 * s(0.09, 12)).max(0.0);
            set(rig, &mut p, "eyebrows-left-up", brows);
            set(rig, &mut p, "eyebrows-right-up", brows);
            set(rig, &mut p, "eye.L_ry", 0.25 * s(0.18, 13));
            set(rig, &mut p, "eye.R_ry", 0.25 * s(0.18, 13));
            p
        })
        .collect()
}
