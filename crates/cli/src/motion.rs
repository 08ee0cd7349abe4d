//! `f3g motion`: motions from other tools onto a body model, and f3g's motions out to them.
//! `--joint-map` ([`RetargetArgs`]) is flattened into every command that takes `--motion`.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand, ValueEnum};
use f3g_motion::rest::up_to_y;
use f3g_motion::{RetargetOptions, Retargeted};
use f3g_rig::{ModelSpec, RoleMap};

/// How a motion of another skeleton maps onto the avatar's body model.
#[derive(Args, Debug, Clone, Default)]
pub struct RetargetArgs {
    /// Roles of the motion's joints, over those inferred from their names: a JSON object from
    /// roles (pelvis, left_hip, …) to the motion's joint names (`f3g motion convert
    /// --save-map` writes the inferred one to edit).
    #[arg(long)]
    pub joint_map: Option<PathBuf>,
    /// The motion's pose its rotations are taken relative to: `auto` (its file's rest pose
    /// where the body stands in it, else the frame that stands best, with the up axis that
    /// stands it), `file-rest`, `first-frame`, or `t-pose` (the file's rest with the trunk
    /// up, legs down and arms out sideways: for a rest in a crouch and frames that never stand).
    #[arg(
        long,
        default_value = "auto",
        value_name = "auto|file-rest|first-frame|t-pose"
    )]
    pub rest: f3g_motion::RestChoice,
    /// Keep planted feet from sliding: where the motion's foot is down and still, the root is
    /// shifted horizontally so that the body's foot stays where it was planted.
    #[arg(long)]
    pub lock_feet: bool,
}

impl RetargetArgs {
    /// Retargeting options resampling to `fps`.
    pub fn options(&self, fps: Option<f32>) -> Result<RetargetOptions> {
        let joint_map = match &self.joint_map {
            Some(p) => Some(RoleMap::read(p)?),
            None => None,
        };
        Ok(RetargetOptions {
            joint_map,
            fps,
            identity: Vec::new(),
            rest: self.rest,
            lock_feet: self.lock_feet,
        })
    }
}

/// `--frames START..END` of a motion, flattened into the commands that read one.
#[derive(Args, Debug, Clone, Default)]
pub struct FramesArg {
    /// Only the motion's frames START..END (end exclusive; `..END` and `START..` too), counted
    /// at the rate the command uses (after --fps).
    #[arg(long, value_name = "START..END")]
    pub frames: Option<String>,
}

impl FramesArg {
    /// The frames of `len` that the flag keeps (all without it).
    pub fn range(&self, len: usize) -> Result<std::ops::Range<usize>> {
        match &self.frames {
            Some(text) => parse_range(text, len),
            None => Ok(0..len),
        }
    }

    /// `frames` cut to the flag's range.
    pub fn cut<T>(&self, mut frames: Vec<T>) -> Result<Vec<T>> {
        let range = self.range(frames.len())?;
        frames.truncate(range.end);
        frames.drain(..range.start);
        Ok(frames)
    }
}

/// `START..END` (end exclusive; an end left out is the sequence's) inside `0..len`.
pub fn parse_range(text: &str, len: usize) -> Result<std::ops::Range<usize>> {
    let quoted = f3g_io::quoted(text);
    let (a, b) = text
        .split_once("..")
        .with_context(|| format!("--frames {quoted}: expected START..END"))?;
    let number = |t: &str, default: usize| -> Result<usize> {
        match t.trim() {
            "" => Ok(default),
            t => t.parse().with_context(|| {
                format!(
                    "--frames {quoted}: {} is not a frame number",
                    f3g_io::quoted(t)
                )
            }),
        }
    };
    let (start, end) = (number(a, 0)?, number(b, len)?);
    if start >= end || end > len {
        bail!("--frames {start}..{end} is not inside the {len} frames of the motion");
    }
    Ok(start..end)
}

