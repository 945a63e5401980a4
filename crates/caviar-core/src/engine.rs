//! Virtual time, stages, barriers and routing.
//!
//! An episode runs steps k = 0, 1, … at virtual time t = k·Ts. Each step runs the
//! stages in order; the modules of one stage run concurrently (Rust modules on a
//! thread pool, Python plugins one after the other on the calling thread) and the
//! stage ends when all of them have returned: that is the barrier.
//!
//! **Visibility.** Messages a stage published are delivered when the stage ends,
//! in module declaration order and, within a module, in publishing order. A module
//! therefore sees, at each of its steps, every message on its subscriptions that was
//! published since its previous step by a module that finished before it started:
//! a message from step k, stage s reaches stages after s in step k, and stage s and
//! earlier stages at their next step (k+1 for modules that run every step). Modules
//! that run every `every`-th step receive all messages of the steps they skipped.
//!
//! **End.** After the configured number of steps, or after the step in which a
//! module published [`END_TOPIC`] (a mission that finished).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use rayon::prelude::*;

use crate::message::{Message, Outgoing, SharedMessage};
use crate::module::{
    module_seed, Module, ModuleError, ResourceProbe, SetupContext, StepInfo, Usage,
};
use crate::recorder::{RecordError, Recorder, TimingRow, CORE};
use crate::topic::{validate_topic, Pattern};

/// Publishing on this topic ends the episode after the current step.
pub const END_TOPIC: &str = "caviar.episode.end";

#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    #[error("module '{module}' failed {}: {}{}", place(.phase, .step, .time), .error.message, trace(.error))]
    Module {
        module: String,
        phase: &'static str,
        step: Option<u64>,
        time: Option<f64>,
        error: ModuleError,
    },
    #[error("module '{module}' published on topic '{topic}' in step {step}: {reason}")]
    Publish {
        module: String,
        step: u64,
        topic: String,
        reason: String,
    },
    #[error("recorder: {0}")]
    Record(#[from] RecordError),
    #[error("interrupted in step {step}")]
    Interrupted { step: u64 },
}

fn place(phase: &str, step: &Option<u64>, time: &Option<f64>) -> String {
    match (step, time) {
        (Some(s), Some(t)) => format!("at step {s} (t = {t:.3} s)"),
        _ => format!("in {phase}"),
    }
}

fn trace(e: &ModuleError) -> String {
    e.trace
        .as_ref()
        .map(|t| format!("\n{}", t.trim_end()))
        .unwrap_or_default()
}

/// Sees each stage's messages when they are delivered, in delivery order (e.g. to
/// mirror them onto a message bus, where a later stage's outside helper may answer).
pub type Tap = Box<dyn FnMut(&[SharedMessage]) + Send>;

/// How a module takes part in an episode.
pub struct ModuleSpec {
    pub name: String,
    pub stage: String,
    pub every: u64,
    pub offset: u64,
    /// `None`: the module's own default subscriptions.
    pub subscribe: Option<Vec<String>>,
    pub params: serde_json::Value,
    pub module: Box<dyn Module>,
}

struct Slot {
    name: String,
    stage: usize,
    every: u64,
    offset: u64,
    subs: Vec<Pattern>,
    seed: u64,
    params: serde_json::Value,
    module: Box<dyn Module>,
    inbox: Vec<SharedMessage>,
    set_up: bool,
}

impl Slot {
    fn runs_at(&self, step: u64) -> bool {
        step >= self.offset && (step - self.offset).is_multiple_of(self.every)
    }
}

/// What one step did.
#[derive(Debug, Clone)]
pub struct StepReport {
    pub step: u64,
    pub time: f64,
    /// Everything published in the step, in delivery order.
    pub messages: Vec<SharedMessage>,
    pub wall_s: f64,
    /// True when this was the last step of the episode.
    pub ended: bool,
}

pub struct EngineOptions {
    pub ts: f64,
    pub steps: Option<u64>,
    pub seed: u64,
    pub stages: Vec<String>,
    pub run_dir: PathBuf,
    pub config_dir: PathBuf,
}

