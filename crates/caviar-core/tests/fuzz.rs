//! Fuzzing of the parsers that take input from outside (issue #28): the wire frame
//! codec, the topic matcher, the TOML loader with `--set` overrides and the
//! run-directory reader. proptest generates their inputs, and mutates a corpus seeded
//! from the tests and the blueprints (flipped, inserted, deleted, duplicated and
//! truncated bytes). The property everywhere: no panic, no hang, and every rejection a
//! clean error that says what was wrong (and, for files, which file).
//!
//! Bounded by default: a fixed number of cases per target from a fixed seed, the same
//! cases on every run (a few seconds each in a debug build). Longer on demand:
//!
//! ```text
//! CAVIAR_FUZZ_SECONDS=300 cargo test --release --test fuzz -- --nocapture
//! ```
//!
//! runs each target for that long, on fresh seeds. `CAVIAR_FUZZ_REPORT=FILE` appends a
//! JSON line per target (cases, seconds, failures); `scripts/fuzz.sh` collects them in
//! `docs/results/reliability.json`.

use std::fmt::Debug;
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use proptest::prelude::*;
use proptest::sample::{select, Index};
use proptest::test_runner::{Config, RngAlgorithm, TestCaseError, TestRng, TestRunner};

use caviar_core::config;
use caviar_core::inspect::inspect;
use caviar_core::module::Usage;
use caviar_core::recorder::{read_messages, read_timings, Recorder};
use caviar_core::status::{RunState, RunStatus};
use caviar_core::topic::{validate_topic, Pattern};
use caviar_core::transport::nats::wire;
use caviar_core::{
    AnyModule, Engine, EngineOptions, Message, Module, ModuleError, ModuleSpec, Outgoing, Payload,
    SharedMessage, StepInfo,
};

/// One case running longer than this is a hang: the process says which and aborts.
const HANG: Duration = Duration::from_secs(20);

// ---------------------------------------------------------------------------------
// The harness: proptest's runner, counted, bounded, watched for hangs.

/// The case in progress, for the hang watch.
#[derive(Default)]
struct Current {
    since: Option<Instant>,
    input: String,
}

/// Runs `check` on inputs from `strategy`: `cases` of them from a fixed seed, or, with
/// `CAVIAR_FUZZ_SECONDS`, fresh seeds for that long. A failing case (an `Err` or a
/// panic) is shrunk by proptest and reported with the target's name.
fn fuzz<S>(
    target: &str,
    cases: u32,
    strategy: S,
    check: impl Fn(S::Value) -> Result<(), TestCaseError>,
) where
    S: Strategy,
    S::Value: Debug,
{
    let seconds: Option<f64> = std::env::var("CAVIAR_FUZZ_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok());
    let started = Instant::now();
    let count = AtomicU64::new(0);
    let current = Arc::new(Mutex::new(Current::default()));
    let done = Arc::new(AtomicBool::new(false));
    let watch = {
        let (current, done, target) = (current.clone(), done.clone(), target.to_string());
        std::thread::spawn(move || {
            while !done.load(Ordering::Relaxed) {
                std::thread::sleep(Duration::from_millis(200));
                let c = current.lock().unwrap_or_else(|p| p.into_inner());
                if c.since.is_some_and(|t| t.elapsed() > HANG) {
                    eprintln!(
                        "fuzz {target}: a case ran for more than {} s (a hang) on input:\n{}",
                        HANG.as_secs(),
                        c.input
                    );
                    std::process::abort();
                }
            }
        })
    };
    let mut round = 0u64;
    let result = loop {
        let config = Config {
            cases: if seconds.is_some() { 2000 } else { cases },
            failure_persistence: None,
            max_shrink_iters: 4096,
            ..Config::default()
        };
        let rng = match seconds {
            None => TestRng::deterministic_rng(RngAlgorithm::ChaCha),
            Some(_) => {
                let nanos = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_nanos() as u64);
                let mut seed = [0u8; 32];
                seed[..8].copy_from_slice(&nanos.to_le_bytes());
                seed[8..16].copy_from_slice(&round.to_le_bytes());
                TestRng::from_seed(RngAlgorithm::ChaCha, &seed)
            }
        };
        let mut runner = TestRunner::new_with_rng(config, rng);
        let outcome = runner.run(&strategy, |value| {
            count.fetch_add(1, Ordering::Relaxed);
            {
                let mut c = current.lock().unwrap_or_else(|p| p.into_inner());
                c.input = format!("{value:.2000?}");
                c.since = Some(Instant::now());
            }
            let r = check(value);
            current.lock().unwrap_or_else(|p| p.into_inner()).since = None;
            r
        });
        round += 1;
        match seconds {
            Some(s) if outcome.is_ok() && started.elapsed().as_secs_f64() < s => continue,
            _ => break outcome,
        }
    };
    done.store(true, Ordering::Relaxed);
    let _ = watch.join();
    let cases = count.load(Ordering::Relaxed);
    let elapsed = started.elapsed().as_secs_f64();
    eprintln!(
        "fuzz {target}: {cases} cases in {elapsed:.1} s, {}",
        if result.is_ok() {
            "no failure"
        } else {
            "FAILED"
        }
    );
    if let Ok(path) = std::env::var("CAVIAR_FUZZ_REPORT") {
        let line = serde_json::json!({
            "target": target, "cases": cases, "seconds": elapsed,
            "failures": u32::from(result.is_err()),
        });
        if let Ok(mut f) = fs::OpenOptions::new().create(true).append(true).open(path) {
            let _ = writeln!(f, "{line}");
        }
    }
    if let Err(e) = result {
        panic!("fuzz {target}: {e}");
    }
}

