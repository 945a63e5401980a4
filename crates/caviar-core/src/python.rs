//! The `caviar._core` extension: hosts Python plugins in-process and exposes the
//! engine to Python. The Python side of the bridge is `caviar/_host.py`; this file
//! moves messages across ([`RawMessage`]), turns Python exceptions into module errors
//! and exposes the core's topic matching and NATS wire format, so that Python does
//! not write them a second time. `caviar/_core.pyi` describes all of it.

use std::path::PathBuf;

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyList, PyString};

use crate::assembly::PrepareError;
use crate::config::{self, ConfigError, LoadedConfig};
use crate::engine::{Engine, EngineError};
use crate::message::{Message, Outgoing, Payload, SharedMessage};
use crate::module::{Module, ModuleError, ResourceProbe, SetupContext, StepInfo, Usage};
use crate::run::{prepare_monitored, PluginLoader};
use crate::status::{write_status, Monitor, RunState, RunStatus};
use crate::transport::nats::wire::{self, WireError};
use crate::transport::nats::WorkerLauncher;

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
}

impl Module for PyPlugin {
    fn default_subscriptions(&self) -> Vec<String> {
        self.subscriptions.clone()
    }

    fn publishes(&self) -> Option<Vec<String>> {
        (!self.publishes.is_empty()).then(|| self.publishes.clone())
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

    fn concurrent(&self) -> bool {
        false
    }
}

/// A routed message as it crosses to Python: `caviar.Message` is made of it, and
/// decodes the payload only when asked. `body` is `str` for JSON and artifacts (the
/// JSON text, the artifact's path in the run directory), `bytes` for binary payloads.
#[pyclass(frozen, get_all, module = "caviar._core")]
struct RawMessage {
    step: u64,
    time: f64,
    topic: String,
    source: String,
    kind: String,
    body: Py<PyAny>,
    meta: Option<String>,
}

#[pymethods]
impl RawMessage {
    #[new]
    #[pyo3(signature = (step, time, topic, source, kind, body, meta=None))]
    fn new(
        step: u64,
        time: f64,
        topic: String,
        source: String,
        kind: String,
        body: Py<PyAny>,
        meta: Option<String>,
    ) -> Self {
        RawMessage {
            step,
            time,
            topic,
            source,
            kind,
            body,
            meta,
        }
    }

    fn __repr__(&self) -> String {
        format!(
            "RawMessage(step={}, topic={:?}, source={:?}, kind={:?})",
            self.step, self.topic, self.source, self.kind
        )
    }
}

fn raw_message(py: Python<'_>, m: &Message) -> PyResult<RawMessage> {
    let (body, meta): (Py<PyAny>, Option<&str>) = match &m.payload {
        Payload::Json(text) | Payload::Artifact(text) => {
            (PyString::new(py, text).into_any().unbind(), None)
        }
        Payload::Binary { meta, data } => (
            PyBytes::new(py, data).into_any().unbind(),
            Some(meta.as_str()),
        ),
    };
    Ok(RawMessage {
        step: m.step,
        time: m.time,
        topic: m.topic.clone(),
        source: m.source.clone(),
        kind: m.payload.kind().as_str().into(),
        body,
        meta: meta.map(String::from),
    })
}

/// Messages as a list of [`RawMessage`].
fn raw_messages<'py, M: std::borrow::Borrow<Message>>(
    py: Python<'py>,
    messages: &[M],
) -> PyResult<Bound<'py, PyList>> {
    let items = messages
        .iter()
        .map(|m| raw_message(py, m.borrow()))
        .collect::<PyResult<Vec<_>>>()?;
    PyList::new(py, items)
}

