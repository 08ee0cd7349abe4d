//! Errors of the avatar stage, naming the file, field or step to look at.

use std::path::{Path, PathBuf};

/// What went wrong building, training, evaluating or animating an avatar.
#[derive(Debug, thiserror::Error)]
pub enum AvatarError {
    /// A configuration value; names the key.
    #[error("configuration `{key}`: {reason}")]
    Config { key: String, reason: String },
    /// A file of a run (checkpoint, config, state); names it.
    #[error("{file}: {reason}")]
    File { file: PathBuf, reason: String },
    /// A loss became NaN or infinite.
    #[error(
        "step {step}: the loss `{name}` is {value}; training stopped, the last good checkpoint is kept{}",
        .checkpoint.as_ref().map(|c| format!(" ({})", c.display())).unwrap_or_default()
    )]
    NonFinite {
        step: u64,
        name: String,
        value: f32,
        checkpoint: Option<PathBuf>,
    },
    #[error(transparent)]
    Data(#[from] f3g_data::DataError),
    #[error(transparent)]
    Template(#[from] f3g_template::TemplateError),
    #[error(transparent)]
    Rig(#[from] f3g_rig::RigError),
    #[error(transparent)]
    Motion(#[from] f3g_motion::MotionError),
    #[error(transparent)]
    Nets(#[from] f3g_nets::NetsError),
    #[error(transparent)]
    Splat(#[from] f3g_splat::SplatError),
    #[error(transparent)]
    Memory(#[from] f3g_io::memory::NotEnoughMemory),
    #[error("{0}")]
    Invalid(String),
}

impl AvatarError {
    pub fn config(key: impl ToString, reason: impl ToString) -> Self {
        Self::Config {
            key: key.to_string(),
            reason: reason.to_string(),
        }
    }

    pub fn file(file: &Path, reason: impl ToString) -> Self {
        Self::File {
            file: file.to_path_buf(),
            reason: reason.to_string(),
        }
    }
}

impl From<f3g_io::IoError> for AvatarError {
    fn from(e: f3g_io::IoError) -> Self {
        Self::File {
            file: e.path,
            reason: e.reason,
        }
    }
}
