//! Tile rasterisation on the GPU, forward and backward: one cube of 16×16 units per tile, one
//! unit per pixel, the tile's Gaussians brought through shared memory in batches of 256 (one
//! per unit). The per-pixel arithmetic, the skipped contributions, the early stop and the
//! `n_contrib` bookkeeping are the CPU's (`crate::cpu` documents them), so that the two paths
//! give the same images and the backward can walk the forward's contributions.
//!
//! Units whose pixel lies outside the image still load Gaussians and reach every barrier:
//! no unit may leave before a `sync_cube`. A tile stops early when all its pixels are done
//! (checked once per batch with a tree reduction in shared memory: no plane operations,
//! which lavapipe lacks).
//!
//! Backward: each unit walks its pixel's contributions back to front from the final
//! transmittance and computes the pixel's share of the current Gaussian's 10 screen-space
//! gradients. The shares are summed and added to the Gaussian's gradient in global memory as
//! [`Accumulation`] says, the fastest the device has: within each plane (warp) with
//! `plane_sum`, skipping planes no pixel of which touched the Gaussian, then one atomic add per
//! plane (CUDA; gsplat's scheme), or over the whole cube in shared memory, then one atomic add
//! (lavapipe and other adapters without plane operations); the add is a float atomic where the
//! device has one, a compare-and-swap loop on the bits where it does not. Sums over tiles
//! arrive in any order, so gradients agree with the CPU to rounding, not bit for bit.

use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::{DType, FloatDType, Shape};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::client::Client;
use burn_cubecl::cubecl::ir::features::{AtomicUsage, Plane};
use burn_cubecl::cubecl::ir::{DeviceProperties, ElemType, FloatKind, Type};
use burn_cubecl::cubecl::{CubeCount, CubeDim};
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_contiguous_dtype;

use super::bin::TileBins;
#[cfg(feature = "cuda-source")]
use super::cuda_source::{CudaTarget, KernelSource, tensor};
use crate::op::{PACKED_CHANNELS, SCREEN_FLOATS};
use crate::semantics::{ALPHA_MIN, TILE_SIZE, TRANSMITTANCE_MIN};

mod kernels {
    use burn_cubecl::cubecl;
    use burn_cubecl::cubecl::prelude::*;

    /// How a sum reaches a Gaussian's gradient slot in global memory.
    #[cube]
    pub trait Accumulate: Send + Sync + 'static {
        /// What a slot holds: f32, or its bits as u32.
        type Slot: Numeric;

