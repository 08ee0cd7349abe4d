//! Motions from other tools, and retargeting onto a body model.
//!
//! Every reader gives one [`Motion`]: a skeleton (names, parents, rest offsets, rest
//! rotations), each frame's local joint rotations and root translation, the frame rate, and
//! the units and up axis *as read* — nothing is converted on reading. [`retarget`] then drives
//! any body model ([`f3g_rig::Rig`]) with it through the body-model contract's joint roles.
//!
//! Formats ([`Format`], by extension, and an `.npz` by the arrays it holds):
//! - AMASS `.npz` (`poses`, `trans`, `betas`, `mocap_framerate` or `mocap_frame_rate`; SMPL,
//!   SMPL-H or SMPL-X layouts by the width of `poses`), Z up, metres;
//! - Meshcapade's `.smpl` (an `.npz` in the `smplcodec` layout: `bodyPose`, `bodyTranslation`,
//!   `frameRate`, …), Y up, metres;
//! - `smpl_params.npz` (AvatarReX / THuman4.0), Y up, metres;
//! - BVH (`.bvh`), any channel order, units and up axis inferred from the rest skeleton;
//! - glTF animations (`.glb`, `.gltf`): a skin's joints driven by the first animation, Y up,
//!   metres;
//! - FBX animation stacks (`.fbx`): the bone nodes driven by the first stack, the file's units
//!   and up axis.
//!
//! Every reader refuses, naming the file and what is wrong, a value that is not finite or not
//! plausible — an angle beyond [`MAX_ANGLE_DEGREES`], a translation or rest offset beyond
//! [`MAX_TRANSLATION_METRES`] — and a rest skeleton of zero length.
//!
//! Conventions: a joint's local transform is `T(offset + t) · R_rest · R` as in
//! [`f3g_rig::skeleton`]; only the root has a translation `t`. Rotations are unit quaternions.

mod bvh;
mod error;
mod export;
mod fbx;
pub mod floor;
pub mod foot_lock;
mod gltf;
pub mod plausibility;
pub mod rest;
pub mod retarget;
mod smpl;

use std::path::Path;

use glam::{Quat, Vec3};

use f3g_rig::{Similarity, Skeleton};

pub use bvh::{parse_bvh, write_bvh};
pub use error::MotionError;
pub use export::from_rig;
pub use fbx::{parse_fbx, write_fbx};
pub use floor::FloorReport;
pub use gltf::{read_gltf, write_gltf};
pub use plausibility::Plausibility;
pub use rest::RestChoice;
pub use retarget::{Correspondence, RetargetOptions, Retargeted, retarget};
pub use smpl::{SmplFamily, SmplMotion};

/// Euler angles `(z, y, x)` in degrees with `R = Rz·Ry·Rx` (BVH's and FBX's writers), computed
/// in f64 from the quaternion renormalised there: next to ±90° about y the x and z angles come
/// from matrix entries of size cos y, so an f32 quaternion's 1e-7 norm error (or f32's asin)
/// would turn them by 1e-3 rad.
pub(crate) fn euler_zyx_degrees(q: glam::Quat) -> (f64, f64, f64) {
    let (z, y, x) = q.as_dquat().normalize().to_euler(glam::EulerRot::ZYX);
    (z.to_degrees(), y.to_degrees(), x.to_degrees())
}

/// Frame counts above this are refused before anything is allocated for them (a day at
/// 120 fps): a damaged header cannot ask for terabytes.
pub const MAX_FRAMES: usize = 10_368_000;
/// Joint counts above this are refused.
pub const MAX_JOINTS: usize = 4096;
/// The largest rotation angle f3g reads (BVH and FBX Euler keys; AMASS and `.smpl`
/// axis-angles the same in radians): about 2 800 turns, far past any unwrapped capture, and
/// where an f32 angle still resolves a tenth of a degree — a larger key is damage, whose
/// sine and cosine are noise.
pub const MAX_ANGLE_DEGREES: f32 = 1e6;
/// The farthest from the origin a root translation or a rest offset may be, in metres: 1 km
/// holds any capture volume or recorded walk, and an f32 position there still resolves
/// 0.1 mm.
pub const MAX_TRANSLATION_METRES: f32 = 1000.0;
/// The shortest rest skeleton read (all bone lengths together, in metres): below it, no
/// units or scale can be inferred from it (a BVH's units come from its height, a retarget's
/// scale from its legs).
const MIN_SKELETON_METRES: f32 = 1e-3;

/// The world axis that points up in a file.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum Up {
    Y,
    Z,
}

