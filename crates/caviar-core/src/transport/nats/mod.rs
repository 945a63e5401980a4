//! The NATS transport: every plugin in a worker process of its own, on this machine
//! or another, stepped over NATS request/reply (docs/nats-protocol.md).
//!
//! The engine does not change: each worker-run module is a [`remote::WorkerModule`],
//! a [`crate::module::RemoteModule`], so barriers, ordering and recording are the
//! in-process ones and a run records the same messages either way.
//!
//! A leaf of the crate, reached through [`crate::transport::Transport`] ([`Nats`]).
//! Inside, lowest first: [`wire`] (frames), [`auth`] (run key, sequence numbers),
//! [`server`] (nats-server), [`settings`] (`[transport.nats]`), `client` (connection,
//! sealing, security), `control` (hello / loaded / heartbeat), `supervisor` (the
//! processes this run started), `link` (the three together), `remote` and `bridge`
//! (modules), [`worker`] (the Rust worker), `python` (the Python worker's bindings).
//! Public for benchmarks and tests: [`prepare`], [`server`], [`settings`], [`worker`],
//! [`wire`] (the frame codec, fuzzed by tests/fuzz.rs).

pub mod auth;
pub(crate) mod bridge;
pub(crate) mod client;
pub(crate) mod control;
pub(crate) mod link;
#[cfg(feature = "python")]
pub(crate) mod python;
pub(crate) mod remote;
pub mod server;
pub mod settings;
pub(crate) mod supervisor;
pub mod wire;
pub mod worker;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use auth::{RunKey, KEY_ENV, KEY_FILE_ENV};
use client::{connect_options, Client};
use control::{ControlPlane, ModuleOffer, WorkerInfo};
use link::{Link, Timeouts};
use remote::{Ready, WorkerModule};
use server::{find_server, write_private, ServerAuth, SpawnedServer};
use settings::NatsSettings;
use supervisor::Supervisor;
use wire::MIRROR_SOURCE_HEADER;

use super::interface::{Connection, Prepared, Transport, WorkerLauncher};
use crate::assembly::{build_modules, is_builtin, PrepareError};
use crate::config::{ConfigError, LoadedConfig, ModuleConfig};
use crate::engine::Tap;
use crate::message::{Payload, SharedMessage};
use crate::module::AnyModule;
use crate::topic::Pattern;

/// `caviar.nats-bridge`: brings plain NATS messages into the episode.
pub const BRIDGE_PLUGIN: &str = "caviar.nats-bridge";

/// `transport.kind = "nats"`.
pub struct Nats;

impl Transport for Nats {
    fn kind(&self) -> &'static str {
        "nats"
    }

    fn builtin_plugins(&self) -> &'static [&'static str] {
        &[BRIDGE_PLUGIN]
    }

    /// The bridge publishes its subjects.
    fn builtin_publishes(&self, cfg: &LoadedConfig, module: &str) -> Option<Vec<String>> {
        serde_json::from_value(cfg.params_json(module)["subjects"].clone()).ok()
    }

    fn check(&self, cfg: &LoadedConfig) -> Result<(), ConfigError> {
        NatsSettings::from_config(cfg).map(drop)
    }

    fn check_files(&self, cfg: &LoadedConfig) -> Result<(), ConfigError> {
        NatsSettings::from_config(cfg)?.check_files(cfg)
    }

    fn step_timeout(&self, cfg: &LoadedConfig) -> Option<f64> {
        NatsSettings::from_config(cfg).ok()?.step_timeout
    }

    fn prepare(
        &self,
        cfg: &LoadedConfig,
        launcher: Option<&WorkerLauncher>,
        run_dir: &Path,
    ) -> Result<Prepared, PrepareError> {
        prepare(cfg, launcher, run_dir)
    }
}

/// The session's handle on the run's link: `security` for run.json, shutdown.
struct RunConnection(Arc<Link>);

impl Connection for RunConnection {
    fn status(&self) -> serde_json::Map<String, serde_json::Value> {
        let mut m = serde_json::Map::new();
        m.insert(
            "security".into(),
            self.0.conn.security.lock().unwrap().to_json(),
        );
        m
    }

    fn shutdown(&self) {
        self.0.shutdown();
    }
}

