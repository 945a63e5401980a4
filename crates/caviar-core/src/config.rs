//! The experiment description: one TOML file.
//!
//! ```toml
//! [episode]
//! ts = 0.1                 # sampling interval Ts, seconds of virtual time
//! duration = 60.0          # or `steps = 600`; neither: until a module ends the episode
//! seed = 7
//! stages = ["mobility", "communications", "ai"]
//! step_timeout = 600.0     # s one module step may take, any transport (default 600)
//! setup_timeout = 600.0    # s one module's setup or teardown may take, in process (default 600)
//!
//! [output]
//! checkpoint_every = 100   # steps between checkpoints for `run --resume` (default 100; 0: none)
//! pace = 1.0               # wall-clock pacing (1: real time); absent: as fast as possible
//! behind = "catch-up"      # or "drop": what a paced run does when it falls behind
//!
//! [modules.uav]
//! stage = "mobility"
//! plugin = "caviar_plugins.mobility:WaypointFlight"   # or an entry-point name
//! every = 1                # run every k-th step (default 1), starting at `offset`
//! subscribe = ["mission.>"]
//! [modules.uav.params]     # the plugin's own parameters
//! speed = 5.0
//! ```
//!
//! Every error names the file, the line and the key. Relative paths in the file are
//! relative to the file's directory.

use std::fmt;
use std::path::{Path, PathBuf};

use indexmap::IndexMap;
use serde::Deserialize;

use crate::pacing::{Behind, Pacer};
use crate::topic::Pattern;

/// A configuration error: file, line (when known), key (when known) and what was expected.
#[derive(Debug, Clone, PartialEq)]
pub struct ConfigError {
    pub file: String,
    pub line: Option<usize>,
    pub key: Option<String>,
    pub message: String,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file)?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        if let Some(key) = &self.key {
            write!(f, ": {key}")?;
        }
        write!(f, ": {}", self.message)
    }
}

impl std::error::Error for ConfigError {}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    pub episode: Episode,
    /// `[transport]`: `kind` and the settings of transports (`[transport.nats]`, …),
    /// read and checked by the transport that `kind` names (`crate::transport`).
    #[serde(default)]
    pub transport: toml::Table,
    #[serde(default)]
    pub output: Output,
    pub modules: IndexMap<String, ModuleConfig>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Episode {
    /// Sampling interval Ts in seconds of virtual time.
    pub ts: f64,
    pub steps: Option<u64>,
    /// Virtual duration in seconds; `steps = ceil(duration / ts)`.
    pub duration: Option<f64>,
    #[serde(default)]
    pub seed: u64,
    /// Stage names in execution order.
    pub stages: Vec<String>,
    /// Seconds one step of one module may take before the run stops (default 600),
    /// whatever the transport. In-process, a step past it cannot be interrupted: the
    /// process writes run.json as `failed`, naming the module and step, and exits (1).
    pub step_timeout: Option<f64>,
    /// Seconds one module's `setup`, or its `teardown`, may take in this process before
    /// the run stops the same way (default 600: a large scene's first ray-tracing
    /// compile can take minutes).
    pub setup_timeout: Option<f64>,
    /// Wiring warnings (a subscription nothing publishes, a topic nobody reads) stop
    /// the run before it starts instead of being printed (`caviar-core run --strict`).
    #[serde(default)]
    pub strict_wiring: bool,
    /// Wall-clock pacing: step k starts no earlier than t0 + k·ts/pace (1: real time,
    /// 2: twice as fast; absent: as fast as possible). See [`crate::pacing`].
    pub pace: Option<f64>,
    /// Falling behind a paced schedule: `catch-up` (default: the late steps run back
    /// to back) or `drop` (the steps whose slot passed are skipped and counted).
    pub behind: Option<String>,
}

/// `episode.step_timeout` when not given.
pub const DEFAULT_STEP_TIMEOUT: f64 = 600.0;

/// `episode.setup_timeout` when not given.
pub const DEFAULT_SETUP_TIMEOUT: f64 = 600.0;

/// `transport.kind` when not given: every module in this process.
pub const IN_PROCESS: &str = "inprocess";

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Output {
    /// Parent directory of run directories (default: `runs` in the current directory).
    pub dir: Option<PathBuf>,
    /// Run name prefix (default: the config file's stem). Runs go to `DIR/NAME-NNN`.
    pub name: Option<String>,
    /// Topic patterns that are routed but not recorded.
    #[serde(default)]
    pub exclude: Vec<String>,
    /// Topic patterns published for the recording (for analysis after the run), not for
    /// another module: a publication they match is not warned about as unread. A pattern
    /// that matches no declared publication is warned about instead.
    #[serde(default)]
    pub analysis: Vec<String>,
    /// Wall-clock seconds between recorder flushes. 0 (default) flushes after every
    /// step, so a killed process loses at most the step in progress.
    #[serde(default)]
    pub flush_interval: f64,
    /// Steps between checkpoints (`caviar-core run --resume`; default 100, 0: none).
    pub checkpoint_every: Option<u64>,
}

