//! Tile binning and per-tile compositing, forward and backward.
//!
//! Work is split by rows of tiles: a row of 16×16 tiles owns 16 contiguous image rows and a
//! contiguous range of the tile/Gaussian intersection list, so threads never share a write.
//! Inside a tile the loop is Gaussian-major: each Gaussian updates the rows of its footprint,
//! 16 pixels at a time with branch-free lane code (masks instead of branches) that the compiler
//! vectorises; [`multiversion`] compiles it for AVX2 and AVX-512 and picks one at run time.
//! Per-lane accumulators keep the backward's reductions vectorisable too. The arithmetic per
//! pixel is exactly the one documented in [`crate::cpu`].

use multiversion::multiversion;
use rayon::prelude::*;

use super::PixelGrads;
use super::project::{Projected, ScreenGaussian, ScreenGrads};
use crate::semantics::{ALPHA_MIN, RenderOptions, TILE_SIZE, TRANSMITTANCE_MIN};
use crate::{Camera, real::Real};

/// Pixels `[x0, x1) × [y0, y1)` whose centres lie in the Gaussian's footprint box
/// `|u − μ_u| ≤ r_x`, `|v − μ_v| ≤ r_y`, clipped to the image; `None` if there are none.
#[inline]
pub fn pixel_box<T: Real>(
    g: &ScreenGaussian<T>,
    width: usize,
    height: usize,
) -> Option<[usize; 4]> {
    let axis = |m: T, r: u32, size: usize| {
        let r = r as f64;
        let m = m.to_f64()?;
        // centre i + 0.5 ∈ [m − r, m + r]
        let lo = (m - r - 0.5).ceil().max(0.0);
        let hi = (m + r - 0.5).floor().min(size as f64 - 1.0);
        (lo <= hi).then_some((lo as usize, hi as usize + 1))
    };
    let (x0, x1) = axis(g.mean[0], g.radii[0], width)?;
    let (y0, y1) = axis(g.mean[1], g.radii[1], height)?;
    Some([x0, x1, y0, y1])
}

/// `min` as one compare-and-select (inputs are never NaN), so it vectorises to one instruction.
#[inline(always)]
fn min<T: Real>(a: T, b: T) -> T {
    if a < b { a } else { b }
}

/// How many tiles the footprint of `g` touches (0 when culled).
pub(crate) fn tiles_touched<T: Real>(g: &ScreenGaussian<T>) -> u64 {
    if !g.is_visible() {
        return 0;
    }
    let [x0, x1, y0, y1] = g.pixels.map(|v| v as u64);
    let t = TILE_SIZE as u64;
    ((x1 - 1) / t - x0 / t + 1) * ((y1 - 1) / t - y0 / t + 1)
}

/// Visible Gaussians listed per tile in depth order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TileBins {
    pub tiles_x: usize,
    pub tiles_y: usize,
    /// `offsets[t]..offsets[t + 1]` indexes `ids` for tile `t` (row-major tiles).
    pub offsets: Vec<u32>,
    /// Gaussian indices, front to back within each tile.
    pub ids: Vec<u32>,
}

impl TileBins {
    /// Number of tile/Gaussian intersections.
    pub fn num_intersections(&self) -> usize {
        self.ids.len()
    }

    fn row_range(&self, row: usize) -> std::ops::Range<usize> {
        self.offsets[row * self.tiles_x] as usize..self.offsets[(row + 1) * self.tiles_x] as usize
    }
}

