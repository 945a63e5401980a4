//! Unit tests of the configuration loader: parsing, checks, overrides and the lines
//! errors name.

use super::*;

const GOOD: &str = r#"
[episode]
ts = 0.5
steps = 4
seed = 3
stages = ["a", "b"]

[modules.second]
stage = "b"
plugin = "x:Y"

[modules.first]
stage = "a"
plugin = "x:Z"
every = 2
offset = 1
subscribe = ["3D.>"]
[modules.first.params]
speed = 5.0
"#;

fn parse_str(text: &str, ov: &[&str]) -> Result<LoadedConfig, ConfigError> {
    let ov: Vec<String> = ov.iter().map(|s| s.to_string()).collect();
    parse(text, "exp.toml", Path::new("."), &ov)
}

#[test]
fn a_good_file_parses_and_keeps_module_order() {
    let c = parse_str(GOOD, &[]).unwrap();
    let names: Vec<&String> = c.config.modules.keys().collect();
    assert_eq!(names, ["second", "first"]);
    assert_eq!(c.steps(), Some(4));
    assert_eq!(c.config.modules["first"].every, 2);
    assert_eq!(c.params_json("first")["speed"], 5.0);
}

#[test]
fn keys_inside_arrays_of_tables_have_their_line() {
    let text = "[m.params]\nx = 1\n[[m.params.sites]]\nname = \"a\"\n[[m.params.sites]]\nname = \"b\"\narray = [1, 2]\n";
    assert_eq!(
        line_of_key(text, &["m", "params", "sites", "1", "name"]),
        Some(6)
    );
    assert_eq!(
        line_of_key(text, &["m", "params", "sites", "0", "name"]),
        Some(4)
    );
    assert_eq!(
        line_of_key(text, &["m", "params", "sites", "1", "array"]),
        Some(7)
    );
    assert_eq!(line_of_key(text, &["m", "params", "sites", "1"]), Some(5));
    assert_eq!(line_of_key(text, &["m", "params", "x"]), Some(2));
}

#[test]
fn unknown_keys_name_file_line_and_key() {
    let text = GOOD.replace("every = 2", "evry = 2");
    let e = parse_str(&text, &[]).unwrap_err();
    assert_eq!(e.file, "exp.toml");
    assert_eq!(e.line, Some(15), "{e}");
    assert!(e.message.contains("unknown field `evry`"), "{e}");
    assert_eq!(e.key.as_deref(), Some("modules.first.evry"), "{e}");
}

#[test]
fn wrong_types_name_the_key() {
    let text = GOOD.replace("ts = 0.5", "ts = \"fast\"");
    let e = parse_str(&text, &[]).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("episode.ts"), "{e}");
    assert_eq!(e.line, Some(3), "{e}");
    assert!(e.message.contains("invalid type"), "{e}");
}

#[test]
fn semantic_errors_point_at_the_key() {
    let e = parse_str(&GOOD.replace("stage = \"b\"", "stage = \"c\""), &[]).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("modules.second.stage"));
    assert_eq!(e.line, Some(9));
    assert!(e.message.contains("unknown stage 'c'"));
    let e = parse_str(&GOOD.replace("offset = 1", "offset = 2"), &[]).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("modules.first.offset"));
    let e = parse_str(&GOOD.replace("\"3D.>\"", "\"3D.>.x\""), &[]).unwrap_err();
    assert!(e.message.contains("last token"), "{e}");
    let e = parse_str(&GOOD.replace("steps = 4", "steps = 4\nduration = 2.0"), &[]).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("episode.duration"));
    let e = parse_str(&GOOD.replace("ts = 0.5", "ts = -1.0"), &[]).unwrap_err();
    assert_eq!(
        e.to_string(),
        "exp.toml:3: episode.ts: expected a positive number of seconds, got -1"
    );
}

#[test]
fn overrides_replace_and_add_values() {
    let c = parse_str(
        GOOD,
        &[
            "episode.steps=10",
            "modules.first.params.speed=2",
            "modules.first.params.label=uav one",
        ],
    )
    .unwrap();
    assert_eq!(c.steps(), Some(10));
    assert_eq!(c.params_json("first")["speed"], 2);
    assert_eq!(c.params_json("first")["label"], "uav one");
    let e = parse_str(GOOD, &["episode.steps=many"]).unwrap_err();
    assert!(e.message.contains("from --set episode.steps=many"), "{e}");
    assert_eq!(e.line, Some(4), "{e}");
    assert!(parse_str(GOOD, &["nonsense"])
        .unwrap_err()
        .message
        .contains("KEY=VALUE"));
}

