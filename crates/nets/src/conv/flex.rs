//! `impl ConvBackend for Flex`: Burn's forward and input gradient, and the weight gradient as
//! im2col + GEMM ([`weight_grad`]).
//!
//! Work split for the weight gradient: the output positions of every image are cut into tiles
//! whose im2col (`C_in·kh·kw` rows × tile columns) fits [`TILE_FLOATS`]; each thread takes a
//! contiguous run of tiles and accumulates `G_tile · X̂_tileᵀ` into its own `[C_out,
//! C_in·kh·kw]` sum with a single-threaded GEMM, and the sums are added at the end. With a
//! single tile the GEMM itself runs on all threads instead. Grouped convolutions and other
//! float types take Burn's route.

use std::borrow::Cow;

use burn::backend::Flex;
use burn::backend::TensorMetadata;
use burn::backend::ops::{FloatTensorOps, ModuleOps};
use burn::backend::tensor::FloatTensor;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{DType, TensorData};
use rayon::prelude::*;

use super::ConvBackend;
use super::profile::{self, Phase};

/// Floats of im2col per tile (1 MiB): a tile's columns stay in cache while its GEMM reads them.
const TILE_FLOATS: usize = 1 << 18;
/// The fewest output positions per tile (the GEMM's K), however many rows the im2col has.
const MIN_TILE: usize = 64;

impl ConvBackend for Flex {
    fn conv2d_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        let shapes = [dims(&x), dims(&weight)];
        profile::timed(
            Phase::Forward,
            || Self::conv2d(x, weight, None, options),
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
            || Self::conv2d_x_backward(x, weight, grad, options),
            |_| shapes,
        )
    }

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
}

fn dims(t: &FloatTensor<Flex>) -> [usize; 4] {
    t.shape().dims()
}

/// [`weight_grad`] on tensors; grouped convolutions and other float types take Burn's route.
fn weight_grad_tensor(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    grad: FloatTensor<Flex>,
    options: ConvOptions<2>,
) -> FloatTensor<Flex> {
    let f32_only = [x.dtype(), weight.dtype(), grad.dtype()] == [DType::F32; 3];
    if options.groups != 1 || !f32_only {
        return Flex::conv2d_weight_backward(x, weight, grad, options);
    }
    let weight_shape = dims(&weight);
    let geometry = Geometry {
        input: dims(&x),
        output: dims(&grad),
        kernel: [weight_shape[2], weight_shape[3]],
        options,
    };
    let values = weight_grad(&geometry, &host_f32(&x), &host_f32(&grad));
    Flex::float_from_data(TensorData::new(values, weight_shape), &Default::default())
}

/// A tensor's values, borrowed when already contiguous.
fn host_f32(t: &FloatTensor<Flex>) -> Cow<'_, [f32]> {
    match t.as_slice::<f32>() {
        Some(values) => Cow::Borrowed(values),
        None => Cow::Owned(
            t.clone()
                .into_data()
                .try_into_vec::<f32>()
                .expect("an f32 tensor converts to f32 values"),
        ),
    }
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
    /// Rows of the im2col: `C_in · kh · kw`.
    fn rows(&self) -> usize {
        self.input[1] * self.kernel[0] * self.kernel[1]
    }
}