/// Byte-level mutations of a seed: what a corrupt file, a truncated frame or a typo does.
#[derive(Debug, Clone)]
enum Edit {
    Flip(Index, u8),
    Insert(Index, u8),
    Delete(Index, usize),
    Duplicate(Index, usize),
    Interesting(Index, u8),
    Truncate(Index),
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<Index>(), 1u8..=255).prop_map(|(i, b)| Edit::Flip(i, b)),
        (any::<Index>(), any::<u8>()).prop_map(|(i, b)| Edit::Insert(i, b)),
        (any::<Index>(), 1usize..64).prop_map(|(i, n)| Edit::Delete(i, n)),
        (any::<Index>(), 1usize..64).prop_map(|(i, n)| Edit::Duplicate(i, n)),
        (any::<Index>(), any::<u8>()).prop_map(|(i, b)| Edit::Interesting(i, b)),
        any::<Index>().prop_map(Edit::Truncate),
    ]
}

/// Bytes that parsers treat specially (quotes, brackets, separators, digits, UTF-8 lead bytes).
const INTERESTING: &[u8] = b"\"'[]{}=.,:#\n\\0-9 \x00\xff\xc3\xe2*>eE+";

fn apply(mut data: Vec<u8>, edits: &[Edit]) -> Vec<u8> {
    for e in edits {
        let n = data.len();
        match *e {
            Edit::Flip(ref i, b) if n > 0 => data[i.index(n)] ^= b,
            Edit::Insert(ref i, b) => data.insert(i.index(n + 1), b),
            Edit::Delete(ref i, len) if n > 0 => {
                let at = i.index(n);
                data.drain(at..(at + len).min(n));
            }
            Edit::Duplicate(ref i, len) if n > 0 => {
                let at = i.index(n);
                let chunk = data[at..(at + len).min(n)].to_vec();
                data.splice(at..at, chunk);
            }
            Edit::Interesting(ref i, b) if n > 0 => {
                data[i.index(n)] = INTERESTING[b as usize % INTERESTING.len()]
            }
            Edit::Truncate(ref i) => data.truncate(i.index(n + 1)),
            _ => {}
        }
    }
    data
}

/// A seed from `seeds`, mutated by up to `max_edits` edits (sometimes none).
fn mutated(seeds: Vec<Vec<u8>>, max_edits: usize) -> impl Strategy<Value = Vec<u8>> {
    (select(seeds), prop::collection::vec(edit(), 0..=max_edits))
        .prop_map(|(seed, edits)| apply(seed, &edits))
}

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

// ---------------------------------------------------------------------------------
// The wire frame codec.

fn payload() -> impl Strategy<Value = Payload> {
    prop_oneof![
        "[ -~]{0,40}".prop_map(Payload::Json),
        "\\PC{0,20}".prop_map(Payload::Artifact),
        ("[ -~]{0,20}", prop::collection::vec(any::<u8>(), 0..64))
            .prop_map(|(meta, data)| Payload::Binary { meta, data }),
    ]
}

