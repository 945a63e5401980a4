//! A worker in Rust: hosts any [`Module`] for a run over NATS, as `caviar worker`
//! does for Python plugins. Benchmarks and tests use it to measure the protocol
//! without an interpreter in the way; it is also the reference for other languages.

use std::time::{Duration, Instant};

use futures_util::StreamExt;
use serde_json::json;

use super::wire::{self, PROTOCOL};
use crate::engine::{process_cpu_seconds, resident_mib};
use crate::message::SharedMessage;
use crate::module::{Module, SetupContext, StepInfo, Usage};

/// Serves `module` as worker `worker_id` of module `name` in run `run_id` until the
/// run ends. Waits up to `wait` for the core to answer its hello.
pub fn serve(
    url: &str,
    run_id: &str,
    name: &str,
    worker_id: &str,
    mut module: Box<dyn Module>,
    wait: Duration,
) -> Result<(), String> {
    // The select loop below (and so every step) runs on the calling thread; the
    // connection and the heartbeat on the runtime's own thread, so a long step does
    // not silence the heartbeat.
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
        let prefix = format!("caviar.{run_id}");
        let hello = json!({"protocol": PROTOCOL, "module": name, "worker": worker_id, "host": "localhost", "pid": std::process::id()});
        let deadline = Instant::now() + wait;
        let spec: serde_json::Value = loop {
            match client.request(format!("{prefix}.hello"), hello.to_string().into()).await {
                Ok(m) => break serde_json::from_slice(&m.payload).map_err(|e| e.to_string())?,
                Err(_) if Instant::now() < deadline => tokio::time::sleep(Duration::from_millis(50)).await,
                Err(e) => return Err(format!("no core answered the hello: {e}")),
            }
        };
        if spec["ok"] != true {
            return Err(format!("the core refused the worker: {}", spec["error"]));
        }
        let me = format!("{prefix}.{name}.{worker_id}");
        let mut setup = client.subscribe(format!("{me}.setup")).await.map_err(|e| e.to_string())?;
        let mut teardown = client.subscribe(format!("{me}.teardown")).await.map_err(|e| e.to_string())?;
        let mut stop = client.subscribe(format!("{prefix}.stop")).await.map_err(|e| e.to_string())?;
        let loaded = json!({"worker": worker_id, "subscribe": module.default_subscriptions()});
        client.publish(format!("{prefix}.loaded"), loaded.to_string().into()).await.map_err(|e| e.to_string())?;
        client.flush().await.map_err(|e| e.to_string())?;
        let (beat_client, beat_subject) = (client.clone(), format!("{prefix}.heartbeat"));
        let body = json!({"worker": worker_id}).to_string();
        let beat = tokio::spawn(async move {
            loop {
                let _ = beat_client.publish(beat_subject.clone(), body.clone().into()).await;
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        });
        let mut steps: Option<async_nats::Subscriber> = None;
        loop {
            tokio::select! {
                Some(m) = setup.next() => {
                    let c: serde_json::Value = serde_json::from_slice(&m.payload).map_err(|e| e.to_string())?;
                    let ctx = SetupContext {
                        name: name.into(),
                        seed: c["seed"].as_u64().unwrap_or(0),
                        ts: c["ts"].as_f64().unwrap_or(1.0),
                        steps: c["steps"].as_u64(),
                        every: c["every"].as_u64().unwrap_or(1),
                        offset: c["offset"].as_u64().unwrap_or(0),
                        run_dir: spec["run_dir"].as_str().unwrap_or(".").into(),
                        config_dir: spec["config_dir"].as_str().unwrap_or(".").into(),
                        params: spec["params"].clone(),
                    };
                    let answer = match module.setup(&ctx) {
                        Ok(()) => {
                            let sub = client
                                .queue_subscribe(format!("{prefix}.{name}.step"), name.to_string())
                                .await
                                .map_err(|e| e.to_string())?;
                            client.flush().await.map_err(|e| e.to_string())?;
                            steps = Some(sub);
                            json!({"ok": true})
                        }
                        Err(e) => json!({"ok": false, "error": {"message": e.message, "trace": e.trace}}),
                    };
                    if let Some(r) = m.reply { client.publish(r, answer.to_string().into()).await.map_err(|e| e.to_string())?; }
                }
                Some(m) = async { match steps.as_mut() { Some(s) => s.next().await, None => std::future::pending().await } } => {
                    let reply = step_reply(module.as_mut(), &m.payload);
                    if let Some(r) = m.reply { client.publish(r, reply.into()).await.map_err(|e| e.to_string())?; }
                }
                Some(m) = teardown.next() => {
                    let answer = match module.teardown() {
                        Ok(()) => json!({"ok": true}),
                        Err(e) => json!({"ok": false, "error": {"message": e.message, "trace": e.trace}}),
                    };
                    if let Some(r) = m.reply { client.publish(r, answer.to_string().into()).await.map_err(|e| e.to_string())?; }
                    break;
                }
                _ = stop.next() => break,
            }
        }
        beat.abort();
        client.flush().await.map_err(|e| e.to_string())
    })
}

fn step_reply(module: &mut dyn Module, payload: &[u8]) -> Vec<u8> {
    let failed = |message: String| {
        let head =
            serde_json::to_vec(&json!({"ok": false, "error": {"message": message}})).expect("json");
        let mut buf = (head.len() as u32).to_le_bytes().to_vec();
        buf.extend(head);
        buf
    };
    let (req, inbox) = match wire::decode_request(payload) {
        Ok(r) => r,
        Err(e) => return failed(e),
    };
    let inbox: Vec<SharedMessage> = inbox.into_iter().map(std::sync::Arc::new).collect();
    let (t0, c0) = (Instant::now(), process_cpu_seconds());
    let mut out = Vec::new();
    match module.step(
        StepInfo {
            step: req.step,
            time: req.time,
        },
        &inbox,
        &mut out,
    ) {
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
