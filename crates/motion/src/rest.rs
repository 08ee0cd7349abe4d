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
//! the up axis that stands it better). `--rest t-pose` builds a reference from the file's rest:
//! each bone keeps its length, the trunk stands along the up axis, the legs hang straight down
//! and the clavicles and arms point straight out sideways, facing as the first frame does,
//! with the up axis along which the trunk stands highest above the ankles over the frames:
//! for a rest that says nothing of up (LAFAN1's) in a motion none of whose frames stands (a
//! crouch, a crawl).

use std::str::FromStr;

use glam::{Mat3, Quat, Vec3};
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
    /// A T-pose built from the file's rest: its bone lengths, the trunk along the up axis,
    /// legs down, arms out sideways.
    TPose,
}

impl FromStr for RestChoice {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Self::Auto),
            "file-rest" => Ok(Self::FileRest),
            "first-frame" => Ok(Self::FirstFrame),
            "t-pose" => Ok(Self::TPose),
            _ => Err(format!(
                "{}: expected auto, file-rest, first-frame or t-pose",
                f3g_io::quoted(s)
            )),
        }
    }
}

/// The reference chosen, for the report.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Reference {
    /// `None`: the file's rest pose (or the T-pose built from it); else the frame used.
    pub frame: Option<usize>,
    /// Whether the reference is the T-pose built from the file's rest (`--rest t-pose`).
    pub t_pose: bool,
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
    /// Bones of the T-pose ([`t_pose`]): (joint, the joint its bone ends at, which way it
    /// points in the T).
    bones: Vec<(usize, usize, TBone)>,
    /// (left, right) hips.
    hips: Option<(usize, usize)>,
}

/// Which way a bone points in the T-pose.
#[derive(Clone, Copy)]
enum TBone {
    Up,
    Down,
    Left,
    Right,
}

