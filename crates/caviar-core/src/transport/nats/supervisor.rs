//! Process supervision: the nats-server and the worker processes this run started,
//! whether they still live, and reaping them at the end.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use super::server::{tail, DieWithParent, SpawnedServer};

/// A worker process this run started, and where its output goes.
struct WorkerProcess {
    module: String,
    child: Child,
    log: PathBuf,
}

#[derive(Default)]
pub struct Supervisor {
    processes: Mutex<Vec<WorkerProcess>>,
    // Declared last: fields drop in order, the workers go before the server.
    server: Mutex<Option<SpawnedServer>>,
}

impl Supervisor {
    pub fn new(server: Option<SpawnedServer>) -> Self {
        Supervisor {
            processes: Mutex::default(),
            server: Mutex::new(server),
        }
    }

    /// Starts a worker process for `module`; its output goes to `log`.
    pub fn spawn_worker(
        &self,
        module: &str,
        command: &[String],
        envs: &[(String, String)],
        log: &Path,
    ) -> Result<(), String> {
        let file = std::fs::File::create(log).map_err(|e| format!("{}: {e}", log.display()))?;
        let child = Command::new(&command[0])
            .die_with_parent()
            .args(&command[1..])
            .envs(envs.iter().map(|(k, v)| (k, v)))
            .stdin(Stdio::null())
            .stdout(file.try_clone().map_err(|e| e.to_string())?)
            .stderr(file)
            .spawn()
            .map_err(|e| {
                format!(
                    "cannot start the worker of module '{module}' ({}): {e}",
                    command[0]
                )
            })?;
        self.processes.lock().unwrap().push(WorkerProcess {
            module: module.into(),
            child,
            log: log.into(),
        });
        Ok(())
    }

    /// Why `module` can no longer answer, if a process tells: the server we started
    /// exited, or a worker process of the module did.
    pub fn check_module(&self, module: &str) -> Result<(), String> {
        if let Some(why) = self
            .server
            .lock()
            .unwrap()
            .as_mut()
            .and_then(|s| s.exited())
        {
            return Err(why);
        }
        for p in self
            .processes
            .lock()
            .unwrap()
            .iter_mut()
            .filter(|p| p.module == module)
        {
            if let Ok(Some(status)) = p.child.try_wait() {
                return Err(format!(
                    "its worker process (pid {}) exited ({status}); {}",
                    p.child.id(),
                    last_lines(&p.log)
                ));
            }
        }
        Ok(())
    }

    /// What the worker processes of `module` that this run started last wrote (their logs'
    /// last lines), if it started any: a worker that stopped beating may still live, and
    /// what it last said is often why (a native crash handler at work, a deadlock's report).
    pub fn last_words(&self, module: &str) -> Option<String> {
        let procs = self.processes.lock().unwrap();
        let words: Vec<String> = procs
            .iter()
            .filter(|p| p.module == module)
            .map(|p| last_lines(&p.log))
            .collect();
        (!words.is_empty()).then(|| words.join("; "))
    }

    /// Checks that every spawned worker process is still running (during startup).
    pub fn check_startup(&self) -> Result<(), String> {
        for p in self.processes.lock().unwrap().iter_mut() {
            if let Ok(Some(status)) = p.child.try_wait() {
                return Err(format!(
                    "the worker process of module '{}' exited during startup ({status}); {}",
                    p.module,
                    last_lines(&p.log)
                ));
            }
        }
        Ok(())
    }

    /// Reaps the worker processes of `module` (they exit after teardown), killing any
    /// still running after `grace`.
    pub fn reap(&self, module: &str, grace: Duration) {
        let mut procs = self.processes.lock().unwrap();
        let deadline = Instant::now() + grace;
        for p in procs.iter_mut().filter(|p| p.module == module) {
            while Instant::now() < deadline {
                if let Ok(Some(_)) = p.child.try_wait() {
                    break;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
            if let Ok(None) = p.child.try_wait() {
                let _ = p.child.kill();
                let _ = p.child.wait();
            }
        }
    }

    /// Reaps every worker process, each module with `grace`.
    pub fn reap_all(&self, grace: Duration) {
        let mut modules: Vec<String> = self
            .processes
            .lock()
            .unwrap()
            .iter()
            .map(|p| p.module.clone())
            .collect();
        modules.dedup();
        for m in modules {
            self.reap(&m, grace);
        }
    }
}

/// "last lines of LOG:" and its last 15 lines, or that the log is empty (a process that
/// died before writing a line, or whose buffered output died with it).
fn last_lines(log: &Path) -> String {
    let lines = tail(log, 15);
    if lines.trim().is_empty() {
        format!("its log {} is empty", log.display())
    } else {
        format!("last lines of {}:\n{lines}", log.display())
    }
}
