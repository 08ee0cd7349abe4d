//! The synthetic capture read back: calibration, silhouettes, splits, loader, bad inputs.

use std::path::Path;
use std::sync::Arc;

use f3g_data::imgops::resized_camera;
use f3g_data::loader::{LoaderOptions, make_view};
use f3g_data::synth::{SynthOptions, generate};
use f3g_data::{Dataset, Loader, Protocol, SplitKind, preset};
use f3g_template::{Projection, rasterize};

fn small_capture(dir: &Path) {
    let options = SynthOptions {
        cameras: 4,
        frames: 3,
        resolution: 192,
        ..Default::default()
    };
    generate(dir, &options, &|_| {}).unwrap();
}

#[test]
fn reprojected_meshes_land_on_the_rendered_silhouettes() {
    let dir = tempfile::tempdir().unwrap();
    small_capture(dir.path());
    let ds = Dataset::open(dir.path(), None).unwrap();
    assert_eq!((ds.cameras.len(), ds.frames()), (4, 3));
    assert_eq!(Protocol::of(&ds), Protocol::Synthetic);
    let rig = ds.rig().unwrap();
    for f in 0..ds.frames() {
        let posed = rig.pose(&ds.params[f]).unwrap();
        for c in 0..ds.cameras.len() {
            let cam = &ds.cameras[c].camera;
            let (w, h) = (cam.width as usize, cam.height as usize);
            let frags = rasterize(
                &posed.vertices,
                &rig.mesh.triangles,
                &Projection::Pinhole(cam.clone()),
                w,
                h,
                true,
            );
            let coverage = supersampled_coverage(&posed.vertices, &rig.mesh.triangles, cam, 4);
            let mask = ds.mask(c, f).unwrap();
            // Soft IoU between the re-projected mesh's pixel coverage and the stored mask.
            let (mut inter, mut union) = (0.0f64, 0.0f64);
            for (&a, &b) in coverage.iter().zip(&mask.data) {
                inter += a.min(b) as f64;
                union += a.max(b) as f64;
            }
            let iou = inter / union;
            assert!(iou >= 0.98, "camera {c} frame {f}: IoU {iou}");
            // Single-sample rasterisation must cover every confidently-inside pixel of the mask
            // and miss every confidently-outside one.
            let (mut inside, mut wrong) = (0usize, 0usize);
            for p in 0..w * h {
                let (covered, alpha) = (frags.covered(p), mask.data[p]);
                inside += (alpha > 0.5) as usize;
                wrong += ((alpha > 0.9 && !covered) || (alpha < 0.1 && covered)) as usize;
            }
            assert!(
                inside > w * h / 20,
                "camera {c} frame {f}: the person is in view"
            );
            assert!(
                wrong * 200 <= inside,
                "camera {c} frame {f}: {wrong} of {inside} pixels disagree"
            );
        }
    }
}

/// Fraction of each pixel covered by the mesh, from an `s × s` grid of samples per pixel.
fn supersampled_coverage(
    vertices: &[glam::Vec3],
    triangles: &[[u32; 3]],
    camera: &f3g_camera::Camera,
    s: usize,
) -> Vec<f32> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let fine = resized_camera(camera, w * s, h * s);
    let frags = rasterize(
        vertices,
        triangles,
        &Projection::Pinhole(fine),
        w * s,
        h * s,
        true,
    );
    let mut coverage = vec![0.0f32; w * h];
    for y in 0..h * s {
        for x in 0..w * s {
            if frags.covered(y * w * s + x) {
                coverage[(y / s) * w + x / s] += 1.0 / (s * s) as f32;
            }
        }
    }
    coverage
}

