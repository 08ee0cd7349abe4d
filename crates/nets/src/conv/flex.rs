//! `impl ConvBackend for Flex`: the convolution, its input gradient and its weight gradient as
//! im2col + GEMM on row-major NCHW data (the `gemm` crate Burn's Flex uses itself).
//!
//! Why not Burn's: Flex 0.22 converts every input to NHWC and back and tiles 512 positions at a
//! time, and derives the weight gradient as a convolution of the swapped input with the output
//! gradient as a kernel (one N = 9 GEMM per input channel); on the StyleUNets' ≤ 32-channel
//! layers that ran at 15–20 GFLOP/s. Here, with `X̂` the im2col of an image (`C_in·kh·kw` rows,
//! one column per output position) and `W` the weight as `[C_out, C_in·kh·kw]`:
//! - forward: `Y = W · X̂`, written straight into the NCHW output (a 1×1 stride-1 convolution
//!   reads the image itself as `X̂`);
//! - input gradient: with stride 1 it is the forward convolution of the output gradient with the
//!   kernel flipped and its channel axes swapped (padding `d·(k−1) − p`); otherwise
//!   `col2im(Wᵀ · G)`, one image per thread;
//! - weight gradient: `dW = Σ_tiles G_tile · X̂_tileᵀ`.
//!
//! Work split: the output positions of every image are cut into tiles whose im2col fits
//! [`TILE_FLOATS`]; tiles run in parallel, each with a single-threaded GEMM (the weight gradient
//! sums per thread over a contiguous run of tiles); with a single tile the GEMM itself runs on
//! all threads instead. Grouped convolutions and other float types take Burn's route.

use std::cell::RefCell;
use std::ops::Range;

use burn::backend::Flex;
use burn::backend::TensorMetadata;
use burn::backend::ops::ModuleOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::DType;
use burn::tensor::ops::ConvOptions;
use rayon::prelude::*;

use super::profile::{self, Phase};
use super::{ConvBackend, output_side};
use crate::host::{from_values, host_f32};

/// Floats of im2col per tile (1 MiB): a tile's columns stay in cache while its GEMM reads them.
const TILE_FLOATS: usize = 1 << 18;
/// The fewest output positions per tile (a dimension of every GEMM), however many rows the
/// im2col has.
const MIN_TILE: usize = 64;

thread_local! {
    /// Each thread's column buffer, kept from one convolution to the next: im2col and the
    /// input gradient's GEMM write every value they use, so it needs no zeroing, whereas a
    /// fresh 1 MiB buffer per tile was zeroed (and, past glibc's mmap threshold, faulted in
    /// page by page) every time.
    static COLUMNS: RefCell<Vec<f32>> = const { RefCell::new(Vec::new()) };
}

/// Runs `f` on this thread's column buffer cut to `len` values of unspecified content
/// (a fresh zeroed one if the thread's buffer is in use further up its stack: a thread waiting
/// in a parallel GEMM may pick up another tile).
fn with_columns<R>(len: usize, f: impl FnOnce(&mut [f32]) -> R) -> R {
    COLUMNS.with(|cell| match cell.try_borrow_mut() {
        Ok(mut columns) => {
            if columns.len() < len {
                columns.resize(len, 0.0);
            }
            f(&mut columns[..len])
        }
        Err(_) => f(&mut vec![0.0; len]),
    })
}

impl ConvBackend for Flex {
    fn conv2d_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        let shapes = [dims(&x), dims(&weight)];
        profile::timed(
            Phase::Forward,
            || forward_tensor(x, weight, options),
            |out| [shapes[0], shapes[1], dims(out)],
        )
    }

    fn conv2d_input_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        let shapes = [dims(&x), dims(&weight), dims(&grad)];
        profile::timed(
            Phase::InputGrad,
            || input_grad_tensor(x, weight, grad, options),
            |_| shapes,
        )
    }

    /// Nothing is queued on the CPU: the gradient is computed at once.
    fn conv2d_weight_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        let shapes = [dims(&x), dims(&weight), dims(&grad)];
        profile::timed(
            Phase::WeightGrad,
            || weight_grad_tensor(x, weight, grad, options),
            |_| shapes,
        )
    }

    fn conv2d_weight_grads_launch_queued(anchor: FloatTensor<Self>) -> FloatTensor<Self> {
        anchor
    }
}