pub struct Engine {
    opts: EngineOptions,
    slots: Vec<Slot>,
    /// Subscribers of each topic seen so far (topics repeat every step).
    routes: HashMap<String, Arc<[usize]>>,
    recorder: Option<Recorder>,
    next_step: u64,
    ended: bool,
    started: Option<Instant>,
    wall_s: f64,
    record_s: f64,
    tap: Option<Tap>,
    probe: Option<Box<dyn ResourceProbe>>,
}

pub(crate) fn thread_cpu_seconds() -> f64 {
    cpu_clock(libc::CLOCK_THREAD_CPUTIME_ID)
}

/// CPU time of all threads of this process, in seconds.
pub(crate) fn process_cpu_seconds() -> f64 {
    cpu_clock(libc::CLOCK_PROCESS_CPUTIME_ID)
}

fn cpu_clock(clock: libc::clockid_t) -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes into the timespec we own.
    unsafe { libc::clock_gettime(clock, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// Work that a module hands to threads of its own (Dr.Jit's pool, a plugin's thread
/// pool) does not show on the thread that ran its step. The process's CPU time over the
/// stage beyond what the in-process modules' own threads used is therefore shared among
/// them, in proportion to their own CPU time (their wall time where that is all zero):
/// a module alone in its stage is charged the process's CPU time of its step. Remote
/// modules report their own process's time and take no share.
fn charge_helper_threads(ran: &mut [Ran], process_cpu_s: f64) {
    let mut local: Vec<&mut Ran> = ran.iter_mut().filter(|r| r.reported.is_none()).collect();
    let own: f64 = local.iter().map(|r| r.cpu_s).sum();
    let extra = process_cpu_s - own;
    if local.is_empty() || extra <= 0.0 {
        return;
    }
    let by_cpu = own > 0.0;
    let total = if by_cpu {
        own
    } else {
        local.iter().map(|r| r.wall_s).sum()
    };
    let count = local.len() as f64;
    for r in local.iter_mut() {
        let weight = if by_cpu { r.cpu_s } else { r.wall_s };
        r.cpu_s += if total > 0.0 {
            extra * weight / total
        } else {
            extra / count
        };
    }
}

/// Resident set size of this process in MiB (Linux; NaN elsewhere).
pub(crate) fn resident_mib() -> f64 {
    use std::os::unix::fs::FileExt;
    use std::sync::OnceLock;
    // Opened once and read with pread: one system call per reading (open + read + close
    // cost about 6 µs, three times per step).
    static STATM: OnceLock<Option<(std::fs::File, f64)>> = OnceLock::new();
    let Some((file, page_mib)) = STATM.get_or_init(|| {
        // SAFETY: sysconf has no preconditions.
        let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) } as f64;
        std::fs::File::open("/proc/self/statm")
            .ok()
            .map(|f| (f, page / (1024.0 * 1024.0)))
    }) else {
        return f64::NAN;
    };
    let mut buf = [0u8; 128];
    let Ok(n) = file.read_at(&mut buf, 0) else {
        return f64::NAN;
    };
    let pages = std::str::from_utf8(&buf[..n]).ok().and_then(|t| {
        t.split_whitespace()
            .nth(1)
            .and_then(|v| v.parse::<f64>().ok())
    });
    pages.map_or(f64::NAN, |p| p * page_mib)
}

/// A module slot with its index, as a stage runs it.
type Indexed<'a> = (usize, &'a mut Slot);

struct Ran {
    slot: usize,
    result: Result<Vec<Outgoing>, ModuleError>,
    wall_s: f64,
    cpu_s: f64,
    /// What the module's own process reported (remote modules): memory and GPU.
    reported: Option<Usage>,
    msgs_in: u32,
}

fn run_slot(i: usize, slot: &mut Slot, at: StepInfo) -> Ran {
    let inbox = std::mem::take(&mut slot.inbox);
    let (t0, c0) = (Instant::now(), thread_cpu_seconds());
    let mut out = Vec::new();
    let result = slot.module.step(at, &inbox, &mut out).map(|()| out);
    Ran {
        slot: i,
        result,
        wall_s: t0.elapsed().as_secs_f64(),
        cpu_s: thread_cpu_seconds() - c0,
        reported: None,
        msgs_in: inbox.len() as u32,
    }
}

/// A remote module's step, started and not yet finished.
struct Started {
    slot: usize,
    msgs_in: u32,
    started: Result<(), ModuleError>,
}

