//! `progress.json`: where a run is (step, stage, modules started), rewritten in
//! place before every module's step so that a killed process leaves it behind.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;

use serde::{Deserialize, Serialize};

/// `progress.json`: rewritten in place (one `pwrite` of a fixed-size, space-padded JSON
/// object) before every module's step, so that a process killed in any way leaves
/// where it was. Cheap enough for every step; readers trim the padding.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(default)]
pub(super) struct ProgressRecord {
    pub(super) steps_done: u64,
    pub(super) step: u64,
    pub(super) stage: String,
    pub(super) modules: Vec<String>,
}

pub const PROGRESS_FILE: &str = "progress.json";
const PROGRESS_SIZE: usize = 1024;

pub(super) fn read_progress(run_dir: &Path) -> Option<ProgressRecord> {
    let text = std::fs::read_to_string(run_dir.join(PROGRESS_FILE)).ok()?;
    serde_json::from_str(text.trim()).ok()
}

pub(super) fn write_progress(f: &File, step: u64, stage: &str, modules: &[&str]) {
    let mut rec = ProgressRecord {
        steps_done: step,
        step,
        stage: stage.to_string(),
        modules: modules.iter().map(|m| m.to_string()).collect(),
    };
    let mut text = serde_json::to_string(&rec).expect("json");
    // The record and its newline fit in PROGRESS_SIZE bytes (a record of exactly that size
    // would lose its closing brace to the newline).
    while text.len() >= PROGRESS_SIZE && !rec.modules.is_empty() {
        rec.modules.pop();
        text = serde_json::to_string(&rec).expect("json");
    }
    if text.len() >= PROGRESS_SIZE {
        return;
    }
    let mut buf = text.into_bytes();
    buf.resize(PROGRESS_SIZE - 1, b' ');
    buf.push(b'\n');
    let _ = f.write_at(&buf, 0);
}
