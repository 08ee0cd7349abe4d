//! `impl SplatBackend for Flex`: the CPU renderer ([`crate::cpu`]) behind the operation, with
//! the saved state converted to and from plain tensors.

use std::borrow::Cow;

use burn::backend::Flex;
use burn::backend::ops::{FloatTensorOps, IntTensorOps};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::{DType, Element, TensorData};

use super::{
    GaussianTensors, PACKED_CHANNELS, RasterState, SCREEN_FLOATS, SplatBackend, SplatForward,
    rejected,
};
use crate::Camera;
use crate::cpu::{self, ForwardOutput, PixelGrads, Projected, ScreenGaussian, TileBins};
use crate::semantics::{GaussianSlices, RenderOptions, TILE_SIZE};

/// A float tensor's values as `f32`, borrowed when already contiguous `f32`.
fn host_f32(t: &FloatTensor<Flex>) -> Cow<'_, [f32]> {
    host(t)
}

fn host<E: Element + bytemuck::Pod>(t: &FloatTensor<Flex>) -> Cow<'_, [E]> {
    match t.as_slice::<E>() {
        Some(s) => Cow::Borrowed(s),
        None => Cow::Owned(
            t.clone()
                .into_data()
                .try_to_vec_as::<E>()
                .expect("every numeric tensor converts to the requested element type"),
        ),
    }
}

fn flex_tensor<E: Element>(values: Vec<E>, shape: &[usize], dtype: DType) -> FloatTensor<Flex> {
    Flex::float_from_data(
        TensorData::new(values, shape.to_vec()).convert_dtype(dtype),
        &Default::default(),
    )
}

fn flex_int<E: Element>(values: Vec<E>, shape: &[usize]) -> IntTensor<Flex> {
    Flex::int_from_data(TensorData::new(values, shape.to_vec()), &Default::default())
}

fn screen_to_floats(projected: &Projected<f32>) -> Vec<f32> {
    projected
        .iter()
        .flat_map(|g| {
            [
                g.mean[0], g.mean[1], g.conic[0], g.conic[1], g.conic[2], g.color[0], g.color[1],
                g.color[2], g.opacity, g.depth,
            ]
        })
        .collect()
}

fn screen_from_floats(
    values: &[f32],
    radii: &[i32],
    width: usize,
    height: usize,
) -> Projected<f32> {
    values
        .chunks_exact(SCREEN_FLOATS)
        .zip(radii.chunks_exact(2))
        .map(|(v, r)| ScreenGaussian {
            mean: [v[0], v[1]],
            conic: [v[2], v[3], v[4]],
            color: [v[5], v[6], v[7]],
            opacity: v[8],
            depth: v[9],
            radii: [r[0].max(0) as u32, r[1].max(0) as u32],
            pixels: [0; 4],
        })
        .map(|g| g.with_footprint(width, height))
        .collect()
}

