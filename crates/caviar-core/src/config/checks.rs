//! The checks of a configuration that its types alone cannot express, one named
//! check after another; each error names the key and its line.

use super::model::{steps_of, ConfigError, LoadedConfig, IN_PROCESS, MAX_STEPS};
use super::text::num;
use crate::pacing::Behind;
use crate::topic::Pattern;

/// Checks what types alone cannot express, one named check after another.
pub(super) fn validate(c: &LoadedConfig) -> Result<(), ConfigError> {
    check_timing(c)?;
    check_length(c)?;
    check_stages(c)?;
    check_modules(c)?;
    check_output(c)?;
    validate_params(c)?;
    check_placement(c)
}

/// `episode.ts`, `duration`, `step_timeout` and `setup_timeout`: positive, finite seconds.
fn check_timing(c: &LoadedConfig) -> Result<(), ConfigError> {
    let ep = &c.config.episode;
    if !(ep.ts.is_finite() && ep.ts > 0.0) {
        return Err(c.error_at(
            "episode.ts",
            format!("expected a positive number of seconds, got {}", ep.ts),
        ));
    }
    if ep.steps.is_some() && ep.duration.is_some() {
        return Err(c.error_at(
            "episode.duration",
            "give either `steps` or `duration`, not both",
        ));
    }
    if let Some(d) = ep.duration {
        if !(d.is_finite() && d > 0.0) {
            return Err(c.error_at(
                "episode.duration",
                format!("expected a positive number of seconds, got {d}"),
            ));
        }
    }
    for (key, value) in [
        ("episode.step_timeout", ep.step_timeout),
        ("episode.setup_timeout", ep.setup_timeout),
    ] {
        if let Some(t) = value.filter(|t| !(t.is_finite() && *t > 0.0)) {
            return Err(c.error_at(
                key,
                format!("expected a positive number of seconds, got {}", num(t)),
            ));
        }
    }
    check_pacing(c)
}

/// `episode.pace`: a positive, finite factor; `episode.behind`: a policy, with a pace.
fn check_pacing(c: &LoadedConfig) -> Result<(), ConfigError> {
    let ep = &c.config.episode;
    if let Some(p) = ep.pace {
        if !(p.is_finite() && p > 0.0) {
            return Err(c.error_at(
                "episode.pace",
                format!(
                    "expected a positive factor of real time (1.0: real time), got {}",
                    num(p)
                ),
            ));
        }
    }
    if let Some(b) = &ep.behind {
        if Behind::parse(b).is_none() {
            return Err(c.error_at(
                "episode.behind",
                format!("expected one of {:?}, got {b:?}", Behind::NAMES),
            ));
        }
        if ep.pace.is_none() {
            return Err(c.error_at(
                "episode.behind",
                "only a paced run (`episode.pace`) can fall behind: give a pace or remove it",
            ));
        }
    }
    Ok(())
}

/// `episode.steps` (or what `duration` makes of it): at least 1, at most 2^53, and a
/// virtual time that stays finite.
fn check_length(c: &LoadedConfig) -> Result<(), ConfigError> {
    let ep = &c.config.episode;
    if ep.steps == Some(0) {
        return Err(c.error_at("episode.steps", "expected at least 1 step"));
    }
    let steps = match (ep.steps, ep.duration) {
        (Some(n), _) => Some(n as f64),
        (None, Some(d)) => Some(steps_of(d, ep.ts)),
        (None, None) => None,
    };
    if let Some(n) = steps {
        if n > MAX_STEPS as f64 {
            let (key, what) = match ep.steps {
                Some(_) => ("episode.steps", format!("{} steps", num(n))),
                None => (
                    "episode.duration",
                    format!(
                        "duration / ts = {} / {} = {} steps",
                        num(ep.duration.unwrap_or(0.0)),
                        num(ep.ts),
                        num(n)
                    ),
                ),
            };
            return Err(c.error_at(
                key,
                format!("{what}: more than the 2^53 a run may have (raise episode.ts or shorten the episode)"),
            ));
        }
    }
    // Virtual time must stay finite for every step the run may take.
    let last = steps.unwrap_or(MAX_STEPS as f64);
    if !(ep.ts * last).is_finite() {
        return Err(c.error_at(
            "episode.ts",
            format!(
                "ts = {} s makes virtual time infinite within {} steps",
                num(ep.ts),
                num(last)
            ),
        ));
    }
    Ok(())
}

/// `episode.stages`: at least one, named, none twice.
fn check_stages(c: &LoadedConfig) -> Result<(), ConfigError> {
    let ep = &c.config.episode;
    if ep.stages.is_empty() {
        return Err(c.error_at("episode.stages", "expected at least one stage name"));
    }
    for (i, s) in ep.stages.iter().enumerate() {
        if s.trim().is_empty() {
            return Err(c.error_at("episode.stages", "a stage name may not be empty"));
        }
        if ep.stages[..i].contains(s) {
            return Err(c.error_at("episode.stages", format!("stage '{s}' is listed twice")));
        }
    }
    Ok(())
}