#[test]
fn the_loader_is_deterministic_resumable_and_composites_the_background() {
    let dir = tempfile::tempdir().unwrap();
    small_capture(dir.path());
    let ds = Arc::new(Dataset::open(dir.path(), None).unwrap());
    let split = preset(
        Protocol::Synthetic,
        SplitKind::Train,
        ds.cameras.len(),
        ds.frames(),
    )
    .unwrap();
    let options = LoaderOptions {
        face_size: 48,
        seed: 3,
        ..Default::default()
    };
    let mut a = Loader::new(ds.clone(), &split, options.clone(), 0).unwrap();
    let first: Vec<_> = (0..5).map(|_| a.next_sample().unwrap()).collect();
    let mut resumed = Loader::new(ds.clone(), &split, options, 3).unwrap();
    for expected in &first[3..] {
        let s = resumed.next_sample().unwrap();
        assert_eq!(
            (s.index, s.frame, s.camera, s.background),
            (
                expected.index,
                expected.frame,
                expected.camera,
                expected.background
            )
        );
        assert_eq!(s.body.image, expected.body.image);
    }
    for s in &first {
        assert!(split.frames.contains(&s.frame) && split.cameras.contains(&s.camera));
        let (w, h) = (s.body.image.width, s.body.image.height);
        assert_eq!((w, h), (72, 96));
        // Away from the person, the ground truth is the sample's background colour.
        for p in 0..w * h {
            if s.body.mask.data[p] == 0.0 && !s.body.band[p] {
                assert_eq!(&s.body.image.data[3 * p..3 * p + 3], &s.background);
            }
        }
        let face = s.face.as_ref().expect("the head is in view");
        assert_eq!((face.image.width, face.camera.width), (48, 48));
        assert!(
            face.mask.data.iter().filter(|&&a| a > 0.5).count() > 48 * 48 / 4,
            "the face crop shows the head"
        );
    }
}

#[test]
fn damaged_captures_are_reported_with_the_file() {
    let dir = tempfile::tempdir().unwrap();
    small_capture(dir.path());
    let root = dir.path();
    // A JPEG cut off inside its header.
    let path = root.join("cam01/00000001.jpg");
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..64]).unwrap();
    let ds = Dataset::open(root, None).unwrap();
    let e = ds
        .image(1, 1)
        .expect_err("a damaged image fails to load")
        .to_string();
    assert!(e.contains("cam01/00000001.jpg"), "{e}");
    let report = f3g_data::check::check(&ds, 1);
    assert!(
        report
            .errors
            .iter()
            .any(|e| e.contains("cam01/00000001.jpg")),
        "{:?}",
        report.errors
    );
    // A mask of the wrong size.
    let mask = root.join("cam02/mask/pha/00000000.jpg");
    f3g_io::write_jpeg(&mask, &f3g_io::Image::filled(10, 10, 1, 1.0), 90).unwrap();
    let e = ds
        .mask(2, 0)
        .expect_err("a wrongly sized mask fails to load")
        .to_string();
    assert!(
        e.contains("cam02/mask/pha/00000000.jpg") && e.contains("imgSize"),
        "{e}"
    );
    // A JPEG whose header claims 60000×60000 (10 GB decoded): refused from the header alone.
    let image = root.join("cam02/00000000.jpg");
    let mut bytes = std::fs::read(&image).unwrap();
    let sof = bytes
        .windows(2)
        .position(|w| w == [0xff, 0xc0])
        .expect("a baseline JPEG");
    bytes[sof + 5..sof + 9].copy_from_slice(&[0xea, 0x60, 0xea, 0x60]);
    std::fs::write(&image, &bytes).unwrap();
    assert_eq!(f3g_io::image_size(&image).unwrap(), (60000, 60000));
    let e = ds.image(2, 0).expect_err("a lying header").to_string();
    assert!(e.contains("is 60000×60000") && e.contains("imgSize"), "{e}");
    // Missing frames are skipped with a warning.
    std::fs::remove_file(root.join("cam03/00000002.jpg")).unwrap();
    let ds = Dataset::open(root, None).unwrap();
    assert!(!ds.has_image(3, 2));
    assert!(
        ds.warnings.iter().any(|w| w.contains("absent")),
        "{:?}",
        ds.warnings
    );
    std::fs::write(root.join("missing_img_files.txt"), "cam00/00000001.jpg\n").unwrap();
    let ds = Dataset::open(root, None).unwrap();
    assert!(!ds.has_image(0, 1) && ds.has_image(0, 0));
    // A calibration without K.
    let calib = root.join("calibration_full.json");
    let text = std::fs::read_to_string(&calib)
        .unwrap()
        .replacen("\"K\"", "\"k\"", 1);
    std::fs::write(&calib, text).unwrap();
    let e = Dataset::open(root, None).err().unwrap().to_string();
    assert!(
        e.contains("calibration_full.json") && e.contains("cam00.K"),
        "{e}"
    );
}

