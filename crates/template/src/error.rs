//! Errors of template building and position maps.

use std::path::{Path, PathBuf};

/// What went wrong, naming the file or setting to fix.
#[derive(Debug, thiserror::Error)]
pub enum TemplateError {
    #[error("{file}: {reason}")]
    File { file: PathBuf, reason: String },
    #[error(transparent)]
    Rig(#[from] f3g_rig::RigError),
    #[error("{0}")]
    Invalid(String),
}

impl TemplateError {
    pub fn file(file: &Path, reason: impl ToString) -> Self {
        Self::File {
            file: file.to_path_buf(),
            reason: reason.to_string(),
        }
    }
}

impl From<f3g_io::IoError> for TemplateError {
    fn from(e: f3g_io::IoError) -> Self {
        Self::File {
            file: e.path,
            reason: e.reason,
        }
    }
}