        fn add(slot: &mut Atomic<Self::Slot>, value: f32);
    }

    /// A float atomic add (CUDA; wgpu adapters with `SHADER_FLOAT32_ATOMIC`).
    #[derive(CubeType)]
    pub struct FloatAdd;

    /// A compare-and-swap loop on the bits (every device).
    #[derive(CubeType)]
    pub struct SwapAdd;

    #[cube]
    impl Accumulate for FloatAdd {
        type Slot = f32;

        fn add(slot: &mut Atomic<f32>, value: f32) {
            slot.fetch_add(value);
        }
    }

    #[cube]
    impl Accumulate for SwapAdd {
        type Slot = u32;

        fn add(slot: &mut Atomic<u32>, value: f32) {
            let mut old = slot.load();
            let mut done = false;
            while !done {
                let seen =
                    slot.compare_exchange_weak(old, f32::to_bits(f32::from_bits(old) + value));
                done = seen == old;
                old = seen;
            }
        }
    }

    /// Puts Gaussian `id`'s screen values and pixel box into slot `t` of the shared batch. The
    /// box is the CPU's `pixel_box` before clipping: pixels whose centre `i + 0.5` lies within
    /// the radius of the mean (in f32 `m − r − ½` rounds, but never across a whole number, so
    /// `ceil` and `floor` agree with the CPU's f64).
    #[cube]
    fn load_gaussian(
        screen: &Tensor<f32>,
        radii: &Tensor<i32>,
        id: i32,
        t: usize,
        gaussians: &mut Shared<[f32]>,
        boxes: &mut Shared<[i32]>,
    ) {
        let id = usize::cast_from(id);
        for j in 0..10usize {
            gaussians[10 * t + j] = screen[10 * id + j];
        }
        let rx = f32::cast_from(radii[2 * id]);
        let ry = f32::cast_from(radii[2 * id + 1]);
        let mx = screen[10 * id];
        let my = screen[10 * id + 1];
        boxes[4 * t] = i32::cast_from(f32::ceil(mx - rx - 0.5f32));
        boxes[4 * t + 1] = i32::cast_from(f32::floor(mx + rx - 0.5f32));
        boxes[4 * t + 2] = i32::cast_from(f32::ceil(my - ry - 0.5f32));
        boxes[4 * t + 3] = i32::cast_from(f32::floor(my + ry - 0.5f32));
    }

    /// Whether pixel `(x, y)` lies in the box of batch slot `k`.
    #[cube]
    fn in_box(boxes: &Shared<[i32]>, k: usize, x: i32, y: i32) -> bool {
        x >= boxes[4 * k] && x <= boxes[4 * k + 1] && y >= boxes[4 * k + 2] && y <= boxes[4 * k + 3]
    }

    /// Composites the tile `CUBE_POS_X, CUBE_POS_Y` front to back.
    #[allow(clippy::too_many_arguments)]
    #[cube(launch)]
    pub fn forward(
        screen: &Tensor<f32>,
        radii: &Tensor<i32>,
        offsets: &Tensor<i32>,
        ids: &Tensor<i32>,
        background: &Tensor<f32>,
        image: &mut Tensor<f32>,
        final_t: &mut Tensor<f32>,
        n_contrib: &mut Tensor<i32>,
        width: u32,
        height: u32,
        alpha_max: f32,
        alpha_min: f32,
        t_min: f32,
        #[comptime] tile: u32,
    ) {
        let units = comptime![(tile * tile) as usize];
        let t = UNIT_POS as usize;
        let x = CUBE_POS_X * tile + UNIT_POS_X;
        let y = CUBE_POS_Y * tile + UNIT_POS_Y;
        let inside = x < width && y < height;
        let tile_id = usize::cast_from(CUBE_POS_Y * CUBE_COUNT_X + CUBE_POS_X);
        let start = usize::cast_from(offsets[tile_id]);
        let end = usize::cast_from(offsets[tile_id + 1]);
        let mut gaussians = Shared::<[f32]>::new_slice(comptime![10 * units]);
        let mut boxes = Shared::<[i32]>::new_slice(comptime![4 * units]);
        let mut flags = Shared::<[u32]>::new_slice(units);

        let px = f32::cast_from(x) + 0.5f32;
        let py = f32::cast_from(y) + 0.5f32;
        let xi = i32::cast_from(x);
        let yi = i32::cast_from(y);
        let mut open = inside;
        let mut trans = 1.0f32;
        let mut r = 0.0f32;
        let mut g = 0.0f32;
        let mut b = 0.0f32;
        let mut z = 0.0f32;
        let mut last = 0i32;
        let mut batch_start = start;
        while batch_start < end {
            // Stop when no pixel of the tile is open (a tree reduction of the flags).
            flags[t] = 0u32;
            if open {
                flags[t] = 1u32;
            }
            sync_cube();
            // Pairwise with doubling strides (a loop variable must start from a literal:
            // one initialised from a comptime value and then changed fails verification).
            let mut stride = 1usize;
            while stride < units {
                if t & (2 * stride - 1) == 0 {
                    flags[t] |= flags[t + stride];
                }
                sync_cube();
                stride *= 2;
            }
            let any_open = flags[0] != 0u32;
            sync_cube();
            if !any_open {
                break;
            }
            let slot = batch_start + t;
            if slot < end {
                load_gaussian(screen, radii, ids[slot], t, &mut gaussians, &mut boxes);
            }
            sync_cube();
            let mut batch = batch_start + units;
            if batch > end {
                batch = end;
            }
            batch -= batch_start;
            for k in 0..batch {
                let inside_box = in_box(&boxes, k, xi, yi);
                if open && inside_box {
                    let dx = px - gaussians[10 * k];
                    let dy = py - gaussians[10 * k + 1];
                    let power = -0.5f32
                        * (gaussians[10 * k + 2] * dx * dx + gaussians[10 * k + 4] * dy * dy)
                        - gaussians[10 * k + 3] * dy * dx;
                    let alpha = (gaussians[10 * k + 8] * f32::exp(power)).min(alpha_max);
                    if power <= 0.0f32 && alpha >= alpha_min {
                        let next = trans * (1.0f32 - alpha);
                        if next <= t_min {
                            open = false;
                        } else {
                            let w = alpha * trans;
                            r += w * gaussians[10 * k + 5];
                            g += w * gaussians[10 * k + 6];
                            b += w * gaussians[10 * k + 7];
                            z += w * gaussians[10 * k + 9];
                            trans = next;
                            last = i32::cast_from(batch_start + k - start) + 1i32;
                        }
                    }
                }
            }
            sync_cube();
            batch_start += units;
        }
        if inside {
            let p = usize::cast_from(y * width + x);
            image[5 * p] = r + trans * background[0];
            image[5 * p + 1] = g + trans * background[1];
            image[5 * p + 2] = b + trans * background[2];
            image[5 * p + 3] = 1.0f32 - trans;
            image[5 * p + 4] = z;
            final_t[p] = trans;
            n_contrib[p] = last;
        }
    }

    /// Walks the tile `CUBE_POS_X, CUBE_POS_Y` back to front and adds each Gaussian's
    /// screen-space gradient (mean 2, conic 3, colour 3, opacity, depth; the layout of
    /// `screen`) into `grads`, whose f32 values are held as bits.
    #[allow(clippy::too_many_arguments, clippy::collapsible_if)]
    #[cube(launch)]
    pub fn backward<A: Accumulate>(
        screen: &Tensor<f32>,
        radii: &Tensor<i32>,
        offsets: &Tensor<i32>,
        ids: &Tensor<i32>,
        background: &Tensor<f32>,
        final_t: &Tensor<f32>,
        n_contrib: &Tensor<i32>,
        grad_image: &Tensor<f32>,
        grads: &mut Tensor<Atomic<A::Slot>>,
        width: u32,
        height: u32,
        alpha_max: f32,
        alpha_min: f32,
        #[comptime] tile: u32,
        #[comptime] planes: bool,
    ) {
        let units = comptime![(tile * tile) as usize];
        let t = UNIT_POS as usize;
        let x = CUBE_POS_X * tile + UNIT_POS_X;
        let y = CUBE_POS_Y * tile + UNIT_POS_Y;
        let inside = x < width && y < height;
        let tile_id = usize::cast_from(CUBE_POS_Y * CUBE_COUNT_X + CUBE_POS_X);
        let start = usize::cast_from(offsets[tile_id]);
        let mut gaussians = Shared::<[f32]>::new_slice(comptime![10 * units]);
        let mut boxes = Shared::<[i32]>::new_slice(comptime![4 * units]);
        let mut sums = Shared::<[f32]>::new_slice(comptime![if planes { 1 } else { 10 * units }]);
        let mut lasts = Shared::<[i32]>::new_slice(units);

        let px = f32::cast_from(x) + 0.5f32;
        let py = f32::cast_from(y) + 0.5f32;
        let xi = i32::cast_from(x);
        let yi = i32::cast_from(y);
        let p = usize::cast_from(y * width + x);
        // The pixel's state: transmittance before the current Gaussian, the colour and depth
        // of everything behind it (background included), its output gradients.
        let mut trans = 0.0f32;
        let mut t_final = 0.0f32;
        let mut last = 0i32;
        let mut behind_r = 0.0f32;
        let mut behind_g = 0.0f32;
        let mut behind_b = 0.0f32;
        let mut behind_z = 0.0f32;
        let mut d_r = 0.0f32;
        let mut d_g = 0.0f32;
        let mut d_b = 0.0f32;
        let mut d_alpha = 0.0f32;
        let mut d_depth = 0.0f32;
        if inside {
            trans = final_t[p];
            t_final = trans;
            last = n_contrib[p];
            behind_r = background[0];
            behind_g = background[1];
            behind_b = background[2];
            d_r = grad_image[5 * p];
            d_g = grad_image[5 * p + 1];
            d_b = grad_image[5 * p + 2];
            d_alpha = grad_image[5 * p + 3];
            d_depth = grad_image[5 * p + 4];
        }
        // Entries after every pixel's last contribution need no visit.
        lasts[t] = last;
        sync_cube();
        let mut stride = 1usize;
        while stride < units {
            // Nested: `&&` in a kernel evaluates both sides, and `t + stride` must be in range.
            if t & (2 * stride - 1) == 0 {
                if lasts[t + stride] > lasts[t] {
                    lasts[t] = lasts[t + stride];
                }
            }
            sync_cube();
            stride *= 2;
        }
        let end = start + usize::cast_from(lasts[0]);
        let mut batch_end = end;
        while batch_end > start {
            let batch_start = if batch_end - start > units {
                batch_end - units
            } else {
                start
            };
            let slot = batch_start + t;
            if slot < batch_end {
                load_gaussian(screen, radii, ids[slot], t, &mut gaussians, &mut boxes);
            }
            sync_cube();
            let batch = batch_end - batch_start;
            let mut k = batch;
            while k > 0 {
                k -= 1;
                let mut shares = Array::<f32>::new(10usize);
                for j in 0..10usize {
                    shares[j] = 0.0f32;
                }
                let position = i32::cast_from(batch_start + k - start) + 1i32;
                let inside_box = in_box(&boxes, k, xi, yi);
                if inside && position <= last && inside_box {
                    let dx = px - gaussians[10 * k];
                    let dy = py - gaussians[10 * k + 1];
                    let ca = gaussians[10 * k + 2];
                    let cb = gaussians[10 * k + 3];
                    let cc = gaussians[10 * k + 4];
                    let power = -0.5f32 * (ca * dx * dx + cc * dy * dy) - cb * dy * dx;
                    let density = f32::exp(power);
                    let raw = gaussians[10 * k + 8] * density;
                    let a = raw.min(alpha_max);
                    if power <= 0.0f32 && a >= alpha_min {
                        let one_minus = 1.0f32 - a;
                        let inv = 1.0f32 / one_minus;
                        let t_k = trans * inv;
                        let w = a * t_k;
                        let cr = gaussians[10 * k + 5];
                        let cg = gaussians[10 * k + 6];
                        let cbl = gaussians[10 * k + 7];
                        let depth = gaussians[10 * k + 9];
                        shares[5] = w * d_r;
                        shares[6] = w * d_g;
                        shares[7] = w * d_b;
                        shares[9] = w * d_depth;
                        let d_a_behind = (depth - behind_z) * d_depth
                            + (cr - behind_r) * d_r
                            + (cg - behind_g) * d_g
                            + (cbl - behind_b) * d_b;
                        let d_a = t_k * d_a_behind + d_alpha * t_final * inv;
                        behind_r = a * cr + one_minus * behind_r;
                        behind_g = a * cg + one_minus * behind_g;
                        behind_b = a * cbl + one_minus * behind_b;
                        behind_z = a * depth + one_minus * behind_z;
                        trans = t_k;
                        // The alpha clamp cuts the gradient to opacity and shape.
                        if raw < alpha_max {
                            shares[8] = density * d_a;
                            let d_power = raw * d_a;
                            shares[0] = d_power * (ca * dx + cb * dy);
                            shares[1] = d_power * (cb * dx + cc * dy);
                            shares[2] = -0.5f32 * d_power * dx * dx;
                            shares[3] = -d_power * dx * dy;
                            shares[4] = -0.5f32 * d_power * dy * dy;
                        }
                    }
                }
                let gid = usize::cast_from(ids[batch_start + k]);
                if comptime![planes] {
                    // Sum within each plane (no barrier), one atomic add per plane; planes
                    // where no pixel touched the Gaussian skip it.
                    let mut touched = false;
                    for j in 0..10usize {
                        touched = touched || shares[j] != 0.0f32;
                    }
                    if plane_any(touched) {
                        for j in 0..10usize {
                            let total = plane_sum(shares[j]);
                            if UNIT_POS_PLANE == 0 && total != 0.0f32 {
                                A::add(&mut grads[10 * gid + j], total);
                            }
                        }
                    }
                } else {
                    // Sum over the cube in shared memory (pairwise with doubling strides; a
                    // loop variable must start from a literal: one initialised from a
                    // comptime value and then changed fails verification), one atomic add.
                    for j in 0..10usize {
                        sums[j * units + t] = shares[j];
                    }
                    sync_cube();
                    let mut stride = 1usize;
                    while stride < units {
                        if t & (2 * stride - 1) == 0 {
                            for j in 0..10usize {
                                sums[j * units + t] += sums[j * units + t + stride];
                            }
                        }
                        sync_cube();
                        stride *= 2;
                    }
                    if t == 0 {
                        for j in 0..10usize {
                            let total = sums[j * units];
                            if total != 0.0f32 {
                                A::add(&mut grads[10 * gid + j], total);
                            }
                        }
                    }
                }
            }
            sync_cube();
            batch_end = batch_start;
        }
    }
}