fn dims(t: &FloatTensor<Flex>) -> [usize; 4] {
    t.shape().dims()
}

/// The shapes of a convolution the GEMM route computes: one group, f32 tensors, a non-empty
/// output. `None` sends the convolution to Burn's route.
fn gemm_geometry(
    tensors: &[&FloatTensor<Flex>],
    input: [usize; 4],
    weight: [usize; 4],
    options: &ConvOptions<2>,
) -> Option<Geometry> {
    let f32_only = tensors.iter().all(|t| t.dtype() == DType::F32);
    if options.groups != 1 || !f32_only || weight[1] != input[1] {
        return None;
    }
    Geometry::new(input, weight, options.clone())
}

/// [`gemm_geometry`] of a gradient, whose output gradient must have the output's shape.
fn gradient_geometry(
    x: &FloatTensor<Flex>,
    weight: &FloatTensor<Flex>,
    grad: &FloatTensor<Flex>,
    options: &ConvOptions<2>,
) -> Option<Geometry> {
    gemm_geometry(&[x, weight, grad], dims(x), dims(weight), options)
        .filter(|geometry| geometry.output == dims(grad))
}

/// [`forward`] on tensors.
fn forward_tensor(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    options: ConvOptions<2>,
) -> FloatTensor<Flex> {
    let Some(geometry) = gemm_geometry(&[&x, &weight], dims(&x), dims(&weight), &options) else {
        return Flex::conv2d(x, weight, None, options);
    };
    let values = forward(&geometry, &host_f32(&x), &host_f32(&weight));
    from_values(values, geometry.output.to_vec())
}

/// The input gradient on tensors: with stride 1 the [`forward`] of the output gradient with
/// the flipped, channel-swapped kernel ([`Geometry::input_grad_as_forward`]), otherwise
/// [`input_grad_col2im`].
fn input_grad_tensor(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    grad: FloatTensor<Flex>,
    options: ConvOptions<2>,
) -> FloatTensor<Flex> {
    let weight_shape = dims(&weight);
    let Some(geometry) = gradient_geometry(&x, &weight, &grad, &options) else {
        return Flex::conv2d_x_backward(x, weight, grad, options);
    };
    let values = match geometry.input_grad_as_forward() {
        Some(transposed) => forward(
            &transposed,
            &host_f32(&grad),
            &flip_and_swap_channels(&host_f32(&weight), weight_shape),
        ),
        None => input_grad_col2im(&geometry, &host_f32(&weight), &host_f32(&grad)),
    };
    from_values(values, geometry.input.to_vec())
}

/// [`weight_grad`] on tensors.
fn weight_grad_tensor(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    grad: FloatTensor<Flex>,
    options: ConvOptions<2>,
) -> FloatTensor<Flex> {
    let weight_shape = dims(&weight);
    let Some(geometry) = gradient_geometry(&x, &weight, &grad, &options) else {
        return Flex::conv2d_weight_backward(x, weight, grad, options);
    };
    from_values(
        weight_grad(&geometry, &host_f32(&x), &host_f32(&grad)),
        weight_shape.to_vec(),
    )
}