/// `dW` (`[C_out, C_in, kh, kw]`, row-major) of a convolution with one group, from the input
/// `x` and the output gradient `grad` (both row-major).
fn weight_grad(geometry: &Geometry, x: &[f32], grad: &[f32]) -> Vec<f32> {
    let [batch, channels_in, height, width] = geometry.input;
    let [_, channels_out, height_out, width_out] = geometry.output;
    let rows = geometry.rows();
    let positions = height_out * width_out;
    let zeros = || vec![0.0f32; channels_out * rows];
    // The GEMM below reads through raw pointers: the slices must hold exactly these shapes.
    assert_eq!(x.len(), batch * channels_in * height * width, "input");
    assert_eq!(
        grad.len(),
        batch * channels_out * positions,
        "output gradient"
    );
    if batch == 0 || positions == 0 || rows == 0 {
        return zeros();
    }
    let tile = (TILE_FLOATS / rows).max(MIN_TILE).min(positions);
    let tiles_per_image = positions.div_ceil(tile);
    let tasks = batch * tiles_per_image;
    let threads = rayon::current_num_threads().clamp(1, tasks);
    let parallelism = if threads == 1 {
        gemm::Parallelism::Rayon(0)
    } else {
        gemm::Parallelism::None
    };
    let per_thread = tasks.div_ceil(threads);
    let image_len = channels_in * height * width;
    (0..threads)
        .into_par_iter()
        .map(|thread| {
            let mut sum = zeros();
            let mut columns = vec![0.0f32; rows * tile];
            for task in thread * per_thread..((thread + 1) * per_thread).min(tasks) {
                let (image, first) = (task / tiles_per_image, (task % tiles_per_image) * tile);
                let len = tile.min(positions - first);
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
            sum
        })
        .reduce_with(|mut total, part| {
            total.iter_mut().zip(part).for_each(|(t, p)| *t += p);
            total
        })
        .unwrap_or_else(zeros)
}

/// Fills `columns` (`C_in·kh·kw` rows of `columns.len() / rows` output positions from `first`)
/// with the input values each kernel tap sees there, zero where it falls in the padding.
fn im2col(geometry: &Geometry, image: &[f32], first: usize, columns: &mut [f32]) {
    let [_, channels_in, height, width] = geometry.input;
    let width_out = geometry.output[3];
    let [kernel_h, kernel_w] = geometry.kernel;
    let ConvOptions {
        stride, dilation, ..
    } = geometry.options;
    let padding = geometry.options.padding_begin();
    let len = columns.len() / geometry.rows();
    let mut rows = columns.chunks_exact_mut(len);
    for channel in 0..channels_in {
        let plane = &image[channel * height * width..(channel + 1) * height * width];
        for ky in 0..kernel_h {
            for kx in 0..kernel_w {
                let row = rows.next().expect("one row per tap");
                // ix = ox·stride + offset
                let offset = (kx * dilation[1]) as isize - padding[1] as isize;
                let mut j = 0;
                while j < len {
                    let (oy, ox0) = ((first + j) / width_out, (first + j) % width_out);
                    let run = (width_out - ox0).min(len - j);
                    let out = &mut row[j..j + run];
                    j += run;
                    let iy = (oy * stride[0] + ky * dilation[0]) as isize - padding[0] as isize;
                    if iy < 0 || iy >= height as isize {
                        out.fill(0.0);
                        continue;
                    }
                    let source = &plane[iy as usize * width..(iy as usize + 1) * width];
                    let (lo, hi) = valid_run(ox0, run, stride[1], offset, width);
                    out[..lo].fill(0.0);
                    out[hi..].fill(0.0);
                    let start = ((ox0 + lo) * stride[1]) as isize + offset;
                    if stride[1] == 1 {
                        out[lo..hi]
                            .copy_from_slice(&source[start as usize..start as usize + hi - lo]);
                    } else {
                        for (k, value) in out[lo..hi].iter_mut().enumerate() {
                            *value = source[start as usize + k * stride[1]];
                        }
                    }
                }
            }
        }
    }
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

    /// The weight gradient by its definition, one term at a time.
    fn reference(geometry: &Geometry, x: &[f32], grad: &[f32]) -> Vec<f32> {
        let [batch, cin, h, w] = geometry.input;
        let [_, cout, ho, wo] = geometry.output;
        let [kh, kw] = geometry.kernel;
        let o = &geometry.options;
        let pad = o.padding_begin();
        let mut dw = vec![0.0f64; cout * cin * kh * kw];
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
                                    let xv =
                                        x[((b * cin + ci) * h + iy as usize) * w + ix as usize];
                                    let gv = grad[((b * cout + co) * ho + oy) * wo + ox];
                                    dw[((co * cin + ci) * kh + ky) * kw + kx] +=
                                        f64::from(xv) * f64::from(gv);
                                }
                            }
                        }
                    }
                }
            }
        }
        dw.into_iter().map(|v| v as f32).collect()
    }

    fn values(n: usize, seed: u32) -> Vec<f32> {
        (0..n)
            .map(|i| ((i as u32).wrapping_mul(2_654_435_761).wrapping_add(seed) >> 8) as f32)
            .map(|v| v / (1u32 << 24) as f32 - 0.5)
            .collect()
    }

    fn check(input: [usize; 4], cout: usize, kernel: [usize; 2], options: ConvOptions<2>) {
        let [b, _, h, w] = input;
        let out = |size: usize, k: usize, axis: usize| {
            let (before, after) = options.padding[axis];
            (size + before + after - options.dilation[axis] * (k - 1) - 1) / options.stride[axis]
                + 1
        };
        let output = [b, cout, out(h, kernel[0], 0), out(w, kernel[1], 1)];
        let geometry = Geometry {
            input,
            output,
            kernel,
            options,
        };
        let x = values(input.iter().product(), 1);
        let grad = values(output.iter().product(), 7);
        let got = weight_grad(&geometry, &x, &grad);
        let expected = reference(&geometry, &x, &grad);
        for (i, (g, e)) in got.iter().zip(&expected).enumerate() {
            assert!(
                (g - e).abs() <= 1e-4 * (1.0 + e.abs()),
                "dW[{i}] = {g}, expected {e}"
            );
        }
    }

    #[test]
    fn stride_one_with_padding() {
        check(
            [2, 3, 9, 7],
            5,
            [3, 3],
            ConvOptions::new([1, 1], [1, 1], [1, 1], 1),
        );
    }

    #[test]
    fn stride_two_without_padding_and_a_wide_kernel() {
        check(
            [1, 4, 11, 12],
            3,
            [4, 3],
            ConvOptions::new([2, 2], [0, 0], [1, 1], 1),
        );
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
        check([1, 2, 300, 298], 2, [3, 3], options);
    }

    #[test]
    fn one_by_one_kernel() {
        check(
            [3, 6, 5, 5],
            4,
            [1, 1],
            ConvOptions::new([1, 1], [0, 0], [1, 1], 1),
        );
    }
}
