//! Joint roles: which joint of a skeleton is the head, the left wrist, the right hip, …
//!
//! The avatar pipeline never looks a joint up by name: it asks the rig for the joint of a
//! [`Role`] ([`crate::Rig::role`]). Every loader fills the rig's [`Roles`] once, when the model
//! loads: from its own table (the built-in human, SMPL-X), from the joint names
//! ([`Roles::infer`]: MHR, rigged glTF), or from a role map the user writes
//! ([`RoleMap`], `MODEL.roles.json` next to a glTF file), which overrides the inference.
//!
//! Name inference splits a name into words (separators, camelCase, letter/digit boundaries),
//! drops rig prefixes (`mixamorig:`, `Bip01`, `DEF-`, `ORG-`, `MCH-`, `J_Bip_`, …) and reads a
//! side marker (`Left`, `L`, `l_`, `L_`, `.L`, `_l`, `lft`, one glued letter as in CMU's
//! `lfemur`; `c_` means centre). What is left is matched against the synonyms of each role
//! (hips/pelvis, upleg/thigh/upperleg/femur, leg/shin/calf/lowerleg/tibia,
//! upperarm/arm/uparm/humerus, forearm/lowerarm/radius, collar/clavicle, hand/wrist, neck and
//! lowerneck/upperneck, …), so that Blender/Rigify, Mixamo, CMU (both its BVH and ASF names),
//! MotionBuilder/HumanIK, LAFAN1, Unreal and Unity humanoid names are read. When several joints
//! match a role, the one nearest the root wins (`upperarm01.L` over `upperarm02.L`). `shoulder`
//! is the clavicle when the same side has an upper-arm joint (Mixamo's `LeftShoulder` →
//! `LeftArm`, Rigify's `shoulder.L` → `upper_arm.L`), the upper arm otherwise (SMPL's
//! `left_shoulder`). A sided `pelvis` (Rigify's and MakeHuman's `pelvis.L`, beside the thigh)
//! is the hip only where the side has no thigh. A rig whose bones come in layers (Rigify's
//! deform `DEF-`, original `ORG-`, unprefixed controls, mechanism `MCH-`) takes its roles from
//! the lowest layer that names any. Joints whose names mark them as helpers (`_end`, `nub`,
//! `twist`, `roll`, `ik`, `tweak`, …) never take a role. [`Roles::completed`] then fills what
//! the names left out from the skeleton's shape.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::RigError;
use crate::skeleton::Skeleton;

/// A joint's part in a humanoid body. `Shoulder` is the joint that turns the upper arm,
/// `Clavicle` the collar bone above it; `Hip` turns the thigh; `Wrist` turns the hand, whose
/// subtree holds the fingers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    Pelvis,
    Spine,
    Chest,
    Neck,
    Head,
    Jaw,
    LeftEye,
    RightEye,
    LeftClavicle,
    RightClavicle,
    LeftShoulder,
    RightShoulder,
    LeftElbow,
    RightElbow,
    LeftWrist,
    RightWrist,
    LeftHip,
    RightHip,
    LeftKnee,
    RightKnee,
    LeftAnkle,
    RightAnkle,
}

impl Role {
    /// Every role, in declaration order.
    pub const ALL: [Role; 22] = [
        Role::Pelvis,
        Role::Spine,
        Role::Chest,
        Role::Neck,
        Role::Head,
        Role::Jaw,
        Role::LeftEye,
        Role::RightEye,
        Role::LeftClavicle,
        Role::RightClavicle,
        Role::LeftShoulder,
        Role::RightShoulder,
        Role::LeftElbow,
        Role::RightElbow,
        Role::LeftWrist,
        Role::RightWrist,
        Role::LeftHip,
        Role::RightHip,
        Role::LeftKnee,
        Role::RightKnee,
        Role::LeftAnkle,
        Role::RightAnkle,
    ];

    /// What the avatar pipeline needs: the head (face region, head crops), the hips and
    /// shoulders (the canonical pose) and the wrists (the hands left out of the networks'
    /// inputs), and the pelvis.
    pub const REQUIRED: [Role; 8] = [
        Role::Pelvis,
        Role::Head,
        Role::LeftHip,
        Role::RightHip,
        Role::LeftShoulder,
        Role::RightShoulder,
        Role::LeftWrist,
        Role::RightWrist,
    ];

