//! The experiment file's types, as read from TOML, and [`LoadedConfig`]: a validated
//! configuration with where it came from and what is derived from it.

use std::fmt;
use std::path::{Path, PathBuf};

use indexmap::IndexMap;
use serde::Deserialize;

use super::text::{line_of_key, override_of};
use crate::pacing::{Behind, Pacer};

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
    /// Steps between checkpoints (`caviar-core run --resume`; default 100, 0: none at all).
    pub checkpoint_every: Option<u64>,
    /// Wall-clock seconds after which a checkpoint is written even before
    /// `checkpoint_every` steps (default 60, 0: by steps only): any run killed after its
    /// first minute resumes.
    pub checkpoint_interval_s: Option<f64>,
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

    /// Steps between checkpoints: `output.checkpoint_every`, or 100; 0: none.
    pub fn checkpoint_every(&self) -> u64 {
        self.config
            .output
            .checkpoint_every
            .unwrap_or(crate::checkpoint::DEFAULT_EVERY)
    }

    /// Wall-clock seconds after which a checkpoint is due whatever the steps:
    /// `output.checkpoint_interval_s`, or 60; `None`: by steps only (0, or no checkpoints).
    pub fn checkpoint_interval(&self) -> Option<std::time::Duration> {
        let s = self
            .config
            .output
            .checkpoint_interval_s
            .unwrap_or(crate::checkpoint::DEFAULT_INTERVAL_S);
        (s > 0.0 && self.checkpoint_every() > 0).then(|| std::time::Duration::from_secs_f64(s))
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
pub(super) fn steps_of(duration: f64, ts: f64) -> f64 {
    (duration / ts - 1e-9).ceil().max(1.0)
}
