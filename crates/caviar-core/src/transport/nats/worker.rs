//! A worker in Rust: hosts any [`Module`] for a run over NATS, as `caviar worker`
//! does for Python plugins. Benchmarks and tests use it to measure the protocol
//! without an interpreter in the way; it is also the reference for other languages.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use async_nats::{Client, Subscriber};
use futures_util::StreamExt;
use serde_json::{json, Value};

use super::auth::{Guard, RunKey};
use super::wire::{self, WireError, PROTOCOL};
use crate::message::SharedMessage;
use crate::metrics::{process_cpu_seconds, resident_mib};
use crate::module::{Module, ModuleError, SetupContext, StepInfo, Usage};

/// Serves `module` as worker `worker_id` of module `name` in run `run_id` until the
/// run ends. Waits up to `wait` for the core to answer its hello. `key` is the run
/// key: every frame of the core is checked with it, every answer sealed.
pub fn serve(
    url: &str,
    run_id: &str,
    name: &str,
    worker_id: &str,
    module: Box<dyn Module>,
    wait: Duration,
    key: RunKey,
) -> Result<(), String> {
    // The select loop (and so every step) runs on the calling thread; the connection
    // and the heartbeat on the runtime's own thread, so a long step does not silence
    // the heartbeat.
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .map_err(|e| e.to_string())?;
    rt.block_on(async move {
        let client = async_nats::ConnectOptions::new()
            .request_timeout(Some(Duration::from_secs(2)))
            .connect(url)
            .await
            .map_err(|e| format!("connect {url}: {e}"))?;
        let mut w = Worker {
            client,
            prefix: format!("caviar.{run_id}"),
            name: name.into(),
            id: worker_id.into(),
            module,
            spec: Value::Null,
            guard: Arc::new(Mutex::new(Guard::new(key, run_id))),
        };
        w.spec = w.hello(wait).await?;
        w.run().await
    })
}

/// One worker's connection and module.
struct Worker {
    client: Client,
    /// `caviar.<run_id>`.
    prefix: String,
    name: String,
    id: String,
    module: Box<dyn Module>,
    /// The core's answer to the hello: plugin parameters and directories.
    spec: Value,
    /// The run key, sequence numbers and step schedule (shared with the heartbeat).
    guard: Arc<Mutex<Guard>>,
}

fn err(e: impl std::fmt::Display) -> String {
    e.to_string()
}

/// `{"ok": true}`, or the failure as the core reads it.
fn ack(result: Result<(), ModuleError>) -> Value {
    match result {
        Ok(()) => json!({"ok": true}),
        Err(e) => json!({"ok": false, "error": {"message": e.message, "trace": e.trace}}),
    }
}

impl Worker {
    /// Asks the core for the module until it answers or `wait` runs out.
    async fn hello(&self, wait: Duration) -> Result<Value, String> {
        let hello = json!({"protocol": PROTOCOL, "module": self.name, "worker": self.id,
                           "host": "localhost", "pid": std::process::id()});
        let deadline = Instant::now() + wait;
        let subject = format!("{}.hello", self.prefix);
        let spec: Value = loop {
            let body = self.seal(&subject, hello.to_string().into_bytes());
            match self.client.request(subject.clone(), body.into()).await {
                Ok(m) => match self.open(&m.subject, &m.payload) {
                    Some(b) => break serde_json::from_slice(&b).map_err(err)?,
                    // Someone without the key answered first: ask again.
                    None => tokio::time::sleep(Duration::from_millis(50)).await,
                },
                Err(_) if Instant::now() < deadline => {
                    tokio::time::sleep(Duration::from_millis(50)).await
                }
                Err(e) => return Err(format!("no core answered the hello: {e}")),
            }
        };
        if spec["ok"] != true {
            return Err(format!("the core refused the worker: {}", spec["error"]));
        }
        Ok(spec)
    }

    async fn subscribe(&self, subject: String) -> Result<Subscriber, String> {
        self.client.subscribe(subject).await.map_err(err)
    }

    async fn respond(
        &self,
        reply: Option<async_nats::Subject>,
        body: Vec<u8>,
    ) -> Result<(), String> {
        match reply {
            Some(r) => {
                let body = self.seal(&r, body);
                self.client.publish(r, body.into()).await.map_err(err)
            }
            None => Ok(()),
        }
    }

    fn seal(&self, subject: &str, body: Vec<u8>) -> Vec<u8> {
        self.guard.lock().unwrap().seal(subject, body)
    }

    /// The body of a frame of the core, or None (logged and counted) if it fails
    /// authentication or repeats a sequence number.
    fn open(&self, subject: &str, frame: &[u8]) -> Option<Vec<u8>> {
        let mut g = self.guard.lock().unwrap();
        match g.open(subject, frame) {
            Ok(b) => Some(b.to_vec()),
            Err(e) => {
                eprintln!(
                    "caviar worker {}: security: refused {e} ({} refused so far)",
                    self.id, g.rejected
                );
                None
            }
        }
    }

    fn refuse(&self, why: &str) {
        let mut g = self.guard.lock().unwrap();
        g.refuse();
        eprintln!(
            "caviar worker {}: security: refused {why} ({} refused so far)",
            self.id, g.rejected
        );
    }