    /// The role's name in role maps and messages (`left_wrist`).
    pub fn name(self) -> String {
        serde_json::to_value(self)
            .ok()
            .and_then(|v| v.as_str().map(String::from))
            .unwrap_or_default()
    }

    /// The role of a side of the body for a sided kind, or the kind itself when unsided.
    fn sided(kind: Kind, side: Side) -> Option<Role> {
        use Role::*;
        let pick = |l: Role, r: Role| match side {
            Side::Left => Some(l),
            Side::Right => Some(r),
            Side::Centre => None,
        };
        let centre = |role: Role| (side == Side::Centre).then_some(role);
        match kind {
            Kind::Pelvis => centre(Pelvis),
            Kind::Spine => centre(Spine),
            Kind::Chest => centre(Chest),
            Kind::Neck => centre(Neck),
            Kind::Head => centre(Head),
            Kind::Jaw => centre(Jaw),
            Kind::Eye => pick(LeftEye, RightEye),
            Kind::Clavicle => pick(LeftClavicle, RightClavicle),
            Kind::UpperArm | Kind::Shoulder => pick(LeftShoulder, RightShoulder),
            Kind::Elbow => pick(LeftElbow, RightElbow),
            Kind::Wrist | Kind::Hand => pick(LeftWrist, RightWrist),
            Kind::Hip | Kind::PelvisSide => pick(LeftHip, RightHip),
            Kind::Knee => pick(LeftKnee, RightKnee),
            Kind::Ankle => pick(LeftAnkle, RightAnkle),
        }
    }
}

/// The joint (index into the skeleton) of each role a body model has.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Roles {
    joints: BTreeMap<Role, usize>,
}

impl Roles {
    /// The joint of `role`, if the model has one.
    pub fn get(&self, role: Role) -> Option<usize> {
        self.joints.get(&role).copied()
    }

