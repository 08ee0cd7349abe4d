//! Retargeting: a motion of any skeleton drives a body model.
//!
//! The rules, in order:
//! 1. **Same family, same parameters.** An SMPL-family motion (AMASS, `.smpl`,
//!    `smpl_params.npz`) on an SMPL-X body model maps parameter for parameter (the global
//!    orientation and translation turned from the file's up axis to +Y).
//! 2. **Correspondence.** Otherwise joints correspond by role: the target's roles are the body
//!    model's ([`f3g_rig::Rig::roles`]); the source's are inferred from its joint names
//!    ([`f3g_rig::Roles::infer`]: prefixes, side markers and synonyms; completed from the
//!    skeleton's shape, [`f3g_rig::Roles::completed`]) or, where the names give neither hip,
//!    from the shape and the motion ([`f3g_rig::Roles::from_motion`]), overridden by a `--joint-map`
//!    ([`f3g_rig::RoleMap`], role → source joint name). Joints whose names are equal
//!    correspond first, unless the pair contradicts the roles: where the target joint's role
//!    belongs to another source joint that no name pairs (Unreal's `root` on the floor is not
//!    the built-in human's `root`, its pelvis: the motion's `pelvis` is), or the other way
//!    round. The pelvis and both hips must correspond.
//! 3. **Axes and units.** The source is scaled to metres, turned from its up axis to +Y and
//!    turned about +Y so that its rest pose faces the target's (left hip to right hip). Its
//!    "rest" here and below is its reference pose ([`crate::rest`]): the file's rest where the
//!    body stands in it, else the motion's best standing frame, whose up axis is used.
//! 4. **Rest-pose alignment.** Each corresponding joint's rotation is taken relative to its own
//!    skeleton's rest pose: the target joint turns by the source joint's world rotation since
//!    rest, after first turning its rest frame onto the source's — the whole body by its up
//!    (pelvis to neck) and left (hip to hip) axes, then each limb joint's bone onto the source's
//!    rest bone (toward the next corresponding joint down the arm or leg). So a T-pose source drives an
//!    A-pose target: at the source's rest, the target's arms are raised into a T. Joints
//!    without a correspondent keep their rest rotation relative to their parent; fingers and
//!    face follow the hands and head.
//! 5. **Root.** The target's pelvis follows the source's, scaled by the ratio of leg lengths
//!    (hip to knee to ankle at rest), its height measured from the lowest joint — the
//!    target's at rest, the source's over the whole motion (where a foot is on the ground) —
//!    so strides fit the legs (rule 6 puts the feet on the floor). The target's own skeleton (every
//!    joint by name, in place) carries its root over unchanged.
//! 6. **Floor.** Where the source's feet touch its floor, the target's lowest point is put on
//!    the target's floor by a vertical shift of the root, interpolated between contacts
//!    ([`crate::floor`]): proportions differ, so rule 5 alone floats or sinks the feet.
//!
//! Channels a body model lacks (a knee that only bends) are left out; the largest angle lost
//! is reported.

use std::collections::BTreeMap;
use std::path::Path;

use glam::{Quat, Vec3};
use serde::Serialize;

use f3g_rig::{Rig, RigParams, Role, RoleMap, Roles};

use crate::floor::{FloorReport, Sole, SourceFeet, shifts};
use crate::foot_lock::{self, FootLockReport};
use crate::plausibility::{self, Plausibility, upright};
use crate::rest::{Reference, RestChoice, StandingJoints, TRUNK_TOP, reference_pose, up_to_y};
use crate::{Motion, MotionError};

/// What retargeting needs beyond the motion and the body model.
#[derive(Clone, Debug, Default)]
pub struct RetargetOptions {
    /// Source roles by joint name, over the inferred ones.
    pub joint_map: Option<RoleMap>,
    /// Resample to this frame rate.
    pub fps: Option<f32>,
    /// The target's shape parameters (the avatar's subject); empty for the model's template.
    pub identity: Vec<f32>,
    /// The source pose its rotations are taken relative to ([`crate::rest`]).
    pub rest: RestChoice,
    /// Keep planted feet from sliding by shifting the root horizontally ([`crate::foot_lock`]).
    pub lock_feet: bool,
}

/// How a target joint found its source joint.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Matched {
    Role(Role),
    Name,
}

