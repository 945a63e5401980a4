//! Messages and their payloads.

use std::sync::Arc;

/// What a message carries. The core never looks inside a payload: JSON stays the
/// text the module wrote, binary data stays bytes (it never goes through JSON).
#[derive(Debug, Clone, PartialEq)]
pub enum Payload {
    /// A JSON document, as text.
    Json(String),
    /// Raw bytes with a small JSON description of what they are, e.g.
    /// `{"dtype": "<c8", "shape": [4, 64]}` for a numpy array.
    Binary { meta: String, data: Vec<u8> },
    /// A file the module wrote into the run directory, passed by its path relative
    /// to the run directory (the paper's "file-based" sharing).
    Artifact(String),
}

impl Payload {
    /// Serialises `value` as a JSON payload.
    pub fn json<T: serde::Serialize>(value: &T) -> Self {
        Payload::Json(serde_json::to_string(value).expect("serialisable value"))
    }

    pub fn kind(&self) -> PayloadKind {
        match self {
            Payload::Json(_) => PayloadKind::Json,
            Payload::Binary { .. } => PayloadKind::Binary,
            Payload::Artifact(_) => PayloadKind::Artifact,
        }
    }

    /// Size in bytes of the payload body.
    pub fn len(&self) -> usize {
        match self {
            Payload::Json(s) | Payload::Artifact(s) => s.len(),
            Payload::Binary { data, .. } => data.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PayloadKind {
    Json,
    Binary,
    Artifact,
}

impl PayloadKind {
    pub fn as_str(self) -> &'static str {
        match self {
            PayloadKind::Json => "json",
            PayloadKind::Binary => "binary",
            PayloadKind::Artifact => "artifact",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "json" => Some(PayloadKind::Json),
            "binary" => Some(PayloadKind::Binary),
            "artifact" => Some(PayloadKind::Artifact),
            _ => None,
        }
    }
}

/// A message as routed and recorded: who published what, when.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    /// Step in which it was published.
    pub step: u64,
    /// Virtual time of that step, in seconds.
    pub time: f64,
    pub topic: String,
    /// Name of the publishing module.
    pub source: String,
    pub payload: Payload,
}

/// Messages are shared between subscribers, the recorder and the caller without copying.
pub type SharedMessage = Arc<Message>;

/// What a module hands back from a step: a topic and a payload.
#[derive(Debug, Clone, PartialEq)]
pub struct Outgoing {
    pub topic: String,
    pub payload: Payload,
}

impl Outgoing {
    pub fn new(topic: impl Into<String>, payload: Payload) -> Self {
        Outgoing {
            topic: topic.into(),
            payload,
        }
    }
}
