//! `run.json`: what ran, how far it got and how it ended — one struct, written by the
//! run and read by `inspect` and the Python side (`caviar.runlog.RunStatus` mirrors it).
//!
//! Fields added after the first release carry `#[serde(default)]`: runs recorded
//! before them still read.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use crate::config::LoadedConfig;
use crate::engine::{EndReason, Engine, EngineError, Phase, StartHook};
use crate::module::StepInfo;
use crate::pacing::PacingReport;

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
        let path = run_dir.join("run.json");
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
        let path = run_dir.join("run.json");
        let tmp = run_dir.join(".run.json.tmp");
        let text = serde_json::to_string_pretty(self).expect("json");
        std::fs::write(&tmp, text + "\n")
            .and_then(|()| std::fs::rename(&tmp, &path))
            .map_err(|e| format!("{}: {e}", path.display()))
    }
}

/// Whether the process `pid` that started at `start` (when known) still runs: a live
/// process under that pid that started at another time is a later one (the pid reused).
/// A zombie (ended, not yet reaped by its parent) is not alive.
fn same_process_alive(pid: u32, start: Option<u64>) -> bool {
    process_alive(pid)
        && proc_stat_field(pid, 3).as_deref() != Some("Z")
        && match (start, process_start(pid)) {
            (Some(then), Some(now)) => then == now,
            _ => true,
        }
}

/// When process `pid` started, in clock ticks after boot (field 22 of /proc/PID/stat;
/// `None` where there is no /proc).
fn process_start(pid: u32) -> Option<u64> {
    proc_stat_field(pid, 22)?.parse().ok()
}

/// Field `n` (1-based, as proc(5) numbers them, from 3 on) of /proc/PID/stat.
fn proc_stat_field(pid: u32, n: usize) -> Option<String> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Field 2, the command, is in parentheses and may hold spaces: fields 3.. follow the last ')'.
    let rest = &stat[stat.rfind(')')? + 1..];
    rest.split_whitespace().nth(n - 3).map(String::from)
}

