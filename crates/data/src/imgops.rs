//! Image operations on `[H, W, C]` f32 images: resizing with matching intrinsics,
//! crop-and-resize, mask morphology, drawing.

use f3g_camera::Camera;
use f3g_io::Image;

/// Resizes to `width × height` (triangle filter, i.e. bilinear with area averaging when
/// shrinking).
pub fn resize(img: &Image, width: usize, height: usize) -> Image {
    use image::imageops::{FilterType, resize as resize_buffer};
    let data = match img.channels {
        1 => {
            let buf = image::ImageBuffer::<image::Luma<f32>, Vec<f32>>::from_raw(
                img.width as u32,
                img.height as u32,
                img.data.clone(),
            )
            .expect("sized buffer");
            resize_buffer(&buf, width as u32, height as u32, FilterType::Triangle).into_raw()
        }
        _ => {
            let buf = image::ImageBuffer::<image::Rgb<f32>, Vec<f32>>::from_raw(
                img.width as u32,
                img.height as u32,
                img.data.clone(),
            )
            .expect("sized buffer");
            resize_buffer(&buf, width as u32, height as u32, FilterType::Triangle).into_raw()
        }
    };
    Image {
        width,
        height,
        channels: img.channels,
        data,
    }
}

/// The first channel of `img` shrunk to `width × height` (no larger than it) by area
/// averaging: each output pixel is the mean of the input area it covers, exactly. Several
/// times faster than [`resize`]'s filter on masks, whose edges it keeps as sharp.
pub fn shrink_channel(img: &Image, width: usize, height: usize) -> Vec<f32> {
    // Per output index: the input indices it covers with their weights (summing to 1).
    let spans = |from: usize, to: usize| -> Vec<Vec<(usize, f32)>> {
        let s = from as f64 / to as f64;
        (0..to)
            .map(|o| {
                let (a, b) = (o as f64 * s, (o + 1) as f64 * s);
                (a.floor() as usize..(b.ceil() as usize).min(from))
                    .map(|i| {
                        let w = (b.min(i as f64 + 1.0) - a.max(i as f64)) / s;
                        (i, w as f32)
                    })
                    .collect()
            })
            .collect()
    };
    let (xs, ys) = (spans(img.width, width), spans(img.height, height));
    let mut rows = vec![0.0f32; width * img.height];
    for y in 0..img.height {
        for (x, span) in xs.iter().enumerate() {
            rows[y * width + x] = span
                .iter()
                .map(|&(i, w)| w * img.data[(y * img.width + i) * img.channels])
                .sum();
        }
    }
    let mut out = vec![0.0f32; width * height];
    for (y, span) in ys.iter().enumerate() {
        for x in 0..width {
            out[y * width + x] = span.iter().map(|&(i, w)| w * rows[i * width + x]).sum();
        }
    }
    out
}

/// The camera of an image resized from the camera's size to `width × height`: pixel
/// coordinates scale by `width / W` and `height / H` (exact, since pixel centres are at i + 0.5).
pub fn resized_camera(camera: &Camera, width: usize, height: usize) -> Camera {
    let (sx, sy) = (
        width as f64 / camera.width as f64,
        height as f64 / camera.height as f64,
    );
    let mut c = camera.clone();
    c.k[0][0] *= sx;
    c.k[0][2] *= sx;
    c.k[1][1] *= sy;
    c.k[1][2] *= sy;
    c.width = width as u32;
    c.height = height as u32;
    c
}

/// Size of an image scaled by `scale` (at least 1×1).
pub fn scaled_size(width: usize, height: usize, scale: f32) -> (usize, usize) {
    (
        ((width as f32 * scale).round() as usize).max(1),
        ((height as f32 * scale).round() as usize).max(1),
    )
}

/// Bilinear sample at continuous pixel coordinates (pixel centres at i + 0.5); `fill` outside.
fn sample(img: &Image, x: f32, y: f32, fill: &[f32], out: &mut [f32]) {
    let (fx, fy) = (x - 0.5, y - 0.5);
    let (x0, y0) = (fx.floor(), fy.floor());
    let (tx, ty) = (fx - x0, fy - y0);
    out.iter_mut().for_each(|o| *o = 0.0);
    for (dx, dy, w) in [
        (0, 0, (1.0 - tx) * (1.0 - ty)),
        (1, 0, tx * (1.0 - ty)),
        (0, 1, (1.0 - tx) * ty),
        (1, 1, tx * ty),
    ] {
        let (xi, yi) = (x0 as i64 + dx, y0 as i64 + dy);
        let inside = xi >= 0 && yi >= 0 && (xi as usize) < img.width && (yi as usize) < img.height;
        for c in 0..img.channels {
            let v = if inside {
                img.data[(yi as usize * img.width + xi as usize) * img.channels + c]
            } else {
                fill[c]
            };
            out[c] += w * v;
        }
    }
}

