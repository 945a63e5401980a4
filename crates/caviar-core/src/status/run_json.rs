//! run.json's contents ([`RunStatus`]), its state and error, the real-time factor,
//! and reading it (with what a reader concludes about a run left `running`), closing
//! it for a dead process, and writing it.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::process::{process_start, same_process_alive};
use super::progress::read_progress;
use crate::config::LoadedConfig;
use crate::engine::{EndReason, Engine, EngineError};
use crate::pacing::PacingReport;

/// The run's status file in its run directory.
pub const STATUS_FILE: &str = "run.json";
/// `rtf_definition` of run.json.
pub const RTF_DEFINITION: &str = "T_p/T_v: wall-clock seconds per virtual second (the paper's RTF)";

/// The paper's real-time factor, T_p / T_v; `None` before any virtual time passed.
pub fn rtf(wall_s: f64, virtual_s: f64) -> Option<f64> {
    (virtual_s > 0.0).then(|| wall_s / virtual_s)
}

/// The paper's real-time factor RTF = T_p / T_v (wall-clock time over virtual time),
/// three decimals; "-" before any virtual time has passed.
pub fn rtf_text(wall_s: f64, virtual_s: f64) -> String {
    match rtf(wall_s, virtual_s) {
        Some(r) => format!("{r:.3}"),
        None => "-".into(),
    }
}

/// `status` in run.json.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RunState {
    #[default]
    Running,
    Completed,
    Failed,
    Interrupted,
    /// Never written: what a reader concludes when run.json says `running` but the
    /// process that wrote it is gone (killed, or exited without closing the run).
    Abandoned,
}