/// One corresponding pair.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Correspondence {
    pub target: String,
    pub source: String,
    pub by: Matched,
}

/// Where the source's roles came from (rule 2).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RolesFrom {
    /// The joint names (completed from the skeleton's shape), or the same family.
    Names,
    /// The skeleton's shape alone ([`Roles::from_motion`]): the names give no hip.
    Shape,
}

/// A retargeted motion and how it was made.
#[derive(Clone, Debug, Serialize)]
pub struct Retargeted {
    #[serde(skip)]
    pub frames: Vec<RigParams>,
    pub fps: f32,
    /// "parameters" (same family) or "rotations".
    pub method: &'static str,
    pub correspondence: Vec<Correspondence>,
    /// The source's roles, as a `--joint-map` file holds them.
    pub source_roles: RoleMap,
    /// Where the source's roles came from.
    pub roles_from: RolesFrom,
    /// Source joints that drive nothing.
    pub unmatched_source: Vec<String>,
    /// Roles of the target with no source joint, each with the motion's unmatched joints
    /// whose names are closest to it (a start for a `--joint-map`).
    pub unmatched_roles: Vec<(Role, Vec<String>)>,
    /// Target metres per source metre (leg lengths).
    pub scale: f32,
    /// Largest rotation (degrees) left out because the body model cannot turn a joint so.
    pub dropped_degrees: f32,
    /// How rule 6 put the body on the floor; `None` where it does not apply (the same
    /// family's parameters, the target's own skeleton, a source without ankles).
    pub floor: Option<FloorReport>,
    /// What `--lock-feet` did; `None` where it was not asked for or does not apply (no floor
    /// contact, no ankles on either side).
    pub feet_locked: Option<FootLockReport>,
    /// Whether the result looks like the source ([`crate::plausibility`]); `None` for the
    /// same family's parameters.
    pub plausibility: Option<Plausibility>,
    /// The source's reference pose and up axis ([`crate::rest`]); `None` for the same
    /// family's parameters.
    pub reference: Option<Reference>,
}

/// Whether `rig` is an SMPL-X model (its joints and parameterisation).
fn is_smplx(rig: &Rig) -> bool {
    rig.parameterization == f3g_rig::Parameterization::AxisAngle
        && rig
            .skeleton
            .joints()
            .iter()
            .map(|j| j.name.as_str())
            .eq(f3g_rig::smplx::JOINT_NAMES)
}

/// Retargets `motion` (read from `path`, named in errors) onto `rig` (module docs).
pub fn retarget(
    motion: &Motion,
    rig: &Rig,
    options: &RetargetOptions,
    path: &Path,
) -> Result<Retargeted, MotionError> {
    if motion.frames() == 0 {
        return Err(MotionError::file(path, "holds no frames"));
    }
    let resampled;
    let motion = match options.fps {
        Some(fps) if fps != motion.fps => {
            if !(fps.is_finite() && fps > 0.0 && fps <= 1000.0) {
                return Err(MotionError::file(
                    path,
                    format!("--fps {fps}: expected between 0 and 1000"),
                ));
            }
            resampled = motion.resampled(fps, path)?;
            &resampled
        }
        _ => motion,
    };
    let mut base = rig.zero_params();
    if !options.identity.is_empty() {
        if options.identity.len() != base.identity.len() {
            return Err(MotionError::retarget(
                path,
                format!(
                    "{} identity values for the body model `{}`, which has {}",
                    options.identity.len(),
                    rig.name,
                    base.identity.len()
                ),
            ));
        }
        base.identity = options.identity.clone();
    }
    match &motion.smpl {
        Some(smpl) if is_smplx(rig) && options.joint_map.is_none() => {
            same_family(motion, smpl, rig, &base, path)
        }
        _ => by_rotations(motion, rig, options, &base, path),
    }
}

