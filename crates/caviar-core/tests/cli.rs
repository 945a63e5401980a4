//! The command line of the Rust binary (built-in modules only, no Python).

use std::fs;
use std::path::Path;
use std::time::Duration;

use caviar_core::cli;
use caviar_core::recorder::{read_messages, Recorder};
use caviar_core::run::BuiltinsOnly;
use caviar_core::{Message, Payload};

fn run(args: &[&str]) -> i32 {
    let argv = std::iter::once("caviar-core")
        .chain(args.iter().copied())
        .map(String::from)
        .collect();
    cli::main(argv, &BuiltinsOnly, &|| false)
}

/// `caviar-core run CONFIG --out OUT`, then `extra`: its exit code.
fn run_into(config: &Path, out: &Path, extra: &[&str]) -> i32 {
    let (config, out) = (config.to_str().unwrap(), out.to_str().unwrap());
    run(&[&["run", config, "--out", out], extra].concat())
}

fn recorded_run(dir: &Path) {
    fs::create_dir_all(dir).unwrap();
    let mut rec = Recorder::create(dir, vec![], Duration::ZERO).unwrap();
    for step in 0..5u64 {
        for topic in ["3D.mobility.positions", "communications.throughput"] {
            rec.record_message(&Message {
                step,
                time: step as f64 * 0.5,
                topic: topic.into(),
                source: "original".into(),
                payload: Payload::Json(format!("{{\"step\":{step}}}")),
            });
        }
        rec.end_step().unwrap();
    }
    rec.finish().unwrap();
}

#[test]
fn the_rust_binary_runs_built_in_modules_and_rejects_python_plugins_clearly() {
    let dir = tempfile::tempdir().unwrap();
    recorded_run(&dir.path().join("original"));
    let config = dir.path().join("replay.toml");
    fs::write(
        &config,
        r#"
[episode]
ts = 0.25
steps = 10
stages = ["mobility"]

[modules.mobility]
stage = "mobility"
plugin = "caviar.replay"
params = { run = "original", topics = ["3D.>"] }
"#,
    )
    .unwrap();
    let out = dir.path().join("out");
    assert_eq!(run_into(&config, &out, &["-q"]), 0);
    let replayed = read_messages(&out).unwrap();
    // Recorded at Ts = 0.5 s, replayed at Ts = 0.25 s: at the same virtual times.
    let at: Vec<(u64, f64)> = replayed.iter().map(|m| (m.step, m.time)).collect();
    assert_eq!(at, [(0, 0.0), (2, 0.5), (4, 1.0), (6, 1.5), (8, 2.0)]);
    assert!(replayed
        .iter()
        .all(|m| m.topic == "3D.mobility.positions" && m.source == "mobility"));
    let status = fs::read_to_string(out.join("run.json")).unwrap();
    assert!(status.contains("\"status\": \"completed\""), "{status}");
    assert!(caviar_core::inspect::inspect(&out)
        .unwrap()
        .contains("3D.mobility.positions"));

    // A Python plugin needs the Python package's caviar-core; a config error is exit 2.
    let text = fs::read_to_string(&config)
        .unwrap()
        .replace("caviar.replay", "pkg.mod:Plugin");
    fs::write(&config, text).unwrap();
    let out2 = dir.path().join("out2");
    assert_eq!(run_into(&config, &out2, &[]), 2);
    assert!(
        !out2.exists(),
        "a config error must not create a run directory"
    );
    // Splitting a module into shards needs the NATS transport.
    let text = fs::read_to_string(&config)
        .unwrap()
        .replace("[modules.mobility]", "[modules.mobility]\nshards = 2");
    fs::write(&config, text).unwrap();
    assert_eq!(run(&["validate", config.to_str().unwrap()]), 2);
    assert_eq!(
        run(&["inspect", dir.path().join("nope").to_str().unwrap()]),
        2
    );
}
