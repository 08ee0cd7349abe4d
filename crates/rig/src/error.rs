//! Errors that name the file and field a user has to fix.

use std::path::{Path, PathBuf};

/// Everything that can go wrong loading or evaluating a body model.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RigError {
    /// A file is missing, unreadable or not in the expected format.
    #[error("{file}: {reason}")]
    File { file: PathBuf, reason: String },
    /// A field inside a file is missing, has the wrong shape or holds bad values.
    #[error("{file}: `{field}`: {reason}")]
    Field {
        file: PathBuf,
        field: String,
        reason: String,
    },
    /// A line of a text format could not be parsed.
    #[error("{file}:{line}: {reason}")]
    Line {
        file: PathBuf,
        line: usize,
        reason: String,
    },
    /// Parameters passed to a model are invalid.
    #[error("parameters: {0}")]
    Params(String),
    /// A model is internally inconsistent.
    #[error("invalid model: {0}")]
    Model(String),
}

impl RigError {
    /// An error about `file`.
    pub fn file(file: &Path, reason: impl ToString) -> Self {
        Self::File {
            file: file.to_path_buf(),
            reason: reason.to_string(),
        }
    }

    /// An error about `field` of `file`.
    pub fn field(file: &Path, field: &str, reason: impl ToString) -> Self {
        Self::Field {
            file: file.to_path_buf(),
            field: field.to_string(),
            reason: reason.to_string(),
        }
    }
}
