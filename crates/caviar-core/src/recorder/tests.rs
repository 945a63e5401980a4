//! Unit tests of the recorder: parts, chunks, compaction, and what a crash between
//! them leaves.

use std::fs;
use std::path::Path;
use std::time::Duration;

use arrow_array::RecordBatch;

use super::writer::write_parquet;
use super::*;
use crate::message::{Message, Payload};
use crate::topic::Pattern;

fn msg(step: u64, topic: &str, payload: Payload) -> Message {
    Message {
        step,
        time: step as f64 * 0.5,
        topic: topic.into(),
        source: "m".into(),
        payload,
    }
}

#[test]
fn parts_are_readable_before_finish_and_compacted_after() {
    let dir = tempfile::tempdir().unwrap();
    let mut r = Recorder::create(
        dir.path(),
        vec![Pattern::new("debug.>").unwrap()],
        Duration::ZERO,
    )
    .unwrap();
    let a = msg(0, "a.b", Payload::Json("{\"x\":1}".into()));
    let b = msg(
        0,
        "bin",
        Payload::Binary {
            meta: "{\"dtype\":\"|u1\"}".into(),
            data: vec![0, 255, 7],
        },
    );
    r.record_message(&a);
    r.record_message(&msg(0, "debug.noise", Payload::Json("1".into())));
    r.record_message(&b);
    r.end_step().unwrap();
    let c = msg(1, "file", Payload::Artifact("images/0001.png".into()));
    r.record_message(&c);
    r.end_step().unwrap();
    // As after a crash: parts only.
    assert_eq!(
        read_messages(dir.path()).unwrap(),
        vec![a.clone(), b.clone(), c.clone()]
    );
    r.finish().unwrap();
    assert!(dir.path().join("messages.parquet").exists());
    assert!(!dir.path().join("messages").exists());
    assert_eq!(read_messages(dir.path()).unwrap(), vec![a, b, c]);
}

fn names(dir: &Path) -> Vec<String> {
    let mut n: Vec<String> = fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    n.sort();
    n
}

#[test]
fn parts_become_chunks_and_a_crash_between_loses_or_repeats_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let mut r = Recorder::create(dir.path(), vec![], Duration::ZERO).unwrap();
    let steps = 2 * CHUNK_PARTS as u64 + 3;
    let all: Vec<Message> = (0..steps)
        .map(|k| msg(k, "a.b", Payload::Json(format!("{{\"k\":{k}}}"))))
        .collect();
    for m in &all {
        r.record_message(m);
        r.end_step().unwrap();
    }
    let last = CHUNK_PARTS * 2 - 1;
    assert_eq!(
        names(&dir.path().join(MESSAGES)),
        vec![
            format!("chunk-000000-{:06}.parquet", CHUNK_PARTS - 1),
            format!("chunk-{:06}-{last:06}.parquet", CHUNK_PARTS),
            format!("part-{:06}.parquet", last + 1),
            format!("part-{:06}.parquet", last + 2),
            format!("part-{:06}.parquet", last + 3),
        ]
    );
    assert_eq!(read_messages(dir.path()).unwrap(), all);
    // As if the process died after renaming a chunk into place, before removing its
    // parts: the parts are there again, and read once.
    for k in [3usize, 4, CHUNK_PARTS + 1] {
        let part = dir
            .path()
            .join(MESSAGES)
            .join(format!("part-{k:06}.parquet"));
        write_parquet(
            &part,
            messages_schema(),
            &[RecordBatch::new_empty(messages_schema())],
        )
        .unwrap();
    }
    assert_eq!(read_messages(dir.path()).unwrap(), all);
    r.finish().unwrap();
    assert_eq!(read_messages(dir.path()).unwrap(), all);
    assert!(!dir.path().join(MESSAGES).exists());
}

#[test]
fn a_missing_run_directory_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let e = read_messages(&dir.path().join("nope"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("not a run directory"), "{e}");
}