/// One line on how a motion was retargeted, and the joints that drive nothing.
pub fn describe(path: &Path, r: &Retargeted, frames: usize) -> String {
    let mut text = format!(
        "{}: {frames} frames at {} fps, retargeted by {} ({} joints correspond",
        path.display(),
        r.fps,
        r.method,
        r.correspondence.len()
    );
    if r.method == "rotations" {
        text += &format!(", scale {:.3}", r.scale);
        if r.dropped_degrees > 0.5 {
            text += &format!(
                ", up to {:.1}° left out where the body model cannot turn a joint",
                r.dropped_degrees
            );
        }
    }
    text += ")";
    if r.roles_from == f3g_motion::retarget::RolesFrom::Shape {
        text += "\n  roles: from the skeleton's shape (its joint names give no hip; check the \
                 contact sheet, or name them with --joint-map)";
    }
    if let Some(reason) = r.reference.as_ref().and_then(|f| f.reason.as_ref()) {
        text += &format!("\n  reference pose: {reason}");
    }
    if let Some(floor) = &r.floor {
        text += &format!(
            "\n  floor: the motion's feet stand at {:.3} (its units, up axis); the body put on the \
             floor in the {} of {} frames where they touch it (root heights shifted by up to \
             {:+.1} cm); left: {:.1} cm above the floor in those frames, {:.1} cm below it",
            floor.source_floor,
            floor.contact_frames,
            floor.frames,
            100.0 * floor.largest_shift_m,
            100.0 * floor.largest_float_m,
            100.0 * floor.largest_penetration_m
        );
    }
    if let Some(lock) = &r.feet_locked {
        text += &format!(
            "\n  feet locked: planted in {} frames, where they slid up to {:.1} cm (now {:.1} cm); \
             the root shifted by up to {:.1} cm",
            lock.planted_frames,
            100.0 * lock.largest_slide_before_m,
            100.0 * lock.largest_slide_after_m,
            100.0 * lock.largest_shift_m
        );
    }
    for warning in r.plausibility.iter().flat_map(|p| &p.warnings) {
        text += &format!("\n  warning: {warning}");
    }
    if !r.unmatched_roles.is_empty() {
        let roles: Vec<String> = r
            .unmatched_roles
            .iter()
            .map(|(role, closest)| match closest.is_empty() {
                true => role.name(),
                false => format!("{} (closest: {})", role.name(), closest.join(", ")),
            })
            .collect();
        text += &format!(
            "\n  roles without a joint in the motion (they keep their rest pose): {} — name them with --joint-map",
            roles.join(", ")
        );
    }
    text
}

/// Motions.
#[derive(Subcommand, Debug)]
pub enum MotionCommand {
    /// Retarget a motion (AMASS .npz, .smpl, smpl_params.npz, BVH, glTF, FBX) onto a body model and
    /// write it as an f3g sequence (.npz), printing the joint correspondence.
    Convert(ConvertArgs),
    /// Write a motion f3g made (a run's training poses or an f3g sequence) for other tools.
    Export(ExportArgs),
    /// A contact sheet of a motion: its skeleton (top row) and the body model it is
    /// retargeted onto (bottom row), seen from the side or front at evenly spaced frames.
    Show(ShowArgs),
}

/// Options of `f3g motion show`.
#[derive(Args, Debug)]
pub struct ShowArgs {
    /// The motion file.
    pub input: PathBuf,
    /// Body model to retarget onto: builtin, smplx:MODEL.npz, mhr:DIR or gltf:FILE.
    #[arg(long, default_value = "builtin")]
    pub to: ModelSpec,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
    /// Frames shown (columns), 1–64.
    #[arg(long, default_value_t = 8, value_parser = crate::bounds::size::<1, 64>)]
    pub columns: usize,
    /// Side of one panel in pixels, 32–1024.
    #[arg(long, default_value_t = 200, value_parser = crate::bounds::size::<32, 1024>)]
    pub panel: usize,
    /// Seen from the front (x, y) or from the left side (z, y: strides and bends).
    #[arg(long, value_enum, default_value = "side")]
    pub view: View,
    #[command(flatten)]
    pub retarget: RetargetArgs,
    #[command(flatten)]
    pub frames: FramesArg,
}

/// Where `f3g motion show` looks from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum View {
    Front,
    Side,
}