/// The run id: the configured one, else the run directory's name made subject-safe.
fn run_id(n: &NatsSettings, run_dir: &Path) -> String {
    n.run_id.clone().unwrap_or_else(|| {
        let name = run_dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "run".into());
        name.chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                    c
                } else {
                    '_'
                }
            })
            .collect()
    })
}

/// The modules run by workers: all but the built-ins (the core's and the bridge).
fn remote_modules(cfg: &LoadedConfig) -> impl Iterator<Item = (&String, &ModuleConfig)> {
    cfg.config
        .modules
        .iter()
        .filter(|(_, m)| !is_builtin(&m.plugin) && m.plugin != BRIDGE_PLUGIN)
}

/// Arguments that give a worker the run's connection settings; secrets (the server's
/// password, the run key) go by environment, never on the command line, where any
/// user of the machine can read them.
fn connection_args(
    cfg: &LoadedConfig,
    n: &NatsSettings,
    link: &Link,
    auth: Option<&ServerAuth>,
) -> (Vec<String>, Vec<(String, String)>) {
    let mut args = Vec::new();
    let path = |p: &PathBuf| cfg.resolve(p).to_string_lossy().into_owned();
    for (flag, value) in [
        ("--creds", &n.credentials),
        ("--tls-ca", &n.tls_ca),
        ("--tls-cert", &n.tls_cert),
        ("--tls-key", &n.tls_key),
    ] {
        if let Some(v) = value {
            args.extend([flag.to_string(), path(v)]);
        }
    }
    let mut envs = Vec::new();
    for (var, value) in [
        ("NATS_TOKEN", &n.token),
        ("NATS_USER", &n.user),
        ("NATS_PASSWORD", &n.password),
    ] {
        if let Some(v) = value {
            envs.push((var.to_string(), v.clone()));
        }
    }
    if let Some(a) = auth {
        // A server of our own: its credentials, made for this run.
        envs.retain(|(k, _)| !k.starts_with("NATS_"));
        envs.push(("NATS_USER".into(), a.user.clone()));
        envs.push(("NATS_PASSWORD".into(), a.password.clone()));
    }
    envs.push((KEY_ENV.into(), link.conn.sealer.key.hex().into()));
    (args, envs)
}

/// Starts (or reaches) the server, starts the workers, waits until every module's
/// plugin is loaded and returns the modules, the mirror tap and the run's connection.
pub fn prepare(
    cfg: &LoadedConfig,
    launcher: Option<&WorkerLauncher>,
    run_dir: &Path,
) -> Result<Prepared, PrepareError> {
    let n = NatsSettings::from_config(cfg)?;
    let server = start_server(cfg, &n, launcher, run_dir)?;
    let auth = server.as_ref().and_then(|s| s.auth.clone());
    let link = connect(cfg, &n, run_dir, server)?;
    spawn_workers(cfg, &n, launcher, &link, auth.as_ref(), run_dir)?;
    let mut ready = wait_for_workers(cfg, &link)?;
    let specs = build_modules(cfg, |name, m| {
        Ok(Some(if m.plugin == BRIDGE_PLUGIN {
            AnyModule::local(bridge::Bridge::from_config(cfg, name, link.clone())?)
        } else {
            let r = ready.remove(name).expect("every remote module is ready");
            AnyModule::remote(WorkerModule::new(link.clone(), name, r, m.shards))
        }))
    })?;
    Ok(Prepared {
        modules: specs,
        tap: mirror_tap(&n, link.clone()),
        connection: Box::new(RunConnection(link)),
    })
}

/// The server this run starts, if it starts one (`transport.nats.spawn`).
fn start_server(
    cfg: &LoadedConfig,
    n: &NatsSettings,
    launcher: Option<&WorkerLauncher>,
    run_dir: &Path,
) -> Result<Option<SpawnedServer>, PrepareError> {
    if !n.spawns_server() {
        return Ok(None);
    }
    let python = launcher.map(|l| PathBuf::from(&l.command[0]));
    let bin = find_server(
        n.server.as_ref().map(|p| cfg.resolve(p)).as_deref(),
        python.as_deref(),
    )
    .map_err(|e| cfg.error_at("transport.nats.spawn", e))?;
    let log = run_dir.join("nats-server.log");
    let auth = ServerAuth::generate().map_err(PrepareError::Io)?;
    Ok(Some(
        SpawnedServer::start_with_auth(&bin, "127.0.0.1", &log, Some(auth))
            .map_err(PrepareError::Io)?,
    ))
}

