//! Rule 6 of retargeting: the body on the floor where the source's feet are on its floor.
//!
//! Scaling the source's pelvis height (rule 5) puts the target's feet on the floor only when
//! the two skeletons have the same proportions and the same joint-to-sole distances; they
//! do not (a Mixamo walk floated 13 cm, a kneel sank 7 cm). So, per frame:
//! - **The source's contact.** Each foot joint (the ankles and every joint below them)
//!   measured against its own height in a standing rest pose (`rest_height`, the joint's
//!   height above the rest's lowest foot joint): a foot is down when a joint is at most that
//!   high. The source's floor is the 5th percentile of the frames' lowest such clearances (a
//!   few frames of a foot dipping through a capture's floor do not move it); a frame is in
//!   contact when its lowest clearance is within [`CONTACT_TOLERANCE`] of the source's leg
//!   length above that floor, or when its lowest foot joint is still and within
//!   [`STILL_HEIGHT`] of it (a motion whose feet sink through its own floor in some frames
//!   moves the floor down; its standing frames still stand).
//! - **The target's lowest point**: its posed mesh's, not a joint's (a heel, a knee when
//!   kneeling, the seat when sitting). Only the vertices that can be lowest are posed
//!   ([`Sole`]).
//! - **The correction**, a vertical shift of the root: in contact frames it puts the lowest
//!   point on the target's floor (its lowest point at rest); between contacts it is
//!   interpolated linearly in time (a jump keeps its arc); before the first and after the
//!   last contact it holds. It never lets the mesh go below the floor.
//!
//! Heights are along +Y, in metres of the target (the source's placed as rule 3 places them).

use glam::Vec3;
use serde::Serialize;

use f3g_rig::{Rig, RigError, RigParams, SkinWeights};

/// A frame is in contact when its lowest foot clearance is within this fraction of the
/// source's leg length (hip to knee to ankle) above the floor: 4.5 cm for a 0.9 m leg, more
/// than a planted foot's capture noise and less than a walking swing foot's lift at mid-swing.
pub const CONTACT_TOLERANCE: f32 = 0.05;
/// A foot slower than this many leg lengths a second is still: 0.1 m/s for a 0.9 m leg, less
/// than a swinging foot's slowest (a walk's swing is 2–4 m/s) and more than a planted foot's
/// capture noise.
pub const STILL_LEGS_PER_SECOND: f32 = 0.11;
/// A still foot within this fraction of the leg length above the floor is planted (20 cm for
/// a 0.9 m leg): a motion whose feet go through its own floor elsewhere (a hand-made kneel)
/// moved its floor down, and its standing frames still stand; a foot held up is higher.
pub const STILL_HEIGHT: f32 = 0.22;

/// What putting the body on the floor did (in `motion convert`'s report).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FloorReport {
    /// The source's floor: the height its feet stand at, in the motion's own units along its
    /// up axis (as a joint standing on it would read in the file).
    pub source_floor: f32,
    /// Frames where the source's feet touch its floor.
    pub contact_frames: usize,
    pub frames: usize,
    /// The largest vertical shift of the root this rule applied (metres; + is up).
    pub largest_shift_m: f32,
    /// After the shift: the most the target's lowest point is above its floor in a contact
    /// frame (metres).
    pub largest_float_m: f32,
    /// After the shift: the most the target's lowest point is below its floor (metres).
    pub largest_penetration_m: f32,
}

/// The target's floor contact points: the rest-mesh vertices that can be the mesh's lowest
/// in some pose, posed by linear blend skinning alone (no pose correctives: they move a
/// surface by millimetres).
pub struct Sole {
    points: Vec<Vec3>,
    skin: SkinWeights,
    /// The lowest point at rest: the target's floor.
    pub floor: f32,
}

