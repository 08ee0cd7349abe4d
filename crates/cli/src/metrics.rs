//! `f3g metrics`: PSNR, SSIM and LPIPS of two images.

use std::path::PathBuf;

use anyhow::{Result, ensure};
use clap::Args;
use f3g_io::Image;
use f3g_nets::lpips::{Lpips, LpipsNet};
use f3g_nets::metrics::{image_tensor, psnr, ssim_images, ssim_skimage};
use serde::Serialize;

use crate::device::DeviceArg;

/// Options of `f3g metrics`.
#[derive(Args, Debug)]
pub struct MetricsArgs {
    /// First image (e.g. the render).
    pub a: PathBuf,
    /// Second image (e.g. the ground truth).
    pub b: PathBuf,
    /// LPIPS backbone.
    #[arg(long, default_value = "alex")]
    pub lpips: LpipsNet,
    /// Mask (grey PNG/JPEG of the same size): pixels below 0.5 are set to white in both
    /// images before scoring (the AvatarReX evaluation protocol).
    #[arg(long)]
    pub mask: Option<PathBuf>,
    #[command(flatten)]
    pub device: DeviceArg,
}

#[derive(Serialize)]
struct Metrics {
    psnr: f64,
    /// scikit-image's SSIM (the paper's evaluation).
    ssim: f64,
    /// SSIM as 3DGS computes it (Gaussian window).
    ssim_3dgs: f64,
    /// `None` when the LPIPS weights are not installed.
    lpips: Option<f64>,
    lpips_net: String,
    lpips_error: Option<String>,
}

/// White outside the mask.
fn apply_mask(img: &mut Image, mask: &Image) {
    for (p, rgb) in img.data.chunks_exact_mut(img.channels).enumerate() {
        if mask.data[p] < 0.5 {
            rgb.fill(1.0);
        }
    }
}

pub fn run(a: &MetricsArgs) -> Result<()> {
    let mut x = f3g_io::read_rgb(&a.a)?;
    let mut y = f3g_io::read_rgb(&a.b)?;
    ensure!(
        (x.width, x.height) == (y.width, y.height),
        "{} is {}×{} but {} is {}×{}: the images must have the same size",
        a.a.display(),
        x.width,
        x.height,
        a.b.display(),
        y.width,
        y.height
    );
    if let Some(path) = &a.mask {
        let mask = f3g_io::read_gray(path)?;
        ensure!(
            (mask.width, mask.height) == (x.width, x.height),
            "{}: the mask is {}×{}, the images {}×{}",
            path.display(),
            mask.width,
            mask.height,
            x.width,
            x.height
        );
        apply_mask(&mut x, &mask);
        apply_mask(&mut y, &mask);
    }
    let device = a.device.open()?;
    let (lpips, lpips_error) = match Lpips::load(a.lpips, &device) {
        Ok(net) => {
            let d = net.forward(image_tensor(&x, &device), image_tensor(&y, &device))?;
            (
                Some(d.into_data().try_into_vec::<f32>().expect("f32")[0] as f64),
                None,
            )
        }
        Err(e) => (None, Some(e.to_string())),
    };
    let out = Metrics {
        psnr: psnr(&x, &y)?,
        ssim: ssim_skimage(&x, &y)?,
        ssim_3dgs: ssim_images(&x, &y)?,
        lpips,
        lpips_net: a.lpips.to_string(),
        lpips_error,
    };
    println!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}
