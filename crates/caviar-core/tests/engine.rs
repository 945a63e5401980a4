//! Behaviour of the engine: stage order, visibility, wildcards, periods, end of
//! episode, determinism, failures and the log after a failure.

use std::path::Path;
use std::sync::{Arc, Mutex};

use caviar_core::recorder::{read_messages, read_timings, Recorder, CORE};
use caviar_core::{
    AnyModule, Engine, EngineError, EngineOptions, Module, ModuleError, ModuleSpec, Outgoing,
    Payload, SharedMessage, StepInfo, END_TOPIC,
};

/// What a probe saw: (its step, topic, source, step the message was published in).
type Seen = Arc<Mutex<Vec<(u64, String, String, u64)>>>;

/// Publishes `topics` with a JSON payload naming itself and the step; remembers its inbox.
struct Probe {
    topics: Vec<String>,
    seen: Seen,
    fail_at: Option<u64>,
    end_at: Option<u64>,
}

impl Module for Probe {
    fn step(
        &mut self,
        at: StepInfo,
        inbox: &[SharedMessage],
        out: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        if Some(at.step) == self.fail_at {
            return Err(ModuleError {
                message: "boom".into(),
                trace: Some("Traceback: probe.rs".into()),
                bad_input: false,
            });
        }
        let mut seen = self.seen.lock().unwrap();
        for m in inbox {
            seen.push((at.step, m.topic.clone(), m.source.clone(), m.step));
        }
        for t in &self.topics {
            out.push(Outgoing::new(
                t.clone(),
                Payload::json(&serde_json::json!({ "step": at.step, "t": at.time })),
            ));
        }
        if Some(at.step) == self.end_at {
            out.push(Outgoing::new(END_TOPIC, Payload::Json("{}".into())));
        }
        Ok(())
    }
}

struct Spec {
    name: &'static str,
    stage: &'static str,
    every: u64,
    offset: u64,
    publish: &'static [&'static str],
    subscribe: &'static [&'static str],
    fail_at: Option<u64>,
    end_at: Option<u64>,
}

const fn spec(
    name: &'static str,
    stage: &'static str,
    publish: &'static [&'static str],
    subscribe: &'static [&'static str],
) -> Spec {
    Spec {
        name,
        stage,
        every: 1,
        offset: 0,
        publish,
        subscribe,
        fail_at: None,
        end_at: None,
    }
}

