//! The two layouts the crate's CubeCL kernels read and write (`fused`, `conv::bands`, `adam`):
//! gapless `[B, C, H, W]` tensors stored row-major or channels-last, a permuted view of a row-major
//! `[B, H, W, C]` — the layout Burn's implicit-GEMM convolutions compute in and hand back (their
//! outputs and input gradients are such views). A kernel that reads channels-last as it is spares a
//! copy of the activation to row-major, and one that writes it spares the next convolution the copy
//! back.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;
use burn_cubecl::ops::{permute_nchw_to_nhwc, permute_nhwc_to_nchw};

/// Whether `t` (`[B, C, H, W]`) is stored channels-last without gaps.
pub(crate) fn channels_last(t: &FloatTensor<CubeBackend>) -> bool {
    pixel_stride(t) == Some(t.shape()[1])
}

/// `t` stored channels-last without gaps: as it is where it is so, else copied.
pub(crate) fn into_channels_last(t: FloatTensor<CubeBackend>) -> FloatTensor<CubeBackend> {
    if channels_last(&t) {
        t
    } else {
        permute_nhwc_to_nchw(into_contiguous(permute_nchw_to_nhwc(t)))
    }
}

/// The values from one pixel to the next of a `t` (`[B, C, H, W]`) stored channels-last with
/// gaps at most between pixels, `C` or more; `None` for any other layout. Why: CUDA pitches a
/// convolution's output row to a power of two bytes, so a ToRGB's map of 12 channels comes
/// back with 16 values a pixel, which a kernel that knows the stride reads without a copy.
pub(crate) fn pixel_stride(t: &FloatTensor<CubeBackend>) -> Option<usize> {
    let [_, c, h, w] = t.shape().dims();
    let strides = t.meta.strides();
    let pixel = strides[3];
    (strides[1] == 1 && pixel >= c && strides[..] == [h * w * pixel, 1, w * pixel, pixel])
        .then_some(pixel)
}

/// `t` as the kernels read it, and whether that is channels-last: a gapless channels-last
/// tensor as it is, any other made row-major.
pub(crate) fn readable(t: FloatTensor<CubeBackend>) -> (FloatTensor<CubeBackend>, bool) {
    if channels_last(&t) {
        (t, true)
    } else {
        (into_contiguous(t), false)
    }
}

/// A gapless f32 tensor of `dims` (`[B, C, H, W]`) on `like`'s device, channels-last or
/// row-major. Never Burn's ordinary allocation, which CUDA pitches (`f3g_splat::cube`'s module
/// doc).
pub(crate) fn empty_in_layout(
    like: &FloatTensor<CubeBackend>,
    [b, c, h, w]: [usize; 4],
    channels_last: bool,
) -> FloatTensor<CubeBackend> {
    let stored = if channels_last {
        [b, h, w, c]
    } else {
        [b, c, h, w]
    };
    let empty = empty_device_contiguous_dtype(
        like.client.clone(),
        like.device.clone(),
        Shape::new(stored),
        DType::F32,
    );
    if channels_last {
        permute_nhwc_to_nchw(empty)
    } else {
        empty
    }
}
