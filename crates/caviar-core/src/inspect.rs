//! What `caviar-core inspect` prints about a recorded run, and the per-module totals
//! of its timings: computed here once, for the command line and for the Python side
//! (`caviar._core.module_totals`, read by `caviar.load_run(...).module_times()`).

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

use crate::engine::EndReason;
use crate::message::Message;
use crate::pacing::{Behind, PacingReport};
use crate::recorder::{read_messages, read_timings, TimingRow, CORE};
use crate::status::{rtf_text, RunErrorInfo, RunStatus};

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
    write_modules(&mut s, &module_totals(&timings));
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
    if let Some(p) = &status.pacing {
        writeln!(s, "pacing    {}", pacing_text(p)).unwrap();
    }
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
    if !status.resumed_at.is_empty() {
        let at: Vec<String> = status.resumed_at.iter().map(u64::to_string).collect();
        writeln!(s, "resumed   at step {}", at.join(", ")).unwrap();
    }
    // The checkpoint itself, not run.json's note of it (written at most once a second).
    let checkpoint = (status.status != crate::status::RunState::Completed)
        .then(|| crate::checkpoint::Checkpoint::read(run_dir).ok())
        .flatten();
    if let Some(cp) = checkpoint {
        let refusal = cp.modules.iter().find_map(|m| match &m.state {
            crate::checkpoint::SavedState::Unsupported { why } => Some((&m.name, why)),
            _ => None,
        });
        match refusal {
            Some((name, why)) => {
                writeln!(s, "resume    not possible: module '{name}': {why}").unwrap()
            }
            None => writeln!(
                s,
                "resume    from step {}: caviar-core run --resume {}",
                cp.next_step,
                run_dir.display()
            )
            .unwrap(),
        }
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

/// `pace 1.0 (real time), 3 of 100 steps late (worst 120.0 ms, p99 80.0 ms), 0 dropped (catch-up)`.
pub fn pacing_text(p: &PacingReport) -> String {
    let pace = serde_json::json!(p.pace);
    let what = if p.pace == 1.0 {
        " (real time)".to_string()
    } else {
        format!(" ({pace}x real time)")
    };
    let behind = match p.behind {
        Behind::CatchUp => "catch-up",
        Behind::Drop => "drop",
    };
    format!(
        "pace {pace}{what}, {} of {} steps late (worst {:.1} ms, p99 {:.1} ms), {} dropped ({behind})",
        p.late_steps, p.steps, p.worst_late_ms, p.p99_late_ms, p.dropped_steps
    )
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

/// One module's timings added up over a run: a row of `inspect`'s module table and of
/// `caviar.load_run(...).module_times()`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ModuleTotals {
    pub module: String,
    /// Steps it ran.
    pub steps: u64,
    pub wall_s: f64,
    pub cpu_s: f64,
    pub rss_max_mib: f64,
    pub msgs_in: u64,
    pub msgs_out: u64,
    /// Mean over the steps where a GPU was measured; `None` where none was.
    pub gpu_util_mean_pct: Option<f64>,
    pub gpu_mem_max_mib: Option<f64>,
    #[serde(skip)]
    gpu_util_sum: f64,
    #[serde(skip)]
    gpu_util_n: u64,
}

impl ModuleTotals {
    fn add(&mut self, t: &TimingRow) {
        self.steps += 1;
        self.wall_s += t.wall_s;
        self.cpu_s += t.cpu_s;
        self.rss_max_mib = self.rss_max_mib.max(t.rss_mib);
        self.msgs_in += t.msgs_in as u64;
        self.msgs_out += t.msgs_out as u64;
        if let Some(u) = t.gpu_util_pct {
            self.gpu_util_sum += u;
            self.gpu_util_n += 1;
            self.gpu_util_mean_pct = Some(self.gpu_util_sum / self.gpu_util_n as f64);
        }
        if let Some(m) = t.gpu_mem_mib {
            self.gpu_mem_max_mib = Some(self.gpu_mem_max_mib.map_or(m, |x: f64| x.max(m)));
        }
    }
}

/// Per module in order of first appearance, the core's row last (it is the overhead
/// of everything above it).
pub fn module_totals(timings: &[TimingRow]) -> Vec<ModuleTotals> {
    let mut modules: Vec<ModuleTotals> = Vec::new();
    for t in timings {
        let i = match modules.iter().position(|r| r.module == t.module) {
            Some(i) => i,
            None => {
                modules.push(ModuleTotals {
                    module: t.module.clone(),
                    ..Default::default()
                });
                modules.len() - 1
            }
        };
        modules[i].add(t);
    }
    modules.sort_by_key(|r| r.module == CORE);
    modules
}

fn write_modules(s: &mut String, modules: &[ModuleTotals]) {
    use std::fmt::Write;
    // GPU columns only where a GPU was measured.
    let gpu = modules
        .iter()
        .any(|r| r.gpu_util_mean_pct.is_some() || r.gpu_mem_max_mib.is_some());
    let total: f64 = modules.iter().map(|r| r.wall_s).sum::<f64>().max(1e-12);
    let w = modules
        .iter()
        .map(|r| r.module.len())
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
    for r in modules {
        let n = &r.module;
        writeln!(
            s,
            "{n:<w$}  {:>6} {:>10.4} {:>6.1}% {:>10.3} {:>9.4} {:>11.1} {:>8} {:>8}",
            r.steps,
            r.wall_s,
            100.0 * r.wall_s / total,
            1e3 * r.wall_s / r.steps.max(1) as f64,
            r.cpu_s,
            r.rss_max_mib,
            r.msgs_in,
            r.msgs_out
        )
        .unwrap();
        if gpu {
            s.pop(); // the newline: the GPU columns continue the row
            let util = r
                .gpu_util_mean_pct
                .map_or("-".into(), |u| format!("{u:.1}"));
            let mem = r.gpu_mem_max_mib.map_or("-".into(), |m| format!("{m:.0}"));
            writeln!(s, "  {util:>10} {mem:>12}").unwrap();
        }
    }
}
