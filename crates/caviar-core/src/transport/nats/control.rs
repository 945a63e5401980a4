//! The run's control plane: workers say hello (and get their module), report their
//! plugin loaded, and beat every second; the registry of who said what, and when.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use serde::Deserialize;
use serde_json::json;

use super::client::{Client, Sealer, Security};
use super::wire::{WireError, PROTOCOL};

/// What a worker told us about itself.
#[derive(Debug, Clone)]
pub struct WorkerInfo {
    pub id: String,
    pub module: String,
    pub host: String,
    pub pid: u32,
    pub last_beat: Instant,
    /// After `loaded`: what the plugin said of itself, or why it could not load.
    pub loaded: Option<Result<LoadedPlugin, WireError>>,
}

/// What a worker's plugin said of itself once loaded.
#[derive(Debug, Clone, Default)]
pub struct LoadedPlugin {
    /// Default subscriptions.
    pub subscribe: Vec<String>,
    /// Topics it declares publishing (`None`: not declared).
    pub publishes: Option<Vec<String>>,
    /// Default subscriptions it works without.
    pub optional: Vec<String>,
    /// Inputs its parameters name: (pattern, key).
    pub required: Vec<(String, String)>,
}

/// The module description a worker receives in reply to its hello.
pub struct ModuleOffer {
    pub plugin: String,
    pub params: serde_json::Value,
    pub shards: u64,
}

#[derive(Deserialize)]
struct Hello {
    protocol: u32,
    module: String,
    worker: String,
    #[serde(default)]
    host: String,
    #[serde(default)]
    pid: u32,
}

#[derive(Deserialize)]
struct Loaded {
    worker: String,
    #[serde(default)]
    subscribe: Vec<String>,
    /// Absent or empty: not declared.
    #[serde(default)]
    publishes: Option<Vec<String>>,
    #[serde(default)]
    optional: Vec<String>,
    #[serde(default)]
    required: Vec<(String, String)>,
    #[serde(default)]
    error: Option<WireError>,
}

#[derive(Deserialize)]
struct Beat {
    worker: String,
    /// Core frames the worker refused so far.
    #[serde(default)]
    rejected: u64,
}

type Registry = Arc<Mutex<HashMap<String, WorkerInfo>>>;

pub struct ControlPlane {
    workers: Registry,
    /// Set once the engine has set the modules up: later workers are turned away.
    started: Arc<AtomicBool>,
}

impl ControlPlane {
    /// Subscribes to the run's hello, loaded and heartbeat subjects and answers
    /// workers' hellos with `offers` (each completed with `base`: run and config dirs).
    pub fn listen(
        conn: &Client,
        offers: HashMap<String, ModuleOffer>,
        base: serde_json::Value,
    ) -> Result<Self, String> {
        let (client, prefix) = (&conn.client, &conn.prefix);
        let subs = conn
            .rt
            .block_on(async {
                let mut subs = Vec::new();
                for leaf in ["hello", "loaded", "heartbeat"] {
                    let s = client
                        .subscribe(format!("{prefix}.{leaf}"))
                        .await
                        .map_err(|e| e.to_string())?;
                    subs.push(s);
                }
                client.flush().await.map_err(|e| e.to_string())?;
                Ok::<_, String>(futures_util::stream::select_all(subs))
            })
            .map_err(|e| format!("NATS subscribe on {prefix}.*: {e}"))?;
        let plane = ControlPlane {
            workers: Registry::default(),
            started: Arc::default(),
        };
        let task = Listener {
            client: client.clone(),
            sealer: conn.sealer.clone(),
            security: conn.security.clone(),
            workers: plane.workers.clone(),
            started: plane.started.clone(),
            offers,
            base,
        };
        conn.rt.spawn(task.serve(subs));
        Ok(plane)
    }

    pub fn mark_started(&self) {
        self.started.store(true, Ordering::SeqCst);
    }

    /// The workers of `module` that have said hello, in the order of their ids.
    pub fn workers_of(&self, module: &str) -> Vec<WorkerInfo> {
        let mut v: Vec<WorkerInfo> = self
            .workers
            .lock()
            .unwrap()
            .values()
            .filter(|w| w.module == module)
            .cloned()
            .collect();
        v.sort_by(|a, b| a.id.cmp(&b.id));
        v
    }

    /// The workers among `expected` that did not beat for longer than `limit`, in words.
    pub fn silent(&self, expected: &[String], limit: Duration) -> Vec<String> {
        let workers = self.workers.lock().unwrap();
        expected
            .iter()
            .filter_map(|id| workers.get(id))
            .filter(|w| w.last_beat.elapsed() > limit)
            .map(|w| {
                format!(
                    "{} (pid {} on {}), silent for {:.1} s",
                    w.id,
                    w.pid,
                    w.host,
                    w.last_beat.elapsed().as_secs_f64()
                )
            })
            .collect()
    }
}

