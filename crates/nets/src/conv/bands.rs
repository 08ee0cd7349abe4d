//! A convolution's weight gradient on `Cube` devices as one batched GEMM over bands of output
//! positions (split-K), for the layers whose implicit GEMM has too few tiles to fill the device.
//!
//! The weight gradient is `G · X̂ᵀ`: `[C_out, K] × [K, N]` with `K = B·H_out·W_out` output
//! positions and `N = C_in·kh·kw` (im2col columns). Burn's implicit GEMM tiles only the `C_out × N`
//! output, so a 32-channel layer at 1024² is a handful of tiles, each walking a million positions
//! alone: on an H200 such launches took 2–16 ms on 2–36 cubes and the weight gradients half the
//! `paper` step's convolution time (BENCHMARKS "Where the device time goes"). Here the positions
//! are cut into bands of `band` consecutive positions (flattened over batch, rows, columns; a
//! length that divides them where one is near, else the last band padded with zeros),
//! [`kernels::band_columns`] writes the im2col of every band (`[bands, N, band]`),
//! [`kernels::band_gradient`] the output gradient's (`[bands, C_out, band]`) — unless the gradient
//! is channels-last and the bands divide it, when its rows are the bands as they are (a launch and
//! a copy of the gradient fewer) — one batched matmul multiplies each band's pair
//! (`[bands, C_out, N]`, `bands` times the tiles) and a sum over the bands ends it — in the
//! backward pass queued ([`BandSum::Queued`]), so that one launch of
//! [`kernels::sum_bands_many`] sums those of many convolutions. The columns cost `4·N·K` bytes
//! written and read once; at most [`MAX_COLUMN_VALUES`] are held at a time (more bands run as
//! several launches, summed).
//!
//! Layouts: `x` `[B, C_in, H, W]` and the output gradient `[B, C_out, H_out, W_out]` are read in
//! either of `crate::cube_layout`'s layouts (anything else is made row-major first): from a
//! channels-last source the bands are written transposed (`[bands, band, N]` with the columns
//! ordered tap-major, `[bands, band, C_out]`), so that neighbouring threads still read
//! neighbouring values, and the matmul reads the transposed operand as a view. What the kernels
//! write is allocated contiguous (CUDA pitches Burn's ordinary allocations: `f3g_splat::cube`'s
//! module doc).

use std::cell::RefCell;

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{DType, Shape, Slice};
use burn_cubecl::CubeBackend;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;
use burn_cubecl::ops::permute_nchw_to_nhwc;

use burn_cubecl::cubecl::prelude::SequenceArg;

use crate::cube_grid::{items_per_launch, one_thread_per_value};
use crate::cube_layout::readable;

/// The cubes a weight gradient should occupy: about eight per multiprocessor of an H100/H200
/// (132 and 132), so that every one has work while others wait on memory.
const TARGET_CUBES: usize = 1024;
/// Fewest positions in a band: below this a band's GEMM is too short to amortise its tile's
/// loads, and the columns' extra traffic outweighs the parallelism.
const MIN_BAND: usize = 1024;
/// Most im2col values held at once (1 GiB of f32): more bands run as several batched GEMMs.
pub const MAX_COLUMN_VALUES: usize = 1 << 28;

/// Most products of the bands' GEMMs held by queued sums (256 MiB of f32): past it the queue
/// is launched at once, so that queueing a backward pass's sums adds at most this much to its
/// memory.
const MAX_QUEUED_VALUES: usize = 1 << 26;
/// Most sums one launch of [`kernels::sum_bands_many`] runs (a `paper` step's backward passes
/// queue 183); fewer where the device binds fewer tensors per kernel.
const MAX_SUMS_PER_LAUNCH: usize = 48;

/// When a weight gradient's sum over its bands runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BandSum {
    /// At once, Burn's sum over the bands' axis.
    Now,
    /// Queued on this thread and written by [`launch_queued_band_sums`] (where the bands' GEMM
    /// is a single launch; a split into several is summed at once).
    Queued,
}

/// How a weight gradient is split: `band` positions per band, at most `bands_per_launch`
/// bands' columns at a time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Bands {
    pub band: usize,
    pub bands_per_launch: usize,
}

