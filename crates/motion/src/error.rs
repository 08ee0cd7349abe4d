//! Errors that name the file (and where it helps, the field, line, frame or joint) to fix.

use std::path::{Path, PathBuf};

/// Everything that can go wrong reading, retargeting or writing a motion.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MotionError {
    /// A file is missing, unreadable or not a motion of a known format.
    #[error("{file}: {reason}")]
    File { file: PathBuf, reason: String },
    /// A field of a file is missing, has the wrong shape or holds bad values.
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
    /// The motion cannot drive the body model.
    #[error("{file}: {reason}")]
    Retarget { file: PathBuf, reason: String },
    /// The body model refused parameters.
    #[error(transparent)]
    Rig(#[from] f3g_rig::RigError),
}

impl MotionError {
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

    pub fn line(file: &Path, line: usize, reason: impl ToString) -> Self {
        Self::Line {
            file: file.to_path_buf(),
            line,
            reason: reason.to_string(),
        }
    }

    pub fn retarget(file: &Path, reason: impl ToString) -> Self {
        Self::Retarget {
            file: file.to_path_buf(),
            reason: reason.to_string(),
        }
    }
}

impl From<f3g_io::IoError> for MotionError {
    fn from(e: f3g_io::IoError) -> Self {
        Self::File {
            file: e.path,
            reason: e.reason,
        }
    }
}