fn start_remote(i: usize, slot: &mut Slot, at: StepInfo) -> Started {
    let inbox = std::mem::take(&mut slot.inbox);
    Started {
        slot: i,
        msgs_in: inbox.len() as u32,
        started: slot.module.start_step(at, &inbox),
    }
}

fn finish_remote(s: Started, slot: &mut Slot) -> Ran {
    let mut out = Vec::new();
    let result = s.started.and_then(|()| slot.module.finish_step(&mut out));
    let usage = result.as_ref().ok().copied().unwrap_or(Usage {
        wall_s: 0.0,
        cpu_s: 0.0,
        rss_mib: f64::NAN,
        gpu_util_pct: None,
        gpu_mem_mib: None,
    });
    Ran {
        slot: s.slot,
        result: result.map(|_| out),
        wall_s: usage.wall_s,
        cpu_s: usage.cpu_s,
        reported: Some(usage),
        msgs_in: s.msgs_in,
    }
}

impl Engine {
    /// Builds an engine. Module order is kept: it fixes the order within a stage.
    /// `recorder` is optional so that benchmarks can measure the bare engine.
    pub fn new(
        opts: EngineOptions,
        modules: Vec<ModuleSpec>,
        recorder: Option<Recorder>,
    ) -> Result<Self, String> {
        let mut slots = Vec::with_capacity(modules.len());
        for spec in modules {
            let stage = opts
                .stages
                .iter()
                .position(|s| *s == spec.stage)
                .ok_or_else(|| format!("module '{}': unknown stage '{}'", spec.name, spec.stage))?;
            let patterns = spec
                .subscribe
                .unwrap_or_else(|| spec.module.default_subscriptions());
            let subs = patterns
                .iter()
                .map(|p| Pattern::new(p).map_err(|e| format!("module '{}': {e}", spec.name)))
                .collect::<Result<Vec<_>, _>>()?;
            slots.push(Slot {
                seed: module_seed(opts.seed, &spec.name),
                name: spec.name,
                stage,
                every: spec.every.max(1),
                offset: spec.offset,
                subs,
                params: spec.params,
                module: spec.module,
                inbox: Vec::new(),
                set_up: false,
            });
        }
        Ok(Engine {
            opts,
            slots,
            routes: HashMap::new(),
            recorder,
            next_step: 0,
            ended: false,
            started: None,
            wall_s: 0.0,
            record_s: 0.0,
            tap: None,
            probe: None,
        })
    }

    /// Samples GPU use after each stage for the in-process modules.
    pub fn set_probe(&mut self, probe: Box<dyn ResourceProbe>) {
        self.probe = Some(probe);
    }

    pub fn set_tap(&mut self, tap: Tap) {
        self.tap = Some(tap);
    }

    pub fn run_dir(&self) -> &Path {
        &self.opts.run_dir
    }

    pub fn ts(&self) -> f64 {
        self.opts.ts
    }

    pub fn planned_steps(&self) -> Option<u64> {
        self.opts.steps
    }

    /// Steps done so far.
    pub fn steps_done(&self) -> u64 {
        self.next_step
    }

    pub fn is_done(&self) -> bool {
        self.ended || self.opts.steps.is_some_and(|n| self.next_step >= n)
    }

    /// Virtual time covered by the steps done so far, in seconds.
    pub fn virtual_time_s(&self) -> f64 {
        self.next_step as f64 * self.opts.ts
    }

    /// Wall-clock seconds spent in steps so far, recording included.
    pub fn wall_s(&self) -> f64 {
        self.wall_s
    }

    /// Of [`Engine::wall_s`], the seconds spent writing the recording.
    pub fn record_s(&self) -> f64 {
        self.record_s
    }

    pub fn module_names(&self) -> impl Iterator<Item = &str> {
        self.slots.iter().map(|s| s.name.as_str())
    }

    /// Calls every module's `setup` (once; `step` does it when needed).
    pub fn setup(&mut self) -> Result<(), EngineError> {
        if self.started.is_some() {
            return Ok(());
        }
        self.started = Some(Instant::now());
        for slot in &mut self.slots {
            let ctx = SetupContext {
                name: slot.name.clone(),
                seed: slot.seed,
                ts: self.opts.ts,
                steps: self.opts.steps,
                every: slot.every,
                offset: slot.offset,
                run_dir: self.opts.run_dir.clone(),
                config_dir: self.opts.config_dir.clone(),
                params: slot.params.clone(),
            };
            slot.module
                .setup(&ctx)
                .map_err(|error| EngineError::Module {
                    module: slot.name.clone(),
                    phase: "setup",
                    step: None,
                    time: None,
                    error,
                })?;
            slot.set_up = true;
        }
        Ok(())
    }

