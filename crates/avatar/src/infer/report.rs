//! Pictures people look at: comparison grids (ground truth | render | error), loss curves as
//! PNG with a small built-in bitmap font, and the run report page.

use std::path::Path;

use burn::tensor::Tensor;

use crate::AvatarError;
use crate::model::host_values;
use f3g_data::imgops::paste;
use f3g_io::Image;
use f3g_io::text::draw_text;

/// Gap between grid cells, pixels.
const GAP: usize = 4;
const PAPER: f32 = 0.12;

/// A rendered `[H, W, 3]` tensor as a host image.
pub fn tensor_to_image(t: Tensor<3>) -> Image {
    let [h, w, c] = t.dims();
    Image {
        width: w,
        height: h,
        channels: c,
        data: host_values(t),
    }
}

/// Per-pixel error `|a − b|` (mean over channels, ×4) as a black → red → yellow heat map.
fn error_map(a: &Image, b: &Image) -> Image {
    let mut out = Image::filled(a.width, a.height, 3, 0.0);
    for (p, px) in out.data.chunks_exact_mut(3).enumerate() {
        let e: f32 = (0..3)
            .map(|c| (a.data[3 * p + c] - b.data[3 * p + c]).abs())
            .sum::<f32>()
            / 3.0;
        let v = (4.0 * e).clamp(0.0, 1.0);
        px.copy_from_slice(&[(2.0 * v).min(1.0), (2.0 * v - 1.0).max(0.0), 0.0]);
    }
    out
}

/// Images side by side on a dark background.
fn hstack(images: &[&Image]) -> Image {
    let h = images.iter().map(|i| i.height).max().unwrap_or(1);
    let w = images.iter().map(|i| i.width).sum::<usize>() + GAP * images.len().saturating_sub(1);
    let mut out = Image::filled(w.max(1), h, 3, PAPER);
    let mut x = 0;
    for img in images {
        paste(&mut out, img, x, 0);
        x += img.width + GAP;
    }
    out
}

/// Ground truth | render | error.
pub fn comparison_row(gt: &Image, render: &Image) -> Image {
    hstack(&[gt, render, &error_map(gt, render)])
}

/// Rows stacked top to bottom (each scaled to the first row's width when narrower rows are
/// wider than it).
pub fn stack_rows(rows: &[Image]) -> Image {
    let w = rows.iter().map(|r| r.width).max().unwrap_or(1);
    let scaled: Vec<Image> = rows
        .iter()
        .map(|r| {
            if r.width == w {
                r.clone()
            } else {
                let h = (r.height as f32 * w as f32 / r.width as f32).round() as usize;
                f3g_data::imgops::resize(r, w, h.max(1))
            }
        })
        .collect();
    let h = scaled.iter().map(|r| r.height).sum::<usize>() + GAP * rows.len().saturating_sub(1);
    let mut out = Image::filled(w, h.max(1), 3, PAPER);
    let mut y = 0;
    for r in &scaled {
        paste(&mut out, r, 0, y);
        y += r.height + GAP;
    }
    out
}

fn draw_line(img: &mut Image, a: (f32, f32), b: (f32, f32), colour: [f32; 3]) {
    let steps = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as usize).max(1);
    for s in 0..=steps {
        let t = s as f32 / steps as f32;
        let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
        for (dx, dy) in [(0i32, 0i32), (1, 0), (0, 1)] {
            let (px, py) = (x as i32 + dx, y as i32 + dy);
            if px >= 0 && py >= 0 && (px as usize) < img.width && (py as usize) < img.height {
                img.pixel_mut(px as usize, py as usize)[..3].copy_from_slice(&colour);
            }
        }
    }
}

const COLOURS: [[f32; 3]; 12] = [
    [0.1, 0.1, 0.1],
    [0.85, 0.2, 0.15],
    [0.15, 0.45, 0.8],
    [0.2, 0.65, 0.25],
    [0.6, 0.3, 0.7],
    [0.9, 0.55, 0.1],
    [0.3, 0.7, 0.75],
    [0.55, 0.45, 0.3],
    [0.9, 0.4, 0.7],
    [0.5, 0.5, 0.5],
    [0.6, 0.6, 0.1],
    [0.1, 0.3, 0.4],
];

/// The dashed lines where a training stage starts, and their labels.
const STAGE_COLOUR: [f32; 3] = [0.35, 0.35, 0.8];

