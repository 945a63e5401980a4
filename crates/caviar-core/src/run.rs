//! From a configuration to a running engine, and the run directory around it.
//!
//! A run directory holds `config.toml` (the exact configuration, overrides applied),
//! `run.json` (status, counts, error), `messages.parquet`, `timings.parquet` and
//! whatever artifacts modules wrote.

use std::fs;
use std::path::{Path, PathBuf};
use std::time::Duration;

use crate::assembly::{build_modules, PrepareError, BRIDGE_PLUGIN, REPLAY_PLUGIN};
use crate::config::{ConfigError, LoadedConfig, TransportKind};
use crate::engine::{Engine, EngineOptions, ModuleSpec};
use crate::module::{AnyModule, Module, ResourceProbe};
use crate::recorder::Recorder;
use crate::status::{write_status, Monitor, RunState};
use crate::topic::Pattern;
use crate::transport::nats::{self, WorkerLauncher};

/// Builds the module of a `[modules.NAME]` table. Loading and checking parameters
/// happens here, before any run directory exists: a config error never starts a run.
pub trait PluginLoader {
    fn load(&self, cfg: &LoadedConfig, name: &str) -> Result<Box<dyn Module>, ConfigError>;

    /// How to start a `caviar worker` process for the NATS transport, if this host can.
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

/// Loads every module of the configuration (what `validate` checks).
pub fn load_modules(
    cfg: &LoadedConfig,
    loader: &dyn PluginLoader,
) -> Result<Vec<ModuleSpec>, ConfigError> {
    build_modules(cfg, |name, m| {
        if m.plugin == BRIDGE_PLUGIN {
            // Needs a live NATS connection: built by `nats::prepare` (allowed only with
            // the NATS transport, so only `validate` gets here).
            return Ok(None);
        }
        loader.load(cfg, name).map(|m| Some(AnyModule::Local(m)))
    })
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
/// be made under `output.dir`, and the files the NATS transport names exist.
pub fn check_paths(cfg: &LoadedConfig) -> Result<(), ConfigError> {
    check_output_dir(cfg)?;
    if cfg.config.transport.kind != TransportKind::Nats {
        return Ok(());
    }
    check_nats_files(cfg)
}

fn check_nats_files(cfg: &LoadedConfig) -> Result<(), ConfigError> {
    let n = &cfg.config.transport.nats;
    let files = [
        ("server", &n.server),
        ("credentials", &n.credentials),
        ("tls_ca", &n.tls_ca),
        ("tls_cert", &n.tls_cert),
        ("tls_key", &n.tls_key),
        ("key_file", &n.key_file),
    ];
    for (key, path) in files {
        if let Some(p) = path {
            let full = cfg.resolve(p);
            if !full.is_file() {
                return Err(cfg.error_at(
                    &format!("transport.nats.{key}"),
                    format!("no such file: {}", full.display()),
                ));
            }
        }
    }
    Ok(())
}

/// Loads every module, creates the run directory and the engine.
/// `out`: the run directory to use instead of `output.dir/NAME-NNN`.
///
/// With the NATS transport the plugins are loaded by their workers, not here: the run
/// directory comes first (worker logs go into it), then the server and the workers.
pub fn prepare(
    cfg: &LoadedConfig,
    loader: &dyn PluginLoader,
    out: Option<&Path>,
) -> Result<Engine, PrepareError> {
    prepare_monitored(cfg, loader, out).map(|(engine, _)| engine)
}

/// [`prepare`], with the [`Monitor`] that keeps run.json and progress.json true as the
/// run goes on (call its `after_step`) and, in-process, stops a module step that
/// outlasts `episode.step_timeout` (the NATS transport has its own deadline).
pub fn prepare_monitored(
    cfg: &LoadedConfig,
    loader: &dyn PluginLoader,
    out: Option<&Path>,
) -> Result<(Engine, Monitor), PrepareError> {
    let in_process = cfg.config.transport.kind == TransportKind::Inprocess;
    if out.is_none() {
        check_output_dir(cfg)?;
    }
    if cfg.config.transport.kind == TransportKind::Nats {
        check_nats_files(cfg)?;
    }
    let specs = if in_process {
        Some(load_modules(cfg, loader)?)
    } else {
        None
    };
    let run_dir = match out {
        Some(dir) => create_exact(dir)?,
        None => create_numbered(cfg)?,
    };
    let io = |e: std::io::Error| PrepareError::Io(format!("{}: {e}", run_dir.display()));
    fs::write(run_dir.join("config.toml"), &cfg.text).map_err(io)?;
    let (specs, tap) = match specs {
        Some(s) => (s, None),
        None => match nats::prepare(cfg, loader.worker_launcher(), &run_dir) {
            Ok(prepared) => prepared,
            Err(e) => {
                // A configuration error (reported by a worker) starts no run: the run
                // directory made for the workers' logs goes again.
                if matches!(e, PrepareError::Config(_)) {
                    let _ = fs::remove_dir_all(&run_dir);
                }
                return Err(e);
            }
        },
    };
    let exclude = cfg
        .config
        .output
        .exclude
        .iter()
        .map(|p| Pattern::new(p).expect("validated"))
        .collect();
    let recorder = Recorder::create(
        &run_dir,
        exclude,
        Duration::from_secs_f64(cfg.config.output.flush_interval),
    )
    .map_err(|e| PrepareError::Io(e.to_string()))?;
    let ep = &cfg.config.episode;
    let opts = EngineOptions {
        ts: ep.ts,
        steps: cfg.steps(),
        seed: ep.seed,
        stages: ep.stages.clone(),
        run_dir: run_dir.clone(),
        config_dir: cfg.base_dir.clone(),
    };
    let mut engine = Engine::new(opts, specs, Some(recorder)).map_err(PrepareError::Io)?;
    if let Some(tap) = tap {
        engine.set_tap(tap);
    }
    if let Some(probe) = loader.resource_probe() {
        engine.set_probe(probe);
    }
    write_status(cfg, &engine, RunState::Running, None).map_err(PrepareError::Io)?;
    let watchdog = in_process.then(|| Duration::from_secs_f64(cfg.step_timeout()));
    let mut monitor = Monitor::install(&mut engine, watchdog);
    monitor.started(cfg, &engine);
    Ok((engine, monitor))
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
