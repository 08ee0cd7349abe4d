//! The run folder: configuration, provenance, checkpoints, pose PCA, logs.
//!
//! ```text
//! RUN/config.json            the TrainConfig
//! RUN/run.json               capture folder, body model, training split
//! RUN/pca.npz                pose PCA of the training posed maps
//! RUN/log.jsonl              one line per step (losses, learning rate, time)
//! RUN/checkpoints/latest     name of the newest complete checkpoint
//! RUN/checkpoints/step-NNNNNNNNN/{nets,optim_body,optim_face,disc,optim_disc}.bpk,
//!                             face_base.npz, state.json
//! ```
//!
//! Every file is written atomically, and a checkpoint only becomes `latest` once all its files
//! are written, so a run killed at any moment resumes from a complete checkpoint. The two
//! newest checkpoints are kept.

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::optim::{ModuleOptimizer, OptimizerRecord};
use burn::tensor::Bytes;
use serde::{Deserialize, Serialize};

use crate::AvatarError;
use crate::config::TrainConfig;
use crate::model::FaceBase;
use f3g_template::PosePca;

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

fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, AvatarError> {
    let text = std::fs::read_to_string(path).map_err(|e| AvatarError::file(path, e))?;
    serde_json::from_str(&text).map_err(|e| AvatarError::file(path, format!("malformed: {e}")))
}

fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), AvatarError> {
    let text = serde_json::to_string_pretty(value).expect("serialisable");
    Ok(f3g_io::write_atomic(path, text.as_bytes())?)
}

/// An opened run folder.
pub struct Run {
    pub dir: PathBuf,
}

impl Run {
    pub fn new(dir: &Path) -> Self {
        Self {
            dir: dir.to_path_buf(),
        }
    }

    pub fn config(&self) -> Result<TrainConfig, AvatarError> {
        let path = self.dir.join("config.json");
        if !path.exists() {
            return Err(AvatarError::file(
                &self.dir,
                "not a training run (no config.json): train one with `f3g train`",
            ));
        }
        TrainConfig::from_file(&path)
    }

    pub fn write_config(&self, config: &TrainConfig) -> Result<(), AvatarError> {
        std::fs::create_dir_all(&self.dir).map_err(|e| AvatarError::file(&self.dir, e))?;
        write_json(&self.dir.join("config.json"), config)
    }

    pub fn info(&self) -> Result<RunInfo, AvatarError> {
        read_json(&self.dir.join("run.json"))
    }

    pub fn write_info(&self, info: &RunInfo) -> Result<(), AvatarError> {
        write_json(&self.dir.join("run.json"), info)
    }

    /// The training frames' body parameters (an f3g sequence).
    pub fn poses_path(&self) -> PathBuf {
        self.dir.join("poses.npz")
    }

    pub fn log_path(&self) -> PathBuf {
        self.dir.join("log.jsonl")
    }

    fn checkpoints(&self) -> PathBuf {
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

    /// Removes the temporary files that writes interrupted by a kill left in the run folder
    /// and its checkpoints (training's own folders; evaluation may be writing elsewhere in the
    /// run at the same time). Returns how many.
    pub fn remove_temporaries(&self) -> Result<usize, AvatarError> {
        let mut dirs = vec![self.dir.clone(), self.checkpoints()];
        if let Ok(entries) = std::fs::read_dir(self.checkpoints()) {
            dirs.extend(entries.flatten().map(|e| e.path()).filter(|p| p.is_dir()));
        }
        let mut removed = 0;
        for dir in dirs {
            let Ok(entries) = std::fs::read_dir(&dir) else {
                continue;
            };
            for path in entries.flatten().map(|e| e.path()) {
                let temporary = path
                    .file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with(f3g_io::TEMPORARY_PREFIX));
                if temporary && path.is_file() {
                    std::fs::remove_file(&path).map_err(|e| AvatarError::file(&path, e))?;
                    removed += 1;
                }
            }
        }
        Ok(removed)
    }