fn one() -> u64 {
    1
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModuleConfig {
    pub stage: String,
    /// `package.module:Class`, an entry-point name of group `caviar.plugins`, or a
    /// built-in (`caviar.replay`).
    pub plugin: String,
    #[serde(default = "one")]
    pub every: u64,
    #[serde(default)]
    pub offset: u64,
    /// Subscription patterns; when absent the plugin's own default applies.
    pub subscribe: Option<Vec<String>>,
    /// NATS transport: pieces each step is split into (the plugin sees `ctx.shard`,
    /// `ctx.shards`); the workers of the module share them through a queue group and
    /// their results are merged in shard order.
    #[serde(default = "one")]
    pub shards: u64,
    /// NATS transport: worker processes the core starts for this module (default: one
    /// per shard); 0 when they are started elsewhere with `caviar worker`.
    pub workers: Option<u64>,
    #[serde(default)]
    pub params: toml::Table,
}

/// A validated configuration together with where it came from.
#[derive(Debug, Clone)]
pub struct LoadedConfig {
    pub config: Config,
    /// The file as given (for messages).
    pub file: String,
    /// Directory that relative paths are resolved against.
    pub base_dir: PathBuf,
    /// The TOML text after `--set` overrides: saved into the run directory.
    pub text: String,
    /// The file's own text, before overrides: the lines messages name are its lines.
    pub source: String,
    pub overrides: Vec<String>,
}

impl LoadedConfig {
    /// Number of steps, or `None` when the episode runs until a module ends it.
    pub fn steps(&self) -> Option<u64> {
        let e = &self.config.episode;
        e.steps
            .or_else(|| e.duration.map(|d| steps_of(d, e.ts) as u64))
    }

    /// The wall-clock pacer of `episode.pace` (validated), if the run is paced.
    pub fn pacer(&self) -> Option<Pacer> {
        let ep = &self.config.episode;
        let behind = ep
            .behind
            .as_deref()
            .and_then(Behind::parse)
            .unwrap_or(Behind::CatchUp);
        ep.pace.map(|p| Pacer::new(p, ep.ts, behind))
    }

    /// Seconds one module step may take: `episode.step_timeout`, or 600.
    pub fn step_timeout(&self) -> f64 {
        self.config
            .episode
            .step_timeout
            .unwrap_or(DEFAULT_STEP_TIMEOUT)
    }

    /// Steps between checkpoints: `output.checkpoint_every`, or 100; 0: none.
    pub fn checkpoint_every(&self) -> u64 {
        self.config
            .output
            .checkpoint_every
            .unwrap_or(crate::checkpoint::DEFAULT_EVERY)
    }

    /// Seconds one module's setup or teardown may take: `episode.setup_timeout`, or 600.
    pub fn setup_timeout(&self) -> f64 {
        self.config
            .episode
            .setup_timeout
            .unwrap_or(DEFAULT_SETUP_TIMEOUT)
    }

    /// `transport.kind`: [`IN_PROCESS`] (the default) or the name of a transport.
    pub fn transport_kind(&self) -> &str {
        self.config
            .transport
            .get("kind")
            .and_then(|k| k.as_str())
            .unwrap_or(IN_PROCESS)
    }

    /// True when every module runs in this process.
    pub fn in_process(&self) -> bool {
        self.transport_kind() == IN_PROCESS
    }

    /// The table at dotted `key` (an empty one where the file has none) as `T`; errors
    /// name the file, the line and the full key, like those of the whole file.
    pub fn section<T: serde::de::DeserializeOwned>(&self, key: &str) -> Result<T, ConfigError> {
        let mut value = toml::Value::Table(self.text.parse().expect("parsed before"));
        for part in key.split('.') {
            value = match value {
                toml::Value::Table(mut t) => t
                    .remove(part)
                    .unwrap_or_else(|| toml::Value::Table(toml::Table::new())),
                other => other,
            };
        }
        serde_path_to_error::deserialize(value).map_err(|e| {
            let path = e.path().to_string();
            let inner = e.into_inner();
            let full = if path.is_empty() || path == "." {
                key.to_string()
            } else {
                format!("{key}.{path}")
            };
            let message = inner.message().trim().to_string();
            match message
                .strip_prefix("missing field `")
                .and_then(|m| m.split('`').next())
            {
                Some(field) => {
                    let mut err = self.error_at(key, "this required key is missing");
                    err.key = Some(format!("{full}.{field}"));
                    err
                }
                None => self.error_at(&full, message),
            }
        })
    }

    pub fn resolve(&self, path: &Path) -> PathBuf {
        if path.is_absolute() {
            path.to_path_buf()
        } else {
            self.base_dir.join(path)
        }
    }

    /// An error about `key` (dotted path), located at its line in the file (before any
    /// override), naming the `--set` override that gave the key its value, if one did.
    pub fn error_at(&self, key: &str, message: impl Into<String>) -> ConfigError {
        let path: Vec<&str> = key.split('.').collect();
        let mut message = message.into();
        if let Some(ov) = override_of(&self.overrides, &path) {
            message.push_str(&format!(" (from --set {ov})"));
        }
        ConfigError {
            file: self.file.clone(),
            line: line_of_key(&self.source, &path),
            key: Some(key.to_string()),
            message,
        }
    }

    /// The module's parameters as JSON, for plugins.
    pub fn params_json(&self, module: &str) -> serde_json::Value {
        serde_json::to_value(&self.config.modules[module].params).expect("TOML is valid JSON")
    }
}

/// At most this many steps (2^53): step indices and virtual times stay exact in f64.
pub const MAX_STEPS: u64 = 1 << 53;

/// `ceil(duration / ts)`, at least 1 for a positive duration (the 1e-9 absorbs
/// rounding noise: 0.3 / 0.1 is 3 steps, not 4).
fn steps_of(duration: f64, ts: f64) -> f64 {
    (duration / ts - 1e-9).ceil().max(1.0)
}

/// Reads, overrides and validates a configuration file.
pub fn load(path: &Path, overrides: &[String]) -> Result<LoadedConfig, ConfigError> {
    let file = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| ConfigError {
        file: file.clone(),
        line: None,
        key: None,
        message: format!("cannot read the configuration file: {e}"),
    })?;
    let base_dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
    parse(&text, &file, &base_dir, overrides)
}

