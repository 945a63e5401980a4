//! Where a recorded table's files lie in a run directory: `TABLE.parquet` once
//! compacted, else chunks and the parts no chunk covers, in recording order.

use std::fs;
use std::path::{Path, PathBuf};

use super::error::{io_err, RecordError};

/// The parts a file of a table's folder holds: `part-N` holds N, `chunk-A-B` A to B.
pub(super) fn parts_of(path: &Path) -> Option<(usize, usize)> {
    let stem = path.file_name()?.to_str()?.strip_suffix(".parquet")?;
    if let Some(n) = stem.strip_prefix("part-") {
        let n = n.parse().ok()?;
        return Some((n, n));
    }
    let (a, b) = stem.strip_prefix("chunk-")?.split_once('-')?;
    Some((a.parse().ok()?, b.parse().ok()?)).filter(|(a, b)| a <= b)
}

/// A table's files in recording order: chunks and the parts no chunk covers.
pub(super) fn part_files(dir: &Path) -> Result<Vec<PathBuf>, RecordError> {
    let mut files: Vec<((usize, usize), PathBuf)> = fs::read_dir(dir)
        .map_err(io_err(dir))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter_map(|p| parts_of(&p).map(|range| (range, p)))
        .collect();
    // Chunks (wider ranges) first at the same start; a part inside a chunk is skipped.
    files.sort_by_key(|((a, b), _)| (*a, std::cmp::Reverse(*b)));
    let mut out = Vec::with_capacity(files.len());
    let mut covered_to: Option<usize> = None;
    for ((a, b), path) in files {
        if covered_to.is_some_and(|end| a <= end) {
            continue;
        }
        covered_to = Some(b);
        out.push(path);
    }
    Ok(out)
}

/// The file a table is compacted into at the end of a run (`messages.parquet`).
pub fn compacted_file(table: &str) -> String {
    format!("{table}.parquet")
}

/// The Parquet files that hold a recorded table (`messages` or `timings`), in order:
/// `TABLE.parquet` once the run was compacted, else `TABLE/part-NNNNNN.parquet` (a
/// run in progress or one that was killed). The one place that knows the layout: the
/// readers of the Rust side and of the Python side (`caviar._core.table_files`) use it.
pub fn table_files(run_dir: &Path, table: &str) -> Result<Vec<PathBuf>, RecordError> {
    let single = run_dir.join(compacted_file(table));
    if single.exists() {
        return Ok(vec![single]);
    }
    let parts_dir = run_dir.join(table);
    if !parts_dir.is_dir() {
        return Err(RecordError::Format {
            path: run_dir.to_path_buf(),
            message: format!("not a run directory: neither {table}.parquet nor {table}/ is there"),
        });
    }
    part_files(&parts_dir)
}