fn build(dir: &Path, steps: Option<u64>, specs: Vec<Spec>) -> (Engine, Vec<(&'static str, Seen)>) {
    let mut seen = Vec::new();
    let modules = specs
        .into_iter()
        .map(|s| {
            let log: Seen = Arc::default();
            seen.push((s.name, log.clone()));
            let probe = Probe {
                topics: s.publish.iter().map(|x| x.to_string()).collect(),
                seen: log,
                fail_at: s.fail_at,
                end_at: s.end_at,
            };
            ModuleSpec {
                every: s.every,
                offset: s.offset,
                subscribe: Some(s.subscribe.iter().map(|x| x.to_string()).collect()),
                ..ModuleSpec::new(s.name, s.stage, AnyModule::local(probe))
            }
        })
        .collect();
    let opts = EngineOptions {
        ts: 0.5,
        steps,
        seed: 1,
        stages: vec!["a".into(), "b".into(), "c".into()],
        run_dir: dir.to_path_buf(),
        config_dir: dir.to_path_buf(),
    };
    let recorder = Recorder::create(dir, vec![], std::time::Duration::ZERO).unwrap();
    (Engine::new(opts, modules, Some(recorder)).unwrap(), seen)
}

fn log_of(seen: &[(&str, Seen)], name: &str) -> Vec<(u64, String, String, u64)> {
    seen.iter()
        .find(|(n, _)| *n == name)
        .unwrap()
        .1
        .lock()
        .unwrap()
        .clone()
}

#[test]
fn later_stages_see_this_step_earlier_and_same_stages_see_it_next_step() {
    let dir = tempfile::tempdir().unwrap();
    let (mut e, seen) = build(
        dir.path(),
        Some(2),
        vec![
            spec("late", "c", &[], &["x.>"]),
            spec("producer", "b", &["x.data"], &[]),
            spec("peer", "b", &[], &["x.data"]),
            spec("early", "a", &[], &["x.data"]),
        ],
    );
    e.run(|_, _| true).unwrap();
    e.close().unwrap();
    let s =
        |step: u64, pub_step: u64| (step, "x.data".to_string(), "producer".to_string(), pub_step);
    // Stage c runs after b: it sees step k's message in step k.
    assert_eq!(log_of(&seen, "late"), vec![s(0, 0), s(1, 1)]);
    // Same stage and earlier stage: one step later.
    assert_eq!(log_of(&seen, "peer"), vec![s(1, 0)]);
    assert_eq!(log_of(&seen, "early"), vec![s(1, 0)]);
}

#[test]
fn wildcards_route_only_matching_topics_in_declaration_order() {
    let dir = tempfile::tempdir().unwrap();
    let (mut e, seen) = build(
        dir.path(),
        Some(1),
        vec![
            spec(
                "p2",
                "a",
                &["communications.throughput", "communications.beam.gains"],
                &[],
            ),
            spec(
                "p1",
                "a",
                &["3D.mobility.positions", "communications.state"],
                &[],
            ),
            spec("star", "b", &[], &["communications.*"]),
            spec("rest", "b", &[], &["communications.>"]),
            spec("mid", "b", &[], &["*.mobility.*"]),
        ],
    );
    e.run(|_, _| true).unwrap();
    let topics = |n| {
        log_of(&seen, n)
            .into_iter()
            .map(|x| x.1)
            .collect::<Vec<_>>()
    };
    // Module p2 is declared before p1, so its messages come first.
    assert_eq!(
        topics("star"),
        ["communications.throughput", "communications.state"]
    );
    assert_eq!(
        topics("rest"),
        [
            "communications.throughput",
            "communications.beam.gains",
            "communications.state"
        ]
    );
    assert_eq!(topics("mid"), ["3D.mobility.positions"]);
}

#[test]
fn periodic_modules_run_every_kth_step_and_get_what_they_missed() {
    let dir = tempfile::tempdir().unwrap();
    let mut slow = spec("slow", "b", &["slow.out"], &["fast.out"]);
    slow.every = 3;
    slow.offset = 1;
    let (mut e, seen) = build(
        dir.path(),
        Some(8),
        vec![spec("fast", "a", &["fast.out"], &[]), slow],
    );
    let mut published_by_slow = Vec::new();
    e.run(|_, r| {
        published_by_slow.extend(
            r.messages
                .iter()
                .filter(|m| m.source == "slow")
                .map(|m| m.step),
        );
        true
    })
    .unwrap();
    assert_eq!(published_by_slow, [1, 4, 7]);
    let got: Vec<(u64, u64)> = log_of(&seen, "slow")
        .into_iter()
        .map(|x| (x.0, x.3))
        .collect();
    // At step 1 it gets steps 0 and 1; at step 4, steps 2..=4; at 7, steps 5..=7.
    assert_eq!(
        got,
        [
            (1, 0),
            (1, 1),
            (4, 2),
            (4, 3),
            (4, 4),
            (7, 5),
            (7, 6),
            (7, 7)
        ]
    );
}

#[test]
fn a_module_ends_the_episode_after_the_current_step() {
    let dir = tempfile::tempdir().unwrap();
    let mut ender = spec("mission", "a", &[], &[]);
    ender.end_at = Some(3);
    let (mut e, seen) = build(
        dir.path(),
        None,
        vec![ender, spec("after", "b", &[], &[END_TOPIC])],
    );
    let mut last = None;
    e.run(|_, r| {
        last = Some((r.step, r.ended));
        true
    })
    .unwrap();
    assert_eq!(last, Some((3, true)));
    assert_eq!(e.steps_done(), 4);
    // The rest of step 3 still ran and saw the end message.
    assert_eq!(log_of(&seen, "after").len(), 1);
}

#[test]
fn runs_with_the_same_setup_record_identical_messages() {
    let record = || {
        let dir = tempfile::tempdir().unwrap();
        let specs = vec![
            spec("a1", "a", &["t.a1"], &[]),
            spec("a2", "a", &["t.a2"], &[]),
            spec("a3", "a", &["t.a3"], &[]),
            spec("b1", "b", &["t.b1"], &["t.*"]),
            spec("c1", "c", &["t.c1"], &[">"]),
        ];
        let (mut e, _) = build(dir.path(), Some(20), specs);
        e.run(|_, _| true).unwrap();
        e.close().unwrap();
        read_messages(dir.path()).unwrap()
    };
    let first = record();
    assert_eq!(first.len(), 20 * 5);
    for _ in 0..3 {
        // Stage a runs its three modules on worker threads; order must not depend on timing.
        assert_eq!(record(), first);
    }
}

#[test]
fn a_failing_module_stops_the_run_naming_module_and_step_and_the_log_stays_readable() {
    let dir = tempfile::tempdir().unwrap();
    let mut bad = spec("detector", "b", &[], &[]);
    bad.fail_at = Some(5);
    let (mut e, _) = build(
        dir.path(),
        Some(100),
        vec![spec("uav", "a", &["3D.mobility.positions"], &[]), bad],
    );
    let err = e.run(|_, _| true).unwrap_err();
    match &err {
        EngineError::Module {
            module,
            step,
            phase,
            ..
        } => {
            assert_eq!(
                (module.as_str(), *step, *phase),
                ("detector", Some(5), "step")
            );
        }
        other => panic!("unexpected {other}"),
    }
    let text = err.to_string();
    assert!(
        text.contains("module 'detector' failed at step 5 (t = 2.500 s): boom"),
        "{text}"
    );
    assert!(text.contains("Traceback: probe.rs"), "{text}");
    // Before close (as after a crash) the parts on disk hold steps 0..=5 of the positions.
    let steps: Vec<u64> = read_messages(dir.path())
        .unwrap()
        .iter()
        .map(|m| m.step)
        .collect();
    assert_eq!(steps, [0, 1, 2, 3, 4, 5]);
    e.close().unwrap();
    assert_eq!(read_messages(dir.path()).unwrap().len(), 6);
    let timings = read_timings(dir.path()).unwrap();
    assert_eq!(timings.iter().filter(|t| t.module == CORE).count(), 6);
}

#[test]
fn publishing_a_wildcard_or_reserved_topic_is_an_error_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let (mut e, _) = build(dir.path(), Some(3), vec![spec("m", "a", &["bad.*"], &[])]);
    let err = e.run(|_, _| true).unwrap_err().to_string();
    assert!(
        err.contains("module 'm' published on topic 'bad.*' in step 0"),
        "{err}"
    );
    let dir = tempfile::tempdir().unwrap();
    let (mut e, _) = build(
        dir.path(),
        Some(3),
        vec![spec("m", "a", &["caviar.clock"], &[])],
    );
    let err = e.run(|_, _| true).unwrap_err().to_string();
    assert!(err.contains("reserved"), "{err}");
}

