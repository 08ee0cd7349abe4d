//! The SMPL family's motion files: AMASS `.npz`, Meshcapade's `.smpl` and `smpl_params.npz`.
//!
//! All three are read into SMPL-X's 55-joint layout ([`f3g_rig::smplx::JOINT_NAMES`]): SMPL's
//! 24 joints give the body (its two hand joints are dropped), SMPL-H's 52 the body and hands,
//! SMPL-X's 55 everything (jaw, eyes). The files hold rotations but not the rest skeleton,
//! which their body model regresses from the shape; a body model of another family is driven
//! through [`schematic_rest`], SMPL-X's T-pose rest skeleton as typed-in proportions (enough
//! for the rotations' retargeting, which needs bone directions and the leg length).
//!
//! Every value must be finite; axis-angles within [`crate::MAX_ANGLE_DEGREES`] (in radians),
//! translations within [`crate::MAX_TRANSLATION_METRES`] of the origin.

use std::path::Path;

use glam::{Quat, Vec3};

use f3g_rig::smplx::{JOINT_NAMES, SmplParams, schematic_rest};

use crate::{MAX_ANGLE_DEGREES, MAX_FRAMES, MAX_TRANSLATION_METRES, Motion, MotionError, Up};

/// Which body model a file's parameters were made for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum SmplFamily {
    Smpl,
    SmplH,
    SmplX,
}

/// What an SMPL-family file holds beyond rotations.
#[derive(Clone, Debug, PartialEq)]
pub struct SmplMotion {
    pub family: SmplFamily,
    /// Shape coefficients of the family's own shape space (SMPL-X's only for SMPL-X files).
    pub betas: Vec<f32>,
    /// `[frames, E]` expression coefficients (SMPL-X files only; E may be 0).
    pub expression: Vec<f32>,
    pub num_expression: usize,
}

impl SmplMotion {
    /// The expressions resampled as [`Motion::resampled`] does the rotations.
    pub(crate) fn resampled(&self, from_fps: f32, to_fps: f32, count: usize) -> SmplMotion {
        let e = self.num_expression;
        let n = self.expression.len().checked_div(e).unwrap_or(0);
        let mut expression = Vec::with_capacity(count * e);
        for i in 0..count {
            if n == 0 {
                break;
            }
            let x = i as f64 / to_fps as f64 * from_fps as f64;
            let a = (x.floor() as usize).min(n - 1);
            let b = (a + 1).min(n - 1);
            let t = (x - a as f64) as f32;
            for k in 0..e {
                let (va, vb) = (self.expression[a * e + k], self.expression[b * e + k]);
                expression.push(va + t * (vb - va));
            }
        }
        SmplMotion {
            expression,
            ..self.clone()
        }
    }

    /// The parameters of `motion` (which this describes) in the `smpl_params.npz` layout.
    pub fn params(&self, motion: &Motion) -> SmplParams {
        let frames = motion.frames();
        let mut p = SmplParams {
            frames,
            betas: self.betas.clone(),
            global_orient: Vec::with_capacity(3 * frames),
            transl: Vec::with_capacity(3 * frames),
            jaw_pose: Vec::with_capacity(3 * frames),
            leye_pose: Vec::with_capacity(3 * frames),
            reye_pose: Vec::with_capacity(3 * frames),
            body_pose: Vec::with_capacity(63 * frames),
            left_hand_pose: Vec::with_capacity(45 * frames),
            right_hand_pose: Vec::with_capacity(45 * frames),
            expression: self.expression.clone(),
        };
        for f in 0..frames {
            let aa: Vec<[f32; 3]> = motion.frame(f).iter().map(|q| axis_angle(*q)).collect();
            p.global_orient.extend(aa[0]);
            p.body_pose.extend(aa[1..22].iter().flatten());
            p.jaw_pose.extend(aa[22]);
            p.leye_pose.extend(aa[23]);
            p.reye_pose.extend(aa[24]);
            p.left_hand_pose.extend(aa[25..40].iter().flatten());
            p.right_hand_pose.extend(aa[40..55].iter().flatten());
            p.transl
                .extend((motion.root_translation[f] * motion.metres_per_unit).to_array());
        }
        p
    }
}

