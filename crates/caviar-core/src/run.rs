//! From a configuration to a running engine, and the run directory around it: one
//! [`RunSession`] for the command line (`caviar-core run`) and for Python
//! (`caviar.Simulation`), from loading the modules to the last line of run.json.
//!
//! A run directory holds `config.toml` (the exact configuration, overrides applied),
//! `run.json` (status, counts, error), `messages.parquet`, `timings.parquet` and
//! whatever artifacts modules wrote.

use std::fs;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::assembly::{build_modules, refuse_unfed, wiring_warnings, PrepareError, REPLAY_PLUGIN};
use crate::checkpoint::{Checkpoint, SavedState};
use crate::config::{ConfigError, LoadedConfig};
use crate::engine::{Engine, EngineError, EngineOptions, ModuleSpec, StepReport, Tap};
use crate::module::{AnyModule, Module, ResourceProbe};
use crate::recorder::Recorder;
use crate::status::{Deadlines, Monitor, RunState, RunStatus};
use crate::topic::Pattern;
use crate::transport::{self, Connection, WorkerLauncher};

/// The configuration a run ran (overrides applied), as the run directory keeps it.
pub const CONFIG_FILE: &str = "config.toml";
/// Builds the module of a `[modules.NAME]` table. Loading and checking parameters
/// happens here, before any run directory exists: a config error never starts a run.
pub trait PluginLoader {
    fn load(&self, cfg: &LoadedConfig, name: &str) -> Result<Box<dyn Module>, ConfigError>;

    /// How to start a worker process of a transport, if this host can.
    fn worker_launcher(&self) -> Option<WorkerLauncher> {
        None
    }

    /// GPU sampling for the modules of this process, where a GPU can be measured.
    fn resource_probe(&self) -> Option<Box<dyn ResourceProbe>> {
        None
    }

    /// Serves a live view of the run directory in the background (port 0: any free
    /// one); returns its URL. Hosts without a viewer say so.
    fn start_viewer(&self, _run_dir: &Path, _port: u16) -> Result<String, String> {
        Err("this caviar-core has no viewer (use the one installed with the Python package)".into())
    }
}

/// The loader of a build without Python: only built-in modules.
pub struct BuiltinsOnly;

impl PluginLoader for BuiltinsOnly {
    fn load(&self, cfg: &LoadedConfig, name: &str) -> Result<Box<dyn Module>, ConfigError> {
        Err(cfg.error_at(
            &format!("modules.{name}.plugin"),
            format!(
                "'{}' is not a built-in module ({}) and this caviar-core binary has no Python; \
                 run the `caviar-core` installed with the Python package (pip install .)",
                cfg.config.modules[name].plugin, REPLAY_PLUGIN
            ),
        ))
    }
}

/// Loads every module of the configuration in this process (what `validate` checks);
/// a transport's own built-ins, which need its connection, are left out.
pub fn load_modules(
    cfg: &LoadedConfig,
    loader: &dyn PluginLoader,
) -> Result<Vec<ModuleSpec>, ConfigError> {
    build_modules(cfg, |name, m| {
        if transport::is_transport_builtin(&m.plugin) {
            return Ok(None);
        }
        loader.load(cfg, name).map(|m| Some(AnyModule::Local(m)))
    })
}

/// Everything `validate` checks, nothing run: the transport's section, the paths, every
/// module loaded with its parameters. Returns the wiring warnings (errors where
/// `episode.strict_wiring`) and what the wiring allows to run at once
/// ([`crate::concurrency`]).
pub fn check(
    cfg: &LoadedConfig,
    loader: &dyn PluginLoader,
) -> Result<(Vec<String>, Vec<String>), ConfigError> {
    transport::check(cfg)?;
    check_paths(cfg)?;
    let specs = load_modules(cfg, loader)?;
    let unbuilt = |name: &str| transport::builtin_publishes(cfg, name);
    refuse_unfed(cfg, &specs, &unbuilt)?;
    let warnings = wiring_warnings(cfg, &specs, &unbuilt);
    strict_wiring(cfg, &warnings)?;
    Ok((
        warnings,
        crate::concurrency::concurrency(cfg, &specs, &unbuilt),
    ))
}

/// With `episode.strict_wiring`, wiring warnings are an error (as mosaik refuses a bad
/// `connect`).
fn strict_wiring(cfg: &LoadedConfig, warnings: &[String]) -> Result<(), ConfigError> {
    if !cfg.config.episode.strict_wiring || warnings.is_empty() {
        return Ok(());
    }
    Err(cfg.error_at(
        "episode.strict_wiring",
        format!(
            "the modules are not wired together ({} problem(s)):\n  {}",
            warnings.len(),
            warnings.join("\n  ")
        ),
    ))
}