/// A square crop: top-left `(x0, y0)` and side in source pixels, resampled to `size × size`
/// (`fill` outside the image). Use [`Camera::crop_resize`] with `scale = size / side` for its
/// intrinsics.
///
/// Enlarging samples bilinearly at each output pixel's centre. Shrinking averages an `n × n`
/// grid of bilinear samples spread over the output pixel's footprint (`n = ⌈side / size⌉`),
/// so a 230-pixel head cut to 128² is filtered over its area instead of aliased.
pub fn crop_resize(img: &Image, x0: f32, y0: f32, side: f32, size: usize, fill: &[f32]) -> Image {
    let scale = side / size as f32;
    let n = scale.ceil().max(1.0) as usize;
    let c = img.channels;
    let mut out = Image::filled(size, size, c, 0.0);
    let mut tap = vec![0.0; c];
    for j in 0..size {
        for i in 0..size {
            let at = (j * size + i) * c;
            for sj in 0..n {
                for si in 0..n {
                    let (x, y) = (
                        x0 + (i as f32 + (si as f32 + 0.5) / n as f32) * scale,
                        y0 + (j as f32 + (sj as f32 + 0.5) / n as f32) * scale,
                    );
                    sample(img, x, y, fill, &mut tap);
                    for (o, t) in out.data[at..at + c].iter_mut().zip(&tap) {
                        *o += t / (n * n) as f32;
                    }
                }
            }
        }
    }
    out
}

/// Animatable Gaussians' LPIPS square: the box `[x0, x1) × [y0, y1)` centred in a square of
/// its longer side (offset `⌊(side − len) / 2⌋` along the shorter axis). The square may reach
/// past the image; its pixels outside the box are background (see [`square_image`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CentredSquare {
    /// The box `[x0, y0, x1, y1]` (end-exclusive), inside the image.
    pub bounds: [usize; 4],
    /// Top-left corner of the square in image pixels.
    pub x0: i64,
    pub y0: i64,
    pub side: usize,
}

impl CentredSquare {
    /// The square around `bounds` (end-exclusive, non-empty).
    pub fn new(bounds: [usize; 4]) -> Self {
        let [x0, y0, x1, y1] = bounds;
        let (w, h) = (x1 - x0, y1 - y0);
        let side = w.max(h);
        Self {
            bounds,
            x0: x0 as i64 - ((side - w) / 2) as i64,
            y0: y0 as i64 - ((side - h) / 2) as i64,
            side,
        }
    }

    /// The square around the mask's pixels above 0.5, their bounding box grown by `pad` pixels
    /// and clipped to the image first (the evaluation's 50-pixel padding; 0 in training).
    pub fn around_mask(mask: &Image, pad: usize) -> Option<Self> {
        let [x0, y0, x1, y1] = mask_bounds(mask, 0.5)?;
        Some(Self::new([
            x0.saturating_sub(pad),
            y0.saturating_sub(pad),
            (x1 + 1 + pad).min(mask.width),
            (y1 + 1 + pad).min(mask.height),
        ]))
    }
}

/// The pixels `[x0, x1) × [y0, y1)` of `img` (inside it) as an image of their own.
pub fn window(img: &Image, x0: usize, y0: usize, x1: usize, y1: usize) -> Image {
    let c = img.channels;
    let data = (y0..y1)
        .flat_map(|y| &img.data[(y * img.width + x0) * c..(y * img.width + x1) * c])
        .copied()
        .collect();
    Image {
        width: x1 - x0,
        height: y1 - y0,
        channels: c,
        data,
    }
}

/// The square of `sq` cut from `img`: the box's pixels, `fill` everywhere else.
pub fn square_image(img: &Image, sq: &CentredSquare, fill: &[f32]) -> Image {
    let c = img.channels;
    let mut out = Image::filled(sq.side, sq.side, c, 0.0);
    out.data
        .chunks_exact_mut(c)
        .for_each(|p| p.copy_from_slice(&fill[..c]));
    let [x0, y0, x1, y1] = sq.bounds;
    let (ox, oy) = ((x0 as i64 - sq.x0) as usize, (y0 as i64 - sq.y0) as usize);
    for y in y0..y1 {
        let src = (y * img.width + x0) * c;
        let dst = ((y - y0 + oy) * sq.side + ox) * c;
        out.data[dst..dst + (x1 - x0) * c].copy_from_slice(&img.data[src..src + (x1 - x0) * c]);
    }
    out
}