impl SplatBackend for Flex {
    fn splat_forward(
        inputs: GaussianTensors<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> SplatForward<Self> {
        let dtype = inputs.means.dtype();
        let (means, log_scales, quats) = (
            host_f32(&inputs.means),
            host_f32(&inputs.log_scales),
            host_f32(&inputs.quats),
        );
        let (opacity_logits, sh) = (host_f32(&inputs.opacity_logits), host_f32(&inputs.sh));
        let background = host_f32(&inputs.background);
        let slices = GaussianSlices {
            means: &means,
            log_scales: &log_scales,
            quats: &quats,
            opacity_logits: &opacity_logits,
            sh: &sh,
        };
        let (w, h) = (camera.width as usize, camera.height as usize);
        let bg = [0, 1, 2].map(|c| background.get(c).copied().unwrap_or(f32::NAN));
        match cpu::render(&slices, &camera, bg, &options) {
            Ok(fwd) => pack_forward(fwd, w, h, dtype),
            Err(error) => rejected(error, &Default::default(), dtype),
        }
    }

    fn splat_backward(
        inputs: GaussianTensors<Self>,
        state: RasterState<Self>,
        grad_image: FloatTensor<Self>,
        camera: Camera,
        options: RenderOptions,
    ) -> GaussianTensors<Self> {
        let dtype = inputs.means.dtype();
        let (means, log_scales, quats) = (
            host_f32(&inputs.means),
            host_f32(&inputs.log_scales),
            host_f32(&inputs.quats),
        );
        let (opacity_logits, sh) = (host_f32(&inputs.opacity_logits), host_f32(&inputs.sh));
        let background = host_f32(&inputs.background);
        let slices = GaussianSlices {
            means: &means,
            log_scales: &log_scales,
            quats: &quats,
            opacity_logits: &opacity_logits,
            sh: &sh,
        };
        let (w, h) = (camera.width as usize, camera.height as usize);
        let radii = host::<i32>(&state.radii);
        let bins = TileBins {
            tiles_x: w.div_ceil(TILE_SIZE),
            tiles_y: h.div_ceil(TILE_SIZE),
            offsets: host::<u32>(&state.tile_offsets).into_owned(),
            ids: host::<u32>(&state.tile_ids).into_owned(),
        };
        let fwd = ForwardOutput {
            color: Vec::new(),
            alpha: Vec::new(),
            depth: Vec::new(),
            final_transmittance: host_f32(&state.final_transmittance).into_owned(),
            n_contrib: host::<u32>(&state.n_contrib).into_owned(),
            projected: screen_from_floats(&host_f32(&state.screen), &radii, w, h),
            bins,
            background: [background[0], background[1], background[2]],
            evaluations: 0,
        };
        let packed = host_f32(&grad_image);
        let mut d_color = Vec::with_capacity(w * h * 3);
        let mut d_alpha = Vec::with_capacity(w * h);
        let mut d_depth = Vec::with_capacity(w * h);
        for px in packed.chunks_exact(PACKED_CHANNELS) {
            d_color.extend_from_slice(&px[..3]);
            d_alpha.push(px[3]);
            d_depth.push(px[4]);
        }
        let pixel_grads = PixelGrads {
            color: &d_color,
            alpha: &d_alpha,
            depth: &d_depth,
        };
        let g = cpu::render_backward(&slices, &camera, &options, &fwd, &pixel_grads);
        let n = slices.len();
        let k = slices.sh_coeffs();
        GaussianTensors {
            means: flex_tensor(g.means, &[n, 3], dtype),
            log_scales: flex_tensor(g.log_scales, &[n, 3], dtype),
            quats: flex_tensor(g.quats, &[n, 4], dtype),
            opacity_logits: flex_tensor(g.opacity_logits, &[n], dtype),
            sh: flex_tensor(g.sh, &[n, k, 3], dtype),
            background: flex_tensor(g.background.to_vec(), &[3], dtype),
        }
    }
}

fn pack_forward(fwd: ForwardOutput<f32>, w: usize, h: usize, dtype: DType) -> SplatForward<Flex> {
    let mut image = Vec::with_capacity(w * h * PACKED_CHANNELS);
    for p in 0..w * h {
        image.extend_from_slice(&[
            fwd.color[3 * p],
            fwd.color[3 * p + 1],
            fwd.color[3 * p + 2],
            fwd.alpha[p],
            fwd.depth[p],
        ]);
    }
    let n = fwd.projected.len();
    let radii: Vec<i32> = fwd
        .projected
        .iter()
        .flat_map(|g| g.radii.map(|r| r.min(i32::MAX as u32) as i32))
        .collect();
    let n_isect = fwd.bins.ids.len();
    let n_offsets = fwd.bins.offsets.len();
    SplatForward {
        image: flex_tensor(image, &[h, w, PACKED_CHANNELS], dtype),
        state: RasterState {
            screen: flex_tensor(
                screen_to_floats(&fwd.projected),
                &[n, SCREEN_FLOATS],
                DType::F32,
            ),
            radii: flex_int(radii, &[n, 2]),
            tile_offsets: flex_int(fwd.bins.offsets, &[n_offsets]),
            tile_ids: flex_int(fwd.bins.ids, &[n_isect]),
            final_transmittance: flex_tensor(fwd.final_transmittance, &[h, w], DType::F32),
            n_contrib: flex_int(fwd.n_contrib, &[h, w]),
        },
        error: None,
    }
}