impl Bands {
    /// The split for a weight gradient of `c_out × columns` over `positions`, or `None` where
    /// the implicit GEMM alone has tiles enough (or the reduction is too short to split).
    /// Tiles are counted as 64×64, the size of Burn's smaller CMMA tiles.
    pub fn plan(positions: usize, c_out: usize, columns: usize) -> Option<Self> {
        let tiles = c_out.div_ceil(64) * columns.div_ceil(64);
        let wanted = TARGET_CUBES.div_ceil(tiles);
        if wanted < 2 || positions < 2 * MIN_BAND {
            return None;
        }
        let band = positions
            .div_ceil(wanted)
            .max(MIN_BAND)
            .next_multiple_of(32);
        // A band that divides the positions, if one is within half of the planned length: a
        // channels-last gradient is then its bands as it is ([`weight_grad_in_bands`]).
        let band = (band / 2..=band)
            .rev()
            .step_by(32)
            .find(|&b| b >= MIN_BAND && positions.is_multiple_of(b))
            .unwrap_or(band);
        let bands = positions.div_ceil(band);
        (bands >= 2).then(|| Self {
            band,
            bands_per_launch: (MAX_COLUMN_VALUES / (columns * band)).clamp(1, bands),
        })
    }
}

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// The im2col of bands `first_band..`: the input value under kernel tap `t` (row `t / kw`,
    /// column `t % kw`) of channel `ci` at output position `p = (first_band + band)·band_len + k`
    /// (flattened `(b, oh, ow)`), zero in the padding and past the last position. Row-major `x`:
    /// `columns[band, ci·kh·kw + t, k]`, `k` fastest; channels-last `x`: `columns[band, k, t·C_in
    /// + ci]`, `ci` fastest — either way neighbouring threads read and write neighbouring values.
    ///
    /// One thread per position and channel, writing every tap: the position's image, row and
    /// column are divided out once for `kh·kw` values. A thread per value divided its index
    /// into band, position, channel and tap and the position into image, row and column for
    /// each value, eight or nine integer divisions and remainders per value written, and was
    /// bound by them (BENCHMARKS "The banded weight gradients' im2col": 0.5 TB/s on an H100,
    /// whose memory takes 3.35).
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn band_columns(
        x: &Tensor<f32>,
        columns: &mut Tensor<f32>,
        first_band: u32,
        band_len: u32,
        positions: u32,
        // x: [B, C_in, H, W]; the output: H_out × W_out.
        c_in: u32,
        h: u32,
        w: u32,
        w_out: u32,
        h_out: u32,
        // kernel, stride, padding, dilation (rows, then columns)
        kh: u32,
        kw: u32,
        sh: u32,
        sw: u32,
        ph: u32,
        pw: u32,
        dh: u32,
        dw: u32,
        #[comptime] channels_last: bool,
    ) {
        let g = ABSOLUTE_POS;
        let taps = kh * kw;
        if g * taps as usize >= columns.len() {
            terminate!();
        }
        let g = g as u32;
        // The thread's channel and its position within the launch's bands (`band·band_len + k`),
        // and where its first tap's value goes; tap `t` lies `t · tap_stride` further.
        let mut ci = (g / band_len) % c_in;
        let mut slot = (g / (band_len * c_in)) * band_len + g % band_len;
        let mut at = (g / band_len) * taps * band_len + g % band_len;
        let mut tap_stride = band_len;
        if comptime![channels_last] {
            ci = g % c_in;
            slot = g / c_in;
            at = slot * taps * c_in + ci;
            tap_stride = c_in;
        }
        let p = first_band * band_len + slot;
        if p < positions {
            let plane = h_out * w_out;
            let b = p / plane;
            let oh = (p % plane) / w_out;
            let ow = p % w_out;
            let top = (oh * sh) as i32 - ph as i32;
            let left = (ow * sw) as i32 - pw as i32;
            for ky in 0..kh {
                let ih = top + (ky * dh) as i32;
                for kx in 0..kw {
                    let iw = left + (kx * dw) as i32;
                    let mut value = 0.0f32;
                    if ih >= 0 && iw >= 0 && ih < h as i32 && iw < w as i32 {
                        let (ih, iw) = (ih as u32, iw as u32);
                        let mut from = ((b * c_in + ci) * h + ih) * w + iw;
                        if comptime![channels_last] {
                            from = ((b * h + ih) * w + iw) * c_in + ci;
                        }
                        value = x[from as usize];
                    }
                    columns[(at + (ky * kw + kx) * tap_stride) as usize] = value;
                }
            }
        } else {
            for t in 0..taps {
                columns[(at + t * tap_stride) as usize] = 0.0f32;
            }
        }
    }

    /// Several weight gradients' sums over their bands: table `n`'s `products[n]`
    /// (`[bands, C_out, N]`, any strides) summed over the bands into `sums[n]` (`C_out·N`
    /// values, gapless). One thread per value of all the tables laid end to end, so that no
    /// cube idles on a table shorter than the longest; each runs its sum down the bands, and
    /// neighbouring threads read neighbouring values.
    #[cube(launch)]
    pub fn sum_bands_many(
        products: &Sequence<OwnedTensor<f32>>,
        sums: &mut Sequence<OwnedTensor<f32>>,
        #[comptime] count: usize,
    ) {
        let g = (CUBE_POS_Y * CUBE_COUNT_X + CUBE_POS_X) * CUBE_DIM_X + UNIT_POS_X;
        let mut start = 0u32;
        #[unroll]
        for n in 0..count {
            let table = products.index(n);
            let columns = table.shape(2) as u32;
            let values = table.shape(1) as u32 * columns;
            if g >= start && g < start + values {
                let j = g - start;
                let at =
                    (j / columns) * table.stride(1) as u32 + (j % columns) * table.stride(2) as u32;
                let step = table.stride(0) as u32;
                let mut sum = 0.0f32;
                for band in 0..table.shape(0) as u32 {
                    sum += table[(band * step + at) as usize];
                }
                sums.index_mut(n)[j as usize] = sum;
            }
            start += values;
        }
    }

    /// The output gradient of channel `c` at position `(first_band + band)·band_len + k`, zero
    /// past the last: `bands[band, c, k]` (`k` fastest) from a row-major `grad`,
    /// `bands[band, k, c]` (`c` fastest) from a channels-last one.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn band_gradient(
        grad: &Tensor<f32>,
        bands: &mut Tensor<f32>,
        first_band: u32,
        band_len: u32,
        positions: u32,
        c_out: u32,
        plane: u32,
        #[comptime] channels_last: bool,
    ) {
        let g = ABSOLUTE_POS;
        if g >= bands.len() {
            terminate!();
        }
        let g = g as u32;
        let mut k = g % band_len;
        let mut c = (g / band_len) % c_out;
        if comptime![channels_last] {
            c = g % c_out;
            k = (g / c_out) % band_len;
        }
        let band = g / (band_len * c_out);
        let p = (first_band + band) * band_len + k;
        let mut value = 0.0f32;
        if p < positions {
            let mut at = ((p / plane) * c_out + c) * plane + p % plane;
            if comptime![channels_last] {
                at = p * c_out + c;
            }
            value = grad[at as usize];
        }
        bands[g as usize] = value;
    }
}

