//! `--lock-feet`: planted feet that do not slide.
//!
//! Retargeting by rotations reproduces the source's joint angles; where the target's thigh and
//! shin are proportioned unlike the source's, a foot the source keeps still moves on the
//! target's floor while the knee bends (a squat, a walk's stance). A foot is **planted** in a
//! frame where the source's body is on its floor (rule 6's contact), its own ankle is within
//! [`crate::floor::CONTACT_TOLERANCE`] of the leg length above its lowest height over the
//! motion, and that ankle is still (slower than [`crate::floor::STILL_LEGS_PER_SECOND`] leg
//! lengths a second). Locking shifts the root horizontally: while one foot stays planted, by
//! what keeps that foot's ankle where it was when it was planted; when it lifts and the other
//! is planted, that one is locked from where it is then; between plants the shift holds. The
//! shift is continuous (no jumps), the body's path drifts from the source's by what the feet
//! would have slid, and nothing vertical changes (rule 6 keeps the floor). Horizontal is the
//! XZ plane (the target's +Y up), in metres.

use glam::Vec3;
use serde::Serialize;

/// What locking the feet did (in `motion convert`'s report).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FootLockReport {
    /// Frames where a foot was planted.
    pub planted_frames: usize,
    /// The farthest a planted ankle moved from where it was planted, before locking (metres).
    pub largest_slide_before_m: f32,
    /// The same after locking (metres): what a foot switching plants leaves, nothing within a
    /// plant.
    pub largest_slide_after_m: f32,
    /// The largest horizontal shift of the root (metres).
    pub largest_shift_m: f32,
}

/// Which foot (0 or 1) is planted in each frame: `planted[foot][frame]`, from the source's
/// ankle positions `ankles[foot][frame]` (placed, metres, +Y up), the body's contact per frame
/// and the source's leg length (module docs).
pub fn planted(ankles: &[Vec<Vec3>; 2], contact: &[bool], fps: f32, leg: f32) -> [Vec<bool>; 2] {
    ankles.each_ref().map(|at| {
        let frames = at.len();
        let lowest = at.iter().map(|p| p.y).fold(f32::INFINITY, f32::min);
        (0..frames)
            .map(|f| {
                let speed = crate::floor::speed_at(|f| at[f], f, frames, fps);
                contact[f]
                    && at[f].y - lowest <= crate::floor::CONTACT_TOLERANCE * leg
                    && speed <= crate::floor::STILL_LEGS_PER_SECOND * leg
            })
            .collect()
    })
}

/// The root's horizontal shift per frame that keeps each planted foot's ankle where it was
/// planted (module docs): `ankles[foot][frame]` are the target's ankle positions before it.
pub fn shifts(ankles: &[Vec<Vec3>; 2], planted: &[Vec<bool>; 2]) -> (Vec<Vec3>, FootLockReport) {
    let frames = ankles[0].len();
    let flat = |v: Vec3| Vec3::new(v.x, 0.0, v.z);
    let mut shift = vec![Vec3::ZERO; frames];
    let mut held = Vec3::ZERO;
    // The locked foot and where its ankle is kept.
    let mut locked: Option<(usize, Vec3)> = None;
    let mut report = FootLockReport::default();
    // Where each foot's current plant began, before and after locking, for the report.
    let mut began: [Option<(Vec3, Vec3)>; 2] = [None, None];
    for f in 0..frames {
        if let Some((foot, _)) = locked
            && !planted[foot][f]
        {
            locked = None;
        }
        if locked.is_none()
            && let Some(foot) = (0..2).find(|&k| planted[k][f])
        {
            locked = Some((foot, flat(ankles[foot][f]) + held));
        }
        if let Some((foot, anchor)) = locked {
            held = anchor - flat(ankles[foot][f]);
        }
        shift[f] = held;
        report.largest_shift_m = report.largest_shift_m.max(held.length());
        for k in 0..2 {
            if !planted[k][f] {
                began[k] = None;
                continue;
            }
            let (before, after) = (flat(ankles[k][f]), flat(ankles[k][f]) + held);
            let (b0, a0) = *began[k].get_or_insert((before, after));
            report.largest_slide_before_m = report.largest_slide_before_m.max(before.distance(b0));
            report.largest_slide_after_m = report.largest_slide_after_m.max(after.distance(a0));
        }
    }
    report.planted_frames = (0..frames)
        .filter(|&f| planted[0][f] || planted[1][f])
        .count();
    (shift, report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_planted_foot_stays_and_the_other_takes_over_where_it_is() {
        // Foot 0 slides 1 cm a frame while planted in frames 0–4; foot 1 is planted in 3–7
        // (sliding 2 cm a frame); nothing is planted in 8–9.
        let ankles = [
            (0..10)
                .map(|f| Vec3::new(0.01 * f as f32, 0.1, 0.0))
                .collect(),
            (0..10)
                .map(|f| Vec3::new(0.3, 0.1, 0.02 * f as f32))
                .collect(),
        ];
        let planted = [
            (0..10).map(|f| f <= 4).collect(),
            (0..10).map(|f| (3..=7).contains(&f)).collect(),
        ];
        let (shift, report) = shifts(&ankles, &planted);
        let after = |k: usize, f: usize| ankles[k][f] + shift[f];
        for f in 0..=4 {
            assert!(after(0, f).distance(after(0, 0)) < 1e-6, "{f}");
        }
        // Foot 1 is locked from frame 5, where foot 0 lifts; the shift then holds.
        for f in 5..=7 {
            assert!(after(1, f).distance(after(1, 5)) < 1e-6, "{f}");
        }
        assert_eq!(shift[8], shift[7]);
        assert_eq!(shift[9], shift[7]);
        assert!(shift.iter().all(|s| s.y == 0.0));
        // Continuous: no frame's shift jumps by more than the slide it cancels.
        for f in 1..10 {
            assert!(shift[f].distance(shift[f - 1]) <= 0.02 + 1e-6, "{f}");
        }
        assert!(
            (report.largest_slide_before_m - 0.08).abs() < 1e-5,
            "{report:?}"
        );
        assert_eq!(report.planted_frames, 8);
    }

    #[test]
    fn a_foot_is_planted_where_it_is_down_and_still() {
        let leg = 0.9;
        // Foot 0: down and still in frames 0–3, then swinging up and forward.
        let swing = |f: usize| match f {
            0..=3 => Vec3::new(0.0, 0.08, 0.0),
            _ => Vec3::new(0.0, 0.08 + 0.05 * (f - 3) as f32, 0.1 * (f - 3) as f32),
        };
        let ankles = [
            (0..8).map(swing).collect(),
            (0..8).map(|_| Vec3::new(0.2, 0.08, 0.0)).collect(),
        ];
        let contact = vec![true; 8];
        let [left, right] = planted(&ankles, &contact, 30.0, leg);
        assert_eq!(left, [true, true, true, false, false, false, false, false]);
        assert!(right.iter().all(|p| *p));
        // Without the body's contact nothing is planted.
        let [left, _] = planted(&ankles, &[false; 8], 30.0, leg);
        assert!(left.iter().all(|p| !p));
    }
}
