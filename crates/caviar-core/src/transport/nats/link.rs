//! The core's connection to NATS for one run: the server (when we start it), the
//! worker processes (when we start them), and the registry of workers that said hello.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use serde::Deserialize;
use serde_json::json;

use super::auth::{RunKey, SeqWindow};
use super::server::{DieWithParent, SpawnedServer};
use super::wire::{WireError, PROTOCOL};
use crate::config::NatsTransport;
use crate::module::ModuleError;

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
    error: Option<WireError>,
}

#[derive(Deserialize)]
struct Beat {
    worker: String,
    /// Core frames the worker refused so far.
    #[serde(default)]
    rejected: u64,
}

/// What was refused during the run: by the core (worker messages that failed
/// authentication) and by each worker (core frames it refused, as it reported them).
#[derive(Debug, Default)]
pub struct Security {
    pub rejected_by_core: u64,
    pub rejected_by_workers: HashMap<String, u64>,
    /// The first refusals, in words.
    pub warnings: Vec<String>,
    /// Sequence numbers seen per worker and subject (hello, loaded, heartbeat).
    seqs: HashMap<(String, String), SeqWindow>,
}

impl Security {
    const MAX_WARNINGS: usize = 50;

    /// Records a message the core refused and says so on stderr.
    pub fn reject(&mut self, why: String) {
        eprintln!("caviar: security: refused {why}");
        self.rejected_by_core += 1;
        if self.warnings.len() < Self::MAX_WARNINGS {
            self.warnings.push(why);
        }
    }

    /// A worker's own count of refused core frames (they only grow).
    pub fn worker_reports(&mut self, worker: &str, rejected: u64) {
        let n = self.rejected_by_workers.entry(worker.into()).or_default();
        if rejected > *n {
            eprintln!(
                "caviar: security: worker {worker} refused {} core frame(s) that failed authentication or were out of sequence",
                rejected - *n
            );
            *n = rejected;
        }
    }

    /// `security` in run.json.
    pub fn to_json(&self) -> serde_json::Value {
        let by_workers: u64 = self.rejected_by_workers.values().sum();
        json!({
            "rejected": self.rejected_by_core + by_workers,
            "rejected_by_core": self.rejected_by_core,
            "rejected_by_workers": self.rejected_by_workers,
            "warnings": self.warnings,
        })
    }
}

/// A worker process this run started, and where its output goes.
struct WorkerProcess {
    module: String,
    child: Child,
    log: PathBuf,
}

pub struct Timeouts {
    pub startup: Duration,
    pub step: Duration,
    pub heartbeat: Duration,
    pub reconnect: Duration,
}

impl Timeouts {
    /// `step`: `LoadedConfig::step_timeout` (episode.step_timeout or its older name).
    pub fn from_config(n: &NatsTransport, step: f64) -> Self {
        Timeouts {
            startup: Duration::from_secs_f64(n.startup_timeout),
            step: Duration::from_secs_f64(step),
            heartbeat: Duration::from_secs_f64(n.heartbeat_timeout),
            reconnect: Duration::from_secs_f64(n.reconnect_timeout),
        }
    }
}

pub struct Link {
    pub rt: tokio::runtime::Runtime,
    pub client: async_nats::Client,
    pub url: String,
    pub run_id: String,
    /// `caviar.<run_id>`: every control subject of the run starts with it.
    pub prefix: String,
    pub timeouts: Timeouts,
    workers: Arc<Mutex<HashMap<String, WorkerInfo>>>,
    /// Set once the engine has set the modules up: later workers are turned away.
    started: Arc<std::sync::atomic::AtomicBool>,
    processes: Mutex<Vec<WorkerProcess>>,
    disconnected_since: Mutex<Option<Instant>>,
    /// Set when the run ends badly (a step past its deadline, Ctrl-C).
    abandoning: std::sync::atomic::AtomicBool,
    /// The run key: every frame is sealed and checked with it (auth.rs).
    pub key: RunKey,
    /// The core's sequence number, one counter for every frame it sends.
    seq: Arc<std::sync::atomic::AtomicU64>,
    pub security: Arc<Mutex<Security>>,
    /// Where run.json is, to record `security` in it when the run ends.
    run_dir: PathBuf,
    // Dropped last (fields drop in order): the workers and the client go before the server.
    server: Mutex<Option<SpawnedServer>>,
}

