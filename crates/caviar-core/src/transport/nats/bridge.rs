//! `caviar.nats-bridge`: brings messages from plain NATS clients into the episode.
//!
//! A module written for the original CAVIAR publishes JSON on the paper's subjects
//! (`communications.throughput`, …) whenever it likes. The bridge subscribes to those
//! subjects and, at each of its steps, publishes into the episode what arrived since
//! its previous step, in arrival order. With `wait_for = N` it first waits for N
//! messages, which keeps a module that answers every input in lockstep with the run.

use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use futures_util::StreamExt;

use super::link::Link;
use super::wire::MIRROR_SOURCE_HEADER;
use crate::config::{ConfigError, LoadedConfig};
use crate::message::{Outgoing, Payload, SharedMessage};
use crate::module::{Module, ModuleError, StepInfo};
use crate::topic::{validate_topic, Pattern};

#[derive(Default)]
struct Arrivals {
    messages: Mutex<Vec<(String, bytes::Bytes)>>,
    arrived: Condvar,
}

pub struct Bridge {
    subjects: Vec<String>,
    wait_for: usize,
    timeout: Duration,
    arrivals: Arc<Arrivals>,
    _link: Arc<Link>,
}

impl Bridge {
    pub fn from_config(
        cfg: &LoadedConfig,
        name: &str,
        link: Arc<Link>,
    ) -> Result<Self, ConfigError> {
        let params = cfg.params_json(name);
        let key = |k: &str| format!("modules.{name}.params.{k}");
        let table = params.as_object().cloned().unwrap_or_default();
        for k in table.keys() {
            if !["subjects", "wait_for", "timeout"].contains(&k.as_str()) {
                return Err(cfg.error_at(
                    &key(k),
                    "unknown parameter of caviar.nats-bridge, expected subjects, wait_for, timeout",
                ));
            }
        }
        let subjects: Vec<String> = table
            .get("subjects")
            .and_then(|v| serde_json::from_value(v.clone()).ok())
            .ok_or_else(|| {
                cfg.error_at(
                    &key("subjects"),
                    "expected a list of NATS subjects, e.g. [\"communications.throughput\"]",
                )
            })?;
        for s in &subjects {
            Pattern::new(s).map_err(|e| cfg.error_at(&key("subjects"), e.to_string()))?;
        }
        let wait_for = match table.get("wait_for") {
            None => 0,
            Some(v) => v.as_u64().ok_or_else(|| {
                cfg.error_at(&key("wait_for"), "expected a number of messages >= 0")
            })? as usize,
        };
        let timeout = match table.get("timeout") {
            None => 10.0,
            Some(v) => v
                .as_f64()
                .filter(|t| *t > 0.0)
                .ok_or_else(|| cfg.error_at(&key("timeout"), "expected seconds > 0"))?,
        };
        let arrivals = Arc::new(Arrivals::default());
        for subject in &subjects {
            let mut sub = link
                .conn
                .rt
                .block_on(link.conn.client.subscribe(subject.clone()))
                .map_err(|e| {
                    cfg.error_at(
                        &key("subjects"),
                        format!("cannot subscribe to '{subject}': {e}"),
                    )
                })?;
            let a = arrivals.clone();
            link.conn.rt.spawn(async move {
                while let Some(m) = sub.next().await {
                    // Our own mirror of episode messages would come straight back.
                    if m.headers
                        .as_ref()
                        .is_some_and(|h| h.get(MIRROR_SOURCE_HEADER).is_some())
                    {
                        continue;
                    }
                    a.messages
                        .lock()
                        .unwrap()
                        .push((m.subject.to_string(), m.payload));
                    a.arrived.notify_all();
                }
            });
        }
        link.conn
            .rt
            .block_on(link.conn.client.flush())
            .map_err(|e| cfg.error_at(&key("subjects"), e.to_string()))?;
        Ok(Bridge {
            subjects,
            wait_for,
            timeout: Duration::from_secs_f64(timeout),
            arrivals,
            _link: link,
        })
    }
}

impl Module for Bridge {
    fn publishes(&self) -> Option<Vec<String>> {
        Some(self.subjects.clone())
    }

    fn step(
        &mut self,
        _at: StepInfo,
        _inbox: &[SharedMessage],
        out: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        let deadline = Instant::now() + self.timeout;
        let mut got = self.arrivals.messages.lock().unwrap();
        while got.len() < self.wait_for {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(ModuleError::new(format!(
                    "expected {} message(s) on {:?} within {:.1} s, got {}",
                    self.wait_for,
                    self.subjects,
                    self.timeout.as_secs_f64(),
                    got.len()
                )));
            }
            got = self.arrivals.arrived.wait_timeout(got, left).unwrap().0;
        }
        for (subject, body) in got.drain(..) {
            validate_topic(&subject).map_err(|e| ModuleError::new(e.to_string()))?;
            // JSON stays JSON (the paper's modules speak JSON); anything else is bytes.
            let payload = match std::str::from_utf8(&body) {
                Ok(text) if serde_json::from_str::<serde_json::Value>(text).is_ok() => {
                    Payload::Json(text.to_string())
                }
                _ => Payload::Binary {
                    meta: "{}".into(),
                    data: body.to_vec(),
                },
            };
            out.push(Outgoing {
                topic: subject,
                payload,
            });
        }
        Ok(())
    }
}