/// The parent of numbered run directories: `output.dir` (relative to the config
/// file), or `runs` in the current directory.
fn output_parent(cfg: &LoadedConfig) -> PathBuf {
    match &cfg.config.output.dir {
        Some(d) => cfg.resolve(d),
        None => PathBuf::from("runs"),
    }
}

/// Checks that run directories can be made under `output.dir` (what `validate` and the
/// start of `run` check), without leaving anything behind: the nearest existing
/// directory on the way must be a directory we can create entries in (probed with a
/// directory created and removed at once).
pub fn check_output_dir(cfg: &LoadedConfig) -> Result<(), ConfigError> {
    let parent = output_parent(cfg);
    let key = if cfg.config.output.dir.is_some() {
        "output.dir"
    } else {
        "output"
    };
    let fail = |why: String| cfg.error_at(key, format!("{}: {why}", parent.display()));
    let mut existing = parent.as_path();
    loop {
        match fs::metadata(existing) {
            Ok(m) if m.is_dir() => break,
            Ok(_) => return Err(fail(format!("{} is not a directory", existing.display()))),
            Err(_) => match existing.parent() {
                Some(p) if !p.as_os_str().is_empty() => existing = p,
                _ => {
                    existing = Path::new(".");
                    break;
                }
            },
        }
    }
    let probe = existing.join(format!(".caviar-probe-{}", std::process::id()));
    match fs::create_dir(&probe) {
        Ok(()) => {
            let _ = fs::remove_dir(&probe);
            Ok(())
        }
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(()),
        Err(e) => Err(fail(format!(
            "cannot create run directories in {}: {e}",
            existing.display()
        ))),
    }
}

/// What `validate` and the start of `run` check on the filesystem: run directories can
/// be made under `output.dir`, and the files the transport names exist.
pub fn check_paths(cfg: &LoadedConfig) -> Result<(), ConfigError> {
    check_output_dir(cfg)?;
    match transport::by_kind(cfg.transport_kind()) {
        Some(t) => t.check_files(cfg),
        None => Ok(()),
    }
}

/// A run from start to end: the engine, the monitor that keeps run.json and
/// progress.json true as it goes, the transport's connection, and the one place that
/// turns how the run ended into run.json.
pub struct RunSession {
    cfg: LoadedConfig,
    engine: Engine,
    monitor: Option<Monitor>,
    connection: Option<Box<dyn Connection>>,
    warnings: Vec<String>,
    ended: Option<RunState>,
    /// When the last checkpoint was written (or the run started): for
    /// `output.checkpoint_interval_s`.
    last_checkpoint: Instant,
}

impl RunSession {
    /// Checks the transport, loads every module, creates the run directory and the
    /// engine. `out`: the run directory to use instead of `output.dir/NAME-NNN`.
    ///
    /// In-process, the plugins are loaded before the run directory exists. A transport
    /// loads them in its workers: the run directory comes first (worker logs go into
    /// it), then its servers and workers; a configuration error there removes the
    /// run directory again.
    pub fn start(
        cfg: LoadedConfig,
        loader: &dyn PluginLoader,
        out: Option<&Path>,
    ) -> Result<Self, PrepareError> {
        let transport = transport::check(&cfg)?;
        if out.is_none() {
            check_output_dir(&cfg)?;
        }
        if let Some(t) = &transport {
            t.check_files(&cfg)?;
        }
        let local = match transport {
            None => Some(load_modules(&cfg, loader)?),
            Some(_) => None,
        };
        // In-process, the wiring is known (and refused where strict) before the run
        // directory exists; a transport knows it once its workers loaded the plugins.
        let mut warnings = Vec::new();
        if let Some(specs) = &local {
            refuse_unfed(&cfg, specs, &|_| None)?;
            warnings = wiring_warnings(&cfg, specs, &|_| None);
            strict_wiring(&cfg, &warnings)?;
        }
        // The folders this run creates on the way to its run directory: a configuration
        // error reported by a worker takes them away again, with the run directory.
        let made = missing_ancestors(&out.map_or_else(|| output_parent(&cfg), |d| d.to_path_buf()));
        let run_dir = match out {
            Some(dir) => create_exact(dir)?,
            None => create_numbered(&cfg)?,
        };
        let io = |e: std::io::Error| PrepareError::Io(format!("{}: {e}", run_dir.display()));
        fs::write(run_dir.join(CONFIG_FILE), &cfg.text).map_err(io)?;
        let (specs, tap, connection) = match (local, transport) {
            (Some(specs), _) => (specs, None, None),
            (None, Some(t)) => {
                let prepared = t
                    .prepare(&cfg, loader.worker_launcher().as_ref(), &run_dir)
                    .and_then(|p| {
                        refuse_unfed(&cfg, &p.modules, &|_| None)?;
                        warnings = wiring_warnings(&cfg, &p.modules, &|_| None);
                        strict_wiring(&cfg, &warnings)?;
                        Ok(p)
                    })
                    .inspect_err(|e| {
                        // A configuration error (reported by a worker) starts no run.
                        if matches!(e, PrepareError::Config(_)) {
                            let _ = fs::remove_dir_all(&run_dir);
                            for dir in &made {
                                let _ = fs::remove_dir(dir); // only if empty
                            }
                        }
                    })?;
                (prepared.modules, prepared.tap, Some(prepared.connection))
            }
            (None, None) => unreachable!("in-process modules are loaded above"),
        };
        let engine = new_engine(&cfg, &run_dir, specs, None)?;
        Self::launch(cfg, loader, engine, tap, connection, warnings)
    }

