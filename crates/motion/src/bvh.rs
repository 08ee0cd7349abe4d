//! BVH (Biovision hierarchy): the motion-capture libraries' text format.
//!
//! Reading: every `ROOT`/`JOINT` is a joint (`End Site`s are not), named by the rest of its
//! line (names with spaces, as 3ds Max's `Bip01 L Thigh`); a joint's rotation is the
//! product of its rotation channels in the order listed (`Zrotation Xrotation Yrotation` is
//! `Rz · Rx · Ry`), in degrees; the root's position channels set its position. Position
//! channels of other joints are read and ignored (the skeleton's offsets are kept). BVH rest
//! frames are world-aligned. The up axis is the one (Y or Z) along which the rest skeleton is
//! longest (retargeting checks it against the frames, [`crate::rest`]); the unit is metres for
//! a skeleton whose largest extent is under 10 units, millimetres above 300, centimetres
//! between (the extent along any axis: a rest whose bones all lie along X, as LAFAN1's, is as
//! large as a standing one); a skeleton of zero length is refused. Sizes are bounded before
//! allocating: frames by [`crate::MAX_FRAMES`] and by the values the file holds, joints by
//! [`crate::MAX_JOINTS`]; rotations by [`crate::MAX_ANGLE_DEGREES`]. A UTF-8 byte-order mark
//! is skipped.
//!
//! Writing: `Xposition Yposition Zposition` on the root, `Zrotation Yrotation Xrotation` on
//! every joint (so `R = Rz · Ry · Rx`, f3g's own Euler order), degrees to 6 decimals.

use std::fmt::Write as _;
use std::path::Path;

use glam::{Quat, Vec3};

use f3g_rig::{Joint, Skeleton};

use crate::{MAX_ANGLE_DEGREES, MAX_FRAMES, MAX_JOINTS, Motion, MotionError, Up};

#[derive(Clone, Copy, Debug, PartialEq)]
enum Channel {
    Position(usize),
    Rotation(usize),
}

/// Whitespace-separated tokens with their line numbers.
struct Tokens<'a> {
    words: std::iter::Peekable<Box<dyn Iterator<Item = (usize, &'a str)> + 'a>>,
    path: &'a Path,
    last_line: usize,
}

impl<'a> Tokens<'a> {
    fn next(&mut self, expected: &str) -> Result<&'a str, MotionError> {
        match self.words.next() {
            Some((line, w)) => {
                self.last_line = line;
                Ok(w)
            }
            None => Err(MotionError::line(
                self.path,
                self.last_line,
                format!("the file ends where {expected} was expected"),
            )),
        }
    }

    /// A joint's name: the words up to the end of its line, or to a `{` on it, joined by single
    /// spaces (3ds Max's `Bip01 L Thigh`; Blender reads names so too).
    fn name(&mut self) -> Result<String, MotionError> {
        let mut name = self.next("a joint name")?.to_string();
        while let Some(&(line, w)) = self.words.peek()
            && line == self.last_line
            && w != "{"
        {
            name.push(' ');
            name.push_str(w);
            self.words.next();
        }
        Ok(name)
    }

    fn expect(&mut self, word: &str) -> Result<(), MotionError> {
        let w = self.next(&format!("`{word}`"))?;
        if w.eq_ignore_ascii_case(word) {
            Ok(())
        } else {
            Err(self.error(format!("expected `{word}`, found {}", f3g_io::quoted(w))))
        }
    }

    fn number(&mut self, what: &str) -> Result<f32, MotionError> {
        Ok(self.number_as_written(what)?.0)
    }

    /// A number and its text as the file writes it (for messages: `1e-300` is not `0`).
    fn number_as_written(&mut self, what: &str) -> Result<(f32, &'a str), MotionError> {
        let w = self.next(what)?;
        match w.parse::<f32>() {
            Ok(v) if v.is_finite() => Ok((v, w)),
            _ => Err(self.error(format!(
                "{what}: {} is not a finite number",
                f3g_io::quoted(w)
            ))),
        }
    }

    fn error(&self, reason: impl ToString) -> MotionError {
        MotionError::line(self.path, self.last_line, reason)
    }
}

