//! The core's NATS client for one run: the connection on a runtime of its own, the
//! run key that seals every frame the core sends and opens every frame it receives,
//! and the record of what was refused (`security` in run.json).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::json;

use super::auth::{RunKey, SeqWindow};
use super::settings::NatsSettings;
use crate::module::ModuleError;

/// What was refused during the run: by the core (worker messages that failed
/// authentication) and by each worker (core frames it refused, as it reported them).
#[derive(Debug, Default)]
pub struct Security {
    pub rejected_by_core: u64,
    pub rejected_by_workers: HashMap<String, u64>,
    /// The first refusals, in words.
    pub warnings: Vec<String>,
    /// Sequence numbers seen per worker and subject (hello, loaded, heartbeat).
    seqs: HashMap<(String, String), SeqWindow>,
}

impl Security {
    const MAX_WARNINGS: usize = 50;

    /// Records a message the core refused and says so on stderr.
    pub fn reject(&mut self, why: String) {
        eprintln!("caviar: security: refused {why}");
        self.rejected_by_core += 1;
        if self.warnings.len() < Self::MAX_WARNINGS {
            self.warnings.push(why);
        }
    }

    /// Accepts sequence number `n` of `worker` on control subject `leaf`, once.
    pub fn accept_seq(&mut self, worker: &str, leaf: &str, n: u64) -> Result<(), String> {
        self.seqs
            .entry((worker.to_string(), leaf.to_string()))
            .or_default()
            .accept(n)
    }

    /// A worker's own count of refused core frames (they only grow).
    pub fn worker_reports(&mut self, worker: &str, rejected: u64) {
        let n = self.rejected_by_workers.entry(worker.into()).or_default();
        if rejected > *n {
            eprintln!(
                "caviar: security: worker {worker} refused {} core frame(s) that failed authentication or were out of sequence",
                rejected - *n
            );
            *n = rejected;
        }
    }

    /// `security` in run.json.
    pub fn to_json(&self) -> serde_json::Value {
        let by_workers: u64 = self.rejected_by_workers.values().sum();
        json!({
            "rejected": self.rejected_by_core + by_workers,
            "rejected_by_core": self.rejected_by_core,
            "rejected_by_workers": self.rejected_by_workers,
            "warnings": self.warnings,
        })
    }
}

/// Seals and opens the run's frames: the run key, the run id and the core's one
/// sequence counter for every frame it sends. Cloned into the control plane's task.
#[derive(Clone)]
pub struct Sealer {
    pub key: RunKey,
    pub run_id: String,
    seq: Arc<AtomicU64>,
}

impl Sealer {
    pub fn new(key: RunKey, run_id: &str) -> Self {
        Sealer {
            key,
            run_id: run_id.to_string(),
            seq: Arc::default(),
        }
    }

    /// A frame of the core for `subject`, with the next sequence number.
    pub fn seal(&self, subject: &str, body: Vec<u8>) -> Vec<u8> {
        let n = self.seq.fetch_add(1, Ordering::SeqCst) + 1;
        self.key.seal(&self.run_id, subject, n, body)
    }

    /// The sequence number and body of a frame received on `subject`.
    pub fn open<'a>(&self, subject: &str, frame: &'a [u8]) -> Result<(u64, &'a [u8]), String> {
        self.key.open(&self.run_id, subject, frame)
    }
}

pub struct Client {
    pub rt: tokio::runtime::Runtime,
    pub client: async_nats::Client,
    pub url: String,
    /// `caviar.<run_id>`: every control subject of the run starts with it.
    pub prefix: String,
    pub sealer: Sealer,
    pub security: Arc<Mutex<Security>>,
    disconnected_since: Mutex<Option<Instant>>,
}

impl Client {
    /// Connects to the server at `url` on a runtime of two threads.
    pub fn open(
        url: &str,
        options: async_nats::ConnectOptions,
        run_id: &str,
        key: RunKey,
    ) -> Result<Self, String> {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("caviar-nats")
            .enable_all()
            .build()
            .map_err(|e| format!("tokio runtime: {e}"))?;
        let client = rt
            .block_on(options.connect(url))
            .map_err(|e| format!("cannot connect to the NATS server at {url}: {e}"))?;
        Ok(Client {
            rt,
            client,
            url: url.to_string(),
            prefix: format!("caviar.{run_id}"),
            sealer: Sealer::new(key, run_id),
            security: Arc::default(),
            disconnected_since: Mutex::new(None),
        })
    }

    pub fn run_id(&self) -> &str {
        &self.sealer.run_id
    }

    /// Seals a frame of the core for `subject` with the next sequence number.
    pub fn seal(&self, subject: &str, body: Vec<u8>) -> Vec<u8> {
        self.sealer.seal(subject, body)
    }

    /// Checks a worker's reply received on `subject` (its own inbox: a reply cannot be
    /// moved to another request); a refusal is recorded.
    pub fn open_reply<'a>(
        &self,
        what: &str,
        subject: &str,
        frame: &'a [u8],
    ) -> Result<&'a [u8], ModuleError> {
        self.sealer
            .open(subject, frame)
            .map(|(_, body)| body)
            .map_err(|e| {
                self.security.lock().unwrap().reject(format!("reply to {what}: {e}"));
                ModuleError::new(format!(
                    "{what}: the reply failed authentication (someone without the run key answered; see security in run.json)"
                ))
            })
    }

    /// Err once the connection has stayed down for longer than `limit`.
    pub fn check_connected(&self, limit: Duration) -> Result<(), String> {
        let mut since = self.disconnected_since.lock().unwrap();
        if self.client.connection_state() != async_nats::connection::State::Disconnected {
            *since = None;
            return Ok(());
        }
        let t = *since.get_or_insert_with(Instant::now);
        if t.elapsed() > limit {
            return Err(format!(
                "the connection to the NATS server at {} dropped and was retried for {:.0} s without success",
                self.url,
                limit.as_secs_f64()
            ));
        }
        Ok(())
    }
}

/// The client options of `[transport.nats]`: credentials, token, user, TLS.
pub fn connect_options(
    n: &NatsSettings,
    resolve: &dyn Fn(&Path) -> PathBuf,
) -> Result<async_nats::ConnectOptions, String> {
    let mut o = async_nats::ConnectOptions::new()
        .name("caviar-core")
        // Our own deadlines apply (step_timeout, heartbeats); the client's 10 s default would cut long steps.
        .request_timeout(None)
        .max_reconnects(None)
        .connection_timeout(Duration::from_secs(5));
    if let Some(c) = &n.credentials {
        let text = std::fs::read_to_string(resolve(c))
            .map_err(|e| format!("transport.nats.credentials: {}: {e}", resolve(c).display()))?;
        o = o
            .credentials(&text)
            .map_err(|e| format!("transport.nats.credentials: {e}"))?;
    }
    if let Some(t) = &n.token {
        o = o.token(t.clone());
    }
    if let (Some(u), Some(p)) = (&n.user, &n.password) {
        o = o.user_and_password(u.clone(), p.clone());
    }
    if let Some(ca) = &n.tls_ca {
        o = o.add_root_certificates(resolve(ca));
    }
    if let (Some(c), Some(k)) = (&n.tls_cert, &n.tls_key) {
        o = o.add_client_certificate(resolve(c), resolve(k));
    }
    if n.tls_required {
        o = o.require_tls(true);
    }
    Ok(o)
}
