//! `f3g data check` and `f3g data show`: validate a capture and draw a contact sheet.

use serde::Serialize;

use crate::DataError;
use crate::crop::head_box;
use crate::dataset::Dataset;
use crate::imgops::{draw_box, paste, resize};
use f3g_io::Image;

/// What a check found.
#[derive(Clone, Debug, Default, Serialize)]
pub struct CheckReport {
    pub layout: String,
    pub model: String,
    pub cameras: usize,
    pub frames: usize,
    pub image_size: Vec<(String, u32, u32)>,
    pub images_present: usize,
    pub images_missing: usize,
    pub images_decoded: usize,
    /// Problems, each naming a file.
    pub errors: Vec<String>,
    pub warnings: Vec<String>,
}

/// Checks every camera, the header of every image and mask (size against `imgSize`), decodes
/// every `decode_every`-th frame (1 = all), and reports the body parameters.
pub fn check(ds: &Dataset, decode_every: usize) -> CheckReport {
    let mut r = CheckReport {
        layout: format!("{:?}", ds.layout),
        model: ds.model.clone(),
        cameras: ds.cameras.len(),
        frames: ds.frames(),
        image_size: ds
            .cameras
            .iter()
            .map(|c| (c.name.clone(), c.camera.width, c.camera.height))
            .collect(),
        warnings: ds.warnings.clone(),
        ..Default::default()
    };
    if ds.rig.is_none() {
        r.warnings.push("SMPL-X parameters without the model file: pass --model smplx:PATH to check posing and face boxes".into());
    }
    for (c, cam) in ds.cameras.iter().enumerate() {
        let expected = (cam.camera.width as usize, cam.camera.height as usize);
        for f in 0..ds.frames() {
            if !ds.has_image(c, f) {
                r.images_missing += 1;
                continue;
            }
            r.images_present += 1;
            for path in [ds.image_path(c, f), ds.mask_path(c, f)] {
                match f3g_io::image_size(&path) {
                    Ok(size) if size != expected => r.errors.push(format!(
                        "{}: is {}×{} but imgSize of `{}` is {}×{}",
                        path.display(),
                        size.0,
                        size.1,
                        cam.name,
                        expected.0,
                        expected.1
                    )),
                    Ok(_) => {}
                    Err(e) => r.errors.push(e.to_string()),
                }
            }
            if f % decode_every.max(1) == 0 {
                match ds.image(c, f).and_then(|_| ds.mask(c, f)) {
                    Ok(_) => r.images_decoded += 1,
                    Err(e) => r.errors.push(e.to_string()),
                }
            }
        }
    }
    if let Ok(rig) = ds.rig() {
        for (f, p) in ds.params.iter().enumerate() {
            if let Err(e) = rig.pose(p) {
                r.errors.push(format!("frame {f}: {e}"));
            }
        }
    }
    r
}

/// All cameras of `frame` side by side (each scaled to `thumb` pixels wide), with the face
/// boxes drawn in red.
pub fn contact_sheet(
    ds: &Dataset,
    frame: usize,
    thumb: usize,
    padding: f32,
) -> Result<Image, DataError> {
    if frame >= ds.frames() {
        return Err(DataError::Invalid(format!(
            "frame {frame} requested, the capture has {}",
            ds.frames()
        )));
    }
    let head = match ds.rig() {
        Ok(rig) => {
            let posed = rig.pose(&ds.params[frame])?;
            Some(
                rig.head_vertices()?
                    .iter()
                    .map(|&v| posed.vertices[v])
                    .collect::<Vec<_>>(),
            )
        }
        Err(_) => None,
    };
    let columns = (ds.cameras.len() as f32).sqrt().ceil() as usize;
    let rows = ds.cameras.len().div_ceil(columns);
    let aspect = ds
        .cameras
        .iter()
        .map(|c| c.camera.height as f32 / c.camera.width as f32)
        .fold(0.0, f32::max);
    let (tw, th) = (thumb, (thumb as f32 * aspect).ceil() as usize);
    let mut sheet = Image::filled(columns * tw, rows * th, 3, 0.1);
    for (c, cam) in ds.cameras.iter().enumerate() {
        if !ds.has_image(c, frame) {
            continue;
        }
        let img = ds.image(c, frame)?;
        let scale = tw as f32 / img.width as f32;
        let mut small = resize(
            &img,
            tw,
            ((img.height as f32 * scale).round() as usize).max(1),
        );
        if let Some(points) = &head
            && let Some(b) = head_box(&cam.camera, points, padding)
        {
            draw_box(
                &mut small,
                b.x0 * scale,
                b.y0 * scale,
                (b.x0 + b.side) * scale,
                (b.y0 + b.side) * scale,
                [1.0, 0.1, 0.1],
            );
        }
        paste(&mut sheet, &small, (c % columns) * tw, (c / columns) * th);
    }
    Ok(sheet)
}