/// A rotation as an axis-angle vector.
pub(crate) fn axis_angle(q: Quat) -> [f32; 3] {
    // The short way round: angles in [0, π].
    let q = if q.w < 0.0 { -q } else { q }.normalize();
    let (axis, angle) = q.to_axis_angle();
    (axis * angle).to_array()
}

/// A motion on the schematic skeleton from parameters in the `smpl_params.npz` layout.
fn motion_of(
    params: &SmplParams,
    family: SmplFamily,
    fps: f32,
    up: Up,
    path: &Path,
) -> Result<Motion, MotionError> {
    let skeleton = schematic_rest();
    let frames = params.frames;
    let mut rotations = Vec::with_capacity(frames * JOINT_NAMES.len());
    for f in 0..frames {
        for aa in params.pose(f).chunks_exact(3).take(JOINT_NAMES.len()) {
            rotations.push(f3g_rig::rig::axis_angle(Vec3::new(aa[0], aa[1], aa[2])));
        }
    }
    let root_translation = params
        .transl
        .chunks_exact(3)
        .map(|t| Vec3::new(t[0], t[1], t[2]))
        .collect();
    let motion = Motion {
        skeleton,
        rotations,
        root_translation,
        fps,
        metres_per_unit: 1.0,
        up,
        smpl: Some(SmplMotion {
            family,
            betas: params.betas.clone(),
            num_expression: params.num_expression(),
            expression: params.expression.clone(),
        }),
    };
    crate::check_values(&motion, path)?;
    Ok(motion)
}

type NpzFile = f3g_io::Npz<std::io::BufReader<std::fs::File>>;

/// What an array's values are, for the plausible range each must be in.
#[derive(Clone, Copy)]
enum Values {
    /// Axis-angle rotations, radians: within [`MAX_ANGLE_DEGREES`].
    Angles,
    /// Root translations, metres: within [`MAX_TRANSLATION_METRES`] (of the origin, per row).
    Metres,
    /// Expression coefficients: finite (their range is the body model's).
    Coefficients,
}

/// Refuses a value of the `[frames, width]` array `name` that is not finite or, for
/// rotations and translations, not within their bound — naming the frame and value.
fn check_values(
    path: &Path,
    name: &str,
    values: &[f32],
    width: usize,
    kind: Values,
) -> Result<(), MotionError> {
    let width = width.max(1);
    let at = |i: usize| format!("frame {}, value {}", i / width, i % width);
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(MotionError::field(
            path,
            name,
            format!("{} is not finite", at(i)),
        ));
    }
    match kind {
        Values::Angles => {
            let limit = MAX_ANGLE_DEGREES.to_radians();
            if let Some(i) = values.iter().position(|v| v.abs() > limit) {
                return Err(MotionError::field(
                    path,
                    name,
                    format!(
                        "{} is {} radians, beyond the ±{limit} (±{MAX_ANGLE_DEGREES}°) f3g reads",
                        at(i),
                        values[i]
                    ),
                ));
            }
        }
        Values::Metres => {
            let far = values.chunks(width).position(|row| {
                row.iter().map(|v| v * v).sum::<f32>().sqrt() > MAX_TRANSLATION_METRES
            });
            if let Some(f) = far {
                return Err(MotionError::field(
                    path,
                    name,
                    format!(
                        "frame {f}: {:?} m is not within {} km of the origin",
                        &values[f * width..(f + 1) * width],
                        MAX_TRANSLATION_METRES / 1000.0
                    ),
                ));
            }
        }
        Values::Coefficients => {}
    }
    Ok(())
}

/// A `[frames, width]` array (or `[frames, joints, 3]` flattened) of plausible `kind`s.
fn rows(
    npz: &mut NpzFile,
    name: &str,
    frames: Option<usize>,
    widths: &[usize],
    kind: Values,
) -> Result<(usize, usize, Vec<f32>), MotionError> {
    let path = npz.path().to_path_buf();
    let shape = npz.shape(name)?;
    let (n, width) = match shape.as_slice() {
        [n, w] => (*n, *w),
        [n, j, 3] => (*n, j * 3),
        _ => {
            return Err(MotionError::field(
                &path,
                name,
                format!("has shape {shape:?}, expected (frames, values)"),
            ));
        }
    };
    if n > MAX_FRAMES {
        return Err(MotionError::field(
            &path,
            name,
            format!("{n} frames: more than f3g reads ({MAX_FRAMES})"),
        ));
    }
    if let Some(f) = frames
        && f != n
    {
        return Err(MotionError::field(
            &path,
            name,
            format!("has {n} frames where the motion has {f}"),
        ));
    }
    if !widths.contains(&width) {
        return Err(MotionError::field(
            &path,
            name,
            format!("has {width} values per frame, expected one of {widths:?}"),
        ));
    }
    let (_, values) = npz.f32(name)?;
    check_values(&path, name, &values, width, kind)?;
    Ok((n, width, values))
}

