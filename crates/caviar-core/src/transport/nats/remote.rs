//! A module that runs in a worker process: the core's side of the step protocol.

use std::sync::Arc;
use std::time::Duration;

use async_nats::client::RequestErrorKind;
use serde::Deserialize;

use super::control::LoadedPlugin;
use super::link::Link;
use super::wire::{self, WireError};
use crate::message::{Outgoing, SharedMessage};
use crate::module::{ModuleError, ModuleState, RemoteModule, SetupContext, StepInfo, Usage};

/// A remote module whose workers are connected with the plugin loaded.
pub(crate) struct Ready {
    /// The plugin's default subscriptions and what it declares publishing.
    pub plugin: LoadedPlugin,
    /// Ids of its workers.
    pub workers: Vec<String>,
}

type Pending = tokio::task::JoinHandle<Result<async_nats::Message, async_nats::RequestError>>;

pub(crate) struct WorkerModule {
    link: Arc<Link>,
    name: String,
    plugin: LoadedPlugin,
    /// Ids of the workers set up for this module.
    workers: Vec<String>,
    shards: u64,
    pending: Vec<Pending>,
    at: Option<StepInfo>,
    /// A step of it was given up (past its deadline, Ctrl-C): its workers are busy
    /// with it and cannot tear down; they are killed at once.
    stuck: bool,
    /// A state to restore, sent with the resume request.
    restored: Option<Vec<u8>>,
}

#[derive(Deserialize)]
struct Ack {
    ok: bool,
    #[serde(default)]
    error: Option<WireError>,
    /// Core frames the worker refused (in its teardown answer).
    #[serde(default)]
    rejected: Option<u64>,
}

impl WorkerModule {
    pub fn new(link: Arc<Link>, name: &str, ready: Ready, shards: u64) -> Self {
        WorkerModule {
            link,
            name: name.into(),
            plugin: ready.plugin,
            workers: ready.workers,
            shards,
            pending: Vec::new(),
            at: None,
            stuck: false,
            restored: None,
        }
    }

    fn subject(&self, leaf: &str) -> String {
        format!("{}.{}.{leaf}", self.link.conn.prefix, self.name)
    }

    /// Sends `payload` sealed with the run key (the sequence number is taken now).
    fn request(&self, subject: String, payload: Vec<u8>) -> Pending {
        let payload = self.link.conn.seal(&subject, payload);
        let client = self.link.conn.client.clone();
        self.link.conn.rt.spawn(async move {
            client
                .send_request(
                    subject,
                    async_nats::Request::new()
                        .payload(payload.into())
                        .timeout(None),
                )
                .await
        })
    }

    /// Sends a control request (setup, teardown, resume) to every worker and checks each
    /// answer.
    fn control(
        &self,
        leaf: &str,
        body: &serde_json::Value,
        timeout: Duration,
    ) -> Result<(), ModuleError> {
        self.control_replies(leaf, body, timeout).map(drop)
    }

    /// As [`Self::control`], returning each worker's answer (JSON).
    fn control_replies(
        &self,
        leaf: &str,
        body: &serde_json::Value,
        timeout: Duration,
    ) -> Result<Vec<serde_json::Value>, ModuleError> {
        let payload = serde_json::to_vec(body).expect("json");
        let pending: Vec<(String, Pending)> = self
            .workers
            .iter()
            .map(|w| {
                (
                    w.clone(),
                    self.request(self.subject(&format!("{w}.{leaf}")), payload.clone()),
                )
            })
            .collect();
        let mut answers = Vec::new();
        for (worker, task) in pending {
            let what = format!("{leaf} of worker {worker}");
            let reply = self
                .link
                .wait(&self.name, &self.workers, &what, task, timeout)?
                .map_err(|e| self.request_error(&what, e))?;
            let body = self
                .link
                .conn
                .open_reply(&what, reply.subject.as_str(), &reply.payload)?;
            let answer: serde_json::Value = serde_json::from_slice(body)
                .map_err(|e| ModuleError::new(format!("{what}: bad reply: {e}")))?;
            let ack: Ack = serde_json::from_value(answer.clone())
                .map_err(|e| ModuleError::new(format!("{what}: bad reply: {e}")))?;
            if let Some(n) = ack.rejected {
                self.link
                    .conn
                    .security
                    .lock()
                    .unwrap()
                    .worker_reports(&worker, n);
            }
            if !ack.ok {
                return Err(wire::failure(ack.error));
            }
            answers.push(answer);
        }
        Ok(answers)
    }
}