impl Sole {
    /// Per joint, among the vertices it moves most, the extreme ones along 98 directions (a
    /// 5×5×5 grid's surface): the lowest point of a part turned rigidly is its extreme along
    /// the turned −Y, found within a few millimetres for body-sized parts. A few thousand
    /// points of any body model, so 7 000 frames take a fraction of a second.
    pub fn new(rig: &Rig, base: &RigParams) -> Result<Self, RigError> {
        let rest_poses = rig.joint_poses(&base.pose)?;
        let rest = rig.rest_vertices(base, &rest_poses);
        let mut directions = Vec::new();
        for x in -2i32..=2 {
            for y in -2i32..=2 {
                for z in -2i32..=2 {
                    if x.abs() == 2 || y.abs() == 2 || z.abs() == 2 {
                        directions.push(Vec3::new(x as f32, y as f32, z as f32).normalize());
                    }
                }
            }
        }
        let mut by_joint: Vec<Vec<usize>> = vec![Vec::new(); rig.skeleton.len()];
        for (v, (joints, weights)) in rig.skin.joints.iter().zip(&rig.skin.weights).enumerate() {
            let dominant = (0..joints.len())
                .max_by(|&a, &b| weights[a].total_cmp(&weights[b]))
                .map_or(0, |k| joints[k] as usize);
            if let Some(group) = by_joint.get_mut(dominant) {
                group.push(v);
            }
        }
        let mut chosen = vec![false; rest.len()];
        for group in by_joint.iter().filter(|g| !g.is_empty()) {
            for d in &directions {
                let best = group
                    .iter()
                    .copied()
                    .max_by(|&a, &b| rest[a].dot(*d).total_cmp(&rest[b].dot(*d)));
                if let Some(v) = best {
                    chosen[v] = true;
                }
            }
        }
        let picked: Vec<usize> = (0..rest.len()).filter(|&v| chosen[v]).collect();
        let mut sole = Self {
            points: picked.iter().map(|&v| rest[v]).collect(),
            skin: SkinWeights {
                joints: picked.iter().map(|&v| rig.skin.joints[v]).collect(),
                weights: picked.iter().map(|&v| rig.skin.weights[v]).collect(),
            },
            floor: 0.0,
        };
        sole.floor = sole.lowest(rig, base)?;
        Ok(sole)
    }

    /// The posed mesh's lowest height (its rest mesh's at `p`'s shape).
    pub fn lowest(&self, rig: &Rig, p: &RigParams) -> Result<f32, RigError> {
        let poses = rig.joint_poses(&p.pose)?;
        let (skinning, _) = rig.skinning_transforms(p, &poses);
        // One thread: a few thousand points a frame, where rayon's hand-offs cost more than
        // the work (retargeting calls this per frame).
        Ok(self
            .points
            .iter()
            .zip(self.skin.joints.iter().zip(&self.skin.weights))
            .map(|(p, (j, w))| f3g_rig::skin::blend(&skinning, j, w).transform_point3(*p).y)
            .fold(f32::INFINITY, f32::min))
    }
}

/// The source's feet over the motion: its foot joints' positions per frame (placed, metres).
pub struct SourceFeet {
    /// Each foot joint's height above the lowest of them in the standing reference pose.
    standing: Vec<f32>,
    /// `[frames · joints]`.
    positions: Vec<Vec3>,
}

impl SourceFeet {
    /// Feet with these standing heights; `None` without foot joints.
    pub fn new(standing: Vec<f32>) -> Option<Self> {
        (!standing.is_empty()).then(|| Self {
            standing,
            positions: Vec::new(),
        })
    }

    /// Records a frame's foot joint positions, in the order of the standing heights.
    pub fn push(&mut self, positions: impl Iterator<Item = Vec3>) {
        self.positions.extend(positions);
    }

    /// The source's floor and whether each frame is in contact (module docs): within
    /// [`CONTACT_TOLERANCE`] of the leg length above the floor, or still (the lowest joint
    /// slower than [`STILL_LEGS_PER_SECOND`] leg lengths a second) and within [`STILL_HEIGHT`]
    /// of it. `None` when no frame was recorded.
    pub fn contact(&self, fps: f32, leg_length: f32) -> Option<(f32, Vec<bool>)> {
        let joints = self.standing.len();
        let frames = self.positions.len() / joints;
        if frames == 0 {
            return None;
        }
        let at = |f: usize, j: usize| self.positions[f * joints + j];
        let lowest: Vec<(usize, f32)> = (0..frames)
            .map(|f| {
                (0..joints)
                    .map(|j| (j, at(f, j).y - self.standing[j]))
                    .min_by(|a, b| a.1.total_cmp(&b.1))
                    .unwrap_or((0, 0.0))
            })
            .collect();
        let mut sorted: Vec<f32> = lowest.iter().map(|l| l.1).collect();
        sorted.sort_by(f32::total_cmp);
        let floor = sorted[(sorted.len() - 1) * 5 / 100];
        let contact = (0..frames)
            .map(|f| {
                let (j, clearance) = lowest[f];
                let above = clearance - floor;
                let speed = speed_at(|f| at(f, j), f, frames, fps);
                above <= CONTACT_TOLERANCE * leg_length
                    || (speed <= STILL_LEGS_PER_SECOND * leg_length
                        && above <= STILL_HEIGHT * leg_length)
            })
            .collect();
        Some((floor, contact))
    }
}

/// How fast a point whose position at each frame is `at` moves at frame `f` of `frames`
/// (units per second): the central difference, one-sided at the ends, 0 for one frame.
pub fn speed_at(at: impl Fn(usize) -> Vec3, f: usize, frames: usize, fps: f32) -> f32 {
    let (a, b) = (f.saturating_sub(1), (f + 1).min(frames - 1));
    match b - a {
        0 => 0.0,
        steps => at(a).distance(at(b)) * fps / steps as f32,
    }
}