/// A motion as read from a file.
#[derive(Clone, Debug)]
pub struct Motion {
    pub skeleton: Skeleton,
    /// `[frames · joints]` local rotations, applied after each joint's rest rotation.
    pub rotations: Vec<Quat>,
    /// `[frames]` translation of the root, added to its rest offset (file units).
    pub root_translation: Vec<Vec3>,
    /// Frames per second.
    pub fps: f32,
    /// Metres per file unit (0.01 for centimetres).
    pub metres_per_unit: f32,
    pub up: Up,
    /// The parameters as read, when the file is of the SMPL family: a body model of the same
    /// family takes them parameter for parameter.
    pub smpl: Option<SmplMotion>,
}

impl Motion {
    pub fn frames(&self) -> usize {
        self.root_translation.len()
    }

    /// The local rotations of frame `f`.
    pub fn frame(&self, f: usize) -> &[Quat] {
        let j = self.skeleton.len();
        &self.rotations[f * j..(f + 1) * j]
    }

    /// World transforms of every joint at frame `f` (file units and axes).
    pub fn world(&self, f: usize) -> Vec<Similarity> {
        let poses: Vec<f3g_rig::JointPose> = self
            .frame(f)
            .iter()
            .enumerate()
            .map(|(j, &rotation)| f3g_rig::JointPose {
                translation: if j == 0 {
                    self.root_translation[f]
                } else {
                    Vec3::ZERO
                },
                rotation,
                log2_scale: 0.0,
            })
            .collect();
        self.skeleton.forward(&poses, None)
    }

    /// Joint positions of frame `f` in metres, +Y up (the file's units and up axis undone).
    pub fn positions(&self, f: usize) -> Vec<Vec3> {
        let upright = match self.up {
            Up::Y => Quat::IDENTITY,
            Up::Z => Quat::from_rotation_x(-std::f32::consts::FRAC_PI_2),
        };
        self.world(f)
            .iter()
            .map(|s| upright * (s.translation * self.metres_per_unit))
            .collect()
    }

    /// The same motion at `fps`: rotations by spherical interpolation, the root linearly;
    /// `path` names the file in errors.
    pub fn resampled(&self, fps: f32, path: &Path) -> Result<Motion, MotionError> {
        let n = self.frames();
        if n < 2 || fps == self.fps {
            return Ok(Motion {
                fps,
                ..self.clone()
            });
        }
        let duration = (n - 1) as f64 / self.fps as f64;
        let count = ((duration * fps as f64).floor() as usize + 1).min(MAX_FRAMES);
        ensure_memory(count, self.skeleton.len(), path)?;
        let j = self.skeleton.len();
        let mut rotations = Vec::with_capacity(count * j);
        let mut root = Vec::with_capacity(count);
        for i in 0..count {
            let x = i as f64 / fps as f64 * self.fps as f64;
            let a = (x.floor() as usize).min(n - 1);
            let b = (a + 1).min(n - 1);
            let t = (x - a as f64) as f32;
            for k in 0..j {
                rotations.push(self.frame(a)[k].slerp(self.frame(b)[k], t).normalize());
            }
            root.push(self.root_translation[a].lerp(self.root_translation[b], t));
        }
        Ok(Motion {
            skeleton: self.skeleton.clone(),
            rotations,
            root_translation: root,
            fps,
            metres_per_unit: self.metres_per_unit,
            up: self.up,
            smpl: self
                .smpl
                .as_ref()
                .map(|s| s.resampled(self.fps, fps, count)),
        })
    }
}

/// The motion file formats f3g reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    Amass,
    SmplCodec,
    SmplParams,
    Bvh,
    Gltf,
    Fbx,
}

/// The formats, as error messages list them.
pub const FORMATS: &str = "AMASS .npz (poses, trans, mocap_framerate), Meshcapade .smpl, \
     smpl_params.npz (AvatarReX / THuman4.0), BVH (.bvh), glTF animations (.glb, .gltf), FBX \
     animation stacks (.fbx), or f3g's own body_params.npz";

