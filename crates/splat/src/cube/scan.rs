//! Exclusive prefix sum of i32 counts on the GPU (the per-Gaussian tile counts become each
//! Gaussian's first slot in the tile-key list). Three passes that need neither plane
//! operations (lavapipe has none) nor cross-cube memory ordering (WGSL gives none): each cube
//! scans 256 values in shared memory and writes its total; the totals are scanned the same
//! way (recursively); each value then gets its cube's offset.

#[cfg(feature = "cuda-source")]
use super::cuda_source::{CudaTarget, KernelSource, tensor};
use burn::backend::tensor::IntTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::{CubeCount, CubeDim};
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;

/// Values per cube (and units per cube).
const BLOCK: usize = 256;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// Exclusive scan of each block of `block` values; the block's total goes to `totals`.
    #[cube(launch)]
    pub fn scan_blocks(
        values: &Tensor<i32>,
        out: &mut Tensor<i32>,
        totals: &mut Tensor<i32>,
        #[comptime] block: usize,
    ) {
        let t = UNIT_POS as usize;
        let g = CUBE_POS * block + t;
        let n = values.len();
        let mut shared = Shared::<[i32]>::new_slice(block);
        let mut x = 0i32;
        if g < n {
            x = values[g];
        }
        shared[t] = x;
        sync_cube();
        // Hillis–Steele: after the step with offset d, shared[t] sums the 2d values up to t.
        let mut offset = 1usize;
        while offset < block {
            let mut left = 0i32;
            if t >= offset {
                left = shared[t - offset];
            }
            sync_cube();
            shared[t] += left;
            sync_cube();
            offset *= 2;
        }
        if g < n {
            out[g] = shared[t] - x;
        }
        // A grid rounded up to whole rows has cubes past the last block: they write nothing.
        if t == block - 1 && CUBE_POS < totals.len() {
            totals[CUBE_POS] = shared[t];
        }
    }

    /// Adds to every value the scanned total of the blocks before its own.
    #[cube(launch)]
    pub fn add_block_offsets(
        out: &mut Tensor<i32>,
        offsets: &Tensor<i32>,
        #[comptime] block: usize,
    ) {
        let g = ABSOLUTE_POS;
        if g < out.len() {
            out[g] += offsets[g / block];
        }
    }
}

/// The kernels above as CUDA C, for the offline NVRTC check.
#[cfg(feature = "cuda-source")]
pub(super) fn cuda_kernels(target: &CudaTarget) -> Result<Vec<KernelSource>, String> {
    let (s, p, t) = target.settings(CubeDim::new_1d(BLOCK as u32));
    Ok(vec![
        target.source(
            "scan_blocks",
            kernels::scan_blocks::ScanBlocks::new(
                s.clone(),
                p.clone(),
                t.clone(),
                tensor(),
                tensor(),
                tensor(),
                BLOCK,
            ),
        )?,
        target.source(
            "add_block_offsets",
            kernels::add_block_offsets::AddBlockOffsets::new(s, p, t, tensor(), tensor(), BLOCK),
        )?,
    ])
}

/// Cubes per grid row: wgpu allows at most 65 535 per dimension.
pub(crate) const MAX_ROW: usize = 65_535;

/// A 2-D grid of at least `cubes` cubes, `row` per row: the last row is filled up to `row`,
/// so every kernel launched on it must ignore the cubes (or units) past its work.
pub(crate) fn grid(cubes: usize, row: usize) -> CubeCount {
    let (cubes, row) = (cubes.max(1) as u32, row.clamp(1, MAX_ROW) as u32);
    CubeCount::Static(cubes.min(row), cubes.div_ceil(row), 1)
}

/// Exclusive prefix sum of the 1-D i32 tensor `values`, and the sum of all of them (`[1]`; an
/// empty input sums to an empty tensor).
pub fn exclusive_scan(
    values: IntTensor<CubeBackend>,
) -> (IntTensor<CubeBackend>, IntTensor<CubeBackend>) {
    exclusive_scan_in_rows(values, MAX_ROW)
}

/// [`exclusive_scan`] on grids of at most `row` cubes per row (tests force several rows, and
/// so cubes past the work, with a small `row`).
pub fn exclusive_scan_in_rows(
    values: IntTensor<CubeBackend>,
    row: usize,
) -> (IntTensor<CubeBackend>, IntTensor<CubeBackend>) {
    let values = into_contiguous(values);
    let n = values.meta.shape()[0];
    let (client, device) = (values.client.clone(), values.device.clone());
    let out =
        empty_device_contiguous_dtype(client.clone(), device.clone(), Shape::new([n]), DType::I32);
    if n == 0 {
        return (out.clone(), out);
    }
    let blocks = n.div_ceil(BLOCK);
    let totals =
        empty_device_contiguous_dtype(client.clone(), device, Shape::new([blocks]), DType::I32);
    kernels::scan_blocks::launch(
        &client,
        grid(blocks, row),
        CubeDim::new_1d(BLOCK as u32),
        values.into_tensor_arg(),
        out.clone().into_tensor_arg(),
        totals.clone().into_tensor_arg(),
        BLOCK,
    );
    if blocks == 1 {
        return (out, totals);
    }
    let (offsets, total) = exclusive_scan_in_rows(totals, row);
    kernels::add_block_offsets::launch(
        &client,
        grid(blocks, row),
        CubeDim::new_1d(BLOCK as u32),
        out.clone().into_tensor_arg(),
        offsets.into_tensor_arg(),
        BLOCK,
    );
    (out, total)
}