/// `[C_out, C_in, kh, kw]` → `[C_in, C_out, kh, kw]` with both kernel axes reversed: the kernel
/// whose convolution of the output gradient is the input gradient of a stride-1 convolution.
fn flip_and_swap_channels(weight: &[f32], [cout, cin, kh, kw]: [usize; 4]) -> Vec<f32> {
    let mut out = vec![0.0f32; weight.len()];
    for co in 0..cout {
        for ci in 0..cin {
            for ky in 0..kh {
                for kx in 0..kw {
                    out[((ci * cout + co) * kh + kh - 1 - ky) * kw + kw - 1 - kx] =
                        weight[((co * cin + ci) * kh + ky) * kw + kx];
                }
            }
        }
    }
    out
}

/// The shapes of one convolution.
struct Geometry {
    /// `[B, C_in, H, W]`
    input: [usize; 4],
    /// `[B, C_out, H_out, W_out]`
    output: [usize; 4],
    /// `[kh, kw]`
    kernel: [usize; 2],
    options: ConvOptions<2>,
}

impl Geometry {
    /// The geometry of `input ∗ weight` (`weight` `[C_out, C_in, kh, kw]`), `None` when the
    /// output would be empty or the kernel is larger than the padded input.
    fn new(input: [usize; 4], weight: [usize; 4], options: ConvOptions<2>) -> Option<Self> {
        let kernel = [weight[2], weight[3]];
        let side = |axis: usize| output_side(input[2 + axis], kernel[axis], &options, axis);
        let output = [input[0], weight[0], side(0)?, side(1)?];
        (output.iter().all(|&d| d > 0) && input[1] > 0).then_some(Self {
            input,
            output,
            kernel,
            options,
        })
    }

    /// Rows of the im2col: `C_in · kh · kw`.
    fn rows(&self) -> usize {
        self.input[1] * self.kernel[0] * self.kernel[1]
    }

    /// Output positions per image.
    fn positions(&self) -> usize {
        self.output[2] * self.output[3]
    }

    /// A 1×1 stride-1 convolution without padding: the image is its own im2col.
    fn is_pointwise(&self) -> bool {
        self.kernel == [1, 1]
            && self.options.stride == [1, 1]
            && self.options.padding == [(0, 0), (0, 0)]
    }

    /// With stride 1, `dx` is the convolution of the output gradient with the flipped,
    /// channel-swapped kernel, padded by `d·(k−1) − p` on each side; `None` for other strides or
    /// when a padding exceeds `d·(k−1)`.
    fn input_grad_as_forward(&self) -> Option<Geometry> {
        if self.options.stride != [1, 1] {
            return None;
        }
        let mut padding = [(0, 0); 2];
        for (axis, pad) in padding.iter_mut().enumerate() {
            let reach = self.options.dilation[axis] * (self.kernel[axis] - 1);
            let (before, after) = self.options.padding[axis];
            *pad = (reach.checked_sub(before)?, reach.checked_sub(after)?);
        }
        let options = ConvOptions {
            stride: [1, 1],
            padding,
            dilation: self.options.dilation,
            groups: 1,
        };
        let weight = [
            self.input[1],
            self.output[1],
            self.kernel[0],
            self.kernel[1],
        ];
        Geometry::new(self.output, weight, options).filter(|g| g.output == self.input)
    }
}

/// How the output positions are cut into tasks.
struct Tiling {
    /// Output positions per tile.
    tile: usize,
    tiles_per_image: usize,
    /// `batch · tiles_per_image`
    tasks: usize,
}

impl Tiling {
    fn new(geometry: &Geometry) -> Self {
        let positions = geometry.positions();
        let tile = (TILE_FLOATS / geometry.rows().max(1))
            .max(MIN_TILE)
            .min(positions);
        let tiles_per_image = positions.div_ceil(tile);
        Self {
            tile,
            tiles_per_image,
            tasks: geometry.input[0] * tiles_per_image,
        }
    }

    /// Task `task` as (image, first position, positions).
    fn task(&self, task: usize, positions: usize) -> (usize, usize, usize) {
        let (image, first) = (
            task / self.tiles_per_image,
            (task % self.tiles_per_image) * self.tile,
        );
        (image, first, self.tile.min(positions - first))
    }

