//! Joint roles from a skeleton's shape, for skeletons whose names say nothing (`Joint12`,
//! `Bone.003`, names in another language): what [`Roles::infer`] cannot read.
//!
//! A humanoid's tree has two branch points that every convention shares: the pelvis, where two
//! legs and the spine leave, and the chest, where two arms and the neck leave. From the root,
//! the first joint with three or more children of at least three joints' depth is the pelvis
//! (passing down the largest such child until then): its child with the largest subtree is the
//! spine, the next two the legs. Up the spine (the
//! child with the largest subtree each time), the first joint with at least two such children
//! besides the one that goes furthest up is the chest: those are the arms. Along a leg (the
//! deepest child each time) hip, knee and ankle are the three joints around the two longest
//! consecutive bones (a zero-length or short pelvis-side bone before the thigh is passed
//! over); along an arm, up to the hand (the first joint where fingers branch), shoulder, elbow
//! and wrist the same way, the joint before the shoulder being the clavicle. Leaf helpers
//! (twist bones, end sites) never lengthen a chain past a deeper child.
//!
//! Sides need a pose: up is the pelvis toward the spine's joints, forward the direction the
//! feet point (ankle to toe, across both legs), and the body's left is up × forward (a
//! right-handed frame: +Y up and +Z forward put the left on +X). Legs that end at the ankles
//! point nowhere; then the motion tells ([`Roles::from_motion`]): knees bend forward, so over
//! its frames the knees' offsets from the hip–ankle lines give forward, each frame in its own
//! orientation (a body that turns around keeps its sides); where the knees stay straight, the
//! direction the pelvis travels does (a walk goes forward). A toeless skeleton whose motion
//! shows neither is refused with that reason. Positions may come in any axes and units (a
//! motion's first frame, whatever its up axis), so a rest laid along one axis is no obstacle.

use glam::Vec3;

use crate::roles::{Role, Roles};
use crate::skeleton::Skeleton;

/// Fewest joints below and including a limb's first joint (hip, knee, ankle).
const LIMB_DEPTH: usize = 3;

impl Roles {
    /// Roles from the skeleton's shape (module docs). `positions`: each joint's world position
    /// in one pose of the body, any axes and units. An error says what was not found.
    pub fn from_shape(skeleton: &Skeleton, positions: &[Vec3]) -> Result<Self, String> {
        Self::from_motion(skeleton, positions, &[])
    }

    /// [`Self::from_shape`] with a motion's poses (each joint's position, in `positions`'
    /// axes and units), which tell the sides apart where the legs have no toes (module docs).
    pub fn from_motion(
        skeleton: &Skeleton,
        positions: &[Vec3],
        frames: &[Vec<Vec3>],
    ) -> Result<Self, String> {
        if let Some(f) = frames.iter().position(|p| p.len() != positions.len()) {
            return Err(format!(
                "frame {f} has {} positions for {} joints",
                frames[f].len(),
                positions.len()
            ));
        }
        Shape::new(skeleton, positions)?.roles(frames)
    }
}

/// The mean position of `joints` in the pose `at`.
fn mean(at: &[Vec3], joints: &[usize]) -> Vec3 {
    joints.iter().map(|&j| at[j]).sum::<Vec3>() / joints.len() as f32
}

/// A body's up in the pose `at`: from the pelvis toward the mean of the spine's subtree
/// (`spine`, every joint above the pelvis); zero where they coincide.
fn body_up(at: &[Vec3], spine: &[usize], pelvis: usize) -> Vec3 {
    (mean(at, spine) - at[pelvis]).normalize_or_zero()
}

/// Knees bent by less than this share of the leg's length on average say nothing of forward.
const LEAST_BEND: f32 = 0.02;

/// A side must win this share of the evidence (each frame weighted by how clearly it shows).
const DECISIVE: f32 = 0.5;

/// A leg (hip, knee, ankle) or an arm (shoulder, elbow, wrist) along its chain.
#[derive(Clone, Copy)]
struct Limb {
    joints: [usize; 3],
    /// The chain's joint before the first: an arm's clavicle.
    before: Option<usize>,
    /// The chain's joint after the last: a leg's toe.
    after: Option<usize>,
}

/// The tree and one pose of a skeleton.
struct Shape<'a> {
    positions: &'a [Vec3],
    children: Vec<Vec<usize>>,
    /// Joints in the subtree of each joint, itself included.
    size: Vec<usize>,
    /// Joints on the longest path down from each joint, itself included.
    depth: Vec<usize>,
}

