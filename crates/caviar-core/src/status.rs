//! `run.json`: what ran, how far it got and how it ended — one struct, written by the
//! run and read by `inspect` and the Python side (`caviar.runlog.RunStatus` mirrors it).
//!
//! Fields added after the first release carry `#[serde(default)]`: runs recorded
//! before them still read.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::config::LoadedConfig;
use crate::engine::{EndReason, Engine, EngineError};

/// `status` in run.json.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RunState {
    #[default]
    Running,
    Completed,
    Failed,
    Interrupted,
}

impl RunState {
    pub fn as_str(self) -> &'static str {
        match self {
            RunState::Running => "running",
            RunState::Completed => "completed",
            RunState::Failed => "failed",
            RunState::Interrupted => "interrupted",
        }
    }
}

/// `error` in run.json: where a module failed, or only the message for other errors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum RunErrorInfo {
    Module {
        module: String,
        phase: String,
        step: Option<u64>,
        time: Option<f64>,
        message: String,
        trace: Option<String>,
    },
    Other {
        message: String,
    },
}

impl RunErrorInfo {
    pub fn message(&self) -> &str {
        match self {
            RunErrorInfo::Module { message, .. } | RunErrorInfo::Other { message } => message,
        }
    }

    fn of(e: &EngineError) -> Self {
        match e {
            EngineError::Module {
                module,
                phase,
                step,
                time,
                error,
            } => RunErrorInfo::Module {
                module: module.clone(),
                phase: phase.to_string(),
                step: *step,
                time: *time,
                message: error.message.clone(),
                trace: error.trace.clone(),
            },
            other => RunErrorInfo::Other {
                message: other.to_string(),
            },
        }
    }
}

/// The contents of run.json.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RunStatus {
    pub caviar_version: String,
    pub status: RunState,
    /// The configuration file as given on the command line.
    pub config_file: String,
    /// The `--set` overrides.
    pub overrides: Vec<String>,
    pub seed: u64,
    pub ts: f64,
    pub steps_planned: Option<u64>,
    pub steps_done: u64,
    pub virtual_time_s: f64,
    /// Wall-clock seconds in steps, recording included.
    pub wall_s: f64,
    /// Of `wall_s`, the seconds spent writing the recording.
    pub record_s: f64,
    /// Real-time factor: virtual seconds per wall second (`None` before the first step).
    pub rtf: Option<f64>,
    pub modules: Vec<String>,
    pub error: Option<RunErrorInfo>,
    /// Why the episode ended (absent while running, and in runs recorded before it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub end_reason: Option<EndReason>,
    /// The module that ended it by publishing `caviar.episode.end`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ended_by: Option<String>,
}

impl RunStatus {
    /// The status of `engine`'s run now.
    pub fn of(
        cfg: &LoadedConfig,
        engine: &Engine,
        status: RunState,
        error: Option<&EngineError>,
    ) -> Self {
        let virtual_s = engine.virtual_time_s();
        let end_reason = match status {
            RunState::Running => None,
            _ => engine.end_reason(),
        };
        RunStatus {
            caviar_version: env!("CARGO_PKG_VERSION").into(),
            status,
            config_file: cfg.file.clone(),
            overrides: cfg.overrides.clone(),
            seed: cfg.config.episode.seed,
            ts: engine.ts(),
            steps_planned: engine.planned_steps(),
            steps_done: engine.steps_done(),
            virtual_time_s: virtual_s,
            wall_s: engine.wall_s(),
            record_s: engine.record_s(),
            rtf: (engine.wall_s() > 0.0).then(|| virtual_s / engine.wall_s()),
            modules: engine.module_names().map(String::from).collect(),
            error: error.map(RunErrorInfo::of),
            end_reason,
            ended_by: end_reason
                .filter(|r| *r == EndReason::Module)
                .and_then(|_| engine.ended_by().map(String::from)),
        }
    }

    /// Reads `RUN_DIR/run.json`.
    pub fn read(run_dir: &Path) -> Result<Self, String> {
        let path = run_dir.join("run.json");
        let text = std::fs::read_to_string(&path)
            .map_err(|e| format!("{}: not a run directory ({e})", run_dir.display()))?;
        serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))
    }

    /// Writes `RUN_DIR/run.json`.
    pub fn write(&self, run_dir: &Path) -> Result<(), String> {
        let path = run_dir.join("run.json");
        let text = serde_json::to_string_pretty(self).expect("json");
        std::fs::write(&path, text + "\n").map_err(|e| format!("{}: {e}", path.display()))
    }
}

/// Writes `run.json` for `engine`'s run: what ran, how far it got and how it ended.
pub fn write_status(
    cfg: &LoadedConfig,
    engine: &Engine,
    status: RunState,
    error: Option<&EngineError>,
) -> Result<(), String> {
    RunStatus::of(cfg, engine, status, error).write(engine.run_dir())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_recorded_before_end_reason_still_read() {
        let old = r#"{"caviar_version": "0.1.0", "status": "failed", "config_file": "c.toml",
            "overrides": [], "seed": 7, "ts": 0.1, "steps_planned": 5, "steps_done": 2,
            "virtual_time_s": 0.2, "wall_s": 0.5, "rtf": 0.4, "modules": ["a"],
            "error": {"module": "a", "phase": "setup", "step": null, "time": null,
                      "message": "boom", "trace": null}}"#;
        let s: RunStatus = serde_json::from_str(old).unwrap();
        assert_eq!(
            (s.status, s.end_reason, s.record_s),
            (RunState::Failed, None, 0.0)
        );
        assert!(matches!(&s.error, Some(RunErrorInfo::Module { phase, .. }) if phase == "setup"));
        let other: RunStatus =
            serde_json::from_str(r#"{"error": {"message": "disk full"}}"#).unwrap();
        assert_eq!(other.error.unwrap().message(), "disk full");
    }

    #[test]
    fn end_reason_is_written_in_lowercase_with_the_module() {
        let s = RunStatus {
            status: RunState::Completed,
            end_reason: Some(EndReason::Module),
            ended_by: Some("mission".into()),
            ..RunStatus::default()
        };
        let v: serde_json::Value = serde_json::to_value(&s).unwrap();
        assert_eq!(v["end_reason"], "module");
        assert_eq!(v["ended_by"], "mission");
        assert_eq!(v["status"], "completed");
        assert!(v["error"].is_null() && v["rtf"].is_null() && v["steps_planned"].is_null());
    }
}