/// Rule 1.
fn same_family(
    motion: &Motion,
    smpl: &crate::SmplMotion,
    rig: &Rig,
    base: &RigParams,
    path: &Path,
) -> Result<Retargeted, MotionError> {
    let turn = up_to_y(motion.up);
    let params = smpl.params(motion);
    let rest_pelvis = rig.joint_world(base)?[0].translation;
    let mut frames = params
        .frames_for(rig)
        .map_err(|e| MotionError::retarget(path, e))?;
    for (f, p) in frames.iter_mut().enumerate() {
        p.identity.clone_from(&base.identity);
        let global = f3g_rig::rig::axis_angle(Vec3::from_slice(&p.pose[0..3]));
        let _ = rig.set_joint_rotation(p, 0, turn * global);
        let t = Vec3::from_slice(&params.transl[3 * f..3 * f + 3]);
        rig.set_root_translation(p, turn * (rest_pelvis + t) - rest_pelvis)?;
    }
    let names: Vec<String> = rig
        .skeleton
        .joints()
        .iter()
        .map(|j| j.name.clone())
        .collect();
    Ok(Retargeted {
        frames,
        fps: motion.fps,
        method: "parameters",
        correspondence: names
            .iter()
            .map(|n| Correspondence {
                target: n.clone(),
                source: n.clone(),
                by: Matched::Name,
            })
            .collect(),
        source_roles: RoleMap::default(),
        roles_from: RolesFrom::Names,
        unmatched_source: Vec::new(),
        unmatched_roles: Vec::new(),
        scale: 1.0,
        dropped_degrees: 0.0,
        floor: None,
        feet_locked: None,
        plausibility: None,
        reference: None,
    })
}

/// The role whose joint a limb role's bone points to. Torso and head bones are not aligned
/// one by one: how a skeleton splits its spine (and tilts its short pelvis bone) is modelling,
/// not pose, so they take the whole body's alignment.
fn bone_end(role: Role) -> &'static [Role] {
    use Role::*;
    match role {
        LeftClavicle => &[LeftShoulder],
        RightClavicle => &[RightShoulder],
        LeftShoulder => &[LeftElbow],
        RightShoulder => &[RightElbow],
        LeftElbow => &[LeftWrist],
        RightElbow => &[RightWrist],
        LeftHip => &[LeftKnee],
        RightHip => &[RightKnee],
        LeftKnee => &[LeftAnkle],
        RightKnee => &[RightAnkle],
        _ => &[],
    }
}

/// Hip to knee to ankle at rest (or the pelvis height above the lowest joint), with the
/// joint of each role given by `joint`.
fn leg_length(joint: impl Fn(Role) -> Option<usize>, rest: &[Vec3], floor: f32) -> f32 {
    let at = |r: Role| joint(r).map(|j| rest[j]);
    match (at(Role::LeftHip), at(Role::LeftKnee), at(Role::LeftAnkle)) {
        (Some(h), Some(k), Some(a)) => h.distance(k) + k.distance(a),
        _ => at(Role::Pelvis).map_or(1.0, |p| p.y - floor),
    }
}

/// Roles the names left out, from the skeleton's shape ([`Roles::completed`]): the pelvis
/// where the two legs meet, the chest where the two arms meet, the spine after the pelvis
/// toward it, and the chain that leaves the chest toward neither arm neck to head (Blender's
/// `spine.004` to `spine.006`).
pub fn complete_by_topology(skeleton: &f3g_rig::Skeleton, roles: Roles) -> Roles {
    roles.completed(skeleton)
}

/// At most this many of a motion's frames (evenly spaced) tell a toeless skeleton's sides.
const SHAPE_FRAMES: usize = 240;

/// The source's roles (rule 2): from its names, completed from its shape; where the names
/// give neither hip, from its shape alone ([`Roles::from_motion`]: the tree and the motion's
/// first frame, its sides from the feet or else from the motion's knees and walk), with what
/// the names do give put over them. The third value says why the shape gave
/// none, when it was tried and failed.
fn source_roles(motion: &Motion) -> (Roles, RolesFrom, Option<String>) {
    let source = &motion.skeleton;
    let named = Roles::infer(source);
    if named.get(Role::LeftHip).is_some() || named.get(Role::RightHip).is_some() {
        return (complete_by_topology(source, named), RolesFrom::Names, None);
    }
    // The motion's poses, for a skeleton without toes (its knees and its walk tell its sides).
    let step = motion.frames().div_ceil(SHAPE_FRAMES).max(1);
    let poses: Vec<Vec<Vec3>> = (0..motion.frames())
        .step_by(step)
        .map(|f| motion.positions(f))
        .collect();
    match Roles::from_motion(source, &motion.positions(0), &poses) {
        Ok(shape) => {
            let taken: Vec<usize> = shape.iter().map(|(_, j)| j).collect();
            let extra = named
                .iter()
                .filter(|(r, j)| shape.get(*r).is_none() && !taken.contains(j));
            let roles = Roles::from_pairs(shape.iter().chain(extra));
            (complete_by_topology(source, roles), RolesFrom::Shape, None)
        }
        Err(e) => (
            complete_by_topology(source, named),
            RolesFrom::Names,
            Some(e),
        ),
    }
}