    /// Every `(role, joint)` pair, in role order.
    pub fn iter(&self) -> impl Iterator<Item = (Role, usize)> + '_ {
        self.joints.iter().map(|(r, j)| (*r, *j))
    }

    pub fn len(&self) -> usize {
        self.joints.len()
    }

    pub fn is_empty(&self) -> bool {
        self.joints.is_empty()
    }

    /// Roles from `(role, joint name)` pairs, for loaders whose joint names are fixed; names the
    /// skeleton lacks are left out.
    pub fn from_names(skeleton: &Skeleton, table: &[(Role, &str)]) -> Self {
        Self {
            joints: table
                .iter()
                .filter_map(|(role, name)| Some((*role, skeleton.index_of(name)?)))
                .collect(),
        }
    }

    /// Roles inferred from the joint names (module docs).
    pub fn infer(skeleton: &Skeleton) -> Self {
        let joints = skeleton.joints();
        let depth: Vec<usize> = (0..joints.len())
            .map(|j| std::iter::successors(joints[j].parent, |&p| joints[p].parent).count())
            .collect();
        let mut read: Vec<Option<(Kind, Side)>> =
            joints.iter().map(|j| read_name(&j.name)).collect();
        // A rig whose bones come in layers (Rigify's `DEF-`, `ORG-`, controls, `MCH-`) takes
        // its roles from one: the lowest that names any.
        let layers: Vec<u8> = joints.iter().map(|j| layer(&j.name)).collect();
        if let Some(lowest) = (0..joints.len())
            .filter(|&j| read[j].is_some())
            .map(|j| layers[j])
            .min()
        {
            for (r, l) in read.iter_mut().zip(&layers) {
                if *l != lowest {
                    *r = None;
                }
            }
        }
        let has = |kind: Kind, side: Side| {
            read.iter()
                .any(|r| matches!(r, Some((k, s)) if *k == kind && *s == side))
        };
        let mut best: BTreeMap<Role, usize> = BTreeMap::new();
        for (j, r) in read.iter().enumerate() {
            let Some((mut kind, side)) = *r else { continue };
            match kind {
                // `shoulder` is the clavicle where the side has an upper arm.
                Kind::Shoulder if has(Kind::UpperArm, side) => kind = Kind::Clavicle,
                // `hand` is the wrist where the side has none; a sided `pelvis` the hip.
                Kind::Hand if has(Kind::Wrist, side) => continue,
                Kind::PelvisSide if has(Kind::Hip, side) => continue,
                _ => {}
            }
            let Some(role) = Role::sided(kind, side) else {
                continue;
            };
            match best.get(&role) {
                Some(&k) if depth[k] <= depth[j] => {}
                _ => {
                    best.insert(role, j);
                }
            }
        }
        Self { joints: best }
    }

    /// These roles completed from the skeleton's shape, for the roles the names left out:
    /// the pelvis is where the two legs meet, the chest where the two arms meet (when it is
    /// not the spine's joint; the joint below it when that is the neck, as in Biped); the spine is the joint after the pelvis on the way to the chest
    /// when no name gave it, or gave the pelvis's own joint (Blender's root `spine`); the
    /// chain that leaves the chest toward neither arm runs neck to head. That chain follows
    /// the child named like the spine, neck or head, else the one with the most joints below
    /// it (the neck, not a breast bone), and ends at the last joint so named (Blender's
    /// `spine.006`, not a face bone below it).
    pub fn completed(self, skeleton: &Skeleton) -> Self {
        let joints = skeleton.joints();
        let mut map = self.joints;
        let ancestors = |j: usize| -> Vec<usize> {
            std::iter::successors(Some(j), |&k| joints[k].parent).collect()
        };
        let meet = |a: usize, b: usize| -> Option<usize> {
            let up = ancestors(b);
            ancestors(a).into_iter().find(|k| up.contains(k))
        };
        let sided =
            |l: Role, r: Role, map: &BTreeMap<Role, usize>| Some((*map.get(&l)?, *map.get(&r)?));
        if !map.contains_key(&Role::Pelvis)
            && let Some((l, r)) = sided(Role::LeftHip, Role::RightHip, &map)
            && let Some(m) = meet(l, r)
        {
            map.insert(Role::Pelvis, m);
        }
        let arms = sided(Role::LeftClavicle, Role::RightClavicle, &map)
            .or_else(|| sided(Role::LeftShoulder, Role::RightShoulder, &map));
        let Some((l, r)) = arms else {
            return Self { joints: map };
        };
        let Some(chest) = meet(l, r) else {
            return Self { joints: map };
        };
        let spine = map.get(&Role::Spine).copied();
        if spine.is_none() || spine == map.get(&Role::Pelvis).copied() {
            map.remove(&Role::Spine);
            // The joint after the pelvis on the way to the chest.
            if let Some(&pelvis) = map.get(&Role::Pelvis) {
                let path = ancestors(chest);
                if let Some(i) = path.iter().position(|&k| k == pelvis)
                    && i >= 1
                {
                    map.insert(Role::Spine, path[i - 1]);
                }
            }
        }
        // Where the arms leave the neck itself (3ds Max's Biped hangs its clavicles from
        // `Bip01 Neck`), the chest is the joint below the neck.
        let chest_role = match joints[chest].parent {
            Some(below) if map.get(&Role::Neck) == Some(&chest) => below,
            _ => chest,
        };
        if !map.contains_key(&Role::Chest)
            && map.get(&Role::Spine) != Some(&chest_role)
            && map.get(&Role::Pelvis) != Some(&chest_role)
        {
            map.insert(Role::Chest, chest_role);
        }
        // The chain that leaves the chest toward neither arm: neck … head.
        let toward_arm =
            |c: usize| skeleton.is_ancestor_or_self(c, l) || skeleton.is_ancestor_or_self(c, r);
        let torso_named = |j: usize| {
            matches!(
                read_name(&joints[j].name),
                Some((
                    Kind::Spine | Kind::Chest | Kind::Neck | Kind::Head,
                    Side::Centre
                ))
            )
        };
        let below = |j: usize| {
            (0..joints.len())
                .filter(|&k| skeleton.is_ancestor_or_self(j, k))
                .count()
        };
        let mut chain = Vec::new();
        let mut at = chest;
        while let Some(next) = (0..joints.len())
            .filter(|&c| joints[c].parent == Some(at) && !toward_arm(c))
            .max_by_key(|&c| (torso_named(c), below(c), std::cmp::Reverse(c)))
        {
            chain.push(next);
            at = next;
        }
        if let Some(last) = chain.iter().rposition(|&c| torso_named(c)) {
            chain.truncate(last + 1);
        }
        let head = match map.get(&Role::Head) {
            Some(&head) => Some(head),
            None => chain.last().copied().inspect(|&head| {
                map.insert(Role::Head, head);
            }),
        };
        if let (Some(head), Some(&first)) = (head, chain.first())
            && first != head
            && skeleton.is_ancestor_or_self(first, head)
        {
            map.entry(Role::Neck).or_insert(first);
        }
        Self { joints: map }
    }

    /// These roles with the map's entries put over them; an entry naming a joint the skeleton
    /// lacks is an error naming the joint and the role.
    pub fn with_map(mut self, skeleton: &Skeleton, map: &RoleMap) -> Result<Self, String> {
        for (role, name) in &map.0 {
            let joint = skeleton.index_of(name).ok_or_else(|| {
                format!(
                    "the role `{}` names the joint `{name}`, which the skeleton does not have",
                    role.name()
                )
            })?;
            self.joints.insert(*role, joint);
        }
        Ok(self)
    }

    /// Checks that every joint index is within `joints` (for roles read from files).
    pub fn validate(&self, joints: usize) -> Result<(), String> {
        match self.joints.iter().find(|(_, j)| **j >= joints) {
            Some((role, j)) => Err(format!(
                "the role `{}` names joint {j} of {joints}",
                role.name()
            )),
            None => Ok(()),
        }
    }

    /// Roles from `(role, joint)` pairs (as a rig file stores them).
    pub fn from_pairs(pairs: impl IntoIterator<Item = (Role, usize)>) -> Self {
        Self {
            joints: pairs.into_iter().collect(),
        }
    }
}

