//! Errors that name the file (and field) of a capture to fix.

use std::path::{Path, PathBuf};

/// What went wrong reading or generating a capture.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error("{file}: {reason}")]
    File { file: PathBuf, reason: String },
    #[error("{file}: `{field}`: {reason}")]
    Field {
        file: PathBuf,
        field: String,
        reason: String,
    },
    #[error(transparent)]
    Rig(#[from] f3g_rig::RigError),
    #[error(transparent)]
    Template(#[from] f3g_template::TemplateError),
    #[error("{0}")]
    Invalid(String),
}

impl DataError {
    pub fn file(file: &Path, reason: impl ToString) -> Self {
        Self::File {
            file: file.to_path_buf(),
            reason: reason.to_string(),
        }
    }

    pub fn field(file: &Path, field: &str, reason: impl ToString) -> Self {
        Self::Field {
            file: file.to_path_buf(),
            field: field.to_string(),
            reason: reason.to_string(),
        }
    }
}

impl From<f3g_io::IoError> for DataError {
    fn from(e: f3g_io::IoError) -> Self {
        Self::File {
            file: e.path,
            reason: e.reason,
        }
    }
}