/// Plots the loss terms of `log.jsonl` (moving average over 2% of the steps, log scale) to a
/// PNG with axes, tick labels, a legend, and a dashed line and the stage's name where each
/// training stage starts (the loss terms change there: the face's join at the joint stage).
pub fn loss_curve(log: &Path, out: &Path) -> Result<(), AvatarError> {
    let text = std::fs::read_to_string(log).map_err(|e| AvatarError::file(log, e))?;
    let mut series: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    let mut stages: Vec<(f64, String)> = Vec::new();
    for line in text.lines() {
        let Ok(v) = serde_json::from_str::<serde_json::Value>(line) else {
            continue;
        };
        let step = v["step"].as_f64().unwrap_or(0.0);
        if let Some(stage) = v["stage"].as_str()
            && stages.last().is_none_or(|(_, s)| s != stage)
        {
            stages.push((step, stage.to_string()));
        }
        let mut entries = vec![("total".to_string(), v["total"].as_f64())];
        if let Some(terms) = v["losses"].as_array() {
            for t in terms {
                entries.push((t[0].as_str().unwrap_or("?").to_string(), t[1].as_f64()));
            }
        }
        for (name, value) in entries {
            let Some(value) = value.filter(|x| *x > 0.0 && x.is_finite()) else {
                continue;
            };
            match series.iter_mut().find(|s| s.0 == name) {
                Some(s) => s.1.push((step, value)),
                None => series.push((name, vec![(step, value)])),
            }
        }
    }
    let (w, h) = (900usize, 520usize);
    let (left, right, top, bottom) = (90.0f32, 220.0f32, 20.0f32, 50.0f32);
    let mut img = Image::filled(w, h, 3, 1.0);
    let points: Vec<&(f64, f64)> = series.iter().flat_map(|s| &s.1).collect();
    if points.is_empty() {
        draw_text(&mut img, "no losses logged yet", 300, 250, COLOURS[0]);
        return Ok(f3g_io::write_png(out, &img)?);
    }
    let max_step = points.iter().map(|p| p.0).fold(1.0f64, f64::max);
    let lo = points
        .iter()
        .map(|p| p.1.log10())
        .fold(f64::MAX, f64::min)
        .floor();
    let hi = points
        .iter()
        .map(|p| p.1.log10())
        .fold(f64::MIN, f64::max)
        .ceil()
        .max(lo + 1.0);
    let px = |s: f64| left + (s / max_step) as f32 * (w as f32 - left - right);
    let py = |v: f64| top + ((hi - v.log10()) / (hi - lo)) as f32 * (h as f32 - top - bottom);
    let grey = [0.8, 0.8, 0.8];
    for d in (lo as i32)..=(hi as i32) {
        let y = py(10f64.powi(d));
        draw_line(&mut img, (left, y), (w as f32 - right, y), grey);
        draw_text(&mut img, &format!("1e{d}"), 20, y as usize - 7, COLOURS[0]);
    }
    for k in 0..=4 {
        let s = max_step * k as f64 / 4.0;
        let x = px(s);
        draw_line(&mut img, (x, top), (x, h as f32 - bottom), grey);
        draw_text(
            &mut img,
            &format!("{}", s.round()),
            x as usize,
            h - 40,
            COLOURS[0],
        );
    }
    draw_text(&mut img, "step", w / 2 - 100, h - 18, COLOURS[0]);
    for (k, (step, name)) in stages.iter().enumerate() {
        let x = px(*step);
        let mut y = top;
        while y < h as f32 - bottom {
            draw_line(
                &mut img,
                (x, y),
                (x, (y + 6.0).min(h as f32 - bottom)),
                STAGE_COLOUR,
            );
            y += 12.0;
        }
        // Labels alternate between two rows, so that short stages do not overwrite each other.
        draw_text(
            &mut img,
            name,
            x as usize + 4,
            top as usize + 4 + 16 * (k % 2),
            STAGE_COLOUR,
        );
    }
    let window = (max_step / 50.0).max(1.0) as usize;
    for (k, (name, pts)) in series.iter().enumerate() {
        let colour = COLOURS[k % COLOURS.len()];
        let smooth: Vec<(f64, f64)> = (0..pts.len())
            .map(|i| {
                let a = i.saturating_sub(window / 2);
                let b = (i + window / 2 + 1).min(pts.len());
                let mean = pts[a..b].iter().map(|p| p.1.ln()).sum::<f64>() / (b - a) as f64;
                (pts[i].0, mean.exp())
            })
            .collect();
        for pair in smooth.windows(2) {
            draw_line(
                &mut img,
                (px(pair[0].0), py(pair[0].1)),
                (px(pair[1].0), py(pair[1].1)),
                colour,
            );
        }
        let ly = top as usize + 10 + 22 * k;
        draw_line(
            &mut img,
            (w as f32 - right + 12.0, ly as f32 + 7.0),
            (w as f32 - right + 36.0, ly as f32 + 7.0),
            colour,
        );
        draw_text(&mut img, name, w - right as usize + 44, ly, colour);
    }
    Ok(f3g_io::write_png(out, &img)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_error_map_is_black_where_images_agree() {
        let a = Image::filled(4, 3, 3, 0.5);
        let mut b = a.clone();
        b.data[0] = 1.0;
        let e = error_map(&a, &b);
        assert_eq!(&e.data[3..6], &[0.0, 0.0, 0.0]);
        assert!(e.data[0] > 0.0);
        let row = comparison_row(&a, &b);
        assert_eq!((row.width, row.height), (3 * 4 + 2 * GAP, 3));
    }

    #[test]
    fn loss_curves_are_drawn_from_the_log() {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("log.jsonl");
        let lines: String = (0..50)
            .map(|s| {
                format!(
                    "{{\"step\":{s},\"stage\":\"{}\",\"total\":{},\"losses\":[[\"l1\",{}]]}}\n",
                    if s < 25 { "body" } else { "joint" },
                    1.0 / (s + 1) as f64,
                    0.5 / (s + 1) as f64
                )
            })
            .collect();
        std::fs::write(&log, lines).unwrap();
        let png = dir.path().join("loss.png");
        loss_curve(&log, &png).unwrap();
        let img = f3g_io::read_rgb(&png).unwrap();
        // Some pixels carry the colour of the second series (l1, red).
        assert!(
            img.data
                .chunks_exact(3)
                .any(|p| p[0] > 0.8 && p[1] < 0.3 && p[2] < 0.3)
        );
        // The joint stage's dashed line stands where step 25 is: halfway along the axis.
        let x = (90.0 + 25.0 / 49.0 * (900.0 - 90.0 - 220.0)) as usize;
        let stage_pixels = (100..400)
            .filter(|&y| {
                let p = img.pixel(x, y);
                (p[0] - STAGE_COLOUR[0]).abs() < 0.02 && (p[2] - STAGE_COLOUR[2]).abs() < 0.02
            })
            .count();
        assert!(stage_pixels > 50, "{stage_pixels} pixels of the stage line");
    }
}