#[test]
fn with_overrides_errors_name_the_files_own_lines_or_the_override() {
    // An override that adds a key to [episode] shifts every later line of the
    // overridden text by one; messages still name the file's lines.
    let bad = GOOD.replace("every = 2", "every = 0");
    let plain = parse_str(&bad, &[]).unwrap_err();
    assert_eq!(plain.line, Some(15), "{plain}");
    for ov in [
        &["episode.strict_wiring=true"][..],
        &["episode.step_timeout=30", "output.name=\"r\""],
    ] {
        let e = parse_str(&bad, ov).unwrap_err();
        assert_eq!(e.key.as_deref(), Some("modules.first.every"), "{e}");
        assert_eq!(e.line, Some(15), "{ov:?}: {e}");
    }
    // A type error found while deserialising: the same.
    let e = parse_str(
        &GOOD.replace("offset = 1", "offset = \"one\""),
        &["episode.strict_wiring=true"],
    )
    .unwrap_err();
    assert_eq!(
        (e.key.as_deref(), e.line),
        (Some("modules.first.offset"), Some(16)),
        "{e}"
    );
    // The bad value came from --set: the key's line in the file and the override.
    let e = parse_str(
        GOOD,
        &["episode.strict_wiring=true", "modules.first.every=0"],
    )
    .unwrap_err();
    assert_eq!(e.line, Some(15), "{e}");
    assert!(
        e.message.contains("(from --set modules.first.every=0)"),
        "{e}"
    );
    let e = parse_str(
        GOOD,
        &["modules.first={ stage = \"zz\", plugin = \"x:Z\" }"],
    )
    .unwrap_err();
    assert!(e.message.contains("from --set modules.first="), "{e}");
}

#[test]
fn numeric_edges_are_config_errors() {
    let e = parse_str(&GOOD.replace("steps = 4", "steps = 0"), &[]).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("episode.steps"), "{e}");
    let tiny = GOOD.replace("ts = 0.5\nsteps = 4", "ts = 1e-300\nduration = 1.0");
    let e = parse_str(&tiny, &[]).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("episode.duration"), "{e}");
    assert!(
        e.message.contains("1e300 steps") && e.message.contains("ts"),
        "{e}"
    );
    let e = parse_str(&GOOD.replace("ts = 0.5", "ts = 1e308"), &[]).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("episode.ts"), "{e}");
    assert!(e.message.contains("infinite"), "{e}");
    let e = parse_str(&GOOD.replace("speed = 5.0", "speed = nan"), &[]).unwrap_err();
    assert_eq!(
        e.to_string(),
        "exp.toml:19: modules.first.params.speed: expected a finite float, got nan"
    );
    let e = parse_str(&GOOD.replace("speed = 5.0", "at = 1979-05-27"), &[]).unwrap_err();
    assert_eq!(e.key.as_deref(), Some("modules.first.params.at"), "{e}");
    let e = parse_str(&GOOD.replace("seed = 3", "seed = 1979-05-27"), &[]).unwrap_err();
    assert!(e.message.contains("TOML date/time"), "{e}");
    for bad in ["\"../up\"", "\"a/b\"", "\"\"", "\"..\""] {
        let text = format!("{GOOD}\n[output]\nname = {bad}\n");
        let e = parse_str(&text, &[]).unwrap_err();
        assert_eq!(e.key.as_deref(), Some("output.name"), "{e}");
    }
    let e = parse_str(&GOOD.replace("ts = 0.5\n", ""), &[]).unwrap_err();
    assert_eq!(
        e.to_string(),
        "exp.toml:2: episode.ts: this required key is missing"
    );
}

#[test]
fn duration_gives_the_step_count() {
    let c = parse_str(&GOOD.replace("steps = 4", "duration = 1.2"), &[]).unwrap();
    assert_eq!(c.steps(), Some(3)); // 1.2 / 0.5 -> 2.4 -> 3 steps
    let c = parse_str(
        &GOOD.replace("ts = 0.5\nsteps = 4", "ts = 0.1\nduration = 0.3"),
        &[],
    )
    .unwrap();
    assert_eq!(c.steps(), Some(3)); // no extra step from rounding noise
    let c = parse_str(&GOOD.replace("steps = 4", "duration = 1e-12"), &[]).unwrap();
    assert_eq!(c.steps(), Some(1)); // a positive duration is at least one step
}