/// The module description a worker receives in reply to its hello.
pub struct ModuleOffer {
    pub plugin: String,
    pub params: serde_json::Value,
    pub shards: u64,
}

pub fn connect_options(
    n: &NatsTransport,
    resolve: &dyn Fn(&Path) -> PathBuf,
) -> Result<async_nats::ConnectOptions, String> {
    let mut o = async_nats::ConnectOptions::new()
        .name("caviar-core")
        // Our own deadlines apply (step_timeout, heartbeats); the client's 10 s default would cut long steps.
        .request_timeout(None)
        .max_reconnects(None)
        .connection_timeout(Duration::from_secs(5));
    if let Some(c) = &n.credentials {
        let text = std::fs::read_to_string(resolve(c))
            .map_err(|e| format!("transport.nats.credentials: {}: {e}", resolve(c).display()))?;
        o = o
            .credentials(&text)
            .map_err(|e| format!("transport.nats.credentials: {e}"))?;
    }
    if let Some(t) = &n.token {
        o = o.token(t.clone());
    }
    if let (Some(u), Some(p)) = (&n.user, &n.password) {
        o = o.user_and_password(u.clone(), p.clone());
    }
    if let Some(ca) = &n.tls_ca {
        o = o.add_root_certificates(resolve(ca));
    }
    if let (Some(c), Some(k)) = (&n.tls_cert, &n.tls_key) {
        o = o.add_client_certificate(resolve(c), resolve(k));
    }
    if n.tls_required {
        o = o.require_tls(true);
    }
    Ok(o)
}