#[test]
fn bad_body_parameters_are_reported() {
    let dir = tempfile::tempdir().unwrap();
    small_capture(dir.path());
    let params = dir.path().join("body_params.npz");
    let rig = f3g_rig::builtin::load().unwrap().rig;
    let mut frames = f3g_rig::sequence::read(&params, &rig).unwrap();
    frames[1].pose[5] = f32::NAN;
    // The writer refuses nothing, so write the NaN and expect the reader to name it.
    f3g_rig::sequence::write(&params, &rig, &frames).unwrap();
    let e = Dataset::open(dir.path(), None).err().unwrap().to_string();
    assert!(
        e.contains("body_params.npz") && e.contains("`pose`") && e.contains("frame 1"),
        "{e}"
    );
    // A pose block one parameter short of the model's.
    let mut npz = f3g_io::Npz::open(&params).unwrap();
    let mut arrays = Vec::new();
    for name in npz.names() {
        let entry = if name.ends_with("names") || name == "model" {
            let (shape, v) = npz.i64(&name).unwrap();
            (name, shape, Err(v))
        } else {
            let (mut shape, mut v) = npz.f32(&name).unwrap();
            if name == "pose" {
                v = v
                    .chunks(shape[1])
                    .flat_map(|row| row[1..].to_vec())
                    .collect();
                shape[1] -= 1;
            }
            (name, shape, Ok(v))
        };
        arrays.push(entry);
    }
    let views: Vec<_> = arrays
        .iter()
        .map(|(name, shape, v)| {
            let values = match v {
                Ok(f) => f3g_io::NpyValues::F32(f),
                Err(i) => f3g_io::NpyValues::I64(i),
            };
            (name.as_str(), shape.as_slice(), values)
        })
        .collect();
    f3g_io::write_npz(&params, &views).unwrap();
    let e = Dataset::open(dir.path(), None).err().unwrap().to_string();
    assert!(
        e.contains("body_params.npz")
            && e.contains("`pose`")
            && e.contains("expected (frames, 212)"),
        "{e}"
    );
    std::fs::remove_file(&params).unwrap();
    let e = Dataset::open(dir.path(), None).err().unwrap().to_string();
    assert!(e.contains("no body parameters"), "{e}");
}

#[test]
fn views_have_consistent_cameras() {
    let dir = tempfile::tempdir().unwrap();
    small_capture(dir.path());
    let ds = Dataset::open(dir.path(), None).unwrap();
    let cache = std::sync::Mutex::new(f3g_data::loader::ImageCache::new(1 << 26));
    let options = LoaderOptions {
        body_scale: 0.5,
        face_size: 64,
        ..Default::default()
    };
    let (body, face, _) = make_view(&ds, &cache, 0, 0, &options, [1.0; 3]).unwrap();
    // The head joint projects inside the face crop, near its centre.
    let rig = ds.rig().unwrap();
    let posed = rig.pose(&ds.params[0]).unwrap();
    let head = posed.joints[rig.skeleton.index_of("head").unwrap()].translation;
    let face = face.unwrap();
    let (uv, _) = face
        .camera
        .project([head.x as f64, head.y as f64, head.z as f64])
        .unwrap();
    assert!(
        uv[0] > 8.0 && uv[0] < 56.0 && uv[1] > 8.0 && uv[1] < 56.0,
        "{uv:?}"
    );
    let (uv_body, _) = body
        .camera
        .project([head.x as f64, head.y as f64, head.z as f64])
        .unwrap();
    assert!(uv_body[0] > 0.0 && uv_body[0] < body.image.width as f64);
    // The cache keeps views prepared for a body scale and a padding: asked with others, it
    // prepares them afresh instead of returning the old ones.
    let full = LoaderOptions {
        body_scale: 1.0,
        face_padding: 2.0,
        ..options
    };
    let (body_full, face_wide, _) = make_view(&ds, &cache, 0, 0, &full, [1.0; 3]).unwrap();
    assert_eq!(body_full.image.width, 2 * body.image.width);
    let zoom = face_wide.unwrap().camera.k[0][0] / face.camera.k[0][0];
    assert!((zoom - 1.3 / 2.0).abs() < 1e-3, "{zoom}");
}