    /// Goes on with the run in `run_dir` from its last checkpoint (`caviar-core run
    /// --resume`): the configuration it saved, every module set up again and given back
    /// its state and inbox, the recording cut to the steps before the checkpoint.
    /// Refused, saying why, for a run that completed or still runs, one without a
    /// checkpoint, over a transport, or with a module that cannot be resumed.
    pub fn resume(run_dir: &Path, loader: &dyn PluginLoader) -> Result<Self, PrepareError> {
        let io = |e: String| PrepareError::Io(e);
        let before = RunStatus::read_live(run_dir).map_err(io)?;
        match before.status {
            RunState::Completed => {
                return Err(io(format!(
                    "{}: the run completed; there is nothing to resume",
                    run_dir.display()
                )))
            }
            RunState::Running => {
                return Err(io(format!(
                    "{}: the run is still running (pid {}); stop it first",
                    run_dir.display(),
                    before.pid.map_or("?".into(), |p| p.to_string())
                )))
            }
            _ => {}
        }
        let cp = Checkpoint::read(run_dir).map_err(io)?;
        if let Some((name, why)) = cp.modules.iter().find_map(|m| match &m.state {
            SavedState::Unsupported { why } => Some((&m.name, why)),
            _ => None,
        }) {
            return Err(io(format!(
                "{}: cannot resume: module '{name}': {why}",
                run_dir.display()
            )));
        }
        let file = run_dir.join(CONFIG_FILE);
        let text = fs::read_to_string(&file).map_err(|e| io(format!("{}: {e}", file.display())))?;
        let mut cfg =
            crate::config::parse(&text, &file.display().to_string(), &cp.config_dir, &[])?;
        // The run as first started: its file and overrides (already in the saved text).
        cfg.file = before.config_file.clone();
        cfg.overrides = before.overrides.clone();
        // In process: the plugins here; over a transport: its server and workers again
        // (their logs start afresh in the run directory).
        let (specs, tap, connection, warnings) = match transport::check(&cfg)? {
            None => {
                let specs = load_modules(&cfg, loader)?;
                let warnings = wiring_warnings(&cfg, &specs, &|_| None);
                (specs, None, None, warnings)
            }
            Some(t) => {
                t.check_files(&cfg)?;
                let p = t.prepare(&cfg, loader.worker_launcher().as_ref(), run_dir)?;
                let warnings = wiring_warnings(&cfg, &p.modules, &|_| None);
                (p.modules, p.tap, Some(p.connection), warnings)
            }
        };
        let engine = new_engine(&cfg, run_dir, specs, Some(cp.next_step))?;
        let mut session = Self::launch(cfg, loader, engine, tap, connection, warnings)?;
        if let Err(e) = session.engine.resume_from(&cp, &before.resumed_at) {
            // Nothing ran: the run stays as it was, failed, with why it did not resume.
            let _ = session.finish(Err(e));
            return Err(io(format!(
                "{}: the run could not be resumed (run.json says why)",
                run_dir.display()
            )));
        }
        Ok(session)
    }

