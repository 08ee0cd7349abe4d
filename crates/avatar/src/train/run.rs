//! The run folder, writing side (the layout and the readers: `crate::infer`'s `run.rs`):
//! the configuration, the provenance with the folder's format version, checkpoints with their
//! optimiser states, the pose PCA; and training's reading of its own configuration.
//!
//! Every file is written atomically, and a checkpoint only becomes `latest` once all its files
//! are written, so a run killed at any moment resumes from a complete checkpoint. The two
//! newest checkpoints are kept.

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::optim::OptimizerRecord;
use burn::tensor::Bytes;
use serde::Serialize;

use super::config::TrainConfig;
use crate::AvatarError;
use crate::infer::run::{RUN_FORMAT, Run, RunInfo, TrainState};
use crate::model::FaceBase;
use f3g_nets::adam::ModuleAdam;
use f3g_template::PosePca;

fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), AvatarError> {
    let text = serde_json::to_string_pretty(value).expect("serialisable");
    Ok(f3g_io::write_atomic(path, text.as_bytes())?)
}

impl Run {
    /// The run's training configuration (`config.json`, checked).
    pub fn config(&self) -> Result<TrainConfig, AvatarError> {
        let path = self.config_path();
        if !path.exists() {
            return Err(self.not_a_run());
        }
        TrainConfig::from_file(&path)
    }

    pub fn write_config(&self, config: &TrainConfig) -> Result<(), AvatarError> {
        std::fs::create_dir_all(self.dir()).map_err(|e| AvatarError::file(self.dir(), e))?;
        write_json(&self.config_path(), config)
    }

    /// Writes `run.json`: `info` and this version's [`RUN_FORMAT`].
    pub fn write_info(&self, info: &RunInfo) -> Result<(), AvatarError> {
        let mut value = serde_json::to_value(info).expect("serialisable");
        if let Some(fields) = value.as_object_mut() {
            fields.insert("format".into(), RUN_FORMAT.into());
        }
        write_json(&self.info_path(), &value)
    }

    /// Removes the temporary files that writes interrupted by a kill left in the run folder
    /// and its checkpoints (training's own folders; evaluation may be writing elsewhere in the
    /// run at the same time). Returns how many.
    pub fn remove_temporaries(&self) -> Result<usize, AvatarError> {
        let mut dirs = vec![self.dir().to_path_buf(), self.checkpoints()];
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
        optim_body: &ModuleAdam,
        optim_face: Option<&ModuleAdam>,
        disc: Option<(&D, &ModuleAdam)>,
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
            &self.pca_path(),
            &[
                ("mean", &[d], F32(&pca.mean)),
                ("components", &[k, d], F32(&pca.components)),
                ("stddev", &[k], F32(&pca.stddev)),
                ("sigma", &[1], F32(&[pca.sigma])),
            ],
        )?;
        Ok(())
    }
}

fn save_optim(optim: &ModuleAdam, path: &Path) -> Result<(), AvatarError> {
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
    optim: ModuleAdam,
    path: &Path,
    module: &M,
) -> Result<ModuleAdam, AvatarError> {
    let bytes = Bytes::from_bytes_vec(std::fs::read(path).map_err(|e| AvatarError::file(path, e))?);
    f3g_nets::checkpoint::check_optimiser_state(&bytes, module)
        .map_err(|e| AvatarError::file(path, format!("not this run's optimiser state: {e}")))?;
    let record = OptimizerRecord::from_bytes(bytes)
        .map_err(|e| AvatarError::file(path, format!("not an optimiser state: {e}")))?;
    Ok(optim.load_record(record))
}

fn save_face_base(path: &Path, b: &FaceBase) -> Result<(), AvatarError> {
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