impl StandingJoints {
    /// From the source's joint of each role; `None` without a pelvis and a trunk top.
    pub fn new(joint: impl Fn(Role) -> Option<usize>) -> Option<Self> {
        let top_role = TRUNK_TOP.into_iter().find(|&r| joint(r).is_some())?;
        let top = joint(top_role)?;
        let legs = [
            [Role::LeftHip, Role::LeftKnee, Role::LeftAnkle],
            [Role::RightHip, Role::RightKnee, Role::RightAnkle],
        ]
        .iter()
        .filter_map(|leg| Some([joint(leg[0])?, joint(leg[1])?, joint(leg[2])?]))
        .collect();
        let pelvis = joint(Role::Pelvis)?;
        use Role::*;
        let chains: [(&[Role], TBone); 5] = [
            (&[Pelvis, top_role, Head], TBone::Up),
            (&[LeftHip, LeftKnee, LeftAnkle], TBone::Down),
            (&[RightHip, RightKnee, RightAnkle], TBone::Down),
            (
                &[LeftClavicle, LeftShoulder, LeftElbow, LeftWrist],
                TBone::Left,
            ),
            (
                &[RightClavicle, RightShoulder, RightElbow, RightWrist],
                TBone::Right,
            ),
        ];
        // Each role's bone ends at the next role of its chain the skeleton has.
        let mut bones = Vec::new();
        for (chain, way) in chains {
            let mut present: Vec<usize> = chain.iter().filter_map(|&r| joint(r)).collect();
            present.dedup();
            bones.extend(present.windows(2).map(|w| (w[0], w[1], way)));
        }
        Some(Self {
            pelvis,
            top,
            legs,
            bones,
            hips: joint(LeftHip).zip(joint(RightHip)),
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

/// The up axis as a vector of `up`-up coordinates.
fn up_vector(up: Up) -> Vec3 {
    match up {
        Up::Y => Vec3::Y,
        Up::Z => Vec3::Z,
    }
}

/// The up axis (Y or Z) along which the trunk's top stands highest above the ankles over the
/// motion's frames: a body's up whether it stands, crouches or sits, when the rest says
/// nothing. `None` without ankles.
fn up_from_frames(motion: &Motion, joints: &StandingJoints) -> Option<Up> {
    let ankles: Vec<usize> = joints.legs.iter().map(|leg| leg[2]).collect();
    if ankles.is_empty() {
        return None;
    }
    let step = motion.frames().div_ceil(FRAMES_TRIED).max(1);
    let mut height = [0.0f32; 2];
    for f in (0..motion.frames()).step_by(step) {
        let pose = motion.world(f);
        for (sum, up) in height.iter_mut().zip([Up::Y, Up::Z]) {
            let axis = up_vector(up);
            let lowest = ankles
                .iter()
                .map(|&a| pose[a].translation.dot(axis))
                .fold(f32::INFINITY, f32::min);
            *sum += pose[joints.top].translation.dot(axis) - lowest;
        }
    }
    Some(if height[1] > height[0] { Up::Z } else { Up::Y })
}

/// `--rest t-pose` (module docs): the file's rest with each bone of `joints` turned to its
/// T-pose direction along `up`, the joints between it and its end turned with it, every other
/// joint with its parent. Left is where the left hip lies in the first frame (the rest's
/// axes may be anything: LAFAN1's hips lie along its forward axis), else in the rest; `None`
/// without two hips apart.
fn t_pose(
    motion: &Motion,
    rest: &[Similarity],
    joints: &StandingJoints,
    up: Up,
) -> Option<Vec<Similarity>> {
    let up = up_vector(up);
    let across = |at: &[Similarity]| {
        let (l, r) = joints.hips?;
        let v = at[l].translation - at[r].translation;
        (v - up * v.dot(up)).try_normalize()
    };
    let left = across(&motion.world(0)).or_else(|| across(rest))?;
    let skeleton = &motion.skeleton;
    let mut turn = vec![Quat::IDENTITY; rest.len()];
    let mut pose = rest.to_vec();
    for j in 0..rest.len() {
        let parent = skeleton.joints()[j].parent;
        let inherited = parent.map_or(Quat::IDENTITY, |p| turn[p]);
        turn[j] = match joints.bones.iter().find(|b| b.0 == j) {
            Some(&(_, end, way)) => {
                let to = match way {
                    TBone::Up => up,
                    TBone::Down => -up,
                    TBone::Left => left,
                    TBone::Right => -left,
                };
                let from = (rest[end].translation - rest[j].translation).try_normalize();
                match (from, j == joints.pelvis) {
                    // The pelvis turns the hips with it: its bone to up and the hips' left
                    // (at rest, across the bone) to left.
                    (Some(from), true) => joints
                        .hips
                        .map(|(l, r)| rest[l].translation - rest[r].translation)
                        .and_then(|l| (l - from * l.dot(from)).try_normalize())
                        .map_or(Quat::from_rotation_arc(from, to), |l| {
                            let basis = |l: Vec3, u: Vec3| Mat3::from_cols(l, u, l.cross(u));
                            let at_rest = basis(l, from);
                            Quat::from_mat3(&(basis(left, up) * at_rest.transpose())).normalize()
                        }),
                    (Some(from), false) => Quat::from_rotation_arc(from, to),
                    (None, _) => inherited,
                }
            }
            None => inherited,
        };
        if let Some(p) = parent {
            pose[j].translation =
                pose[p].translation + turn[p] * (rest[j].translation - rest[p].translation);
        }
        pose[j].rotation = (turn[j] * rest[j].rotation).normalize();
    }
    Some(pose)
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
            t_pose: false,
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
        RestChoice::TPose => match joints.and_then(|j| {
            let up = up_from_frames(motion, j).unwrap_or(motion.up);
            Some((t_pose(motion, &rest, j, up)?, up))
        }) {
            Some((pose, up)) => {
                let reference = Reference {
                    frame: None,
                    t_pose: true,
                    up,
                    reason: Some(format!(
                        "--rest t-pose: the file's rest with the trunk up, legs down and arms \
                         out sideways, {up:?} up (where the trunk stands highest above the \
                         ankles over the frames)"
                    )),
                };
                (pose, reference)
            }
            None => file(Some(
                "--rest t-pose needs a pelvis, a trunk and two hips apart: the file's rest kept"
                    .into(),
            )),
        },
        RestChoice::FirstFrame => {
            let pose = motion.world(0);
            let up = best_up(&pose);
            let reference = Reference {
                frame: Some(0),
                t_pose: false,
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
                        t_pose: false,
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
