//! StyleGAN2's modulated weight and its gradients: one cube per output channel, which sums the
//! demodulation's squares (and, backward, its projection) in shared memory; the style's gradient
//! a second kernel, one cube per input channel summing over output channels and taps (and a
//! few more writing the zeros of the network's other styles: the layer reads its style from
//! the network's vector of them all, `fused::modulate`).
//!
//! The modulated weight (and an equalised convolution's scaled weight, [`scale_weight`]) is
//! written channels-last (`[C_out, kh, kw, C_in]` in memory), the layout
//! Burn's implicit-GEMM convolution reads its weight in, forward and for the input gradient:
//! written row-major, each of those copied it first. Its gradient, which the weight-gradient
//! GEMM hands back channels-last, is read as it comes.

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::{CubeCount, CubeDim};
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;

use super::sum::SUM_UNITS;
use super::{dims, u32_of};
use crate::cube_grid::{UNITS, one_thread_per_value};
use crate::cube_layout::{empty_in_layout, readable};
use crate::fused::DEMODULATION_EPSILON;

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    use super::super::sum::cube_sum;

    /// The buffer offset of value `j = i · taps + k` (input channel `i`, tap `k`) of the output
    /// channel at `base`: `base + j` row-major, `base + k · inputs + i` channels-last.
    #[cube]
    fn offset(base: u32, j: u32, taps: u32, inputs: u32, #[comptime] channels_last: bool) -> u32 {
        let mut at = base + j;
        if comptime![channels_last] {
            at = base + (j % taps) * inputs + j / taps;
        }
        at
    }

    /// One cube per output channel `o` (`CUBE_POS_X`): `out[o, j] = weight[o, j] ·
    /// styles[first + j / taps] · scale`, times `(Σ_j (weight · style · scale)² + epsilon)^(−½)`
    /// if `demodulate` (`j` over the channel's `per_output` values); `out` channels-last.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn modulate(
        weight: &Tensor<f32>,
        styles: &Tensor<f32>,
        out: &mut Tensor<f32>,
        per_output: u32,
        taps: u32,
        first: u32,
        scale: f32,
        epsilon: f32,
        #[comptime] demodulate: bool,
        #[comptime] units: u32,
    ) {
        let inputs = per_output / taps;
        let t = UNIT_POS;
        let base = CUBE_POS_X * per_output;
        let mut partial = Shared::<[f32]>::new_slice(comptime![units as usize]);
        let mut d = 1.0f32;
        if comptime![demodulate] {
            let mut sum = 0.0f32;
            let mut j = t;
            while j < per_output {
                let u = weight[(base + j) as usize] * styles[(first + j / taps) as usize] * scale;
                sum += u * u;
                j += units;
            }
            partial[t as usize] = sum;
            cube_sum(&mut partial, units);
            d = 1.0 / f32::sqrt(partial[0] + epsilon);
        }
        let mut j = t;
        while j < per_output {
            let u = weight[(base + j) as usize] * styles[(first + j / taps) as usize] * scale;
            out[offset(base, j, taps, inputs, true) as usize] = u * d;
            j += units;
        }
    }

    /// The backward of [`modulate`], one cube per output channel: `d_weight` and
    /// `terms = ∂u · weight · scale`, whose sums over output channels and taps are the style's
    /// gradient ([`style_grad`]); `grad` row-major or, with `grad_last`, channels-last.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn modulate_grad(
        weight: &Tensor<f32>,
        styles: &Tensor<f32>,
        grad: &Tensor<f32>,
        d_weight: &mut Tensor<f32>,
        terms: &mut Tensor<f32>,
        per_output: u32,
        taps: u32,
        first: u32,
        scale: f32,
        epsilon: f32,
        #[comptime] demodulate: bool,
        #[comptime] grad_last: bool,
        #[comptime] units: u32,
    ) {
        let inputs = per_output / taps;
        let t = UNIT_POS;
        let base = CUBE_POS_X * per_output;
        let mut squares = Shared::<[f32]>::new_slice(comptime![units as usize]);
        let mut projections = Shared::<[f32]>::new_slice(comptime![units as usize]);
        let mut d = 1.0f32;
        let mut projection = 0.0f32;
        if comptime![demodulate] {
            let mut uu = 0.0f32;
            let mut gu = 0.0f32;
            let mut j = t;
            while j < per_output {
                let u = weight[(base + j) as usize] * styles[(first + j / taps) as usize] * scale;
                uu += u * u;
                gu += grad[offset(base, j, taps, inputs, grad_last) as usize] * u;
                j += units;
            }
            squares[t as usize] = uu;
            projections[t as usize] = gu;
            cube_sum(&mut squares, units);
            cube_sum(&mut projections, units);
            d = 1.0 / f32::sqrt(squares[0] + epsilon);
            projection = projections[0] * d * d;
        }
        let mut j = t;
        while j < per_output {
            let s = styles[(first + j / taps) as usize];
            let w = weight[(base + j) as usize];
            let u = w * s * scale;
            let g = grad[offset(base, j, taps, inputs, grad_last) as usize];
            let d_u = d * (g - u * projection);
            d_weight[(base + j) as usize] = d_u * s * scale;
            terms[(base + j) as usize] = d_u * w * scale;
            j += units;
        }
    }

    /// `out = weight · scale` with `out` channels-last, one thread per weight value (`j` its
    /// row-major offset).
    #[cube(launch)]
    pub fn scale_weight(
        weight: &Tensor<f32>,
        out: &mut Tensor<f32>,
        per_output: u32,
        taps: u32,
        scale: f32,
    ) {
        let j = ABSOLUTE_POS as u32;
        if j >= weight.len() as u32 {
            terminate!();
        }
        let base = (j / per_output) * per_output;
        let inputs = per_output / taps;
        out[offset(base, j % per_output, taps, inputs, true) as usize] = weight[j as usize] * scale;
    }

    /// `d_weight = grad · scale`, row-major, from `grad` row-major or, with `grad_last`,
    /// channels-last; one thread per value.
    #[cube(launch)]
    pub fn scale_weight_grad(
        grad: &Tensor<f32>,
        d_weight: &mut Tensor<f32>,
        per_output: u32,
        taps: u32,
        scale: f32,
        #[comptime] grad_last: bool,
    ) {
        let j = ABSOLUTE_POS as u32;
        if j >= d_weight.len() as u32 {
            terminate!();
        }
        let base = (j / per_output) * per_output;
        let inputs = per_output / taps;
        d_weight[j as usize] =
            grad[offset(base, j % per_output, taps, inputs, grad_last) as usize] * scale;
    }

    /// `d_styles[first + i] = Σ_{o, k} terms[o, i·taps + k]`, one cube per input channel `i <
    /// inputs` (`CUBE_POS_X`), its units striding over the `(o, k)` pairs; the cubes after
    /// those write the zeros of the other layers' styles, a value per unit.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn style_grad(
        terms: &Tensor<f32>,
        d_styles: &mut Tensor<f32>,
        outputs: u32,
        per_output: u32,
        taps: u32,
        first: u32,
        inputs: u32,
        #[comptime] units: u32,
    ) {
        let t = UNIT_POS;
        let i = CUBE_POS_X;
        if i < inputs {
            let mut partial = Shared::<[f32]>::new_slice(comptime![units as usize]);
            let mut sum = 0.0f32;
            let mut n = t;
            while n < outputs * taps {
                sum += terms[((n / taps) * per_output + i * taps + n % taps) as usize];
                n += units;
            }
            partial[t as usize] = sum;
            cube_sum(&mut partial, units);
            if t == 0 {
                d_styles[(first + i) as usize] = partial[0];
            }
        } else {
            let z = (i - inputs) * units + t;
            if (z as usize) < d_styles.len() - inputs as usize {
                let mut at = z;
                if z >= first {
                    at = z + inputs;
                }
                d_styles[at as usize] = 0.0;
            }
        }
    }
}