/// A user's role map: a JSON object from role names to joint names, e.g.
/// `{"head": "Bone.012", "left_wrist": "Bone.031"}`; the roles it names override the inferred
/// ones.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RoleMap(pub BTreeMap<Role, String>);

impl RoleMap {
    /// Reads a role map file; an unknown role is an error listing the known ones.
    pub fn read(path: &Path) -> Result<Self, RigError> {
        let text = std::fs::read_to_string(path).map_err(|e| RigError::file(path, e))?;
        serde_json::from_str(&text).map_err(|e| {
            let known: Vec<String> = Role::ALL.iter().map(|r| r.name()).collect();
            RigError::file(
                path,
                format!(
                    "not a role map ({e}): expected a JSON object from roles ({}) to joint names",
                    known.join(", ")
                ),
            )
        })
    }

    /// The role map next to a model file: `MODEL.roles.json` (`body.glb` → `body.roles.json`).
    pub fn beside(model: &Path) -> std::path::PathBuf {
        model.with_extension("roles.json")
    }
}

/// What a name says a joint is, before sides are resolved.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Pelvis,
    Spine,
    Chest,
    Neck,
    Head,
    Jaw,
    Eye,
    Clavicle,
    /// `shoulder`: the clavicle or the upper arm, depending on the rest of the skeleton.
    Shoulder,
    UpperArm,
    Elbow,
    Wrist,
    /// `hand`: the wrist when the skeleton has no `wrist`.
    Hand,
    Hip,
    /// A sided `pelvis` (Rigify's and MakeHuman's `pelvis.L`: the bone from the pelvis toward
    /// the hip, which does not turn the thigh): the hip only when the side has no thigh.
    PelvisSide,
    Knee,
    Ankle,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Side {
    Left,
    Right,
    Centre,
}

/// Words of rig prefixes, dropped before matching.
const PREFIXES: [&str; 12] = [
    "mixamorig",
    "bip",
    "def",
    "org",
    "mch",
    "j",
    "jnt",
    "bone",
    "b",
    "cc",
    "base",
    "rig",
];

/// Words that mark a helper joint, which takes no role.
const HELPERS: [&str; 18] = [
    "end",
    "nub",
    "tip",
    "twist",
    "roll",
    "ik",
    "fk",
    "target",
    "pole",
    "helper",
    "null",
    "socket",
    "top",
    "ctrl",
    "tweak",
    "vis",
    "wgt",
    "corrective",
];

/// The layer of a rig whose bones come in copies (Blender's Rigify: `DEF-` deform bones,
/// `ORG-` originals, `MCH-` mechanism, controls unprefixed): the lower, the likelier to
/// carry the pose as the mesh sees it.
fn layer(name: &str) -> u8 {
    match words(name).first().map(String::as_str) {
        Some("def") => 0,
        Some("org") => 1,
        Some("mch") => 3,
        _ => 2,
    }
}