/// Depth sort of the visible Gaussians (ties broken by index, so the order is total and
/// deterministic), then a counting sort by tile that keeps the depth order inside every tile.
pub fn bin_tiles<T: Real>(projected: &Projected<T>, width: usize, height: usize) -> TileBins {
    let tiles_x = width.div_ceil(TILE_SIZE);
    let tiles_y = height.div_ceil(TILE_SIZE);
    // Depths are positive (≥ near), so their IEEE bit patterns sort like the values.
    let mut keyed: Vec<(u64, u32)> = projected
        .par_iter()
        .enumerate()
        .filter(|(_, g)| g.is_visible())
        .map(|(i, g)| (g.depth.to_f64().map_or(u64::MAX, f64::to_bits), i as u32))
        .collect();
    keyed.par_sort_unstable();
    let tile_rects: Vec<(u32, [usize; 4])> = keyed
        .par_iter()
        .map(|&(_, i)| {
            let [x0, x1, y0, y1] = projected[i as usize].pixels.map(|v| v as usize);
            (
                i,
                [
                    x0 / TILE_SIZE,
                    (x1 - 1) / TILE_SIZE,
                    y0 / TILE_SIZE,
                    (y1 - 1) / TILE_SIZE,
                ],
            )
        })
        .collect();
    let mut counts = vec![0u32; tiles_x * tiles_y];
    for (_, [tx0, tx1, ty0, ty1]) in &tile_rects {
        for ty in *ty0..=*ty1 {
            for c in &mut counts[ty * tiles_x + tx0..=ty * tiles_x + tx1] {
                *c += 1;
            }
        }
    }
    let mut offsets = Vec::with_capacity(counts.len() + 1);
    let mut total = 0u32;
    offsets.push(0);
    for c in &counts {
        total += c;
        offsets.push(total);
    }
    let mut cursor = offsets.clone();
    let mut ids = vec![0u32; total as usize];
    for (i, [tx0, tx1, ty0, ty1]) in &tile_rects {
        for ty in *ty0..=*ty1 {
            for t in ty * tiles_x + tx0..=ty * tiles_x + tx1 {
                ids[cursor[t] as usize] = *i;
                cursor[t] += 1;
            }
        }
    }
    TileBins {
        tiles_x,
        tiles_y,
        offsets,
        ids,
    }
}

/// Everything a forward render produces; the backward pass reads it back.
#[derive(Clone, Debug)]
pub struct ForwardOutput<T> {
    /// `[H,W,3]`, background composited.
    pub color: Vec<T>,
    /// `[H,W]`, `1 − T_final`.
    pub alpha: Vec<T>,
    /// `[H,W]`, `Σ zᵢ αᵢ Tᵢ`.
    pub depth: Vec<T>,
    /// Final transmittance per pixel `[H,W]`.
    pub final_transmittance: Vec<T>,
    /// Per pixel, one past the tile-list position of its last contribution `[H,W]`.
    pub n_contrib: Vec<u32>,
    pub projected: Projected<T>,
    pub bins: TileBins,
    pub background: [T; 3],
    /// Number of Gaussian–pixel evaluations (footprint pixels visited while still compositing).
    pub evaluations: u64,
}

/// A tile's pixel rectangle.
#[derive(Clone, Copy)]
struct TileRect {
    x_base: usize,
    y_base: usize,
    w: usize,
    h: usize,
}

impl TileRect {
    /// The Gaussian's footprint inside this tile, in tile-local lane/row coordinates.
    #[inline]
    fn clip<T: Real>(&self, g: &ScreenGaussian<T>) -> [usize; 4] {
        let [x0, x1, y0, y1] = g.pixels.map(|v| v as usize);
        [
            x0.max(self.x_base) - self.x_base,
            x1.min(self.x_base + self.w).max(self.x_base) - self.x_base,
            y0.max(self.y_base) - self.y_base,
            y1.min(self.y_base + self.h).max(self.y_base) - self.y_base,
        ]
    }
}

/// One tile row: a fixed-size array, so lane indexing needs no bounds checks and vectorises.
type Row<T> = [T; TILE_SIZE];

/// Per-pixel compositing state of one tile, as rows of lanes.
struct ForwardTile<T> {
    t: [Row<T>; TILE_SIZE],
    rgb: [[Row<T>; TILE_SIZE]; 3],
    z: [Row<T>; TILE_SIZE],
    last: [Row<u32>; TILE_SIZE],
    done: [Row<u32>; TILE_SIZE],
    /// Pixels of each row still compositing, so finished rows are skipped.
    row_open: Row<u32>,
}