/// The kernels above as CUDA C, for the offline NVRTC check: the backward in the variant
/// [`Accumulation::for_properties`] picks for `target`, as a launch on it would.
#[cfg(feature = "cuda-source")]
pub(super) fn cuda_kernels(target: &CudaTarget) -> Result<Vec<KernelSource>, String> {
    let (s, p, t) = target.settings(CubeDim::new_2d(TILE_SIZE as u32, TILE_SIZE as u32));
    let forward = target.source(
        "forward",
        kernels::forward::Forward::new(
            s.clone(),
            p.clone(),
            t.clone(),
            tensor(),
            tensor(),
            tensor(),
            tensor(),
            tensor(),
            tensor(),
            tensor(),
            tensor(),
            (),
            (),
            (),
            (),
            (),
            TILE_SIZE as u32,
        ),
    )?;
    let accumulation = Accumulation::for_properties(target.properties());
    let label = format!(
        "backward ({}, {})",
        if accumulation.float_atomics {
            "float atomics"
        } else {
            "compare-and-swap"
        },
        if accumulation.planes {
            "plane sums"
        } else {
            "cube sums"
        }
    );
    macro_rules! backward {
        ($add:ty) => {
            target.source(
                label,
                kernels::backward::Backward::<$add>::new(
                    s,
                    p,
                    t,
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    tensor(),
                    (),
                    (),
                    (),
                    (),
                    TILE_SIZE as u32,
                    accumulation.planes,
                ),
            )
        };
    }
    let backward = if accumulation.float_atomics {
        backward!(kernels::FloatAdd)?
    } else {
        backward!(kernels::SwapAdd)?
    };
    Ok(vec![forward, backward])
}