/// A scalar (or one-element array), such as a frame rate.
fn scalar(npz: &mut NpzFile, name: &str) -> Result<f32, MotionError> {
    let path = npz.path().to_path_buf();
    let (shape, values) = npz.f32(name)?;
    match values.as_slice() {
        [v] if v.is_finite() => Ok(*v),
        _ => Err(MotionError::field(
            &path,
            name,
            format!("expected one finite number, found shape {shape:?}"),
        )),
    }
}

/// The shape coefficients: `(B,)` or `(F, B)` (row 0).
fn betas(npz: &mut NpzFile, name: &str) -> Result<Vec<f32>, MotionError> {
    let path = npz.path().to_path_buf();
    if !npz.contains(name) {
        return Ok(Vec::new());
    }
    let (shape, values) = npz.f32(name)?;
    let values = match shape.as_slice() {
        [n] => values[..*n].to_vec(),
        [_, n] if !values.is_empty() => values[..*n].to_vec(),
        _ => {
            return Err(MotionError::field(
                &path,
                name,
                format!("has shape {shape:?}, expected (B,) or (F, B)"),
            ));
        }
    };
    if values.iter().any(|v| !v.is_finite()) {
        return Err(MotionError::field(&path, name, "holds a non-finite value"));
    }
    Ok(values)
}

/// Parameters in SMPL-X's layout from a full pose row of any family's width.
fn layout(
    poses: &[f32],
    width: usize,
    frames: usize,
    transl: Vec<f32>,
    betas: Vec<f32>,
) -> SmplParams {
    let mut p = SmplParams {
        frames,
        betas,
        global_orient: Vec::with_capacity(3 * frames),
        transl,
        jaw_pose: vec![0.0; 3 * frames],
        leye_pose: vec![0.0; 3 * frames],
        reye_pose: vec![0.0; 3 * frames],
        body_pose: Vec::with_capacity(63 * frames),
        left_hand_pose: vec![0.0; 45 * frames],
        right_hand_pose: vec![0.0; 45 * frames],
        expression: Vec::new(),
    };
    for f in 0..frames {
        let row = &poses[f * width..(f + 1) * width];
        p.global_orient.extend(&row[0..3]);
        p.body_pose.extend(&row[3..66]);
        let hands = match width {
            156 => Some(66),
            165 => {
                p.jaw_pose[3 * f..3 * f + 3].copy_from_slice(&row[66..69]);
                p.leye_pose[3 * f..3 * f + 3].copy_from_slice(&row[69..72]);
                p.reye_pose[3 * f..3 * f + 3].copy_from_slice(&row[72..75]);
                Some(75)
            }
            _ => None,
        };
        if let Some(h) = hands {
            p.left_hand_pose[45 * f..45 * f + 45].copy_from_slice(&row[h..h + 45]);
            p.right_hand_pose[45 * f..45 * f + 45].copy_from_slice(&row[h + 45..h + 90]);
        }
    }
    p
}

/// An AMASS `.npz`: `poses` `(F, 72 | 156 | 165)` (SMPL, SMPL-H, SMPL-X), `trans` `(F, 3)`,
/// `betas`, `mocap_framerate` or `mocap_frame_rate`. Z up.
pub(crate) fn read_amass(path: &Path) -> Result<Motion, MotionError> {
    let mut npz = f3g_io::Npz::open(path)?;
    let (frames, width, poses) = rows(&mut npz, "poses", None, &[72, 156, 165], Values::Angles)?;
    let (_, _, transl) = rows(&mut npz, "trans", Some(frames), &[3], Values::Metres)?;
    let fps = match ["mocap_framerate", "mocap_frame_rate"]
        .into_iter()
        .find(|k| npz.contains(k))
    {
        Some(key) => scalar(&mut npz, key)?,
        None => {
            return Err(MotionError::file(
                path,
                "an AMASS file needs its frame rate: `mocap_framerate` or `mocap_frame_rate`",
            ));
        }
    };
    let family = match width {
        72 => SmplFamily::Smpl,
        156 => SmplFamily::SmplH,
        _ => SmplFamily::SmplX,
    };
    let betas = betas(&mut npz, "betas")?;
    let params = layout(&poses, width, frames, transl, betas);
    motion_of(&params, family, fps, Up::Z, path)
}

