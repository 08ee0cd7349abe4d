//! Sums a cube each: one cube per output value, its units striding over the terms, then a
//! pairwise sum in shared memory. For sums of hundreds to thousands of terms per value over few
//! values (a style vector's 512, a modulation's style gradient): one thread per value ran each
//! sum serially on a couple of cubes, ≈ 100 µs a launch on an H200 for a few µs of arithmetic
//! (BENCHMARKS, "GPU: an H200 lent on 2026-11-29"). The noise strength's gradient sums its
//! per-pixel products the same way, a cube of pixels each (`bias_leaky_relu.rs`).
//!
//! Every unit of a cube reaches [`cube_sum`]'s barriers: a kernel never returns early around
//! them (WGSL wants barriers in uniform control flow), it only leaves out the writes of cubes
//! past its values.

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::{CubeCount, CubeDim};

use crate::cube_grid::cubes_in_rows;

/// Units per summing cube.
pub(super) const SUM_UNITS: u32 = 64;

/// The cubes and cube shape for one cube of [`SUM_UNITS`] per each of `values` values, in
/// rows ([`cubes_in_rows`], [`cube_index`]); the last row may run past the values.
pub(super) fn one_cube_per_value(values: usize) -> (CubeCount, CubeDim) {
    (cubes_in_rows(values), CubeDim::new_1d(SUM_UNITS))
}

/// One cube per channel (`CUBE_POS_X`: at most 65 535, wgpu's limit per dimension) in each of
/// `layers` grid layers (`CUBE_POS_Z`), one per queued layer or table (the batched kernels of
/// `modulate.rs` and `bias_leaky_relu.rs`).
pub(super) fn one_cube_per_channel_in_layers(
    channels: usize,
    which: &str,
    layers: usize,
) -> CubeCount {
    let cubes = u32::try_from(channels)
        .ok()
        .filter(|&c| c <= 65_535)
        .unwrap_or_else(|| panic!("at most 65 535 {which} channels"));
    CubeCount::Static(
        cubes,
        1,
        u32::try_from(layers).expect("a few layers per launch"),
    )
}

/// The cube's position on [`one_cube_per_value`]'s grid.
#[cube]
pub(super) fn cube_index() -> u32 {
    CUBE_POS_Y * CUBE_COUNT_X + CUBE_POS_X
}

/// Sums `partial` (one value per unit, `units` a power of two) into `partial[0]`, pairwise
/// with doubling strides; every unit must call it.
#[cube]
pub(super) fn cube_sum(partial: &mut Shared<[f32]>, #[comptime] units: u32) {
    let t = UNIT_POS;
    sync_cube();
    let mut stride = 1u32;
    while stride < units {
        if t & (2 * stride - 1) == 0 {
            partial[t as usize] += partial[(t + stride) as usize];
        }
        sync_cube();
        stride *= 2;
    }
}
