//! The NATS transport: every plugin in a worker process of its own, on this machine
//! or another, stepped over NATS request/reply (docs/nats-protocol.md).
//!
//! The engine does not change: each worker-run module is a [`remote::RemoteModule`]
//! behind the same `Module` trait, so barriers, ordering and recording are the
//! in-process ones and a run records the same messages either way.

pub mod bridge;
pub mod link;
pub mod remote;
pub mod server;
pub mod wire;
pub mod worker;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

pub use bridge::PLUGIN as BRIDGE_PLUGIN;
use link::{connect_options, Link, ModuleOffer, Timeouts};
use remote::RemoteModule;
use server::{find_server, SpawnedServer};

use crate::config::{LoadedConfig, ModuleConfig};
use crate::engine::{ModuleSpec, Tap};
use crate::message::{Payload, SharedMessage};
use crate::module::Module;
use crate::replay;
use crate::run::{build_modules, PrepareError};
use crate::topic::Pattern;

/// Header naming the source module on mirrored messages (and marking them as ours).
pub const MIRROR_SOURCE_HEADER: &str = "Caviar-Source";

/// How to start a worker: the interpreter and arguments before `--nats …`.
pub struct WorkerLauncher {
    pub command: Vec<String>,
}

/// The run id: the configured one, else the run directory's name made subject-safe.
fn run_id(cfg: &LoadedConfig, run_dir: &Path) -> String {
    cfg.config.transport.nats.run_id.clone().unwrap_or_else(|| {
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

/// The modules run by workers: all but the built-ins.
fn remote_modules(cfg: &LoadedConfig) -> impl Iterator<Item = (&String, &ModuleConfig)> {
    let builtin = |p: &str| p == replay::PLUGIN || p == BRIDGE_PLUGIN;
    cfg.config
        .modules
        .iter()
        .filter(move |(_, m)| !builtin(&m.plugin))
}

/// Arguments that give a worker the run's connection settings (secrets go by environment).
fn connection_args(cfg: &LoadedConfig) -> (Vec<String>, Vec<(String, String)>) {
    let n = &cfg.config.transport.nats;
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
    (args, envs)
}

/// Starts (or reaches) the server, starts the workers, waits until every module's
/// plugin is loaded and returns the modules and the mirror tap.
pub fn prepare(
    cfg: &LoadedConfig,
    launcher: Option<WorkerLauncher>,
    run_dir: &Path,
) -> Result<(Vec<ModuleSpec>, Option<Tap>), PrepareError> {
    let n = &cfg.config.transport.nats;
    let io = PrepareError::Io;
    let id = run_id(cfg, run_dir);
    let server = if n.spawns_server() {
        let python = launcher.as_ref().map(|l| PathBuf::from(&l.command[0]));
        let bin = find_server(
            n.server.as_ref().map(|p| cfg.resolve(p)).as_deref(),
            python.as_deref(),
        )
        .map_err(|e| cfg.error_at("transport.nats.spawn", e))?;
        Some(
            SpawnedServer::start(&bin, "127.0.0.1", &run_dir.join("nats-server.log"))
                .map_err(io)?,
        )
    } else {
        None
    };
    let url = server
        .as_ref()
        .map(|s| s.url.clone())
        .or_else(|| n.url.clone())
        .expect("validated: url or spawn");
    let options = connect_options(n, &|p| cfg.resolve(p)).map_err(io)?;
    let mut offers = HashMap::new();
    for (name, m) in remote_modules(cfg) {
        offers.insert(
            name.clone(),
            ModuleOffer {
                plugin: m.plugin.clone(),
                params: cfg.params_json(name),
                shards: m.shards,
            },
        );
    }
    let base = serde_json::json!({
        "run_dir": run_dir.canonicalize().unwrap_or_else(|_| run_dir.to_path_buf()),
        "config_dir": cfg.base_dir.canonicalize().unwrap_or_else(|_| cfg.base_dir.clone()),
    });
    let link = Link::connect(
        &url,
        options,
        &id,
        offers,
        base,
        Timeouts::from_config(n),
        server,
    )
    .map_err(io)?;

    // Start the workers this run owns; tell the user about the ones it waits for.
    let (extra_args, envs) = connection_args(cfg);
    let logs = run_dir.join("workers");
    for (name, m) in remote_modules(cfg) {
        let count = m.workers.unwrap_or(m.shards);
        if count == 0 {
            eprintln!("caviar: waiting for module '{name}': start `caviar worker --nats {url} --run {id} --module {name}`");
            continue;
        }
        let Some(l) = &launcher else {
            return Err(cfg
                .error_at(
                    &format!("modules.{name}.workers"),
                    "starting workers needs the Python package's caviar-core (pip install .); \
                     or set workers = 0 and start `caviar worker` yourself",
                )
                .into());
        };
        std::fs::create_dir_all(&logs).map_err(|e| io(format!("{}: {e}", logs.display())))?;
        for i in 0..count {
            let mut cmd = l.command.clone();
            cmd.extend([
                "--nats".into(),
                url.clone(),
                "--run".into(),
                id.clone(),
                "--module".into(),
                name.clone(),
            ]);
            cmd.extend(["--worker-id".into(), format!("{name}-{i}")]);
            cmd.extend(extra_args.iter().cloned());
            link.spawn_worker(name, &cmd, &envs, &logs.join(format!("{name}-{i}.log")))
                .map_err(io)?;
        }
    }
    let ready = wait_for_workers(cfg, &link)?;

    let specs = build_modules(cfg, |name, m| {
        let module: Box<dyn Module> = if m.plugin == BRIDGE_PLUGIN {
            Box::new(bridge::Bridge::from_config(cfg, name, link.clone())?)
        } else {
            let (subs, ids) = ready[name].clone();
            Box::new(RemoteModule::new(link.clone(), name, subs, ids, m.shards))
        };
        Ok(Some(module))
    })?;
    Ok((specs, mirror_tap(cfg, link)))
}

/// A module's default subscriptions and the ids of its workers, once they are ready.
type Ready = HashMap<String, (Vec<String>, Vec<String>)>;

/// Waits until each remote module has its workers connected with the plugin loaded;
/// returns each module's default subscriptions and worker ids.
fn wait_for_workers(cfg: &LoadedConfig, link: &Link) -> Result<Ready, PrepareError> {
    let timeout = link.timeouts.startup;
    let t0 = Instant::now();
    loop {
        link.check_processes().map_err(PrepareError::Io)?;
        let mut ready = HashMap::new();
        let mut missing = Vec::new();
        for (name, m) in remote_modules(cfg) {
            let workers = link.workers_of(name);
            for w in &workers {
                if let Some(Err(e)) = &w.loaded {
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
                    return Err(cfg.error_at(&key, message).into());
                }
            }
            let loaded: Vec<_> = workers
                .iter()
                .filter(|w| matches!(w.loaded, Some(Ok(_))))
                .collect();
            if loaded.len() >= m.workers.unwrap_or(m.shards).max(1) as usize {
                let subs = match &loaded[0].loaded {
                    Some(Ok(s)) => s.clone(),
                    _ => unreachable!(),
                };
                ready.insert(
                    name.clone(),
                    (subs, loaded.iter().map(|w| w.id.clone()).collect()),
                );
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
                link.url,
                link.run_id
            )));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Publishes the episode's data messages on their own subjects (the paper's names).
fn mirror_tap(cfg: &LoadedConfig, link: Arc<Link>) -> Option<Tap> {
    let patterns: Vec<Pattern> = cfg
        .config
        .transport
        .nats
        .mirror
        .iter()
        .map(|p| Pattern::new(p).expect("validated"))
        .collect();
    if patterns.is_empty() {
        // The link must still live as long as the engine: the remote modules hold it.
        return None;
    }
    Some(Box::new(move |messages: &[SharedMessage]| {
        let client = link.client.clone();
        let batch: Vec<SharedMessage> = messages
            .iter()
            .filter(|m| patterns.iter().any(|p| p.matches(&m.topic)))
            .cloned()
            .collect();
        if batch.is_empty() {
            return;
        }
        link.rt.block_on(async move {
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