/// Parses a BVH file's bytes (module docs); `path` names it in errors.
pub fn parse_bvh(bytes: &[u8], path: &Path) -> Result<Motion, MotionError> {
    let text = std::str::from_utf8(bytes)
        .map_err(|e| MotionError::file(path, format!("not a text file (BVH is text): {e}")))?;
    // Windows editors start UTF-8 text with a byte-order mark.
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let words: Box<dyn Iterator<Item = (usize, &str)> + '_> = Box::new(
        text.lines()
            .enumerate()
            .flat_map(|(i, l)| l.split_whitespace().map(move |w| (i + 1, w))),
    );
    let mut t = Tokens {
        words: words.peekable(),
        path,
        last_line: 1,
    };
    t.expect("HIERARCHY")?;
    let mut joints: Vec<Joint> = Vec::new();
    let mut channels: Vec<Vec<Channel>> = Vec::new();
    // Open braces: the joint each belongs to (None for an End Site).
    let mut stack: Vec<Option<usize>> = Vec::new();
    loop {
        let w = t.next("a joint or `MOTION`")?;
        match w {
            "ROOT" | "JOINT" => {
                if (w == "ROOT") != stack.is_empty() {
                    return Err(t.error(format!(
                        "{} where a {} was expected",
                        f3g_io::quoted(w),
                        if stack.is_empty() { "ROOT" } else { "JOINT" }
                    )));
                }
                if joints.len() >= MAX_JOINTS {
                    return Err(t.error(format!("more than {MAX_JOINTS} joints")));
                }
                let name = t.name()?;
                let parent = match stack.last() {
                    Some(Some(p)) => Some(*p),
                    Some(None) => return Err(t.error("a joint inside an End Site")),
                    None => None,
                };
                t.expect("{")?;
                t.expect("OFFSET")?;
                let offset = Vec3::new(
                    t.number("OFFSET x")?,
                    t.number("OFFSET y")?,
                    t.number("OFFSET z")?,
                );
                t.expect("CHANNELS")?;
                let count = t.number("the channel count")?;
                if !(0.0..=6.0).contains(&count) || count.fract() != 0.0 {
                    return Err(t.error(format!("{count} channels: expected 0 to 6")));
                }
                let mut list = Vec::new();
                for _ in 0..count as usize {
                    let c = t.next("a channel")?;
                    let axis = match c.as_bytes().first().map(u8::to_ascii_lowercase) {
                        Some(b'x') => 0,
                        Some(b'y') => 1,
                        Some(b'z') => 2,
                        _ => return Err(t.error(format!("unknown channel `{c}`"))),
                    };
                    list.push(match c[1..].to_ascii_lowercase().as_str() {
                        "position" => Channel::Position(axis),
                        "rotation" => Channel::Rotation(axis),
                        _ => return Err(t.error(format!("unknown channel `{c}`"))),
                    });
                }
                stack.push(Some(joints.len()));
                joints.push(Joint {
                    name,
                    parent,
                    offset,
                    pre_rotation: Quat::IDENTITY,
                });
                channels.push(list);
            }
            "End" => {
                t.expect("Site")?;
                t.expect("{")?;
                t.expect("OFFSET")?;
                for axis in ["x", "y", "z"] {
                    t.number(&format!("End Site OFFSET {axis}"))?;
                }
                stack.push(None);
            }
            "}" => {
                if stack.pop().is_none() {
                    return Err(t.error("`}` without a matching `{`"));
                }
            }
            "MOTION" if stack.is_empty() && !joints.is_empty() => break,
            _ => return Err(t.error(format!("unexpected {}", f3g_io::quoted(w)))),
        }
    }
    t.expect("Frames:")?;
    let (frames, written) = t.number_as_written("the frame count")?;
    if !(1.0..=MAX_FRAMES as f32).contains(&frames) || frames.fract() != 0.0 {
        return Err(t.error(format!(
            "{} frames: expected a whole number from 1 to {MAX_FRAMES}",
            f3g_io::quoted(written)
        )));
    }
    let frames = frames as usize;
    t.expect("Frame")?;
    t.expect("Time:")?;
    let (frame_time, written) = t.number_as_written("the frame time")?;
    if !(frame_time > 1e-4 && frame_time <= 10.0) {
        return Err(t.error(format!(
            "frame time {} s: expected between 0.0001 and 10 seconds",
            f3g_io::quoted(written)
        )));
    }
    let per_frame: usize = channels.iter().map(Vec::len).sum();
    let skeleton = Skeleton::new(joints).map_err(|e| MotionError::file(path, e))?;
    let n = skeleton.len();
    let mut rotations = Vec::new();
    let mut root_translation = Vec::new();
    let mut values = vec![0.0f32; per_frame];
    for f in 0..frames {
        for (k, v) in values.iter_mut().enumerate() {
            *v = t.number(&format!("frame {f}, channel {k}"))?;
        }
        let mut k = 0;
        let mut root = Vec3::ZERO;
        for (j, list) in channels.iter().enumerate() {
            let mut rotation = Quat::IDENTITY;
            let mut position = skeleton.joints()[j].offset;
            for c in list {
                match *c {
                    Channel::Position(axis) => position[axis] = values[k],
                    Channel::Rotation(axis) => {
                        if values[k].abs() > MAX_ANGLE_DEGREES {
                            return Err(t.error(format!(
                                "frame {f}, channel {k} (joint `{}`): rotation {}° is beyond ±{MAX_ANGLE_DEGREES}°",
                                skeleton.joints()[j].name, values[k]
                            )));
                        }
                        let angle = values[k].to_radians();
                        rotation *= match axis {
                            0 => Quat::from_rotation_x(angle),
                            1 => Quat::from_rotation_y(angle),
                            _ => Quat::from_rotation_z(angle),
                        };
                    }
                }
                k += 1;
            }
            if j == 0 {
                root = position - skeleton.joints()[0].offset;
            }
            rotations.push(rotation.normalize());
        }
        root_translation.push(root);
        debug_assert_eq!(rotations.len(), (f + 1) * n);
    }
    if let Some((line, w)) = t.words.next() {
        return Err(MotionError::line(
            path,
            line,
            format!(
                "{} after the {frames} frames the header announces",
                f3g_io::quoted(w)
            ),
        ));
    }
    let (up, metres_per_unit) = infer_up_and_units(&skeleton);
    let motion = Motion {
        skeleton,
        rotations,
        root_translation,
        // Frame times are written rounded (0.0333333): a rate that close to whole is whole.
        fps: {
            let fps = 1.0 / frame_time;
            if (fps - fps.round()).abs() < 1e-4 * fps {
                fps.round()
            } else {
                fps
            }
        },
        metres_per_unit,
        up,
        smpl: None,
    };
    crate::check_values(&motion, path)?;
    Ok(motion)
}

