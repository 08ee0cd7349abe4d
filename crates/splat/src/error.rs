//! Errors for everything a user can get wrong when rendering or reading Gaussians.

use std::path::PathBuf;

/// What went wrong, phrased so that the user can fix the input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SplatError {
    /// A tensor or array has a shape other than the one the renderer needs.
    #[error("`{name}` has shape {got:?}, expected {expected}")]
    Shape {
        name: &'static str,
        got: Vec<usize>,
        expected: String,
    },
    /// A parameter holds NaN or ±inf.
    #[error("`{name}` holds a non-finite value ({value}) at flat index {index}")]
    NonFinite {
        name: &'static str,
        index: usize,
        value: f64,
    },
    /// The camera cannot be used for projection.
    #[error(transparent)]
    Camera(#[from] f3g_camera::CameraError),
    /// The spherical-harmonics coefficient count is not (degree + 1)² for a degree 0..=3.
    #[error(
        "spherical harmonics with {coeffs} coefficients per channel: expected 1, 4, 9 or 16 (degree 0..3)"
    )]
    ShDegree { coeffs: usize },
    /// A render option is out of its valid range.
    #[error("invalid render option `{name}`: {reason}")]
    Option { name: &'static str, reason: String },
    /// The footprints cover more (Gaussian, tile) pairs than the tile lists can index.
    #[error(
        "the Gaussians' footprints cover about {count} (Gaussian, tile) pairs, more than the {limit} a render can list; render a smaller image or fewer, smaller Gaussians"
    )]
    Intersections { count: u64, limit: u64 },
    /// A `.ply` file could not be read or written.
    #[error("{path}: {reason}")]
    Ply { path: PathBuf, reason: String },
    /// An `.spz` file could not be written.
    #[error("{path}: {reason}")]
    Spz { path: PathBuf, reason: String },
}
