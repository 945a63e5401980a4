//! A worker in Rust: hosts any [`Module`] for a run over NATS, as `caviar worker`
//! does for Python plugins. Benchmarks and tests use it to measure the protocol
//! without an interpreter in the way; it is also the reference for other languages.

use std::time::{Duration, Instant};

use async_nats::{Client, Subscriber};
use futures_util::StreamExt;
use serde_json::{json, Value};

use super::wire::{self, WireError, PROTOCOL};
use crate::message::SharedMessage;
use crate::metrics::{process_cpu_seconds, resident_mib};
use crate::module::{Module, ModuleError, SetupContext, StepInfo, Usage};

/// Serves `module` as worker `worker_id` of module `name` in run `run_id` until the
/// run ends. Waits up to `wait` for the core to answer its hello.
pub fn serve(
    url: &str,
    run_id: &str,
    name: &str,
    worker_id: &str,
    module: Box<dyn Module>,
    wait: Duration,
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
            match self
                .client
                .request(subject.clone(), hello.to_string().into())
                .await
            {
                Ok(m) => break serde_json::from_slice(&m.payload).map_err(err)?,
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
            Some(r) => self.client.publish(r, body.into()).await.map_err(err),
            None => Ok(()),
        }
    }

    /// Says the plugin is loaded, beats, and answers the core until teardown or stop.
    async fn run(&mut self) -> Result<(), String> {
        let me = format!("{}.{}.{}", self.prefix, self.name, self.id);
        let mut setup = self.subscribe(format!("{me}.setup")).await?;
        let mut teardown = self.subscribe(format!("{me}.teardown")).await?;
        let mut stop = self.subscribe(format!("{}.stop", self.prefix)).await?;
        let loaded = json!({"worker": self.id, "subscribe": self.module.default_subscriptions(),
                            "publishes": self.module.publishes()});
        let subject = format!("{}.loaded", self.prefix);
        self.client
            .publish(subject, loaded.to_string().into())
            .await
            .map_err(err)?;
        self.client.flush().await.map_err(err)?;
        let beat = self.heartbeat();
        let mut steps: Option<Subscriber> = None;
        let result = loop {
            tokio::select! {
                Some(m) = setup.next() => {
                    let (answer, sub) = self.setup(&m.payload).await?;
                    steps = sub.or(steps);
                    self.respond(m.reply, answer.to_string().into_bytes()).await?;
                }
                Some(m) = async { match steps.as_mut() { Some(s) => s.next().await, None => std::future::pending().await } } => {
                    let reply = step_reply(self.module.as_mut(), &m.payload);
                    self.respond(m.reply, reply).await?;
                }
                Some(m) = teardown.next() => {
                    let answer = ack(self.module.teardown());
                    break self.respond(m.reply, answer.to_string().into_bytes()).await;
                }
                _ = stop.next() => break Ok(()),
            }
        };
        beat.abort();
        result?;
        self.client.flush().await.map_err(err)
    }

    /// Beats every second on the runtime's thread.
    fn heartbeat(&self) -> tokio::task::JoinHandle<()> {
        let (client, subject) = (self.client.clone(), format!("{}.heartbeat", self.prefix));
        let body = json!({"worker": self.id}).to_string();
        tokio::spawn(async move {
            loop {
                let _ = client.publish(subject.clone(), body.clone().into()).await;
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

fn step_reply(module: &mut dyn Module, payload: &[u8]) -> Vec<u8> {
    let failed = |message: String| {
        wire::encode_failure(&WireError {
            message,
            trace: None,
            key: None,
        })
    };
    let (req, inbox) = match wire::decode_request(payload) {
        Ok(r) => r,
        Err(e) => return failed(e),
    };
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
            wire::encode_reply(&out, usage)
        }
        Err(e) => failed(e.message),
    }
}