/// Inclusive pixel bounds `[x0, y0, x1, y1]` of the mask's pixels above `threshold`; `None`
/// when there are none.
pub fn mask_bounds(mask: &Image, threshold: f32) -> Option<[usize; 4]> {
    let (w, h) = (mask.width, mask.height);
    let (mut x0, mut x1, mut y0, mut y1) = (usize::MAX, 0, usize::MAX, 0);
    for y in 0..h {
        for x in 0..w {
            if mask.data[(y * w + x) * mask.channels] > threshold {
                (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
            }
        }
    }
    (x0 <= x1).then_some([x0, y0, x1, y1])
}

/// Square dilation (`grow`) or erosion of a boolean mask with a `(2r+1)²` window, clipped to
/// the image. Separable, each pass a sliding count of set pixels (a window is all set when its
/// count is its length): O(1) per pixel whatever `r`, and the column pass walks rows, not
/// columns (the loader runs this on every training view: 3 M pixels at 1536 × 2048).
pub fn morph(mask: &[bool], width: usize, height: usize, r: usize, grow: bool) -> Vec<bool> {
    if width == 0 || height == 0 {
        return Vec::new();
    }
    let keep = |count: u32, len: usize| {
        if grow {
            count > 0
        } else {
            count as usize == len
        }
    };
    let span = |i: usize, n: usize| (i + r).min(n - 1) - i.saturating_sub(r) + 1;
    let mut rows = vec![false; mask.len()];
    for (src, dst) in mask.chunks_exact(width).zip(rows.chunks_exact_mut(width)) {
        let mut count = src[..=r.min(width - 1)].iter().filter(|&&b| b).count() as u32;
        for x in 0..width {
            dst[x] = keep(count, span(x, width));
            if x + r + 1 < width && src[x + r + 1] {
                count += 1;
            }
            if x >= r && src[x - r] {
                count -= 1;
            }
        }
    }
    let mut counts = vec![0u32; width];
    let add = |counts: &mut [u32], row: &[bool], sign: i32| {
        for (c, &b) in counts.iter_mut().zip(row) {
            *c = c.wrapping_add_signed(sign * b as i32);
        }
    };
    let row = |y: usize| &rows[y * width..(y + 1) * width];
    for y in 0..=r.min(height - 1) {
        add(&mut counts, row(y), 1);
    }
    let mut out = vec![false; mask.len()];
    for (y, dst) in out.chunks_exact_mut(width).enumerate() {
        let len = span(y, height);
        for (o, &c) in dst.iter_mut().zip(&counts) {
            *o = keep(c, len);
        }
        if y + r + 1 < height {
            add(&mut counts, row(y + r + 1), 1);
        }
        if y >= r {
            add(&mut counts, row(y - r), -1);
        }
    }
    out
}

/// Draws a rectangle outline (thickness 2) on an RGB image.
pub fn draw_box(img: &mut Image, x0: f32, y0: f32, x1: f32, y1: f32, colour: [f32; 3]) {
    let (w, h) = (img.width as i64, img.height as i64);
    let (x0, y0, x1, y1) = (
        x0.round() as i64,
        y0.round() as i64,
        x1.round() as i64,
        y1.round() as i64,
    );
    let mut put = |x: i64, y: i64| {
        if x >= 0 && y >= 0 && x < w && y < h {
            img.pixel_mut(x as usize, y as usize)[..3].copy_from_slice(&colour);
        }
    };
    for t in 0..2 {
        for x in x0..=x1 {
            put(x, y0 + t);
            put(x, y1 - t);
        }
        for y in y0..=y1 {
            put(x0 + t, y);
            put(x1 - t, y);
        }
    }
}

/// Pastes `tile` into `canvas` at `(x, y)` (RGB).
pub fn paste(canvas: &mut Image, tile: &Image, x: usize, y: usize) {
    for j in 0..tile.height.min(canvas.height.saturating_sub(y)) {
        for i in 0..tile.width.min(canvas.width.saturating_sub(x)) {
            let src = tile.pixel(i, j);
            let rgb = if tile.channels == 1 {
                [src[0]; 3]
            } else {
                [src[0], src[1], src[2]]
            };
            canvas.pixel_mut(x + i, y + j)[..3].copy_from_slice(&rgb);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Area averaging keeps a mask's mean and makes each output pixel the covered share: a
    /// 9-pixel-wide block shrunk by 2.25 covers 4 output pixels exactly.
    #[test]
    fn shrinking_averages_the_covered_area() {
        let (w, h) = (18, 9);
        let data: Vec<f32> = (0..w * h).map(|p| (p % w < 9) as u8 as f32).collect();
        let img = Image {
            width: w,
            height: h,
            channels: 1,
            data,
        };
        let out = shrink_channel(&img, 8, 4);
        let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
        assert!((mean(&out) - mean(&img.data)).abs() < 1e-5);
        for y in 0..4 {
            let row = &out[y * 8..(y + 1) * 8];
            for (x, &v) in row.iter().enumerate() {
                let expected = if x < 4 { 1.0 } else { 0.0 };
                assert!((v - expected).abs() < 1e-5, "({x}, {y}): {v}");
            }
        }
    }

    #[test]
    fn crop_resize_samples_where_the_camera_says() {
        // A horizontal ramp: value = x coordinate of the pixel centre / width.
        let (w, h) = (40, 30);
        let data: Vec<f32> = (0..w * h)
            .flat_map(|p| [((p % w) as f32 + 0.5) / w as f32; 3])
            .collect();
        let img = Image::from_vec(w, h, 3, data).unwrap();
        let crop = crop_resize(&img, 10.0, 5.0, 20.0, 10, &[0.0; 3]);
        // Output pixel i samples x = 10 + (i + 0.5)·2.
        for i in 1..9 {
            let expected = (10.0 + (i as f32 + 0.5) * 2.0) / w as f32;
            assert!((crop.pixel(i, 4)[0] - expected).abs() < 1e-5);
        }
    }

    #[test]
    fn shrinking_crops_average_the_footprint() {
        // A one-pixel checkerboard cut 4:1 averages to grey; a single bilinear tap at each
        // output pixel's centre (here a source pixel's centre) would return black or white.
        let (w, h) = (64, 64);
        let data: Vec<f32> = (0..w * h).map(|p| ((p % w + p / w) % 2) as f32).collect();
        let img = Image::from_vec(w, h, 1, data).unwrap();
        let crop = crop_resize(&img, 0.5, 0.5, 64.0, 16, &[0.0]);
        // The last row and column reach past the image (filled with 0).
        for j in 0..15 {
            for i in 0..15 {
                let v = crop.pixel(i, j)[0];
                assert!((v - 0.5).abs() < 1e-5, "({i}, {j}): {v}");
            }
        }
        // Enlarging (n = 1) is the plain bilinear tap at the centre.
        let up = crop_resize(&img, 8.0, 8.0, 4.0, 8, &[0.0]);
        let mut tap = [0.0];
        sample(&img, 8.25, 8.25, &[0.0], &mut tap);
        assert_eq!(up.data[0], tap[0]);
    }

    /// The definition: each output pixel over its clipped window.
    fn morph_by_definition(m: &[bool], w: usize, h: usize, r: usize, grow: bool) -> Vec<bool> {
        let mut out = Vec::with_capacity(m.len());
        for y in 0..h {
            for x in 0..w {
                let mut window = (y.saturating_sub(r)..=(y + r).min(h - 1)).flat_map(|v| {
                    (x.saturating_sub(r)..=(x + r).min(w - 1)).map(move |u| m[v * w + u])
                });
                out.push(if grow {
                    window.any(|b| b)
                } else {
                    window.all(|b| b)
                });
            }
        }
        out
    }

    proptest! {
        #[test]
        fn morphology_matches_its_definition(
            (w, h, m) in (1usize..24, 1usize..24).prop_flat_map(|(w, h)| {
                (Just(w), Just(h), proptest::collection::vec(proptest::bool::weighted(0.6), w * h))
            }),
            r in 0usize..6,
            grow: bool,
        ) {
            prop_assert_eq!(morph(&m, w, h, r, grow), morph_by_definition(&m, w, h, r, grow));
        }
    }

    #[test]
    fn morphology() {
        let (w, h) = (7, 7);
        let mut m = vec![false; w * h];
        m[3 * w + 3] = true;
        let grown = morph(&m, w, h, 1, true);
        assert_eq!(grown.iter().filter(|x| **x).count(), 9);
        assert_eq!(morph(&grown, w, h, 1, false), m);
    }
}