/// A stand-in for the nvidia-ml-py probe (no NVIDIA GPU on the test machine): a GPU
/// whose memory grows by 100 MiB at every sample.
struct FakeGpu {
    samples: u32,
}

impl caviar_core::ResourceProbe for FakeGpu {
    fn sample(&mut self) -> Option<(f64, f64)> {
        self.samples += 1;
        Some((50.0, 100.0 * self.samples as f64))
    }
}

#[test]
fn gpu_use_is_sampled_after_each_stage_and_charged_to_its_modules() {
    let dir = tempfile::tempdir().unwrap();
    let (mut e, _) = build(
        dir.path(),
        Some(2),
        vec![
            spec("uav", "a", &["x"], &[]),
            spec("radio", "b", &["y"], &["x"]),
            spec("ai", "b", &[], &["y"]),
        ],
    );
    e.set_probe(Box::new(FakeGpu { samples: 0 }));
    e.run(|_, _| true).unwrap();
    e.close().unwrap();
    let t = read_timings(dir.path()).unwrap();
    let mem = |m: &str| {
        t.iter()
            .filter(|r| r.module == m)
            .map(|r| r.gpu_mem_mib)
            .collect::<Vec<_>>()
    };
    // Two stages ran per step (c is empty): samples 1-2 in step 0, 3-4 in step 1.
    assert_eq!(mem("uav"), [Some(100.0), Some(300.0)]);
    assert_eq!(mem("radio"), [Some(200.0), Some(400.0)]);
    assert_eq!(
        mem("ai"),
        mem("radio"),
        "modules of one stage share the process's sample"
    );
    assert_eq!(mem(CORE), [None, None]);
    assert!(t
        .iter()
        .filter(|r| r.module != CORE)
        .all(|r| r.gpu_util_pct == Some(50.0)));
    std::fs::write(dir.path().join("run.json"), r#"{"status": "completed"}"#).unwrap();
    let text = caviar_core::inspect::inspect(dir.path()).unwrap();
    assert!(text.contains("mean GPU %  max GPU MiB"), "{text}");
    assert!(
        text.lines()
            .any(|l| l.starts_with("radio") && l.trim_end().ends_with("50.0          400")),
        "{text}"
    );
}

#[test]
fn without_a_gpu_the_gpu_columns_are_empty_and_inspect_leaves_them_out() {
    let dir = tempfile::tempdir().unwrap();
    let (mut e, _) = build(dir.path(), Some(2), vec![spec("uav", "a", &["x"], &[])]);
    e.run(|_, _| true).unwrap();
    e.close().unwrap();
    let t = read_timings(dir.path()).unwrap();
    assert!(t
        .iter()
        .all(|r| r.gpu_util_pct.is_none() && r.gpu_mem_mib.is_none()));
    std::fs::write(dir.path().join("run.json"), r#"{"status": "completed"}"#).unwrap();
    assert!(!caviar_core::inspect::inspect(dir.path())
        .unwrap()
        .contains("GPU"));
}
