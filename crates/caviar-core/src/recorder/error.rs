//! The recorder's error: a file that could not be written or read, or a table that
//! is not what a run records (naming the file).

use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Parquet {
        path: PathBuf,
        source: parquet::errors::ParquetError,
    },
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
}

pub(super) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> RecordError + '_ {
    move |source| RecordError::Io {
        path: path.to_path_buf(),
        source,
    }
}

pub(super) fn pq_err(
    path: &Path,
) -> impl FnOnce(parquet::errors::ParquetError) -> RecordError + '_ {
    move |source| RecordError::Parquet {
        path: path.to_path_buf(),
        source,
    }
}
