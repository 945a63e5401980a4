//! The core's side of a NATS run, put together: the [`Client`], the
//! [`ControlPlane`] that knows the workers, and the [`Supervisor`] of the processes
//! this run started. Remote modules and the bridge hold it; the session shuts it down.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use super::client::Client;
use super::control::ControlPlane;
use super::settings::NatsSettings;
use super::supervisor::Supervisor;
use crate::module::ModuleError;

pub struct Timeouts {
    pub startup: Duration,
    pub step: Duration,
    pub heartbeat: Duration,
    pub reconnect: Duration,
}

impl Timeouts {
    /// `step`: `LoadedConfig::step_timeout` (episode.step_timeout or its older name).
    pub fn from_config(n: &NatsSettings, step: f64) -> Self {
        Timeouts {
            startup: Duration::from_secs_f64(n.startup_timeout),
            step: Duration::from_secs_f64(step),
            heartbeat: Duration::from_secs_f64(n.heartbeat_timeout),
            reconnect: Duration::from_secs_f64(n.reconnect_timeout),
        }
    }
}

pub struct Link {
    pub conn: Client,
    pub control: ControlPlane,
    pub timeouts: Timeouts,
    /// Set when the run ends badly (a step past its deadline, Ctrl-C).
    abandoning: AtomicBool,
    /// Set once the workers were told to stop.
    shut: AtomicBool,
    // Dropped last (fields drop in order): the client goes before the server.
    pub procs: Supervisor,
}

impl Link {
    pub fn new(conn: Client, control: ControlPlane, procs: Supervisor, timeouts: Timeouts) -> Self {
        Link {
            conn,
            control,
            timeouts,
            abandoning: AtomicBool::new(false),
            shut: AtomicBool::new(false),
            procs,
        }
    }

    /// Why `module` can no longer answer, if we can tell: the server or a worker
    /// process of it that exited, workers that stopped beating, a connection that
    /// stayed down.
    pub fn check_alive(&self, module: &str, expected: &[String]) -> Result<(), String> {
        self.procs.check_module(module)?;
        let silent = self.control.silent(expected, self.timeouts.heartbeat);
        if !silent.is_empty() && silent.len() == expected.len() {
            let words = self.procs.last_words(module);
            return Err(format!(
                "its worker stopped answering (no heartbeat): {}{}",
                silent.join("; "),
                words.map(|w| format!("; {w}")).unwrap_or_default()
            ));
        }
        self.conn.check_connected(self.timeouts.reconnect)
    }

    /// Waits for `task`, checking every 100 ms that `module` can still answer.
    pub fn wait<T: Send + 'static>(
        &self,
        module: &str,
        expected: &[String],
        what: &str,
        mut task: tokio::task::JoinHandle<T>,
        timeout: Duration,
    ) -> Result<T, ModuleError> {
        let t0 = Instant::now();
        loop {
            // Replies of a stage arrive together: most are in before we ask, and need no timer.
            if task.is_finished() {
                return self
                    .conn
                    .rt
                    .block_on(task)
                    .map_err(|e| ModuleError::new(format!("{what}: {e}")));
            }
            let done = self.conn.rt.block_on(async {
                tokio::select! {
                    r = &mut task => Some(r),
                    _ = tokio::time::sleep(Duration::from_millis(100)) => None,
                }
            });
            if let Some(r) = done {
                return r.map_err(|e| ModuleError::new(format!("{what}: {e}")));
            }
            if let Err(why) = self.check_alive(module, expected) {
                task.abort();
                self.abandon();
                return Err(ModuleError::new(format!("{what}: {why}")));
            }
            if crate::interrupt::requested() {
                task.abort();
                self.abandon();
                return Err(ModuleError::new(format!("{what}: interrupted (Ctrl-C)")));
            }
            if t0.elapsed() > timeout {
                task.abort();
                self.abandon();
                return Err(ModuleError::new(format!(
                    "{what}: no reply within {:.0} s (episode.step_timeout / transport.nats.startup_timeout)",
                    timeout.as_secs_f64()
                )));
            }
        }
    }

    /// The run is ending badly (a step timed out, Ctrl-C): teardowns get a short grace.
    pub fn abandon(&self) {
        self.abandoning.store(true, Ordering::Relaxed);
    }

    pub fn abandoning(&self) -> bool {
        self.abandoning.load(Ordering::Relaxed)
    }

    /// Tells every worker of the run to leave, then makes sure the ones we started did.
    /// Once; later calls (and the drop) do nothing.
    pub fn shutdown(&self) {
        if self.shut.swap(true, Ordering::SeqCst) {
            return;
        }
        let (c, subject) = (
            self.conn.client.clone(),
            format!("{}.stop", self.conn.prefix),
        );
        let stop = self.conn.seal(&subject, b"{}".to_vec());
        let flush = Duration::from_millis(if self.abandoning() { 300 } else { 2000 });
        let _ = self.conn.rt.block_on(async move {
            let _ = c.publish(subject, stop.into()).await;
            tokio::time::timeout(flush, c.flush()).await
        });
        let grace = if self.abandoning() { 1 } else { 3 };
        self.procs.reap_all(Duration::from_secs(grace));
    }
}

impl Drop for Link {
    fn drop(&mut self) {
        self.shutdown();
    }
}