    fn subscribers(&mut self, topic: &str) -> Arc<[usize]> {
        if let Some(r) = self.routes.get(topic) {
            return r.clone();
        }
        let r: Arc<[usize]> = self
            .slots
            .iter()
            .enumerate()
            .filter(|(_, s)| s.subs.iter().any(|p| p.matches(topic)))
            .map(|(i, _)| i)
            .collect();
        self.routes.insert(topic.to_string(), r.clone());
        r
    }

    /// Runs one step. Returns `None` once the episode is over.
    pub fn step(&mut self) -> Result<Option<StepReport>, EngineError> {
        if self.is_done() {
            return Ok(None);
        }
        self.setup()?;
        let step = self.next_step;
        let at = StepInfo {
            step,
            time: step as f64 * self.opts.ts,
        };
        let t_step = Instant::now();
        let mut published = Vec::new();
        let mut module_wall = 0.0;
        let mut failure = None;
        let mut end = false;

        for stage in 0..self.opts.stages.len() {
            let stage_start = published.len();
            let (t_stage, cpu_stage) = (Instant::now(), process_cpu_seconds());
            let mut ran = self.run_stage(stage, at);
            let stage_wall = t_stage.elapsed().as_secs_f64();
            charge_helper_threads(&mut ran, process_cpu_seconds() - cpu_stage);
            // Modules of one process share its memory: the process's size after the stage
            // is what each module of the stage is charged with (NATS workers report their own).
            let sampled = self.recorder.is_some() && !ran.is_empty();
            let rss_mib = if sampled { resident_mib() } else { f64::NAN };
            let gpu = if sampled {
                self.probe.as_mut().and_then(|p| p.sample())
            } else {
                None
            };
            // The stage's share of module work is its slowest member (they ran side by side).
            module_wall += ran
                .iter()
                .map(|r| r.wall_s)
                .fold(0.0, f64::max)
                .min(stage_wall);
            ran.sort_by_key(|r| r.slot);
            for r in ran {
                let name = self.slots[r.slot].name.clone();
                let outgoing = match r.result {
                    Ok(out) => out,
                    Err(error) => {
                        failure.get_or_insert(EngineError::Module {
                            module: name.clone(),
                            phase: "step",
                            step: Some(step),
                            time: Some(at.time),
                            error,
                        });
                        Vec::new()
                    }
                };
                if let Some(rec) = &mut self.recorder {
                    let (rss_mib, gpu_util_pct, gpu_mem_mib) = match r.reported {
                        Some(u) => (u.rss_mib, u.gpu_util_pct, u.gpu_mem_mib),
                        None => (rss_mib, gpu.map(|g| g.0), gpu.map(|g| g.1)),
                    };
                    rec.record_timing(&TimingRow {
                        step,
                        time: at.time,
                        module: name.clone(),
                        wall_s: r.wall_s,
                        cpu_s: r.cpu_s,
                        rss_mib,
                        msgs_in: r.msgs_in,
                        msgs_out: outgoing.len() as u32,
                        gpu_util_pct,
                        gpu_mem_mib,
                    });
                }
                for o in outgoing {
                    if let Err(reason) = check_publish(&o.topic) {
                        failure.get_or_insert(EngineError::Publish {
                            module: name.clone(),
                            step,
                            topic: o.topic,
                            reason,
                        });
                        continue;
                    }
                    end |= o.topic == END_TOPIC;
                    let msg = Arc::new(Message {
                        step,
                        time: at.time,
                        topic: o.topic,
                        source: name.clone(),
                        payload: o.payload,
                    });
                    for &j in self.subscribers(&msg.topic).iter() {
                        self.slots[j].inbox.push(msg.clone());
                    }
                    if let Some(rec) = &mut self.recorder {
                        rec.record_message(&msg);
                    }
                    published.push(msg);
                }
            }
            if let Some(tap) = &mut self.tap {
                tap(&published[stage_start..]);
            }
            if failure.is_some() {
                break;
            }
        }

        let wall_s = t_step.elapsed().as_secs_f64();
        self.next_step += 1;
        let t_record = Instant::now();
        if let Some(rec) = &mut self.recorder {
            rec.record_timing(&TimingRow {
                step,
                time: at.time,
                module: CORE.into(),
                wall_s: (wall_s - module_wall).max(0.0),
                cpu_s: 0.0,
                rss_mib: resident_mib(),
                msgs_in: 0,
                msgs_out: 0,
                gpu_util_pct: None,
                gpu_mem_mib: None,
            });
            if failure.is_some() {
                rec.flush()?;
            } else {
                rec.end_step()?;
            }
        }
        let record_s = t_record.elapsed().as_secs_f64();
        self.record_s += record_s;
        let wall_s = wall_s + record_s;
        self.wall_s += wall_s;
        if let Some(f) = failure {
            self.ended = true;
            return Err(f);
        }
        self.ended |= end;
        Ok(Some(StepReport {
            step,
            time: at.time,
            messages: published,
            wall_s,
            ended: self.is_done(),
        }))
    }