/// The task that answers the control subjects.
struct Listener {
    client: async_nats::Client,
    sealer: Sealer,
    security: Arc<Mutex<Security>>,
    workers: Registry,
    started: Arc<AtomicBool>,
    offers: HashMap<String, ModuleOffer>,
    base: serde_json::Value,
}

impl Listener {
    async fn serve(self, mut subs: futures_util::stream::SelectAll<async_nats::Subscriber>) {
        while let Some(msg) = subs.next().await {
            let subject = msg.subject.as_str();
            let Some(body) = self.authentic(subject, &msg.payload) else {
                continue;
            };
            if subject.ends_with(".hello") {
                let answer = self.answer_hello(body);
                if let Some(reply) = msg.reply {
                    let sealed = self
                        .sealer
                        .seal(&reply, serde_json::to_vec(&answer).expect("json"));
                    let _ = self.client.publish(reply, sealed.into()).await;
                }
            } else if subject.ends_with(".loaded") {
                self.loaded(body);
            } else if let Ok(b) = serde_json::from_slice::<Beat>(body) {
                if let Some(info) = self.workers.lock().unwrap().get_mut(&b.worker) {
                    info.last_beat = Instant::now();
                }
                self.security
                    .lock()
                    .unwrap()
                    .worker_reports(&b.worker, b.rejected);
            }
        }
    }

    /// The body of a frame from a worker that holds the run key, in sequence; a refusal
    /// is recorded.
    fn authentic<'a>(&self, subject: &str, frame: &'a [u8]) -> Option<&'a [u8]> {
        let mut sec = self.security.lock().unwrap();
        match self.sealer.open(subject, frame) {
            Ok((n, body)) => {
                let who = serde_json::from_slice::<Beat>(body)
                    .map(|b| b.worker)
                    .unwrap_or_default();
                let leaf = subject.rsplit('.').next().unwrap_or("");
                if let Err(e) = sec.accept_seq(&who, leaf, n) {
                    sec.reject(format!("{subject} from '{who}': {e}"));
                    return None;
                }
                Some(body)
            }
            Err(e) => {
                sec.reject(e);
                None
            }
        }
    }

    fn loaded(&self, body: &[u8]) {
        let Ok(l) = serde_json::from_slice::<Loaded>(body) else {
            return;
        };
        if let Some(info) = self.workers.lock().unwrap().get_mut(&l.worker) {
            info.last_beat = Instant::now();
            let plugin = LoadedPlugin {
                subscribe: l.subscribe,
                publishes: l.publishes.filter(|p| !p.is_empty()),
                optional: l.optional,
                required: l.required,
            };
            info.loaded = Some(l.error.map_or(Ok(plugin), Err));
        }
    }

    fn answer_hello(&self, payload: &[u8]) -> serde_json::Value {
        let hello: Hello = match serde_json::from_slice(payload) {
            Ok(h) => h,
            Err(e) => return json!({"ok": false, "error": format!("bad hello: {e}")}),
        };
        if hello.protocol != PROTOCOL {
            return json!({"ok": false, "error": format!("this core speaks protocol {PROTOCOL}, the worker {}", hello.protocol)});
        }
        let Some(offer) = self.offers.get(&hello.module) else {
            let mut known: Vec<&String> = self.offers.keys().collect();
            known.sort();
            return json!({"ok": false, "error": format!("this run has no remote module '{}' (remote modules: {known:?})", hello.module)});
        };
        if self.started.load(Ordering::SeqCst) {
            return json!({"ok": false, "error": "the run has already started; workers must join before the first step"});
        }
        let mut w = self.workers.lock().unwrap();
        let again = w
            .get(&hello.worker)
            .is_some_and(|o| o.pid == hello.pid && o.host == hello.host && o.loaded.is_none());
        if w.contains_key(&hello.worker) && !again {
            return json!({"ok": false, "error": format!("a worker with id '{}' already joined", hello.worker)});
        }
        w.insert(
            hello.worker.clone(),
            WorkerInfo {
                id: hello.worker,
                module: hello.module.clone(),
                host: hello.host,
                pid: hello.pid,
                last_beat: Instant::now(),
                loaded: None,
            },
        );
        let mut answer = self.base.clone();
        let o = answer.as_object_mut().expect("object");
        o.insert("ok".into(), true.into());
        o.insert("protocol".into(), PROTOCOL.into());
        o.insert("module".into(), hello.module.into());
        o.insert("plugin".into(), offer.plugin.clone().into());
        o.insert("params".into(), offer.params.clone());
        o.insert("shards".into(), offer.shards.into());
        answer
    }
}