fn topic() -> impl Strategy<Value = String> {
    prop::collection::vec("[a-zA-Z0-9_-]{1,6}", 1..4).prop_map(|t| t.join("."))
}

fn message() -> impl Strategy<Value = Message> {
    (
        any::<u64>(),
        any::<f64>().prop_filter("finite", |t| t.is_finite()),
        topic(),
        "[a-z]{0,8}",
        payload(),
    )
        .prop_map(|(step, time, topic, source, payload)| Message {
            step,
            time,
            topic,
            source,
            payload,
        })
}

#[test]
fn wire_frames_round_trip_exactly() {
    let cases = (
        any::<u64>(),
        any::<f64>().prop_filter("finite", |t| t.is_finite()),
        prop::collection::vec(message(), 0..5),
    );
    fuzz("wire round trip", 2000, cases, |(step, time, inbox)| {
        let shared: Vec<SharedMessage> = inbox.iter().cloned().map(Arc::new).collect();
        let frame = wire::encode_request(StepInfo { step, time }, 1, 3, &shared);
        let (req, back) = wire::decode_request(&frame).map_err(TestCaseError::fail)?;
        prop_assert_eq!(
            (req.step, req.time.to_bits(), req.shard, req.shards),
            (step, time.to_bits(), 1, 3)
        );
        prop_assert_eq!(back.len(), inbox.len());
        for (a, b) in back.iter().zip(&inbox) {
            // Bit for bit: a run over NATS records the same times as one in process.
            prop_assert_eq!(
                (a.step, a.time.to_bits(), &a.topic, &a.source, &a.payload),
                (b.step, b.time.to_bits(), &b.topic, &b.source, &b.payload)
            );
        }
        let out: Vec<Outgoing> = inbox
            .iter()
            .map(|m| Outgoing::new(m.topic.clone(), m.payload.clone()))
            .collect();
        let usage = Usage {
            wall_s: time.abs(),
            cpu_s: 0.5,
            rss_mib: 12.0,
            gpu_util_pct: None,
            gpu_mem_mib: None,
        };
        let mut decoded = Vec::new();
        let got = wire::decode_reply(&wire::encode_reply(&out, usage), &mut decoded)
            .map_err(|e| TestCaseError::fail(e.message))?;
        prop_assert_eq!(got.wall_s.to_bits(), time.abs().to_bits());
        prop_assert_eq!(decoded, out);
        Ok(())
    });
}

#[test]
fn corrupt_frames_are_rejected_with_a_reason() {
    // Seeds: valid requests and replies of every payload kind, failures, and junk.
    let inbox: Vec<SharedMessage> = vec![
        Message {
            step: 3,
            time: 0.3,
            topic: "a.b".into(),
            source: "m".into(),
            payload: Payload::Json("{\"x\": 1}".into()),
        },
        Message {
            step: 3,
            time: 0.3,
            topic: "img.rgb".into(),
            source: "cam".into(),
            payload: Payload::Binary {
                meta: "{\"shape\": [2, 2]}".into(),
                data: vec![0, 1, 2, 255],
            },
        },
        Message {
            step: 2,
            time: 0.2,
            topic: "a.file".into(),
            source: "m".into(),
            payload: Payload::Artifact("out/x.png".into()),
        },
    ]
    .into_iter()
    .map(Arc::new)
    .collect();
    let out: Vec<Outgoing> = inbox
        .iter()
        .map(|m| Outgoing::new(m.topic.clone(), m.payload.clone()))
        .collect();
    let usage = Usage {
        wall_s: 0.1,
        cpu_s: 0.1,
        rss_mib: 10.0,
        gpu_util_pct: Some(3.0),
        gpu_mem_mib: None,
    };
    let failure = wire::WireError {
        message: "boom".into(),
        trace: Some("Traceback".into()),
        key: Some("params.x".into()),
    };
    let seeds = vec![
        wire::encode_request(StepInfo { step: 3, time: 0.3 }, 0, 1, &inbox),
        wire::encode_request(
            StepInfo { step: 0, time: 0.0 },
            0,
            1,
            &[] as &[SharedMessage],
        ),
        wire::encode_reply(&out, usage),
        wire::encode_failure(&failure),
        b"\x02\x00\x00\x00{}".to_vec(),
        Vec::new(),
    ];
    let strategy = prop_oneof![
        4 => mutated(seeds, 6),
        1 => prop::collection::vec(any::<u8>(), 0..64),
    ];
    fuzz("wire frames", 20_000, strategy, |bytes| {
        match wire::decode_request(&bytes) {
            Ok((req, inbox)) => prop_assert_eq!(req.messages.len(), 0, "{:?}", inbox),
            Err(e) => prop_assert!(!e.is_empty()),
        }
        let mut out = Vec::new();
        if let Err(e) = wire::decode_reply(&bytes, &mut out) {
            prop_assert!(!e.message.is_empty());
        }
        Ok(())
    });
}