/// Up to three of `names` closest to `role`'s name: edit distance between the lowercase
/// letters and digits of each (`mixamorig:LeftStrut` → `mixamorigleftstrut` against
/// `lefthip`), with the role's side word required when it has one.
fn closest_names(role: Role, names: &[&str]) -> Vec<String> {
    let key = |s: &str| -> Vec<char> {
        s.chars()
            .filter(char::is_ascii_alphanumeric)
            .map(|c| c.to_ascii_lowercase())
            .collect()
    };
    let target = key(&role.name());
    let side = ["left", "right"]
        .into_iter()
        .find(|s| role.name().starts_with(s));
    let distance = |a: &[char], b: &[char]| -> usize {
        // Levenshtein, one row; `b` may contain `a` anywhere at no cost for the rest.
        let mut row: Vec<usize> = vec![0; b.len() + 1];
        for (i, ca) in a.iter().enumerate() {
            let mut previous = row[0];
            row[0] = i + 1;
            for (j, cb) in b.iter().enumerate() {
                let substitute = previous + usize::from(ca != cb);
                previous = row[j + 1];
                row[j + 1] = substitute.min(row[j] + 1).min(row[j + 1] + 1);
            }
        }
        row.into_iter().min().unwrap_or(a.len())
    };
    let mut scored: Vec<(usize, &str)> = names
        .iter()
        .filter(|n| {
            side.is_none_or(|s| {
                let k: String = key(n).into_iter().collect();
                k.contains(s) || k.ends_with(&s[..1]) || k.starts_with(&s[..1])
            })
        })
        .map(|n| (distance(&target, &key(n)), *n))
        .filter(|(d, _)| 2 * *d <= target.len())
        .collect();
    scored.sort();
    scored
        .into_iter()
        .take(3)
        .map(|(_, n)| n.to_string())
        .collect()
}

