//! The launch shape of the crate's element-wise CubeCL kernels (`conv::bands`, `adam`, `fused`): one
//! thread per value, [`UNITS`] per cube, on a 2-D grid because wgpu allows at most 65 535 cubes
//! per dimension. The last row runs past the work: every kernel ignores the units past its
//! tensor's length.

use burn_cubecl::cubecl::{CubeCount, CubeDim};

/// Threads per cube.
pub(crate) const UNITS: u32 = 256;
/// Cubes per grid row.
const MAX_ROW: u32 = 65_535;

/// The cubes and cube shape for one thread per each of `values` values.
pub(crate) fn one_thread_per_value(values: usize) -> (CubeCount, CubeDim) {
    let cubes = values.div_ceil(UNITS as usize).max(1) as u32;
    (
        CubeCount::Static(cubes.min(MAX_ROW), cubes.div_ceil(MAX_ROW), 1),
        CubeDim::new_1d(UNITS),
    )
}
