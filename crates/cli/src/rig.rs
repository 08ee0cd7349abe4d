//! `f3g rig`: inspect body models and convert parameters between them.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use f3g_rig::fit::{Correspondence, FitOptions, default_joint_map, fit_sequence};
use f3g_rig::{ModelSpec, sequence};
use indicatif::{ProgressBar, ProgressStyle};

/// Body models.
#[derive(Subcommand, Debug)]
pub enum RigCommand {
    /// Pose a body model and write the mesh as OBJ.
    Show(ShowArgs),
    /// Convert per-frame parameters from one body model to another by fitting.
    Fit(FitArgs),
}

/// Options of `f3g rig show`.
#[derive(Args, Debug)]
pub struct ShowArgs {
    /// Body model: builtin, smplx:MODEL.npz, mhr:DIR or gltf:FILE.
    #[arg(long, default_value = "builtin")]
    pub model: ModelSpec,
    /// Parameters: a JSON file of named values, smpl_params.npz (SMPL-X) or an f3g .npz sequence.
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// Frame of a sequence file.
    #[arg(long, default_value_t = 0)]
    pub frame: usize,
    /// Output OBJ.
    #[arg(long)]
    pub out: PathBuf,
    /// Also print the model's parameter names.
    #[arg(long)]
    pub list_params: bool,
}

/// Options of `f3g rig fit`.
#[derive(Args, Debug)]
pub struct FitArgs {
    /// Model the parameters are for (e.g. smplx:SMPLX_NEUTRAL.npz).
    #[arg(long)]
    pub from: ModelSpec,
    /// Source parameters (smpl_params.npz, an f3g .npz sequence, or JSON).
    #[arg(long)]
    pub params: PathBuf,
    /// Model to fit (builtin, mhr:DIR, gltf:FILE).
    #[arg(long, default_value = "builtin")]
    pub to: ModelSpec,
    /// Output f3g parameter sequence (.npz).
    #[arg(long)]
    pub out: PathBuf,
    /// Vertex correspondence: an .npz with `triangle_ids (V,)` into the source mesh and
    /// `baryc_coords (V,3)`, one row per target-model vertex (MHR's mapping files). Without it,
    /// nearest vertices are used (or identity when the topologies match).
    #[arg(long)]
    pub correspondence: Option<PathBuf>,
    /// λ, the weight of the joint term.
    #[arg(long, default_value_t = 1.0)]
    pub joint_weight: f32,
    /// Frames to convert, as START..END (end exclusive); all by default.
    #[arg(long)]
    pub frames: Option<String>,
    /// Also fit expression coefficients (slower).
    #[arg(long)]
    pub fit_expression: bool,
    /// Levenberg–Marquardt iterations per frame.
    #[arg(long, default_value_t = 50)]
    pub iterations: usize,
}

pub fn run(cmd: &RigCommand) -> Result<()> {
    match cmd {
        RigCommand::Show(a) => show(a),
        RigCommand::Fit(a) => fit_params(a),
    }
}

fn show(a: &ShowArgs) -> Result<()> {
    let rig = a.model.load()?;
    let params = match &a.params {
        Some(p) => {
            let frames = sequence::read(p, &rig)?;
            frames.get(a.frame).cloned().with_context(|| {
                format!(
                    "{}: frame {} requested, the file has {}",
                    p.display(),
                    a.frame,
                    frames.len()
                )
            })?
        }
        None => rig.zero_params(),
    };
    let posed = rig.pose(&params)?;
    f3g_rig::obj::write_obj(&a.out, &posed.vertices, &rig.mesh.triangles)?;
    let (lo, hi) = posed
        .vertices
        .iter()
        .fold((glam::Vec3::MAX, glam::Vec3::MIN), |(l, h), v| {
            (l.min(*v), h.max(*v))
        });
    println!(
        "{}: {} vertices, {} triangles, {} joints, {} pose / {} identity / {} expression parameters; bounds {:.3?}..{:.3?}; wrote {}",
        rig.name,
        rig.mesh.vertices.len(),
        rig.mesh.triangles.len(),
        rig.skeleton.len(),
        rig.num_pose_params(),
        rig.identity.len(),
        rig.expression.len(),
        lo.to_array(),
        hi.to_array(),
        a.out.display()
    );
    if a.list_params {
        println!("pose: {}", rig.pose_param_names().join(" "));
        println!("identity: {}", rig.identity.names.join(" "));
        println!("expression: {}", rig.expression.names.join(" "));
    }
    Ok(())
}

fn fit_params(a: &FitArgs) -> Result<()> {
    let source = a.from.load()?;
    let model = a.to.load()?;
    let frames = sequence::read(&a.params, &source)?;
    let range = match &a.frames {
        Some(r) => crate::motion::parse_range(r, frames.len())?,
        None => 0..frames.len(),
    };
    let correspondence = match &a.correspondence {
        Some(path) => {
            let mut npz = f3g_io::Npz::open(path)?;
            let (_, tri) = npz.i64("triangle_ids")?;
            let (shape, bary) = npz.f32("baryc_coords")?;
            if shape.len() != 2 || shape[1] != 3 || shape[0] != tri.len() {
                bail!(
                    "{}: `baryc_coords` has shape {shape:?}, expected ({}, 3)",
                    path.display(),
                    tri.len()
                );
            }
            let faces = &source.mesh.triangles;
            let triangles = tri
                .iter()
                .map(|&t| {
                    faces.get(t as usize).copied().with_context(|| {
                        format!(
                            "{}: triangle {t} is not a face of the source mesh",
                            path.display()
                        )
                    })
                })
                .collect::<Result<Vec<_>>>()?;
            Correspondence::Barycentric {
                triangles,
                weights: bary.chunks_exact(3).map(|w| [w[0], w[1], w[2]]).collect(),
            }
        }
        None => Correspondence::between(&source, &model),
    };
    println!(
        "fitting {} frames of {} to {} ({} joint pairs, {} correspondence)",
        range.len(),
        source.name,
        model.name,
        default_joint_map(&source, &model).len(),
        correspondence.describe()
    );
    let bar = ProgressBar::new(range.len() as u64).with_style(ProgressStyle::with_template(
        "{bar:30} {pos}/{len} frames {msg} [{elapsed} < {eta}]",
    )?);
    let options = FitOptions {
        joint_weight: a.joint_weight,
        max_iterations: a.iterations,
        fit_expression: a.fit_expression,
        ..Default::default()
    };
    let fitted = fit_sequence(
        &source,
        &frames[range.clone()],
        &model,
        &correspondence,
        &options,
        |r| {
            bar.set_message(format!("vertex RMS {:.1} mm", r.vertex_rms * 1e3));
            bar.inc(1);
        },
    )
    .context("fitting")?;
    bar.finish_and_clear();
    sequence::write(&a.out, &model, &fitted.frames)?;
    println!(
        "residuals: mean vertex RMS {:.2} mm, worst {:.2} mm (frame {}); wrote {} frames to {}",
        fitted.mean_vertex_rms * 1e3,
        fitted.worst.0 * 1e3,
        range.start + fitted.worst.1,
        fitted.frames.len(),
        a.out.display()
    );
    Ok(())
}