    /// The GEMM's own threads: all of them when there is a single task, none otherwise (the
    /// tasks run in parallel instead).
    fn gemm_parallelism(tasks: usize) -> gemm::Parallelism {
        if tasks == 1 {
            gemm::Parallelism::Rayon(0)
        } else {
            gemm::Parallelism::None
        }
    }
}

/// A pointer that tasks writing disjoint parts of one buffer share.
#[derive(Clone, Copy)]
struct SharedOutput(*mut f32);

// SAFETY: the tasks that share it write disjoint elements (see `forward`).
unsafe impl Send for SharedOutput {}
// SAFETY: shared, it is only copied; the writes through it are to disjoint elements, as above.
unsafe impl Sync for SharedOutput {}

impl SharedOutput {
    /// The pointer (a method, so closures capture the whole `Sync` wrapper).
    fn at(self, offset: usize) -> *mut f32 {
        self.0.wrapping_add(offset)
    }
}

/// `Y = W · X̂` per tile, written into the NCHW output (`[B, C_out, H_out, W_out]`).
fn forward(geometry: &Geometry, x: &[f32], weight: &[f32]) -> Vec<f32> {
    let [batch, channels_in, height, width] = geometry.input;
    let channels_out = geometry.output[1];
    let (rows, positions) = (geometry.rows(), geometry.positions());
    // The GEMM below reads and writes through raw pointers: the slices must hold these shapes.
    assert_eq!(x.len(), batch * channels_in * height * width, "input");
    assert_eq!(weight.len(), channels_out * rows, "weight");
    let total = batch * channels_out * positions;
    // Not zeroed: the GEMMs below write every output value (`read_dst` false).
    let mut out: Vec<f32> = Vec::with_capacity(total);
    let tiling = Tiling::new(geometry);
    let parallelism = Tiling::gemm_parallelism(tiling.tasks);
    let pointwise = geometry.is_pointwise();
    let image_len = channels_in * height * width;
    let output = SharedOutput(out.as_mut_ptr());
    (0..tiling.tasks).into_par_iter().for_each(|task| {
        let (image, first, len) = tiling.task(task, positions);
        let image_x = &x[image * image_len..(image + 1) * image_len];
        let multiply = |rhs: *const f32, rhs_row_stride: usize| {
            // out[image, co, first + j] = Σ_r weight[co, r] · X̂[r, j]
            // SAFETY: dst (co, j) at image·C_out·positions + co·positions + first + j lies in
            // `out`'s allocation, and no two tasks share an (image, position); lhs (co, r) at
            // co·rows + r < C_out·rows; rhs (r, j) at r·stride + j stays inside the im2col
            // (r·len + j < rows·len) or, pointwise, inside the image (r·positions + first + j <
            // C_in·positions).
            unsafe {
                gemm::gemm(
                    channels_out,
                    len,
                    rows,
                    output.at(image * channels_out * positions + first),
                    1,
                    positions as isize,
                    false,
                    weight.as_ptr(),
                    1,
                    rows as isize,
                    rhs,
                    1,
                    rhs_row_stride as isize,
                    0.0,
                    1.0,
                    false,
                    false,
                    false,
                    parallelism,
                );
            }
        };
        if pointwise {
            multiply(image_x[first..].as_ptr(), positions);
        } else {
            with_columns(rows * len, |columns| {
                im2col(geometry, image_x, first, columns);
                multiply(columns.as_ptr(), len);
            });
        }
    });
    // SAFETY: the tasks cover every (image, position) and each GEMM wrote all C_out channels
    // there, so all `total` values are initialised.
    unsafe { out.set_len(total) };
    out
}