/// Connects to the run's server and starts answering workers with their module.
fn connect(
    cfg: &LoadedConfig,
    n: &NatsSettings,
    run_dir: &Path,
    server: Option<SpawnedServer>,
) -> Result<Arc<Link>, PrepareError> {
    let url = server
        .as_ref()
        .map(|s| s.url.clone())
        .or_else(|| n.url.clone())
        .expect("validated: url or spawn");
    let mut options = connect_options(n, &|p| cfg.resolve(p)).map_err(PrepareError::Io)?;
    if let Some(a) = server.as_ref().and_then(|s| s.auth.as_ref()) {
        options = options.user_and_password(a.user.clone(), a.password.clone());
    }
    let key = match &n.key_file {
        Some(f) => {
            let path = cfg.resolve(f);
            let text = std::fs::read_to_string(&path).map_err(|e| {
                cfg.error_at(
                    "transport.nats.key_file",
                    format!("{}: {e}", path.display()),
                )
            })?;
            RunKey::from_key_file_text(&text).map_err(|e| {
                cfg.error_at(
                    "transport.nats.key_file",
                    format!("{}: {e}", path.display()),
                )
            })?
        }
        None => RunKey::generate().map_err(PrepareError::Io)?,
    };
    let offers = remote_modules(cfg)
        .map(|(name, m)| {
            let offer = ModuleOffer {
                plugin: m.plugin.clone(),
                params: cfg.params_json(name),
                shards: m.shards,
            };
            (name.clone(), offer)
        })
        .collect();
    let base = serde_json::json!({
        "run_dir": run_dir.canonicalize().unwrap_or_else(|_| run_dir.to_path_buf()),
        "config_dir": cfg.base_dir.canonicalize().unwrap_or_else(|_| cfg.base_dir.clone()),
    });
    let timeouts = Timeouts::from_config(n, n.step_timeout(cfg));
    let conn = Client::open(&url, options, &run_id(n, run_dir), key).map_err(PrepareError::Io)?;
    let control = ControlPlane::listen(&conn, offers, base).map_err(PrepareError::Io)?;
    Ok(Arc::new(Link::new(
        conn,
        control,
        Supervisor::new(server),
        timeouts,
    )))
}

/// Starts the workers this run owns; tells the user about the ones it waits for.
fn spawn_workers(
    cfg: &LoadedConfig,
    n: &NatsSettings,
    launcher: Option<&WorkerLauncher>,
    link: &Link,
    auth: Option<&ServerAuth>,
    run_dir: &Path,
) -> Result<(), PrepareError> {
    let (url, id) = (&link.conn.url, link.conn.run_id());
    let (extra_args, envs) = connection_args(cfg, n, link, auth);
    let logs = run_dir.join("workers");
    let mut key_file = n.key_file.as_ref().map(|f| cfg.resolve(f));
    for (name, m) in remote_modules(cfg) {
        let count = m.workers.unwrap_or(m.shards);
        if count == 0 {
            let file = match &key_file {
                Some(f) => f.clone(),
                None => {
                    // Workers started by hand need the run key (and a server of our
                    // own's credentials): in a file only this user can read.
                    let f = run_dir.join("run.key");
                    let mut text = format!("{KEY_ENV}={}\n", link.conn.sealer.key.hex());
                    if let Some(a) = auth {
                        text += &format!("NATS_USER={}\nNATS_PASSWORD={}\n", a.user, a.password);
                    }
                    write_private(&f, &text)
                        .map_err(|e| PrepareError::Io(format!("{}: {e}", f.display())))?;
                    key_file = Some(f.clone());
                    f
                }
            };
            let file = file.canonicalize().unwrap_or(file);
            eprintln!(
                "caviar: waiting for module '{name}': start `{KEY_FILE_ENV}={} caviar worker --nats {url} --run {id} --module {name}`",
                file.display()
            );
            continue;
        }
        let Some(l) = launcher else {
            return Err(cfg
                .error_at(
                    &format!("modules.{name}.workers"),
                    "starting workers needs the Python package's caviar-core (pip install .); \
                     or set workers = 0 and start `caviar worker` yourself",
                )
                .into());
        };
        std::fs::create_dir_all(&logs)
            .map_err(|e| PrepareError::Io(format!("{}: {e}", logs.display())))?;
        for i in 0..count {
            let mut cmd = l.command.clone();
            cmd.extend(["--nats", url, "--run", id, "--module", name].map(String::from));
            cmd.extend(["--worker-id".into(), format!("{name}-{i}")]);
            cmd.extend(extra_args.iter().cloned());
            let log = logs.join(format!("{name}-{i}.log"));
            link.procs
                .spawn_worker(name, &cmd, &envs, &log)
                .map_err(PrepareError::Io)?;
        }
    }
    Ok(())
}

