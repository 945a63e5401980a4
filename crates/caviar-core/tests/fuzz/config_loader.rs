//! The TOML loader with `--set` overrides, on the blueprints and test configurations
//! mutated.

use std::fs;
use std::path::{Path, PathBuf};

use proptest::prelude::*;
use proptest::sample::select;

use caviar_core::config;

use crate::harness::fuzz;
use crate::mutation::mutated;

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

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
                    prop_assert!(caviar_core::transport::step_timeout(&loaded) > 0.0);
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