/// A forward render on the device: the packed `[H, W, 5]` image (RGB, alpha, depth), the
/// final transmittance `[H, W]` and the one-past-last contributing list position `[H, W]`.
#[derive(Clone, Debug)]
pub struct Raster {
    pub image: FloatTensor<CubeBackend>,
    pub final_transmittance: FloatTensor<CubeBackend>,
    pub n_contrib: IntTensor<CubeBackend>,
}

fn tile_grid(width: u32, height: u32) -> CubeCount {
    let tile = TILE_SIZE as u32;
    CubeCount::Static(width.div_ceil(tile), height.div_ceil(tile), 1)
}

/// Composites `bins` (the projected Gaussians `screen` with their `radii`) over `background`
/// (`[3]`) into a `width × height` image.
#[allow(clippy::too_many_arguments)]
pub fn rasterize(
    screen: &FloatTensor<CubeBackend>,
    radii: &IntTensor<CubeBackend>,
    bins: &TileBins,
    background: &FloatTensor<CubeBackend>,
    width: u32,
    height: u32,
    alpha_max: f64,
) -> Raster {
    let screen = into_contiguous(screen.clone());
    let (client, device) = (screen.client.clone(), screen.device.clone());
    let (w, h) = (width as usize, height as usize);
    let empty = |shape: Shape, dtype: DType| {
        empty_device_contiguous_dtype(client.clone(), device.clone(), shape, dtype)
    };
    let image = empty(Shape::new([h, w, PACKED_CHANNELS]), DType::F32);
    let final_transmittance = empty(Shape::new([h, w]), DType::F32);
    let n_contrib = empty(Shape::new([h, w]), DType::I32);
    kernels::forward::launch(
        &client,
        tile_grid(width, height),
        CubeDim::new_2d(TILE_SIZE as u32, TILE_SIZE as u32),
        screen.into_tensor_arg(),
        into_contiguous(radii.clone()).into_tensor_arg(),
        bins.offsets.clone().into_tensor_arg(),
        bins.ids.clone().into_tensor_arg(),
        into_contiguous(background.clone()).into_tensor_arg(),
        image.clone().into_tensor_arg(),
        final_transmittance.clone().into_tensor_arg(),
        n_contrib.clone().into_tensor_arg(),
        width,
        height,
        alpha_max as f32,
        ALPHA_MIN as f32,
        TRANSMITTANCE_MIN as f32,
        TILE_SIZE as u32,
    );
    Raster {
        image,
        final_transmittance,
        n_contrib,
    }
}