    /// The session around a run's engine, for `start` and `resume` alike: the
    /// transport's tap, this host's GPU probe, the monitor (with its watchdog in
    /// process; a transport has its own deadlines) and run.json saying `running`.
    fn launch(
        cfg: LoadedConfig,
        loader: &dyn PluginLoader,
        mut engine: Engine,
        tap: Option<Tap>,
        connection: Option<Box<dyn Connection>>,
        warnings: Vec<String>,
    ) -> Result<Self, PrepareError> {
        if let Some(tap) = tap {
            engine.set_tap(tap);
        }
        if let Some(probe) = loader.resource_probe() {
            engine.set_probe(probe);
        }
        let watchdog = connection.is_none().then(|| Deadlines {
            step: Duration::from_secs_f64(transport::step_timeout(&cfg)),
            setup: Duration::from_secs_f64(cfg.setup_timeout()),
        });
        let mut monitor = Monitor::install(&mut engine, watchdog);
        RunStatus::of(&cfg, &engine, RunState::Running, None)
            .write(engine.run_dir())
            .map_err(PrepareError::Io)?;
        monitor.started(&cfg, &engine);
        Ok(RunSession {
            cfg,
            engine,
            monitor: Some(monitor),
            connection,
            warnings,
            ended: None,
            last_checkpoint: Instant::now(),
        })
    }

    pub fn engine(&self) -> &Engine {
        &self.engine
    }

    pub fn config(&self) -> &LoadedConfig {
        &self.cfg
    }

    /// The wiring warnings of the run's modules (the start of `run` prints them).
    pub fn warnings(&self) -> &[String] {
        &self.warnings
    }

    /// How the run ended; `None` while it goes on.
    pub fn ended(&self) -> Option<RunState> {
        self.ended
    }

    /// Runs one step; `None` when the episode is over.
    pub fn step(&mut self) -> Result<Option<StepReport>, EngineError> {
        let report = self.engine.step()?;
        if let Some(r) = &report {
            checkpoint_due(&self.cfg, &mut self.engine, r, &mut self.last_checkpoint)?;
        }
        if let (Some(m), Some(_)) = (&mut self.monitor, &report) {
            m.after_step(&self.cfg, &self.engine);
        }
        Ok(report)
    }

    /// Runs to the end of the episode; `on_step` after every step, `false` stops it
    /// (interrupted).
    pub fn run(
        &mut self,
        mut on_step: impl FnMut(&Engine, &StepReport) -> bool,
    ) -> Result<(), EngineError> {
        let (monitor, cfg, last) = (&mut self.monitor, &self.cfg, &mut self.last_checkpoint);
        loop {
            let Some(report) = self.engine.step()? else {
                return Ok(());
            };
            checkpoint_due(cfg, &mut self.engine, &report, last)?;
            if let Some(m) = monitor.as_mut() {
                m.after_step(cfg, &self.engine);
            }
            let go_on = on_step(&self.engine, &report) && !crate::interrupt::requested();
            if !go_on && !report.ended {
                return Err(self.engine.interrupt_after(report.step));
            }
        }
    }

    /// Ends the run with `result` (how running went): tears the modules down,
    /// compacts the recording, shuts the transport down and writes run.json:
    /// `completed`, `interrupted` (Ctrl-C) or `failed`, with the error. The error of
    /// the run, or else of the teardown, is returned. Once; later calls return `Ok`.
    pub fn finish(&mut self, result: Result<(), EngineError>) -> Result<(), EngineError> {
        if self.ended.is_some() {
            return Ok(());
        }
        let closed = self.engine.close();
        // The watchdog stops before the last run.json is written.
        self.monitor = None;
        if let Some(c) = &self.connection {
            c.shutdown();
        }
        let error = result.err().or(closed.err());
        let state = match &error {
            None => RunState::Completed,
            Some(EngineError::Interrupted { .. }) => RunState::Interrupted,
            Some(_) => RunState::Failed,
        };
        self.ended = Some(state);
        let mut status = RunStatus::of(&self.cfg, &self.engine, state, error.as_ref());
        if let Some(c) = &self.connection {
            status.transport = c.status();
        }
        if let Err(e) = status.write(self.engine.run_dir()) {
            eprintln!("error: {e}");
        }
        error.map_or(Ok(()), Err)
    }
}

/// A session dropped before its end (`del sim`, a host that returned early) is
/// finished here, so that run.json does not stay `running`.
impl Drop for RunSession {
    fn drop(&mut self) {
        let _ = self.finish(Ok(()));
    }
}