impl<'a> Shape<'a> {
    fn new(skeleton: &Skeleton, positions: &'a [Vec3]) -> Result<Self, String> {
        let joints = skeleton.joints();
        if positions.len() != joints.len() {
            return Err(format!(
                "{} positions for {} joints",
                positions.len(),
                joints.len()
            ));
        }
        let n = joints.len();
        let mut children = vec![Vec::new(); n];
        for (j, joint) in joints.iter().enumerate() {
            if let Some(p) = joint.parent {
                children[p].push(j);
            }
        }
        let (mut size, mut depth) = (vec![1; n], vec![1; n]);
        // Parents precede children, so a reverse sweep sees every subtree before its root.
        for j in (0..n).rev() {
            if let Some(p) = joints[j].parent {
                size[p] += size[j];
                depth[p] = depth[p].max(depth[j] + 1);
            }
        }
        Ok(Self {
            positions,
            children,
            size,
            depth,
        })
    }

    /// Children of `j` deep enough to be a limb, largest subtree first.
    fn limbs(&self, j: usize) -> Vec<usize> {
        let mut v: Vec<usize> = self.children[j]
            .iter()
            .copied()
            .filter(|&c| self.depth[c] >= LIMB_DEPTH)
            .collect();
        v.sort_by_key(|&c| (std::cmp::Reverse(self.size[c]), c));
        v
    }

    /// Every joint of `j`'s subtree.
    fn subtree(&self, j: usize) -> Vec<usize> {
        let mut out = vec![j];
        let mut i = 0;
        while i < out.len() {
            out.extend(&self.children[out[i]]);
            i += 1;
        }
        out
    }

    /// From `j`, the deepest child each time, until a joint with none or, with `to_hand`,
    /// with several of two joints' depth or more (the hand, where fingers branch; a twist
    /// bone beside the forearm is a leaf).
    fn chain(&self, mut j: usize, to_hand: bool) -> Vec<usize> {
        let branches = |j: usize| self.children[j].iter().filter(|&&c| self.depth[c] >= 2);
        let mut out = vec![j];
        while !(to_hand && branches(j).count() > 1)
            && let Some(&next) = self.children[j]
                .iter()
                .max_by_key(|&&c| (self.depth[c], std::cmp::Reverse(c)))
        {
            out.push(next);
            j = next;
        }
        out
    }

    /// The limb from `first` ([`Self::chain`]): the three joints around its two longest
    /// consecutive bones, `None` if its bones have no length.
    fn limb(&self, first: usize, to_hand: bool) -> Option<Limb> {
        let chain = self.chain(first, to_hand);
        let i = self.long_pair(&chain)?;
        Some(Limb {
            joints: [chain[i], chain[i + 1], chain[i + 2]],
            before: i.checked_sub(1).map(|k| chain[k]),
            after: chain.get(i + 3).copied(),
        })
    }

    /// The index `i` in `chain` of the first of three joints around its two longest
    /// consecutive bones (hip–knee–ankle, shoulder–elbow–wrist).
    fn long_pair(&self, chain: &[usize]) -> Option<usize> {
        let bone = |i: usize| self.positions[chain[i]].distance(self.positions[chain[i + 1]]);
        (0..chain.len().checked_sub(2)?)
            .map(|i| (i, bone(i) + bone(i + 1)))
            .fold(None, |best: Option<(usize, f32)>, (i, l)| match best {
                Some((_, b)) if b >= l => best,
                _ => Some((i, l)),
            })
            .filter(|(_, l)| *l > 0.0)
            .map(|(i, _)| i)
    }

