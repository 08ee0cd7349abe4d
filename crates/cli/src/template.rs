//! `f3g template` (build a canonical clothed template) and `f3g posmaps` (look at its maps).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use f3g_io::Image;
use f3g_rig::{ModelSpec, sequence};

use crate::data::CaptureModelArg;
use f3g_template::canonical::CanonicalPose;
use f3g_template::mesh::read_mesh;
use f3g_template::posmap::position_colours;
use f3g_template::template::Template;
use f3g_template::{HeadMaps, Poser, PositionMaps, TransferOptions, posed_positions};

/// Build a canonical template: the body model in the canonical pose, optionally with a garment.
#[derive(Args, Debug)]
#[command(args_conflicts_with_subcommands = true)]
pub struct TemplateArgs {
    #[command(subcommand)]
    pub command: Option<TemplateCommand>,
    #[command(flatten)]
    pub build: BuildArgs,
}

/// Template subcommands.
#[derive(Subcommand, Debug)]
pub enum TemplateCommand {
    /// Reconstruct the clothed geometry of a capture frame (visual hull of its masks), bring
    /// it to the canonical pose and write the garment part as a mesh for `--clothes`.
    Reconstruct(ReconstructArgs),
}

/// Options of `f3g template reconstruct`.
#[derive(Args, Debug)]
pub struct ReconstructArgs {
    /// Capture folder.
    #[arg(long)]
    pub data: PathBuf,
    /// Frame to carve (an A-pose-like frame sees most of the surface).
    #[arg(long, default_value_t = 0)]
    pub frame: usize,
    #[command(flatten)]
    pub model: CaptureModelArg,
    /// Garment mesh to write (OBJ, canonical pose).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write the carved hull in the frame's pose (OBJ).
    #[arg(long)]
    pub hull: Option<PathBuf>,
    /// Voxels along the longest side (16–512).
    #[arg(long, default_value_t = 128, value_parser = crate::bounds::size::<16, 512>)]
    pub resolution: usize,
    /// Hull points farther than this from the body are garment, metres.
    #[arg(long, default_value_t = 0.015)]
    pub garment_distance: f32,
    /// Hip rotation of the canonical pose, degrees (as `f3g template`).
    #[arg(long, default_value_t = 25.0)]
    pub leg_spread: f32,
    /// Upper-arm rotation of the canonical pose, degrees (as `f3g template`).
    #[arg(long, default_value_t = 0.0)]
    pub arm_raise: f32,
}

/// Options of `f3g template`.
#[derive(Args, Debug)]
pub struct BuildArgs {
    /// Body model: builtin, smplx:MODEL.npz, mhr:DIR or gltf:FILE.
    #[arg(long, default_value = "builtin")]
    pub body: ModelSpec,
    /// Garment mesh aligned with the canonical body (.obj, .ply, .gltf, .glb), or
    /// `builtin:skirt` for the built-in human's skirt.
    #[arg(long)]
    pub clothes: Option<String>,
    /// Output template (.npz).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Hip rotation of the canonical pose, degrees.
    #[arg(long, default_value_t = 25.0)]
    pub leg_spread: f32,
    /// Upper-arm rotation of the canonical pose (up from the rest pose), degrees.
    #[arg(long, default_value_t = 0.0)]
    pub arm_raise: f32,
    /// Closest-point matches farther than this fraction of the garment's bounding-box
    /// diagonal are inpainted.
    #[arg(long, default_value_t = 0.05)]
    pub distance_ratio: f32,
    /// Matches whose normals differ by more than this many degrees are inpainted.
    #[arg(long, default_value_t = 30.0)]
    pub max_angle: f32,
}

pub fn run(args: &TemplateArgs) -> Result<()> {
    match &args.command {
        Some(TemplateCommand::Reconstruct(a)) => reconstruct(a),
        None => build(&args.build),
    }
}

fn reconstruct(a: &ReconstructArgs) -> Result<()> {
    use f3g_template::reconstruct::{HullOptions, Silhouette, reconstruct};
    let ds = f3g_data::Dataset::open(&a.data, a.model.spec.as_ref())?;
    let rig = ds.rig()?;
    anyhow::ensure!(
        a.frame < ds.frames(),
        "--frame {}: the capture has {} frames",
        a.frame,
        ds.frames()
    );
    let cams: Vec<usize> = (0..ds.cameras.len())
        .filter(|&c| ds.has_image(c, a.frame))
        .collect();
    let masks = cams
        .iter()
        .map(|&c| ds.mask(c, a.frame))
        .collect::<Result<Vec<_>, _>>()?;
    let views: Vec<Silhouette> = cams
        .iter()
        .zip(&masks)
        .map(|(&c, m)| Silhouette {
            camera: &ds.cameras[c].camera,
            mask: m,
        })
        .collect();
    let params = &ds.params[a.frame];
    let posed = rig.pose(params)?;
    let pose = CanonicalPose {
        leg_spread_deg: a.leg_spread,
        arm_raise_deg: a.arm_raise,
    };
    let mut canonical = rig.canonical_params(&pose)?;
    canonical.identity = params.identity.clone();
    let options = HullOptions {
        resolution: a.resolution,
        garment_distance: a.garment_distance,
        ..Default::default()
    };
    let start = std::time::Instant::now();
    let r = reconstruct(&views, rig, &posed, &rig.surface, &canonical, &options)
        .with_context(|| format!("reconstructing frame {} of {}", a.frame, a.data.display()))?;
    f3g_rig::obj::write_obj(&a.out, &r.garment.vertices, &r.garment.triangles)?;
    if let Some(h) = &a.hull {
        f3g_rig::obj::write_obj(h, &r.hull.vertices, &r.hull.triangles)?;
    }
    println!(
        "carved {} views at {} voxels in {:.1} s: hull {} vertices; garment {} vertices, {} triangles (canonical pose) -> {}",
        views.len(),
        a.resolution,
        start.elapsed().as_secs_f32(),
        r.hull.vertices.len(),
        r.garment_vertices,
        r.garment.triangles.len(),
        a.out.display()
    );
    println!(
        "next: f3g template --clothes {} --out template.npz (or train with --set garment={})",
        a.out.display(),
        a.out.display()
    );
    Ok(())
}