/// `dx = col2im(Wᵀ · G)`, one image per task (the tiles of an image overlap in `dx`).
fn input_grad_col2im(geometry: &Geometry, weight: &[f32], grad: &[f32]) -> Vec<f32> {
    let [batch, channels_in, height, width] = geometry.input;
    let channels_out = geometry.output[1];
    let (rows, positions) = (geometry.rows(), geometry.positions());
    assert_eq!(weight.len(), channels_out * rows, "weight");
    assert_eq!(
        grad.len(),
        batch * channels_out * positions,
        "output gradient"
    );
    let image_len = channels_in * height * width;
    let mut dx = vec![0.0f32; batch * image_len];
    let tile = Tiling::new(geometry).tile;
    let parallelism = Tiling::gemm_parallelism(batch);
    dx.par_chunks_mut(image_len)
        .zip(grad.par_chunks(channels_out * positions))
        .for_each(|(dx_image, grad_image)| {
            with_columns(rows * tile, |columns| {
                for first in (0..positions).step_by(tile) {
                    let len = tile.min(positions - first);
                    let columns = &mut columns[..rows * len];
                    // columns[r, j] = Σ_co weight[co, r] · grad[co, first + j]
                    // SAFETY: dst (r, j) at r·len + j < rows·len; lhs (r, co) at co·rows + r <
                    // C_out·rows; rhs (co, j) at co·positions + first + j < C_out·positions.
                    unsafe {
                        gemm::gemm(
                            rows,
                            len,
                            channels_out,
                            columns.as_mut_ptr(),
                            1,
                            len as isize,
                            false,
                            weight.as_ptr(),
                            rows as isize,
                            1,
                            grad_image[first..].as_ptr(),
                            1,
                            positions as isize,
                            0.0,
                            1.0,
                            false,
                            false,
                            false,
                            parallelism,
                        );
                    }
                    col2im(geometry, columns, first, dx_image);
                }
            })
        });
    dx
}

/// `dW` (`[C_out, C_in, kh, kw]`, row-major) of a convolution with one group, from the input
/// `x` and the output gradient `grad` (both row-major): `Σ_tiles G_tile · X̂_tileᵀ`, summed per
/// thread over a contiguous run of tiles.
fn weight_grad(geometry: &Geometry, x: &[f32], grad: &[f32]) -> Vec<f32> {
    let [batch, channels_in, height, width] = geometry.input;
    let channels_out = geometry.output[1];
    let (rows, positions) = (geometry.rows(), geometry.positions());
    let zeros = || vec![0.0f32; channels_out * rows];
    // The GEMM below reads through raw pointers: the slices must hold exactly these shapes.
    assert_eq!(x.len(), batch * channels_in * height * width, "input");
    assert_eq!(
        grad.len(),
        batch * channels_out * positions,
        "output gradient"
    );
    let tiling = Tiling::new(geometry);
    let threads = rayon::current_num_threads().clamp(1, tiling.tasks);
    let parallelism = Tiling::gemm_parallelism(threads);
    let per_thread = tiling.tasks.div_ceil(threads);
    let image_len = channels_in * height * width;
    (0..threads)
        .into_par_iter()
        .map(|thread| {
            let mut sum = zeros();
            with_columns(rows * tiling.tile, |columns| {
                for task in thread * per_thread..((thread + 1) * per_thread).min(tiling.tasks) {
                    let (image, first, len) = tiling.task(task, positions);
                    let columns = &mut columns[..rows * len];
                    im2col(
                        geometry,
                        &x[image * image_len..(image + 1) * image_len],
                        first,
                        columns,
                    );
                    let grad_tile = &grad[image * channels_out * positions + first..];
                    // sum[co, r] += Σ_j grad[co, first + j] · columns[r, j]
                    // SAFETY: every index the GEMM reads or writes lies inside the slices above:
                    // lhs (co, j) at co·positions + j < channels_out·positions − first, rhs (j, r) at
                    // r·len + j < rows·len, dst (co, r) at co·rows + r < channels_out·rows.
                    unsafe {
                        gemm::gemm(
                            channels_out,
                            rows,
                            len,
                            sum.as_mut_ptr(),
                            1,
                            rows as isize,
                            true,
                            grad_tile.as_ptr(),
                            1,
                            positions as isize,
                            columns.as_ptr(),
                            len as isize,
                            1,
                            1.0,
                            1.0,
                            false,
                            false,
                            false,
                            parallelism,
                        );
                    }
                }
            });
            sum
        })
        .reduce_with(|mut total, part| {
            total.iter_mut().zip(part).for_each(|(t, p)| *t += p);
            total
        })
        .unwrap_or_else(zeros)
}