/// Rules 2 to 5.
fn by_rotations(
    motion: &Motion,
    rig: &Rig,
    options: &RetargetOptions,
    base: &RigParams,
    path: &Path,
) -> Result<Retargeted, MotionError> {
    let source = &motion.skeleton;
    let target = &rig.skeleton;
    let (mut source_roles, roles_from, shape_failure) = source_roles(motion);
    if let Some(map) = &options.joint_map {
        source_roles = source_roles
            .with_map(source, map)
            .map_err(|e| MotionError::retarget(path, format!("--joint-map: {e}")))?;
    }
    let roles_of = |roles: &Roles, n: usize| -> Vec<Option<Role>> {
        let mut v = vec![None; n];
        for (r, j) in roles.iter() {
            v[j] = Some(r);
        }
        v
    };
    let target_role = roles_of(&rig.roles, target.len());
    let source_role = roles_of(&source_roles, source.len());

    // Rule 2: correspondence, by name first (the same name is the same joint), then by role.
    let mut pair: Vec<Option<usize>> = target
        .joints()
        .iter()
        .map(|j| source.index_of(&j.name))
        .collect();
    // A pair by name yields where it contradicts the roles: the target joint's role is
    // another source joint's, one no name pairs (Unreal's `root` on the floor is not the
    // built-in human's `root`, its pelvis; the motion's `pelvis` is), or the other way round.
    let named: Vec<Option<usize>> = pair.clone();
    let name_paired_source = |s: usize| named.contains(&Some(s));
    for t in 0..target.len() {
        let Some(s) = named[t] else { continue };
        let (rt, rs) = (target_role[t], source_role[s]);
        if rt == rs {
            continue;
        }
        let source_has_other = rt
            .and_then(|r| source_roles.get(r))
            .is_some_and(|o| o != s && !name_paired_source(o));
        let target_has_other = rs
            .and_then(|r| rig.roles.get(r))
            .is_some_and(|o| o != t && named[o].is_none());
        if source_has_other || target_has_other {
            pair[t] = None;
        }
    }
    let mut by: Vec<Option<Matched>> = pair.iter().map(|p| p.map(|_| Matched::Name)).collect();
    for t in 0..target.len() {
        if let (None, Some(r)) = (pair[t], target_role[t])
            && let Some(s) = source_roles.get(r)
            && !pair.contains(&Some(s))
        {
            pair[t] = Some(s);
            by[t] = Some(Matched::Role(r));
        }
    }
    let correspondence: Vec<Correspondence> = (0..target.len())
        .filter_map(|t| {
            Some(Correspondence {
                target: target.joints()[t].name.clone(),
                source: source.joints()[pair[t]?].name.clone(),
                by: by[t]?,
            })
        })
        .collect();
    let source_of = |r: Role| rig.roles.get(r).and_then(|t| pair[t]);
    let unmatched_source: Vec<String> = (0..source.len())
        .filter(|s| !pair.contains(&Some(*s)))
        .map(|s| source.joints()[s].name.clone())
        .collect();
    let without_role: Vec<&str> = (0..source.len())
        .filter(|&s| source_role[s].is_none() && !pair.contains(&Some(s)))
        .map(|s| source.joints()[s].name.as_str())
        .collect();
    let unmatched_roles: Vec<(Role, Vec<String>)> = rig
        .roles
        .iter()
        .map(|(r, _)| r)
        .filter(|&r| source_of(r).is_none())
        .map(|r| (r, closest_names(r, &without_role)))
        .collect();
    for needed in [Role::Pelvis, Role::LeftHip, Role::RightHip] {
        if let Some((_, closest)) = unmatched_roles.iter().find(|(r, _)| *r == needed) {
            let guess = closest.first().map_or("Hips", String::as_str);
            return Err(MotionError::retarget(
                path,
                format!(
                    "no joint of the motion's skeleton takes the role `{}` (closest names: \
                     {}){}: name it in a --joint-map file (JSON, role → joint, e.g. \
                     {{\"{}\": \"{guess}\"}}); the joints without a role are: {}",
                    needed.name(),
                    if closest.is_empty() {
                        "none".into()
                    } else {
                        closest.join(", ")
                    },
                    shape_failure
                        .as_ref()
                        .map_or(String::new(), |e| format!(", nor from its shape: {e}")),
                    needed.name(),
                    without_role.join(", ")
                ),
            ));
        }
    }
    let source_role_map = RoleMap(
        source_roles
            .iter()
            .map(|(r, j)| (r, source.joints()[j].name.clone()))
            .collect::<BTreeMap<_, _>>(),
    );

    // Rule 3: the source's world in the target's.
    let unit = motion.metres_per_unit;
    let standing = StandingJoints::new(|r| source_roles.get(r));
    let (source_rest, reference) = reference_pose(motion, options.rest, standing.as_ref());
    let up_turn = up_to_y(reference.up);
    let target_rest = rig.joint_world(base)?;
    let horizontal = |v: Vec3| {
        let v = Vec3::new(v.x, 0.0, v.z);
        (v.length() > 1e-6).then(|| v.normalize())
    };
    let source_left = source_of(Role::LeftHip)
        .zip(source_of(Role::RightHip))
        .and_then(|(l, r)| {
            horizontal(up_turn * (source_rest[l].translation - source_rest[r].translation))
        });
    let target_left = rig
        .roles
        .get(Role::LeftHip)
        .zip(rig.roles.get(Role::RightHip))
        .and_then(|(l, r)| horizontal(target_rest[l].translation - target_rest[r].translation));
    let facing = match (source_left, target_left) {
        (Some(s), Some(t)) => Quat::from_rotation_arc(s, t),
        _ => Quat::IDENTITY,
    };
    let turn = (facing * up_turn).normalize();
    let place = |p: Vec3| turn * (p * unit);

    // Rule 4: rest-pose alignment. The whole body first (its up and left axes at rest: a
    // source whose rest lies in its file's world, as AMASS's does, stands up), then each
    // corresponding joint's bone onto the source's, toward the corresponding joint of the
    // next role down its chain.
    let placed_rest: Vec<Vec3> = source_rest.iter().map(|s| place(s.translation)).collect();
    let target_positions: Vec<Vec3> = target_rest.iter().map(|s| s.translation).collect();
    let body = |joint: &dyn Fn(Role) -> Option<usize>, at: &[Vec3]| -> Option<Quat> {
        let pelvis = at[joint(Role::Pelvis)?];
        let top = TRUNK_TOP.into_iter().find_map(joint)?;
        let up = (at[top] - pelvis).normalize_or_zero();
        let left = at[joint(Role::LeftHip)?] - at[joint(Role::RightHip)?];
        let left = (left - up * left.dot(up)).normalize_or_zero();
        (up != Vec3::ZERO && left != Vec3::ZERO)
            .then(|| Quat::from_mat3(&glam::Mat3::from_cols(left, up, left.cross(up))))
    };
    let whole = match (
        body(&source_of, &placed_rest),
        body(&|r| rig.roles.get(r), &target_positions),
    ) {
        (Some(s), Some(t)) => (s * t.conjugate()).normalize(),
        _ => Quat::IDENTITY,
    };
    let bone = |t: usize, s: usize| -> Option<(Vec3, Vec3)> {
        bone_end(target_role[t]?).iter().find_map(|&end| {
            let c = rig.roles.get(end)?;
            let sc = pair[c]?;
            let tv = whole * (target_positions[c] - target_positions[t]);
            let sv = placed_rest[sc] - placed_rest[s];
            (tv.length() > 1e-6 && sv.length() > 1e-6).then(|| (tv.normalize(), sv.normalize()))
        })
    };
    let mut align = vec![whole; target.len()];
    for t in 0..target.len() {
        let inherited = target.joints()[t].parent.map_or(whole, |p| align[p]);
        align[t] = match pair[t].and_then(|s| bone(t, s)) {
            Some((tv, sv)) => (Quat::from_rotation_arc(tv, sv) * whole).normalize(),
            None => inherited,
        };
    }

    // Rule 5: the root, measured from the lowest joint: the target's at rest, the source's
    // over the whole motion (where a foot touches the ground), or at rest when the source is
    // the target's own skeleton in place.
    let lowest = |at: &[Vec3]| at.iter().map(|p| p.y).fold(f32::MAX, f32::min);
    let own_skeleton = correspondence.len() == target.len()
        && (0..target.len())
            .all(|t| pair[t].is_some_and(|s| placed_rest[s].distance(target_positions[t]) < 1e-3));
    let target_floor = lowest(&target_positions);
    let source_floor = if own_skeleton {
        lowest(&placed_rest)
    } else {
        (0..motion.frames())
            .map(|f| {
                let w: Vec<Vec3> = motion
                    .world(f)
                    .iter()
                    .map(|s| place(s.translation))
                    .collect();
                lowest(&w)
            })
            .fold(f32::MAX, f32::min)
    };
    let source_leg = leg_length(source_of, &placed_rest, lowest(&placed_rest)).max(1e-6);
    let scale = leg_length(|r| rig.roles.get(r), &target_positions, target_floor) / source_leg;
    // Rule 6's source side: the ankles and every joint below them, each against its height
    // above the lowest of them at rest (a foot is down when a joint is that low).
    let mut foot = vec![false; source.len()];
    for (j, joint) in source.joints().iter().enumerate() {
        foot[j] = [Role::LeftAnkle, Role::RightAnkle]
            .iter()
            .any(|&r| source_roles.get(r) == Some(j))
            || joint.parent.is_some_and(|p| foot[p]);
    }
    let foot_joints: Vec<usize> = (0..source.len()).filter(|&j| foot[j]).collect();
    let rest_sole = foot_joints
        .iter()
        .map(|&j| placed_rest[j].y)
        .fold(f32::INFINITY, f32::min);
    let mut feet = SourceFeet::new(
        foot_joints
            .iter()
            .map(|&j| placed_rest[j].y - rest_sole)
            .collect(),
    );
    let target_pelvis = rig.roles.get(Role::Pelvis).unwrap_or(0);
    let source_pelvis = pair[target_pelvis].unwrap_or(0);
    // (target, source) ankles, left and right, and the source's over the frames where the
    // feet are to be locked.
    let ankle_pairs = [Role::LeftAnkle, Role::RightAnkle]
        .map(|r| rig.roles.get(r).and_then(|t| Some((t, pair[t]?))));
    let mut source_ankles: [Vec<Vec3>; 2] = [Vec::new(), Vec::new()];

    // The plausibility checks' bones (each limb bone with both ends corresponding) and trunks.
    // Each bone's joints: target from, target to, source from, source to.
    let mut bone_ends: Vec<[usize; 4]> = Vec::new();
    let mut bones: Vec<plausibility::Bone> = Vec::new();
    for t in 0..target.len() {
        let Some(s) = pair[t] else { continue };
        let ends = target_role[t].map_or(&[][..], bone_end);
        if let Some((c, sc)) = ends
            .iter()
            .find_map(|&e| rig.roles.get(e).and_then(|c| Some((c, pair[c]?))))
        {
            let name = |names: &f3g_rig::Skeleton, a: usize, b: usize| {
                format!("{} → {}", names.joints()[a].name, names.joints()[b].name)
            };
            let bone = plausibility::Bone::new(name(target, t, c), name(source, s, sc));
            bone_ends.push([t, c, s, sc]);
            bones.push(bone);
        }
    }
    let target_top = TRUNK_TOP.iter().find_map(|&r| rig.roles.get(r));
    let source_top = TRUNK_TOP.iter().find_map(|&r| source_of(r));
    let (mut upright_target, mut upright_source) = (Vec::new(), Vec::new());

    let joints = target.joints();
    let mut dropped = 0.0f32;
    let mut frames = Vec::with_capacity(motion.frames());
    let mut world = vec![Quat::IDENTITY; target.len()];
    for f in 0..motion.frames() {
        let posed = motion.world(f);
        let mut p = base.clone();
        for t in 0..target.len() {
            let parent = joints[t].parent.map_or(Quat::IDENTITY, |q| world[q]);
            world[t] = match pair[t] {
                Some(s) => {
                    let delta = turn
                        * posed[s].rotation
                        * source_rest[s].rotation.conjugate()
                        * turn.conjugate();
                    (delta * align[t] * target_rest[t].rotation).normalize()
                }
                None => {
                    let rest_parent = joints[t]
                        .parent
                        .map_or(Quat::IDENTITY, |q| target_rest[q].rotation);
                    (parent * rest_parent.conjugate() * target_rest[t].rotation).normalize()
                }
            };
            let local = joints[t].pre_rotation.conjugate() * parent.conjugate() * world[t];
            let set = rig.set_joint_rotation(&mut p, t, local);
            // The angle of what could not be set, from its sine (acos of a dot product near 1
            // has f32 noise of 1e-3); the children continue from where the joint really is.
            let missed = 2.0 * (set.conjugate() * local).xyz().length().min(1.0).asin();
            dropped = dropped.max(missed);
            world[t] = (parent * joints[t].pre_rotation * set).normalize();
        }
        if let Some(feet) = &mut feet {
            feet.push(foot_joints.iter().map(|&j| place(posed[j].translation)));
        }
        if options.lock_feet {
            for (track, ankle) in source_ankles.iter_mut().zip(ankle_pairs) {
                if let Some((_, s)) = ankle {
                    track.push(place(posed[s].translation));
                }
            }
        }
        let src = place(posed[source_pelvis].translation);
        let want = Vec3::new(
            src.x * scale,
            target_floor + (src.y - source_floor) * scale,
            src.z * scale,
        );
        let target_world = rig.joint_world(&p)?;
        let at = target_world[target_pelvis].translation;
        rig.set_root_translation(&mut p, want - at)?;
        let target_at = |j: usize| target_world[j].translation;
        let source_at = |j: usize| place(posed[j].translation);
        for ([t, c, s, sc], bone) in bone_ends.iter().zip(&mut bones) {
            bone.record(
                source_at(*sc) - source_at(*s),
                target_at(*c) - target_at(*t),
            );
        }
        if let (Some(tt), Some(st)) = (target_top, source_top) {
            upright_target.push(upright(target_at(tt) - at));
            upright_source.push(upright(source_at(st) - src));
        }
        frames.push(p);
    }
    let contact = feet
        .and_then(|f| f.contact(motion.fps, source_leg))
        .filter(|_| !own_skeleton);
    let floor = match &contact {
        Some((source_floor, contact)) => Some(on_the_floor(
            rig,
            base,
            &mut frames,
            contact,
            source_floor / unit,
        )?),
        None => None,
    };
    let feet_locked = match (&contact, ankle_pairs) {
        (Some((_, contact)), [Some((left, _)), Some((right, _))]) if options.lock_feet => {
            let planted = foot_lock::planted(&source_ankles, contact, motion.fps, source_leg);
            Some(lock_feet(rig, &mut frames, [left, right], &planted)?)
        }
        _ => None,
    };
    Ok(Retargeted {
        frames,
        fps: motion.fps,
        method: "rotations",
        correspondence,
        source_roles: source_role_map,
        roles_from,
        unmatched_source,
        unmatched_roles,
        scale,
        dropped_degrees: dropped.to_degrees(),
        plausibility: Some(plausibility_of(
            &upright_target,
            &upright_source,
            &bones,
            floor.as_ref(),
            !own_skeleton && foot_joints.is_empty(),
        )),
        floor,
        feet_locked,
        reference: Some(reference),
    })
}

