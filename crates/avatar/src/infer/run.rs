//! The run folder, as inference (and a resumed run) reads it; training writes it
//! (`crate::train`'s `run.rs`).
//!
//! ```text
//! RUN/config.json            the training configuration (inference reads its model keys)
//! RUN/run.json               the folder's format version, capture folder, body model, split
//! RUN/body_model.npz, RUN/template.npz, RUN/setup.npz
//!                            the stored setup (crate::model's setup_file.rs)
//! RUN/poses.npz              the training frames' body parameters
//! RUN/pca.npz                pose PCA of the training posed maps
//! RUN/log.jsonl              one line per step (losses, learning rate, time)
//! RUN/checkpoints/latest     name of the newest complete checkpoint
//! RUN/checkpoints/step-NNNNNNNNN/{nets,optim_body,optim_face,disc,optim_disc}.bpk,
//!                             face_base.npz, state.json
//! ```
//!
//! A run folder holds everything inference needs, so it never needs the body model's files or
//! the capture. `run.json`'s `format` says which layout a folder has ([`RUN_FORMAT`]); a
//! folder of another format (runs made before the version, which may lack the stored setup or
//! the training poses) is refused with an error that says to retrain, rather than rebuilt
//! from files that may be gone.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::AvatarError;
use crate::model::FaceBase;
use f3g_template::PosePca;

/// The layout of run folders this version writes and reads: `run.json`'s `format`. Runs
/// without the key were made before it existed; format 1's networks held one style layer per
/// modulated convolution, format 2's one per network (`f3g_nets::DualStyleUNet::styles`).
pub const RUN_FORMAT: u64 = 2;

/// Where a run came from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunInfo {
    /// The capture folder.
    pub data: PathBuf,
    /// The body model, as the capture names it.
    pub model: String,
    /// The subject's shape parameters the template was built with.
    pub identity: Vec<f32>,
    pub train_cameras: Vec<usize>,
    pub train_frames: Vec<usize>,
}

/// Progress saved with a checkpoint.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainState {
    /// The next step to run.
    pub step: u64,
    /// Seconds spent training so far.
    pub seconds: f64,
    /// Discriminator steps so far (drives lazy R1).
    pub disc_steps: u64,
    /// The device that wrote the checkpoint (Burn's name for it; empty in checkpoints written
    /// before it was recorded). Resuming and evaluating may use another.
    #[serde(default)]
    pub device: String,
    /// Data-parallel replicas (devices) of the run that wrote the checkpoint: step `s` drew
    /// samples `s·replicas …`; absent in older checkpoints, which had one.
    #[serde(default = "one")]
    pub replicas: u64,
}

fn one() -> u64 {
    1
}

pub(crate) fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, AvatarError> {
    let text = std::fs::read_to_string(path).map_err(|e| AvatarError::file(path, e))?;
    serde_json::from_str(&text).map_err(|e| AvatarError::file(path, format!("malformed: {e}")))
}

/// A run folder.
pub struct Run {
    dir: PathBuf,
}

