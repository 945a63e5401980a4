//! The `caviar-core` command line: `run`, `validate`, `inspect`.
//!
//! Exit codes: 0 success, 1 the run failed (a module error), 2 bad input (usage,
//! configuration, unreadable run directory), 130 interrupted.

use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::assembly::wiring_warnings;
use crate::config;
use crate::engine::{EndReason, Engine, EngineError, StepReport};
use crate::message::Message;
use crate::recorder::{read_messages, read_timings, TimingRow, CORE};
use crate::run::{check_paths, load_modules, prepare_monitored, PluginLoader};
use crate::status::{write_status, RunErrorInfo, RunState, RunStatus};

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
    /// Run an episode described by a TOML file.
    Run {
        config: PathBuf,
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
    },
    /// Check a configuration and load its plugins without running anything.
    Validate {
        config: PathBuf,
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
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
            set,
            out,
            quiet,
            view,
            view_port,
        } => {
            let view = view.then_some(view_port.unwrap_or(0));
            run(
                &config,
                &set,
                out.as_deref(),
                quiet,
                view,
                loader,
                interrupted,
            )
        }
        Command::Validate { config, set } => validate(&config, &set, loader),
        Command::Inspect { run_dir } => match inspect(&run_dir) {
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

fn validate(path: &Path, set: &[String], loader: &dyn PluginLoader) -> i32 {
    let result = config::load(path, set).and_then(|cfg| {
        check_paths(&cfg)?;
        let specs = load_modules(&cfg, loader)?;
        let n = cfg.config.modules.len();
        Ok((wiring_warnings(&cfg, &specs), cfg, n))
    });
    match result {
        Ok((warnings, cfg, n)) => {
            for w in warnings {
                eprintln!("warning: {w}");
            }
            let steps = cfg
                .steps()
                .map_or("until a module ends it".to_string(), |s| {
                    format!("{s} steps")
                });
            println!(
                "{}: ok ({n} modules in {} stages, Ts = {} s, {steps})",
                path.display(),
                cfg.config.episode.stages.len(),
                cfg.config.episode.ts
            );
            0
        }
        Err(e) => {
            eprintln!("error: {e}");
            2
        }
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

    fn update(&mut self, engine: &Engine, report: &StepReport) {
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
            "step {done}{of}, t = {virtual_s:.2} s, wall {wall:.1} s, RTF {}{eta}",
            rtf_text(wall, virtual_s)
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

fn show_progress(bar: &ProgressBar, engine: &Engine, report: &StepReport) {
    bar.set_position(report.step + 1);
    let virtual_s = engine.virtual_time_s();
    let rtf = rtf_text(engine.wall_s(), virtual_s);
    bar.set_message(format!("t = {virtual_s:.2} s  RTF {rtf}"));
}

fn run(
    path: &Path,
    set: &[String],
    out: Option<&Path>,
    quiet: bool,
    view_port: Option<u16>,
    loader: &dyn PluginLoader,
    interrupted: &dyn Fn() -> bool,
) -> i32 {
    let cfg = match config::load(path, set) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: {e}");
            return 2;
        }
    };
    let (mut engine, mut monitor) = match prepare_monitored(&cfg, loader, out) {
        Ok(e) => e,
        Err(e) => {
            eprintln!("error: {e}");
            return 2;
        }
    };
    let viewing = view_port.is_some_and(|port| start_viewer(loader, engine.run_dir(), port));
    let started = Instant::now();
    // Ctrl-C sets a flag polled between steps and while NATS replies are awaited; a
    // Python plugin never sees it as KeyboardInterrupt.
    let sigint = crate::interrupt::Guard::install();
    let bar = progress_bar(&engine, quiet);
    let mut log = LogProgress::new(quiet);
    let result = engine.run(|engine, report| {
        monitor.after_step(&cfg, engine);
        show_progress(&bar, engine, report);
        log.update(engine, report);
        !interrupted()
    });
    bar.finish_and_clear();
    let closed = engine.close();
    drop(monitor);
    drop(sigint);
    let error = result.err().or(closed.err());
    let status = match &error {
        None => RunState::Completed,
        Some(EngineError::Interrupted { .. }) => RunState::Interrupted,
        Some(_) => RunState::Failed,
    };
    if let Err(e) = write_status(&cfg, &engine, status, error.as_ref()) {
        eprintln!("error: {e}");
    }
    let code = finish_line(&engine, status, error, started.elapsed().as_secs_f64());
    if viewing && std::io::stderr().is_terminal() && status != RunState::Interrupted {
        eprintln!("view: still serving the finished run; Ctrl-C to stop");
        while !interrupted() {
            std::thread::sleep(std::time::Duration::from_millis(200));
        }
    }
    code
}

/// The paper's real-time factor RTF = T_p / T_v (wall-clock time over virtual time),
/// three decimals; "-" before any virtual time has passed.
fn rtf_text(wall_s: f64, virtual_s: f64) -> String {
    match crate::status::rtf(wall_s, virtual_s) {
        Some(r) => format!("{r:.3}"),
        None => "-".into(),
    }
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

/// The last line of a run (stdout when it completed, stderr with the error otherwise);
/// returns the exit code.
fn finish_line(engine: &Engine, status: RunState, error: Option<EngineError>, wall: f64) -> i32 {
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
            eprintln!("error: {e}");
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

fn human_bytes(n: u64) -> String {
    match n {
        n if n >= 1 << 30 => format!("{:.1} GiB", n as f64 / (1u64 << 30) as f64),
        n if n >= 1 << 20 => format!("{:.1} MiB", n as f64 / (1u64 << 20) as f64),
        n if n >= 1 << 10 => format!("{:.1} KiB", n as f64 / 1024.0),
        n => format!("{n} B"),
    }
}

/// The text `caviar-core inspect` prints.
pub fn inspect(run_dir: &Path) -> Result<String, String> {
    let status = RunStatus::read_live(run_dir)?;
    let messages = read_messages(run_dir).map_err(|e| e.to_string())?;
    let timings = read_timings(run_dir).map_err(|e| e.to_string())?;
    let mut s = String::new();
    write_summary(&mut s, run_dir, &status, &messages);
    write_topics(&mut s, &messages);
    write_modules(&mut s, module_rows(&timings));
    Ok(s)
}

/// How the episode ended, in words.
fn end_text(status: &RunStatus) -> Option<String> {
    Some(match status.end_reason? {
        EndReason::Steps => "all planned steps ran".into(),
        EndReason::Module => format!(
            "module '{}' published caviar.episode.end",
            status.ended_by.as_deref().unwrap_or("?")
        ),
        EndReason::Error => "an error (below)".into(),
        EndReason::Interrupted => "interrupted (Ctrl-C)".into(),
        EndReason::Closed => "closed by the host before its end".into(),
    })
}

/// The head: status, steps, wall time, messages, how it ended, the error.
fn write_summary(s: &mut String, run_dir: &Path, status: &RunStatus, messages: &[Message]) {
    use std::fmt::Write;
    let planned = status
        .steps_planned
        .map_or("open-ended".to_string(), |n| n.to_string());
    let (wall, virt) = (status.wall_s, status.virtual_time_s);
    writeln!(
        s,
        "run       {}  ({})",
        run_dir.display(),
        status.status.as_str()
    )
    .unwrap();
    writeln!(
        s,
        "steps     {} of {planned}, Ts = {} s, {virt:.3} s virtual",
        status.steps_done,
        serde_json::json!(status.ts)
    )
    .unwrap();
    let rtf = rtf_text(wall, virt);
    let record = status.record_s;
    writeln!(
        s,
        "wall      {wall:.3} s in steps ({record:.3} s of it recording), RTF {rtf} \
         (T_p/T_v: wall-clock s per virtual s; < 1 is faster than real time)"
    )
    .unwrap();
    let total_bytes: u64 = messages.iter().map(|m| m.payload.len() as u64).sum();
    writeln!(
        s,
        "messages  {} ({})",
        messages.len(),
        human_bytes(total_bytes)
    )
    .unwrap();
    if let Some(end) = end_text(status) {
        writeln!(s, "ended     {end}").unwrap();
    }
    if let Some(text) = status.abandoned_text() {
        writeln!(s, "ended     {text}").unwrap();
    }
    if let Some(err) = &status.error {
        writeln!(s, "error     {}", err.message()).unwrap();
        if let RunErrorInfo::Module {
            module,
            phase,
            step,
            ..
        } = err
        {
            let step = serde_json::json!(step);
            writeln!(s, "          in module '{module}', {phase} at step {step}").unwrap();
        }
    }
}

/// One row per topic: kind, count, steps, bytes, sources.
fn write_topics(s: &mut String, messages: &[Message]) {
    use std::fmt::Write;
    struct TopicRow {
        kind: &'static str,
        count: u64,
        first: u64,
        last: u64,
        bytes: u64,
        sources: Vec<String>,
    }
    let mut topics: BTreeMap<&str, TopicRow> = BTreeMap::new();
    for m in messages {
        let row = topics.entry(&m.topic).or_insert(TopicRow {
            kind: m.payload.kind().as_str(),
            count: 0,
            first: m.step,
            last: m.step,
            bytes: 0,
            sources: Vec::new(),
        });
        row.count += 1;
        row.last = m.step;
        row.bytes += m.payload.len() as u64;
        if !row.sources.contains(&m.source) {
            row.sources.push(m.source.clone());
        }
    }
    let w = topics.keys().map(|t| t.len()).max().unwrap_or(5).max(5);
    writeln!(
        s,
        "\n{:<w$}  {:<8} {:>9} {:>13} {:>10}  from",
        "topic", "kind", "messages", "steps", "bytes"
    )
    .unwrap();
    for (t, r) in &topics {
        writeln!(
            s,
            "{t:<w$}  {:<8} {:>9} {:>13} {:>10}  {}",
            r.kind,
            r.count,
            format!("{}-{}", r.first, r.last),
            human_bytes(r.bytes),
            r.sources.join(", ")
        )
        .unwrap();
    }
}

/// A module's timings added up over the run.
#[derive(Default)]
struct ModuleRow {
    runs: u64,
    wall: f64,
    cpu: f64,
    rss_max: f64,
    msgs_in: u64,
    msgs_out: u64,
    gpu_util_sum: f64,
    gpu_util_n: u64,
    gpu_mem_max: Option<f64>,
}

impl ModuleRow {
    fn add(&mut self, t: &TimingRow) {
        self.runs += 1;
        self.wall += t.wall_s;
        self.cpu += t.cpu_s;
        self.rss_max = self.rss_max.max(t.rss_mib);
        self.msgs_in += t.msgs_in as u64;
        self.msgs_out += t.msgs_out as u64;
        if let Some(u) = t.gpu_util_pct {
            self.gpu_util_sum += u;
            self.gpu_util_n += 1;
        }
        if let Some(m) = t.gpu_mem_mib {
            self.gpu_mem_max = Some(self.gpu_mem_max.map_or(m, |x: f64| x.max(m)));
        }
    }
}

/// Per module in order of first appearance, the core's row last (it is the overhead
/// of everything above it).
fn module_rows(timings: &[TimingRow]) -> Vec<(String, ModuleRow)> {
    let mut modules: Vec<(String, ModuleRow)> = Vec::new();
    for t in timings {
        let i = match modules.iter().position(|(n, _)| *n == t.module) {
            Some(i) => i,
            None => {
                modules.push((t.module.clone(), ModuleRow::default()));
                modules.len() - 1
            }
        };
        modules[i].1.add(t);
    }
    modules.sort_by_key(|(n, _)| n == CORE);
    modules
}

fn write_modules(s: &mut String, modules: Vec<(String, ModuleRow)>) {
    use std::fmt::Write;
    // GPU columns only where a GPU was measured.
    let gpu = modules
        .iter()
        .any(|(_, r)| r.gpu_util_n > 0 || r.gpu_mem_max.is_some());
    let total: f64 = modules.iter().map(|(_, r)| r.wall).sum::<f64>().max(1e-12);
    let w = modules
        .iter()
        .map(|(n, _)| n.len())
        .max()
        .unwrap_or(6)
        .max(6);
    writeln!(
        s,
        "\n{:<w$}  {:>6} {:>10} {:>7} {:>10} {:>9} {:>11} {:>8} {:>8}{}",
        "module",
        "steps",
        "wall s",
        "share",
        "mean ms",
        "cpu s",
        "max RSS MiB",
        "in",
        "out",
        if gpu { "  mean GPU %  max GPU MiB" } else { "" }
    )
    .unwrap();
    for (n, r) in &modules {
        writeln!(
            s,
            "{n:<w$}  {:>6} {:>10.4} {:>6.1}% {:>10.3} {:>9.4} {:>11.1} {:>8} {:>8}",
            r.runs,
            r.wall,
            100.0 * r.wall / total,
            1e3 * r.wall / r.runs.max(1) as f64,
            r.cpu,
            r.rss_max,
            r.msgs_in,
            r.msgs_out
        )
        .unwrap();
        if gpu {
            s.pop(); // the newline: the GPU columns continue the row
            let util = if r.gpu_util_n > 0 {
                format!("{:.1}", r.gpu_util_sum / r.gpu_util_n as f64)
            } else {
                "-".into()
            };
            let mem = r.gpu_mem_max.map_or("-".into(), |m| format!("{m:.0}"));
            writeln!(s, "  {util:>10} {mem:>12}").unwrap();
        }
    }
}