/// The weight gradient of a convolution of `x` (groups 1, symmetric padding) given its output
/// gradient `grad`, in bands where [`Bands::plan`] splits it, their sum queued
/// ([`BandSum::Queued`]); `None` where it does not split (the caller runs the implicit GEMM).
pub fn weight_grad_split(
    x: FloatTensor<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
    weight_shape: Shape,
    options: &ConvOptions<2>,
) -> Option<FloatTensor<CubeBackend>> {
    let [batch, c_in, _, _] = x.shape().dims();
    let [c_out, _, kh, kw] = weight_shape.dims();
    let [_, _, h_out, w_out] = grad.shape().dims();
    let bands = Bands::plan(batch * h_out * w_out, c_out, c_in * kh * kw)?;
    weight_grad_in_bands(x, grad, weight_shape, options, bands, BandSum::Queued)
}

/// The weight gradient `[C_out, C_in, kh, kw]` of a convolution of `x` (groups 1, symmetric
/// padding) given its output gradient `grad`, split as `bands` says, summed over the bands as
/// `sum` says (a permuted view of a `[C_out, kh, kw, C_in]` tensor where `x` is
/// channels-last). Values are indexed with 32 bits: `None` where a tensor is too large for that.
pub fn weight_grad_in_bands(
    x: FloatTensor<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
    weight_shape: Shape,
    options: &ConvOptions<2>,
    bands: Bands,
    sum: BandSum,
) -> Option<FloatTensor<CubeBackend>> {
    let [batch, c_in, h, w] = x.shape().dims();
    let [_, c_out, h_out, w_out] = grad.shape().dims();
    let [_, _, kh, kw] = weight_shape.dims();
    let positions = batch * h_out * w_out;
    let columns = c_in * kh * kw;
    let band_count = positions.div_ceil(bands.band);
    let fits = |values: usize| u32::try_from(values).is_ok();
    if positions == 0
        || !fits(x.shape().num_elements())
        || !fits(grad.shape().num_elements())
        || !fits(band_count * bands.band * columns.max(c_out))
    {
        return None;
    }
    let u = |v: usize| v as u32;
    let ((x, x_last), (grad, grad_last)) = (readable(x), readable(grad));
    let (client, device) = (x.client.clone(), x.device.clone());
    let per_launch = bands.bands_per_launch.max(1);
    // A channels-last gradient is `[positions, C_out]` row-major: where whole bands cover the
    // positions, `[bands, band, C_out]` as it is, and no copy into bands is needed.
    let grad_bands = (grad_last && positions == band_count * bands.band).then(|| {
        let rows = permute_nchw_to_nhwc(grad.clone());
        CubeBackend::float_reshape(rows, Shape::new([band_count, bands.band, c_out]))
    });
    // Bands `first..first + count`: `[count, C_out, N]`, their products.
    let products = |first: usize| {
        let count = per_launch.min(band_count - first);
        // `[count, rows, band]`, or `[count, band, rows]` where the source is channels-last.
        let empty = |rows: usize, transposed: bool| {
            let shape = if transposed {
                [count, bands.band, rows]
            } else {
                [count, rows, bands.band]
            };
            empty_device_contiguous_dtype(client.clone(), device.clone(), shape.into(), DType::F32)
        };
        let cols = empty(columns, x_last);
        // A thread per position and input channel ([`kernels::band_columns`]).
        let (cubes, cube) = one_thread_per_value(count * c_in * bands.band);
        kernels::band_columns::launch(
            &client,
            cubes,
            cube,
            x.clone().into_tensor_arg(),
            cols.clone().into_tensor_arg(),
            u(first),
            u(bands.band),
            u(positions),
            u(c_in),
            u(h),
            u(w),
            u(w_out),
            u(h_out),
            u(kh),
            u(kw),
            u(options.stride[0]),
            u(options.stride[1]),
            u(options.padding[0].0),
            u(options.padding[1].0),
            u(options.dilation[0]),
            u(options.dilation[1]),
            x_last,
        );
        let gradient = match &grad_bands {
            // Bands `first..first + count` of the gradient's rows, a view where aligned.
            Some(all) => {
                CubeBackend::float_slice(all.clone(), &[Slice::from(first..first + count)])
            }
            None => {
                let gradient = empty(c_out, grad_last);
                let (cubes, cube) = one_thread_per_value(count * c_out * bands.band);
                kernels::band_gradient::launch(
                    &client,
                    cubes,
                    cube,
                    grad.clone().into_tensor_arg(),
                    gradient.clone().into_tensor_arg(),
                    u(first),
                    u(bands.band),
                    u(positions),
                    u(c_out),
                    u(h_out * w_out),
                    grad_last,
                );
                gradient
            }
        };
        // [count, C_out, band] × [count, band, N] → [count, C_out, N]; the operands stored the
        // other way round are transposed views the matmul reads as they are.
        let lhs = if grad_last {
            CubeBackend::float_swap_dims(gradient, 1, 2)
        } else {
            gradient
        };
        let rhs = if x_last {
            cols
        } else {
            CubeBackend::float_swap_dims(cols, 1, 2)
        };
        CubeBackend::float_matmul(lhs, rhs)
    };
    let queued = sum == BandSum::Queued && per_launch >= band_count;
    let sum = if queued && fits(band_count * c_out * columns) {
        queue_band_sum(products(0))
    } else {
        let summed = |first| CubeBackend::float_sum_dim(products(first), 0);
        let mut sum = summed(0);
        for first in (per_launch..band_count).step_by(per_launch) {
            sum = CubeBackend::float_add(sum, summed(first));
        }
        sum
    };
    if x_last {
        // Columns ordered (tap, channel): `[C_out, kh, kw, C_in]`, seen as the weight's layout.
        let sum = CubeBackend::float_reshape(sum, Shape::new([c_out, kh, kw, c_in]));
        return Some(CubeBackend::float_permute(sum, &[0, 3, 1, 2]));
    }
    Some(CubeBackend::float_reshape(
        sum,
        Shape::new([c_out, c_in, kh, kw]),
    ))
}