/// The up axis and unit of a rest skeleton (module docs).
fn infer_up_and_units(skeleton: &Skeleton) -> (Up, f32) {
    let rest = skeleton.rest(None);
    let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
    for s in &rest {
        lo = lo.min(s.translation);
        hi = hi.max(s.translation);
    }
    let extent = (hi - lo).max(Vec3::ZERO);
    let up = if extent.z > extent.y { Up::Z } else { Up::Y };
    let size = extent.max_element();
    let unit = if size > 300.0 {
        0.001
    } else if size > 10.0 {
        0.01
    } else {
        1.0
    };
    (up, unit)
}

/// Writes a motion whose rest frames are world-aligned (as BVH needs; [`crate::retarget`]'s
/// exports are) as BVH text.
pub fn write_bvh(motion: &Motion) -> Result<String, String> {
    let joints = motion.skeleton.joints();
    if let Some(j) = joints.iter().find(|j| j.pre_rotation != Quat::IDENTITY) {
        return Err(format!(
            "joint `{}` has a rest rotation, which BVH cannot hold",
            j.name
        ));
    }
    // A name is read back as the rest of its line with single spaces, up to a `{`.
    let readable = |n: &str| {
        !n.is_empty() && !n.contains('{') && n.split_whitespace().collect::<Vec<_>>().join(" ") == n
    };
    if let Some(j) = joints.iter().find(|j| !readable(&j.name)) {
        return Err(format!(
            "joint name {} cannot be written to BVH (empty, a `{{`, or whitespace other than \
             single spaces between words)",
            f3g_io::quoted(&j.name)
        ));
    }
    let mut out = String::from("HIERARCHY\n");
    let children = |p: usize| (0..joints.len()).filter(move |&c| joints[c].parent == Some(p));
    fn write_joint(
        out: &mut String,
        joints: &[Joint],
        children: &dyn Fn(usize) -> Vec<usize>,
        j: usize,
        depth: usize,
    ) {
        let pad = "  ".repeat(depth);
        let kind = if joints[j].parent.is_none() {
            "ROOT"
        } else {
            "JOINT"
        };
        let o = joints[j].offset;
        let _ = writeln!(out, "{pad}{kind} {}\n{pad}{{", joints[j].name);
        let _ = writeln!(out, "{pad}  OFFSET {} {} {}", o.x, o.y, o.z);
        if joints[j].parent.is_none() {
            let _ = writeln!(
                out,
                "{pad}  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation"
            );
        } else {
            let _ = writeln!(out, "{pad}  CHANNELS 3 Zrotation Yrotation Xrotation");
        }
        let kids = children(j);
        if kids.is_empty() {
            let _ = writeln!(
                out,
                "{pad}  End Site\n{pad}  {{\n{pad}    OFFSET 0 0 0\n{pad}  }}"
            );
        }
        for c in kids {
            write_joint(out, joints, children, c, depth + 1);
        }
        let _ = writeln!(out, "{pad}}}");
    }
    let children = |p: usize| children(p).collect::<Vec<_>>();
    for root in (0..joints.len()).filter(|&j| joints[j].parent.is_none()) {
        if root != 0 {
            return Err("BVH holds one root joint; this skeleton has several".into());
        }
        write_joint(&mut out, joints, &children, root, 0);
    }
    // Frame order must follow the hierarchy's depth-first order, which parents-first storage
    // does not guarantee.
    let mut order = Vec::with_capacity(joints.len());
    fn visit(j: usize, children: &dyn Fn(usize) -> Vec<usize>, order: &mut Vec<usize>) {
        order.push(j);
        for c in children(j) {
            visit(c, children, order);
        }
    }
    visit(0, &children, &mut order);
    let _ = writeln!(
        out,
        "MOTION\nFrames: {}\nFrame Time: {:.9}",
        motion.frames(),
        1.0 / motion.fps
    );
    for f in 0..motion.frames() {
        let p = joints[0].offset + motion.root_translation[f];
        let mut line = format!("{} {} {}", p.x, p.y, p.z);
        for &j in &order {
            let (z, y, x) = crate::euler_zyx_degrees(motion.frame(f)[j]);
            let _ = write!(line, " {z:.6} {y:.6} {x:.6}");
        }
        out.push_str(&line);
        out.push('\n');
    }
    Ok(out)
}