    /// Says the plugin is loaded, beats, and answers the core until teardown or stop.
    async fn run(&mut self) -> Result<(), String> {
        let me = format!("{}.{}.{}", self.prefix, self.name, self.id);
        let mut setup = self.subscribe(format!("{me}.setup")).await?;
        let mut teardown = self.subscribe(format!("{me}.teardown")).await?;
        let mut stop = self.subscribe(format!("{}.stop", self.prefix)).await?;
        let loaded = json!({"worker": self.id, "subscribe": self.module.default_subscriptions(),
                            "publishes": self.module.publishes(),
                            "optional": self.module.optional_subscriptions(),
                            "required": self.module.required_inputs()});
        let subject = format!("{}.loaded", self.prefix);
        let body = self.seal(&subject, loaded.to_string().into_bytes());
        self.client
            .publish(subject, body.into())
            .await
            .map_err(err)?;
        self.client.flush().await.map_err(err)?;
        let beat = self.heartbeat();
        let mut steps: Option<Subscriber> = None;
        let result = loop {
            tokio::select! {
                Some(m) = setup.next() => {
                    let Some(body) = self.open(&m.subject, &m.payload) else { continue };
                    if m.reply.is_none() {
                        self.refuse("a setup without a reply subject");
                        continue;
                    }
                    let (answer, sub) = self.setup(&body).await?;
                    steps = sub.or(steps);
                    self.respond(m.reply, answer.to_string().into_bytes()).await?;
                }
                Some(m) = async { match steps.as_mut() { Some(s) => s.next().await, None => std::future::pending().await } } => {
                    let Some(body) = self.open(&m.subject, &m.payload) else { continue };
                    let Some(reply) = step_reply(self.module.as_mut(), &body, &self.guard, &self.id) else { continue };
                    self.respond(m.reply, reply).await?;
                }
                Some(m) = teardown.next() => {
                    let Some(_) = self.open(&m.subject, &m.payload) else { continue };
                    if m.reply.is_none() {
                        self.refuse("a teardown without a reply subject");
                        continue;
                    }
                    let mut answer = ack(self.module.teardown());
                    answer["rejected"] = self.guard.lock().unwrap().rejected.into();
                    break self.respond(m.reply, answer.to_string().into_bytes()).await;
                }
                Some(m) = stop.next() => {
                    if self.open(&m.subject, &m.payload).is_some() {
                        break Ok(());
                    }
                }
                else => break Ok(()),
            }
        };
        beat.abort();
        result?;
        self.client.flush().await.map_err(err)
    }

    /// Beats every second on the runtime's thread.
    fn heartbeat(&self) -> tokio::task::JoinHandle<()> {
        let (client, subject) = (self.client.clone(), format!("{}.heartbeat", self.prefix));
        let (id, guard) = (self.id.clone(), self.guard.clone());
        tokio::spawn(async move {
            loop {
                let body = {
                    let mut g = guard.lock().unwrap();
                    let beat = json!({"worker": id, "rejected": g.rejected}).to_string();
                    g.seal(&subject, beat.into_bytes())
                };
                let _ = client.publish(subject.clone(), body.into()).await;
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        })
    }

    /// Sets the module up; once it is, joins the module's queue group for steps.
    async fn setup(&mut self, payload: &[u8]) -> Result<(Value, Option<Subscriber>), String> {
        let c: Value = serde_json::from_slice(payload).map_err(err)?;
        let spec = &self.spec;
        let ctx = SetupContext {
            name: self.name.clone(),
            seed: c["seed"].as_u64().unwrap_or(0),
            ts: c["ts"].as_f64().unwrap_or(1.0),
            steps: c["steps"].as_u64(),
            every: c["every"].as_u64().unwrap_or(1),
            offset: c["offset"].as_u64().unwrap_or(0),
            run_dir: spec["run_dir"].as_str().unwrap_or(".").into(),
            config_dir: spec["config_dir"].as_str().unwrap_or(".").into(),
            params: spec["params"].clone(),
        };
        let result = self.module.setup(&ctx);
        self.guard.lock().unwrap().schedule(
            ctx.every,
            ctx.offset,
            ctx.steps,
            spec["shards"].as_u64().unwrap_or(1),
            c["exclusive"].as_bool().unwrap_or(false),
        );
        if result.is_err() {
            return Ok((ack(result), None));
        }
        let subject = format!("{}.{}.step", self.prefix, self.name);
        let sub = self
            .client
            .queue_subscribe(subject, self.name.clone())
            .await
            .map_err(err)?;
        self.client.flush().await.map_err(err)?;
        Ok((ack(result), Some(sub)))
    }
}

/// The reply to a step request, or None when the step is out of sequence (refused).
fn step_reply(
    module: &mut dyn Module,
    payload: &[u8],
    guard: &Mutex<Guard>,
    id: &str,
) -> Option<Vec<u8>> {
    let failed = |message: String| {
        wire::encode_failure(&WireError {
            message,
            trace: None,
            key: None,
        })
    };
    let (req, inbox) = match wire::decode_request(payload) {
        Ok(r) => r,
        Err(e) => return Some(failed(e)),
    };
    {
        let mut g = guard.lock().unwrap();
        if let Err(e) = g.accept_step(req.step, req.shard) {
            eprintln!(
                "caviar worker {id}: security: refused {e} ({} refused so far)",
                g.rejected
            );
            return None;
        }
    }
    let inbox: Vec<SharedMessage> = inbox.into_iter().map(std::sync::Arc::new).collect();
    let (t0, c0) = (Instant::now(), process_cpu_seconds());
    let mut out = Vec::new();
    let at = StepInfo {
        step: req.step,
        time: req.time,
    };
    match module.step(at, &inbox, &mut out) {
        Ok(()) => {
            let usage = Usage {
                wall_s: t0.elapsed().as_secs_f64(),
                cpu_s: process_cpu_seconds() - c0,
                rss_mib: resident_mib(),
                gpu_util_pct: None,
                gpu_mem_mib: None,
            };
            Some(wire::encode_reply(&out, usage))
        }
        Err(e) => Some(failed(e.message)),
    }
}
