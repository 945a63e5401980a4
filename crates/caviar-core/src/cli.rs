//! The `caviar-core` command line: `run`, `validate`, `inspect`.
//!
//! Exit codes: 0 success, 1 the run failed (a module error), 2 bad input (usage,
//! configuration, unreadable run directory), 130 interrupted.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::config;
use crate::engine::{Engine, EngineError, StepReport};
use crate::recorder::{read_messages, read_timings, CORE};
use crate::run::{load_modules, prepare, write_status, PluginLoader};

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
        } => run(&config, &set, out.as_deref(), quiet, loader, interrupted),
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
        load_modules(&cfg, loader)?;
        let n = cfg.config.modules.len();
        Ok((cfg, n))
    });
    match result {
        Ok((cfg, n)) => {
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
        use std::io::IsTerminal;
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
            "step {done}{of}, t = {virtual_s:.2} s, wall {wall:.1} s, RTF {:.3}{eta}",
            virtual_s / wall
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
    let rtf = virtual_s / engine.wall_s().max(1e-12);
    bar.set_message(format!("t = {virtual_s:.2} s  RTF {rtf:.3}"));
}

fn run(
    path: &Path,
    set: &[String],
    out: Option<&Path>,
    quiet: bool,
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
    let mut engine = match prepare(&cfg, loader, out) {
        Ok(e) => e,
        Err(e) => {
            eprintln!("error: {e}");
            return 2;
        }
    };
    let started = Instant::now();
    let bar = progress_bar(&engine, quiet);
    let mut log = LogProgress::new(quiet);
    let result = engine.run(|engine, report| {
        show_progress(&bar, engine, report);
        log.update(engine, report);
        !interrupted()
    });
    bar.finish_and_clear();
    let closed = engine.close();
    let error = result.err().or(closed.err());
    let status = match &error {
        None => "completed",
        Some(EngineError::Interrupted { .. }) => "interrupted",
        Some(_) => "failed",
    };
    if let Err(e) = write_status(&cfg, &engine, status, error.as_ref()) {
        eprintln!("error: {e}");
    }
    let virtual_s = engine.virtual_time_s();
    let wall = started.elapsed().as_secs_f64();
    let dir = engine.run_dir().display();
    match error {
        None => {
            println!(
                "{dir}: {status}, {} steps, {virtual_s:.2} s virtual in {wall:.2} s wall (RTF {:.3})",
                engine.steps_done(),
                virtual_s / wall.max(1e-12)
            );
            0
        }
        Some(e) => {
            eprintln!("error: {e}");
            eprintln!(
                "{dir}: {status} after {} steps; what was recorded is in the run directory",
                engine.steps_done()
            );
            if matches!(e, EngineError::Interrupted { .. }) {
                130
            } else {
                1
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
    use std::fmt::Write;
    let status: serde_json::Value = std::fs::read_to_string(run_dir.join("run.json"))
        .map_err(|e| format!("{}: not a run directory ({e})", run_dir.display()))
        .and_then(|t| {
            serde_json::from_str(&t)
                .map_err(|e| format!("{}: {e}", run_dir.join("run.json").display()))
        })?;
    let messages = read_messages(run_dir).map_err(|e| e.to_string())?;
    let timings = read_timings(run_dir).map_err(|e| e.to_string())?;

    let mut s = String::new();
    let get = |k: &str| status.get(k).cloned().unwrap_or(serde_json::Value::Null);
    let steps_done = get("steps_done").as_u64().unwrap_or(0);
    let planned = get("steps_planned")
        .as_u64()
        .map_or("open-ended".to_string(), |n| n.to_string());
    let wall = get("wall_s").as_f64().unwrap_or(0.0);
    let virt = get("virtual_time_s").as_f64().unwrap_or(0.0);
    writeln!(
        s,
        "run       {}  ({})",
        run_dir.display(),
        get("status").as_str().unwrap_or("?")
    )
    .unwrap();
    writeln!(
        s,
        "steps     {steps_done} of {planned}, Ts = {} s, {virt:.3} s virtual",
        get("ts")
    )
    .unwrap();
    let rtf = if wall > 0.0 {
        format!("{:.3}", virt / wall)
    } else {
        "-".into()
    };
    let record = get("record_s").as_f64().unwrap_or(0.0);
    writeln!(s, "wall      {wall:.3} s in steps ({record:.3} s of it recording), RTF {rtf} (virtual s per wall s)").unwrap();
    let total_bytes: u64 = messages.iter().map(|m| m.payload.len() as u64).sum();
    writeln!(
        s,
        "messages  {} ({})",
        messages.len(),
        human_bytes(total_bytes)
    )
    .unwrap();
    if let Some(err) = get("error").as_object() {
        writeln!(
            s,
            "error     {}",
            err.get("message").and_then(|m| m.as_str()).unwrap_or("?")
        )
        .unwrap();
        if let Some(m) = err.get("module").and_then(|m| m.as_str()) {
            writeln!(
                s,
                "          in module '{m}', {} at step {}",
                err["phase"].as_str().unwrap_or("?"),
                err["step"]
            )
            .unwrap();
        }
    }

    struct TopicRow {
        kind: &'static str,
        count: u64,
        first: u64,
        last: u64,
        bytes: u64,
        sources: Vec<String>,
    }
    let mut topics: BTreeMap<&str, TopicRow> = BTreeMap::new();
    for m in &messages {
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
    let mut modules: Vec<(String, ModuleRow)> = Vec::new();
    for t in &timings {
        let i = match modules.iter().position(|(n, _)| *n == t.module) {
            Some(i) => i,
            None => {
                modules.push((t.module.clone(), ModuleRow::default()));
                modules.len() - 1
            }
        };
        let r = &mut modules[i].1;
        r.runs += 1;
        r.wall += t.wall_s;
        r.cpu += t.cpu_s;
        r.rss_max = r.rss_max.max(t.rss_mib);
        r.msgs_in += t.msgs_in as u64;
        r.msgs_out += t.msgs_out as u64;
        if let Some(u) = t.gpu_util_pct {
            r.gpu_util_sum += u;
            r.gpu_util_n += 1;
        }
        if let Some(m) = t.gpu_mem_mib {
            r.gpu_mem_max = Some(r.gpu_mem_max.map_or(m, |x: f64| x.max(m)));
        }
    }
    // GPU columns only where a GPU was measured.
    let gpu = modules
        .iter()
        .any(|(_, r)| r.gpu_util_n > 0 || r.gpu_mem_max.is_some());
    // The core's row last: it is the overhead of everything above it.
    modules.sort_by_key(|(n, _)| n == CORE);
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
    Ok(s)
}
