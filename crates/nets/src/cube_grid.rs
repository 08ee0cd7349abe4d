//! The launch shape of the element-wise CubeCL kernels (this crate's `conv::bands`, `adam`,
//! `fused`, and `f3g-avatar`'s skinning): one thread per value, [`UNITS`] per cube, on a 2-D
//! grid because wgpu allows at most 65 535 cubes per dimension (and a third dimension for
//! kernels that treat several tensors, one per layer).
//! The last row runs past the work: every kernel ignores the units past its tensor's length.

use burn_cubecl::cubecl::client::Client;
use burn_cubecl::cubecl::{CubeCount, CubeDim};

/// Threads per cube.
pub(crate) const UNITS: u32 = 256;
/// Cubes per grid row.
const MAX_ROW: u32 = 65_535;

/// The cubes and cube shape for one thread per each of `values` values.
pub fn one_thread_per_value(values: usize) -> (CubeCount, CubeDim) {
    (
        cubes_in_rows(values.div_ceil(UNITS as usize)),
        CubeDim::new_1d(UNITS),
    )
}

/// `cubes` cubes (at least one) in rows of at most 65 535; cube `(CUBE_POS_Y · CUBE_COUNT_X +
/// CUBE_POS_X)` counts along them, and the last row may run past `cubes`.
pub(crate) fn cubes_in_rows(cubes: usize) -> CubeCount {
    let cubes = u32::try_from(cubes.max(1)).expect("fewer than 2^32 cubes");
    CubeCount::Static(cubes.min(MAX_ROW), cubes.div_ceil(MAX_ROW), 1)
}

/// [`one_thread_per_value`] for the longest of `layers` tensors, one grid layer (`CUBE_POS_Z`)
/// each; a unit's position in its tensor is `(CUBE_POS_Y · CUBE_COUNT_X + CUBE_POS_X) · UNITS +
/// UNIT_POS_X`.
pub(crate) fn one_thread_per_value_in_layers(values: usize, layers: usize) -> (CubeCount, CubeDim) {
    let (cubes, cube) = one_thread_per_value(values);
    let CubeCount::Static(x, y, _) = cubes else {
        unreachable!("one_thread_per_value counts statically")
    };
    (CubeCount::Static(x, y, layers as u32), cube)
}

/// How many items of a batch one launch binds (`crate::adam`'s shared updates, `fused`'s
/// modulated layers): `each` tensors per item beside `shared` ones, within the tensors the
/// device binds per kernel; at least one, at most `most`.
pub(crate) fn items_per_launch(client: &Client, each: usize, shared: usize, most: usize) -> usize {
    ((client.properties().hardware.max_bindings as usize).saturating_sub(shared) / each)
        .clamp(1, most)
}