impl View {
    /// A point's (right, up) on the sheet.
    fn project(self, p: glam::Vec3) -> glam::Vec2 {
        match self {
            View::Front => glam::Vec2::new(p.x, p.y),
            View::Side => glam::Vec2::new(p.z, p.y),
        }
    }
}

/// Options of `f3g motion convert`.
#[derive(Args, Debug)]
pub struct ConvertArgs {
    /// The motion file.
    pub input: PathBuf,
    /// Body model to drive: builtin, smplx:MODEL.npz, mhr:DIR or gltf:FILE.
    #[arg(long, default_value = "builtin")]
    pub to: ModelSpec,
    /// Output f3g sequence (.npz).
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub retarget: RetargetArgs,
    #[command(flatten)]
    pub frames: FramesArg,
    /// Resample to this frame rate (default: the file's).
    #[arg(long)]
    pub fps: Option<f32>,
    /// Also write the motion's joint roles (inferred, or --joint-map's) as an editable
    /// --joint-map file.
    #[arg(long)]
    pub save_map: Option<PathBuf>,
    /// Also write the correspondence and retargeting summary as JSON.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Retarget onto this body model first (e.g. smplx:SMPLX_NEUTRAL.npz for an AMASS file:
    /// parameter for parameter), then fit --to's model to its posed vertices frame by frame,
    /// as `f3g rig fit` does: slower, but the body's surface is matched, not only its joints.
    #[arg(long)]
    pub via: Option<ModelSpec>,
    /// Levenberg–Marquardt iterations per frame of the --via fit, 1–1000.
    #[arg(long, default_value_t = 50, value_parser = crate::bounds::size::<1, 1000>)]
    pub iterations: usize,
}

/// Formats `f3g motion export` writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum ExportFormat {
    /// Biovision hierarchy: the body model's skeleton, world-aligned rest frames, metres.
    Bvh,
    /// A glTF binary with the skeleton under a skin and one animation (no mesh).
    Glb,
    /// An ASCII FBX 7.4 file: the skeleton as bones and one animation stack.
    Fbx,
}

/// Options of `f3g motion export`.
#[derive(Args, Debug)]
pub struct ExportArgs {
    /// A run folder (its training poses) or an f3g sequence (.npz, naming its body model).
    pub input: PathBuf,
    /// File format.
    #[arg(long, value_enum, default_value = "bvh")]
    pub format: ExportFormat,
    /// Output file.
    #[arg(long)]
    pub out: PathBuf,
    /// Frame rate written to the file.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f32,
}

pub fn run(cmd: &MotionCommand) -> Result<()> {
    match cmd {
        MotionCommand::Convert(a) => convert(a),
        MotionCommand::Export(a) => export(a),
        MotionCommand::Show(a) => show(a),
    }
}

fn convert(a: &ConvertArgs) -> Result<()> {
    let options = a.retarget.options(a.fps)?;
    let rig = a.to.load()?;
    let via = a.via.as_ref().map(|m| m.load()).transpose()?;
    let motion = f3g_motion::read(&a.input)?;
    let mut r = f3g_motion::retarget(&motion, via.as_ref().unwrap_or(&rig), &options, &a.input)?;
    r.frames = a.frames.cut(std::mem::take(&mut r.frames))?;
    eprintln!("{}", describe(&a.input, &r, r.frames.len()));
    for c in &r.correspondence {
        let by = match c.by {
            f3g_motion::retarget::Matched::Role(role) => role.name(),
            f3g_motion::retarget::Matched::Name => "same name".into(),
        };
        eprintln!("  {:<24} ← {:<28} ({by})", c.target, c.source);
    }
    if !r.unmatched_source.is_empty() {
        eprintln!(
            "  motion joints that drive nothing: {}",
            r.unmatched_source.join(", ")
        );
    }
    if let Some(p) = &a.save_map {
        let json = serde_json::to_string_pretty(&r.source_roles)?;
        f3g_io::write_atomic(p, format!("{json}\n").as_bytes())?;
        eprintln!("wrote the joint map {}", p.display());
    }
    if let Some(p) = &a.report {
        let json = serde_json::to_string_pretty(&r)?;
        f3g_io::write_atomic(p, format!("{json}\n").as_bytes())?;
    }
    let frames = match &via {
        Some(source) => fit_onto(source, &r.frames, &rig, a.iterations)?,
        None => r.frames,
    };
    f3g_rig::sequence::write(&a.out, &rig, &frames)?;
    eprintln!(
        "wrote {} ({} frames for {})",
        a.out.display(),
        frames.len(),
        rig.name
    );
    Ok(())
}

