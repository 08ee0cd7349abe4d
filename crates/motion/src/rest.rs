//! The source's reference pose: the pose its rotations are taken relative to (retargeting's
//! rule 4), and its up axis.
//!
//! A file's rest pose is the natural reference when the body stands in it (a T-pose, an
//! A-pose, arms down). Some do not: LAFAN1's rest has every bone along +X and only the frames'
//! rotations stand the body up; others rest in a crouch. Taken as the reference, such a rest
//! turns the target into a contorted body lying on its side. So a rest is checked: it
//! **stands** when, with the up axis turned to +Y, the trunk (pelvis to neck) is within
//! [`STANDING_DEGREES`] of +Y and each thigh and shin within it of −Y. Where it does not
//! (`--rest auto`, the default), the reference is the motion's frame that stands best (the
//! earliest within a degree of it), under whichever up axis (Y or Z) makes one stand; where
//! none stands, the file's rest is kept and the plausibility checks report the result.
//! `--rest file-rest` and `--rest first-frame` choose without checking (the first frame under
//! the up axis that stands it better).

use std::str::FromStr;

use glam::{Quat, Vec3};
use serde::Serialize;

use f3g_rig::{Role, Similarity};

use crate::{Motion, Up};

/// Trunk and leg bones within this of vertical stand (legs spread for an A-pose, a slight
/// forward lean of a capture's rest).
pub const STANDING_DEGREES: f32 = 35.0;

/// The trunk's top joint, the first of these roles a skeleton has: the trunk (pelvis to it)
/// gives a body's up.
pub const TRUNK_TOP: [Role; 4] = [Role::Neck, Role::Head, Role::Chest, Role::Spine];

/// At most this many frames are tried for the best standing one (evenly spaced).
const FRAMES_TRIED: usize = 2000;

/// `--rest`: which pose the source's rotations are taken relative to.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum RestChoice {
    /// The file's rest where the body stands in it, else the frame that stands best.
    #[default]
    Auto,
    /// The file's rest pose, whatever it is.
    FileRest,
    /// The motion's first frame.
    FirstFrame,
}

impl FromStr for RestChoice {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Self::Auto),
            "file-rest" => Ok(Self::FileRest),
            "first-frame" => Ok(Self::FirstFrame),
            _ => Err(format!(
                "{}: expected auto, file-rest or first-frame",
                f3g_io::quoted(s)
            )),
        }
    }
}

/// The reference chosen, for the report.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Reference {
    /// `None`: the file's rest pose; else the frame used.
    pub frame: Option<usize>,
    pub up: Up,
    /// Why the file's rest or up axis was not used, when it was not.
    pub reason: Option<String>,
}

/// The joints a standing check needs, by role.
pub struct StandingJoints {
    pub pelvis: usize,
    pub top: usize,
    /// (hip, knee, ankle) of each leg that has all three.
    pub legs: Vec<[usize; 3]>,
}

impl StandingJoints {
    /// From the source's joint of each role; `None` without a pelvis and a trunk top.
    pub fn new(joint: impl Fn(Role) -> Option<usize>) -> Option<Self> {
        let top = TRUNK_TOP.into_iter().find_map(&joint)?;
        let legs = [
            [Role::LeftHip, Role::LeftKnee, Role::LeftAnkle],
            [Role::RightHip, Role::RightKnee, Role::RightAnkle],
        ]
        .iter()
        .filter_map(|leg| Some([joint(leg[0])?, joint(leg[1])?, joint(leg[2])?]))
        .collect();
        Some(Self {
            pelvis: joint(Role::Pelvis)?,
            top,
            legs,
        })
    }

    /// The largest angle (degrees) of the trunk from +Y and of a thigh or shin from −Y, for
    /// positions in +Y-up axes.
    pub fn worst_degrees(&self, at: &[Vec3]) -> f32 {
        let angle = |v: Vec3, to: Vec3| {
            v.try_normalize()
                .map_or(180.0, |v| v.dot(to).clamp(-1.0, 1.0).acos().to_degrees())
        };
        let mut worst = angle(at[self.top] - at[self.pelvis], Vec3::Y);
        for [hip, knee, ankle] in &self.legs {
            worst = worst
                .max(angle(at[*knee] - at[*hip], Vec3::NEG_Y))
                .max(angle(at[*ankle] - at[*knee], Vec3::NEG_Y));
        }
        worst
    }
}

/// The rotation taking `up`-up coordinates to +Y-up ones.
pub fn up_to_y(up: Up) -> Quat {
    match up {
        Up::Y => Quat::IDENTITY,
        Up::Z => Quat::from_rotation_x(-std::f32::consts::FRAC_PI_2),
    }
}

fn other(up: Up) -> Up {
    match up {
        Up::Y => Up::Z,
        Up::Z => Up::Y,
    }
}

/// The reference pose (world transforms, file units and axes) and its up axis (module docs).
pub fn reference_pose(
    motion: &Motion,
    choice: RestChoice,
    joints: Option<&StandingJoints>,
) -> (Vec<Similarity>, Reference) {
    let rest = motion.skeleton.rest(None);
    let worst = |pose: &[Similarity], up: Up| {
        joints.map_or(0.0, |j| {
            let turn = up_to_y(up);
            let at: Vec<Vec3> = pose.iter().map(|s| turn * s.translation).collect();
            j.worst_degrees(&at)
        })
    };
    let file = |reason: Option<String>| {
        let reference = Reference {
            frame: None,
            up: motion.up,
            reason,
        };
        (rest.clone(), reference)
    };
    let best_up = |pose: &[Similarity]| {
        [motion.up, other(motion.up)]
            .into_iter()
            .map(|up| (worst(pose, up), up))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map_or(motion.up, |(_, up)| up)
    };
    match choice {
        RestChoice::FileRest => file(None),
        RestChoice::FirstFrame => {
            let pose = motion.world(0);
            let up = best_up(&pose);
            let reference = Reference {
                frame: Some(0),
                up,
                reason: Some("--rest first-frame".into()),
            };
            (pose, reference)
        }
        RestChoice::Auto => {
            let at_rest = worst(&rest, motion.up);
            if joints.is_none() || at_rest <= STANDING_DEGREES {
                return file(None);
            }
            let step = motion.frames().div_ceil(FRAMES_TRIED).max(1);
            let tried: Vec<(f32, usize, Up)> = (0..motion.frames())
                .step_by(step)
                .flat_map(|f| {
                    let pose = motion.world(f);
                    [motion.up, other(motion.up)].map(|up| (worst(&pose, up), f, up))
                })
                .collect();
            // The earliest frame within a degree of the best: the start of a clip, not a
            // frame that wins by rounding.
            let least = tried.iter().map(|t| t.0).fold(f32::INFINITY, f32::min);
            let best = tried.into_iter().find(|t| t.0 <= least + 1.0);
            match best {
                Some((w, f, up)) if w <= STANDING_DEGREES => {
                    let reference = Reference {
                        frame: Some(f),
                        up,
                        reason: Some(format!(
                            "the file's rest pose does not stand (a trunk or leg bone \
                             {at_rest:.0}° from vertical): frame {f} stands best ({w:.0}°), \
                             with {up:?} up"
                        )),
                    };
                    (motion.world(f), reference)
                }
                _ => file(Some(format!(
                    "the file's rest pose does not stand ({at_rest:.0}° from vertical) and no \
                     frame does: kept"
                ))),
            }
        }
    }
}