/// The configuration error of a worker that could not load its plugin.
fn load_failure(cfg: &LoadedConfig, name: &str, w: &WorkerInfo) -> Option<PrepareError> {
    let Some(Err(e)) = &w.loaded else {
        return None;
    };
    let key = format!(
        "modules.{name}.{}",
        e.key.clone().unwrap_or_else(|| "plugin".into())
    );
    let mut message = format!("worker {} on {}: {}", w.id, w.host, e.message);
    if e.key.is_none() {
        if let Some(t) = &e.trace {
            message = format!("{message}\n{}", t.trim_end());
        }
    }
    Some(cfg.error_at(&key, message).into())
}

/// Waits until each remote module has its workers connected with the plugin loaded.
fn wait_for_workers(
    cfg: &LoadedConfig,
    link: &Link,
) -> Result<HashMap<String, Ready>, PrepareError> {
    let timeout = link.timeouts.startup;
    let t0 = Instant::now();
    loop {
        link.procs.check_startup().map_err(PrepareError::Io)?;
        let mut ready = HashMap::new();
        let mut missing = Vec::new();
        for (name, m) in remote_modules(cfg) {
            let workers = link.control.workers_of(name);
            if let Some(e) = workers.iter().find_map(|w| load_failure(cfg, name, w)) {
                return Err(e);
            }
            let loaded: Vec<_> = workers
                .iter()
                .filter_map(|w| match &w.loaded {
                    Some(Ok(p)) => Some((w.id.clone(), p)),
                    _ => None,
                })
                .collect();
            if loaded.len() >= m.workers.unwrap_or(m.shards).max(1) as usize {
                let plugin = loaded[0].1.clone();
                let workers = loaded.into_iter().map(|(id, _)| id).collect();
                ready.insert(name.clone(), Ready { plugin, workers });
            } else {
                missing.push(name.as_str());
            }
        }
        if missing.is_empty() {
            return Ok(ready);
        }
        if t0.elapsed() > timeout {
            return Err(PrepareError::Io(format!(
                "no worker with its plugin loaded within {:.0} s (transport.nats.startup_timeout) for module(s) {} \
                 on {} (run id '{}')",
                timeout.as_secs_f64(),
                missing.join(", "),
                link.conn.url,
                link.conn.run_id()
            )));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Publishes the episode's data messages on their own subjects (the paper's names).
fn mirror_tap(n: &NatsSettings, link: Arc<Link>) -> Option<Tap> {
    let patterns: Vec<Pattern> = n
        .mirror
        .iter()
        .map(|p| Pattern::new(p).expect("validated"))
        .collect();
    if patterns.is_empty() {
        // The link must still live as long as the engine: the remote modules hold it.
        return None;
    }
    Some(Box::new(move |messages: &[SharedMessage]| {
        let client = link.conn.client.clone();
        let batch: Vec<SharedMessage> = messages
            .iter()
            .filter(|m| patterns.iter().any(|p| p.matches(&m.topic)))
            .cloned()
            .collect();
        if batch.is_empty() {
            return;
        }
        link.conn.rt.block_on(async move {
            for m in batch {
                let mut h = async_nats::HeaderMap::new();
                h.insert(MIRROR_SOURCE_HEADER, m.source.as_str());
                h.insert("Caviar-Step", m.step.to_string().as_str());
                h.insert("Caviar-Time", m.time.to_string().as_str());
                h.insert("Caviar-Kind", m.payload.kind().as_str());
                let body = match &m.payload {
                    Payload::Json(t) | Payload::Artifact(t) => {
                        bytes::Bytes::from(t.clone().into_bytes())
                    }
                    Payload::Binary { meta, data } => {
                        h.insert("Caviar-Meta", meta.as_str());
                        bytes::Bytes::from(data.clone())
                    }
                };
                // A mirror is for observers: a full client buffer must not stop the run.
                let _ = client.publish_with_headers(m.topic.clone(), h, body).await;
            }
        });
    }))
}