impl<T: Real> ForwardTile<T> {
    fn new() -> Self {
        Self {
            t: [[T::one(); TILE_SIZE]; TILE_SIZE],
            rgb: [[[T::zero(); TILE_SIZE]; TILE_SIZE]; 3],
            z: [[T::zero(); TILE_SIZE]; TILE_SIZE],
            last: [[0; TILE_SIZE]; TILE_SIZE],
            done: [[0; TILE_SIZE]; TILE_SIZE],
            row_open: [0; TILE_SIZE],
        }
    }

    /// Fresh state; lanes outside the image (`w × h` valid) count as done.
    fn reset(&mut self, w: usize, h: usize) {
        *self = Self::new();
        self.done = std::array::from_fn(|ly| std::array::from_fn(|lx| (lx >= w || ly >= h) as u32));
        self.row_open = std::array::from_fn(|ly| if ly < h { w as u32 } else { 0 });
    }
}

/// Composites one tile's list front to back; returns the number of evaluations.
#[multiversion(targets(
    "x86_64+avx512f+avx512vl+avx512bw+avx512dq+avx2+fma",
    "x86_64+avx2+fma"
))]
fn composite_tile<T: Real>(
    list: &[u32],
    projected: &[ScreenGaussian<T>],
    rect: TileRect,
    alpha_max: T,
    s: &mut ForwardTile<T>,
) -> u64 {
    let (alpha_min, t_min) = (T::c(ALPHA_MIN), T::c(TRANSMITTANCE_MIN));
    let half = T::c(0.5);
    let mut active = (rect.w * rect.h) as u32;
    let mut evaluations = 0u64;
    for (k, &id) in list.iter().enumerate() {
        if active == 0 {
            break;
        }
        let g = &projected[id as usize];
        let [lx0, lx1, ly0, ly1] = rect.clip(g);
        let (lx0, lx1) = (lx0 as u32, lx1 as u32);
        let dx: Row<T> =
            std::array::from_fn(|lane| T::c((rect.x_base + lane) as f64 + 0.5) - g.mean[0]);
        let quad_x: Row<T> = std::array::from_fn(|lane| g.conic[0] * dx[lane] * dx[lane]);
        let k1 = k as u32 + 1;
        let mut stops = 0u32;
        for ly in ly0..ly1 {
            if s.row_open[ly] == 0 {
                continue;
            }
            let dy = T::c((rect.y_base + ly) as f64 + 0.5) - g.mean[1];
            let quad_y = g.conic[2] * dy * dy;
            let cross = g.conic[1] * dy;
            let [r, gr, b] = &mut s.rgb;
            let (r, gr, b) = (&mut r[ly], &mut gr[ly], &mut b[ly]);
            let (t, z, last, done) = (&mut s.t[ly], &mut s.z[ly], &mut s.last[ly], &mut s.done[ly]);
            let mut row_evals = 0u32;
            let mut row_stops = 0u32;
            for lane in 0..TILE_SIZE {
                let power = -half * (quad_x[lane] + quad_y) - cross * dx[lane];
                let alpha = min(g.opacity * power.raster_exp(), alpha_max);
                let in_box = (lane as u32 >= lx0) & ((lane as u32) < lx1);
                let open = in_box & (done[lane] == 0);
                row_evals += open as u32;
                let live = open & (power <= T::zero()) & (alpha >= alpha_min);
                let next_t = t[lane] * (T::one() - alpha);
                let stop = live & (next_t <= t_min);
                let contrib = live & !stop;
                let w = if contrib { alpha * t[lane] } else { T::zero() };
                r[lane] = w.mul_add(g.color[0], r[lane]);
                gr[lane] = w.mul_add(g.color[1], gr[lane]);
                b[lane] = w.mul_add(g.color[2], b[lane]);
                z[lane] = w.mul_add(g.depth, z[lane]);
                t[lane] = if contrib { next_t } else { t[lane] };
                last[lane] = if contrib { k1 } else { last[lane] };
                done[lane] |= stop as u32;
                row_stops += stop as u32;
            }
            evaluations += row_evals as u64;
            s.row_open[ly] -= row_stops;
            stops += row_stops;
        }
        active -= stops;
    }
    evaluations
}

