//! Messages as they cross between the core and Python ([`RawMessage`] and what a
//! plugin returns), shared by the extension (`python`) and the Python worker's
//! bindings of the transports.

use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyList, PyString};

use crate::message::{Message, Outgoing, Payload};

/// A routed message as it crosses to Python: `caviar.Message` is made of it, and
/// decodes the payload only when asked. `body` is `str` for JSON and artifacts (the
/// JSON text, the artifact's path in the run directory), `bytes` for binary payloads.
#[pyclass(frozen, get_all, module = "caviar._core")]
pub struct RawMessage {
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
pub fn raw_messages<'py, M: std::borrow::Borrow<Message>>(
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
pub fn outgoing_from_python(result: &Bound<'_, PyAny>, out: &mut Vec<Outgoing>) -> PyResult<()> {
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