// ---------------------------------------------------------------------------------
// The topic matcher, against a reference written from NATS's rules.

/// NATS subject rules, independently: non-empty tokens without whitespace; `*` and `>`
/// only as whole tokens of a pattern, `>` only last.
fn reference_valid(text: &str, wildcards: bool) -> bool {
    let tokens: Vec<&str> = text.split('.').collect();
    !text.is_empty()
        && tokens.iter().enumerate().all(|(i, t)| {
            !t.is_empty()
                && !t.chars().any(char::is_whitespace)
                && if wildcards {
                    (*t == "*" || *t == ">" || !(t.contains('*') || t.contains('>')))
                        && (*t != ">" || i + 1 == tokens.len())
                } else {
                    !(t.contains('*') || t.contains('>'))
                }
        })
}

fn reference_matches(pattern: &[&str], topic: &[&str]) -> bool {
    match (pattern.split_first(), topic.split_first()) {
        (None, None) => true,
        (Some((&">", _)), Some(_)) => true,
        (Some((p, prest)), Some((t, trest))) => {
            (*p == "*" || p == t) && reference_matches(prest, trest)
        }
        _ => false,
    }
}

fn token() -> impl Strategy<Value = String> {
    prop_oneof![
        6 => select(vec!["a", "b", "ab", "*", ">"]).prop_map(str::to_string),
        1 => select(vec!["", " ", "a*", ">b", "\t", "é", "*>"]).prop_map(str::to_string),
        1 => "\\PC{0,3}",
    ]
}

fn subject() -> impl Strategy<Value = String> {
    prop::collection::vec(token(), 1..5).prop_map(|t| t.join("."))
}

#[test]
fn the_topic_matcher_agrees_with_nats_rules() {
    fuzz(
        "topic matcher",
        20_000,
        (subject(), subject(), subject()),
        |(p, q, t)| {
            prop_assert_eq!(
                validate_topic(&t).is_ok(),
                reference_valid(&t, false),
                "topic {:?}",
                t
            );
            let pattern = Pattern::new(&p);
            prop_assert_eq!(
                pattern.is_ok(),
                reference_valid(&p, true),
                "pattern {:?}",
                p
            );
            if let Err(e) = &pattern {
                prop_assert!(e.to_string().contains(&p), "{}", e);
            }
            let (Ok(pattern), true) = (pattern, reference_valid(&t, false)) else {
                return Ok(());
            };
            let split = |s: &str| s.split('.').map(str::to_string).collect::<Vec<_>>();
            let (pt, tt) = (split(&p), split(&t));
            let (pt, tt): (Vec<&str>, Vec<&str>) = (
                pt.iter().map(String::as_str).collect(),
                tt.iter().map(String::as_str).collect(),
            );
            prop_assert_eq!(
                pattern.matches(&t),
                reference_matches(&pt, &tt),
                "{:?} ~ {:?}",
                p,
                t
            );
            // Overlap: true exactly when some topic matches both (searched over the
            // patterns' own literals and one fresh token, up to one token longer).
            let Ok(other) = Pattern::new(&q) else {
                return Ok(());
            };
            let mut alphabet: Vec<String> = p
                .split('.')
                .chain(q.split('.'))
                .filter(|t| *t != "*" && *t != ">")
                .map(str::to_string)
                .collect();
            alphabet.push("zz".into());
            alphabet.sort();
            alphabet.dedup();
            let longest = p.split('.').count().max(q.split('.').count()) + 1;
            let mut witness = false;
            let mut topics: Vec<Vec<String>> = vec![vec![]];
            for _ in 0..longest {
                topics = topics
                    .into_iter()
                    .flat_map(|t| {
                        alphabet.iter().map(move |a| {
                            let mut t = t.clone();
                            t.push(a.clone());
                            t
                        })
                    })
                    .collect();
                witness |= topics.iter().any(|t| {
                    let s = t.join(".");
                    pattern.matches(&s) && other.matches(&s)
                });
            }
            prop_assert_eq!(
                pattern.overlaps(&other),
                witness,
                "{:?} overlaps {:?}",
                p,
                q
            );
            Ok(())
        },
    );
}