impl Link {
    /// Connects and starts answering workers' hellos with `offers`.
    #[allow(clippy::too_many_arguments)]
    pub fn connect(
        url: &str,
        options: async_nats::ConnectOptions,
        run_id: &str,
        key: RunKey,
        offers: HashMap<String, ModuleOffer>,
        base: serde_json::Value,
        run_dir: &Path,
        timeouts: Timeouts,
        server: Option<SpawnedServer>,
    ) -> Result<Arc<Link>, String> {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("caviar-nats")
            .enable_all()
            .build()
            .map_err(|e| format!("tokio runtime: {e}"))?;
        let client = rt
            .block_on(options.connect(url))
            .map_err(|e| format!("cannot connect to the NATS server at {url}: {e}"))?;
        let prefix = format!("caviar.{run_id}");
        let workers: Arc<Mutex<HashMap<String, WorkerInfo>>> = Arc::default();
        let started = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let mut subs = rt
            .block_on(async {
                let hello = client
                    .subscribe(format!("{prefix}.hello"))
                    .await
                    .map_err(|e| e.to_string())?;
                let loaded = client
                    .subscribe(format!("{prefix}.loaded"))
                    .await
                    .map_err(|e| e.to_string())?;
                let beat = client
                    .subscribe(format!("{prefix}.heartbeat"))
                    .await
                    .map_err(|e| e.to_string())?;
                client.flush().await.map_err(|e| e.to_string())?;
                Ok::<_, String>(futures_util::stream::select_all([hello, loaded, beat]))
            })
            .map_err(|e| format!("NATS subscribe on {prefix}.*: {e}"))?;
        let (c, w, s) = (client.clone(), workers.clone(), started.clone());
        let security: Arc<Mutex<Security>> = Arc::default();
        let seq = Arc::new(std::sync::atomic::AtomicU64::new(0));
        let (sec, k, run, hello_seq) = (
            security.clone(),
            key.clone(),
            run_id.to_string(),
            seq.clone(),
        );
        rt.spawn(async move {
            while let Some(msg) = subs.next().await {
                let subject = msg.subject.as_str();
                // Only workers that hold the run key are heard.
                let body = match k.open(&run, subject, &msg.payload) {
                    Ok((n, body)) => {
                        let who = serde_json::from_slice::<Beat>(body)
                            .map(|b| b.worker)
                            .unwrap_or_default();
                        let leaf = subject.rsplit('.').next().unwrap_or("").to_string();
                        let mut sec = sec.lock().unwrap();
                        if let Err(e) = sec.seqs.entry((who.clone(), leaf)).or_default().accept(n) {
                            sec.reject(format!("{subject} from '{who}': {e}"));
                            continue;
                        }
                        body
                    }
                    Err(e) => {
                        sec.lock().unwrap().reject(e);
                        continue;
                    }
                };
                if subject.ends_with(".hello") {
                    let answer = answer_hello(body, &offers, &base, &w, &s);
                    if let Some(reply) = msg.reply {
                        let n = hello_seq.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
                        let sealed =
                            k.seal(&run, &reply, n, serde_json::to_vec(&answer).expect("json"));
                        let _ = c.publish(reply, sealed.into()).await;
                    }
                } else if subject.ends_with(".loaded") {
                    if let Ok(l) = serde_json::from_slice::<Loaded>(body) {
                        if let Some(info) = w.lock().unwrap().get_mut(&l.worker) {
                            info.last_beat = Instant::now();
                            let plugin = LoadedPlugin {
                                subscribe: l.subscribe,
                                publishes: l.publishes.filter(|p| !p.is_empty()),
                            };
                            info.loaded = Some(l.error.map_or(Ok(plugin), Err));
                        }
                    }
                } else if let Ok(b) = serde_json::from_slice::<Beat>(body) {
                    if let Some(info) = w.lock().unwrap().get_mut(&b.worker) {
                        info.last_beat = Instant::now();
                    }
                    sec.lock().unwrap().worker_reports(&b.worker, b.rejected);
                }
            }
        });
        Ok(Arc::new(Link {
            rt,
            client,
            url: url.to_string(),
            run_id: run_id.to_string(),
            prefix,
            timeouts,
            workers,
            started,
            processes: Mutex::new(Vec::new()),
            disconnected_since: Mutex::new(None),
            abandoning: std::sync::atomic::AtomicBool::new(false),
            key,
            seq,
            security,
            run_dir: run_dir.to_path_buf(),
            server: Mutex::new(server),
        }))
    }

    /// Seals a frame of the core for `subject` with the next sequence number.
    pub fn seal(&self, subject: &str, body: Vec<u8>) -> Vec<u8> {
        let n = self.seq.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
        self.key.seal(&self.run_id, subject, n, body)
    }