/// One cube per output channel ([`per_output_channel`]), on the weight and styles made
/// row-major; the output channels-last.
pub(super) fn modulate(
    weight: FloatTensor<CubeBackend>,
    styles: FloatTensor<CubeBackend>,
    first: usize,
    scale: f32,
    demodulate: bool,
) -> FloatTensor<CubeBackend> {
    let shape = dims(&weight);
    check_styles(&styles, first, shape[1]);
    let (weight, styles) = (into_contiguous(weight), into_contiguous(styles));
    let out = empty_in_layout(&weight, shape, true);
    if let Some((cubes, cube, per_output, taps)) = per_output_channel(shape) {
        kernels::modulate::launch(
            &weight.client,
            cubes,
            cube,
            weight.clone().into_tensor_arg(),
            styles.into_tensor_arg(),
            out.clone().into_tensor_arg(),
            per_output,
            taps,
            u32_of(first),
            scale,
            DEMODULATION_EPSILON,
            demodulate,
            UNITS,
        );
    }
    out
}

/// [`kernels::modulate_grad`] per output channel, then [`kernels::style_grad`]'s sums into
/// the layer's range of the styles' gradient and zeros elsewhere, on the weight and styles
/// made row-major and the gradient as it comes if channels-last.
pub(super) fn modulate_grad(
    weight: FloatTensor<CubeBackend>,
    styles: FloatTensor<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
    first: usize,
    scale: f32,
    demodulate: bool,
) -> (FloatTensor<CubeBackend>, FloatTensor<CubeBackend>) {
    let shape = dims(&weight);
    assert_eq!(dims(&grad), shape, "weight and gradient shapes");
    let count = check_styles(&styles, first, shape[1]);
    let [weight, styles] = [weight, styles].map(into_contiguous);
    let (grad, grad_last) = readable(grad);
    let d_weight = empty_in_layout(&weight, shape, false);
    let terms = empty_in_layout(&weight, shape, false);
    let d_styles = empty_device_contiguous_dtype(
        weight.client.clone(),
        weight.device.clone(),
        Shape::new([count]),
        DType::F32,
    );
    let Some((cubes, cube, per_output, taps)) = per_output_channel(shape) else {
        // A weight without values: no style value has any effect.
        let zeros =
            CubeBackend::float_zeros(Shape::new([count]), &weight.device, DType::F32.into());
        return (d_weight, zeros);
    };
    kernels::modulate_grad::launch(
        &weight.client,
        cubes,
        cube,
        weight.clone().into_tensor_arg(),
        styles.into_tensor_arg(),
        grad.into_tensor_arg(),
        d_weight.clone().into_tensor_arg(),
        terms.clone().into_tensor_arg(),
        per_output,
        taps,
        u32_of(first),
        scale,
        DEMODULATION_EPSILON,
        demodulate,
        grad_last,
        UNITS,
    );
    let zero_cubes = (count - shape[1]).div_ceil(SUM_UNITS as usize);
    kernels::style_grad::launch(
        &weight.client,
        one_cube_per_channel(shape[1] + zero_cubes, "input"),
        CubeDim::new_1d(SUM_UNITS),
        terms.into_tensor_arg(),
        d_styles.clone().into_tensor_arg(),
        u32_of(shape[0]),
        per_output,
        taps,
        u32_of(first),
        u32_of(shape[1]),
        SUM_UNITS,
    );
    (d_weight, d_styles)
}