// ---------------------------------------------------------------------------------
// The TOML loader with `--set` overrides.

fn config_seeds() -> Vec<Vec<u8>> {
    let mut seeds = Vec::new();
    for dir in ["blueprints", "tests/data"] {
        let Ok(walk) = fs::read_dir(repo_root().join(dir)) else {
            continue;
        };
        for entry in walk.flatten() {
            let p = entry.path();
            let file = if p.is_dir() { p.join("config.toml") } else { p };
            if file.extension().is_some_and(|e| e == "toml") {
                if let Ok(text) = fs::read(&file) {
                    seeds.push(text);
                }
            }
        }
    }
    seeds.push(
        br#"[episode]
ts = 0.1
steps = 3
stages = ["s"]
pace = 1.0
behind = "drop"

[modules.m]
stage = "s"
plugin = "sample_plugins:Counter"
params = { start = 1, names = ["a", "b"], nested = { x = 1.5 } }
subscribe = ["a.*", "b.>"]
"#
        .to_vec(),
    );
    assert!(
        seeds.len() >= 5,
        "blueprints found at {}",
        repo_root().display()
    );
    seeds
}

fn override_text() -> impl Strategy<Value = String> {
    let key = prop_oneof![
        select(vec![
            "episode.ts",
            "episode.steps",
            "episode.duration",
            "episode.seed",
            "episode.stages",
            "episode.pace",
            "episode.behind",
            "episode.step_timeout",
            "output.dir",
            "transport.kind",
            "modules.m.params.start",
            "modules.m.params.nested.x",
            "modules.m.params.new.deep",
            "modules.m.every",
            "modules.m.stage",
            "modules.m",
            "episode",
            "a..b",
            "",
            ".",
        ])
        .prop_map(str::to_string),
        "[a-z.]{0,12}",
    ];
    let value = prop_oneof![
        select(vec![
            "1",
            "-1",
            "0",
            "0.0",
            "1e400",
            "nan",
            "inf",
            "true",
            "\"s\"",
            "[1, 2]",
            "[\"a\"]",
            "{ x = 1 }",
            "18446744073709551616",
            "1979-05-27T07:32:00Z",
            "",
            "=",
            "[",
            "\"",
        ])
        .prop_map(str::to_string),
        "\\PC{0,10}",
    ];
    (key, value, any::<bool>()).prop_map(|(k, v, eq)| {
        if eq {
            format!("{k}={v}")
        } else {
            format!("{k}{v}")
        }
    })
}

#[test]
fn the_config_loader_rejects_bad_files_and_overrides_by_name() {
    let text = mutated(config_seeds(), 4).prop_map(|b| String::from_utf8_lossy(&b).into_owned());
    let strategy = (text, prop::collection::vec(override_text(), 0..3));
    let base = repo_root();
    fuzz(
        "config loader with --set",
        3000,
        strategy,
        |(text, overrides)| {
            match config::parse(&text, "fuzz.toml", &base, &overrides) {
                Ok(loaded) => {
                    // What loaded is usable: the numbers the run is built from are sane.
                    prop_assert!(
                        loaded.config.episode.ts > 0.0 && loaded.config.episode.ts.is_finite()
                    );
                    prop_assert!(loaded.step_timeout() > 0.0);
                }
                Err(e) => {
                    prop_assert_eq!(&e.file, "fuzz.toml");
                    prop_assert!(!e.message.trim().is_empty(), "{:?}", e);
                    prop_assert!(e.line.is_none_or(|l| l >= 1), "{:?}", e);
                    prop_assert!(e.to_string().starts_with("fuzz.toml"), "{}", e);
                }
            }
            Ok(())
        },
    );
}

// ---------------------------------------------------------------------------------
// The run-directory reader.

/// Publishes a JSON and a binary message each step.
struct Talker;