/// A Meshcapade `.smpl` file (`smplcodec`): `bodyPose` `(F, 22, 3)` with the global
/// orientation first, `headPose` `(F, 3, 3)` (jaw, eyes), `leftHandPose`/`rightHandPose`
/// `(F, 15, 3)`, `bodyTranslation` `(F, 3)`, `frameRate`, `shapeParameters`,
/// `expressionParameters`. Y up. A file without `frameCount` is one still body.
pub(crate) fn read_smpl_codec(path: &Path) -> Result<Motion, MotionError> {
    let mut npz = f3g_io::Npz::open(path)?;
    let (frames, _, body) = rows(&mut npz, "bodyPose", None, &[66], Values::Angles)?;
    let transl = if npz.contains("bodyTranslation") {
        rows(
            &mut npz,
            "bodyTranslation",
            Some(frames),
            &[3],
            Values::Metres,
        )?
        .2
    } else {
        vec![0.0; 3 * frames]
    };
    let fps = if npz.contains("frameRate") {
        scalar(&mut npz, "frameRate")?
    } else {
        30.0
    };
    let mut optional = |name: &str, width: usize| -> Result<Option<Vec<f32>>, MotionError> {
        if npz.contains(name) {
            Ok(Some(
                rows(&mut npz, name, Some(frames), &[width], Values::Angles)?.2,
            ))
        } else {
            Ok(None)
        }
    };
    let head = optional("headPose", 9)?;
    let left = optional("leftHandPose", 45)?;
    let right = optional("rightHandPose", 45)?;
    let family = if head.is_some() {
        SmplFamily::SmplX
    } else if left.is_some() {
        SmplFamily::SmplH
    } else {
        SmplFamily::Smpl
    };
    let mut poses = Vec::with_capacity(frames * 165);
    for f in 0..frames {
        poses.extend(&body[66 * f..66 * f + 66]);
        match &head {
            Some(h) => poses.extend(&h[9 * f..9 * f + 9]),
            None => poses.extend([0.0; 9]),
        }
        for hand in [&left, &right] {
            match hand {
                Some(h) => poses.extend(&h[45 * f..45 * f + 45]),
                None => poses.extend([0.0; 45]),
            }
        }
    }
    let betas = betas(&mut npz, "shapeParameters")?;
    let mut params = layout(&poses, 165, frames, transl, betas);
    if npz.contains("expressionParameters") {
        let shape = npz.shape("expressionParameters")?;
        let width = shape.get(1).copied().unwrap_or(0);
        params.expression = rows(
            &mut npz,
            "expressionParameters",
            Some(frames),
            &[width],
            Values::Coefficients,
        )?
        .2;
    }
    motion_of(&params, family, fps, Up::Y, path)
}

/// An `smpl_params.npz` (AvatarReX, THuman4.0: SMPL-X, Y up). No frame rate is stored: 30.
pub(crate) fn read_smpl_params(path: &Path) -> Result<Motion, MotionError> {
    let params = f3g_rig::smplx::read_params(path)?;
    if params.frames > MAX_FRAMES {
        return Err(MotionError::file(path, "more frames than f3g reads"));
    }
    for (name, values, width) in [
        ("global_orient", &params.global_orient, 3),
        ("body_pose", &params.body_pose, 63),
        ("jaw_pose", &params.jaw_pose, 3),
        ("leye_pose", &params.leye_pose, 3),
        ("reye_pose", &params.reye_pose, 3),
        ("left_hand_pose", &params.left_hand_pose, 45),
        ("right_hand_pose", &params.right_hand_pose, 45),
    ] {
        check_values(path, name, values, width, Values::Angles)?;
    }
    check_values(path, "transl", &params.transl, 3, Values::Metres)?;
    motion_of(&params, SmplFamily::SmplX, 30.0, Up::Y, path)
}