/// The vertical shift per frame (module docs): `lowest[f]` is the target's lowest point before
/// it, `contact[f]` whether the source's feet are down.
pub fn shifts(lowest: &[f32], contact: &[bool], floor: f32) -> Vec<f32> {
    // (frame, the shift that puts it on the floor) of each contact frame, in time order.
    let planted: Vec<(usize, f32)> = (0..lowest.len())
        .filter(|&f| contact[f])
        .map(|f| (f, floor - lowest[f]))
        .collect();
    (0..lowest.len())
        .map(|f| {
            let next = planted.partition_point(|&(c, _)| c < f);
            let shift = match (next.checked_sub(1).map(|i| planted[i]), planted.get(next)) {
                (_, Some(&(b, sb))) if b == f => sb,
                (Some((a, sa)), Some(&(b, sb))) => sa + (sb - sa) * (f - a) as f32 / (b - a) as f32,
                (Some((_, s)), None) | (None, Some(&(_, s))) => s,
                (None, None) => 0.0,
            };
            shift.max(floor - lowest[f])
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn contact_frames_put_the_lowest_point_on_the_floor_and_jumps_keep_their_arc() {
        // Frames 0-1 and 4-5 planted (the target 10 cm too high), 2-3 in the air.
        let lowest = [0.1, 0.1, 0.4, 0.4, 0.1, 0.1];
        let contact = [true, true, false, false, true, true];
        let s = shifts(&lowest, &contact, 0.0);
        for (f, (l, s)) in lowest.iter().zip(&s).enumerate() {
            let after = l + s;
            if contact[f] {
                assert!(after.abs() < 1e-6, "frame {f}: {after}");
            } else {
                assert!(
                    (after - 0.3).abs() < 1e-6,
                    "frame {f} keeps its height: {after}"
                );
            }
        }
    }

    #[test]
    fn between_contacts_the_shift_is_interpolated_and_never_sinks_the_body() {
        let lowest = [0.0, 0.1, -0.5, 0.2];
        let contact = [true, false, false, true];
        let s = shifts(&lowest, &contact, 0.0);
        assert!(
            (s[0] - 0.0).abs() < 1e-6 && (s[3] + 0.2).abs() < 1e-6,
            "{s:?}"
        );
        assert!((s[1] + 0.2 / 3.0).abs() < 1e-6, "{s:?}");
        assert!(
            (lowest[2] + s[2]).abs() < 1e-6,
            "frame 2 lifted out of the floor: {s:?}"
        );
        assert_eq!(shifts(&[0.3, -0.1], &[false, false], 0.0), [0.0, 0.1]);
    }

    /// Feet of one joint standing at height 0 with `heights` per frame, 1 m legs, 30 fps.
    fn feet(heights: &[f32], step: f32) -> SourceFeet {
        let mut feet = SourceFeet::new(vec![0.0]).unwrap();
        for (f, &h) in heights.iter().enumerate() {
            feet.push(std::iter::once(Vec3::new(step * f as f32, h, 0.0)));
        }
        feet
    }

    #[test]
    fn the_source_floor_ignores_a_few_frames_dipping_through_it() {
        let mut heights = vec![0.0; 100];
        heights[7] = -0.3;
        heights[50..60].fill(0.3);
        let (floor, contact) = feet(&heights, 0.0).contact(30.0, 1.0).unwrap();
        assert_eq!(floor, 0.0);
        assert_eq!(contact.iter().filter(|c| !**c).count(), 10);
        assert!(SourceFeet::new(Vec::new()).is_none());
        assert!(feet(&[], 0.0).contact(30.0, 1.0).is_none());
    }

    #[test]
    fn still_feet_a_little_above_a_sunk_floor_stand_and_moving_ones_do_not() {
        // Half the frames 15 cm through the floor: the floor moves down to them.
        let mut heights = vec![0.0; 20];
        heights[10..].fill(-0.15);
        let (floor, contact) = feet(&heights, 0.0).contact(30.0, 1.0).unwrap();
        assert_eq!(floor, -0.15);
        // All but frame 9, whose foot drops 15 cm to the next (not still, not low).
        let up: Vec<usize> = (0..20).filter(|&f| !contact[f]).collect();
        assert_eq!(up, [9], "{contact:?}");
        // The same heights with the foot sliding at 0.3 m a frame (9 m/s): only the sunk
        // frames are down.
        let (_, contact) = feet(&heights, 0.3).contact(30.0, 1.0).unwrap();
        assert_eq!(contact.iter().filter(|c| **c).count(), 10, "{contact:?}");
    }
}