/// The last `--set KEY=VALUE` whose key is `path` or a table holding it: where the value
/// at `path` came from.
fn override_of<'a>(overrides: &'a [String], path: &[&str]) -> Option<&'a str> {
    overrides
        .iter()
        .rev()
        .find(|ov| {
            let key = ov.split_once('=').map_or(ov.as_str(), |(k, _)| k);
            let set: Vec<&str> = key.trim().split('.').collect();
            path.len() >= set.len() && path[..set.len()] == set[..]
        })
        .map(String::as_str)
}

/// Like [`load`], from text; `file` is only used in messages.
pub fn parse(
    source: &str,
    file: &str,
    base_dir: &Path,
    overrides: &[String],
) -> Result<LoadedConfig, ConfigError> {
    let error = |line, key: Option<String>, message: String| ConfigError {
        file: file.to_string(),
        line,
        key,
        message,
    };
    let text = if overrides.is_empty() {
        source.to_string()
    } else {
        apply_overrides(source, overrides).map_err(|e| error(None, None, e))?
    };
    let de = toml::Deserializer::new(&text);
    let config: Config = serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let mut line = inner.span().map(|s| line_at(&text, s.start));
        let mut key = (path != "." && !path.is_empty()).then_some(path);
        let mut message = inner.message().to_string();
        if message.is_empty() {
            // The TOML parser says nothing of some characters (a control character in
            // a comment): say what is at the place it points to.
            let at = inner.span().map_or(text.len(), |s| s.start);
            message = match text.get(at..).and_then(|rest| rest.chars().next()) {
                Some(c) if c.is_control() => format!(
                    "a control character (U+{:04X}) is not allowed here in TOML",
                    c as u32
                ),
                Some(c) => format!("invalid TOML at '{c}'"),
                None => "the file ends where TOML expects more".into(),
            };
        }
        // "missing field `ts`" at `episode`: name the missing key, at its table's line.
        if let Some(field) = message
            .strip_prefix("missing field `")
            .and_then(|m| m.strip_suffix('`'))
        {
            let full = match &key {
                Some(k) => format!("{k}.{field}"),
                None => field.to_string(),
            };
            let table: Vec<&str> = full.split('.').collect();
            line = line_of_key(&text, &table[..table.len() - 1]).filter(|_| table.len() > 1);
            key = Some(full);
            message = "this required key is missing".into();
        }
        // serde sees a TOML date/time as a map: say what it is.
        if message.starts_with("invalid type: map") {
            let path: Vec<&str> = key.as_deref().unwrap_or("").split('.').collect();
            if is_datetime_at(&text, &path) {
                message = message.replace("invalid type: map", "invalid type: TOML date/time");
            }
        }
        if !overrides.is_empty() {
            // Lines were counted in the overridden text: name the file's own line, and
            // the override that set the key.
            let path: Vec<&str> = key.as_deref().map_or(vec![], |k| k.split('.').collect());
            match override_of(overrides, &path).filter(|_| !path.is_empty()) {
                Some(ov) => message.push_str(&format!(" (from --set {ov})")),
                None => message.push_str(" (after --set overrides)"),
            }
            line = (!path.is_empty())
                .then(|| line_of_key(source, &path))
                .flatten();
        }
        error(line, key, message)
    })?;
    let loaded = LoadedConfig {
        config,
        file: file.to_string(),
        base_dir: base_dir.to_path_buf(),
        text,
        source: source.to_string(),
        overrides: overrides.to_vec(),
    };
    validate(&loaded)?;
    Ok(loaded)
}

