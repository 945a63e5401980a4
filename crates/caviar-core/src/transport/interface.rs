//! What the run needs from a transport, and all it sees of one.
//!
//! HELICS keeps its cores the same way, as leaves behind one interface. The run needs
//! four things:
//!
//! - **check** its section of the experiment file (`[transport.KIND]`) before anything
//!   runs, and the files it names ([`Transport::check`], [`Transport::check_files`]);
//! - **prepare** the run: start or reach its servers and workers, and hand back the
//!   run's modules, [`crate::module::RemoteModule`]s for the ones it hosts
//!   ([`Transport::prepare`] → [`Prepared`]);
//! - report its **status** for `run.json` when the run ends ([`Connection::status`]);
//! - **shut down** its workers and servers ([`Connection::shutdown`]).

use std::path::Path;

use crate::assembly::PrepareError;
use crate::config::{ConfigError, LoadedConfig};
use crate::engine::{ModuleSpec, Tap};

/// How this host starts a worker process of a transport: the interpreter and the
/// arguments that come before the transport's own (the Python package gives
/// `python -m caviar.worker`; a build without Python has none).
#[derive(Debug, Clone)]
pub struct WorkerLauncher {
    pub command: Vec<String>,
}

/// A way of running modules outside this process, as `transport.kind` names it.
pub trait Transport {
    /// The `transport.kind` that selects it, and the name of its section.
    fn kind(&self) -> &'static str;

    /// Built-in plugins this transport provides (they need its connection).
    fn builtin_plugins(&self) -> &'static [&'static str] {
        &[]
    }

    /// What a built-in module of this transport publishes, for the wiring checks of
    /// `validate` (which builds no connection, so not the module).
    fn builtin_publishes(&self, _cfg: &LoadedConfig, _module: &str) -> Option<Vec<String>> {
        None
    }

    /// Reads and checks `[transport.KIND]` (errors name the file, line and key). Called
    /// whenever the file has the section, whichever transport runs, and when this one runs.
    fn check(&self, cfg: &LoadedConfig) -> Result<(), ConfigError>;

    /// An older name of `episode.step_timeout` in this transport's section, if it has one
    /// and the file gives it (it applies whichever transport runs).
    fn step_timeout(&self, _cfg: &LoadedConfig) -> Option<f64> {
        None
    }

    /// Checks that the files the section names exist (what `validate` and the start of
    /// `run` check on the filesystem).
    fn check_files(&self, _cfg: &LoadedConfig) -> Result<(), ConfigError> {
        Ok(())
    }

    /// Starts what the run needs and returns every module of the configuration, in its
    /// order, with a tap on the routed messages if it mirrors them, and the connection
    /// to shut down at the end. `run_dir` exists (logs go into it).
    fn prepare(
        &self,
        cfg: &LoadedConfig,
        launcher: Option<&WorkerLauncher>,
        run_dir: &Path,
    ) -> Result<Prepared, PrepareError>;
}

/// What [`Transport::prepare`] hands to the run.
pub struct Prepared {
    pub modules: Vec<ModuleSpec>,
    pub tap: Option<Tap>,
    pub connection: Box<dyn Connection>,
}

/// A prepared transport, as the run session holds it until the end.
pub trait Connection: Send {
    /// Fields `run.json` records of the transport (NATS: `security`), read when the
    /// run ends.
    fn status(&self) -> serde_json::Map<String, serde_json::Value> {
        serde_json::Map::new()
    }

    /// Stops the workers and servers this run started. Called once the engine is
    /// closed; must be safe to call again (and on drop).
    fn shutdown(&self);
}