/// Synonyms of each kind, as the words left after prefixes, sides and numbers are dropped
/// (joined without separators).
const SYNONYMS: [(Kind, &[&str]); 16] = [
    (Kind::Pelvis, &["pelvis", "hips", "hip"]),
    (
        Kind::Spine,
        &["spine", "abdomen", "waist", "torso", "spine0"],
    ),
    (Kind::Chest, &["chest", "upperchest", "thorax", "ribs"]),
    (Kind::Neck, &["neck", "lowerneck", "upperneck"]),
    (Kind::Head, &["head"]),
    (Kind::Jaw, &["jaw", "mandible"]),
    (Kind::Eye, &["eye", "eyeball"]),
    (Kind::Clavicle, &["clavicle", "collar", "collarbone"]),
    (Kind::Shoulder, &["shoulder"]),
    (Kind::UpperArm, &["upperarm", "uparm", "arm", "humerus"]),
    (
        Kind::Elbow,
        &["forearm", "lowerarm", "loarm", "lowarm", "elbow", "radius"],
    ),
    (Kind::Wrist, &["wrist"]),
    (Kind::Hand, &["hand"]),
    (Kind::Hip, &["upleg", "upperleg", "thigh", "femur", "hip"]),
    (
        Kind::Knee,
        &[
            "knee", "leg", "lowerleg", "loleg", "lowleg", "shin", "calf", "tibia",
        ],
    ),
    (Kind::Ankle, &["ankle", "foot"]),
];

/// Splits a joint name into lower-case words: at separators, lower-to-upper case changes and
/// letter/digit boundaries.
fn words(name: &str) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    let mut current = String::new();
    let mut previous: Option<char> = None;
    for c in name.chars() {
        if !c.is_alphanumeric() {
            if !current.is_empty() {
                out.push(std::mem::take(&mut current));
            }
            previous = None;
            continue;
        }
        let boundary = previous.is_some_and(|p| {
            (p.is_lowercase() && c.is_uppercase()) || (p.is_ascii_digit() != c.is_ascii_digit())
        });
        if boundary && !current.is_empty() {
            out.push(std::mem::take(&mut current));
        }
        current.extend(c.to_lowercase());
        previous = Some(c);
    }
    if !current.is_empty() {
        out.push(current);
    }
    out
}