/// Composites every tile front to back.
pub fn rasterize<T: Real>(
    projected: Projected<T>,
    bins: TileBins,
    camera: &Camera,
    background: [T; 3],
    options: &RenderOptions,
) -> ForwardOutput<T> {
    let (width, height) = (camera.width as usize, camera.height as usize);
    let mut color = vec![T::zero(); width * height * 3];
    let mut alpha = vec![T::zero(); width * height];
    let mut depth = vec![T::zero(); width * height];
    let mut final_t = vec![T::one(); width * height];
    let mut n_contrib = vec![0u32; width * height];
    let alpha_max = T::c(options.alpha_max);
    let rows = TILE_SIZE * width;

    let evaluations: u64 = color
        .par_chunks_mut(rows * 3)
        .zip(alpha.par_chunks_mut(rows))
        .zip(depth.par_chunks_mut(rows))
        .zip(final_t.par_chunks_mut(rows))
        .zip(n_contrib.par_chunks_mut(rows))
        .enumerate()
        .map(
            |(tile_row, ((((color, alpha), depth), final_t), n_contrib))| {
                let y_base = tile_row * TILE_SIZE;
                let mut evaluations = 0u64;
                let mut s = ForwardTile::new();
                for tile_col in 0..bins.tiles_x {
                    let x_base = tile_col * TILE_SIZE;
                    let rect = TileRect {
                        x_base,
                        y_base,
                        w: (width - x_base).min(TILE_SIZE),
                        h: (height - y_base).min(TILE_SIZE),
                    };
                    let tile = tile_row * bins.tiles_x + tile_col;
                    let list =
                        &bins.ids[bins.offsets[tile] as usize..bins.offsets[tile + 1] as usize];
                    s.reset(rect.w, rect.h);
                    evaluations += composite_tile(list, &projected, rect, alpha_max, &mut s);
                    for ly in 0..rect.h {
                        for lx in 0..rect.w {
                            let o = ly * width + x_base + lx;
                            let t = s.t[ly][lx];
                            for c in 0..3 {
                                color[3 * o + c] = s.rgb[c][ly][lx] + t * background[c];
                            }
                            alpha[o] = T::one() - t;
                            depth[o] = s.z[ly][lx];
                            final_t[o] = t;
                            n_contrib[o] = s.last[ly][lx];
                        }
                    }
                }
                evaluations
            },
        )
        .sum();

    ForwardOutput {
        color,
        alpha,
        depth,
        final_transmittance: final_t,
        n_contrib,
        projected,
        bins,
        background,
        evaluations,
    }
}

/// Gradients with respect to the screen-space Gaussians and the background.
#[derive(Clone, Debug)]
pub struct RasterGrads<T> {
    /// One per Gaussian (zero for culled ones).
    pub screen: Vec<ScreenGrads<T>>,
    pub background: [T; 3],
    /// Number of Gaussian–pixel evaluations performed.
    pub evaluations: u64,
}

/// Per-pixel backward state of one tile, as rows of lanes.
struct BackwardTile<T> {
    /// Transmittance before the current Gaussian (starts at the final one).
    t: [Row<T>; TILE_SIZE],
    final_t: [Row<T>; TILE_SIZE],
    /// Colour and depth of everything behind the current Gaussian, background included.
    behind: [[Row<T>; TILE_SIZE]; 3],
    behind_z: [Row<T>; TILE_SIZE],
    last: [Row<u32>; TILE_SIZE],
    d_color: [[Row<T>; TILE_SIZE]; 3],
    d_alpha: [Row<T>; TILE_SIZE],
    d_depth: [Row<T>; TILE_SIZE],
}