/// Writes a checkpoint after `report`'s step when one is due (`output.checkpoint_every`
/// steps, or `output.checkpoint_interval_s` of wall time since `last`; none after the last
/// step). Its time counts in the step's wall time.
fn checkpoint_due(
    cfg: &LoadedConfig,
    engine: &mut Engine,
    report: &StepReport,
    last: &mut Instant,
) -> Result<(), EngineError> {
    let every = cfg.checkpoint_every();
    let by_time = cfg
        .checkpoint_interval()
        .is_some_and(|i| last.elapsed() >= i);
    if every == 0 || report.ended || !(engine.steps_done().is_multiple_of(every) || by_time) {
        return Ok(());
    }
    let t = Instant::now();
    *last = t;
    let cp = engine.checkpoint()?;
    let resumable = !cp
        .modules
        .iter()
        .any(|m| matches!(m.state, SavedState::Unsupported { .. }));
    if !resumable && engine.run_dir().join(crate::checkpoint::FILE).exists() {
        // Keep the checkpoint there is (a worker that did not answer this time must not
        // take away the last good one; a refusal is already written).
        engine.add_checkpoint_s(t.elapsed().as_secs_f64());
        return Ok(());
    }
    cp.write(engine.run_dir()).map_err(|message| {
        EngineError::Record(crate::recorder::RecordError::Format {
            path: engine.run_dir().join(crate::checkpoint::FILE),
            message,
        })
    })?;
    engine.add_checkpoint_s(t.elapsed().as_secs_f64());
    Ok(())
}

/// The engine of a run: the episode's timing and stages, and its recorder in `run_dir`,
/// new, or with `resume_at` (a resumed run's next step) the one there, cut to the steps
/// before it.
fn new_engine(
    cfg: &LoadedConfig,
    run_dir: &Path,
    specs: Vec<ModuleSpec>,
    resume_at: Option<u64>,
) -> Result<Engine, PrepareError> {
    let exclude = cfg
        .config
        .output
        .exclude
        .iter()
        .map(|p| Pattern::new(p).expect("validated"))
        .collect();
    let flush = Duration::from_secs_f64(cfg.config.output.flush_interval);
    let recorder = match resume_at {
        None => Recorder::create(run_dir, exclude, flush),
        Some(next_step) => Recorder::resume(run_dir, exclude, flush, next_step),
    }
    .map_err(|e| PrepareError::Io(e.to_string()))?;
    let ep = &cfg.config.episode;
    let opts = EngineOptions {
        ts: ep.ts,
        steps: cfg.steps(),
        seed: ep.seed,
        stages: ep.stages.clone(),
        run_dir: run_dir.to_path_buf(),
        config_dir: cfg.base_dir.clone(),
    };
    let mut engine = Engine::new(opts, specs, Some(recorder)).map_err(PrepareError::Io)?;
    if let Some(pacer) = cfg.pacer() {
        engine.set_pacer(pacer);
    }
    Ok(engine)
}

/// `dir` and those of its ancestors that do not exist yet, deepest first.
fn missing_ancestors(dir: &Path) -> Vec<PathBuf> {
    dir.ancestors()
        .take_while(|d| !d.as_os_str().is_empty() && !d.exists())
        .map(Path::to_path_buf)
        .collect()
}

fn create_exact(dir: &Path) -> Result<PathBuf, PrepareError> {
    if dir.exists()
        && fs::read_dir(dir)
            .map(|mut d| d.next().is_some())
            .unwrap_or(true)
    {
        return Err(PrepareError::Io(format!(
            "{}: the run directory exists and is not empty",
            dir.display()
        )));
    }
    fs::create_dir_all(dir).map_err(|e| PrepareError::Io(format!("{}: {e}", dir.display())))?;
    Ok(dir.to_path_buf())
}

/// `output.dir/NAME-001`, `NAME-002`, …: the first free one.
fn create_numbered(cfg: &LoadedConfig) -> Result<PathBuf, PrepareError> {
    let parent = output_parent(cfg);
    let name = cfg.config.output.name.clone().unwrap_or_else(|| {
        Path::new(&cfg.file)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "run".into())
    });
    fs::create_dir_all(&parent)
        .map_err(|e| PrepareError::Io(format!("{}: {e}", parent.display())))?;
    for n in 1.. {
        let dir = parent.join(format!("{name}-{n:03}"));
        // create_dir (not _all) fails if it exists: two runs never share a directory.
        match fs::create_dir(&dir) {
            Ok(()) => return Ok(dir),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(PrepareError::Io(format!("{}: {e}", dir.display()))),
        }
    }
    unreachable!()
}