/// What a joint name says: its kind and side, or `None` for a name that matches no role.
fn read_name(name: &str) -> Option<(Kind, Side)> {
    let mut ws = words(name);
    // Rig prefixes lead the name (with their numbers: `Bip01`).
    while ws.len() > 1
        && (PREFIXES.contains(&ws[0].as_str()) || ws[0].chars().all(|c| c.is_ascii_digit()))
    {
        ws.remove(0);
    }
    if ws.iter().any(|w| HELPERS.contains(&w.as_str())) {
        return None;
    }
    let mut side = Side::Centre;
    let mut rest: Vec<&str> = Vec::new();
    for w in &ws {
        match w.as_str() {
            "left" | "l" | "lft" => side = Side::Left,
            "right" | "r" | "rgt" | "rt" => side = Side::Right,
            "c" | "center" | "centre" | "mid" => {}
            w if w.chars().all(|c| c.is_ascii_digit()) => {}
            w => rest.push(w),
        }
    }
    // Sides glued to a word: `lshoulder`, `lefthand`.
    let mut base = rest.concat();
    for (prefix, s) in [("left", Side::Left), ("right", Side::Right)] {
        if side == Side::Centre
            && let Some(stripped) = base.strip_prefix(prefix)
            && !stripped.is_empty()
        {
            base = stripped.to_string();
            side = s;
        }
    }
    let synonym = |base: &str| {
        SYNONYMS
            .iter()
            .find(|(_, names)| names.contains(&base))
            .map(|(k, _)| *k)
    };
    // One glued side letter, as CMU's ASF names have it (`lfemur`, `rhumerus`): only where
    // the rest is a synonym and the whole is not (`leg` stays a leg).
    if side == Side::Centre && synonym(&base).is_none() {
        for (prefix, s) in [('l', Side::Left), ('r', Side::Right)] {
            if let Some(stripped) = base.strip_prefix(prefix)
                && synonym(stripped).is_some()
            {
                base = stripped.to_string();
                side = s;
                break;
            }
        }
    }
    let kind = synonym(&base)?;
    // `hip` alone is the pelvis; with a side, the thigh's joint. A sided `pelvis` is the
    // pelvis bone of that side, the hip only where nothing else is.
    let kind = match (kind, side) {
        (Kind::Pelvis, Side::Left | Side::Right) if base == "pelvis" => Kind::PelvisSide,
        (Kind::Pelvis, Side::Left | Side::Right) => Kind::Hip,
        (Kind::Hip, Side::Centre) if base == "hip" => Kind::Pelvis,
        (k, _) => k,
    };
    Some((kind, side))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skeleton::Joint;
    use glam::{Quat, Vec3};

    fn skeleton(names: &[(&str, Option<usize>)]) -> Skeleton {
        Skeleton::new(
            names
                .iter()
                .map(|(n, p)| Joint {
                    name: n.to_string(),
                    parent: *p,
                    offset: Vec3::Y,
                    pre_rotation: Quat::IDENTITY,
                })
                .collect(),
        )
        .unwrap()
    }

    #[test]
    fn names_split_into_words() {
        assert_eq!(
            words("mixamorig:LeftUpLeg"),
            ["mixamorig", "left", "up", "leg"]
        );
        assert_eq!(words("upperarm01.L"), ["upperarm", "01", "l"]);
        assert_eq!(words("Bip01 L Thigh"), ["bip", "01", "l", "thigh"]);
        assert_eq!(words("spine.001"), ["spine", "001"]);
    }

    #[test]
    fn names_of_the_common_families_are_read() {
        let cases = [
            ("mixamorig:LeftUpLeg", Some((Kind::Hip, Side::Left))),
            ("mixamorig:RightLeg", Some((Kind::Knee, Side::Right))),
            ("mixamorig:LeftShoulder", Some((Kind::Shoulder, Side::Left))),
            ("mixamorig:LeftArm", Some((Kind::UpperArm, Side::Left))),
            ("mixamorig:LeftHand", Some((Kind::Hand, Side::Left))),
            ("mixamorig:LeftHandIndex1", None),
            ("mixamorig:HeadTop_End", None),
            ("mixamorig:Hips", Some((Kind::Pelvis, Side::Centre))),
            ("left_wrist", Some((Kind::Wrist, Side::Left))),
            ("right_collar", Some((Kind::Clavicle, Side::Right))),
            ("upperleg01.L", Some((Kind::Hip, Side::Left))),
            ("lowerarm01.R", Some((Kind::Elbow, Side::Right))),
            ("l_upleg", Some((Kind::Hip, Side::Left))),
            ("r_uparm", Some((Kind::UpperArm, Side::Right))),
            ("c_head", Some((Kind::Head, Side::Centre))),
            ("Bip01 L Thigh", Some((Kind::Hip, Side::Left))),
            ("thigh_r", Some((Kind::Hip, Side::Right))),
            ("DEF-forearm.L", Some((Kind::Elbow, Side::Left))),
            ("J_Bip_L_UpperArm", Some((Kind::UpperArm, Side::Left))),
            ("LeftForeArmRoll", None),
            ("Hip_L", Some((Kind::Hip, Side::Left))),
            ("eye.R", Some((Kind::Eye, Side::Right))),
            ("jaw", Some((Kind::Jaw, Side::Centre))),
            ("Bone.012", None),
            ("mixamorig1:LeftArm", Some((Kind::UpperArm, Side::Left))),
            ("mixamorig_LeftForeArm", Some((Kind::Elbow, Side::Left))),
            // Blender / Rigify, with its layers' prefixes.
            ("thigh.L", Some((Kind::Hip, Side::Left))),
            ("DEF-shin.R", Some((Kind::Knee, Side::Right))),
            ("ORG-upper_arm.L", Some((Kind::UpperArm, Side::Left))),
            ("DEF-upper_arm.L.001", Some((Kind::UpperArm, Side::Left))),
            ("MCH-foot.L", Some((Kind::Ankle, Side::Left))),
            ("shoulder.L", Some((Kind::Shoulder, Side::Left))),
            ("pelvis.L", Some((Kind::PelvisSide, Side::Left))),
            ("spine.003", Some((Kind::Spine, Side::Centre))),
            ("upper_arm_tweak.L", None),
            ("upper_arm_parent.L", None),
            ("hand_ik.L", None),
            // CMU's ASF names: one glued side letter.
            ("lfemur", Some((Kind::Hip, Side::Left))),
            ("rhumerus", Some((Kind::UpperArm, Side::Right))),
            ("lradius", Some((Kind::Elbow, Side::Left))),
            ("ltibia", Some((Kind::Knee, Side::Left))),
            ("rclavicle", Some((Kind::Clavicle, Side::Right))),
            ("lwrist", Some((Kind::Wrist, Side::Left))),
            ("lhipjoint", None),
            ("LHipJoint", None),
            ("lowerback", None),
            ("lowerneck", Some((Kind::Neck, Side::Centre))),
            ("thorax", Some((Kind::Chest, Side::Centre))),
            ("leg", Some((Kind::Knee, Side::Centre))),
            // Unreal.
            ("upperarm_l", Some((Kind::UpperArm, Side::Left))),
            ("lowerarm_r", Some((Kind::Elbow, Side::Right))),
            ("calf_l", Some((Kind::Knee, Side::Left))),
            ("clavicle_l", Some((Kind::Clavicle, Side::Left))),
            ("spine_01", Some((Kind::Spine, Side::Centre))),
            ("upperarm_twist_01_l", None),
            ("ik_foot_l", None),
            ("ball_l", None),
            // Unity's humanoid, MotionBuilder / HumanIK, LAFAN1, other side markers.
            ("LeftUpperLeg", Some((Kind::Hip, Side::Left))),
            ("RightLowerLeg", Some((Kind::Knee, Side::Right))),
            ("LeftUpperArm", Some((Kind::UpperArm, Side::Left))),
            ("LeftLowerArm", Some((Kind::Elbow, Side::Left))),
            ("UpperChest", Some((Kind::Chest, Side::Centre))),
            ("Spine1", Some((Kind::Spine, Side::Centre))),
            ("LeftUpLegRoll", None),
            ("LeftToe", None),
            ("L_Thigh", Some((Kind::Hip, Side::Left))),
            ("Thigh_R", Some((Kind::Hip, Side::Right))),
            ("ThighLeft", Some((Kind::Hip, Side::Left))),
        ];
        for (name, expected) in cases {
            assert_eq!(read_name(name), expected, "{name}");
        }
    }

    #[test]
    fn a_mixamo_skeleton_gets_its_roles() {
        let s = skeleton(&[
            ("mixamorig:Hips", None),
            ("mixamorig:Spine", Some(0)),
            ("mixamorig:Neck", Some(1)),
            ("mixamorig:Head", Some(2)),
            ("mixamorig:LeftShoulder", Some(1)),
            ("mixamorig:LeftArm", Some(4)),
            ("mixamorig:LeftForeArm", Some(5)),
            ("mixamorig:LeftHand", Some(6)),
            ("mixamorig:LeftUpLeg", Some(0)),
            ("mixamorig:LeftLeg", Some(8)),
            ("mixamorig:LeftFoot", Some(9)),
        ]);
        let roles = Roles::infer(&s);
        for (role, joint) in [
            (Role::Pelvis, 0),
            (Role::Spine, 1),
            (Role::Neck, 2),
            (Role::Head, 3),
            (Role::LeftClavicle, 4),
            (Role::LeftShoulder, 5),
            (Role::LeftElbow, 6),
            (Role::LeftWrist, 7),
            (Role::LeftHip, 8),
            (Role::LeftKnee, 9),
            (Role::LeftAnkle, 10),
        ] {
            assert_eq!(roles.get(role), Some(joint), "{role:?}");
        }
        assert_eq!(roles.get(Role::RightWrist), None);
    }

    #[test]
    fn the_joint_nearest_the_root_wins_and_maps_override() {
        let s = skeleton(&[
            ("root", None),
            ("upperarm01.L", Some(0)),
            ("upperarm02.L", Some(1)),
            ("Bone.7", Some(0)),
        ]);
        let roles = Roles::infer(&s);
        assert_eq!(roles.get(Role::LeftShoulder), Some(1));
        let map = RoleMap([(Role::Head, "Bone.7".to_string())].into());
        let roles = roles.with_map(&s, &map).unwrap();
        assert_eq!(roles.get(Role::Head), Some(3));
        let bad = RoleMap([(Role::Head, "Bone.8".to_string())].into());
        let e = Roles::default().with_map(&s, &bad).unwrap_err();
        assert!(e.contains("Bone.8") && e.contains("`head`"), "{e}");
    }

    #[test]
    fn a_sided_pelvis_is_the_hip_only_without_a_thigh() {
        // Rigify's `pelvis.L` leaves the root beside `thigh.L`, and first.
        let s = skeleton(&[
            ("spine", None),
            ("pelvis.L", Some(0)),
            ("thigh.L", Some(0)),
            ("shin.L", Some(2)),
        ]);
        let roles = Roles::infer(&s);
        assert_eq!(roles.get(Role::LeftHip), Some(2));
        let s = skeleton(&[("spine", None), ("pelvis.L", Some(0)), ("shin.L", Some(1))]);
        assert_eq!(Roles::infer(&s).get(Role::LeftHip), Some(1));
    }

    #[test]
    fn a_layered_rig_takes_its_roles_from_its_deform_bones() {
        // A generated Rigify rig: controls, originals and deform bones of the same limbs.
        let s = skeleton(&[
            ("root", None),
            ("ORG-thigh.L", Some(0)),
            ("hips", Some(0)),
            ("thigh_fk.L", Some(0)),
            ("DEF-spine", Some(0)),
            ("DEF-thigh.L", Some(4)),
            ("DEF-thigh.L.001", Some(5)),
            ("DEF-shin.L", Some(6)),
            ("MCH-shin.L", Some(0)),
        ]);
        let roles = Roles::infer(&s);
        assert_eq!(roles.get(Role::LeftHip), Some(5));
        assert_eq!(roles.get(Role::LeftKnee), Some(7));
        // The `hips` control is not the deform layer's: the pelvis comes from the shape.
        assert_eq!(roles.get(Role::Pelvis), None);
        assert_eq!(roles.get(Role::Spine), Some(4));
    }

    #[test]
    fn the_head_chain_follows_the_spine_names_past_breasts_and_faces() {
        // Rigify's metarig: `breast.L` before `spine.004` under the chest, the face below
        // `spine.006`; the root `spine` is the pelvis.
        let s = skeleton(&[
            ("spine", None),          // 0
            ("spine.001", Some(0)),   // 1
            ("spine.002", Some(1)),   // 2
            ("spine.003", Some(2)),   // 3
            ("breast.L", Some(3)),    // 4
            ("shoulder.L", Some(3)),  // 5
            ("upper_arm.L", Some(5)), // 6
            ("shoulder.R", Some(3)),  // 7
            ("upper_arm.R", Some(7)), // 8
            ("spine.004", Some(3)),   // 9
            ("spine.005", Some(9)),   // 10
            ("spine.006", Some(10)),  // 11
            ("face", Some(11)),       // 12
            ("nose", Some(12)),       // 13
            ("thigh.L", Some(0)),     // 14
            ("thigh.R", Some(0)),     // 15
        ]);
        let roles = Roles::infer(&s).completed(&s);
        for (role, joint) in [
            (Role::Pelvis, 0),
            (Role::Spine, 1),
            (Role::Chest, 3),
            (Role::Neck, 9),
            (Role::Head, 11),
            (Role::LeftClavicle, 5),
            (Role::LeftShoulder, 6),
        ] {
            assert_eq!(roles.get(role), Some(joint), "{role:?}");
        }
        // Unnamed: the chain with the most joints below, to its end.
        let s = skeleton(&[
            ("Bone", None),
            ("Bone.001", Some(0)),
            ("Bone.002", Some(1)),
            ("Bone.003", Some(1)),
            ("Bone.004", Some(3)),
            ("Arm_L", Some(1)),
            ("Arm_R", Some(1)),
            ("Leg_L", Some(0)),
            ("Leg_R", Some(0)),
        ]);
        let roles = Roles::infer(&s).completed(&s);
        assert_eq!(roles.get(Role::Chest), Some(1));
        assert_eq!(roles.get(Role::Neck), Some(3));
        assert_eq!(roles.get(Role::Head), Some(4));
    }

    #[test]
    fn role_names_are_snake_case() {
        assert_eq!(Role::LeftWrist.name(), "left_wrist");
        let map: RoleMap = serde_json::from_str(r#"{"head": "a", "right_hip": "b"}"#).unwrap();
        assert_eq!(map.0[&Role::RightHip], "b");
        assert!(serde_json::from_str::<RoleMap>(r#"{"noggin": "a"}"#).is_err());
    }
}