/// `--lock-feet` ([`crate::foot_lock`]): shifts each frame's root horizontally so that planted
/// feet stay where they were planted. `ankles`: the target's left and right ankle joints.
fn lock_feet(
    rig: &Rig,
    frames: &mut [RigParams],
    ankles: [usize; 2],
    planted: &[Vec<bool>; 2],
) -> Result<FootLockReport, MotionError> {
    let mut at: [Vec<Vec3>; 2] = [Vec::new(), Vec::new()];
    for p in frames.iter() {
        let world = rig.joint_world(p)?;
        for (track, &j) in at.iter_mut().zip(&ankles) {
            track.push(world[j].translation);
        }
    }
    let (shift, report) = foot_lock::shifts(&at, planted);
    for (p, s) in frames.iter_mut().zip(shift) {
        let root = rig.root_translation(p);
        rig.set_root_translation(p, root + s)?;
    }
    Ok(report)
}

/// The plausibility checks ([`crate::plausibility`]), with one more finding: `no_ankles` where
/// the body could not be placed on a floor.
fn plausibility_of(
    upright_target: &[bool],
    upright_source: &[bool],
    bones: &[plausibility::Bone],
    floor: Option<&FloorReport>,
    no_ankles: bool,
) -> Plausibility {
    let mut report = plausibility::check(upright_target, upright_source, bones, floor);
    if no_ankles {
        report
            .warnings
            .push("the motion has no ankle joints: the body is not placed on the floor".into());
    }
    report
}