/// Which format `path` holds, by content (an `.npz`'s arrays) or extension.
pub fn detect(path: &Path) -> Result<Format, MotionError> {
    let extension = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    if !path.is_file() {
        return Err(MotionError::file(
            path,
            format!("no such motion file (f3g reads {FORMATS})"),
        ));
    }
    match extension.as_deref() {
        Some("bvh") => return Ok(Format::Bvh),
        Some("glb" | "gltf") => return Ok(Format::Gltf),
        Some("fbx") => return Ok(Format::Fbx),
        Some("npz" | "smpl") => {}
        _ => {
            return Err(MotionError::file(
                path,
                format!("not a motion file f3g knows: it reads {FORMATS}"),
            ));
        }
    }
    let npz = f3g_io::Npz::open(path)
        .map_err(|e| MotionError::file(path, format!("{} (f3g reads {FORMATS})", e.reason)))?;
    if npz.contains("bodyPose") {
        Ok(Format::SmplCodec)
    } else if npz.contains("poses") && npz.contains("trans") {
        Ok(Format::Amass)
    } else if npz.contains("global_orient") && npz.contains("body_pose") {
        Ok(Format::SmplParams)
    } else {
        Err(MotionError::file(
            path,
            format!(
                "an .npz with none of the arrays of a motion format (it has {}); f3g reads {FORMATS}",
                npz.names().join(", ")
            ),
        ))
    }
}

/// Reads a motion of any [`Format`].
pub fn read(path: &Path) -> Result<Motion, MotionError> {
    match detect(path)? {
        Format::Bvh => {
            let bytes = std::fs::read(path).map_err(|e| MotionError::file(path, e))?;
            parse_bvh(&bytes, path)
        }
        Format::Amass => smpl::read_amass(path),
        Format::SmplCodec => smpl::read_smpl_codec(path),
        Format::SmplParams => smpl::read_smpl_params(path),
        Format::Gltf => gltf::read_gltf(path, None),
        Format::Fbx => {
            let bytes = std::fs::read(path).map_err(|e| MotionError::file(path, e))?;
            parse_fbx(&bytes, path)
        }
    }
}

/// Refuses a motion of `frames` × `joints` rotations that the memory budget cannot hold,
/// before it is allocated.
pub(crate) fn ensure_memory(frames: usize, joints: usize, path: &Path) -> Result<(), MotionError> {
    let bytes = (frames as u64)
        .saturating_mul(joints as u64)
        .saturating_mul(16);
    f3g_io::memory::ensure_available(bytes, &format!("{frames} frames of {joints} joints"))
        .map_err(|e| MotionError::file(path, e))
}

/// Checks that every value of a motion is finite and plausible — translations and rest
/// offsets within [`MAX_TRANSLATION_METRES`], a rest skeleton of some length, a frame rate
/// up to 10 000 fps — naming the frame and joint that is not.
pub(crate) fn check_values(motion: &Motion, path: &Path) -> Result<(), MotionError> {
    let j = motion.skeleton.len();
    let metres = motion.metres_per_unit;
    if let Some(i) = motion.rotations.iter().position(|q| !q.is_finite()) {
        return Err(MotionError::file(
            path,
            format!(
                "frame {}: the rotation of joint `{}` is not finite",
                i / j,
                motion.skeleton.joints()[i % j].name
            ),
        ));
    }
    let too_far = |v: Vec3| !v.is_finite() || v.length() * metres > MAX_TRANSLATION_METRES;
    if let Some(f) = motion.root_translation.iter().position(|&t| too_far(t)) {
        return Err(MotionError::file(
            path,
            format!(
                "frame {f}: the root translation {} m is not within {} km of the origin",
                motion.root_translation[f] * metres,
                MAX_TRANSLATION_METRES / 1000.0
            ),
        ));
    }
    if let Some(joint) = motion.skeleton.joints().iter().find(|j| too_far(j.offset)) {
        return Err(MotionError::file(
            path,
            format!(
                "the rest offset of joint `{}`, {} m, is not within {} km",
                joint.name,
                joint.offset * metres,
                MAX_TRANSLATION_METRES / 1000.0
            ),
        ));
    }
    let length: f32 = motion
        .skeleton
        .joints()
        .iter()
        .filter(|j| j.parent.is_some())
        .map(|j| j.offset.length() * metres)
        .sum();
    if length == 0.0 {
        return Err(MotionError::file(
            path,
            "the rest skeleton has zero length: no units or scale can be inferred",
        ));
    }
    if length < MIN_SKELETON_METRES {
        return Err(MotionError::file(
            path,
            format!(
                "the rest skeleton's bones measure {length} m in all, under 1 mm: no units or scale can be inferred"
            ),
        ));
    }
    if !(motion.fps.is_finite() && motion.fps > 0.0 && motion.fps <= 10_000.0) {
        return Err(MotionError::file(
            path,
            format!(
                "frame rate {} is not between 0 and 10 000 frames per second",
                motion.fps
            ),
        ));
    }
    Ok(())
}
