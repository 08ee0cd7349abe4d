//! Whether a retargeted motion looks like its source: checked after every conversion by
//! rotations, so that a wrong up axis, a misread rest pose or a wrong joint correspondence
//! is reported instead of turned silently into a contorted body.
//!
//! Three checks, frame by frame, in the target's world (+Y up, metres):
//! - **Upright**: the target's trunk (pelvis to neck) within [`UPRIGHT_DEGREES`] of +Y; a
//!   body that is not upright in most frames is reported, and whether the source's trunk (as
//!   placed: its up axis turned to +Y) is.
//! - **Limbs**: every corresponding limb bone (upper arm, forearm, thigh, shin, clavicle) points
//!   within [`LIMB_DEGREES`] of the source's bone in the same frame; the bones off are named
//!   with their frames.
//! - **Floor**: the feet on the floor where the source's are ([`crate::floor`]'s report): none
//!   of the frames in contact, or the body left floating, is reported.

use glam::Vec3;
use serde::Serialize;

use crate::floor::FloorReport;

/// A trunk more than this far from vertical is not upright (a deep bow is still upright).
pub const UPRIGHT_DEGREES: f32 = 60.0;
/// A limb bone more than this far from the source's points elsewhere (the corpus of
/// conventions converts within 1°; joint limits of a body model cost a few degrees).
pub const LIMB_DEGREES: f32 = 20.0;
/// Feet further than this above the floor in a contact frame float (metres).
pub const FLOAT_METRES: f32 = 0.02;

/// A limb bone that points away from the source's.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct LimbOff {
    /// The target's bone, `joint → joint`.
    pub target: String,
    /// The source's, `joint → joint`.
    pub source: String,
    pub worst_degrees: f32,
    pub worst_frame: usize,
    /// The frames beyond [`LIMB_DEGREES`], as ranges `start..end` (end exclusive).
    pub frames: Vec<(usize, usize)>,
}

/// The checks' results (in `motion convert --report`), with a sentence per problem.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Plausibility {
    pub frames: usize,
    /// Frames whose target trunk is upright.
    pub upright_frames: usize,
    /// Frames whose source trunk is upright (as placed).
    pub source_upright_frames: usize,
    pub limbs_off: Vec<LimbOff>,
    /// One sentence per implausible finding; empty when the result looks like the source.
    pub warnings: Vec<String>,
}

/// One bone compared: names, then per frame the source's and the target's direction.
pub struct Bone {
    pub target: String,
    pub source: String,
    angles: Vec<f32>,
}

impl Bone {
    pub fn new(target: String, source: String) -> Self {
        Self {
            target,
            source,
            angles: Vec::new(),
        }
    }

    /// Records one frame's bone vectors (any length; a zero one counts as aligned).
    pub fn record(&mut self, source: Vec3, target: Vec3) {
        let angle = match (source.try_normalize(), target.try_normalize()) {
            (Some(s), Some(t)) => s.dot(t).clamp(-1.0, 1.0).acos().to_degrees(),
            _ => 0.0,
        };
        self.angles.push(angle);
    }
}

/// Whether a trunk vector (pelvis to neck) is upright.
pub fn upright(trunk: Vec3) -> bool {
    trunk
        .try_normalize()
        .is_some_and(|t| t.y >= UPRIGHT_DEGREES.to_radians().cos())
}

/// Runs of `true` in `flags`, as `start..end` ranges.
fn ranges(flags: impl Iterator<Item = bool>) -> Vec<(usize, usize)> {
    let mut out: Vec<(usize, usize)> = Vec::new();
    for (f, on) in flags.enumerate() {
        match out.last_mut() {
            Some(last) if on && last.1 == f => last.1 = f + 1,
            _ if on => out.push((f, f + 1)),
            _ => {}
        }
    }
    out
}

/// `a..b` ranges written for people: `12`, `12–40` (inclusive), at most five then a count.
fn frames_text(ranges: &[(usize, usize)]) -> String {
    let mut parts: Vec<String> = ranges
        .iter()
        .take(5)
        .map(|&(a, b)| match b - a {
            1 => a.to_string(),
            _ => format!("{a}–{}", b - 1),
        })
        .collect();
    if ranges.len() > 5 {
        parts.push(format!("and {} more runs", ranges.len() - 5));
    }
    parts.join(", ")
}