/// `model`'s parameters fitted to `source` posed by each of `frames` (`motion convert --via`).
fn fit_onto(
    source: &f3g_rig::Rig,
    frames: &[f3g_rig::RigParams],
    model: &f3g_rig::Rig,
    iterations: usize,
) -> Result<Vec<f3g_rig::RigParams>> {
    use f3g_rig::fit::{Correspondence, FitOptions, fit_sequence};
    let correspondence = Correspondence::between(source, model);
    eprintln!(
        "fitting {} to {} frame by frame ({} correspondence)",
        model.name,
        source.name,
        correspondence.describe()
    );
    let bar = indicatif::ProgressBar::new(frames.len() as u64).with_style(
        indicatif::ProgressStyle::with_template(
            "{bar:30} {pos}/{len} frames {msg} [{elapsed} < {eta}]",
        )?,
    );
    let options = FitOptions {
        max_iterations: iterations,
        ..Default::default()
    };
    let fitted = fit_sequence(source, frames, model, &correspondence, &options, |r| {
        bar.set_message(format!("vertex RMS {:.1} mm", r.vertex_rms * 1e3));
        bar.inc(1);
    })
    .context("fitting the --via model's vertices")?;
    bar.finish_and_clear();
    eprintln!(
        "  residuals: mean vertex RMS {:.2} mm, worst {:.2} mm (frame {})",
        fitted.mean_vertex_rms * 1e3,
        fitted.worst.0 * 1e3,
        fitted.worst.1
    );
    Ok(fitted.frames)
}

fn export(a: &ExportArgs) -> Result<()> {
    if !(a.fps.is_finite() && a.fps > 0.0 && a.fps <= 1000.0) {
        bail!("--fps {}: expected between 0 and 1000", a.fps);
    }
    let (rig, frames) = if a.input.is_dir() {
        let model = a.input.join("body_model.npz");
        let rig = f3g_rig::file::read(&model).with_context(|| {
            format!(
                "{} is not a run folder that stores its body model",
                a.input.display()
            )
        })?;
        let frames = f3g_rig::sequence::read(&a.input.join("poses.npz"), &rig)?;
        (rig, frames)
    } else {
        let model = sequence_model(&a.input)?;
        let rig = model.load()?;
        let frames = f3g_rig::sequence::read(&a.input, &rig)?;
        (rig, frames)
    };
    let motion = f3g_motion::from_rig(&rig, &frames, a.fps)?;
    match a.format {
        ExportFormat::Bvh => {
            let text = f3g_motion::write_bvh(&motion).map_err(anyhow::Error::msg)?;
            f3g_io::write_atomic(&a.out, text.as_bytes())?;
        }
        ExportFormat::Glb => f3g_io::write_atomic(&a.out, &f3g_motion::write_gltf(&motion))?,
        ExportFormat::Fbx => {
            let text = f3g_motion::write_fbx(&motion).map_err(anyhow::Error::msg)?;
            f3g_io::write_atomic(&a.out, text.as_bytes())?;
        }
    }
    eprintln!(
        "wrote {} ({} frames of {} joints at {} fps)",
        a.out.display(),
        frames.len(),
        rig.skeleton.len(),
        a.fps
    );
    Ok(())
}

/// The body model an f3g sequence names.
fn sequence_model(path: &Path) -> Result<ModelSpec> {
    let text = f3g_rig::sequence::model_of(path).with_context(|| {
        format!(
            "{}: not an f3g sequence; export takes a run folder or an f3g .npz",
            path.display()
        )
    })?;
    text.parse::<ModelSpec>()
        .map_err(|e| anyhow::anyhow!("{}: `model`: {e}", path.display()))
}