fn build(a: &BuildArgs) -> Result<()> {
    let out = a.out.as_ref().context("--out is required")?;
    let pose = CanonicalPose {
        leg_spread_deg: a.leg_spread,
        arm_raise_deg: a.arm_raise,
    };
    let garment = match a.clothes.as_deref() {
        None => None,
        Some("builtin:skirt") => Some((
            f3g_template::template::builtin_skirt(&pose)?,
            PathBuf::from("builtin:skirt"),
        )),
        Some(path) => {
            let path = PathBuf::from(path);
            Some((read_mesh(&path)?, path))
        }
    };
    let options = TransferOptions {
        distance_ratio: a.distance_ratio,
        max_angle_deg: a.max_angle,
    };
    let rig = a.body.load()?;
    let (template, report) = Template::build(
        &rig,
        &pose,
        None,
        garment.as_ref().map(|(m, p)| (m.clone(), p.as_path())),
        &options,
    )?;
    template.save(out, &rig)?;
    println!(
        "template: {} vertices, {} triangles ({}) -> {}",
        template.mesh.vertices.len(),
        template.mesh.triangles.len(),
        if garment.is_some() {
            "body + garment"
        } else {
            "body"
        },
        out.display()
    );
    if let Some(g) = &report.garment {
        println!(
            "garment: {} vertices matched the body, {} inpainted, {} kept closest-point weights (no match in their component); {} degenerate triangles dropped, {} non-manifold edges, {} unused vertices",
            report.matched,
            report.inpainted,
            report.fallback,
            g.degenerate_triangles,
            g.non_manifold_edges,
            g.unused_vertices
        );
    }
    Ok(())
}

/// Write PNG pictures of a template's position maps.
#[derive(Args, Debug)]
pub struct PosmapsArgs {
    /// Template (.npz) from `f3g template`.
    #[arg(long)]
    pub template: PathBuf,
    /// Output directory: new, empty, or an earlier `posmaps` one (whose pictures it replaces).
    #[arg(long)]
    pub out: PathBuf,
    /// Write into an --out that holds other files (those of the same names are replaced,
    /// nothing else is removed).
    #[arg(long)]
    pub overwrite: bool,
    /// Pixels per side of each (front, back) map (16–4096).
    #[arg(long, default_value_t = 256, value_parser = crate::bounds::size::<16, 4096>)]
    pub resolution: usize,
    /// Parameters of a frame to draw the posed maps of (JSON, smpl_params.npz or f3g .npz).
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// Frame of a sequence file.
    #[arg(long, default_value_t = 0)]
    pub frame: usize,
}

fn save(
    path: &std::path::Path,
    width: usize,
    height: usize,
    channels: usize,
    data: Vec<f32>,
) -> Result<()> {
    f3g_io::write_png(
        path,
        &Image::from_vec(width, height, channels, data).map_err(anyhow::Error::msg)?,
    )?;
    Ok(())
}

pub fn posmaps(a: &PosmapsArgs) -> Result<()> {
    let (template, rig) = Template::load(&a.template)?;
    let mut out = f3g_io::OutputDir::open(&a.out, "posmaps", a.overwrite)?;
    let maps = PositionMaps::build(&template, a.resolution, None)?;
    let (w, h) = maps.size();
    save(
        &out.file("canonical.png")?,
        w,
        h,
        3,
        maps.scatter(&position_colours(&maps.positions)),
    )?;
    let normals: Vec<[f32; 3]> = maps
        .normals
        .iter()
        .map(|n| (*n * 0.5 + 0.5).to_array())
        .collect();
    save(&out.file("normals.png")?, w, h, 3, maps.scatter(&normals))?;
    save(
        &out.file("mask.png")?,
        w,
        h,
        1,
        maps.mask().iter().map(|&m| m as u8 as f32).collect(),
    )?;
    let head = HeadMaps::build(&maps, &rig.head_joints()?, f3g_template::head::DENSIFY)?;
    let hs = head.size;
    save(
        &out.file("head.png")?,
        2 * hs,
        hs,
        3,
        head.scatter(&position_colours(&head.positions)),
    )?;
    if let Some(p) = &a.params {
        let frames = sequence::read(p, &rig)?;
        let frame = frames.get(a.frame).with_context(|| {
            format!(
                "{}: frame {} requested, the file has {}",
                p.display(),
                a.frame,
                frames.len()
            )
        })?;
        let poser = Poser::new(&rig, &template)?;
        let posed = posed_positions(&poser, &maps, frame)?;
        save(
            &out.file("posed.png")?,
            w,
            h,
            3,
            maps.scatter(&position_colours(&posed)),
        )?;
        let posed_head = poser.pose_points(&head.positions, &head.skin, frame, false)?;
        save(
            &out.file("head_posed.png")?,
            2 * hs,
            hs,
            3,
            head.scatter(&position_colours(&posed_head)),
        )?;
    }
    out.finish()?;
    println!(
        "{} Gaussians on {}×{} maps; head crop {:?} densified to {} face Gaussians on {}×{} head maps; pictures in {}",
        maps.len(),
        h,
        w,
        head.crop,
        head.len(),
        hs,
        2 * hs,
        a.out.display()
    );
    Ok(())
}