/// The checks (module docs) from each frame's trunk uprightness (target, source), the
/// compared bones and the floor's report (where the body was placed on a floor).
pub fn check(
    upright_target: &[bool],
    upright_source: &[bool],
    bones: &[Bone],
    floor: Option<&FloorReport>,
) -> Plausibility {
    let frames = upright_target.len();
    let count = |v: &[bool]| v.iter().filter(|u| **u).count();
    let mut report = Plausibility {
        frames,
        upright_frames: count(upright_target),
        source_upright_frames: count(upright_source),
        ..Plausibility::default()
    };
    if frames > 0 && 2 * report.upright_frames < frames {
        let lying = ranges(upright_target.iter().map(|u| !u));
        report.warnings.push(format!(
            "the body is upright in only {} of {frames} frames (not in frames {}){}",
            report.upright_frames,
            frames_text(&lying),
            if 2 * report.source_upright_frames < frames {
                "; neither is the source's as read: if it stands in the file, its up axis or \
                 rest pose was misread"
            } else {
                ", though the source's is: its rest pose was misread or a joint correspondence is \
                 wrong (see the correspondence; --joint-map)"
            }
        ));
    }
    for bone in bones {
        let off = ranges(bone.angles.iter().map(|a| *a > LIMB_DEGREES));
        if off.is_empty() {
            continue;
        }
        let (worst_frame, worst_degrees) = bone
            .angles
            .iter()
            .copied()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap_or((0, 0.0));
        report.warnings.push(format!(
            "the bone {} points up to {worst_degrees:.0}° away from the source's {} (frame \
             {worst_frame}; beyond {LIMB_DEGREES}° in frames {})",
            bone.target,
            bone.source,
            frames_text(&off)
        ));
        report.limbs_off.push(LimbOff {
            target: bone.target.clone(),
            source: bone.source.clone(),
            worst_degrees,
            worst_frame,
            frames: off,
        });
    }
    match floor {
        Some(f) if f.contact_frames == 0 => report
            .warnings
            .push("the source's feet never touch a floor: the body is not placed on one".into()),
        Some(f) if f.largest_float_m > FLOAT_METRES => report.warnings.push(format!(
            "the feet stay up to {:.1} cm above the floor where the source's touch it",
            100.0 * f.largest_float_m
        )),
        _ => {}
    }
    report
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_of_frames_are_named_briefly() {
        let r = ranges([true, true, false, true, false, false, true].into_iter());
        assert_eq!(r, [(0, 2), (3, 4), (6, 7)]);
        assert_eq!(frames_text(&r), "0–1, 3, 6");
        let many: Vec<(usize, usize)> = (0..7).map(|i| (2 * i, 2 * i + 1)).collect();
        assert_eq!(frames_text(&many), "0, 2, 4, 6, 8, and 2 more runs");
    }

    #[test]
    fn a_body_lying_down_and_a_limb_pointing_elsewhere_are_reported() {
        let mut arm = Bone::new(
            "upperarm_l → lowerarm_l".into(),
            "LeftArm → LeftForeArm".into(),
        );
        let mut leg = Bone::new("thigh_l → calf_l".into(), "LeftUpLeg → LeftLeg".into());
        for f in 0..4 {
            arm.record(Vec3::NEG_Y, if f == 2 { Vec3::Z } else { Vec3::NEG_Y });
            leg.record(Vec3::NEG_Y, Vec3::new(0.1, -1.0, 0.0));
        }
        let floor = FloorReport {
            contact_frames: 4,
            frames: 4,
            ..FloorReport::default()
        };
        let fine = check(&[true; 4], &[true; 4], &[], Some(&floor));
        assert!(fine.warnings.is_empty(), "{fine:?}");
        let r = check(
            &[false, false, true, false],
            &[true; 4],
            &[arm, leg],
            Some(&floor),
        );
        assert_eq!(r.warnings.len(), 2, "{r:?}");
        assert!(
            r.warnings[0].contains("upright in only 1 of 4") && r.warnings[0].contains("0–1, 3")
        );
        assert!(
            r.warnings[0].contains("correspondence"),
            "{}",
            r.warnings[0]
        );
        assert_eq!(r.limbs_off.len(), 1);
        assert_eq!(
            (r.limbs_off[0].worst_frame, r.limbs_off[0].frames.clone()),
            (2, vec![(2, 3)])
        );
        assert!(
            r.warnings[1].contains("upperarm_l") && r.warnings[1].contains("90°"),
            "{}",
            r.warnings[1]
        );
        let floating = FloorReport {
            largest_float_m: 0.05,
            ..floor
        };
        let r = check(&[true; 4], &[true; 4], &[], Some(&floating));
        assert!(r.warnings[0].contains("5.0 cm above"), "{r:?}");
        assert!(check(&[true; 4], &[true; 4], &[], None).warnings.is_empty());
        assert!(upright(Vec3::new(0.0, 1.0, 1.5)) && !upright(Vec3::new(0.0, 1.0, 2.0)));
    }
}
