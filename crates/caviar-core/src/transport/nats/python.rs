//! The Python worker's side of the NATS transport, for `caviar._core`: the step frames
//! (decode a request, encode a reply or a failure) and the run's authentication, so
//! that `caviar.worker` does not write either a second time.

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyList};

use super::auth;
use super::wire::{self, WireError};
use crate::module::Usage;
use crate::py_messages::{outgoing_from_python, raw_messages};

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
struct Guard(std::sync::Mutex<auth::Guard>);

#[pymethods]
impl Guard {
    /// `key`: 64 hex digits; `None` reads CAVIAR_RUN_KEY or CAVIAR_RUN_KEY_FILE.
    #[new]
    #[pyo3(signature = (run, key=None))]
    fn new(run: &str, key: Option<&str>) -> PyResult<Self> {
        use auth::RunKey;
        let key = match key {
            Some(k) => RunKey::from_hex(k),
            None => RunKey::from_env(),
        }
        .map_err(PyValueError::new_err)?;
        Ok(Guard(std::sync::Mutex::new(auth::Guard::new(key, run))))
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

    /// A resumed run: the next step is `next_step` (the first on the schedule from it).
    fn resume_at(&self, next_step: u64) {
        self.0.lock().unwrap().resume_at(next_step);
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
    let k = auth::RunKey::from_hex(key).map_err(PyValueError::new_err)?;
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
    let k = auth::RunKey::from_hex(key).map_err(PyValueError::new_err)?;
    let (seq, body) = k.open(run, subject, frame).map_err(PyValueError::new_err)?;
    Ok((seq, PyBytes::new(py, body)))
}

/// Adds the worker's bindings to the extension module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("PROTOCOL", wire::PROTOCOL)?;
    m.add_class::<StepRequest>()?;
    m.add_function(wrap_pyfunction!(decode_request, m)?)?;
    m.add_function(wrap_pyfunction!(encode_reply, m)?)?;
    m.add_function(wrap_pyfunction!(encode_failure, m)?)?;
    m.add_class::<Guard>()?;
    m.add_function(wrap_pyfunction!(sign, m)?)?;
    m.add_function(wrap_pyfunction!(verify, m)?)?;
    Ok(())
}
