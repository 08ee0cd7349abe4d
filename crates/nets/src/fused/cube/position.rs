//! Where a value sits in the gapless `[B, C, H, W]` tensors the kernels read and write, stored
//! row-major or channels-last (`crate::cube_layout`): the index arithmetic every resampling
//! kernel shares.

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

/// Where a value sits in a `[B, C, H, W]` tensor.
#[derive(CubeType)]
pub(super) struct Position {
    pub(super) batch: u32,
    pub(super) channel: u32,
    pub(super) y: u32,
    pub(super) x: u32,
}

/// The position of buffer offset `i` in a gapless `[B, channels, h, w]` tensor, stored
/// row-major or, with `channels_last`, as `[B, h, w, channels]`.
#[cube]
pub(super) fn position(
    i: u32,
    channels: u32,
    h: u32,
    w: u32,
    #[comptime] channels_last: bool,
) -> Position {
    if comptime![channels_last] {
        Position {
            batch: i / (channels * w * h),
            channel: i % channels,
            y: (i / (channels * w)) % h,
            x: (i / channels) % w,
        }
    } else {
        Position {
            batch: i / (w * h * channels),
            channel: (i / (w * h)) % channels,
            y: (i / w) % h,
            x: i % w,
        }
    }
}

/// The buffer offset of `(batch, channel, y, x)` in the tensor [`position`] describes.
#[allow(clippy::too_many_arguments)]
#[cube]
pub(super) fn offset(
    batch: u32,
    channel: u32,
    y: u32,
    x: u32,
    channels: u32,
    h: u32,
    w: u32,
    #[comptime] channels_last: bool,
) -> usize {
    let mut o = ((batch * channels + channel) * h + y) * w + x;
    if comptime![channels_last] {
        o = ((batch * h + y) * w + x) * channels + channel;
    }
    o as usize
}