/// One run of im2col columns on one output row, for one kernel tap (`row` of the im2col).
struct Run {
    row: usize,
    /// The run's columns.
    columns: Range<usize>,
    /// The columns whose tap falls inside the image (a sub-range of `columns`).
    inside: Range<usize>,
    /// The image index the first inside column reads; the next ones are `step` further on.
    input: usize,
    step: usize,
}

/// Walks the im2col of one image for the `len` output positions from `first`, run by run.
fn for_each_run(geometry: &Geometry, first: usize, len: usize, mut visit: impl FnMut(Run)) {
    let [_, channels_in, height, width] = geometry.input;
    let width_out = geometry.output[3];
    let [kernel_h, kernel_w] = geometry.kernel;
    let ConvOptions {
        stride, dilation, ..
    } = geometry.options;
    let padding = geometry.options.padding_begin();
    for channel in 0..channels_in {
        for ky in 0..kernel_h {
            for kx in 0..kernel_w {
                let row = (channel * kernel_h + ky) * kernel_w + kx;
                // ix = ox·stride + offset
                let offset = (kx * dilation[1]) as isize - padding[1] as isize;
                let mut j = 0;
                while j < len {
                    let (oy, ox0) = ((first + j) / width_out, (first + j) % width_out);
                    let run = (width_out - ox0).min(len - j);
                    let iy = (oy * stride[0] + ky * dilation[0]) as isize - padding[0] as isize;
                    let (lo, hi) = if (0..height as isize).contains(&iy) {
                        valid_run(ox0, run, stride[1], offset, width)
                    } else {
                        (0, 0)
                    };
                    let input = if lo < hi {
                        let column = ((ox0 + lo) * stride[1]) as isize + offset;
                        (channel * height + iy as usize) * width + column as usize
                    } else {
                        0
                    };
                    visit(Run {
                        row,
                        columns: j..j + run,
                        inside: j + lo..j + hi,
                        input,
                        step: stride[1],
                    });
                    j += run;
                }
            }
        }
    }
}

/// Fills `columns` (`C_in·kh·kw` rows of `columns.len() / rows` output positions from `first`)
/// with the input values each kernel tap sees there, zero where it falls in the padding.
fn im2col(geometry: &Geometry, image: &[f32], first: usize, columns: &mut [f32]) {
    let len = columns.len() / geometry.rows();
    for_each_run(geometry, first, len, |run| {
        let row = &mut columns[run.row * len..(run.row + 1) * len];
        row[run.columns.start..run.inside.start].fill(0.0);
        row[run.inside.end..run.columns.end].fill(0.0);
        let out = &mut row[run.inside];
        if run.step == 1 {
            out.copy_from_slice(&image[run.input..run.input + out.len()]);
        } else {
            for (k, value) in out.iter_mut().enumerate() {
                *value = image[run.input + k * run.step];
            }
        }
    });
}

/// The adjoint of [`im2col`]: adds every column value to the image element its tap read.
fn col2im(geometry: &Geometry, columns: &[f32], first: usize, image: &mut [f32]) {
    let len = columns.len() / geometry.rows();
    for_each_run(geometry, first, len, |run| {
        let values = &columns[run.row * len..][run.inside];
        if run.step == 1 {
            let out = &mut image[run.input..run.input + values.len()];
            out.iter_mut().zip(values).for_each(|(o, v)| *o += v);
        } else {
            for (k, value) in values.iter().enumerate() {
                image[run.input + k * run.step] += value;
            }
        }
    });
}

