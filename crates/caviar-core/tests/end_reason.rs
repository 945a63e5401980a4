//! Why an episode ended, as the engine tells it and run.json records it; local and
//! remote modules side by side in one stage.

use std::sync::{Arc, Mutex};

use caviar_core::recorder::Recorder;
use caviar_core::status::{RunState, RunStatus};
use caviar_core::{
    AnyModule, EndReason, Engine, EngineError, EngineOptions, Module, ModuleError, ModuleSpec,
    Outgoing, Payload, RemoteModule, SharedMessage, StepInfo, Usage, END_TOPIC,
};

/// Ends the episode at `end_at`, fails at `fail_at` (default: neither).
#[derive(Default)]
struct Local {
    end_at: Option<u64>,
    fail_at: Option<u64>,
}

impl Module for Local {
    fn step(
        &mut self,
        at: StepInfo,
        _: &[SharedMessage],
        out: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        if Some(at.step) == self.fail_at {
            return Err(ModuleError::new("broke"));
        }
        out.push(Outgoing::new("local.tick", Payload::Json("1".into())));
        if Some(at.step) == self.end_at {
            out.push(Outgoing::new(END_TOPIC, Payload::Json("{}".into())));
        }
        Ok(())
    }
}

/// A remote module that answers at once; logs the calls it gets.
struct Remote {
    calls: Arc<Mutex<Vec<String>>>,
    inbox: usize,
}

impl RemoteModule for Remote {
    fn default_subscriptions(&self) -> Vec<String> {
        vec!["local.*".into()]
    }
    fn start_step(&mut self, at: StepInfo, inbox: &[SharedMessage]) -> Result<(), ModuleError> {
        self.calls
            .lock()
            .unwrap()
            .push(format!("start {}", at.step));
        self.inbox = inbox.len();
        Ok(())
    }
    fn finish_step(&mut self, out: &mut Vec<Outgoing>) -> Result<Usage, ModuleError> {
        self.calls.lock().unwrap().push("finish".into());
        out.push(Outgoing::new(
            "remote.seen",
            Payload::Json(self.inbox.to_string()),
        ));
        Ok(Usage {
            wall_s: 0.001,
            cpu_s: 0.0005,
            rss_mib: 10.0,
            gpu_util_pct: None,
            gpu_mem_mib: None,
        })
    }
}

fn engine(
    dir: &std::path::Path,
    steps: Option<u64>,
    local: Local,
) -> (Engine, Arc<Mutex<Vec<String>>>) {
    let calls = Arc::default();
    let opts = EngineOptions {
        ts: 0.5,
        steps,
        seed: 1,
        stages: vec!["a".into(), "b".into()],
        run_dir: dir.into(),
        config_dir: dir.into(),
    };
    let modules = vec![
        ModuleSpec::new("local", "a", AnyModule::local(local)),
        ModuleSpec::new(
            "remote",
            "b",
            AnyModule::remote(Remote {
                calls: Arc::clone(&calls),
                inbox: 0,
            }),
        ),
    ];
    let rec = Recorder::create(dir, vec![], std::time::Duration::ZERO).unwrap();
    (Engine::new(opts, modules, Some(rec)).unwrap(), calls)
}

fn status_of(
    dir: &std::path::Path,
    e: &Engine,
    state: RunState,
    err: Option<&EngineError>,
) -> RunStatus {
    let text = "[episode]\nts = 0.5\nstages = [\"a\", \"b\"]\n[modules.local]\nstage = \"a\"\nplugin = \"x\"\n";
    let cfg = caviar_core::config::parse(text, "c.toml", dir, &[]).unwrap();
    RunStatus::of(&cfg, e, state, err)
        .write(e.run_dir())
        .unwrap();
    RunStatus::read(dir).unwrap()
}

#[test]
fn planned_steps_end_with_reason_steps_and_remote_modules_start_then_finish() {
    let dir = tempfile::tempdir().unwrap();
    let (mut e, calls) = engine(dir.path(), Some(2), Local::default());
    assert_eq!(e.end_reason(), None);
    let mut seen = Vec::new();
    e.run(|_, r| {
        seen.extend(
            r.messages
                .iter()
                .map(|m| (m.topic.clone(), m.payload.clone())),
        );
        true
    })
    .unwrap();
    e.close().unwrap();
    assert_eq!(e.end_reason(), Some(EndReason::Steps));
    assert_eq!(
        *calls.lock().unwrap(),
        ["start 0", "finish", "start 1", "finish"]
    );
    assert!(seen.contains(&("remote.seen".into(), Payload::Json("1".into()))));
    let s = status_of(dir.path(), &e, RunState::Completed, None);
    assert_eq!((s.end_reason, s.ended_by), (Some(EndReason::Steps), None));
}

#[test]
fn a_module_that_publishes_the_end_topic_is_named_as_the_end() {
    let dir = tempfile::tempdir().unwrap();
    let (mut e, _) = engine(
        dir.path(),
        None,
        Local {
            end_at: Some(1),
            ..Local::default()
        },
    );
    e.run(|_, _| true).unwrap();
    e.close().unwrap();
    assert_eq!(
        (e.end_reason(), e.ended_by()),
        (Some(EndReason::Module), Some("local"))
    );
    let s = status_of(dir.path(), &e, RunState::Completed, None);
    assert_eq!(s.end_reason, Some(EndReason::Module));
    assert_eq!(s.ended_by.as_deref(), Some("local"));
    let text = caviar_core::inspect::inspect(dir.path()).unwrap();
    assert!(
        text.contains("ended     module 'local' published caviar.episode.end"),
        "{text}"
    );
}

#[test]
fn errors_interruptions_and_early_closes_are_told_apart() {
    let dir = tempfile::tempdir().unwrap();
    let (mut e, _) = engine(
        dir.path(),
        Some(5),
        Local {
            fail_at: Some(1),
            ..Local::default()
        },
    );
    let err = e.run(|_, _| true).unwrap_err();
    e.close().unwrap();
    assert_eq!(e.end_reason(), Some(EndReason::Error));
    let s = status_of(dir.path(), &e, RunState::Failed, Some(&err));
    assert_eq!(s.end_reason, Some(EndReason::Error));
    assert!(caviar_core::inspect::inspect(dir.path())
        .unwrap()
        .contains("ended     an error"));

    let dir = tempfile::tempdir().unwrap();
    let (mut e, _) = engine(dir.path(), Some(5), Local::default());
    let err = e.run(|e, _| e.steps_done() < 2).unwrap_err();
    assert!(matches!(err, EngineError::Interrupted { step: 1 }));
    assert_eq!(e.end_reason(), Some(EndReason::Interrupted));
    e.close().unwrap();

    let dir = tempfile::tempdir().unwrap();
    let (mut e, _) = engine(dir.path(), Some(5), Local::default());
    e.step().unwrap();
    assert_eq!(e.end_reason(), None);
    e.close().unwrap();
    assert_eq!(e.end_reason(), Some(EndReason::Closed));
    let s = status_of(dir.path(), &e, RunState::Completed, None);
    assert_eq!(s.end_reason, Some(EndReason::Closed));
}