impl RunState {
    pub fn as_str(self) -> &'static str {
        match self {
            RunState::Running => "running",
            RunState::Completed => "completed",
            RunState::Failed => "failed",
            RunState::Interrupted => "interrupted",
            RunState::Abandoned => "abandoned",
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
    /// Steps that finished, every module's part done: for a run that failed at step k
    /// (0-based), whatever the fault (an exception, an exit, a crash, a deadline, in
    /// process or over a transport), k. What the failed step's earlier stages published
    /// is recorded all the same.
    pub steps_done: u64,
    pub virtual_time_s: f64,
    /// Wall-clock seconds in steps, recording included.
    pub wall_s: f64,
    /// Of `wall_s`, the seconds spent writing the recording.
    pub record_s: f64,
    /// The paper's real-time factor RTF = T_p / T_v: wall-clock seconds per virtual
    /// second (< 1: faster than real time; `None` before any virtual time passed). Runs
    /// recorded before `rtf_definition` existed stored the inverse here.
    pub rtf: Option<f64>,
    /// What `rtf` means, spelled out in the file ("T_p/T_v …").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rtf_definition: Option<String>,
    pub modules: Vec<String>,
    pub error: Option<RunErrorInfo>,
    /// Why the episode ended (absent while running, and in runs recorded before it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub end_reason: Option<EndReason>,
    /// The module that ended it by publishing `caviar.episode.end`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ended_by: Option<String>,
    /// The process running the episode (while `running`: whether it still lives tells a
    /// reader if the run was abandoned).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pid: Option<u32>,
    /// When that process started (clock ticks after boot, Linux's /proc/PID/stat): a pid
    /// is reused by a later process, the pair is not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pid_start: Option<u64>,
    /// Where the run was last seen (from `progress.json`, updated as modules start):
    /// the step in progress, its stage and the modules that had started it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_step: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_stage: Option<String>,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub last_modules: Vec<String>,
    /// What the transport records when the run ends, as top-level fields: NATS runs
    /// add `security`, the frames refused for failing authentication or being out of
    /// sequence (`{rejected, rejected_by_core, rejected_by_workers, warnings}`,
    /// docs/nats-protocol.md).
    #[serde(flatten)]
    pub transport: serde_json::Map<String, serde_json::Value>,
    /// How a paced run (`episode.pace`) kept to the wall clock: late and dropped steps,
    /// the worst and the 99th-percentile lateness.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pacing: Option<PacingReport>,
    /// The step the last checkpoint resumes at (`checkpoint.json`; `run --resume`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub checkpoint_step: Option<u64>,
    /// The steps this run was resumed at, in order (empty: never resumed).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub resumed_at: Vec<u64>,
    /// Seconds of `wall_s` spent writing checkpoints (this process's part of the run).
    #[serde(default)]
    pub checkpoint_s: f64,
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
            rtf: rtf(engine.wall_s(), virtual_s),
            rtf_definition: Some(RTF_DEFINITION.into()),
            modules: engine.module_names().map(String::from).collect(),
            error: error.map(RunErrorInfo::of),
            end_reason,
            ended_by: end_reason
                .filter(|r| *r == EndReason::Module)
                .and_then(|_| engine.ended_by().map(String::from)),
            pid: (status == RunState::Running).then(std::process::id),
            pid_start: (status == RunState::Running)
                .then(|| process_start(std::process::id()))
                .flatten(),
            last_step: None,
            last_stage: None,
            last_modules: Vec::new(),
            transport: serde_json::Map::new(),
            pacing: engine.pacing(),
            checkpoint_step: engine.checkpoint_step(),
            resumed_at: engine.resumed_at().to_vec(),
            checkpoint_s: engine.checkpoint_s(),
        }
    }

    /// Reads `RUN_DIR/run.json` and tells the truth about a run that was left running:
    /// the step reached and the modules in it from `progress.json`, and `abandoned`
    /// when the process that ran it is gone.
    pub fn read_live(run_dir: &Path) -> Result<Self, String> {
        let mut s = Self::read(run_dir)?;
        if s.status != RunState::Running {
            return Ok(s);
        }
        if let Some(p) = read_progress(run_dir) {
            s.steps_done = s.steps_done.max(p.steps_done);
            s.virtual_time_s = s.virtual_time_s.max(s.steps_done as f64 * s.ts);
            s.last_step = Some(p.step);
            s.last_stage = Some(p.stage);
            s.last_modules = p.modules;
        }
        if s.pid
            .is_some_and(|pid| !same_process_alive(pid, s.pid_start))
        {
            s.status = RunState::Abandoned;
        }
        Ok(s)
    }

    /// One line on an abandoned run: how far it got and what it was doing.
    pub fn abandoned_text(&self) -> Option<String> {
        if self.status != RunState::Abandoned {
            return None;
        }
        let after = match self.steps_done {
            0 => "before its first step ended".to_string(),
            n => format!("after step {} ({n} steps done)", n - 1),
        };
        let doing = match (&self.last_step, self.last_modules.as_slice()) {
            (Some(k), [one]) => format!("; the last module started was '{one}', at step {k}"),
            (Some(k), []) => format!("; no module was running (step {k}, between stages)"),
            (Some(k), many) => format!("; modules {many:?} had started step {k}"),
            (None, _) => String::new(),
        };
        Some(format!(
            "abandoned {after}: the process (pid {}) is gone without closing the run{doing}",
            self.pid.map_or("?".into(), |p| p.to_string())
        ))
    }

    /// Reads `RUN_DIR/run.json`.
    pub fn read(run_dir: &Path) -> Result<Self, String> {
        let path = run_dir.join(STATUS_FILE);
        let text = std::fs::read_to_string(&path)
            .map_err(|e| format!("{}: not a run directory ({e})", run_dir.display()))?;
        serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))
    }

    /// Closes the run.json that a dead process left `running` as `failed`, with
    /// `message` (the cause, told by whoever saw the process end: "the process was
    /// killed by SIGKILL") followed by where it was, from `progress.json`: the module
    /// started last and its step. Returns that place in words (", in module 'x' at
    /// step 3"), or `None` when the run is not `running` (it was closed: left as it is).
    pub fn close_failed(run_dir: &Path, message: &str) -> Result<Option<String>, String> {
        let mut status = Self::read(run_dir)?;
        if status.status != RunState::Running {
            return Ok(None);
        }
        let progress = read_progress(run_dir);
        let step = progress.as_ref().map(|p| p.step);
        let module = progress.as_ref().and_then(|p| p.modules.last().cloned());
        let place = match (&module, step) {
            (Some(m), Some(k)) => format!(", in module '{m}' at step {k}"),
            (None, Some(k)) => format!(", between stages of step {k}"),
            _ => ", before its first step".to_string(),
        };
        let mut text: String = message.to_string();
        if let Some(first) = text.get(..1) {
            text = first.to_uppercase() + &text[1..];
        }
        text.push_str(&place);
        status.steps_done = status
            .steps_done
            .max(progress.as_ref().map_or(0, |p| p.steps_done));
        status.virtual_time_s = status.steps_done as f64 * status.ts;
        status.status = RunState::Failed;
        status.end_reason = Some(EndReason::Error);
        status.error = Some(match module {
            Some(module) => RunErrorInfo::Module {
                module,
                phase: "step".into(),
                step,
                time: None,
                message: text,
                trace: None,
            },
            None => RunErrorInfo::Other { message: text },
        });
        status.last_step = step;
        status.last_stage = progress.as_ref().map(|p| p.stage.clone());
        status.last_modules = progress.map(|p| p.modules).unwrap_or_default();
        status.pid = None;
        status.pid_start = None;
        status.write(run_dir)?;
        Ok(Some(place))
    }

    /// Writes `RUN_DIR/run.json` atomically (a temporary file renamed over it): a reader
    /// or a crash never sees half of it.
    pub fn write(&self, run_dir: &Path) -> Result<(), String> {
        let path = run_dir.join(STATUS_FILE);
        let tmp = run_dir.join(".run.json.tmp");
        let text = serde_json::to_string_pretty(self).expect("json");
        std::fs::write(&tmp, text + "\n")
            .and_then(|()| std::fs::rename(&tmp, &path))
            .map_err(|e| format!("{}: {e}", path.display()))
    }
}