/// The outputs `k ∈ [lo, hi)` of a run of `run` outputs from `ox0` whose input column
/// `(ox0 + k)·stride + offset` lies in `[0, width)`.
fn valid_run(ox0: usize, run: usize, stride: usize, offset: isize, width: usize) -> (usize, usize) {
    let (ox0, stride) = (ox0 as isize, stride as isize);
    // First output with a column ≥ 0, and first with a column ≥ width.
    let first_at = |bound: isize| {
        let needed = bound - offset; // (ox0 + k)·stride ≥ needed
        let ox = if needed <= 0 {
            0
        } else {
            (needed + stride - 1) / stride
        };
        (ox - ox0).clamp(0, run as isize) as usize
    };
    let lo = first_at(0);
    (lo, first_at(width as isize).max(lo))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The output, input gradient and weight gradient by their definitions, one term at a time.
    fn reference(geometry: &Geometry, x: &[f32], weight: &[f32], grad: &[f32]) -> [Vec<f32>; 3] {
        let [batch, cin, h, w] = geometry.input;
        let [_, cout, ho, wo] = geometry.output;
        let [kh, kw] = geometry.kernel;
        let o = &geometry.options;
        let pad = o.padding_begin();
        let mut y = vec![0.0f64; grad.len()];
        let mut dx = vec![0.0f64; x.len()];
        let mut dw = vec![0.0f64; weight.len()];
        for b in 0..batch {
            for co in 0..cout {
                for ci in 0..cin {
                    for ky in 0..kh {
                        for kx in 0..kw {
                            for oy in 0..ho {
                                for ox in 0..wo {
                                    let iy = (oy * o.stride[0] + ky * o.dilation[0]) as isize
                                        - pad[0] as isize;
                                    let ix = (ox * o.stride[1] + kx * o.dilation[1]) as isize
                                        - pad[1] as isize;
                                    if iy < 0 || ix < 0 || iy >= h as isize || ix >= w as isize {
                                        continue;
                                    }
                                    let xi = ((b * cin + ci) * h + iy as usize) * w + ix as usize;
                                    let yi = ((b * cout + co) * ho + oy) * wo + ox;
                                    let wi = ((co * cin + ci) * kh + ky) * kw + kx;
                                    y[yi] += f64::from(x[xi]) * f64::from(weight[wi]);
                                    dx[xi] += f64::from(grad[yi]) * f64::from(weight[wi]);
                                    dw[wi] += f64::from(x[xi]) * f64::from(grad[yi]);
                                }
                            }
                        }
                    }
                }
            }
        }
        [y, dx, dw].map(|v| v.into_iter().map(|v| v as f32).collect())
    }

    fn values(n: usize, seed: u32) -> Vec<f32> {
        (0..n)
            .map(|i| ((i as u32).wrapping_mul(2_654_435_761).wrapping_add(seed) >> 8) as f32)
            .map(|v| v / (1u32 << 24) as f32 - 0.5)
            .collect()
    }

    fn assert_close(got: &[f32], expected: &[f32], what: &str) {
        assert_eq!(got.len(), expected.len(), "{what}: lengths");
        for (i, (g, e)) in got.iter().zip(expected).enumerate() {
            assert!(
                (g - e).abs() <= 1e-4 * (1.0 + e.abs()),
                "{what}[{i}] = {g}, expected {e}"
            );
        }
    }

    /// The forward, both gradients (and which route the input gradient takes) against the
    /// definitions.
    fn check(
        input: [usize; 4],
        cout: usize,
        kernel: [usize; 2],
        options: ConvOptions<2>,
        input_grad_as_forward: bool,
    ) {
        let weight_shape = [cout, input[1], kernel[0], kernel[1]];
        let geometry = Geometry::new(input, weight_shape, options).expect("a valid geometry");
        let x = values(input.iter().product(), 1);
        let weight = values(weight_shape.iter().product(), 3);
        let grad = values(geometry.output.iter().product(), 7);
        let [y, dx, dw] = reference(&geometry, &x, &weight, &grad);
        assert_close(&forward(&geometry, &x, &weight), &y, "y");
        assert_close(&weight_grad(&geometry, &x, &grad), &dw, "dW");
        assert_close(&input_grad_col2im(&geometry, &weight, &grad), &dx, "dx");
        let transposed = geometry.input_grad_as_forward();
        assert_eq!(transposed.is_some(), input_grad_as_forward, "dx's route");
        if let Some(transposed) = transposed {
            let flipped = flip_and_swap_channels(&weight, weight_shape);
            assert_close(&forward(&transposed, &grad, &flipped), &dx, "dx as forward");
        }
    }

    /// The column buffers are reused uninitialised from one convolution to the next: a
    /// convolution with padding after one that filled them with values on every thread (the
    /// test's threads and rayon's) must still see zeros in its padding.
    #[test]
    fn reused_column_buffers_leave_no_trace() {
        let options = ConvOptions::new([1, 1], [0, 0], [1, 1], 1);
        let padded = ConvOptions::new([1, 1], [2, 2], [1, 1], 1);
        for _ in 0..2 {
            check([4, 8, 33, 31], 6, [3, 3], options.clone(), true);
            check([4, 8, 17, 15], 6, [5, 5], padded.clone(), true);
        }
    }

    #[test]
    fn stride_one_with_padding() {
        let options = ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
        check([2, 3, 9, 7], 5, [3, 3], options, true);
    }

    #[test]
    fn stride_two_without_padding_and_a_wide_kernel() {
        let options = ConvOptions::new([2, 2], [0, 0], [1, 1], 1);
        check([1, 4, 11, 12], 3, [4, 3], options, false);
    }

    #[test]
    fn dilation_asymmetric_padding_and_several_tiles() {
        // 2 · 3 · 3 rows: a tile of TILE_FLOATS / 18 positions, so 300×300 outputs take several.
        let options = ConvOptions {
            stride: [1, 1],
            padding: [(2, 0), (1, 3)],
            dilation: [2, 1],
            groups: 1,
        };
        // Padding 3 > d·(k − 1) = 2 on the right: dx goes through col2im.
        check([1, 2, 300, 298], 2, [3, 3], options.clone(), false);
        let inside = ConvOptions {
            padding: [(2, 0), (1, 2)],
            ..options
        };
        check([2, 2, 40, 37], 3, [3, 3], inside, true);
    }

    #[test]
    fn one_by_one_kernels_read_the_image_itself() {
        let options = ConvOptions::new([1, 1], [0, 0], [1, 1], 1);
        let geometry = Geometry::new([3, 6, 5, 5], [4, 6, 1, 1], options.clone()).unwrap();
        assert!(geometry.is_pointwise());
        check([3, 6, 5, 5], 4, [1, 1], options, true);
        // Padded or strided 1×1 convolutions need an im2col.
        let padded = ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
        check([1, 3, 4, 4], 2, [1, 1], padded, false);
        let strided = ConvOptions::new([2, 2], [0, 0], [1, 1], 1);
        check([2, 3, 7, 6], 2, [1, 1], strided, false);
    }

    #[test]
    fn geometries_burn_would_reject_take_burns_route() {
        let options = ConvOptions::new([1, 1], [0, 0], [1, 1], 1);
        // A kernel larger than the input.
        assert!(Geometry::new([1, 2, 2, 2], [3, 2, 3, 3], options.clone()).is_none());
        // An empty batch or no channels.
        assert!(Geometry::new([0, 2, 4, 4], [3, 2, 3, 3], options.clone()).is_none());
        assert!(Geometry::new([1, 0, 4, 4], [3, 0, 3, 3], options).is_none());
    }
}
