//! The `caviar-core` command line: `run`, `validate`, `inspect`.
//!
//! Exit codes: 0 success, 1 the run failed (a module error), 2 bad input (usage,
//! configuration, unreadable run directory), 130 interrupted.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::assembly::PrepareError;
use crate::config;
use crate::engine::{Engine, EngineError, StepReport, STATUS_TOPIC};
use crate::message::Payload;
use crate::run::{self, PluginLoader, RunSession};
use crate::status::{rtf_text, RunState};

#[derive(Parser, Debug)]
#[command(
    name = "caviar-core",
    version,
    about = "CAVIAR co-simulation of 6G communications, 3D scenarios and AI"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run an episode described by a TOML file, or resume one (--resume RUN_DIR).
    Run {
        #[arg(required_unless_present = "resume")]
        config: Option<PathBuf>,
        /// Go on with the run in RUN_DIR from its last checkpoint (a run that crashed,
        /// was killed or failed; in-process runs whose modules can be resumed).
        #[arg(long, value_name = "RUN_DIR", conflicts_with_all = ["config", "set", "out", "strict"])]
        resume: Option<PathBuf>,
        /// Override a value: --set episode.steps=10 --set modules.uav.params.speed=3
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
        /// Run directory to use (default: output.dir/NAME-NNN).
        #[arg(long)]
        out: Option<PathBuf>,
        /// No progress bar, only the final summary line.
        #[arg(long, short)]
        quiet: bool,
        /// Watch the run in the browser (`caviar-core view` on the run directory, on
        /// 127.0.0.1); with a terminal, it keeps serving after the run until Ctrl-C.
        #[arg(long)]
        view: bool,
        /// Port of the view (default: a free one).
        #[arg(long, requires = "view", value_name = "PORT")]
        view_port: Option<u16>,
        /// Refuse to run when the modules are not wired together (a subscription
        /// nothing publishes, a topic nobody reads): `episode.strict_wiring = true`.
        #[arg(long)]
        strict: bool,
    },
    /// Check a configuration and load its plugins without running anything; say what the
    /// wiring lets run at once (modules no data path joins, and across steps).
    Validate {
        config: PathBuf,
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
        /// Wiring warnings are errors (`episode.strict_wiring = true`).
        #[arg(long)]
        strict: bool,
    },
    /// Summarise a recorded run: steps, topics, message counts, time per module, RTF.
    Inspect { run_dir: PathBuf },
}

/// Entry point shared by the Rust binary and the Python package's console script.
/// `interrupted` is polled after every step (Ctrl-C handling belongs to the host).
pub fn main(args: Vec<String>, loader: &dyn PluginLoader, interrupted: &dyn Fn() -> bool) -> i32 {
    let cli = match Cli::try_parse_from(args) {
        Ok(cli) => cli,
        Err(e) => {
            let _ = e.print();
            return if e.use_stderr() { 2 } else { 0 };
        }
    };
    match cli.command {
        Command::Run {
            config,
            resume,
            set,
            out,
            quiet,
            view,
            view_port,
            strict,
        } => {
            let view = view.then_some(view_port.unwrap_or(0));
            let start = match (resume, config) {
                (Some(run_dir), _) => Start::Resume(run_dir),
                (None, Some(config)) => Start::New {
                    config,
                    set: with_strict(set, strict),
                    out,
                },
                (None, None) => unreachable!("clap requires one"),
            };
            run(start, quiet, view, loader, interrupted)
        }
        Command::Validate {
            config,
            set,
            strict,
        } => validate(&config, &with_strict(set, strict), loader),
        Command::Inspect { run_dir } => match crate::inspect::inspect(&run_dir) {
            Ok(text) => {
                print!("{text}");
                0
            }
            Err(e) => {
                eprintln!("error: {e}");
                2
            }
        },
    }
}

/// `--strict` is `--set episode.strict_wiring=true`.
fn with_strict(mut set: Vec<String>, strict: bool) -> Vec<String> {
    if strict {
        set.push("episode.strict_wiring=true".into());
    }
    set
}

