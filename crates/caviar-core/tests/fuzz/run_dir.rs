//! The run-directory reader, on real run directories (compacted, or left in parts)
//! with one file corrupted or removed.

use std::fs;
use std::path::{Path, PathBuf};
use std::time::Duration;

use proptest::prelude::*;
use proptest::sample::select;

use caviar_core::inspect::inspect;
use caviar_core::recorder::{read_messages, read_timings, Recorder};
use caviar_core::status::{RunState, RunStatus};
use caviar_core::{
    AnyModule, Engine, EngineOptions, Module, ModuleError, ModuleSpec, Outgoing, Payload,
    SharedMessage, StepInfo,
};

use crate::harness::fuzz;
use crate::mutation::{apply, edit};

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
        subscribe: Some(vec![]),
        ..ModuleSpec::new("talker", "s", AnyModule::local(Talker))
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