    /// Whether `legs[0]` is the left leg, from the motion's `frames` (module docs): where the
    /// knees bend, else where the pelvis travels; `None` where neither tells.
    fn first_leg_is_left(
        &self,
        frames: &[Vec<Vec3>],
        legs: [Limb; 2],
        spine: usize,
        pelvis: usize,
    ) -> Option<bool> {
        let spine = self.subtree(spine);
        let leg_length = |at: &[Vec3], leg: Limb| {
            let [h, k, a] = leg.joints.map(|j| at[j]);
            h.distance(k) + k.distance(a)
        };
        // Per frame: its up, the hips' axis across it (legs[0] − legs[1]), and for a forward
        // `f` the evidence `axis · (up × f)`: positive when legs[0] lies on the left.
        let (mut bend, mut bend_total, mut bent) = (0.0f32, 0.0f32, 0.0f32);
        let (mut travel, mut travel_total, mut travelled) = (0.0f32, 0.0f32, Vec3::ZERO);
        let mut previous: Option<Vec3> = None;
        for at in frames {
            let up = body_up(at, &spine, pelvis);
            let flat = |v: Vec3| v - up * v.dot(up);
            let axis = flat(at[legs[0].joints[0]] - at[legs[1].joints[0]]);
            let length = 0.5 * (leg_length(at, legs[0]) + leg_length(at, legs[1]));
            if up == Vec3::ZERO || length <= 0.0 {
                continue;
            }
            let knees: Vec3 = legs
                .iter()
                .map(|leg| {
                    let [h, k, a] = leg.joints.map(|j| at[j]);
                    let line = (a - h).normalize_or_zero();
                    k - h - line * (k - h).dot(line)
                })
                .sum();
            let knees = flat(knees) / length;
            bend += axis.dot(up.cross(knees));
            bend_total += axis.length() * knees.length();
            bent += 0.5 * knees.length();
            let here = at[pelvis];
            if let Some(before) = previous {
                let step = flat(here - before) / length;
                travel += axis.dot(up.cross(step));
                travel_total += axis.length() * step.length();
                travelled += step;
            }
            previous = Some(here);
        }
        let frames = frames.len().max(1) as f32;
        if bent / frames >= LEAST_BEND && bend.abs() > DECISIVE * bend_total {
            return Some(bend > 0.0);
        }
        // A walk, not a sway: the pelvis ends a leg's length or more from where it began.
        (travelled.length() >= 1.0 && travel.abs() > DECISIVE * travel_total)
            .then_some(travel > 0.0)
    }