    fn run_stage(&mut self, stage: usize, at: StepInfo) -> Vec<Ran> {
        let (remote, local): (Vec<Indexed>, Vec<Indexed>) = self
            .slots
            .iter_mut()
            .enumerate()
            .filter(|(_, s)| s.stage == stage && s.runs_at(at.step))
            .partition(|(_, s)| s.module.remote());
        // Remote modules first: they work while this process runs the local ones.
        let mut remote: Vec<(Started, &mut Slot)> = remote
            .into_iter()
            .map(|(i, s)| (start_remote(i, s, at), s))
            .collect();
        let (mut parallel, mut serial): (Vec<Indexed>, Vec<Indexed>) =
            local.into_iter().partition(|(_, s)| s.module.concurrent());
        let mut ran = if parallel.len() <= 1 {
            // Not worth a thread hop.
            serial.append(&mut parallel);
            serial
                .into_iter()
                .map(|(i, s)| run_slot(i, s, at))
                .collect()
        } else {
            let (mut a, b) = rayon::join(
                || {
                    parallel
                        .par_iter_mut()
                        .map(|(i, s)| run_slot(*i, s, at))
                        .collect::<Vec<_>>()
                },
                || {
                    serial
                        .into_iter()
                        .map(|(i, s)| run_slot(i, s, at))
                        .collect::<Vec<_>>()
                },
            );
            a.extend(b);
            a
        };
        ran.extend(
            remote
                .drain(..)
                .map(|(started, slot)| finish_remote(started, slot)),
        );
        ran
    }

    /// Runs steps until the episode ends. `after_step` sees each step; returning
    /// `false` from it interrupts the run.
    pub fn run(
        &mut self,
        mut after_step: impl FnMut(&Engine, &StepReport) -> bool,
    ) -> Result<(), EngineError> {
        while let Some(report) = self.step()? {
            if !after_step(self, &report) && !report.ended {
                self.ended = true;
                return Err(EngineError::Interrupted { step: report.step });
            }
        }
        Ok(())
    }

    /// Tears the modules down and finishes the recording. Call once, also after a
    /// failed step: whatever was recorded is then compacted and readable.
    pub fn close(&mut self) -> Result<(), EngineError> {
        let mut first = None;
        for slot in self.slots.iter_mut().filter(|s| s.set_up) {
            slot.set_up = false;
            if let Err(error) = slot.module.teardown() {
                first.get_or_insert(EngineError::Module {
                    module: slot.name.clone(),
                    phase: "teardown",
                    step: None,
                    time: None,
                    error,
                });
            }
        }
        if let Some(rec) = self.recorder.take() {
            rec.finish()?;
        }
        first.map_or(Ok(()), Err)
    }
}

fn check_publish(topic: &str) -> Result<(), String> {
    validate_topic(topic).map_err(|e| e.to_string())?;
    if topic.starts_with("caviar.") && topic != END_TOPIC {
        return Err(format!(
            "topics under 'caviar.' are reserved for the core (modules may publish '{END_TOPIC}')"
        ));
    }
    Ok(())
}