impl Module for Talker {
    fn step(
        &mut self,
        at: StepInfo,
        _: &[SharedMessage],
        out: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        out.push(Outgoing::new(
            "a.json",
            Payload::json(&serde_json::json!({ "step": at.step })),
        ));
        out.push(Outgoing::new(
            "a.bin",
            Payload::Binary {
                meta: "{}".into(),
                data: vec![at.step as u8; 8],
            },
        ));
        Ok(())
    }
}

/// A real, small run directory: 6 steps, compacted (`compact`) or left in parts.
fn recorded_run(dir: &Path, compact: bool) {
    let opts = EngineOptions {
        ts: 0.5,
        steps: Some(6),
        seed: 1,
        stages: vec!["s".into()],
        run_dir: dir.to_path_buf(),
        config_dir: dir.to_path_buf(),
    };
    let module = ModuleSpec {
        name: "talker".into(),
        stage: "s".into(),
        every: 1,
        offset: 0,
        subscribe: Some(vec![]),
        params: serde_json::Value::Null,
        module: AnyModule::local(Talker),
    };
    let recorder = Recorder::create(dir, vec![], Duration::ZERO).unwrap();
    let mut engine = Engine::new(opts, vec![module], Some(recorder)).unwrap();
    engine.run(|_, _| true).unwrap();
    if compact {
        engine.close().unwrap();
    } else {
        std::mem::forget(engine); // killed: the parts stay as they are
    }
    let status = RunStatus {
        status: if compact {
            RunState::Completed
        } else {
            RunState::Running
        },
        ts: 0.5,
        steps_planned: Some(6),
        steps_done: 6,
        modules: vec!["talker".into()],
        pid: (!compact).then_some(u32::MAX - 7),
        ..RunStatus::default()
    };
    status.write(dir).unwrap();
    fs::write(dir.join("config.toml"), "[episode]\nts = 0.5\n").unwrap();
}

fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(files_under(&p));
        } else {
            out.push(p);
        }
    }
    out.sort();
    out
}

#[test]
fn a_corrupt_run_directory_is_reported_naming_the_file() {
    let root = tempfile::tempdir().unwrap();
    let runs: Vec<PathBuf> = [true, false]
        .into_iter()
        .map(|compact| {
            let dir = root
                .path()
                .join(if compact { "compacted" } else { "parts" });
            fs::create_dir_all(&dir).unwrap();
            recorded_run(&dir, compact);
            dir
        })
        .collect();
    // Sanity: the real runs read back whole.
    for run in &runs {
        assert_eq!(read_messages(run).unwrap().len(), 12, "{}", run.display());
        inspect(run).unwrap();
    }
    // (run, file to corrupt, edits; or remove it)
    let targets: Vec<(PathBuf, PathBuf)> = runs
        .iter()
        .flat_map(|run| files_under(run).into_iter().map(move |f| (run.clone(), f)))
        .collect();
    let strategy = (
        select(targets),
        prop::collection::vec(edit(), 0..6),
        prop::bool::weighted(0.05),
    );
    let scratch = root.path().join("case");
    fuzz(
        "run directory reader",
        600,
        strategy,
        |((run, file), edits, remove)| {
            let _ = fs::remove_dir_all(&scratch);
            copy_dir(&run, &scratch);
            let target = scratch.join(file.strip_prefix(&run).unwrap());
            if remove {
                fs::remove_file(&target).unwrap();
            } else {
                fs::write(&target, apply(fs::read(&file).unwrap(), &edits)).unwrap();
            }
            let named = |e: &str| e.contains(&scratch.display().to_string());
            if let Err(e) = RunStatus::read_live(&scratch) {
                prop_assert!(named(&e), "{}", e);
            }
            if let Err(e) = read_messages(&scratch) {
                prop_assert!(named(&e.to_string()), "{}", e);
            }
            if let Err(e) = read_timings(&scratch) {
                prop_assert!(named(&e.to_string()), "{}", e);
            }
            if let Err(e) = inspect(&scratch) {
                prop_assert!(named(&e), "{}", e);
            }
            Ok(())
        },
    );
}

fn copy_dir(from: &Path, to: &Path) {
    fs::create_dir_all(to).unwrap();
    for e in fs::read_dir(from).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            copy_dir(&p, &to.join(e.file_name()));
        } else {
            fs::copy(&p, to.join(e.file_name())).unwrap();
        }
    }
}