/// `[modules.NAME]`: names usable as subject tokens, known stages, periods, plugins
/// and subscription patterns.
fn check_modules(c: &LoadedConfig) -> Result<(), ConfigError> {
    let (cfg, ep) = (&c.config, &c.config.episode);
    if cfg.modules.is_empty() {
        return Err(ConfigError {
            file: c.file.clone(),
            line: None,
            key: Some("modules".into()),
            message: "expected at least one [modules.NAME] table".into(),
        });
    }
    for (name, m) in &cfg.modules {
        let key = |k: &str| format!("modules.{name}.{k}");
        if name.is_empty()
            || !name
                .chars()
                .all(|ch| ch.is_ascii_alphanumeric() || ch == '_' || ch == '-')
        {
            return Err(c.error_at(
                &format!("modules.{name}"),
                "module names may use only letters, digits, '_' and '-' (they become NATS subject tokens)",
            ));
        }
        if !ep.stages.contains(&m.stage) {
            return Err(c.error_at(
                &key("stage"),
                format!(
                    "unknown stage '{}', expected one of {:?} (episode.stages)",
                    m.stage, ep.stages
                ),
            ));
        }
        if m.every == 0 {
            return Err(c.error_at(&key("every"), "expected a period of at least 1 step"));
        }
        if m.offset >= m.every {
            return Err(c.error_at(
                &key("offset"),
                format!(
                    "expected an offset below `every` ({}), got {}",
                    m.every, m.offset
                ),
            ));
        }
        if m.plugin.trim().is_empty() {
            return Err(c.error_at(
                &key("plugin"),
                "expected `package.module:Class` or an entry-point name",
            ));
        }
        for p in m.subscribe.iter().flatten() {
            Pattern::new(p).map_err(|e| c.error_at(&key("subscribe"), e.to_string()))?;
        }
    }
    Ok(())
}

/// `[output]`: a plain run name, a directory, topic patterns, a flush interval.
fn check_output(c: &LoadedConfig) -> Result<(), ConfigError> {
    let cfg = &c.config;
    if let Some(name) = &cfg.output.name {
        if name.is_empty() || name == "." || name == ".." || name.contains(['/', '\\', '\0']) {
            return Err(c.error_at(
                "output.name",
                format!(
                    "expected a plain name for the run directories (NAME-001, …) inside output.dir, got {name:?}"
                ),
            ));
        }
    }
    if cfg
        .output
        .dir
        .as_ref()
        .is_some_and(|d| d.as_os_str().is_empty())
    {
        return Err(c.error_at("output.dir", "expected a directory, got an empty path"));
    }
    for p in &cfg.output.exclude {
        Pattern::new(p).map_err(|e| c.error_at("output.exclude", e.to_string()))?;
    }
    for p in &cfg.output.analysis {
        Pattern::new(p).map_err(|e| c.error_at("output.analysis", e.to_string()))?;
    }
    if !(cfg.output.flush_interval.is_finite() && cfg.output.flush_interval >= 0.0) {
        return Err(c.error_at("output.flush_interval", "expected a number of seconds >= 0"));
    }
    if let Some(s) = cfg.output.checkpoint_interval_s {
        if !(s.is_finite() && s >= 0.0) {
            return Err(c.error_at(
                "output.checkpoint_interval_s",
                format!(
                    "expected a number of seconds >= 0 (0: by steps only), got {}",
                    num(s)
                ),
            ));
        }
    }
    Ok(())
}

/// Parameter values JSON cannot carry to a plugin (NaN, infinities, TOML dates) are
/// refused here, naming the key: they would reach Python as `None` or a private table.
fn validate_params(c: &LoadedConfig) -> Result<(), ConfigError> {
    fn walk(c: &LoadedConfig, key: &str, v: &toml::Value) -> Result<(), ConfigError> {
        match v {
            toml::Value::Float(f) if !f.is_finite() => {
                Err(c.error_at(key, format!("expected a finite float, got {}", num(*f))))
            }
            toml::Value::Datetime(d) => Err(c.error_at(
                key,
                format!(
                    "a TOML date/time is not a parameter value; write it as a string (\"{d}\")"
                ),
            )),
            toml::Value::Array(items) => items.iter().enumerate().try_for_each(|(i, v)| {
                walk(c, key, v).map_err(|mut e| {
                    e.message = format!("item {i}: {}", e.message);
                    e
                })
            }),
            toml::Value::Table(t) => t
                .iter()
                .try_for_each(|(k, v)| walk(c, &format!("{key}.{k}"), v)),
            _ => Ok(()),
        }
    }
    for (name, m) in &c.config.modules {
        for (k, v) in &m.params {
            walk(c, &format!("modules.{name}.params.{k}"), v)?;
        }
    }
    Ok(())
}

/// Where modules run: `transport.kind` is a name, and shards and workers (several
/// processes for one module) need a transport that starts processes. The transport's
/// own section is read and checked by the transport (`crate::transport::check`).
fn check_placement(c: &LoadedConfig) -> Result<(), ConfigError> {
    if let Some(kind) = c.config.transport.get("kind") {
        if kind.as_str().is_none_or(str::is_empty) {
            return Err(c.error_at(
                "transport.kind",
                format!(
                    "expected the name of a transport (\"{IN_PROCESS}\", \"nats\"), got {kind}"
                ),
            ));
        }
    }
    for (name, m) in &c.config.modules {
        let key = |k: &str| format!("modules.{name}.{k}");
        if m.shards == 0 {
            return Err(c.error_at(&key("shards"), "expected at least 1 shard"));
        }
        if c.in_process() && (m.shards > 1 || m.workers.is_some()) {
            let k = if m.shards > 1 { "shards" } else { "workers" };
            return Err(c.error_at(
                &key(k),
                "needs a transport with worker processes (transport.kind = \"nats\")",
            ));
        }
    }
    Ok(())
}
