//! `f3g data check` and `f3g data show`: validate a capture and draw a contact sheet.
//!
//! Both set the posed body model against every camera's mask: its silhouette (the model's
//! mesh rasterised with the camera's calibration) and the mask compared at [`FIT_WIDTH`]
//! pixels across. Two numbers per camera: the IoU, and the share of the body's silhouette
//! that lies inside the mask. Clothes can make a mask much larger than the body (a long skirt:
//! a low IoU with a right calibration), but the body drawn where the mask is empty means a
//! wrong calibration, a flipped axis or a bad body fit, so the second number is the one a
//! camera is flagged by ([`MIN_BODY_IN_MASK`]).

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::DataError;
use crate::crop::head_box;
use crate::dataset::Dataset;
use crate::imgops::{draw_box, paste, resize, resized_camera};
use f3g_camera::Camera;
use f3g_io::Image;
use f3g_io::text::draw_text;
use f3g_template::raster::{Projection, rasterize};

/// Below this share of the posed body's silhouette inside a camera's mask the camera is
/// flagged (module docs). A right calibration and fit reach 0.97–1.0 on the synthetic
/// capture; the loss is the blur of a mask's edge at [`FIT_WIDTH`].
pub const MIN_BODY_IN_MASK: f32 = 0.9;
/// Width in pixels at which a silhouette and a mask are compared.
pub const FIT_WIDTH: usize = 256;

/// How well the posed body model lies on one camera's masks, over the frames checked.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct CameraFit {
    pub camera: String,
    /// Frames compared.
    pub frames: usize,
    /// Mean over those frames of the IoU of the body's silhouette and the mask.
    pub iou: f32,
    /// Mean share of the body's silhouette inside the mask.
    pub body_in_mask: f32,
    /// `body_in_mask` < [`MIN_BODY_IN_MASK`].
    pub flagged: bool,
}

impl CameraFit {
    /// The fit of `camera` from sums over `frames` frames of (IoU, body in mask).
    pub(crate) fn new(camera: &str, (iou, inside, frames): (f32, f32, usize)) -> Self {
        let body_in_mask = inside / frames as f32;
        Self {
            camera: camera.to_string(),
            frames,
            iou: iou / frames as f32,
            body_in_mask,
            flagged: body_in_mask < MIN_BODY_IN_MASK,
        }
    }
}

/// The silhouette (`width × height`, row-major) of a posed mesh seen by `camera`, drawn at
/// that size (the camera scaled to it).
pub fn silhouette(
    vertices: &[Vec3],
    triangles: &[[u32; 3]],
    camera: &Camera,
    width: usize,
    height: usize,
) -> Vec<bool> {
    let camera = resized_camera(camera, width, height);
    let f = rasterize(
        vertices,
        triangles,
        &Projection::Pinhole(camera),
        width,
        height,
        false,
    );
    (0..width * height).map(|p| f.covered(p)).collect()
}

/// `(IoU, share of the body inside the mask)` of a silhouette and a mask of the same size (a
/// mask value above 0.5 is inside). An empty silhouette is wholly outside (0, 0).
pub fn agreement(body: &[bool], mask: &Image) -> (f32, f32) {
    let (mut both, mut either, mut drawn) = (0usize, 0usize, 0usize);
    for (&b, m) in body.iter().zip(mask.data.chunks_exact(mask.channels)) {
        let m = m[0] > 0.5;
        both += (b && m) as usize;
        either += (b || m) as usize;
        drawn += b as usize;
    }
    if drawn == 0 {
        return (0.0, 0.0);
    }
    (both as f32 / either as f32, both as f32 / drawn as f32)
}

/// The posed mesh's silhouette seen by `camera` at `width × height`, and its [`agreement`]
/// with `mask` resized to that size.
fn against_mask(
    (vertices, triangles): &PosedMesh,
    camera: &Camera,
    mask: &Image,
    width: usize,
    height: usize,
) -> (Vec<bool>, (f32, f32)) {
    let body = silhouette(vertices, triangles, camera, width, height);
    let scores = agreement(&body, &resize(mask, width, height));
    (body, scores)
}

/// The size a camera's images are compared at: [`FIT_WIDTH`] wide (or narrower images as they
/// are), the height in proportion.
pub(crate) fn fit_size(camera: &Camera, width: usize) -> (usize, usize) {
    let w = width.min(camera.width as usize).max(1);
    let h = ((camera.height as f32 * w as f32 / camera.width as f32).round() as usize).max(1);
    (w, h)
}

/// A posed body model's mesh: vertices and the model's triangles.
type PosedMesh<'a> = (Vec<Vec3>, &'a [[u32; 3]]);

/// The body model's posed mesh for `frame`, or `None` without a body model.
fn posed_body(ds: &Dataset, frame: usize) -> Result<Option<PosedMesh<'_>>, DataError> {
    let Ok(rig) = ds.rig() else {
        return Ok(None);
    };
    let posed = rig.pose(&ds.params[frame])?;
    Ok(Some((posed.vertices, &rig.mesh.triangles)))
}

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
    /// The posed body model against each camera's masks, on the decoded frames (empty without
    /// a body model).
    pub silhouettes: Vec<CameraFit>,
}