    /// Writes a checkpoint and makes it `latest`; removes all but the two newest.
    #[allow(clippy::too_many_arguments)]
    pub fn write_checkpoint<N: Module, D: Module>(
        &self,
        state: &TrainState,
        nets: &N,
        optim_body: &ModuleOptimizer,
        optim_face: Option<&ModuleOptimizer>,
        disc: Option<(&D, &ModuleOptimizer)>,
        face_base: Option<&FaceBase>,
    ) -> Result<PathBuf, AvatarError> {
        let name = format!("step-{:09}", state.step);
        let dir = self.checkpoints().join(&name);
        std::fs::create_dir_all(&dir).map_err(|e| AvatarError::file(&dir, e))?;
        f3g_nets::checkpoint::save(nets.clone(), &dir.join("nets.bpk"))?;
        save_optim(optim_body, &dir.join("optim_body.bpk"))?;
        if let Some(o) = optim_face {
            save_optim(o, &dir.join("optim_face.bpk"))?;
        }
        if let Some((d, o)) = disc {
            f3g_nets::checkpoint::save(d.clone(), &dir.join("disc.bpk"))?;
            save_optim(o, &dir.join("optim_disc.bpk"))?;
        }
        if let Some(b) = face_base {
            save_face_base(&dir.join("face_base.npz"), b)?;
        }
        write_json(&dir.join("state.json"), state)?;
        f3g_io::write_atomic(&self.checkpoints().join("latest"), name.as_bytes())?;
        let mut all: Vec<PathBuf> = std::fs::read_dir(self.checkpoints())
            .map_err(|e| AvatarError::file(&self.checkpoints(), e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.is_dir()
                    && p.file_name()
                        .and_then(|n| n.to_str())
                        .is_some_and(|n| n.starts_with("step-"))
            })
            .collect();
        all.sort();
        for old in all.iter().rev().skip(2) {
            std::fs::remove_dir_all(old).map_err(|e| AvatarError::file(old, e))?;
        }
        Ok(dir)
    }

    pub fn write_pca(&self, pca: &PosePca) -> Result<(), AvatarError> {
        use f3g_io::NpyValues::F32;
        let (k, d) = (pca.stddev.len(), pca.mean.len());
        f3g_io::write_npz(
            &self.dir.join("pca.npz"),
            &[
                ("mean", &[d], F32(&pca.mean)),
                ("components", &[k, d], F32(&pca.components)),
                ("stddev", &[k], F32(&pca.stddev)),
                ("sigma", &[1], F32(&[pca.sigma])),
            ],
        )?;
        Ok(())
    }

    pub fn pca(&self) -> Result<PosePca, AvatarError> {
        let path = self.dir.join("pca.npz");
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

fn save_optim(optim: &ModuleOptimizer, path: &Path) -> Result<(), AvatarError> {
    let bytes = optim
        .to_record()
        .into_bytes()
        .map_err(|e| AvatarError::file(path, e))?;
    let bytes =
        f3g_nets::checkpoint::canonical_burnpack(bytes).map_err(|e| AvatarError::file(path, e))?;
    Ok(f3g_io::write_atomic(path, &bytes)?)
}

/// Loads an optimiser's state saved with a checkpoint for the module it steps (checked
/// against it first: Burn's loader trusts the file).
pub fn load_optim<M: Module>(
    optim: ModuleOptimizer,
    path: &Path,
    module: &M,
) -> Result<ModuleOptimizer, AvatarError> {
    let bytes = Bytes::from_bytes_vec(std::fs::read(path).map_err(|e| AvatarError::file(path, e))?);
    f3g_nets::checkpoint::check_optimiser_state(&bytes, module)
        .map_err(|e| AvatarError::file(path, format!("not this run's optimiser state: {e}")))?;
    let record = OptimizerRecord::from_bytes(bytes)
        .map_err(|e| AvatarError::file(path, format!("not an optimiser state: {e}")))?;
    Ok(optim.load_record(record))
}

pub fn save_face_base(path: &Path, b: &FaceBase) -> Result<(), AvatarError> {
    use f3g_io::NpyValues::F32;
    let n = b.len();
    f3g_io::write_npz(
        path,
        &[
            ("positions", &[n, 3], F32(&b.positions)),
            ("colours", &[n, 3], F32(&b.colours)),
            ("opacity_logits", &[n], F32(&b.opacity_logits)),
            ("log_scales", &[n, 3], F32(&b.log_scales)),
            ("quats", &[n, 4], F32(&b.quats)),
        ],
    )?;
    Ok(())
}

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
