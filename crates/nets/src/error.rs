//! Errors of network construction, weight files and metrics.

use std::path::PathBuf;

/// What went wrong building, loading or evaluating a network.
#[derive(Debug, thiserror::Error)]
pub enum NetsError {
    /// A configuration value is out of range; names the field.
    #[error("network configuration: `{field}`: {reason}")]
    Config { field: &'static str, reason: String },
    /// A weight file could not be used; names the file (and tensor when known).
    #[error("{file}: {reason}")]
    Weights { file: PathBuf, reason: String },
    /// Inputs of the wrong shape or with non-finite values.
    #[error("{0}")]
    Input(String),
}

impl NetsError {
    pub(crate) fn config(field: &'static str, reason: impl ToString) -> Self {
        Self::Config {
            field,
            reason: reason.to_string(),
        }
    }

    pub(crate) fn weights(file: &std::path::Path, reason: impl ToString) -> Self {
        Self::Weights {
            file: file.to_path_buf(),
            reason: reason.to_string(),
        }
    }
}