    /// Checks a worker's reply received on `subject` (its own inbox: a reply cannot be
    /// moved to another request); a refusal is recorded.
    pub fn open_reply<'a>(
        &self,
        what: &str,
        subject: &str,
        frame: &'a [u8],
    ) -> Result<&'a [u8], ModuleError> {
        self.key
            .open(&self.run_id, subject, frame)
            .map(|(_, body)| body)
            .map_err(|e| {
                self.security.lock().unwrap().reject(format!("reply to {what}: {e}"));
                ModuleError::new(format!(
                    "{what}: the reply failed authentication (someone without the run key answered; see security in run.json)"
                ))
            })
    }

    /// Records `security` in run.json (the run's status is written before the link goes).
    fn record_security(&self) {
        let path = self.run_dir.join("run.json");
        let Ok(text) = std::fs::read_to_string(&path) else {
            return;
        };
        let Ok(mut status) = serde_json::from_str::<serde_json::Value>(&text) else {
            return;
        };
        let Some(o) = status.as_object_mut() else {
            return;
        };
        o.insert("security".into(), self.security.lock().unwrap().to_json());
        let tmp = self.run_dir.join("run.json.security.tmp");
        let text = serde_json::to_string_pretty(&status).expect("json");
        if std::fs::write(&tmp, text).is_ok() {
            let _ = std::fs::rename(&tmp, &path);
        }
    }

    /// Starts a worker process for `module`; its output goes to `log`.
    pub fn spawn_worker(
        &self,
        module: &str,
        command: &[String],
        envs: &[(String, String)],
        log: &Path,
    ) -> Result<(), String> {
        let file = std::fs::File::create(log).map_err(|e| format!("{}: {e}", log.display()))?;
        let child = Command::new(&command[0])
            .die_with_parent()
            .args(&command[1..])
            .envs(envs.iter().map(|(k, v)| (k, v)))
            .stdin(Stdio::null())
            .stdout(file.try_clone().map_err(|e| e.to_string())?)
            .stderr(file)
            .spawn()
            .map_err(|e| {
                format!(
                    "cannot start the worker of module '{module}' ({}): {e}",
                    command[0]
                )
            })?;
        self.processes.lock().unwrap().push(WorkerProcess {
            module: module.into(),
            child,
            log: log.into(),
        });
        Ok(())
    }

    pub fn mark_started(&self) {
        self.started
            .store(true, std::sync::atomic::Ordering::SeqCst);
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

    /// Why `module` can no longer answer, if we can tell: a worker process of it that
    /// exited, workers that stopped beating, a connection that stayed down.
    pub fn check_alive(&self, module: &str, expected: &[String]) -> Result<(), String> {
        if let Some(why) = self
            .server
            .lock()
            .unwrap()
            .as_mut()
            .and_then(|s| s.exited())
        {
            return Err(why);
        }
        for p in self
            .processes
            .lock()
            .unwrap()
            .iter_mut()
            .filter(|p| p.module == module)
        {
            if let Ok(Some(status)) = p.child.try_wait() {
                return Err(format!(
                    "its worker process (pid {}) exited ({status}); last lines of {}:\n{}",
                    p.child.id(),
                    p.log.display(),
                    tail(&p.log, 15)
                ));
            }
        }
        let silent: Vec<String> = {
            let workers = self.workers.lock().unwrap();
            expected
                .iter()
                .filter_map(|id| workers.get(id))
                .filter(|w| w.last_beat.elapsed() > self.timeouts.heartbeat)
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
        };
        if !silent.is_empty() && silent.len() == expected.len() {
            return Err(format!(
                "its worker stopped answering (no heartbeat): {}",
                silent.join("; ")
            ));
        }
        let mut since = self.disconnected_since.lock().unwrap();
        if self.client.connection_state() == async_nats::connection::State::Disconnected {
            let t = *since.get_or_insert_with(Instant::now);
            if t.elapsed() > self.timeouts.reconnect {
                return Err(format!(
                    "the connection to the NATS server at {} dropped and was retried for {:.0} s without success",
                    self.url,
                    self.timeouts.reconnect.as_secs_f64()
                ));
            }
        } else {
            *since = None;
        }
        Ok(())
    }

    /// Waits for `task`, checking every 100 ms that `module` can still answer.
    pub fn wait<T: Send + 'static>(
        &self,
        module: &str,
        expected: &[String],
        what: &str,
        mut task: tokio::task::JoinHandle<T>,
        timeout: Duration,
    ) -> Result<T, ModuleError> {
        let t0 = Instant::now();
        loop {
            // Replies of a stage arrive together: most are in before we ask, and need no timer.
            if task.is_finished() {
                return self
                    .rt
                    .block_on(task)
                    .map_err(|e| ModuleError::new(format!("{what}: {e}")));
            }
            let done = self.rt.block_on(async {
                tokio::select! {
                    r = &mut task => Some(r),
                    _ = tokio::time::sleep(Duration::from_millis(100)) => None,
                }
            });
            if let Some(r) = done {
                return r.map_err(|e| ModuleError::new(format!("{what}: {e}")));
            }
            if let Err(why) = self.check_alive(module, expected) {
                task.abort();
                self.abandon();
                return Err(ModuleError::new(format!("{what}: {why}")));
            }
            if crate::interrupt::requested() {
                task.abort();
                self.abandon();
                return Err(ModuleError::new(format!("{what}: interrupted (Ctrl-C)")));
            }
            if t0.elapsed() > timeout {
                task.abort();
                self.abandon();
                return Err(ModuleError::new(format!(
                    "{what}: no reply within {:.0} s (episode.step_timeout / transport.nats.startup_timeout)",
                    timeout.as_secs_f64()
                )));
            }
        }
    }

    /// The run is ending badly (a step timed out, Ctrl-C): teardowns get a short grace.
    pub fn abandon(&self) {
        self.abandoning
            .store(true, std::sync::atomic::Ordering::Relaxed);
    }

    pub fn abandoning(&self) -> bool {
        self.abandoning.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Reaps the worker processes of `module` (they exit after teardown), killing any
    /// still running after `grace`.
    pub fn reap(&self, module: &str, grace: Duration) {
        let mut procs = self.processes.lock().unwrap();
        let deadline = Instant::now() + grace;
        for p in procs.iter_mut().filter(|p| p.module == module) {
            while Instant::now() < deadline {
                if let Ok(Some(_)) = p.child.try_wait() {
                    break;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
            if let Ok(None) = p.child.try_wait() {
                let _ = p.child.kill();
                let _ = p.child.wait();
            }
        }
    }

    /// Checks that every spawned process is still running (during startup).
    pub fn check_processes(&self) -> Result<(), String> {
        for p in self.processes.lock().unwrap().iter_mut() {
            if let Ok(Some(status)) = p.child.try_wait() {
                return Err(format!(
                    "the worker process of module '{}' exited during startup ({status}); last lines of {}:\n{}",
                    p.module,
                    p.log.display(),
                    tail(&p.log, 15)
                ));
            }
        }
        Ok(())
    }
}

impl Drop for Link {
    fn drop(&mut self) {
        // Tell every worker of the run to leave, then make sure the ones we started did.
        let (c, subject) = (self.client.clone(), format!("{}.stop", self.prefix));
        let stop = self.seal(&subject, b"{}".to_vec());
        let flush = Duration::from_millis(if self.abandoning() { 300 } else { 2000 });
        let _ = self.rt.block_on(async move {
            let _ = c.publish(subject, stop.into()).await;
            tokio::time::timeout(flush, c.flush()).await
        });
        let modules: Vec<String> = self
            .processes
            .lock()
            .unwrap()
            .iter()
            .map(|p| p.module.clone())
            .collect();
        let grace = if self.abandoning() { 1 } else { 3 };
        for m in modules {
            self.reap(&m, Duration::from_secs(grace));
        }
        self.record_security();
    }
}

fn answer_hello(
    payload: &[u8],
    offers: &HashMap<String, ModuleOffer>,
    base: &serde_json::Value,
    workers: &Mutex<HashMap<String, WorkerInfo>>,
    started: &std::sync::atomic::AtomicBool,
) -> serde_json::Value {
    let hello: Hello = match serde_json::from_slice(payload) {
        Ok(h) => h,
        Err(e) => return json!({"ok": false, "error": format!("bad hello: {e}")}),
    };
    if hello.protocol != PROTOCOL {
        return json!({"ok": false, "error": format!("this core speaks protocol {PROTOCOL}, the worker {}", hello.protocol)});
    }
    let Some(offer) = offers.get(&hello.module) else {
        let mut known: Vec<&String> = offers.keys().collect();
        known.sort();
        return json!({"ok": false, "error": format!("this run has no remote module '{}' (remote modules: {known:?})", hello.module)});
    };
    if started.load(std::sync::atomic::Ordering::SeqCst) {
        return json!({"ok": false, "error": "the run has already started; workers must join before the first step"});
    }
    let mut w = workers.lock().unwrap();
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
    let mut answer = base.clone();
    let o = answer.as_object_mut().expect("object");
    o.insert("ok".into(), true.into());
    o.insert("protocol".into(), PROTOCOL.into());
    o.insert("module".into(), hello.module.into());
    o.insert("plugin".into(), offer.plugin.clone().into());
    o.insert("params".into(), offer.params.clone());
    o.insert("shards".into(), offer.shards.into());
    answer
}

/// The last `n` lines of a log file.
pub fn tail(path: &Path, n: usize) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}
