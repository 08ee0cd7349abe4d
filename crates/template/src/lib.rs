//! Canonical clothed templates and the 2-D layouts the networks see.
//!
//! - [`raster`]: a triangle rasteriser (orthographic and pinhole) used for position maps here
//!   and for ground-truth rendering in the synthetic capture.
//! - [`canonical`]: the canonical pose (legs apart, configurable arms) and root-free posing.
//! - [`template`], [`transfer`], [`mesh`]: the clothed template (body, optionally a garment
//!   whose skin weights are transferred robustly), its file format, mesh import and operators.
//! - [`reconstruct`]: clothed geometry from a capture (visual hull → canonical garment).
//! - [`posmap`]: front/back orthographic position maps, one Gaussian per covered pixel, and
//!   posed maps; [`head`]: the densified head maps of the face branch; [`pca`]: pose PCA.
//!
//! Conventions: metres, +Y up, the body faces +Z. Maps are `[R, 2R]` (front | back), pixel
//! centres at `(i + 0.5, j + 0.5)`, Gaussians numbered row-major over the map.

pub mod canonical;
mod error;
pub mod head;
pub mod mesh;
pub mod pca;
pub mod posmap;
pub mod raster;
pub mod reconstruct;
pub mod template;
pub mod transfer;

pub use canonical::{CanonicalPose, without_root};
pub use error::TemplateError;
pub use head::HeadMaps;
pub use pca::PosePca;
pub use posmap::{Poser, PositionMaps, posed_positions};
pub use raster::{Fragments, Projection, View, rasterize};
pub use template::Template;
pub use transfer::{TransferOptions, transfer_weights};