/// Whether process `pid` exists (signal 0: permission denied still means it does).
fn process_alive(pid: u32) -> bool {
    // SAFETY: kill with signal 0 only checks.
    let r = unsafe { libc::kill(pid as libc::pid_t, 0) };
    r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

/// `progress.json`: rewritten in place (one `pwrite` of a fixed-size, space-padded JSON
/// object) before every module's step, so that a process killed in any way leaves
/// where it was. Cheap enough for every step; readers trim the padding.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(default)]
struct ProgressRecord {
    steps_done: u64,
    step: u64,
    stage: String,
    modules: Vec<String>,
}

const PROGRESS_FILE: &str = "progress.json";
const PROGRESS_SIZE: usize = 1024;

fn read_progress(run_dir: &Path) -> Option<ProgressRecord> {
    let text = std::fs::read_to_string(run_dir.join(PROGRESS_FILE)).ok()?;
    serde_json::from_str(text.trim()).ok()
}

/// What the watchdog sees: the module step (or setup, or teardown) in progress and
/// since when.
struct Current {
    phase: Phase,
    step: u64,
    modules: Vec<String>,
    since: Instant,
    /// The last run.json written, to write it again as `failed`.
    status: Option<RunStatus>,
}

/// How long an in-process module may take before the watchdog stops the run.
#[derive(Debug, Clone, Copy)]
pub struct Deadlines {
    /// One step (`episode.step_timeout`).
    pub step: Duration,
    /// One module's setup, or its teardown (`episode.setup_timeout`).
    pub setup: Duration,
}

impl Deadlines {
    fn of(&self, phase: Phase) -> (Duration, &'static str) {
        match phase {
            Phase::Step => (self.step, "episode.step_timeout"),
            Phase::Setup | Phase::Teardown => (self.setup, "episode.setup_timeout"),
        }
    }
}

/// Keeps run.json and progress.json true while a run goes on, and stops a run whose
/// module step, setup or teardown outlasts its deadline (in-process modules cannot be
/// interrupted: the process writes run.json as `failed` and exits with status 1).
pub struct Monitor {
    run_dir: PathBuf,
    current: Arc<Mutex<Current>>,
    last_write: Option<Instant>,
    stop: Arc<std::sync::atomic::AtomicBool>,
}

/// run.json is rewritten after a step at most this often.
const STATUS_EVERY: Duration = Duration::from_secs(1);

impl Monitor {
    /// The monitor of `engine`'s run: installs the engine's start hook, and a watchdog
    /// thread when `deadlines` are given.
    pub fn install(engine: &mut Engine, deadlines: Option<Deadlines>) -> Monitor {
        let run_dir = engine.run_dir().to_path_buf();
        let current = Arc::new(Mutex::new(Current {
            phase: Phase::Setup,
            step: 0,
            modules: Vec::new(),
            since: Instant::now(),
            status: None,
        }));
        let file = File::create(run_dir.join(PROGRESS_FILE)).ok();
        let shared = current.clone();
        let hook: StartHook =
            Box::new(move |phase, at: StepInfo, stage: &str, modules: &[&str]| {
                if let Ok(mut c) = shared.lock() {
                    c.phase = phase;
                    c.step = at.step;
                    c.modules = modules.iter().map(|m| m.to_string()).collect();
                    c.since = Instant::now();
                }
                if let (Some(f), false, Phase::Step) = (&file, modules.is_empty(), phase) {
                    write_progress(f, at.step, stage, modules);
                }
            });
        engine.set_start_hook(hook);
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        if let Some(limits) = deadlines {
            let (current, stop, run_dir) = (current.clone(), stop.clone(), run_dir.clone());
            std::thread::Builder::new()
                .name("caviar-watchdog".into())
                .spawn(move || watchdog(current, stop, run_dir, limits))
                .expect("watchdog thread");
        }
        Monitor {
            run_dir,
            current,
            last_write: None,
            stop,
        }
    }

    /// After a step: rewrites run.json (running, steps so far) at most once a second.
    pub fn after_step(&mut self, cfg: &LoadedConfig, engine: &Engine) {
        if self.last_write.is_some_and(|t| t.elapsed() < STATUS_EVERY) {
            return;
        }
        self.last_write = Some(Instant::now());
        let status = RunStatus::of(cfg, engine, RunState::Running, None);
        let _ = status.write(&self.run_dir);
        if let Ok(mut c) = self.current.lock() {
            c.status = Some(status);
        }
    }

    /// Remembers run.json as first written (what the watchdog rewrites before a step).
    pub fn started(&mut self, cfg: &LoadedConfig, engine: &Engine) {
        if let Ok(mut c) = self.current.lock() {
            c.status = Some(RunStatus::of(cfg, engine, RunState::Running, None));
        }
    }
}

impl Drop for Monitor {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

fn write_progress(f: &File, step: u64, stage: &str, modules: &[&str]) {
    let mut rec = ProgressRecord {
        steps_done: step,
        step,
        stage: stage.to_string(),
        modules: modules.iter().map(|m| m.to_string()).collect(),
    };
    let mut text = serde_json::to_string(&rec).expect("json");
    while text.len() > PROGRESS_SIZE && !rec.modules.is_empty() {
        rec.modules.pop();
        text = serde_json::to_string(&rec).expect("json");
    }
    if text.len() > PROGRESS_SIZE {
        return;
    }
    let mut buf = text.into_bytes();
    buf.resize(PROGRESS_SIZE - 1, b' ');
    buf.push(b'\n');
    let _ = f.write_at(&buf, 0);
}

fn watchdog(
    current: Arc<Mutex<Current>>,
    stop: Arc<std::sync::atomic::AtomicBool>,
    run_dir: PathBuf,
    limits: Deadlines,
) {
    let shortest = limits.step.min(limits.setup);
    let tick = (shortest / 10).clamp(Duration::from_millis(10), Duration::from_millis(100));
    let mut announced = false;
    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
        std::thread::sleep(tick);
        let Ok(c) = current.lock() else { return };
        let presses = crate::interrupt::count();
        let what = match c.phase {
            Phase::Step => format!("step {}", c.step),
            phase => phase.as_str().to_string(),
        };
        if presses == 1 && !announced && !c.modules.is_empty() {
            announced = true;
            eprintln!(
                "interrupting after module '{}' finishes {what} (Ctrl-C again to stop at once)",
                c.modules.join("', '"),
            );
        }
        if c.modules.is_empty() {
            continue;
        }
        let modules = c.modules.join("', '");
        if presses >= 2 {
            let message =
                format!("interrupted in {what} (Ctrl-C twice, module '{modules}' still running)");
            let error = RunErrorInfo::Other { message };
            end_now(&c, &run_dir, RunState::Interrupted, error);
        }
        let (limit, key) = limits.of(c.phase);
        if c.since.elapsed() < limit {
            continue;
        }
        let message = format!(
            "module '{modules}' did not finish {what} within {} s ({key}); \
             the run was stopped (a module running in this process cannot be interrupted)",
            limit.as_secs_f64()
        );
        eprintln!("error: {message}");
        let stepping = c.phase == Phase::Step;
        let error = RunErrorInfo::Module {
            module: c.modules[0].clone(),
            phase: c.phase.as_str().into(),
            step: stepping.then_some(c.step),
            time: stepping.then(|| c.step as f64 * c.status.as_ref().map_or(0.0, |s| s.ts)),
            message,
            trace: None,
        };
        end_now(&c, &run_dir, RunState::Failed, error);
    }
}

/// Ends the process at once from the watchdog, with run.json saying how: `failed` (a
/// step past its deadline, exit 1) or `interrupted` (Ctrl-C twice, exit 130), at the
/// step and modules in progress. The recorder has flushed every finished step.
fn end_now(c: &Current, run_dir: &Path, state: RunState, error: RunErrorInfo) -> ! {
    let mut status = c.status.clone().unwrap_or_default();
    status.status = state;
    status.pid = None;
    status.pid_start = None;
    status.steps_done = status.steps_done.max(c.step);
    status.virtual_time_s = status.steps_done as f64 * status.ts;
    status.end_reason = Some(match state {
        RunState::Interrupted => EndReason::Interrupted,
        _ => EndReason::Error,
    });
    status.last_step = (c.phase == Phase::Step).then_some(c.step);
    status.last_modules = c.modules.clone();
    status.error = Some(error);
    let _ = status.write(run_dir);
    let (what, code) = match state {
        RunState::Interrupted if c.phase != Phase::Step => {
            (format!("interrupted in {}", c.phase.as_str()), 130)
        }
        RunState::Interrupted => (format!("interrupted in step {}", c.step), 130),
        _ => (format!("failed after {} steps", status.steps_done), 1),
    };
    eprintln!(
        "{}: {what}; what was recorded is in the run directory",
        run_dir.display()
    );
    // SAFETY: ends the process at once; the recorder has flushed every finished step.
    unsafe { libc::_exit(code) };
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
    fn a_run_left_running_is_closed_failed_where_progress_json_says() {
        let dir = std::env::temp_dir().join(format!("caviar-close-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let s = RunStatus {
            status: RunState::Running,
            ts: 0.5,
            steps_done: 2,
            pid: Some(1),
            ..Default::default()
        };
        s.write(&dir).unwrap();
        // No progress.json yet: before its first step.
        let place = RunStatus::close_failed(&dir, "the process was killed").unwrap();
        assert_eq!(place.as_deref(), Some(", before its first step"));
        s.write(&dir).unwrap();
        std::fs::write(
            dir.join(PROGRESS_FILE),
            r#"{"steps_done": 4, "step": 4, "stage": "s", "modules": ["a", "b"]}   "#,
        )
        .unwrap();
        let place = RunStatus::close_failed(&dir, "the process was killed by SIGKILL").unwrap();
        assert_eq!(place.as_deref(), Some(", in module 'b' at step 4"));
        let closed = RunStatus::read(&dir).unwrap();
        assert_eq!(
            (closed.status, closed.end_reason, closed.steps_done, closed.pid),
            (RunState::Failed, Some(EndReason::Error), 4, None)
        );
        assert_eq!(closed.virtual_time_s, 2.0);
        assert!(matches!(&closed.error, Some(RunErrorInfo::Module { module, step: Some(4), message, .. })
            if module == "b" && message == "The process was killed by SIGKILL, in module 'b' at step 4"));
        // Closed already: left as it is.
        assert_eq!(RunStatus::close_failed(&dir, "again").unwrap(), None);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_reused_pid_does_not_keep_an_abandoned_run_alive() {
        let dir = std::env::temp_dir().join(format!("caviar-pid-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let me = std::process::id();
        let start = process_start(me).expect("/proc on Linux");
        let mut s = RunStatus {
            status: RunState::Running,
            pid: Some(me),
            pid_start: Some(start),
            ..RunStatus::default()
        };
        s.write(&dir).unwrap();
        assert_eq!(
            RunStatus::read_live(&dir).unwrap().status,
            RunState::Running
        );
        // The same pid, another start: the process that ran it is gone, this is a later one.
        s.pid_start = Some(start + 1);
        s.write(&dir).unwrap();
        assert_eq!(
            RunStatus::read_live(&dir).unwrap().status,
            RunState::Abandoned
        );
        // Runs recorded before pid_start existed: the pid alone decides.
        s.pid_start = None;
        s.write(&dir).unwrap();
        assert_eq!(
            RunStatus::read_live(&dir).unwrap().status,
            RunState::Running
        );
        std::fs::remove_dir_all(&dir).unwrap();
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