/// Rule 6 (crate::floor): shifts each frame's root vertically so that the target's lowest
/// point is on its floor where the source's feet are down (`contact`), and measures what is
/// left. `source_floor` is reported as given (the motion's units).
fn on_the_floor(
    rig: &Rig,
    base: &RigParams,
    frames: &mut [RigParams],
    contact: &[bool],
    source_floor: f32,
) -> Result<FloorReport, MotionError> {
    let sole = Sole::new(rig, base)?;
    let lowest = frames
        .iter()
        .map(|p| sole.lowest(rig, p))
        .collect::<Result<Vec<f32>, _>>()?;
    let shift = shifts(&lowest, contact, sole.floor);
    let mut report = FloorReport {
        source_floor,
        contact_frames: contact.iter().filter(|c| **c).count(),
        frames: frames.len(),
        ..FloorReport::default()
    };
    for (((p, s), &down), low) in frames.iter_mut().zip(&shift).zip(contact).zip(&lowest) {
        let root = rig.root_translation(p);
        rig.set_root_translation(p, root + Vec3::Y * *s)?;
        // The root's translation moves every point alike.
        let above = low + s - sole.floor;
        if s.abs() > report.largest_shift_m.abs() {
            report.largest_shift_m = *s;
        }
        report.largest_penetration_m = report.largest_penetration_m.max(-above);
        if down {
            report.largest_float_m = report.largest_float_m.max(above);
        }
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_closest_names_to_a_role_are_offered() {
        let names = [
            "mixamorig:RightStrut",
            "Bone_007",
            "mixamorig:LeftStrut",
            "LeftEar",
        ];
        let left = closest_names(Role::LeftHip, &names);
        assert!(left.iter().any(|n| n == "mixamorig:LeftStrut"), "{left:?}");
        assert!(!left.iter().any(|n| n.contains("Right")), "{left:?}");
        assert!(closest_names(Role::Pelvis, &names).is_empty());
        assert_eq!(
            closest_names(Role::Head, &["HeadTop", "Bone_007"]),
            ["HeadTop"]
        );
    }
}
