//! The `caviar._core` extension: hosts Python plugins in-process and exposes the
//! engine to Python. The Python side of the bridge is `caviar/_host.py`; this file
//! moves messages across ([`RawMessage`]), turns Python exceptions into module errors
//! and exposes the core's topic matching and NATS wire format, so that Python does
//! not write them a second time. `caviar/_core.pyi` describes all of it.

use std::path::PathBuf;

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyList;

use crate::assembly::PrepareError;
use crate::config::{self, ConfigError, LoadedConfig};
use crate::engine::EngineError;
use crate::message::{Outgoing, SharedMessage};
use crate::module::{Module, ModuleError, ModuleState, ResourceProbe, SetupContext, StepInfo};
use crate::py_messages::{outgoing_from_python, raw_messages, RawMessage};
use crate::run::{PluginLoader, RunSession};
use crate::status::RunStatus;
use crate::transport::WorkerLauncher;

/// The exception classes of `caviar.errors`, raised from here.
mod errors {
    pyo3::import_exception!(caviar.errors, ConfigError);
    pyo3::import_exception!(caviar.errors, RunError);
}

fn host(py: Python<'_>) -> PyResult<Bound<'_, PyModule>> {
    py.import("caviar._host")
}

/// "Type: message" and the formatted traceback of a Python exception. A
/// KeyboardInterrupt is Ctrl-C reaching the plugin's code: the run is interrupted.
fn module_error(py: Python<'_>, err: PyErr) -> ModuleError {
    if err.is_instance_of::<pyo3::exceptions::PyKeyboardInterrupt>(py) {
        crate::interrupt::request();
        return ModuleError::new("interrupted (Ctrl-C)");
    }
    if err.is_instance_of::<errors::ConfigError>(py) {
        // caviar.ConfigError from a plugin: bad input it found, not a crash; its key
        // is relative to the module's table.
        let value = err.value(py);
        let key = value
            .getattr("key")
            .and_then(|k| k.extract::<Option<String>>())
            .ok()
            .flatten();
        let message = value.to_string();
        return ModuleError::bad_input(match key {
            Some(k) => format!("{k}: {message}"),
            None => message,
        });
    }
    let message = err.to_string();
    let trace = host(py)
        .and_then(|h| h.call_method1("format_exception", (err.value(py), err.traceback(py))))
        .and_then(|t| t.extract::<String>())
        .ok();
    ModuleError {
        message,
        trace,
        bad_input: false,
    }
}

/// A Python plugin, wrapped by `caviar._host.Hosted`.
struct PyPlugin {
    hosted: Py<PyAny>,
    subscriptions: Vec<String>,
    /// Empty: not declared.
    publishes: Vec<String>,
    optional: Vec<String>,
    required: Vec<(String, String)>,
}

impl Module for PyPlugin {
    fn default_subscriptions(&self) -> Vec<String> {
        self.subscriptions.clone()
    }

    fn publishes(&self) -> Option<Vec<String>> {
        (!self.publishes.is_empty()).then(|| self.publishes.clone())
    }

    fn optional_subscriptions(&self) -> Vec<String> {
        self.optional.clone()
    }

    fn required_inputs(&self) -> Vec<(String, String)> {
        self.required.clone()
    }

    fn setup(&mut self, ctx: &SetupContext) -> Result<(), ModuleError> {
        Python::with_gil(|py| {
            let args = (
                ctx.seed,
                ctx.ts,
                ctx.steps,
                ctx.every,
                ctx.offset,
                ctx.run_dir.to_string_lossy().into_owned(),
                ctx.config_dir.to_string_lossy().into_owned(),
            );
            self.hosted
                .call_method1(py, "setup", args)
                .map(drop)
                .map_err(|e| module_error(py, e))
        })
    }

    fn step(
        &mut self,
        at: StepInfo,
        inbox: &[SharedMessage],
        out: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        Python::with_gil(|py| {
            let raw = raw_messages(py, inbox).map_err(|e| module_error(py, e))?;
            let result = self
                .hosted
                .call_method1(py, "step", (at.step, at.time, raw))
                .map_err(|e| module_error(py, e))?;
            outgoing_from_python(result.bind(py), out).map_err(|e| module_error(py, e))
        })
    }

    fn teardown(&mut self) -> Result<(), ModuleError> {
        Python::with_gil(|py| {
            self.hosted
                .call_method0(py, "teardown")
                .map(drop)
                .map_err(|e| module_error(py, e))
        })
    }

    fn state(&mut self) -> Result<ModuleState, ModuleError> {
        Python::with_gil(|py| {
            let r = self
                .hosted
                .call_method0(py, "state")
                .map_err(|e| module_error(py, e))?;
            let (kind, value): (String, Bound<'_, PyAny>) =
                r.bind(py).extract().map_err(|e| module_error(py, e))?;
            Ok(match kind.as_str() {
                "stateless" => ModuleState::Stateless,
                "saved" => ModuleState::Saved(value.extract().map_err(|e| module_error(py, e))?),
                _ => ModuleState::Unsupported(value.extract().map_err(|e| module_error(py, e))?),
            })
        })
    }

    fn restore(&mut self, state: &[u8]) -> Result<(), ModuleError> {
        Python::with_gil(|py| {
            let data = pyo3::types::PyBytes::new(py, state);
            self.hosted
                .call_method1(py, "restore", (data,))
                .map(drop)
                .map_err(|e| module_error(py, e))
        })
    }

    fn concurrent(&self) -> bool {
        false
    }
}

/// Loads plugins through `caviar._host.load_plugin`.
struct PyLoader;

/// GPU use of this process through `caviar._gpu` (nvidia-ml-py).
struct PyGpuProbe {
    sampler: Py<PyAny>,
}

impl ResourceProbe for PyGpuProbe {
    fn sample(&mut self) -> Option<(f64, f64)> {
        Python::with_gil(|py| {
            self.sampler
                .call_method0(py, "sample")
                .ok()?
                .extract::<Option<(f64, f64)>>(py)
                .ok()?
        })
    }
}

impl PluginLoader for PyLoader {
    /// `caviar.view.start_server`: a daemon thread of this interpreter serves the page.
    fn start_viewer(&self, run_dir: &std::path::Path, port: u16) -> Result<String, String> {
        Python::with_gil(|py| {
            let server = py
                .import("caviar.view")?
                .call_method1("start_server", (run_dir.to_path_buf(), "127.0.0.1", port))?;
            server.getattr("url")?.extract::<String>()
        })
        .map_err(|e: PyErr| e.to_string())
    }

    /// Present only where nvidia-ml-py finds an NVIDIA driver and a GPU.
    fn resource_probe(&self) -> Option<Box<dyn ResourceProbe>> {
        Python::with_gil(|py| {
            let sampler = py
                .import("caviar._gpu")
                .ok()?
                .call_method0("open_sampler")
                .ok()?;
            (!sampler.is_none()).then(|| {
                Box::new(PyGpuProbe {
                    sampler: sampler.unbind(),
                }) as Box<dyn ResourceProbe>
            })
        })
    }

    /// Workers run under this interpreter: the same environment, the same plugins.
    fn worker_launcher(&self) -> Option<WorkerLauncher> {
        Python::with_gil(|py| {
            let exe: String = py
                .import("sys")
                .ok()?
                .getattr("executable")
                .ok()?
                .extract()
                .ok()?;
            (!exe.is_empty()).then(|| WorkerLauncher {
                command: vec![exe, "-m".into(), "caviar.worker".into()],
            })
        })
    }

    fn load(&self, cfg: &LoadedConfig, name: &str) -> Result<Box<dyn Module>, ConfigError> {
        Python::with_gil(|py| {
            let m = &cfg.config.modules[name];
            let params = serde_json::to_string(&cfg.params_json(name)).expect("json");
            let result = host(py).and_then(|h| {
                h.call_method1(
                    "load_plugin",
                    (
                        name,
                        m.plugin.as_str(),
                        params,
                        cfg.base_dir.to_string_lossy().into_owned(),
                    ),
                )
            });
            match result {
                Ok(tuple) => {
                    type Loaded = (
                        Py<PyAny>,
                        Vec<String>,
                        Vec<String>,
                        Vec<String>,
                        Vec<(String, String)>,
                    );
                    let (hosted, subscriptions, publishes, optional, required): Loaded =
                        tuple.extract().map_err(|e| {
                            cfg.error_at(&format!("modules.{name}.plugin"), e.to_string())
                        })?;
                    Ok(Box::new(PyPlugin {
                        hosted,
                        subscriptions,
                        publishes,
                        optional,
                        required,
                    }) as Box<dyn Module>)
                }
                Err(e) => {
                    // `_host` raises caviar.ConfigError with the key relative to the module table.
                    let key: Option<String> = e
                        .value(py)
                        .getattr("key")
                        .ok()
                        .and_then(|k| k.extract().ok());
                    let message: String = e
                        .value(py)
                        .getattr("message")
                        .and_then(|m| m.extract())
                        .unwrap_or_else(|_| e.to_string());
                    let key = format!("modules.{name}.{}", key.unwrap_or_else(|| "plugin".into()));
                    Err(cfg.error_at(&key, message))
                }
            }
        })
    }
}

fn config_error(e: impl ToString) -> PyErr {
    errors::ConfigError::new_err((e.to_string(),))
}

/// Raises `caviar.errors.RunError` carrying module, phase and step.
fn run_error(e: &EngineError, run_dir: &std::path::Path) -> PyErr {
    let (module, phase, step) = match e {
        EngineError::Module {
            module,
            phase,
            step,
            ..
        } => (Some(module.clone()), Some(*phase), *step),
        EngineError::Publish { module, step, .. } => {
            (Some(module.clone()), Some("step"), Some(*step))
        }
        EngineError::Interrupted { step } => (None, None, Some(*step)),
        EngineError::Record(_) => (None, None, None),
    };
    errors::RunError::new_err((
        e.to_string(),
        module,
        phase,
        step,
        run_dir.to_string_lossy().into_owned(),
    ))
}

/// An episode driven from Python. `caviar.Simulation` wraps it.
#[pyclass(unsendable, module = "caviar._core")]
struct Episode {
    session: RunSession,
}

#[pymethods]
impl Episode {
    #[new]
    #[pyo3(signature = (path, overrides, out=None))]
    fn new(path: PathBuf, overrides: Vec<String>, out: Option<PathBuf>) -> PyResult<Self> {
        crate::interrupt::reset();
        let cfg = config::load(&path, &overrides).map_err(config_error)?;
        let session = RunSession::start(cfg, &PyLoader, out.as_deref()).map_err(|e| match e {
            PrepareError::Config(c) => config_error(c),
            PrepareError::Io(s) => pyo3::exceptions::PyOSError::new_err(s),
        })?;
        Ok(Episode { session })
    }

    /// Runs one step; returns its messages, or None when the episode is over.
    fn step<'py>(&mut self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyList>>> {
        if self.session.ended().is_some() {
            return Ok(None);
        }
        let session = &mut self.session;
        match py.allow_threads(|| session.step()) {
            Ok(Some(report)) => Ok(Some(raw_messages(py, &report.messages)?)),
            Ok(None) => Ok(None),
            Err(e) => Err(self.finish(py, Err(e))),
        }
    }

    /// Runs to the end. `progress` is called with (steps done, planned or None, wall s)
    /// after every step; Ctrl-C interrupts the run cleanly.
    #[pyo3(signature = (progress=None))]
    fn run(&mut self, py: Python<'_>, progress: Option<Py<PyAny>>) -> PyResult<()> {
        if self.session.ended().is_some() {
            return Ok(());
        }
        let session = &mut self.session;
        let result = py.allow_threads(|| {
            session.run(|e, _| {
                Python::with_gil(|py| {
                    if let Some(cb) = &progress {
                        if cb
                            .call1(py, (e.steps_done(), e.planned_steps(), e.wall_s()))
                            .is_err()
                        {
                            return false;
                        }
                    }
                    py.check_signals().is_ok()
                })
            })
        });
        match result {
            Ok(()) => self.close(py),
            Err(e) => Err(self.finish(py, Err(e))),
        }
    }

    /// Tears down the modules, compacts the recording and writes run.json.
    fn close(&mut self, py: Python<'_>) -> PyResult<()> {
        if self.session.ended().is_some() {
            return Ok(());
        }
        match self.finish_quietly(py, Ok(())) {
            Ok(()) => Ok(()),
            Err(e) => Err(run_error(&e, self.session.engine().run_dir())),
        }
    }

    /// The wiring warnings of the run's modules (a subscription nothing publishes, a
    /// topic nobody reads), as `caviar-core validate` prints them.
    #[getter]
    fn warnings(&self) -> Vec<String> {
        self.session.warnings().to_vec()
    }
    #[getter]
    fn run_dir(&self) -> PathBuf {
        self.session.engine().run_dir().to_path_buf()
    }
    #[getter]
    fn steps_done(&self) -> u64 {
        self.session.engine().steps_done()
    }
    #[getter]
    fn planned_steps(&self) -> Option<u64> {
        self.session.engine().planned_steps()
    }
    #[getter]
    fn ts(&self) -> f64 {
        self.session.engine().ts()
    }
    #[getter]
    fn done(&self) -> bool {
        self.session.ended().is_some() || self.session.engine().is_done()
    }
    #[getter]
    fn wall_s(&self) -> f64 {
        self.session.engine().wall_s()
    }
}

impl Episode {
    /// Ends the session with `result` (run.json written); its error, if any.
    fn finish_quietly(
        &mut self,
        py: Python<'_>,
        result: Result<(), EngineError>,
    ) -> Result<(), EngineError> {
        let session = &mut self.session;
        py.allow_threads(|| session.finish(result))
    }

    /// After a failed step: close what can be closed, write run.json, raise RunError.
    fn finish(&mut self, py: Python<'_>, result: Result<(), EngineError>) -> PyErr {
        match self.finish_quietly(py, result) {
            Err(e) => run_error(&e, self.session.engine().run_dir()),
            Ok(()) => PyRuntimeError::new_err("the run ended without an error"),
        }
    }
}

/// The `caviar-core` command line; returns the exit code.
#[pyfunction]
fn main(py: Python<'_>, argv: Vec<String>) -> i32 {
    py.allow_threads(|| {
        crate::cli::main(argv, &PyLoader, &|| {
            Python::with_gil(|py| py.check_signals().is_err())
        })
    })
}

/// The names of a run directory's files, as the core writes them: `status` (run.json),
/// `progress`, `config`, `checkpoint`.
#[pyfunction]
fn run_dir_files() -> std::collections::HashMap<&'static str, &'static str> {
    std::collections::HashMap::from([
        ("status", crate::status::STATUS_FILE),
        ("progress", crate::status::PROGRESS_FILE),
        ("config", crate::run::CONFIG_FILE),
        ("checkpoint", crate::checkpoint::FILE),
    ])
}

/// The file a recorded table is compacted into when its run ends.
#[pyfunction]
fn compacted_file(table: &str) -> String {
    crate::recorder::compacted_file(table)
}

/// Closes the run.json a dead process left `running` as `failed` with `message`, at the
/// step and module progress.json names; where, in words (None: not running).
#[pyfunction]
fn close_failed_run(run_dir: PathBuf, message: &str) -> PyResult<Option<String>> {
    crate::status::RunStatus::close_failed(&run_dir, message).map_err(PyValueError::new_err)
}

/// run.json of RUN_DIR as JSON text, with what a reader concludes about a run left
/// `running` (`abandoned` when its process is gone, the step and modules it was in).
#[pyfunction]
fn run_status(run_dir: PathBuf) -> PyResult<String> {
    let s = RunStatus::read_live(&run_dir).map_err(pyo3::exceptions::PyValueError::new_err)?;
    let mut v = serde_json::to_value(&s).expect("json");
    if let Some(text) = s.abandoned_text() {
        v["abandoned"] = text.into();
    }
    Ok(v.to_string())
}

/// The text of `caviar-core inspect RUN_DIR`.
#[pyfunction]
fn inspect(run_dir: PathBuf) -> PyResult<String> {
    crate::inspect::inspect(&run_dir).map_err(pyo3::exceptions::PyValueError::new_err)
}

/// The Parquet files holding table `table` (`messages` or `timings`) of RUN_DIR, in
/// order (the compacted file, or the parts of a run in progress); ValueError when
/// RUN_DIR has neither.
#[pyfunction]
fn table_files(run_dir: PathBuf, table: &str) -> PyResult<Vec<PathBuf>> {
    crate::recorder::table_files(&run_dir, table).map_err(|e| PyValueError::new_err(e.to_string()))
}

/// Per-module totals of RUN_DIR's timings as JSON text (a list of objects, the core's
/// row last): what `caviar-core inspect` shows.
#[pyfunction]
fn module_totals(run_dir: PathBuf) -> PyResult<String> {
    let timings = crate::recorder::read_timings(&run_dir)
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    Ok(serde_json::to_string(&crate::inspect::module_totals(&timings)).expect("json"))
}

/// True if `topic` matches `pattern` (`*`: one token, `>`: the rest); ValueError
/// for a pattern that is not valid.
#[pyfunction]
fn matches(pattern: &str, topic: &str) -> PyResult<bool> {
    crate::topic::matches(pattern, topic).map_err(|e| PyValueError::new_err(e.to_string()))
}

/// Resident memory of this process, MiB (NaN where it cannot tell).
#[pyfunction]
fn resident_mib() -> f64 {
    crate::metrics::resident_mib()
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<Episode>()?;
    m.add_class::<RawMessage>()?;
    m.add_function(wrap_pyfunction!(main, m)?)?;
    m.add_function(wrap_pyfunction!(inspect, m)?)?;
    m.add_function(wrap_pyfunction!(run_status, m)?)?;
    m.add_function(wrap_pyfunction!(close_failed_run, m)?)?;
    m.add_function(wrap_pyfunction!(run_dir_files, m)?)?;
    m.add_function(wrap_pyfunction!(compacted_file, m)?)?;
    m.add_function(wrap_pyfunction!(table_files, m)?)?;
    m.add_function(wrap_pyfunction!(module_totals, m)?)?;
    m.add_function(wrap_pyfunction!(matches, m)?)?;
    m.add_function(wrap_pyfunction!(resident_mib, m)?)?;
    crate::transport::register_python(m)?;
    Ok(())
}
