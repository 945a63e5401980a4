//! Unit tests of run.json: old runs still read, a run left running is closed or
//! found abandoned, and what is written.

use super::process::process_start;
use super::progress::PROGRESS_FILE;
use super::*;
use crate::engine::EndReason;

#[test]
fn runs_recorded_before_end_reason_still_read() {
    let old = r#"{"caviar_version": "0.1.0", "status": "failed", "config_file": "c.toml",
            "overrides": [], "seed": 7, "ts": 0.1, "steps_planned": 5, "steps_done": 2,
            "virtual_time_s": 0.2, "wall_s": 0.5, "rtf": 0.4, "modules": ["a"],
            "error": {"module": "a", "phase": "setup", "step": null, "time": null,
                      "message": "boom", "trace": null}}"#;
    let s: RunStatus = serde_json::from_str(old).unwrap();
    assert_eq!(
        (s.status, s.end_reason, s.record_s),
        (RunState::Failed, None, 0.0)
    );
    assert!(matches!(&s.error, Some(RunErrorInfo::Module { phase, .. }) if phase == "setup"));
    let other: RunStatus = serde_json::from_str(r#"{"error": {"message": "disk full"}}"#).unwrap();
    assert_eq!(other.error.unwrap().message(), "disk full");
}

#[test]
fn a_run_left_running_is_closed_failed_where_progress_json_says() {
    let dir = std::env::temp_dir().join(format!("caviar-close-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let s = RunStatus {
        status: RunState::Running,
        ts: 0.5,
        steps_done: 2,
        pid: Some(1),
        ..Default::default()
    };
    s.write(&dir).unwrap();
    // No progress.json yet: before its first step.
    let place = RunStatus::close_failed(&dir, "the process was killed").unwrap();
    assert_eq!(place.as_deref(), Some(", before its first step"));
    s.write(&dir).unwrap();
    std::fs::write(
        dir.join(PROGRESS_FILE),
        r#"{"steps_done": 4, "step": 4, "stage": "s", "modules": ["a", "b"]}   "#,
    )
    .unwrap();
    let place = RunStatus::close_failed(&dir, "the process was killed by SIGKILL").unwrap();
    assert_eq!(place.as_deref(), Some(", in module 'b' at step 4"));
    let closed = RunStatus::read(&dir).unwrap();
    assert_eq!(
        (
            closed.status,
            closed.end_reason,
            closed.steps_done,
            closed.pid
        ),
        (RunState::Failed, Some(EndReason::Error), 4, None)
    );
    assert_eq!(closed.virtual_time_s, 2.0);
    assert!(
        matches!(&closed.error, Some(RunErrorInfo::Module { module, step: Some(4), message, .. })
        if module == "b" && message == "The process was killed by SIGKILL, in module 'b' at step 4")
    );
    // Closed already: left as it is.
    assert_eq!(RunStatus::close_failed(&dir, "again").unwrap(), None);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_reused_pid_does_not_keep_an_abandoned_run_alive() {
    let dir = std::env::temp_dir().join(format!("caviar-pid-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let me = std::process::id();
    let start = process_start(me).expect("/proc on Linux");
    let mut s = RunStatus {
        status: RunState::Running,
        pid: Some(me),
        pid_start: Some(start),
        ..RunStatus::default()
    };
    s.write(&dir).unwrap();
    assert_eq!(
        RunStatus::read_live(&dir).unwrap().status,
        RunState::Running
    );
    // The same pid, another start: the process that ran it is gone, this is a later one.
    s.pid_start = Some(start + 1);
    s.write(&dir).unwrap();
    assert_eq!(
        RunStatus::read_live(&dir).unwrap().status,
        RunState::Abandoned
    );
    // Runs recorded before pid_start existed: the pid alone decides.
    s.pid_start = None;
    s.write(&dir).unwrap();
    assert_eq!(
        RunStatus::read_live(&dir).unwrap().status,
        RunState::Running
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn end_reason_is_written_in_lowercase_with_the_module() {
    let s = RunStatus {
        status: RunState::Completed,
        end_reason: Some(EndReason::Module),
        ended_by: Some("mission".into()),
        ..RunStatus::default()
    };
    let v: serde_json::Value = serde_json::to_value(&s).unwrap();
    assert_eq!(v["end_reason"], "module");
    assert_eq!(v["ended_by"], "mission");
    assert_eq!(v["status"], "completed");
    assert!(v["error"].is_null() && v["rtf"].is_null() && v["steps_planned"].is_null());
}
