//! The bytes of a step on the wire (protocol version [`PROTOCOL`], docs/nats-protocol.md).
//!
//! A step request and its reply are one *frame*: a 4-byte little-endian length, a
//! JSON header of that length, then the message bodies back to back in header order.
//! Bodies stay bytes (an image never becomes base64) and any language can read the
//! header with its JSON library.

use serde::{Deserialize, Serialize};

use crate::message::{Message, Outgoing, Payload, PayloadKind};
use crate::module::{ModuleError, StepInfo, Usage};

pub const PROTOCOL: u32 = 2;

/// Header naming the source module on mirrored messages (and marking them as ours).
pub const MIRROR_SOURCE_HEADER: &str = "Caviar-Source";

/// One message in a frame header; its body is the next `len` bytes of the frame.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct WireMessage {
    pub topic: String,
    /// `json`, `binary` or `artifact`.
    pub kind: String,
    pub len: usize,
    /// Description of a binary body (dtype, shape, …), JSON text.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub meta: Option<String>,
    /// Publishing module, step and virtual time (requests only: replies are this step's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StepRequest {
    pub protocol: u32,
    pub step: u64,
    pub time: f64,
    pub shard: u64,
    pub shards: u64,
    pub messages: Vec<WireMessage>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct WireError {
    pub message: String,
    #[serde(default)]
    pub trace: Option<String>,
    /// For configuration errors: the key under `modules.NAME.`.
    #[serde(default)]
    pub key: Option<String>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StepReply {
    pub ok: bool,
    #[serde(default)]
    pub messages: Vec<WireMessage>,
    #[serde(default)]
    pub wall_s: f64,
    #[serde(default)]
    pub cpu_s: f64,
    /// Resident memory of the worker process, MiB (absent when it cannot tell).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rss_mib: Option<f64>,
    /// GPU utilisation (%) and the worker process's GPU memory (MiB), where it has a GPU.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gpu_util_pct: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gpu_mem_mib: Option<f64>,
    #[serde(default)]
    pub error: Option<WireError>,
}

fn body(p: &Payload) -> (&[u8], Option<&str>) {
    match p {
        Payload::Json(t) | Payload::Artifact(t) => (t.as_bytes(), None),
        Payload::Binary { meta, data } => (data, Some(meta)),
    }
}

fn frame<H: Serialize>(header: &H, bodies: &[&[u8]]) -> Vec<u8> {
    let head = serde_json::to_vec(header).expect("serialisable header");
    let mut buf =
        Vec::with_capacity(4 + head.len() + bodies.iter().map(|b| b.len()).sum::<usize>());
    buf.extend_from_slice(&(head.len() as u32).to_le_bytes());
    buf.extend_from_slice(&head);
    for b in bodies {
        buf.extend_from_slice(b);
    }
    buf
}

/// Splits a frame into its header and the bytes after it.
pub fn split_frame<'a, H: Deserialize<'a>>(buf: &'a [u8]) -> Result<(H, &'a [u8]), String> {
    if buf.len() < 4 {
        return Err(format!(
            "frame of {} bytes is shorter than its length prefix",
            buf.len()
        ));
    }
    let n = u32::from_le_bytes(buf[..4].try_into().expect("4 bytes")) as usize;
    let head = buf.get(4..4 + n).ok_or_else(|| {
        format!(
            "frame header of {n} bytes overruns a frame of {}",
            buf.len()
        )
    })?;
    let header = serde_json::from_slice(head).map_err(|e| format!("frame header: {e}"))?;
    Ok((header, &buf[4 + n..]))
}

pub fn encode_request(
    at: StepInfo,
    shard: u64,
    shards: u64,
    inbox: &[impl AsRef<Message>],
) -> Vec<u8> {
    let mut messages = Vec::with_capacity(inbox.len());
    let mut bodies = Vec::with_capacity(inbox.len());
    for m in inbox {
        let m = m.as_ref();
        let (b, meta) = body(&m.payload);
        messages.push(WireMessage {
            topic: m.topic.clone(),
            kind: m.payload.kind().as_str().into(),
            len: b.len(),
            meta: meta.map(str::to_string),
            source: Some(m.source.clone()),
            step: Some(m.step),
            time: Some(m.time),
        });
        bodies.push(b);
    }
    let header = StepRequest {
        protocol: PROTOCOL,
        step: at.step,
        time: at.time,
        shard,
        shards,
        messages,
    };
    frame(&header, &bodies)
}

pub fn encode_reply(out: &[Outgoing], usage: Usage) -> Vec<u8> {
    let mut messages = Vec::with_capacity(out.len());
    let mut bodies = Vec::with_capacity(out.len());
    for o in out {
        let (b, meta) = body(&o.payload);
        messages.push(WireMessage {
            topic: o.topic.clone(),
            kind: o.payload.kind().as_str().into(),
            len: b.len(),
            meta: meta.map(str::to_string),
            source: None,
            step: None,
            time: None,
        });
        bodies.push(b);
    }
    let header = StepReply {
        ok: true,
        messages,
        wall_s: usage.wall_s,
        cpu_s: usage.cpu_s,
        rss_mib: usage.rss_mib.is_finite().then_some(usage.rss_mib),
        gpu_util_pct: usage.gpu_util_pct,
        gpu_mem_mib: usage.gpu_mem_mib,
        error: None,
    };
    frame(&header, &bodies)
}

/// A failed step reply: the error and no messages.
pub fn encode_failure(error: &WireError) -> Vec<u8> {
    frame(&serde_json::json!({"ok": false, "error": error}), &[])
}

/// Reads the messages of a frame whose header was already parsed.
fn payloads(
    messages: Vec<WireMessage>,
    mut rest: &[u8],
) -> Result<Vec<(WireMessage, Payload)>, String> {
    let mut out = Vec::with_capacity(messages.len());
    for m in messages {
        if rest.len() < m.len {
            return Err(format!(
                "message on '{}' declares {} bytes, {} are left in the frame",
                m.topic,
                m.len,
                rest.len()
            ));
        }
        let (b, tail) = rest.split_at(m.len);
        rest = tail;
        let text = || {
            String::from_utf8(b.to_vec())
                .map_err(|_| format!("{} body on '{}' is not UTF-8", m.kind, m.topic))
        };
        let payload = match PayloadKind::parse(&m.kind) {
            Some(PayloadKind::Json) => Payload::Json(text()?),
            Some(PayloadKind::Artifact) => Payload::Artifact(text()?),
            Some(PayloadKind::Binary) => Payload::Binary {
                meta: m.meta.clone().unwrap_or_else(|| "{}".into()),
                data: b.to_vec(),
            },
            None => {
                return Err(format!(
                    "unknown payload kind '{}' on '{}'",
                    m.kind, m.topic
                ))
            }
        };
        out.push((m, payload));
    }
    if !rest.is_empty() {
        return Err(format!(
            "{} bytes after the last message of the frame",
            rest.len()
        ));
    }
    Ok(out)
}

/// The module error of a failed reply (setup, step or teardown).
pub fn failure(error: Option<WireError>) -> ModuleError {
    match error {
        Some(e) => ModuleError {
            message: e.message,
            trace: e.trace,
            bad_input: false,
        },
        None => ModuleError::new("the worker reported a failure without details"),
    }
}

/// Decodes a step reply into the module's outgoing messages and what the step cost.
pub fn decode_reply(buf: &[u8], out: &mut Vec<Outgoing>) -> Result<Usage, ModuleError> {
    let (reply, rest): (StepReply, _) =
        split_frame(buf).map_err(|e| ModuleError::new(format!("bad step reply: {e}")))?;
    if !reply.ok {
        return Err(failure(reply.error));
    }
    let usage = Usage {
        wall_s: reply.wall_s,
        cpu_s: reply.cpu_s,
        rss_mib: reply.rss_mib.unwrap_or(f64::NAN),
        gpu_util_pct: reply.gpu_util_pct,
        gpu_mem_mib: reply.gpu_mem_mib,
    };
    for (m, payload) in payloads(reply.messages, rest)
        .map_err(|e| ModuleError::new(format!("bad step reply: {e}")))?
    {
        out.push(Outgoing {
            topic: m.topic,
            payload,
        });
    }
    Ok(usage)
}

/// Decodes a step request (what a worker does; used by Rust workers and tests).
pub fn decode_request(buf: &[u8]) -> Result<(StepRequest, Vec<Message>), String> {
    let (mut req, rest): (StepRequest, _) = split_frame(buf)?;
    if req.protocol != PROTOCOL {
        return Err(format!(
            "protocol {} requested, this side speaks {PROTOCOL}",
            req.protocol
        ));
    }
    let messages = std::mem::take(&mut req.messages);
    let inbox = payloads(messages, rest)?
        .into_iter()
        .map(|(m, payload)| Message {
            step: m.step.unwrap_or(req.step),
            time: m.time.unwrap_or(req.time),
            topic: m.topic,
            source: m.source.unwrap_or_default(),
            payload,
        })
        .collect();
    Ok((req, inbox))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn request_and_reply_round_trip_every_payload_kind() {
        let inbox = vec![
            Message {
                step: 3,
                time: 0.3,
                topic: "a.b".into(),
                source: "m".into(),
                payload: Payload::Json("{\"x\":1}".into()),
            },
            Message {
                step: 3,
                time: 0.3,
                topic: "img".into(),
                source: "cam".into(),
                payload: Payload::Binary {
                    meta: "{\"shape\":[2]}".into(),
                    data: vec![0, 255],
                },
            },
            Message {
                step: 2,
                time: 0.2,
                topic: "f".into(),
                source: "m".into(),
                payload: Payload::Artifact("x.png".into()),
            },
        ];
        let at = StepInfo { step: 4, time: 0.4 };
        let shared: Vec<std::sync::Arc<Message>> =
            inbox.iter().cloned().map(std::sync::Arc::new).collect();
        let (req, back) = decode_request(&encode_request(at, 1, 3, &shared)).unwrap();
        assert_eq!((req.step, req.shard, req.shards), (4, 1, 3));
        assert_eq!(back, inbox);

        let out: Vec<Outgoing> = inbox
            .iter()
            .map(|m| Outgoing::new(m.topic.clone(), m.payload.clone()))
            .collect();
        let usage = Usage {
            wall_s: 0.5,
            cpu_s: 0.25,
            rss_mib: 100.0,
            gpu_util_pct: Some(40.0),
            gpu_mem_mib: Some(1024.0),
        };
        let mut got = Vec::new();
        assert_eq!(
            decode_reply(&encode_reply(&out, usage), &mut got).unwrap(),
            usage
        );
        assert_eq!(got, out);
    }

    #[test]
    fn truncated_and_failed_replies_are_errors_that_say_why() {
        let out = vec![Outgoing::new("t", Payload::Json("[1,2,3]".into()))];
        let buf = encode_reply(
            &out,
            Usage {
                wall_s: 0.0,
                cpu_s: 0.0,
                rss_mib: 0.0,
                gpu_util_pct: None,
                gpu_mem_mib: None,
            },
        );
        let err = decode_reply(&buf[..buf.len() - 2], &mut Vec::new()).unwrap_err();
        assert!(
            err.message.contains("declares 7 bytes, 5 are left"),
            "{}",
            err.message
        );
        let failed = encode_failure(&WireError {
            message: "ValueError: boom".into(),
            trace: Some("tb".into()),
            key: None,
        });
        let err = decode_reply(&failed, &mut Vec::new()).unwrap_err();
        assert_eq!(
            (err.message.as_str(), err.trace.as_deref()),
            ("ValueError: boom", Some("tb"))
        );
    }
}