/// `_host` normalises a plugin's return value to a list of `(topic, kind, body, meta)`.
fn outgoing_from_python(result: &Bound<'_, PyAny>, out: &mut Vec<Outgoing>) -> PyResult<()> {
    for item in result.try_iter()? {
        let (topic, kind, body, meta): (String, String, Bound<'_, PyAny>, Option<String>) =
            item?.extract()?;
        let payload = match kind.as_str() {
            "json" => Payload::Json(body.extract()?),
            "artifact" => Payload::Artifact(body.extract()?),
            "binary" => Payload::Binary {
                meta: meta.unwrap_or_else(|| "{}".into()),
                data: match body.downcast::<PyBytes>() {
                    Ok(b) => b.as_bytes().to_vec(),
                    Err(_) => body.extract::<Vec<u8>>()?,
                },
            },
            other => {
                return Err(PyRuntimeError::new_err(format!(
                    "unknown payload kind '{other}' from caviar._host"
                )))
            }
        };
        out.push(Outgoing { topic, payload });
    }
    Ok(())
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
                    let (hosted, subscriptions, publishes): (Py<PyAny>, Vec<String>, Vec<String>) =
                        tuple.extract().map_err(|e| {
                            cfg.error_at(&format!("modules.{name}.plugin"), e.to_string())
                        })?;
                    Ok(Box::new(PyPlugin {
                        hosted,
                        subscriptions,
                        publishes,
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
    cfg: LoadedConfig,
    engine: Engine,
    monitor: Monitor,
    closed: bool,
}

#[pymethods]
impl Episode {
    #[new]
    #[pyo3(signature = (path, overrides, out=None))]
    fn new(path: PathBuf, overrides: Vec<String>, out: Option<PathBuf>) -> PyResult<Self> {
        crate::interrupt::reset();
        let cfg = config::load(&path, &overrides).map_err(config_error)?;
        let (engine, monitor) =
            prepare_monitored(&cfg, &PyLoader, out.as_deref()).map_err(|e| match e {
                PrepareError::Config(c) => config_error(c),
                PrepareError::Io(s) => pyo3::exceptions::PyOSError::new_err(s),
            })?;
        Ok(Episode {
            cfg,
            engine,
            monitor,
            closed: false,
        })
    }

    /// Runs one step; returns its messages, or None when the episode is over.
    fn step<'py>(&mut self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyList>>> {
        if self.closed {
            return Ok(None);
        }
        let engine = &mut self.engine;
        match py.allow_threads(|| engine.step()) {
            Ok(Some(report)) => {
                self.monitor.after_step(&self.cfg, &self.engine);
                Ok(Some(raw_messages(py, &report.messages)?))
            }
            Ok(None) => Ok(None),
            Err(e) => Err(self.fail(py, e)),
        }
    }

    /// Runs to the end. `progress` is called with (steps done, planned or None, wall s)
    /// after every step; Ctrl-C interrupts the run cleanly.
    #[pyo3(signature = (progress=None))]
    fn run(&mut self, py: Python<'_>, progress: Option<Py<PyAny>>) -> PyResult<()> {
        if self.closed {
            return Ok(());
        }
        let (engine, monitor, cfg) = (&mut self.engine, &mut self.monitor, &self.cfg);
        let result = py.allow_threads(|| {
            engine.run(|e, _| {
                monitor.after_step(cfg, e);
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
            Err(e) => Err(self.fail(py, e)),
        }
    }

    /// Tears down the modules, compacts the recording and writes run.json.
    fn close(&mut self, py: Python<'_>) -> PyResult<()> {
        if self.closed {
            return Ok(());
        }
        self.closed = true;
        let engine = &mut self.engine;
        match py.allow_threads(|| engine.close()) {
            Ok(()) => {
                write_status(&self.cfg, &self.engine, RunState::Completed, None)
                    .map_err(PyRuntimeError::new_err)?;
                Ok(())
            }
            Err(e) => {
                let _ = write_status(&self.cfg, &self.engine, RunState::Failed, Some(&e));
                Err(run_error(&e, self.engine.run_dir()))
            }
        }
    }

    #[getter]
    fn run_dir(&self) -> PathBuf {
        self.engine.run_dir().to_path_buf()
    }
    #[getter]
    fn steps_done(&self) -> u64 {
        self.engine.steps_done()
    }
    #[getter]
    fn planned_steps(&self) -> Option<u64> {
        self.engine.planned_steps()
    }
    #[getter]
    fn ts(&self) -> f64 {
        self.engine.ts()
    }
    #[getter]
    fn done(&self) -> bool {
        self.closed || self.engine.is_done()
    }
    #[getter]
    fn wall_s(&self) -> f64 {
        self.engine.wall_s()
    }
}

/// An episode dropped without `close()` (`del sim`) is closed here, so that run.json
/// does not stay `running`.
impl Drop for Episode {
    fn drop(&mut self) {
        if self.closed {
            return;
        }
        self.closed = true;
        match self.engine.close() {
            Ok(()) => {
                let _ = write_status(&self.cfg, &self.engine, RunState::Completed, None);
            }
            Err(e) => {
                let _ = write_status(&self.cfg, &self.engine, RunState::Failed, Some(&e));
            }
        }
    }
}

impl Episode {
    /// After a failed step: close what can be closed, write run.json, raise RunError.
    fn fail(&mut self, py: Python<'_>, e: EngineError) -> PyErr {
        self.closed = true;
        let engine = &mut self.engine;
        let _ = py.allow_threads(|| engine.close());
        let status = if matches!(e, EngineError::Interrupted { .. }) {
            RunState::Interrupted
        } else {
            RunState::Failed
        };
        let _ = write_status(&self.cfg, &self.engine, status, Some(&e));
        run_error(&e, self.engine.run_dir())
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
    crate::cli::inspect(&run_dir).map_err(pyo3::exceptions::PyValueError::new_err)
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

/// A step request of the NATS protocol, decoded.
#[pyclass(frozen, get_all, module = "caviar._core")]
struct StepRequest {
    protocol: u32,
    step: u64,
    time: f64,
    shard: u64,
    shards: u64,
    messages: Py<PyList>,
}

/// Decodes a step request frame; ValueError if it is malformed or of another protocol.
#[pyfunction]
fn decode_request(py: Python<'_>, frame: &[u8]) -> PyResult<StepRequest> {
    let (req, inbox) = wire::decode_request(frame).map_err(PyValueError::new_err)?;
    Ok(StepRequest {
        protocol: req.protocol,
        step: req.step,
        time: req.time,
        shard: req.shard,
        shards: req.shards,
        messages: raw_messages(py, &inbox)?.unbind(),
    })
}

/// Encodes a successful step reply: the step's messages as `_host` returns them and
/// what the step cost.
#[pyfunction]
#[pyo3(signature = (out, wall_s, cpu_s, rss_mib=None, gpu=None))]
fn encode_reply<'py>(
    py: Python<'py>,
    out: &Bound<'py, PyAny>,
    wall_s: f64,
    cpu_s: f64,
    rss_mib: Option<f64>,
    gpu: Option<(f64, f64)>,
) -> PyResult<Bound<'py, PyBytes>> {
    let mut messages = Vec::new();
    outgoing_from_python(out, &mut messages)?;
    let usage = Usage {
        wall_s,
        cpu_s,
        rss_mib: rss_mib.unwrap_or(f64::NAN),
        gpu_util_pct: gpu.map(|g| g.0),
        gpu_mem_mib: gpu.map(|g| g.1),
    };
    Ok(PyBytes::new(py, &wire::encode_reply(&messages, usage)))
}

/// Encodes a failed step reply.
#[pyfunction]
#[pyo3(signature = (message, trace=None, key=None))]
fn encode_failure(
    py: Python<'_>,
    message: String,
    trace: Option<String>,
    key: Option<String>,
) -> Bound<'_, PyBytes> {
    let error = WireError {
        message,
        trace,
        key,
    };
    PyBytes::new(py, &wire::encode_failure(&error))
}

/// A worker's side of the run's authentication (transport/nats/auth.rs): the run
/// key, the core's sequence numbers seen, the worker's own counter and its step
/// schedule. Thread-safe (the heartbeat thread seals too).
#[pyclass(frozen, module = "caviar._core")]
struct Guard(std::sync::Mutex<crate::transport::nats::auth::Guard>);

#[pymethods]
impl Guard {
    /// `key`: 64 hex digits; `None` reads CAVIAR_RUN_KEY or CAVIAR_RUN_KEY_FILE.
    #[new]
    #[pyo3(signature = (run, key=None))]
    fn new(run: &str, key: Option<&str>) -> PyResult<Self> {
        use crate::transport::nats::auth::RunKey;
        let key = match key {
            Some(k) => RunKey::from_hex(k),
            None => RunKey::from_env(),
        }
        .map_err(PyValueError::new_err)?;
        Ok(Guard(std::sync::Mutex::new(
            crate::transport::nats::auth::Guard::new(key, run),
        )))
    }

    /// `body` sealed for `subject` with this worker's next sequence number.
    fn seal<'py>(&self, py: Python<'py>, subject: &str, body: &[u8]) -> Bound<'py, PyBytes> {
        PyBytes::new(py, &self.0.lock().unwrap().seal(subject, body.to_vec()))
    }

    /// The body of a frame of the core received on `subject`; ValueError (counted) if it
    /// fails authentication or repeats a sequence number.
    fn open<'py>(
        &self,
        py: Python<'py>,
        subject: &str,
        frame: &[u8],
    ) -> PyResult<Bound<'py, PyBytes>> {
        let mut g = self.0.lock().unwrap();
        let body = g.open(subject, frame).map_err(PyValueError::new_err)?;
        Ok(PyBytes::new(py, body))
    }

    /// The module's schedule, from its setup.
    fn schedule(&self, every: u64, offset: u64, steps: Option<u64>, shards: u64, exclusive: bool) {
        self.0
            .lock()
            .unwrap()
            .schedule(every, offset, steps, shards, exclusive);
    }

    /// Accepts a step, or ValueError (counted) when it is out of sequence.
    fn accept_step(&self, step: u64, shard: u64) -> PyResult<()> {
        self.0
            .lock()
            .unwrap()
            .accept_step(step, shard)
            .map_err(PyValueError::new_err)
    }

    /// Counts a refusal decided by the worker (a teardown without a reply subject).
    fn refuse(&self) {
        self.0.lock().unwrap().refuse();
    }

    /// Core frames refused so far.
    #[getter]
    fn rejected(&self) -> u64 {
        self.0.lock().unwrap().rejected
    }
}

/// `body` sealed with the run key `key` (hex) for `subject` of run `run`, sequence `seq`.
#[pyfunction]
fn sign<'py>(
    py: Python<'py>,
    key: &str,
    run: &str,
    subject: &str,
    seq: u64,
    body: &[u8],
) -> PyResult<Bound<'py, PyBytes>> {
    let k = crate::transport::nats::auth::RunKey::from_hex(key).map_err(PyValueError::new_err)?;
    Ok(PyBytes::new(py, &k.seal(run, subject, seq, body.to_vec())))
}

