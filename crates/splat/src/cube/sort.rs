//! Stable LSD radix sort of `(u32 key, i32 value)` pairs on the GPU, 4 bits per pass: per
//! block of 1 024 keys a 16-bin histogram (bin-major, so that one exclusive scan of all of
//! them gives every block's first slot per bin), then a scatter that keeps the order of equal
//! keys (each unit's rank among its block's equal digits comes from a scan over the units in
//! shared memory). No plane operations and no atomics, so it runs the same on lavapipe, any
//! wgpu adapter and CUDA. Only the passes the key width needs are run (`bits`).

use burn::backend::tensor::IntTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::CubeDim;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;

#[cfg(feature = "cuda-source")]
use super::cuda_source::{CudaTarget, KernelSource, tensor};
use super::scan::{MAX_ROW, exclusive_scan_in_rows, grid};

/// Units per cube.
const UNITS: usize = 256;
/// Keys per unit (consecutive, so that a block covers `UNITS · PER_UNIT` consecutive keys).
const PER_UNIT: usize = 4;
/// Bits per pass (16 bins).
const DIGIT_BITS: u32 = 4;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// How many of the `per_unit` keys from `start` have each digit at `shift`, into `own`
    /// (cleared first: local arrays start undefined on CUDA).
    #[cube]
    fn digit_counts(
        keys: &Tensor<u32>,
        start: usize,
        shift: u32,
        own: &mut Array<i32>,
        #[comptime] per_unit: usize,
    ) {
        for b in 0..16usize {
            own[b] = 0i32;
        }
        for j in 0..per_unit {
            let g = start + j;
            if g < keys.len() {
                let bin = usize::cast_from((keys[g] >> shift) & 15u32);
                own[bin] += 1i32;
            }
        }
    }

    /// `hist[bin · blocks + block]` = how many keys of the block have digit `bin` at `shift`.
    #[cube(launch)]
    pub fn count(
        keys: &Tensor<u32>,
        hist: &mut Tensor<i32>,
        shift: u32,
        blocks: u32,
        #[comptime] units: usize,
        #[comptime] per_unit: usize,
    ) {
        let t = UNIT_POS as usize;
        let block = CUBE_POS;
        let mut counts = Shared::<[i32]>::new_slice(comptime![16 * units]);
        let mut own = Array::<i32>::new(16usize);
        digit_counts(
            keys,
            (block * units + t) * per_unit,
            shift,
            &mut own,
            per_unit,
        );
        for b in 0..16usize {
            counts[b * units + t] = own[b];
        }
        sync_cube();
        // Pairwise sums with doubling strides; unit 0 ends with the block's totals.
        let mut stride = 1usize;
        while stride < units {
            if t & (2 * stride - 1) == 0 {
                for b in 0..16usize {
                    counts[b * units + t] += counts[b * units + t + stride];
                }
            }
            sync_cube();
            stride *= 2;
        }
        // A grid rounded up to whole rows has cubes past the last block: their zeros would
        // land in the next bin's counts.
        if t < 16 && block < usize::cast_from(blocks) {
            hist[t * usize::cast_from(blocks) + block] = counts[t * units];
        }
    }

    /// Moves every pair to its slot: the block's first slot for its digit (`offsets`, the
    /// scanned histogram) plus its rank among the block's earlier keys with that digit.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn scatter(
        keys: &Tensor<u32>,
        values: &Tensor<i32>,
        offsets: &Tensor<i32>,
        keys_out: &mut Tensor<u32>,
        values_out: &mut Tensor<i32>,
        shift: u32,
        blocks: u32,
        #[comptime] units: usize,
        #[comptime] per_unit: usize,
    ) {
        let t = UNIT_POS as usize;
        let block = CUBE_POS;
        let n = keys.len();
        let mut counts = Shared::<[i32]>::new_slice(comptime![16 * units]);
        let start = (block * units + t) * per_unit;
        let mut own = Array::<i32>::new(16usize);
        digit_counts(keys, start, shift, &mut own, per_unit);
        // Local arrays start undefined on CUDA (WGSL zeroes them): clear before counting.
        let mut seen = Array::<i32>::new(16usize);
        for b in 0..16usize {
            seen[b] = 0i32;
        }
        for b in 0..16usize {
            counts[b * units + t] = own[b];
        }
        sync_cube();
        // Inclusive scan over the units, for every bin at once (Hillis–Steele).
        let mut left = Array::<i32>::new(16usize);
        let mut offset = 1usize;
        while offset < units {
            for b in 0..16usize {
                left[b] = 0i32;
                if t >= offset {
                    left[b] = counts[b * units + t - offset];
                }
            }
            sync_cube();
            for b in 0..16usize {
                counts[b * units + t] += left[b];
            }
            sync_cube();
            offset *= 2;
        }
        for j in 0..per_unit {
            let g = start + j;
            if g < n {
                let key = keys[g];
                let bin = usize::cast_from((key >> shift) & 15u32);
                let before = counts[bin * units + t] - own[bin] + seen[bin];
                let slot = offsets[bin * usize::cast_from(blocks) + block] + before;
                keys_out[usize::cast_from(slot)] = key;
                values_out[usize::cast_from(slot)] = values[g];
                seen[bin] += 1i32;
            }
        }
    }
}