fn show(a: &ShowArgs) -> Result<()> {
    let options = a.retarget.options(None)?;
    let rig = a.to.load()?;
    let motion = f3g_motion::read(&a.input)?;
    let r = f3g_motion::retarget(&motion, &rig, &options, &a.input)?;
    eprintln!("{}", describe(&a.input, &r, r.frames.len()));
    let range = a.frames.range(r.frames.len())?;
    let n = range.len();
    let columns = a.columns.min(n);
    let picked: Vec<usize> = (0..columns)
        .map(|k| range.start + k * (n - 1) / (columns - 1).max(1))
        .collect();
    let parents = |s: &f3g_rig::Skeleton| -> Vec<Option<usize>> {
        s.joints().iter().map(|j| j.parent).collect()
    };
    // The source stood up by the up axis retargeting used (its reference pose's: LAFAN1's
    // rest lies along +X and its file's axes say Z), not the one read from the rest alone.
    let up = r.reference.as_ref().map_or(motion.up, |f| f.up);
    let turn = up_to_y(up) * up_to_y(motion.up).inverse();
    let source: Vec<Vec<glam::Vec3>> = picked
        .iter()
        .map(|&f| motion.positions(f).into_iter().map(|p| turn * p).collect())
        .collect();
    let target: Vec<Vec<glam::Vec3>> = picked
        .iter()
        .map(|&f| {
            rig.joint_world(&r.frames[f])
                .map(|w| w.iter().map(|s| s.translation).collect())
        })
        .collect::<Result<_, _>>()?;
    let side = a.panel;
    let mut sheet = f3g_io::Image::filled(side * picked.len(), 2 * side, 3, 1.0);
    for (row, (poses, parents, colour)) in [
        (&source, parents(&motion.skeleton), [0.15, 0.3, 0.75]),
        (&target, parents(&rig.skeleton), [0.85, 0.4, 0.1]),
    ]
    .into_iter()
    .enumerate()
    {
        // One scale per row (its largest pose), so the panels compare; each pose centred in
        // its panel.
        let extent = poses
            .iter()
            .map(|pose| {
                let (a, b) = bounds(pose, a.view);
                (b - a).max_element()
            })
            .fold(1e-6f32, f32::max);
        let scale = 0.9 * side as f32 / extent;
        for (column, pose) in poses.iter().enumerate() {
            let (lo, hi) = bounds(pose, a.view);
            let centre = 0.5 * (lo + hi);
            let to_pixel = |p: glam::Vec3| {
                let q = (a.view.project(p) - centre) * scale;
                glam::Vec2::new(
                    (column * side) as f32 + 0.5 * side as f32 + q.x,
                    (row * side) as f32 + 0.5 * side as f32 - q.y,
                )
            };
            for (j, parent) in parents.iter().enumerate() {
                if let Some(p) = parent {
                    draw_line(&mut sheet, to_pixel(pose[*p]), to_pixel(pose[j]), colour);
                }
            }
        }
    }
    f3g_io::write_png(&a.out, &sheet)?;
    eprintln!(
        "wrote {} (frames {:?}; top: the motion's skeleton, bottom: {})",
        a.out.display(),
        picked,
        rig.name
    );
    Ok(())
}

/// The corners of a pose's bounding box in `view`.
fn bounds(pose: &[glam::Vec3], view: View) -> (glam::Vec2, glam::Vec2) {
    pose.iter().fold(
        (glam::Vec2::splat(f32::MAX), glam::Vec2::splat(f32::MIN)),
        |(a, b), p| (a.min(view.project(*p)), b.max(view.project(*p))),
    )
}

/// A two-pixel-wide line.
fn draw_line(img: &mut f3g_io::Image, a: glam::Vec2, b: glam::Vec2, colour: [f32; 3]) {
    let steps = (a.distance(b) * 2.0).ceil().max(1.0) as usize;
    for k in 0..=steps {
        let p = a.lerp(b, k as f32 / steps as f32);
        for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            let (x, y) = (p.x as isize + dx, p.y as isize + dy);
            if x >= 0 && y >= 0 && (x as usize) < img.width && (y as usize) < img.height {
                img.pixel_mut(x as usize, y as usize)
                    .copy_from_slice(&colour);
            }
        }
    }
}