fn validate(path: &Path, set: &[String], loader: &dyn PluginLoader) -> i32 {
    let result = config::load(path, set).and_then(|cfg| Ok((run::check(&cfg, loader)?, cfg)));
    match result {
        Ok(((warnings, concurrency), cfg)) => {
            for w in warnings {
                eprintln!("warning: {w}");
            }
            let steps = cfg
                .steps()
                .map_or("until a module ends it".to_string(), |s| {
                    format!("{s} steps")
                });
            println!(
                "{}: ok ({} modules in {} stages, Ts = {} s, {steps})",
                path.display(),
                cfg.config.modules.len(),
                cfg.config.episode.stages.len(),
                cfg.config.episode.ts
            );
            for line in concurrency {
                println!("  {line}");
            }
            0
        }
        Err(e) => {
            eprintln!("error: {e}");
            2
        }
    }
}

/// Each module's latest `caviar.status` line, shown beside the progress.
#[derive(Default)]
struct Statuses(std::collections::BTreeMap<String, String>);

impl Statuses {
    fn update(&mut self, report: &StepReport) {
        for m in &report.messages {
            if m.topic != STATUS_TOPIC {
                continue;
            }
            if let Payload::Json(text) = &m.payload {
                let line = serde_json::from_str::<String>(text).unwrap_or_else(|_| text.clone());
                let line: String = line.chars().filter(|c| !c.is_control()).take(80).collect();
                self.0.insert(m.source.clone(), line);
            }
        }
    }

    /// `"  comm: …  other: …"`, or nothing.
    fn text(&self) -> String {
        self.0.iter().map(|(m, s)| format!("  {m}: {s}")).collect()
    }
}

/// Progress for logs (stderr is not a terminal): a line every 10 s of wall time.
struct LogProgress {
    enabled: bool,
    last: Instant,
}

impl LogProgress {
    fn new(quiet: bool) -> Self {
        LogProgress {
            enabled: !quiet && !std::io::stderr().is_terminal(),
            last: Instant::now(),
        }
    }

    fn update(&mut self, engine: &Engine, report: &StepReport, statuses: &Statuses) {
        if !self.enabled || (self.last.elapsed().as_secs_f64() < 10.0 && !report.ended) {
            return;
        }
        self.last = Instant::now();
        let done = report.step + 1;
        let virtual_s = engine.virtual_time_s();
        let wall = engine.wall_s().max(1e-12);
        let eta = engine
            .planned_steps()
            .map(|n| {
                format!(
                    ", ETA {:.0} s",
                    wall / done as f64 * n.saturating_sub(done) as f64
                )
            })
            .unwrap_or_default();
        let of = engine
            .planned_steps()
            .map(|n| format!("/{n}"))
            .unwrap_or_default();
        eprintln!(
            "step {done}{of}, t = {virtual_s:.2} s, wall {wall:.1} s, RTF {}{eta}{}",
            rtf_text(wall, virtual_s),
            statuses.text()
        );
    }
}

fn progress_bar(engine: &Engine, quiet: bool) -> ProgressBar {
    let bar = match engine.planned_steps() {
        Some(n) => ProgressBar::new(n).with_style(
            ProgressStyle::with_template("{bar:30.cyan/blue} {pos}/{len} steps  {msg}  ETA {eta}")
                .expect("template"),
        ),
        None => ProgressBar::new_spinner().with_style(
            ProgressStyle::with_template("{spinner} {pos} steps  {msg}").expect("template"),
        ),
    };
    if quiet {
        bar.set_draw_target(ProgressDrawTarget::hidden());
    }
    bar
}

fn show_progress(bar: &ProgressBar, engine: &Engine, report: &StepReport, statuses: &Statuses) {
    bar.set_position(report.step + 1);
    let virtual_s = engine.virtual_time_s();
    let rtf = rtf_text(engine.wall_s(), virtual_s);
    bar.set_message(format!(
        "t = {virtual_s:.2} s  RTF {rtf}{}",
        statuses.text()
    ));
}

/// A new run of a configuration, or a run resumed from its checkpoint.
enum Start {
    New {
        config: PathBuf,
        set: Vec<String>,
        out: Option<PathBuf>,
    },
    Resume(PathBuf),
}

