//! The CPU reference renderer: plain Rust, multi-threaded with rayon, generic over `f32`/`f64`.
//!
//! Pipeline: [`project`] (per Gaussian: cull, EWA covariance, SH colour) → [`bin_tiles`]
//! (16×16 tiles, stable depth order) → [`rasterize`] (per tile, front to back) and, for
//! gradients, [`rasterize_backward`] (per tile, back to front from the final transmittance) →
//! [`project_backward`] (per Gaussian).
//!
//! The rendering semantics every path shares (cut-offs, footprints, outputs, layouts) are
//! stated in [`crate::semantics`].

mod project;
mod raster;

pub use project::{Projected, ScreenGaussian, ScreenGrads, project, project_backward};
pub use raster::{
    ForwardOutput, RasterGrads, TileBins, bin_tiles, pixel_box, rasterize, rasterize_backward,
};

use crate::semantics::{GaussianSlices, MAX_INTERSECTIONS, RenderOptions, check_finite};
use crate::{Camera, SplatError, real::Real};

/// Per-pixel gradients of the loss with respect to the three outputs.
#[derive(Clone, Copy, Debug)]
pub struct PixelGrads<'a, T> {
    /// `[H,W,3]`
    pub color: &'a [T],
    /// `[H,W]`
    pub alpha: &'a [T],
    /// `[H,W]`
    pub depth: &'a [T],
}

/// Gradients of the loss with respect to every input, same layouts as the inputs.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianGrads<T> {
    pub means: Vec<T>,
    pub log_scales: Vec<T>,
    pub quats: Vec<T>,
    pub opacity_logits: Vec<T>,
    pub sh: Vec<T>,
    pub background: [T; 3],
    /// Screen-space mean gradient `[N,2]` (pixels), the statistic densification uses.
    pub means2d: Vec<T>,
}

/// Renders Gaussians: validation, projection, binning and rasterisation.
pub fn render<T: Real>(
    gaussians: &GaussianSlices<T>,
    camera: &Camera,
    background: [T; 3],
    options: &RenderOptions,
) -> Result<ForwardOutput<T>, SplatError> {
    camera.validate()?;
    options.validate()?;
    gaussians.validate()?;
    check_finite("background", &background)?;
    let projected = project(gaussians, camera);
    let count: u64 = projected.iter().map(raster::tiles_touched).sum();
    if count > MAX_INTERSECTIONS {
        return Err(SplatError::Intersections {
            count,
            limit: MAX_INTERSECTIONS,
        });
    }
    let bins = bin_tiles(&projected, camera.width as usize, camera.height as usize);
    Ok(rasterize(projected, bins, camera, background, options))
}

/// Gradients of a render with respect to its inputs, given the per-pixel output gradients.
pub fn render_backward<T: Real>(
    gaussians: &GaussianSlices<T>,
    camera: &Camera,
    options: &RenderOptions,
    forward: &ForwardOutput<T>,
    grads: &PixelGrads<T>,
) -> GaussianGrads<T> {
    let raster = rasterize_backward(forward, camera, options, grads);
    let mut out = project_backward(gaussians, camera, &forward.projected, &raster.screen);
    out.background = raster.background;
    out
}
