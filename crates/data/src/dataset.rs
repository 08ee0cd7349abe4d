//! Capture folders in the two layouts the readers accept.
//!
//! AvatarReX (and `f3g synth`): `calibration_full.json`, images `<camera>/%08d.jpg`, masks
//! `<camera>/mask/pha/%08d.jpg`. THuman4.0: `calibration.json`, `images/<camera>/%08d.jpg`,
//! `masks/<camera>/%08d.jpg`. Both: `missing_img_files.txt` (optional; one image path per line,
//! relative to the folder) lists frames to skip, and body parameters are either
//! `smpl_params.npz` (SMPL-X; the model file must be supplied) or `body_params.npz` (an f3g
//! parameter sequence naming its model, e.g. the built-in human of the synthetic capture).

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use crate::DataError;
use crate::calibration::{CaptureCamera, read_calibration};
use f3g_io::Image;
use f3g_rig::{ModelSpec, Rig, RigParams};

/// Folder layout of a capture.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    AvatarRex,
    Thuman4,
}

/// Parameter file of the synthetic capture (and of converted captures).
pub const BODY_PARAMS: &str = "body_params.npz";
/// SMPL-X parameter file of AvatarReX and THuman4.0.
pub const SMPL_PARAMS: &str = "smpl_params.npz";

/// An opened capture.
pub struct Dataset {
    pub root: PathBuf,
    pub layout: Layout,
    pub cameras: Vec<CaptureCamera>,
    /// The body model the parameters belong to, when it could be loaded.
    pub rig: Option<Rig>,
    /// How the model was named (`builtin`, `smplx:...`).
    pub model: String,
    /// Body parameters per frame.
    pub params: Vec<RigParams>,
    /// `(camera, frame)` pairs without an image.
    pub missing: HashSet<(usize, usize)>,
    /// Warnings gathered while opening (skipped or missing files).
    pub warnings: Vec<String>,
}

impl Dataset {
    /// Opens a capture. `model` is needed for `smpl_params.npz` (SMPL-X); a `body_params.npz`
    /// names its own model.
    pub fn open(root: &Path, model: Option<&ModelSpec>) -> Result<Self, DataError> {
        let (layout, cameras) = locate(root)?;
        let (rig, model_text, params) = read_body(root, model)?;
        let mut ds = Self {
            root: root.to_path_buf(),
            layout,
            cameras,
            rig,
            model: model_text,
            params,
            missing: HashSet::new(),
            warnings: Vec::new(),
        };
        ds.find_missing()?;
        Ok(ds)
    }

    /// Opens a capture for fitting its body parameters with `rig`, whatever parameter file it
    /// has or lacks: the frames are those with an image in some camera, counted from 0 until
    /// the first frame no camera has, and each frame's parameters are the rest pose until
    /// fitted.
    pub fn open_unfitted(root: &Path, rig: Rig, model: String) -> Result<Self, DataError> {
        let (layout, cameras) = locate(root)?;
        let mut ds = Self {
            root: root.to_path_buf(),
            layout,
            cameras,
            rig: None,
            model,
            params: Vec::new(),
            missing: HashSet::new(),
            warnings: Vec::new(),
        };
        let frames = (0usize..)
            .take_while(|&f| (0..ds.cameras.len()).any(|c| ds.image_path(c, f).exists()))
            .count();
        if frames == 0 {
            return Err(DataError::file(
                root,
                format!("no images: expected e.g. {}", ds.image_path(0, 0).display()),
            ));
        }
        ds.params = vec![rig.zero_params(); frames];
        ds.rig = Some(rig);
        ds.find_missing()?;
        Ok(ds)
    }

    /// Number of frames (from the body parameters).
    pub fn frames(&self) -> usize {
        self.params.len()
    }

    /// Image path of `(camera, frame)`.
    pub fn image_path(&self, camera: usize, frame: usize) -> PathBuf {
        let name = &self.cameras[camera].name;
        match self.layout {
            Layout::AvatarRex => self.root.join(name).join(format!("{frame:08}.jpg")),
            Layout::Thuman4 => self
                .root
                .join("images")
                .join(name)
                .join(format!("{frame:08}.jpg")),
        }
    }

    /// Mask path of `(camera, frame)`.
    pub fn mask_path(&self, camera: usize, frame: usize) -> PathBuf {
        let name = &self.cameras[camera].name;
        match self.layout {
            Layout::AvatarRex => self
                .root
                .join(name)
                .join("mask/pha")
                .join(format!("{frame:08}.jpg")),
            Layout::Thuman4 => self
                .root
                .join("masks")
                .join(name)
                .join(format!("{frame:08}.jpg")),
        }
    }

    /// Whether `(camera, frame)` has an image.
    pub fn has_image(&self, camera: usize, frame: usize) -> bool {
        !self.missing.contains(&(camera, frame))
    }

    /// Reads the image of `(camera, frame)`, checking its size against the calibration.
    pub fn image(&self, camera: usize, frame: usize) -> Result<Image, DataError> {
        let path = self.image_path(camera, frame);
        self.check_size(&path, camera)?;
        let img = f3g_io::read_rgb(&path)?;
        self.check_decoded(&path, camera, &img)?;
        Ok(img)
    }