impl<T: Real> BackwardTile<T> {
    fn new() -> Self {
        let zero = [[T::zero(); TILE_SIZE]; TILE_SIZE];
        Self {
            t: zero,
            final_t: zero,
            behind: [zero; 3],
            behind_z: zero,
            last: [[0; TILE_SIZE]; TILE_SIZE],
            d_color: [zero; 3],
            d_alpha: zero,
            d_depth: zero,
        }
    }
}

/// Sum of a row in a fixed pairwise order: deterministic, and it vectorises (unlike a fold).
#[inline(always)]
fn tree_sum<T: Real>(v: &Row<T>) -> T {
    let h8: [T; 8] = std::array::from_fn(|i| v[i] + v[i + 8]);
    let h4: [T; 4] = std::array::from_fn(|i| h8[i] + h8[i + 4]);
    (h4[0] + h4[2]) + (h4[1] + h4[3])
}

/// Walks one tile's list back to front; writes one gradient per list entry.
///
/// Each row is done in two lane loops (alpha and masks first, then the state and gradient
/// updates) so that each loop keeps few enough arrays live to vectorise with 16 registers.
#[multiversion(targets(
    "x86_64+avx512f+avx512vl+avx512bw+avx512dq+avx2+fma",
    "x86_64+avx2+fma"
))]
fn backward_tile<T: Real>(
    list: &[u32],
    projected: &[ScreenGaussian<T>],
    rect: TileRect,
    alpha_max: T,
    s: &mut BackwardTile<T>,
    out: &mut [ScreenGrads<T>],
) -> u64 {
    let alpha_min = T::c(ALPHA_MIN);
    let half = T::c(0.5);
    let (zero, one) = (T::zero(), T::one());
    // Rows whose pixels all stopped before list position k are skipped.
    let row_last: Row<u32> =
        std::array::from_fn(|ly| s.last[ly].iter().copied().max().unwrap_or(0));
    let max_last = row_last.iter().copied().max().unwrap_or(0) as usize;
    let mut evaluations = 0u64;
    for k in (0..max_last).rev() {
        let g = &projected[list[k] as usize];
        let [lx0, lx1, ly0, ly1] = rect.clip(g);
        let (lx0, lx1) = (lx0 as u32, lx1 as u32);
        let dx: Row<T> =
            std::array::from_fn(|lane| T::c((rect.x_base + lane) as f64 + 0.5) - g.mean[0]);
        let quad_x: Row<T> = std::array::from_fn(|lane| g.conic[0] * dx[lane] * dx[lane]);
        let k1 = k as u32 + 1;
        // Per-lane partial sums over rows. With p = ∂L/∂power: Σp, Σ dy·p, Σ dy²·p (the shape
        // gradients are moments of p, finished below with dx), then colour (3), opacity, depth.
        let mut acc = [[zero; TILE_SIZE]; 8];
        for ly in ly0..ly1 {
            if k1 > row_last[ly] {
                continue;
            }
            let dy = T::c((rect.y_base + ly) as f64 + 0.5) - g.mean[1];
            let (quad_y, cross) = (g.conic[2] * dy * dy, g.conic[1] * dy);
            let last = &s.last[ly];
            // Pass 1: alpha, the validity mask (as 0/1) and the unclamped-alpha mask.
            let mut alpha: Row<T> = [zero; TILE_SIZE];
            let mut raw: Row<T> = [zero; TILE_SIZE];
            let mut density: Row<T> = [zero; TILE_SIZE];
            let mut valid: Row<T> = [zero; TILE_SIZE];
            let mut shape: Row<T> = [zero; TILE_SIZE];
            let mut row_evals = 0u32;
            let mut row_valid = 0u32;
            for lane in 0..TILE_SIZE {
                let power = -half * (quad_x[lane] + quad_y) - cross * dx[lane];
                let d = power.raster_exp();
                let r = g.opacity * d;
                let a = min(r, alpha_max);
                let in_box = (lane as u32 >= lx0) & ((lane as u32) < lx1);
                let open = in_box & (k1 <= last[lane]);
                row_evals += open as u32;
                let ok = open & (power <= zero) & (a >= alpha_min);
                row_valid += ok as u32;
                density[lane] = d;
                raw[lane] = r;
                alpha[lane] = if ok { a } else { zero };
                valid[lane] = if ok { one } else { zero };
                // The alpha clamp cuts the gradient to opacity and shape.
                shape[lane] = if ok & (r < alpha_max) { one } else { zero };
            }
            evaluations += row_evals as u64;
            if row_valid == 0 {
                continue;
            }
            // Pass 2: un-composite this Gaussian and accumulate its gradient. Invalid lanes have
            // alpha 0, so t and the colour behind are unchanged there and their weight is 0.
            let [br, bg, bb] = &mut s.behind;
            let behind = [&mut br[ly], &mut bg[ly], &mut bb[ly]];
            let (t, behind_z) = (&mut s.t[ly], &mut s.behind_z[ly]);
            let (final_t, d_alpha, d_depth) = (&s.final_t[ly], &s.d_alpha[ly], &s.d_depth[ly]);
            let d_color = [&s.d_color[0][ly], &s.d_color[1][ly], &s.d_color[2][ly]];
            for lane in 0..TILE_SIZE {
                let a = alpha[lane];
                let one_minus = one - a;
                let inv_one_minus = one / one_minus;
                let t_k = t[lane] * inv_one_minus;
                let w = a * t_k;
                let mut d_a = (g.depth - behind_z[lane]) * d_depth[lane];
                for c in 0..3 {
                    acc[3 + c][lane] = w.mul_add(d_color[c][lane], acc[3 + c][lane]);
                    d_a = (g.color[c] - behind[c][lane]).mul_add(d_color[c][lane], d_a);
                    behind[c][lane] = a.mul_add(g.color[c], one_minus * behind[c][lane]);
                }
                acc[7][lane] = w.mul_add(d_depth[lane], acc[7][lane]);
                let d_a =
                    t_k.mul_add(d_a, d_alpha[lane] * final_t[lane] * inv_one_minus) * valid[lane];
                behind_z[lane] = a.mul_add(g.depth, one_minus * behind_z[lane]);
                t[lane] = t_k;
                let d_a = d_a * shape[lane];
                acc[6][lane] = density[lane].mul_add(d_a, acc[6][lane]);
                let d_pw = raw[lane] * d_a;
                acc[0][lane] = acc[0][lane] + d_pw;
                acc[1][lane] = dy.mul_add(d_pw, acc[1][lane]);
                acc[2][lane] = (dy * dy).mul_add(d_pw, acc[2][lane]);
            }
        }
        // power = −½(a dx² + c dy²) − b dx dy, with dx = px − μx, dy = py − μy.
        let p_dx: Row<T> = std::array::from_fn(|i| acc[0][i] * dx[i]);
        let p_dx2: Row<T> = std::array::from_fn(|i| p_dx[i] * dx[i]);
        let p_dxdy: Row<T> = std::array::from_fn(|i| acc[1][i] * dx[i]);
        let (s_x, s_xx) = (tree_sum(&p_dx), tree_sum(&p_dx2));
        let (s_y, s_xy, s_yy) = (tree_sum(&acc[1]), tree_sum(&p_dxdy), tree_sum(&acc[2]));
        let [ca, cb, cc] = g.conic;
        out[k] = ScreenGrads {
            mean: [ca * s_x + cb * s_y, cb * s_x + cc * s_y],
            conic: [-half * s_xx, -s_xy, -half * s_yy],
            color: [tree_sum(&acc[3]), tree_sum(&acc[4]), tree_sum(&acc[5])],
            opacity: tree_sum(&acc[6]),
            depth: tree_sum(&acc[7]),
        };
    }
    evaluations
}