/// A sum over the bands queued by [`queue_band_sum`]: the bands' products `[bands, C_out, N]`
/// and their `[C_out, N]` sum, allocated and not yet written.
struct QueuedBandSum {
    products: FloatTensor<CubeBackend>,
    sum: FloatTensor<CubeBackend>,
}

thread_local! {
    /// Sums queued by [`queue_band_sum`], launched by [`launch_queued_band_sums`].
    static BAND_SUMS: RefCell<Vec<QueuedBandSum>> = const { RefCell::new(Vec::new()) };
}

/// Queues the sum of `products` (`[bands, C_out, N]`) over its bands on this thread and
/// returns it (`[C_out, N]`), allocated now and written by [`launch_queued_band_sums`] (one
/// stream per device: before any later kernel reads it). Past [`MAX_QUEUED_VALUES`] held the
/// queue is launched at once.
fn queue_band_sum(products: FloatTensor<CubeBackend>) -> FloatTensor<CubeBackend> {
    let [_, c_out, columns] = products.shape().dims();
    let sum = empty_device_contiguous_dtype(
        products.client.clone(),
        products.device.clone(),
        Shape::new([c_out, columns]),
        DType::F32,
    );
    let held = BAND_SUMS.with(|queue| {
        let mut queue = queue.borrow_mut();
        queue.push(QueuedBandSum {
            products,
            sum: sum.clone(),
        });
        queue
            .iter()
            .map(|q| q.products.shape().num_elements())
            .sum::<usize>()
    });
    if held > MAX_QUEUED_VALUES {
        launch_queued_band_sums();
    }
    sum
}