/// The kernels above as CUDA C, for the offline NVRTC check.
#[cfg(feature = "cuda-source")]
pub(super) fn cuda_kernels(target: &CudaTarget) -> Result<Vec<KernelSource>, String> {
    let (s, p, t) = target.settings(CubeDim::new_1d(UNITS as u32));
    Ok(vec![
        target.source(
            "count",
            kernels::count::Count::new(
                s.clone(),
                p.clone(),
                t.clone(),
                tensor(),
                tensor(),
                (),
                (),
                UNITS,
                PER_UNIT,
            ),
        )?,
        target.source(
            "scatter",
            kernels::scatter::Scatter::new(
                s,
                p,
                t,
                tensor(),
                tensor(),
                tensor(),
                tensor(),
                tensor(),
                (),
                (),
                UNITS,
                PER_UNIT,
            ),
        )?,
    ])
}

/// Sorts `(keys, values)` by the low `bits` bits of the keys (u32 and i32 tensors of one
/// length), keeping the order of equal keys.
pub fn sort_pairs(
    keys: IntTensor<CubeBackend>,
    values: IntTensor<CubeBackend>,
    bits: u32,
) -> (IntTensor<CubeBackend>, IntTensor<CubeBackend>) {
    sort_pairs_in_rows(keys, values, bits, MAX_ROW)
}

/// [`sort_pairs`] on grids of at most `row` cubes per row (tests force several rows, and so
/// cubes past the last block, with a small `row`).
pub fn sort_pairs_in_rows(
    keys: IntTensor<CubeBackend>,
    values: IntTensor<CubeBackend>,
    bits: u32,
    row: usize,
) -> (IntTensor<CubeBackend>, IntTensor<CubeBackend>) {
    let mut keys = into_contiguous(keys);
    let mut values = into_contiguous(values);
    let n = keys.meta.shape()[0];
    if n <= 1 {
        return (keys, values);
    }
    let (client, device) = (keys.client.clone(), keys.device.clone());
    let blocks = n.div_ceil(UNITS * PER_UNIT);
    let empty = |len: usize, dtype: DType| {
        empty_device_contiguous_dtype(client.clone(), device.clone(), Shape::new([len]), dtype)
    };
    for pass in 0..bits.div_ceil(DIGIT_BITS) {
        let shift = pass * DIGIT_BITS;
        let hist = empty(16 * blocks, DType::I32);
        kernels::count::launch(
            &client,
            grid(blocks, row),
            CubeDim::new_1d(UNITS as u32),
            keys.clone().into_tensor_arg(),
            hist.clone().into_tensor_arg(),
            shift,
            blocks as u32,
            UNITS,
            PER_UNIT,
        );
        let (offsets, _) = exclusive_scan_in_rows(hist, row);
        let (keys_out, values_out) = (empty(n, DType::U32), empty(n, DType::I32));
        kernels::scatter::launch(
            &client,
            grid(blocks, row),
            CubeDim::new_1d(UNITS as u32),
            keys.into_tensor_arg(),
            values.into_tensor_arg(),
            offsets.into_tensor_arg(),
            keys_out.clone().into_tensor_arg(),
            values_out.clone().into_tensor_arg(),
            shift,
            blocks as u32,
            UNITS,
            PER_UNIT,
        );
        keys = keys_out;
        values = values_out;
    }
    (keys, values)
}
