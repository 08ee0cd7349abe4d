//! Multi-view captures: readers for the AvatarReX and THuman4.0 layouts, split presets, face
//! crops with updated intrinsics, the training loader, and the synthetic capture of the
//! built-in human.
//!
//! Conventions: images `[H, W, 3]` f32 RGB in [0, 1], masks `[H, W, 1]` alpha; OpenCV cameras
//! (`x_cam = R x + T`); crop of a box with top-left `(x0, y0)` resized by `s`:
//! `fx' = s fx, cx' = s (cx − x0)` (R, T unchanged).

pub mod calibration;
pub mod check;
pub mod crop;
pub mod dataset;
mod error;
pub mod fit;
pub mod imgops;
pub mod keypoints;
pub mod loader;
pub mod split;
pub mod synth;

pub use calibration::{CaptureCamera, read_calibration, write_calibration};
pub use dataset::{Dataset, Layout};
pub use error::DataError;
pub use loader::{Loader, LoaderOptions, Sample, View};
pub use split::{Protocol, Split, SplitKind, preset};