/// Walks every pixel's contributions back to front from its final transmittance.
pub fn rasterize_backward<T: Real>(
    fwd: &ForwardOutput<T>,
    camera: &Camera,
    options: &RenderOptions,
    grads: &PixelGrads<T>,
) -> RasterGrads<T> {
    let (width, height) = (camera.width as usize, camera.height as usize);
    let bins = &fwd.bins;
    let alpha_max = T::c(options.alpha_max);
    let zero = T::zero();

    // One gradient slot per intersection, split by tile rows so that threads write disjoint ranges.
    let mut per_isect = vec![ScreenGrads::<T>::default(); bins.num_intersections()];
    let mut row_slices = Vec::with_capacity(bins.tiles_y);
    let mut rest = per_isect.as_mut_slice();
    for row in 0..bins.tiles_y {
        let (head, tail) = rest.split_at_mut(bins.row_range(row).len());
        row_slices.push(head);
        rest = tail;
    }

    let evaluations: u64 = row_slices
        .into_par_iter()
        .enumerate()
        .map(|(tile_row, row_grads)| {
            let y_base = tile_row * TILE_SIZE;
            let row_start = bins.row_range(tile_row).start;
            let mut evaluations = 0u64;
            let mut s = BackwardTile::new();
            for tile_col in 0..bins.tiles_x {
                let x_base = tile_col * TILE_SIZE;
                let rect = TileRect {
                    x_base,
                    y_base,
                    w: (width - x_base).min(TILE_SIZE),
                    h: (height - y_base).min(TILE_SIZE),
                };
                let tile = tile_row * bins.tiles_x + tile_col;
                let start = bins.offsets[tile] as usize;
                let list = &bins.ids[start..bins.offsets[tile + 1] as usize];
                for ly in 0..TILE_SIZE {
                    for lx in 0..TILE_SIZE {
                        s.behind_z[ly][lx] = zero;
                        if lx >= rect.w || ly >= rect.h {
                            s.last[ly][lx] = 0;
                            continue;
                        }
                        let o = (y_base + ly) * width + x_base + lx;
                        s.t[ly][lx] = fwd.final_transmittance[o];
                        s.final_t[ly][lx] = s.t[ly][lx];
                        s.last[ly][lx] = fwd.n_contrib[o];
                        s.d_alpha[ly][lx] = grads.alpha[o];
                        s.d_depth[ly][lx] = grads.depth[o];
                        for c in 0..3 {
                            s.behind[c][ly][lx] = fwd.background[c];
                            s.d_color[c][ly][lx] = grads.color[3 * o + c];
                        }
                    }
                }
                let out = &mut row_grads[start - row_start..start - row_start + list.len()];
                evaluations += backward_tile(list, &fwd.projected, rect, alpha_max, &mut s, out);
            }
            evaluations
        })
        .sum();

    let mut screen = vec![ScreenGrads::<T>::default(); fwd.projected.len()];
    for (acc, &id) in per_isect.iter().zip(&bins.ids) {
        let s = &mut screen[id as usize];
        for c in 0..2 {
            s.mean[c] = s.mean[c] + acc.mean[c];
        }
        for c in 0..3 {
            s.conic[c] = s.conic[c] + acc.conic[c];
            s.color[c] = s.color[c] + acc.color[c];
        }
        s.opacity = s.opacity + acc.opacity;
        s.depth = s.depth + acc.depth;
    }

    let background = fwd
        .final_transmittance
        .par_iter()
        .zip(grads.color.par_chunks(3))
        .map(|(&t, dc)| [t * dc[0], t * dc[1], t * dc[2]])
        .reduce(|| [zero; 3], |a, b| [a[0] + b[0], a[1] + b[1], a[2] + b[2]]);
    RasterGrads {
        screen,
        background,
        evaluations,
    }
}