/// Launches the sums over the bands queued on this thread ([`kernels::sum_bands_many`], up to
/// [`MAX_SUMS_PER_LAUNCH`] a launch). Every launch binds the same number of sums, a short last
/// one made up with fillers (one-value sums of an unwritten value): the number is a
/// compile-time constant of the kernel, and the queue's length varies with where the memory
/// bound launched it, so each length would be another kernel to compile (six in a `paper`
/// step, where one will do).
pub fn launch_queued_band_sums() {
    let queue: Vec<QueuedBandSum> = BAND_SUMS.with(|q| std::mem::take(&mut *q.borrow_mut()));
    let Some(first) = queue.first() else {
        return;
    };
    let (client, device) = (first.products.client.clone(), first.products.device.clone());
    let empty = |shape: Shape| {
        empty_device_contiguous_dtype(client.clone(), device.clone(), shape, DType::F32)
    };
    let filler = QueuedBandSum {
        products: empty(Shape::new([1, 1, 1])),
        sum: empty(Shape::new([1])),
    };
    let count = items_per_launch(&client, 2, 0, MAX_SUMS_PER_LAUNCH);
    for chunk in queue.chunks(count) {
        let (mut products, mut sums) = (SequenceArg::new(), SequenceArg::new());
        let fillers = std::iter::repeat_n(&filler, count - chunk.len());
        for q in chunk.iter().chain(fillers) {
            products.push(q.products.clone().into_tensor_arg());
            sums.push(q.sum.clone().into_tensor_arg());
        }
        let values = chunk
            .iter()
            .map(|q| q.sum.shape().num_elements())
            .sum::<usize>()
            + count;
        let (cubes, cube) = one_thread_per_value(values);
        kernels::sum_bands_many::launch(&client, cubes, cube, products, sums, count);
    }
}