    /// Reads the alpha mask of `(camera, frame)` in [0, 1], checking its size.
    pub fn mask(&self, camera: usize, frame: usize) -> Result<Image, DataError> {
        let path = self.mask_path(camera, frame);
        self.check_size(&path, camera)?;
        let img = f3g_io::read_gray(&path)?;
        self.check_decoded(&path, camera, &img)?;
        Ok(img)
    }

    /// Checks the size in the file's header before anything is decoded, so that a file
    /// claiming a huge size is an error, not an allocation of that size.
    fn check_size(&self, path: &Path, camera: usize) -> Result<(), DataError> {
        let (width, height) = f3g_io::image_size(path)?;
        self.size_matches(path, camera, width, height)
    }

    /// The decoded size (which a lying header could differ from).
    fn check_decoded(&self, path: &Path, camera: usize, img: &Image) -> Result<(), DataError> {
        self.size_matches(path, camera, img.width, img.height)
    }

    fn size_matches(
        &self,
        path: &Path,
        camera: usize,
        width: usize,
        height: usize,
    ) -> Result<(), DataError> {
        let cam = &self.cameras[camera].camera;
        if (width, height) != (cam.width as usize, cam.height as usize) {
            return Err(DataError::file(
                path,
                format!(
                    "is {width}×{height} but the calibration of `{}` says imgSize [{}, {}]",
                    self.cameras[camera].name, cam.width, cam.height
                ),
            ));
        }
        Ok(())
    }

    /// The body model, or an error saying how to supply it.
    pub fn rig(&self) -> Result<&Rig, DataError> {
        self.rig.as_ref().ok_or_else(|| {
            DataError::file(&self.root.join(SMPL_PARAMS), "holds SMPL-X parameters: pass the model with --model smplx:SMPLX_NEUTRAL.npz (or convert them with `f3g rig fit`)")
        })
    }

    fn find_missing(&mut self) -> Result<(), DataError> {
        let listed = self.root.join("missing_img_files.txt");
        let mut listed_paths = HashSet::new();
        if listed.exists() {
            let text = std::fs::read_to_string(&listed).map_err(|e| DataError::file(&listed, e))?;
            for line in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
                listed_paths.insert(self.root.join(line));
            }
        }
        let mut absent = 0;
        for c in 0..self.cameras.len() {
            for f in 0..self.frames() {
                let path = self.image_path(c, f);
                if listed_paths.contains(&path) {
                    self.missing.insert((c, f));
                } else if !path.exists() {
                    self.missing.insert((c, f));
                    absent += 1;
                }
            }
        }
        if !listed_paths.is_empty() {
            self.warnings.push(format!(
                "{} images listed in missing_img_files.txt are skipped",
                listed_paths.len()
            ));
        }
        if absent > 0 {
            let example = self
                .missing
                .iter()
                .find(|(c, f)| !listed_paths.contains(&self.image_path(*c, *f)))
                .map(|(c, f)| self.image_path(*c, *f));
            self.warnings.push(format!(
                "{absent} images are absent and skipped (e.g. {})",
                example.map(|p| p.display().to_string()).unwrap_or_default()
            ));
        }
        Ok(())
    }
}

/// A capture's layout and cameras, from the calibration file found in `root`.
fn locate(root: &Path) -> Result<(Layout, Vec<CaptureCamera>), DataError> {
    let (layout, calibration) = if root.join("calibration_full.json").exists() {
        (Layout::AvatarRex, root.join("calibration_full.json"))
    } else if root.join("calibration.json").exists() {
        (Layout::Thuman4, root.join("calibration.json"))
    } else {
        return Err(DataError::file(
            root,
            "not a capture: expected calibration_full.json (AvatarReX layout) or calibration.json (THuman4.0 layout)",
        ));
    };
    Ok((layout, read_calibration(&calibration)?))
}

type Body = (Option<Rig>, String, Vec<RigParams>);

fn read_body(root: &Path, model: Option<&ModelSpec>) -> Result<Body, DataError> {
    let body = root.join(BODY_PARAMS);
    let smpl = root.join(SMPL_PARAMS);
    if body.exists() {
        let mut npz = f3g_io::Npz::open(&body)?;
        let (_, bytes) = npz.i64("model")?;
        let text = String::from_utf8(bytes.into_iter().map(|b| b as u8).collect())
            .map_err(|e| DataError::field(&body, "model", e))?;
        let spec: ModelSpec = match model {
            Some(m) => m.clone(),
            None => text
                .parse()
                .map_err(|e: String| DataError::field(&body, "model", e))?,
        };
        let rig = spec.load()?;
        let params = f3g_rig::sequence::read(&body, &rig)?;
        Ok((Some(rig), text, params))
    } else if smpl.exists() {
        let p = f3g_rig::smplx::read_params(&smpl)?;
        match model {
            Some(spec) => {
                let rig = spec.load()?;
                let params = p.frames_for(&rig).map_err(|e| DataError::file(&smpl, e))?;
                Ok((Some(rig), spec.to_string(), params))
            }
            None => {
                // Without the model the frames can still be counted and checked.
                let zero = RigParams {
                    pose: vec![0.0; 168],
                    identity: p.betas.clone(),
                    expression: vec![],
                };
                let params = (0..p.frames)
                    .map(|i| RigParams {
                        pose: p.pose(i),
                        ..zero.clone()
                    })
                    .collect();
                Ok((None, "smplx".into(), params))
            }
        }
    } else {
        Err(DataError::file(
            root,
            format!("no body parameters: expected {BODY_PARAMS} or {SMPL_PARAMS}"),
        ))
    }
}
