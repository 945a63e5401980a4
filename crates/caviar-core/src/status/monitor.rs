//! The [`Monitor`] of a run in this process: keeps run.json and progress.json true
//! while it goes on, and its watchdog stops a run whose module outlasts its deadline
//! (or on a second Ctrl-C), writing run.json as it ends the process.

use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::progress::{write_progress, PROGRESS_FILE};
use super::run_json::{RunErrorInfo, RunState, RunStatus};
use crate::config::LoadedConfig;
use crate::engine::{EndReason, Engine, Phase, StartHook};
use crate::module::StepInfo;

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
