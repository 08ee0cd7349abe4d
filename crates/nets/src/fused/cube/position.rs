//! Where a value sits in the gapless `[B, C, H, W]` tensors the kernels read and write, stored
//! row-major or channels-last (`crate::cube_layout`), the ×2 up-sampling's taps and the Haar
//! transform's sub-bands: the arithmetic the resampling kernels share.

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

/// The buffer offset of `(batch, channel, y, x)` in `t`, a `[B, C, H, W]` view with any strides
/// (a slice of a concatenation's gradient, a pitched convolution output): read so, a tensor
/// needs no copy into one of the two layouts first.
#[cube]
pub(super) fn strided(t: &Tensor<f32>, batch: u32, channel: u32, y: u32, x: u32) -> usize {
    batch as usize * t.stride(0)
        + channel as usize * t.stride(1)
        + y as usize * t.stride(2)
        + x as usize * t.stride(3)
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

/// Sub-band `band` ∈ (LL, LH, HL, HH) of the 2 × 2 block `(p q / r s)`: `½(p ± q ± r ± s)`, HL
/// and HH negating the right column (`q`, `s`), LH and HH the bottom row (`r`, `s`).
#[cube]
pub(super) fn analysed(p: f32, q: f32, r: f32, s: f32, band: u32) -> f32 {
    let mut sign_q = 1.0f32;
    if band >= 2 {
        sign_q = -1.0f32;
    }
    let mut sign_r = 1.0f32;
    if band % 2 == 1 {
        sign_r = -1.0f32;
    }
    0.5f32 * (p + sign_q * q + sign_r * r + sign_q * sign_r * s)
}

/// Pixel `(i, j)` of channel `c` of the Haar synthesis of `bands` (`[B, 4·channels, h, w]`,
/// channels-last with `last`): `½(a ± b ± c ± d)` of the four sub-bands at `(i / 2, j / 2)`,
/// the bottom row negating LH, the right column HL, the corner both (HH twice).
#[allow(clippy::too_many_arguments)]
#[cube]
pub(super) fn synthesised(
    bands: &Tensor<f32>,
    batch: u32,
    c: u32,
    i: u32,
    j: u32,
    h: u32,
    w: u32,
    channels4: u32,
    #[comptime] last: bool,
) -> f32 {
    let (y, x, first) = (i / 2, j / 2, 4 * c);
    let ll = bands[offset(batch, first, y, x, channels4, h, w, last)];
    let lh = bands[offset(batch, first + 1, y, x, channels4, h, w, last)];
    let hl = bands[offset(batch, first + 2, y, x, channels4, h, w, last)];
    let hh = bands[offset(batch, first + 3, y, x, channels4, h, w, last)];
    let mut sign_b = 1.0f32;
    if i % 2 == 1 {
        sign_b = -1.0f32;
    }
    let mut sign_c = 1.0f32;
    if j % 2 == 1 {
        sign_c = -1.0f32;
    }
    0.5f32 * (ll + sign_b * lh + sign_c * hl + sign_b * sign_c * hh)
}
