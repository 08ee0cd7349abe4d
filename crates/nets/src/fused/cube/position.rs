//! Where a value sits in the gapless `[B, C, H, W]` tensors the kernels read and write, stored
//! row-major or channels-last (`crate::cube_layout`), and the ×2 up-sampling's taps: the index
//! arithmetic the resampling kernels share.

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

/// The sample `2i ∓ 1`'s neighbour along an axis of `n` samples: output `o` of the ×2
/// up-sampling blends sample `o / 2` (¾) with this one (¼), the edge repeated.
#[cube]
pub(super) fn upsample_neighbour(o: u32, n: u32) -> u32 {
    let i = o / 2;
    let mut neighbour = i;
    if o % 2 == 1 {
        if i + 1 < n {
            neighbour = i + 1;
        }
    } else if i > 0 {
        neighbour = i - 1;
    }
    neighbour
}

/// The weight with which output `2i + tap − 1` of the ×2 up-sampling (along an axis of `n`
/// samples) reads sample `i`: ¼ from the odd output before and the even one after, ¾ from
/// its own two, the edge outputs reading their edge sample twice.
#[cube]
pub(super) fn upsample_adjoint_weight(i: u32, n: u32, tap: u32) -> f32 {
    let mut weight = 0.0f32;
    if tap == 0 {
        if i > 0 {
            weight = 0.25;
        }
    } else if tap == 1 {
        weight = 0.75;
        if i == 0 {
            weight = 1.0;
        }
    } else if tap == 2 {
        weight = 0.75;
        if i + 1 == n {
            weight = 1.0;
        }
    } else if i + 1 < n {
        weight = 0.25;
    }
    weight
}