/// `(seq, body)` of a sealed frame, or ValueError when it fails authentication.
#[pyfunction]
fn verify<'py>(
    py: Python<'py>,
    key: &str,
    run: &str,
    subject: &str,
    frame: &[u8],
) -> PyResult<(u64, Bound<'py, PyBytes>)> {
    let k = crate::transport::nats::auth::RunKey::from_hex(key).map_err(PyValueError::new_err)?;
    let (seq, body) = k.open(run, subject, frame).map_err(PyValueError::new_err)?;
    Ok((seq, PyBytes::new(py, body)))
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("PROTOCOL", wire::PROTOCOL)?;
    m.add_class::<Episode>()?;
    m.add_class::<RawMessage>()?;
    m.add_class::<StepRequest>()?;
    m.add_function(wrap_pyfunction!(main, m)?)?;
    m.add_function(wrap_pyfunction!(inspect, m)?)?;
    m.add_function(wrap_pyfunction!(run_status, m)?)?;
    m.add_function(wrap_pyfunction!(matches, m)?)?;
    m.add_function(wrap_pyfunction!(resident_mib, m)?)?;
    m.add_function(wrap_pyfunction!(decode_request, m)?)?;
    m.add_function(wrap_pyfunction!(encode_reply, m)?)?;
    m.add_function(wrap_pyfunction!(encode_failure, m)?)?;
    m.add_class::<Guard>()?;
    m.add_function(wrap_pyfunction!(sign, m)?)?;
    m.add_function(wrap_pyfunction!(verify, m)?)?;
    Ok(())
}