fn run(
    start: Start,
    quiet: bool,
    view_port: Option<u16>,
    loader: &dyn PluginLoader,
    interrupted: &dyn Fn() -> bool,
) -> i32 {
    let session = match &start {
        Start::New { config, set, out } => config::load(config, set)
            .map_err(PrepareError::from)
            .and_then(|cfg| RunSession::start(cfg, loader, out.as_deref())),
        Start::Resume(run_dir) => RunSession::resume(run_dir, loader),
    };
    let mut session = match session {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: {e}");
            return 2;
        }
    };
    // A supervising parent (caviar.cli) learns where the run is, to tell the truth about
    // a process that ends without closing it.
    if let Some(note) = std::env::var_os("CAVIAR_RUN_DIR_FILE") {
        let _ = std::fs::write(
            note,
            session.engine().run_dir().as_os_str().as_encoded_bytes(),
        );
    }
    for w in session.warnings() {
        eprintln!("warning: {w}");
    }
    if let Start::Resume(_) = start {
        eprintln!(
            "{}: resumed at step {}",
            session.engine().run_dir().display(),
            session.engine().steps_done()
        );
    }
    let viewing =
        view_port.is_some_and(|port| start_viewer(loader, session.engine().run_dir(), port));
    let started = Instant::now();
    // Ctrl-C sets a flag polled between steps and while transport replies are awaited;
    // a Python plugin never sees it as KeyboardInterrupt.
    let sigint = crate::interrupt::Guard::install();
    let bar = progress_bar(session.engine(), quiet);
    let mut log = LogProgress::new(quiet);
    let mut statuses = Statuses::default();
    let result = session.run(|engine, report| {
        statuses.update(report);
        show_progress(&bar, engine, report, &statuses);
        log.update(engine, report, &statuses);
        !interrupted()
    });
    bar.finish_and_clear();
    // The cause at once: the teardown after it (worker processes given a grace to leave)
    // may take seconds.
    let told = result
        .as_ref()
        .err()
        .inspect(|e| eprintln!("error: {e}"))
        .is_some();
    let error = session.finish(result).err();
    drop(sigint);
    let state = session.ended().expect("finished");
    let code = finish_line(
        session.engine(),
        state,
        error,
        told,
        started.elapsed().as_secs_f64(),
    );
    if !quiet {
        for (module, line) in &statuses.0 {
            eprintln!("  {module}: {line}");
        }
    }
    if viewing && std::io::stderr().is_terminal() && state != RunState::Interrupted {
        eprintln!("view: still serving the finished run; Ctrl-C to stop");
        while !interrupted() {
            std::thread::sleep(std::time::Duration::from_millis(200));
        }
    }
    code
}

/// Starts the host's viewer on the run directory; prints where, or why not.
fn start_viewer(loader: &dyn PluginLoader, run_dir: &Path, port: u16) -> bool {
    match loader.start_viewer(run_dir, port) {
        Ok(url) => {
            eprintln!("view: {url}");
            true
        }
        Err(e) => {
            eprintln!("warning: --view: {e}");
            false
        }
    }
}

/// The last line of a run (stdout when it completed, stderr with the error otherwise,
/// unless it was `told` already); returns the exit code.
fn finish_line(
    engine: &Engine,
    status: RunState,
    error: Option<EngineError>,
    told: bool,
    wall: f64,
) -> i32 {
    let virtual_s = engine.virtual_time_s();
    let dir = engine.run_dir().display();
    let status = status.as_str();
    match error {
        None => {
            println!(
                "{dir}: {status}, {} steps, {virtual_s:.2} s virtual in {wall:.2} s wall \
                 (RTF = T_p/T_v = {})",
                engine.steps_done(),
                rtf_text(wall, virtual_s)
            );
            0
        }
        Some(e) => {
            if !told {
                eprintln!("error: {e}");
            }
            eprintln!(
                "{dir}: {status} after {} steps; what was recorded is in the run directory",
                engine.steps_done()
            );
            match e {
                EngineError::Interrupted { .. } => 130,
                EngineError::Module { error, .. } if error.bad_input => 2,
                _ => 1,
            }
        }
    }
}