impl WorkerModule {
    /// A failed request, with the cause when it can be found: "no responders" right after
    /// a worker died races with reaping its process, so its exit is looked for briefly
    /// (up to 0.5 s) before falling back to the bare symptom.
    fn request_error(&self, what: &str, e: async_nats::RequestError) -> ModuleError {
        if e.kind() == RequestErrorKind::NoResponders {
            for _ in 0..10 {
                if let Err(why) = self.link.check_alive(&self.name, &self.workers) {
                    return ModuleError::new(format!("{what}: {why}"));
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        }
        request_error(what, e)
    }
}

fn request_error(what: &str, e: async_nats::RequestError) -> ModuleError {
    ModuleError::new(match e.kind() {
        RequestErrorKind::NoResponders => {
            format!("{what}: no worker is listening (it exited or never subscribed)")
        }
        RequestErrorKind::MaxPayloadExceeded => {
            format!("{what}: the request exceeds the NATS server's max_payload (raise it in the server's configuration)")
        }
        _ => format!("{what}: {e}"),
    })
}

impl RemoteModule for WorkerModule {
    fn default_subscriptions(&self) -> Vec<String> {
        self.plugin.subscribe.clone()
    }

    fn publishes(&self) -> Option<Vec<String>> {
        self.plugin.publishes.clone()
    }

    fn optional_subscriptions(&self) -> Vec<String> {
        self.plugin.optional.clone()
    }

    fn required_inputs(&self) -> Vec<(String, String)> {
        self.plugin.required.clone()
    }

    fn setup(&mut self, ctx: &SetupContext) -> Result<(), ModuleError> {
        self.link.control.mark_started();
        let body = serde_json::json!({
            "seed": ctx.seed, "ts": ctx.ts, "steps": ctx.steps, "every": ctx.every, "offset": ctx.offset,
            // The only worker of the module sees every step: it expects exactly the next one.
            "exclusive": self.workers.len() == 1,
        });
        self.control("setup", &body, self.link.timeouts.startup)
    }

    fn start_step(&mut self, at: StepInfo, inbox: &[SharedMessage]) -> Result<(), ModuleError> {
        self.at = Some(at);
        let subject = self.subject("step");
        let max = self.link.conn.client.server_info().max_payload;
        for shard in 0..self.shards {
            let payload = wire::encode_request(at, shard, self.shards, inbox);
            if payload.len() + super::auth::TRAILER > max {
                self.pending.clear();
                return Err(ModuleError::new(format!(
                    "its inbox of {} messages is {} bytes on the wire, above the NATS server's max_payload of {max} \
                     (raise max_payload in the server's configuration)",
                    inbox.len(),
                    payload.len()
                )));
            }
            let task = self.request(subject.clone(), payload);
            self.pending.push(task);
        }
        Ok(())
    }

    /// Shard replies are merged in shard order: the run does not depend on which
    /// worker answered first.
    fn finish_step(&mut self, out: &mut Vec<Outgoing>) -> Result<Usage, ModuleError> {
        let mut usage = Usage {
            wall_s: 0.0,
            cpu_s: 0.0,
            rss_mib: f64::NAN,
            gpu_util_pct: None,
            gpu_mem_mib: None,
        };
        let pending = std::mem::take(&mut self.pending);
        for (shard, task) in pending.into_iter().enumerate() {
            let what = if self.shards > 1 {
                format!("shard {shard} of {}", self.shards)
            } else {
                "step".into()
            };
            let reply = self
                .link
                .wait(
                    &self.name,
                    &self.workers,
                    &what,
                    task,
                    self.link.timeouts.step,
                )
                .inspect_err(|_| self.stuck = true)?;
            let reply = reply.map_err(|e| self.request_error(&what, e))?;
            let body = self
                .link
                .conn
                .open_reply(&what, reply.subject.as_str(), &reply.payload)?;
            let u = wire::decode_reply(body, out)?;
            // Shards run side by side: the step takes as long as the slowest; CPU adds up.
            usage.wall_s = usage.wall_s.max(u.wall_s);
            usage.cpu_s += u.cpu_s;
            usage.rss_mib = usage.rss_mib.max(u.rss_mib);
            let max = |a: Option<f64>, b: Option<f64>| a.into_iter().chain(b).reduce(f64::max);
            usage.gpu_util_pct = max(usage.gpu_util_pct, u.gpu_util_pct);
            usage.gpu_mem_mib = max(usage.gpu_mem_mib, u.gpu_mem_mib);
        }
        Ok(usage)
    }

    fn state(&mut self) -> Result<ModuleState, ModuleError> {
        // A worker that does not answer (a Rust worker has no state requests; one that
        // died is found at the next step) makes the module not resumable, not the run fail.
        let answers =
            match self.control_replies("state", &serde_json::json!({}), self.link.timeouts.startup)
            {
                Ok(a) => a,
                Err(e) => {
                    return Ok(ModuleState::Unsupported(format!(
                        "its worker did not answer the state request ({e})"
                    )))
                }
            };
        let kinds: Vec<&str> = answers
            .iter()
            .map(|a| a["kind"].as_str().unwrap_or("?"))
            .collect();
        if kinds.iter().all(|k| *k == "stateless") {
            return Ok(ModuleState::Stateless);
        }
        if let [one] = answers.as_slice() {
            match one["kind"].as_str() {
                Some("saved") => {
                    let hex = one["hex"].as_str().unwrap_or_default();
                    return crate::checkpoint::unhex(hex)
                        .map(ModuleState::Saved)
                        .map_err(|e| ModuleError::new(format!("state of worker: {e}")));
                }
                Some("unsupported") => {
                    let why = one["why"].as_str().unwrap_or("no state hooks");
                    return Ok(ModuleState::Unsupported(why.to_string()));
                }
                _ => {}
            }
        }
        Ok(ModuleState::Unsupported(format!(
            "its state is split over {} workers (resume takes one worker per stateful module)",
            answers.len()
        )))
    }

    fn restore(&mut self, state: &[u8]) -> Result<(), ModuleError> {
        self.restored = Some(state.to_vec());
        Ok(())
    }

    fn resume_at(&mut self, next_step: u64) -> Result<(), ModuleError> {
        let hex = self.restored.take().map(|b| crate::checkpoint::hex(&b));
        let body = serde_json::json!({ "next_step": next_step, "hex": hex });
        self.control("resume", &body, self.link.timeouts.startup)
    }

    fn teardown(&mut self) -> Result<(), ModuleError> {
        for t in self.pending.drain(..) {
            t.abort();
        }
        // Workers that already died or are stuck in a step given up cannot tear down:
        // the stuck ones are killed at once. The others get a few seconds (30 s, 2 s
        // when the run is ending badly).
        if self.stuck {
            self.link.procs.reap(&self.name, Duration::ZERO);
            return Ok(());
        }
        let alive = self.link.check_alive(&self.name, &self.workers).is_ok();
        let (grace, reap) = if self.link.abandoning() {
            (2, 1)
        } else {
            (30, 5)
        };
        let result = if alive {
            self.control(
                "teardown",
                &serde_json::json!({}),
                Duration::from_secs(grace),
            )
        } else {
            Ok(())
        };
        self.link.procs.reap(&self.name, Duration::from_secs(reap));
        result
    }
}