/// Checks every camera, the header of every image and mask (size against `imgSize`), decodes
/// every `decode_every`-th frame (1 = all), reports the body parameters, and sets the posed
/// body model against the decoded masks (a warning names each flagged camera).
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
    // Every frame posed once: its errors reported after the images' (as they always were), its
    // mesh kept for the frames that are decoded.
    let every = decode_every.max(1);
    let mut pose_errors = Vec::new();
    let bodies: Vec<Option<PosedMesh>> = (0..ds.frames())
        .map(|f| match posed_body(ds, f) {
            Ok(mesh) => mesh.filter(|_| f % every == 0),
            Err(e) => {
                pose_errors.push(format!("frame {f}: {e}"));
                None
            }
        })
        .collect();
    let mut sums = vec![(0.0f32, 0.0f32, 0usize); ds.cameras.len()];
    for (c, cam) in ds.cameras.iter().enumerate() {
        let expected = (cam.camera.width as usize, cam.camera.height as usize);
        for (f, body) in bodies.iter().enumerate() {
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
            if f % every == 0 {
                match ds.image(c, f).and_then(|_| ds.mask(c, f)) {
                    Ok(mask) => {
                        r.images_decoded += 1;
                        if let Some(mesh) = body {
                            let (w, h) = fit_size(&cam.camera, FIT_WIDTH);
                            let (_, (iou, inside)) = against_mask(mesh, &cam.camera, &mask, w, h);
                            sums[c].0 += iou;
                            sums[c].1 += inside;
                            sums[c].2 += 1;
                        }
                    }
                    Err(e) => r.errors.push(e.to_string()),
                }
            }
        }
    }
    r.errors.extend(pose_errors);
    r.silhouettes = ds
        .cameras
        .iter()
        .zip(sums)
        .filter(|(_, s)| s.2 > 0)
        .map(|(cam, s)| CameraFit::new(&cam.name, s))
        .collect();
    for fit in r.silhouettes.iter().filter(|f| f.flagged) {
        r.warnings.push(format!(
            "camera `{}`: only {:.0} % of the posed body lies inside its masks (IoU {:.2}; \
             expected at least {:.0} %): a wrong calibration, a flipped axis or body parameters \
             that do not fit this capture?",
            fit.camera,
            100.0 * fit.body_in_mask,
            fit.iou,
            100.0 * MIN_BODY_IN_MASK
        ));
    }
    r
}

/// Colour of the body's outline on a contact sheet.
const OUTLINE: [f32; 3] = [0.1, 0.9, 1.0];

/// All cameras of `frame` side by side (each scaled to `thumb` pixels wide), with the face
/// boxes drawn in red. With `overlay`, the posed body model's outline is drawn over each
/// image, its IoU with the mask and the share of it inside the mask printed on the tile (red
/// when the camera is flagged), and returned per camera.
pub fn contact_sheet(
    ds: &Dataset,
    frame: usize,
    thumb: usize,
    padding: f32,
    overlay: bool,
) -> Result<(Image, Vec<CameraFit>), DataError> {
    if frame >= ds.frames() {
        return Err(DataError::Invalid(format!(
            "frame {frame} requested, the capture has {}",
            ds.frames()
        )));
    }
    // The frame's posed body (without a body model: no face boxes, and no overlay).
    let mesh = posed_body(ds, frame)?;
    let head = match (&mesh, ds.rig()) {
        (Some((vertices, _)), Ok(rig)) => Some(
            rig.head_vertices()?
                .iter()
                .map(|&v| vertices[v])
                .collect::<Vec<_>>(),
        ),
        _ => None,
    };
    if overlay && mesh.is_none() {
        return Err(DataError::Invalid(
            "the overlay needs the body model: pass --model".into(),
        ));
    }
    let body = mesh.filter(|_| overlay);
    let columns = (ds.cameras.len() as f32).sqrt().ceil() as usize;
    let rows = ds.cameras.len().div_ceil(columns);
    let aspect = ds
        .cameras
        .iter()
        .map(|c| c.camera.height as f32 / c.camera.width as f32)
        .fold(0.0, f32::max);
    let (tw, th) = (thumb, (thumb as f32 * aspect).ceil() as usize);
    let mut sheet = Image::filled(columns * tw, rows * th, 3, 0.1);
    let mut fits = Vec::new();
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
        if let Some(mesh) = &body {
            let (w, h) = (small.width, small.height);
            let (drawn, (iou, inside)) = against_mask(mesh, &cam.camera, &ds.mask(c, frame)?, w, h);
            draw_outline(&mut small, &drawn);
            let fit = CameraFit::new(&cam.name, (iou, inside, 1));
            let colour = if fit.flagged {
                [1.0, 0.15, 0.15]
            } else {
                [1.0, 1.0, 1.0]
            };
            draw_text(&mut small, &cam.name, 4, 4, colour);
            draw_text(&mut small, &format!("iou {iou:.2}"), 4, 22, colour);
            draw_text(&mut small, &format!("in {inside:.2}"), 4, 40, colour);
            fits.push(fit);
        }
        paste(&mut sheet, &small, (c % columns) * tw, (c / columns) * th);
    }
    Ok((sheet, fits))
}

/// Colours the pixels of `img` on the edge of `drawn` (drawn, with a 4-neighbour not).
fn draw_outline(img: &mut Image, drawn: &[bool]) {
    let (w, h) = (img.width, img.height);
    let at = |x: usize, y: usize| drawn[y * w + x];
    for y in 0..h {
        for x in 0..w {
            let edge = at(x, y)
                && (x == 0 || y == 0 || x + 1 == w || y + 1 == h || {
                    !(at(x - 1, y) && at(x + 1, y) && at(x, y - 1) && at(x, y + 1))
                });
            if edge {
                img.pixel_mut(x, y)[..3].copy_from_slice(&OUTLINE);
            }
        }
    }
}
