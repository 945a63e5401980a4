//! `run.json`: what ran, how far it got and how it ended — one struct, written by the
//! run and read by `inspect` and the Python side (`caviar.runlog.RunStatus` mirrors it).
//!
//! Fields added after the first release carry `#[serde(default)]`: runs recorded
//! before them still read.
//!
//! Here: run.json itself (`run_json`), progress.json (`progress`), whether the process
//! that wrote them still lives (`process`), and the [`Monitor`] that keeps both true
//! while a run goes on and stops a stuck one (`monitor`).

mod monitor;
mod process;
mod progress;
mod run_json;

pub use monitor::{Deadlines, Monitor};
pub use progress::PROGRESS_FILE;
pub use run_json::{rtf, rtf_text, RunErrorInfo, RunState, RunStatus, RTF_DEFINITION, STATUS_FILE};

#[cfg(test)]
mod tests;