/// Checks what types alone cannot express, one named check after another.
fn validate(c: &LoadedConfig) -> Result<(), ConfigError> {
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

/// Applies `key.path=value` overrides. The value is read as a TOML value
/// (`3`, `2.5`, `true`, `"text"`, `[1, 2]`); anything else is taken as a string.
fn apply_overrides(text: &str, overrides: &[String]) -> Result<String, String> {
    let mut doc: toml_edit::DocumentMut = text
        .parse()
        .map_err(|e: toml_edit::TomlError| e.to_string())?;
    for ov in overrides {
        let (key, raw) = ov
            .split_once('=')
            .ok_or_else(|| format!("--set '{ov}': expected KEY=VALUE, e.g. episode.steps=10"))?;
        let path: Vec<&str> = key.trim().split('.').collect();
        if path.iter().any(|p| p.is_empty()) {
            return Err(format!("--set '{ov}': '{key}' is not a dotted key path"));
        }
        let value: toml_edit::Value = raw
            .trim()
            .parse()
            .unwrap_or_else(|_| toml_edit::Value::from(raw.trim()));
        let mut table = doc.as_table_mut() as &mut dyn toml_edit::TableLike;
        for part in &path[..path.len() - 1] {
            let entry = table.entry(part).or_insert(toml_edit::table());
            table = entry
                .as_table_like_mut()
                .ok_or_else(|| format!("--set '{ov}': '{part}' is a value, not a table"))?;
        }
        table.insert(path[path.len() - 1], toml_edit::Item::Value(value));
    }
    Ok(doc.to_string())
}

fn is_datetime_at(text: &str, path: &[&str]) -> bool {
    let Ok(doc) = toml_edit::ImDocument::parse(text) else {
        return false;
    };
    let mut item: &toml_edit::Item = doc.as_item();
    for part in path {
        match item.get(part) {
            Some(i) => item = i,
            None => return false,
        }
    }
    item.as_datetime().is_some()
}

/// A number for messages: plain when readable, else in scientific notation.
fn num(x: f64) -> String {
    if x == 0.0 || (1e-4..1e9).contains(&x.abs()) {
        format!("{x}")
    } else if x.is_finite() {
        let s = format!("{x:.3e}");
        let (mantissa, exp) = s.split_once('e').expect("scientific notation");
        let mantissa = mantissa.trim_end_matches('0').trim_end_matches('.');
        format!("{mantissa}e{exp}")
    } else {
        format!("{x}").to_lowercase()
    }
}

/// 1-based line of byte offset `pos`.
fn line_at(text: &str, pos: usize) -> usize {
    text[..pos.min(text.len())]
        .bytes()
        .filter(|&b| b == b'\n')
        .count()
        + 1
}

/// 1-based line where the key path is written (its value, or the deepest part found).
pub fn line_of_key(text: &str, path: &[&str]) -> Option<usize> {
    let doc = toml_edit::ImDocument::parse(text).ok()?;
    let mut table: &dyn toml_edit::TableLike = doc.as_table();
    let mut line = None;
    let mut i = 0;
    while i < path.len() {
        let Some((k, item)) = table.get_key_value(path[i]) else {
            break;
        };
        if let Some(span) = item.span().or_else(|| k.span()) {
            line = Some(line_at(text, span.start));
        }
        // `sites.1.name`: the second `[[…sites]]` table (or item of an inline array).
        let index = path.get(i + 1).and_then(|p| p.parse::<usize>().ok());
        if let (Some(n), Some(tables)) = (index, item.as_array_of_tables()) {
            let Some(t) = tables.get(n) else { break };
            if let Some(span) = t.span() {
                line = Some(line_at(text, span.start));
            }
            i += 2;
            table = t;
            continue;
        }
        if let (Some(n), Some(array)) = (index, item.as_array()) {
            if let Some(span) = array.get(n).and_then(|v| v.span()) {
                line = Some(line_at(text, span.start));
            }
            break;
        }
        i += 1;
        if i == path.len() {
            break;
        }
        match item.as_table_like() {
            Some(t) => table = t,
            None => break,
        }
    }
    line
}

#[cfg(test)]
mod tests {
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
        let e =
            parse_str(&GOOD.replace("steps = 4", "steps = 4\nduration = 2.0"), &[]).unwrap_err();
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
}