impl Run {
    pub fn new(dir: &Path) -> Self {
        Self {
            dir: dir.to_path_buf(),
        }
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub(crate) fn config_path(&self) -> PathBuf {
        self.dir.join("config.json")
    }

    pub(crate) fn info_path(&self) -> PathBuf {
        self.dir.join("run.json")
    }

    /// The error of a folder that holds no run (or of a path that names nothing: a mistyped
    /// avatar file reaches here too).
    pub(crate) fn not_a_run(&self) -> AvatarError {
        if !self.dir.exists() {
            return AvatarError::file(&self.dir, "no such file or folder");
        }
        AvatarError::file(
            &self.dir,
            "not a training run (no config.json): train one with `f3g train`",
        )
    }

    /// Where the run came from; an error naming the folder when it is not of this version's
    /// format ([`RUN_FORMAT`]).
    pub fn info(&self) -> Result<RunInfo, AvatarError> {
        let path = self.info_path();
        let mut value: Value = read_json(&path)?;
        let format = value
            .as_object_mut()
            .and_then(|o| o.remove("format"))
            .map_or(Some(0), |f| f.as_u64());
        match format {
            Some(RUN_FORMAT) => {}
            Some(older) if older < RUN_FORMAT => {
                return Err(AvatarError::file(
                    &self.dir,
                    format!(
                        "is a run folder of format {older}, made by an older f3g; this version \
                         reads format {RUN_FORMAT} (its networks' parameters are laid out \
                         differently): retrain with this version of f3g (`f3g train`)"
                    ),
                ));
            }
            Some(newer) => {
                return Err(AvatarError::file(
                    &self.dir,
                    format!(
                        "is a run folder of format {newer}, made by a newer f3g; this version \
                         reads format {RUN_FORMAT}: use the f3g that trained it"
                    ),
                ));
            }
            None => return Err(AvatarError::file(&path, "`format` is not a whole number")),
        }
        serde_json::from_value(value)
            .map_err(|e| AvatarError::file(&path, format!("malformed: {e}")))
    }

    /// The training frames' body parameters (an f3g sequence).
    pub fn poses_path(&self) -> PathBuf {
        self.dir.join("poses.npz")
    }

    pub fn log_path(&self) -> PathBuf {
        self.dir.join("log.jsonl")
    }

    pub(crate) fn pca_path(&self) -> PathBuf {
        self.dir.join("pca.npz")
    }

    pub(crate) fn checkpoints(&self) -> PathBuf {
        self.dir.join("checkpoints")
    }

    /// The newest complete checkpoint.
    pub fn latest(&self) -> Result<Option<PathBuf>, AvatarError> {
        let pointer = self.checkpoints().join("latest");
        if !pointer.exists() {
            return Ok(None);
        }
        let name = std::fs::read_to_string(&pointer).map_err(|e| AvatarError::file(&pointer, e))?;
        let dir = self.checkpoints().join(name.trim());
        if !dir.join("state.json").exists() {
            return Err(AvatarError::file(
                &pointer,
                format!("names {} which is incomplete or missing", dir.display()),
            ));
        }
        Ok(Some(dir))
    }

    /// The pose PCA (`pca.npz`), its shapes and values checked.
    pub fn pca(&self) -> Result<PosePca, AvatarError> {
        let path = self.pca_path();
        let mut npz = f3g_io::Npz::open(&path)?;
        let (_, mean) = npz.f32("mean")?;
        let (shape, components) = npz.f32("components")?;
        let (_, stddev) = npz.f32("stddev")?;
        let (_, sigma) = npz.f32("sigma")?;
        if shape.len() != 2
            || shape[1] != mean.len()
            || shape[0] != stddev.len()
            || sigma.len() != 1
        {
            return Err(AvatarError::file(&path, "inconsistent array shapes"));
        }
        if !mean
            .iter()
            .chain(&components)
            .chain(&stddev)
            .chain(&sigma)
            .all(|v| v.is_finite())
        {
            return Err(AvatarError::file(&path, "holds NaN or infinite values"));
        }
        Ok(PosePca {
            mean,
            components,
            stddev,
            sigma: sigma[0],
        })
    }
}

/// Reads the training state of a checkpoint.
pub fn read_state(checkpoint: &Path) -> Result<TrainState, AvatarError> {
    let path = checkpoint.join("state.json");
    let state: TrainState = read_json(&path)?;
    if !(state.seconds.is_finite() && state.seconds >= 0.0) {
        return Err(AvatarError::file(
            &path,
            format!("`seconds` is {}, expected a duration ≥ 0", state.seconds),
        ));
    }
    Ok(state)
}

/// The canonical face model saved with a checkpoint, checked to hold `expected` Gaussians of
/// finite values.
pub fn load_face_base(path: &Path, expected: usize) -> Result<FaceBase, AvatarError> {
    let mut npz = f3g_io::Npz::open(path)?;
    let mut get = |name: &str, cols: usize| -> Result<Vec<f32>, AvatarError> {
        let (shape, v) = npz.f32(name)?;
        let want: Vec<usize> = if cols == 1 {
            vec![expected]
        } else {
            vec![expected, cols]
        };
        if shape != want || v.iter().any(|x| !x.is_finite()) {
            return Err(AvatarError::file(
                path,
                format!("`{name}` is {shape:?}, expected {want:?} of finite values"),
            ));
        }
        Ok(v)
    };
    Ok(FaceBase {
        positions: get("positions", 3)?,
        colours: get("colours", 3)?,
        opacity_logits: get("opacity_logits", 1)?,
        log_scales: get("log_scales", 3)?,
        quats: get("quats", 4)?,
    })
}

/// `n` items spread evenly over `items` (all of them when there are fewer): the training poses
/// that the pose PCA is fitted on and that baking samples.
pub(crate) fn evenly<T: Clone>(items: &[T], n: usize) -> Vec<T> {
    if items.len() <= n {
        return items.to_vec();
    }
    (0..n).map(|i| items[i * items.len() / n].clone()).collect()
}
