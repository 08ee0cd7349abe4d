//! Gaussian–tile intersections: every visible Gaussian writes the ids of the tiles its
//! footprint touches (row by row) and its own id at its slot of the list, the exclusive scan of
//! the tile counts. Unsorted: the depth and tile sorts follow.

use burn::backend::Cube;
use burn::backend::ops::IntTensorOps;
use burn::backend::tensor::IntTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::cubecl::CubeDim;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_dtype;

use super::project::Projection;
use super::scan::{exclusive_scan, grid};
use crate::cpu::TILE_SIZE;

/// Units per cube.
const UNITS: usize = 256;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// Gaussian `ABSOLUTE_POS` writes its `tiles[i]` intersections from `offsets[i]` on.
    #[cube(launch)]
    pub fn intersect(
        rects: &Tensor<i32>,
        tiles: &Tensor<i32>,
        offsets: &Tensor<i32>,
        tile_of: &mut Tensor<i32>,
        gaussian_of: &mut Tensor<i32>,
        tiles_x: i32,
    ) {
        let i = ABSOLUTE_POS;
        if i >= tiles.len() {
            terminate!();
        }
        if tiles[i] > 0i32 {
            let mut k = usize::cast_from(offsets[i]);
            let mut ty = rects[4 * i + 1];
            while ty <= rects[4 * i + 3] {
                let mut tx = rects[4 * i];
                while tx <= rects[4 * i + 2] {
                    tile_of[k] = ty * tiles_x + tx;
                    gaussian_of[k] = i32::cast_from(i);
                    k += 1;
                    tx += 1i32;
                }
                ty += 1i32;
            }
        }
    }
}

/// The intersections of a projection: `tile_of [M]` and `gaussian_of [M]` (i32), Gaussian by
/// Gaussian, `offsets [N]` where each Gaussian's run starts, and their number `M`.
#[derive(Clone, Debug)]
pub struct Intersections {
    pub tile_of: IntTensor<Cube>,
    pub gaussian_of: IntTensor<Cube>,
    pub offsets: IntTensor<Cube>,
    pub count: usize,
}

/// Lists the Gaussian–tile intersections of `projection` for an image `width` pixels wide.
///
/// Reads one number back to the host: the intersection count, which sizes the lists (the one
/// readback of a render).
pub fn intersect(projection: &Projection, width: u32) -> Intersections {
    let tiles = into_contiguous(projection.tiles.clone());
    let n = tiles.meta.shape()[0];
    let (client, device) = (tiles.client.clone(), tiles.device.clone());
    let (offsets, total) = exclusive_scan(tiles.clone());
    let count = if n == 0 {
        0
    } else {
        let total = burn::tensor::read_sync(Cube::int_into_data(total))
            .expect("reading the intersection count back from the device");
        total.convert::<i64>().as_slice::<i64>().expect("one i64")[0].max(0) as usize
    };
    let list = || {
        empty_device_dtype(
            client.clone(),
            device.clone(),
            Shape::new([count]),
            DType::I32,
        )
    };
    let (tile_of, gaussian_of) = (list(), list());
    if count > 0 {
        kernels::intersect::launch(
            &client,
            grid(n.div_ceil(UNITS)),
            CubeDim::new_1d(UNITS as u32),
            into_contiguous(projection.rects.clone()).into_tensor_arg(),
            tiles.into_tensor_arg(),
            offsets.clone().into_tensor_arg(),
            tile_of.clone().into_tensor_arg(),
            gaussian_of.clone().into_tensor_arg(),
            width.div_ceil(TILE_SIZE as u32) as i32,
        );
    }
    Intersections {
        tile_of,
        gaussian_of,
        offsets,
        count,
    }
}
