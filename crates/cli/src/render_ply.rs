//! `f3g render-ply`: render a standard 3DGS `.ply` from a camera given as JSON.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use burn::tensor::{Tensor, TensorData};
use clap::Args;
use f3g_io::Image;
use f3g_splat::{Camera, RenderOptions, cpu, ply};

use crate::device::{DeviceArg, DeviceSpec};

/// Host bytes a forward render holds per pixel (colour, alpha, depth, transmittance,
/// contributor count, the PNG's buffer) and per Gaussian (parameters, projection, tile lists).
const RENDER_BYTES_PER_PIXEL: u64 = 48;
const RENDER_BYTES_PER_GAUSSIAN: u64 = 400;

/// Render a 3DGS `.ply` file with a pinhole camera.
#[derive(Args, Debug)]
pub struct RenderPlyArgs {
    /// The Gaussians, in the standard 3DGS `.ply` layout.
    #[arg(long)]
    pub ply: PathBuf,
    /// Camera JSON: {"K": [[fx,0,cx],[0,fy,cy],[0,0,1]], "R": [[..],[..],[..]], "t": [..],
    /// "width": W, "height": H} with x_cam = R x_world + t (OpenCV); optional "near", "far".
    #[arg(long)]
    pub camera: PathBuf,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
    /// Background colour as r,g,b in [0, 1].
    #[arg(long, default_value = "0,0,0", value_parser = parse_rgb)]
    pub background: [f32; 3],
    /// Also write the float image [H, W, 3] as `.npy`.
    #[arg(long)]
    pub raw: Option<PathBuf>,
    /// Upper clamp of one Gaussian's alpha (3DGS 0.99, gsplat 0.999).
    #[arg(long, default_value_t = 0.99)]
    pub alpha_max: f64,
    #[command(flatten)]
    pub device: DeviceArg,
}

/// Parses `r,g,b` with each component in [0, 1].
pub fn parse_rgb(text: &str) -> Result<[f32; 3], String> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let [r, g, b] = parts.as_slice() else {
        return Err(format!(
            "expected three comma-separated numbers r,g,b, got {}",
            f3g_io::quoted(text)
        ));
    };
    let mut out = [0.0; 3];
    for (o, p) in out.iter_mut().zip([r, g, b]) {
        *o = p
            .parse::<f32>()
            .map_err(|_| format!("{} is not a number", f3g_io::quoted(p)))?;
        if !(0.0..=1.0).contains(o) {
            return Err(format!("{o} is outside [0, 1]"));
        }
    }
    Ok(out)
}

/// Reads and validates a camera JSON file.
pub fn read_camera(path: &Path) -> Result<Camera> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading camera {}", path.display()))?;
    let camera: Camera = serde_json::from_str(&text)
        .with_context(|| format!("parsing camera {}", path.display()))?;
    camera
        .validate()
        .with_context(|| format!("camera {}", path.display()))?;
    Ok(camera)
}

pub fn run(args: &RenderPlyArgs) -> Result<()> {
    let cloud = ply::read_ply(&args.ply)?;
    let camera = read_camera(&args.camera)?;
    if !(args.alpha_max > 0.0 && args.alpha_max < 1.0) {
        bail!("--alpha-max must lie in (0, 1), got {}", args.alpha_max);
    }
    let options = RenderOptions {
        alpha_max: args.alpha_max,
    };
    let pixels = camera.width as u64 * camera.height as u64;
    f3g_io::memory::ensure_available(
        pixels * RENDER_BYTES_PER_PIXEL + cloud.len() as u64 * RENDER_BYTES_PER_GAUSSIAN,
        &format!(
            "rendering {} Gaussians at {}x{} ({})",
            cloud.len(),
            camera.width,
            camera.height,
            args.camera.display()
        ),
    )?;
    let (color, visible) = if args.device.spec == DeviceSpec::Cpu {
        let out = cpu::render(&cloud.slices(), &camera, args.background, &options)
            .with_context(|| format!("rendering {}", args.ply.display()))?;
        let visible = out.projected.iter().filter(|g| g.is_visible()).count();
        (out.color, visible)
    } else {
        let device = args.device.open()?;
        let background =
            Tensor::<1>::from_data(TensorData::new(args.background.to_vec(), [3]), &device);
        let out = f3g_splat::render(&cloud.to_tensors(&device), &camera, background, &options)
            .with_context(|| format!("rendering {} on {}", args.ply.display(), args.device))?;
        let color = out
            .color
            .to_data()
            .convert::<f32>()
            .try_into_vec::<f32>()
            .map_err(|e| anyhow::anyhow!("reading the image back from {}: {e:?}", args.device))?;
        let radii = out
            .radii
            .to_data()
            .convert::<i64>()
            .try_into_vec::<i64>()
            .map_err(|e| anyhow::anyhow!("reading the radii back from {}: {e:?}", args.device))?;
        let visible = radii.chunks_exact(2).filter(|r| r != &[0, 0]).count();
        (color, visible)
    };
    let (w, h) = (camera.width as usize, camera.height as usize);
    let image = Image::from_vec(w, h, 3, color).map_err(anyhow::Error::msg)?;
    f3g_io::write_png(&args.out, &image)?;
    if let Some(raw) = &args.raw {
        f3g_io::write_npy_f32(raw, &[h, w, 3], &image.data)?;
    }
    println!(
        "rendered {} of {} Gaussians at {w}x{h} to {}",
        visible,
        cloud.len(),
        args.out.display()
    );
    Ok(())
}