/// The posed body model set against every camera's masks: right calibrations agree, a flipped
/// axis and another camera's extrinsics are flagged, by `check` and on the overlay sheet.
#[test]
fn a_wrong_calibration_is_flagged_by_the_body_against_the_masks() {
    let dir = tempfile::tempdir().unwrap();
    small_capture(dir.path());
    let root = dir.path();
    let ds = Dataset::open(root, None).unwrap();
    let report = f3g_data::check::check(&ds, 1);
    assert_eq!(report.silhouettes.len(), 4);
    for fit in &report.silhouettes {
        assert_eq!(fit.frames, 3);
        assert!(
            fit.iou > 0.9 && fit.body_in_mask > 0.95 && !fit.flagged,
            "{fit:?}"
        );
    }
    assert!(report.warnings.is_empty(), "{:?}", report.warnings);

    // cam01 turned upside down about its optical axis (the first two rows of R and T negated:
    // a rotation still, unlike a single flipped axis, which reading refuses), cam02 given
    // cam03's extrinsics.
    let calib = root.join("calibration_full.json");
    let mut c: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&calib).unwrap()).unwrap();
    for k in 0..6 {
        let v = c["cam01"]["R"][k].as_f64().unwrap();
        c["cam01"]["R"][k] = (-v).into();
    }
    for k in 0..2 {
        let t = c["cam01"]["T"][k].as_f64().unwrap();
        c["cam01"]["T"][k] = (-t).into();
    }
    for key in ["R", "T"] {
        c["cam02"][key] = c["cam03"][key].clone();
    }
    std::fs::write(&calib, serde_json::to_string(&c).unwrap()).unwrap();
    let ds = Dataset::open(root, None).unwrap();
    let report = f3g_data::check::check(&ds, 1);
    let flagged: Vec<&str> = report
        .silhouettes
        .iter()
        .filter(|f| f.flagged)
        .map(|f| f.camera.as_str())
        .collect();
    assert_eq!(flagged, ["cam01", "cam02"], "{:?}", report.silhouettes);
    for camera in ["cam01", "cam02"] {
        assert!(
            report
                .warnings
                .iter()
                .any(|w| w.contains(&format!("`{camera}`"))),
            "{:?}",
            report.warnings
        );
    }
    // The overlay draws the outline and gives the same verdict for the frame it shows.
    let (sheet, fits) = f3g_data::check::contact_sheet(&ds, 1, 64, 1.3, true).unwrap();
    let flagged: Vec<&str> = fits
        .iter()
        .filter(|f| f.flagged)
        .map(|f| f.camera.as_str())
        .collect();
    assert_eq!(flagged, ["cam01", "cam02"], "{fits:?}");
    let outline = sheet
        .data
        .chunks_exact(3)
        .filter(|p| p == &[0.1, 0.9, 1.0])
        .count();
    assert!(outline > 100, "{outline} outline pixels");
    let (plain, fits) = f3g_data::check::contact_sheet(&ds, 1, 64, 1.3, false).unwrap();
    assert!(fits.is_empty());
    assert!(
        !plain.data.chunks_exact(3).any(|p| p == [0.1, 0.9, 1.0]),
        "no outline without the overlay"
    );
}