    fn roles(&self, frames: &[Vec<Vec3>]) -> Result<Roles, String> {
        // The pelvis: from the root down the one limb-deep child until three leave together.
        // Parents precede children: joint 0 is a root, and the only one if it holds them all.
        if self.children.is_empty() || self.subtree(0).len() != self.children.len() {
            return Err("the skeleton is empty or has several roots".into());
        }
        let mut pelvis = 0;
        let (spine, legs) = loop {
            match self.limbs(pelvis)[..] {
                [spine, a, b, ..] => break (spine, [a, b]),
                // Down the largest (past Unreal's `root` with its IK bones beside the pelvis).
                [largest, ..] => pelvis = largest,
                [] => {
                    return Err(
                        "no joint where two legs and a spine leave together (a pelvis)".into(),
                    );
                }
            }
        };
        let up = body_up(self.positions, &self.subtree(spine), pelvis);
        // The chest: up the spine until two limbs leave besides the one going furthest up.
        let mut chest = spine;
        let arms = loop {
            let mut limbs = self.limbs(chest);
            let rise =
                |c: usize| (mean(self.positions, &self.subtree(c)) - self.positions[chest]).dot(up);
            let neck = self.children[chest]
                .iter()
                .copied()
                .max_by(|&a, &b| rise(a).total_cmp(&rise(b)));
            limbs.retain(|&c| Some(c) != neck);
            if let [a, b, ..] = limbs[..] {
                break [a, b];
            }
            match self.children[chest]
                .iter()
                .copied()
                .max_by_key(|&c| (self.size[c], std::cmp::Reverse(c)))
            {
                Some(next) => chest = next,
                None => return Err("no joint where two arms leave the spine (a chest)".into()),
            }
        };
        let limb = |first: usize, to_hand: bool| {
            self.limb(first, to_hand).ok_or(if to_hand {
                "an arm whose bones have no length"
            } else {
                "a leg whose bones have no length"
            })
        };
        let (mut left_leg, mut right_leg) = (limb(legs[0], false)?, limb(legs[1], false)?);
        let (mut left_arm, mut right_arm) = (limb(arms[0], true)?, limb(arms[1], true)?);
        // Forward: where the feet point (ankle to toe), across the up axis.
        let toes: Vec<Vec3> = [left_leg, right_leg]
            .iter()
            .filter_map(|leg| {
                let d = self.positions[leg.after?] - self.positions[leg.joints[2]];
                Some(d - up * d.dot(up))
            })
            .collect();
        let forward = toes.iter().sum::<Vec3>().normalize_or_zero();
        let left = if toes.len() == 2 && forward != Vec3::ZERO && up != Vec3::ZERO {
            up.cross(forward)
        } else {
            let hips = self.positions[left_leg.joints[0]] - self.positions[right_leg.joints[0]];
            match self.first_leg_is_left(frames, [left_leg, right_leg], spine, pelvis) {
                Some(true) => hips,
                Some(false) => -hips,
                None => {
                    return Err(
                        "the legs end at the ankles (no toe joints), and over the motion the \
                         knees never bend and the body does not walk, so which side is left \
                         cannot be told"
                            .into(),
                    );
                }
            }
        };
        let side = |a: usize, b: usize| (self.positions[a] - self.positions[b]).dot(left);
        if side(left_leg.joints[0], right_leg.joints[0]) < 0.0 {
            std::mem::swap(&mut left_leg, &mut right_leg);
        }
        if side(left_arm.joints[0], right_arm.joints[0]) < 0.0 {
            std::mem::swap(&mut left_arm, &mut right_arm);
        }
        use Role::*;
        // The chest (and spine, neck, head) follow from these in `Roles::completed`.
        let mut pairs = vec![(Pelvis, pelvis)];
        for (roles, limb) in [
            ([LeftHip, LeftKnee, LeftAnkle], left_leg),
            ([RightHip, RightKnee, RightAnkle], right_leg),
            ([LeftShoulder, LeftElbow, LeftWrist], left_arm),
            ([RightShoulder, RightElbow, RightWrist], right_arm),
        ] {
            pairs.extend(roles.into_iter().zip(limb.joints));
        }
        // The joint before an arm's shoulder is its clavicle (unless that is the chest).
        for (role, arm) in [(LeftClavicle, left_arm), (RightClavicle, right_arm)] {
            if let Some(c) = arm.before.filter(|&c| c != chest) {
                pairs.push((role, c));
            }
        }
        Ok(Roles::from_pairs(pairs))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skeleton::Joint;
    use glam::Quat;

    /// A humanoid standing (Y up, facing +Z, its left at +X), in metres: name, parent, world
    /// position. The left side; [`skeleton`] mirrors it.
    const LEFT: [(&str, &str, [f32; 3]); 14] = [
        ("pelvis_l", "hips", [0.05, 0.95, 0.0]),
        ("thigh_l", "pelvis_l", [0.09, 0.92, 0.0]),
        ("thigh_twist_l", "thigh_l", [0.09, 0.7, 0.0]),
        ("shin_l", "thigh_l", [0.09, 0.5, 0.01]),
        ("foot_l", "shin_l", [0.09, 0.08, -0.02]),
        ("toe_l", "foot_l", [0.09, 0.01, 0.12]),
        ("collar_l", "chest", [0.04, 1.42, 0.0]),
        ("arm_l", "collar_l", [0.18, 1.42, -0.02]),
        ("arm_twist_l", "arm_l", [0.3, 1.42, -0.02]),
        ("elbow_l", "arm_l", [0.45, 1.42, -0.03]),
        ("hand_l", "elbow_l", [0.7, 1.42, -0.02]),
        ("thumb_l", "hand_l", [0.74, 1.41, 0.02]),
        ("thumb_tip_l", "thumb_l", [0.77, 1.40, 0.05]),
        ("index_l", "hand_l", [0.8, 1.42, 0.0]),
    ];

    /// Joints named `j0…` in a shuffled order (parents first), their positions turned by
    /// `turn` and scaled by `scale`; also the joint of each name.
    fn skeleton(turn: Quat, scale: f32, toes: bool) -> (Skeleton, Vec<Vec3>, Vec<String>) {
        let mut bones: Vec<(String, String, Vec3)> = [
            ("root", "", [0.0, 0.0, 0.0]),
            ("ik_hand_root", "root", [0.0, 0.0, 0.0]),
            ("ik_hand_gun", "ik_hand_root", [0.3, 1.0, 0.2]),
            ("ik_hand_l", "ik_hand_gun", [0.6, 1.0, 0.2]),
            ("hips", "root", [0.0, 0.95, 0.0]),
            ("spine", "hips", [0.0, 1.1, 0.0]),
            ("chest", "spine", [0.0, 1.3, 0.0]),
            ("neck", "chest", [0.0, 1.5, 0.0]),
            ("head", "neck", [0.0, 1.6, 0.02]),
        ]
        .iter()
        .map(|(n, p, x)| (n.to_string(), p.to_string(), Vec3::from_array(*x)))
        .collect();
        for (n, p, x) in LEFT {
            if !toes && n.starts_with("toe") {
                continue;
            }
            let x = Vec3::from_array(x);
            bones.push((n.into(), p.into(), x));
            let mirror = |s: &str| s.replace("_l", "_r");
            bones.push((mirror(n), mirror(p), Vec3::new(-x.x, x.y, x.z)));
        }
        // The right leg first (the arms left first), so that the order says nothing of the side.
        bones.swap(9, 10);
        let names: Vec<String> = bones.iter().map(|b| b.0.clone()).collect();
        let joints = bones
            .iter()
            .enumerate()
            .map(|(i, (_, p, x))| {
                let parent = names.iter().position(|n| n == p);
                assert!(parent.is_none_or(|p| p < i), "{i}");
                let at = parent.map_or(Vec3::ZERO, |p| bones[p].2);
                Joint {
                    name: format!("j{i}"),
                    parent,
                    offset: *x - at,
                    pre_rotation: Quat::IDENTITY,
                }
            })
            .collect();
        let positions = bones.iter().map(|b| turn * b.2 * scale).collect();
        (Skeleton::new(joints).unwrap(), positions, names)
    }

    fn expected() -> Vec<(Role, &'static str)> {
        use Role::*;
        vec![
            (Pelvis, "hips"),
            (LeftHip, "thigh_l"),
            (LeftKnee, "shin_l"),
            (LeftAnkle, "foot_l"),
            (RightHip, "thigh_r"),
            (RightKnee, "shin_r"),
            (RightAnkle, "foot_r"),
            (LeftClavicle, "collar_l"),
            (LeftShoulder, "arm_l"),
            (LeftElbow, "elbow_l"),
            (LeftWrist, "hand_l"),
            (RightClavicle, "collar_r"),
            (RightShoulder, "arm_r"),
            (RightElbow, "elbow_r"),
            (RightWrist, "hand_r"),
        ]
    }

    #[test]
    fn an_anonymous_humanoid_gets_its_roles_in_any_axes_and_units() {
        for (turn, scale) in [
            (Quat::IDENTITY, 1.0),
            // Z up and facing −Y (Blender), in centimetres.
            (Quat::from_rotation_x(std::f32::consts::FRAC_PI_2), 100.0),
            // Lying along +X, turned about it, in inches.
            (
                Quat::from_rotation_z(-1.3) * Quat::from_rotation_x(2.0),
                39.37,
            ),
        ] {
            let (s, positions, names) = skeleton(turn, scale, true);
            let roles = Roles::from_shape(&s, &positions).unwrap();
            for (role, name) in expected() {
                let got = roles.get(role).map(|j| names[j].as_str());
                assert_eq!(got, Some(name), "{role:?} with {turn:?} × {scale}");
            }
            // The rest follows from the tree: chest, spine, neck and head.
            let completed = roles.completed(&s);
            for (role, name) in [
                (Role::Chest, "chest"),
                (Role::Spine, "spine"),
                (Role::Neck, "neck"),
                (Role::Head, "head"),
            ] {
                assert_eq!(completed.get(role).map(|j| names[j].as_str()), Some(name));
            }
        }
    }

    #[test]
    fn a_mirrored_pose_swaps_the_sides() {
        let (s, positions, names) = skeleton(Quat::IDENTITY, 1.0, true);
        let mirrored: Vec<Vec3> = positions
            .iter()
            .map(|p| Vec3::new(-p.x, p.y, p.z))
            .collect();
        let roles = Roles::from_shape(&s, &mirrored).unwrap();
        assert_eq!(
            roles.get(Role::LeftHip).map(|j| names[j].as_str()),
            Some("thigh_r")
        );
        assert_eq!(
            roles.get(Role::RightWrist).map(|j| names[j].as_str()),
            Some("hand_l")
        );
    }

    /// `positions` with `move` applied to the named joints, then turned about +Y by `yaw`.
    fn posed(positions: &[Vec3], names: &[String], moved: &[(&str, Vec3)], yaw: f32) -> Vec<Vec3> {
        let turn = Quat::from_rotation_y(yaw);
        let mut at = positions.to_vec();
        for (name, by) in moved {
            let j = names.iter().position(|n| n == name).unwrap();
            at[j] += *by;
        }
        at.iter().map(|p| turn * *p).collect()
    }

    fn assert_sides(roles: &Roles, names: &[String], why: &str) {
        for (role, name) in expected() {
            let got = roles.get(role).map(|j| names[j].as_str());
            assert_eq!(got, Some(name), "{role:?}: {why}");
        }
    }

    #[test]
    fn without_toes_the_motion_tells_the_sides() {
        let (s, positions, names) = skeleton(Quat::IDENTITY, 1.0, false);
        // Knees bent forward (+Z) by turns, the body turning round as it goes: each frame's
        // own orientation counts, not the first frame's.
        let walk: Vec<Vec<Vec3>> = (0..12)
            .map(|f| {
                let swing = 0.04 + 0.06 * (f as f32 * 0.7).sin().abs();
                let knees = [
                    ("shin_l", Vec3::Z * swing),
                    ("shin_r", Vec3::Z * (0.1 - swing)),
                ];
                posed(&positions, &names, &knees, f as f32 * 0.5)
            })
            .collect();
        let roles = Roles::from_motion(&s, &positions, &walk).unwrap();
        assert_sides(&roles, &names, "from the knees");
        // Mirrored, the knees tell the other way.
        let mirror = |p: &Vec<Vec3>| p.iter().map(|v| Vec3::new(-v.x, v.y, v.z)).collect();
        let mirrored: Vec<Vec<Vec3>> = walk.iter().map(mirror).collect();
        let roles = Roles::from_motion(&s, &mirror(&positions), &mirrored).unwrap();
        assert_eq!(
            roles.get(Role::LeftHip).map(|j| names[j].as_str()),
            Some("thigh_r")
        );
        // Straight knees, the body gliding forward two leg lengths.
        let glide: Vec<Vec<Vec3>> = (0..10)
            .map(|f| {
                let ahead = Vec3::Z * 0.2 * f as f32;
                posed(&positions, &names, &[], 0.0)
                    .into_iter()
                    .map(|p| p + ahead)
                    .collect()
            })
            .collect();
        let roles = Roles::from_motion(&s, &positions, &glide).unwrap();
        assert_sides(&roles, &names, "from the travel");
        // Standing still, straight-legged (the fixture's knees, 2 cm forward of the hip–ankle
        // line, moved onto it): nothing tells.
        let straight = [("shin_l", Vec3::Z * -0.02), ("shin_r", Vec3::Z * -0.02)];
        let still = vec![posed(&positions, &names, &straight, 0.0); 10];
        let e = Roles::from_motion(&s, &positions, &still).unwrap_err();
        assert!(
            e.contains("no toe joints") && e.contains("knees never bend"),
            "{e}"
        );
        let e = Roles::from_motion(&s, &positions, &[vec![Vec3::ZERO; 3]]).unwrap_err();
        assert!(e.contains("frame 0 has 3 positions"), "{e}");
    }

    #[test]
    fn what_the_shape_cannot_tell_is_an_error_naming_it() {
        let (s, positions, _) = skeleton(Quat::IDENTITY, 1.0, false);
        let e = Roles::from_shape(&s, &positions).unwrap_err();
        assert!(e.contains("no toe joints"), "{e}");
        // Joints named `b<i>` with these parents.
        let bare = |parents: &[Option<usize>]| {
            let joints = parents.iter().enumerate().map(|(i, &parent)| Joint {
                name: format!("b{i}"),
                parent,
                offset: Vec3::Y,
                pre_rotation: Quat::IDENTITY,
            });
            Skeleton::new(joints.collect()).unwrap()
        };
        let chain = bare(&[None, Some(0), Some(1), Some(2), Some(3), Some(4)]);
        let e = Roles::from_shape(&chain, &[Vec3::ZERO; 6]).unwrap_err();
        assert!(e.contains("pelvis"), "{e}");
        let e = Roles::from_shape(&chain, &[Vec3::ZERO; 2]).unwrap_err();
        assert!(e.contains("2 positions for 6 joints"), "{e}");
        let two_roots = bare(&[None, None]);
        let e = Roles::from_shape(&two_roots, &[Vec3::ZERO; 2]).unwrap_err();
        assert!(e.contains("several roots"), "{e}");
    }
}