/// How the backward sums each Gaussian's gradient over the pixels of a tile and over tiles.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Accumulation {
    /// Float atomic adds into global memory; otherwise a compare-and-swap loop on the bits.
    pub float_atomics: bool,
    /// Sums within planes (warps) and one atomic per plane; otherwise sums over the whole
    /// cube in shared memory and one atomic per cube.
    pub planes: bool,
}

impl Accumulation {
    /// The fastest that `client`'s device supports.
    pub fn best(client: &Client) -> Self {
        Self::for_properties(client.properties())
    }

    /// The fastest that a device with these properties supports.
    pub fn for_properties(properties: &DeviceProperties) -> Self {
        Self {
            float_atomics: properties
                .atomic_type_usage(Type::atomic(ElemType::Float(FloatKind::F32)))
                .contains(AtomicUsage::Add),
            planes: properties.features.plane.contains(Plane::Ops),
        }
    }
}

/// Gradients of a render with respect to its screen-space Gaussians (`[N, 10]`, the layout of
/// `screen`) and its background (`[3]`), given the gradient of the packed image.
#[allow(clippy::too_many_arguments)]
pub fn rasterize_backward(
    screen: &FloatTensor<CubeBackend>,
    radii: &IntTensor<CubeBackend>,
    bins: &TileBins,
    background: &FloatTensor<CubeBackend>,
    final_transmittance: &FloatTensor<CubeBackend>,
    n_contrib: &IntTensor<CubeBackend>,
    grad_image: &FloatTensor<CubeBackend>,
    width: u32,
    height: u32,
    alpha_max: f64,
    accumulation: Accumulation,
) -> (FloatTensor<CubeBackend>, FloatTensor<CubeBackend>) {
    let screen = into_contiguous(screen.clone());
    let n = screen.meta.shape()[0];
    let (client, device) = (screen.client.clone(), screen.device.clone());
    let grad_image = into_contiguous(grad_image.clone());
    let (w, h) = (width as usize, height as usize);
    // Zero bits are 0.0 either way; the compare-and-swap path reads and writes the same bytes
    // as u32. Made flat, then reshaped: a `[n, 10]` allocation would be pitched on CUDA.
    let grads = CubeBackend::float_reshape(
        CubeBackend::float_zeros(Shape::new([n * SCREEN_FLOATS]), &device, FloatDType::F32),
        Shape::new([n, SCREEN_FLOATS]),
    );
    if n > 0 && bins.count > 0 {
        let launch = if accumulation.float_atomics {
            kernels::backward::launch::<kernels::FloatAdd>
        } else {
            kernels::backward::launch::<kernels::SwapAdd>
        };
        launch(
            &client,
            tile_grid(width, height),
            CubeDim::new_2d(TILE_SIZE as u32, TILE_SIZE as u32),
            screen.into_tensor_arg(),
            into_contiguous(radii.clone()).into_tensor_arg(),
            bins.offsets.clone().into_tensor_arg(),
            bins.ids.clone().into_tensor_arg(),
            into_contiguous(background.clone()).into_tensor_arg(),
            into_contiguous(final_transmittance.clone()).into_tensor_arg(),
            into_contiguous(n_contrib.clone()).into_tensor_arg(),
            grad_image.clone().into_tensor_arg(),
            grads.clone().into_tensor_arg(),
            width,
            height,
            alpha_max as f32,
            ALPHA_MIN as f32,
            TILE_SIZE as u32,
            accumulation.planes,
        );
    }
    // Background: Σ over pixels of T_final · ∂L/∂colour.
    let colour_grad = CubeBackend::float_slice(
        grad_image,
        &[
            burn::tensor::Slice::from(0..h),
            burn::tensor::Slice::from(0..w),
            burn::tensor::Slice::from(0..3),
        ],
    );
    let weighted = CubeBackend::float_mul(
        colour_grad,
        CubeBackend::float_reshape(final_transmittance.clone(), Shape::new([h, w, 1])),
    );
    // Rows first, then the column of row sums: without autotune Burn reduces an axis with one
    // thread per output, so one `[h·w, 3]` sum is three threads walking every pixel. (On the
    // H200 the op's backward grew with the pixels, not the Gaussians: 67 ms at 1024² for 10k
    // or 300k Gaussians; this sum was its one step on three threads.)
    let row_sums = CubeBackend::float_sum_dim(weighted, 1);
    let background_grad =
        CubeBackend::float_reshape(CubeBackend::float_sum_dim(row_sums, 0), Shape::new([3]));
    (grads, background_grad)
}