/// The number of `styles`, checked to hold `inputs` from `first` on.
fn check_styles(styles: &FloatTensor<CubeBackend>, first: usize, inputs: usize) -> usize {
    let [count] = styles.shape().dims();
    assert!(
        first + inputs <= count,
        "styles {first}..{} of {count}",
        first + inputs
    );
    count
}

/// One thread per value, the output channels-last.
pub(super) fn scale_weight(
    weight: FloatTensor<CubeBackend>,
    scale: f32,
) -> FloatTensor<CubeBackend> {
    let shape = dims(&weight);
    let weight = into_contiguous(weight);
    let out = empty_in_layout(&weight, shape, true);
    if let Some((_, _, per_output, taps)) = per_output_channel(shape) {
        let (cubes, cube) = one_thread_per_value(weight.shape().num_elements());
        kernels::scale_weight::launch(
            &weight.client,
            cubes,
            cube,
            weight.clone().into_tensor_arg(),
            out.clone().into_tensor_arg(),
            per_output,
            taps,
            scale,
        );
    }
    out
}

/// One thread per value, from the gradient as it comes if channels-last, into a row-major
/// gradient.
pub(super) fn scale_weight_grad(
    grad: FloatTensor<CubeBackend>,
    scale: f32,
) -> FloatTensor<CubeBackend> {
    let shape = dims(&grad);
    let (grad, grad_last) = readable(grad);
    let d_weight = empty_in_layout(&grad, shape, false);
    if let Some((_, _, per_output, taps)) = per_output_channel(shape) {
        let (cubes, cube) = one_thread_per_value(grad.shape().num_elements());
        kernels::scale_weight_grad::launch(
            &grad.client,
            cubes,
            cube,
            grad.clone().into_tensor_arg(),
            d_weight.clone().into_tensor_arg(),
            per_output,
            taps,
            scale,
            grad_last,
        );
    }
    d_weight
}

/// The launch of [`kernels::modulate`] and its gradient for a weight of `shape`: one cube of
/// [`UNITS`] per output channel, the values per output channel and the taps per input channel
/// as kernel arguments; `None` for a weight without values.
fn per_output_channel(shape: [usize; 4]) -> Option<(CubeCount, CubeDim, u32, u32)> {
    let [c_out, c_in, kh, kw] = shape;
    let per_output = c_in * kh * kw;
    if c_out * per_output == 0 {
        return None;
    }
    u32_of(c_out * per_output);
    Some((
        one_cube_per_channel(c_out, "output"),
        CubeDim::new_1d(UNITS),
        u32_of(per_output),
        u32_of(kh * kw),
    ))
}

/// A row of one cube per channel (`CUBE_POS_X`): at most 65 535 (wgpu's limit per dimension).
fn one_cube_per_channel(channels: usize, which: &str) -> CubeCount {
    let cubes = u32::try_from(channels)
        .ok()
        .filter(|&c| c <= 65_535)
        .unwrap_or_else(|| panic!("at most 65 535 {which} channels"));
    CubeCount::Static(cubes, 1, 1)
}
