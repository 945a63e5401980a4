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
//! module published [`END_TOPIC`] (a mission that finished); [`EndReason`] says which
//! (or that an error, an interruption or an early close ended it).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use rayon::prelude::*;

use serde::{Deserialize, Serialize};

use crate::checkpoint::{Checkpoint, ModuleCheckpoint, SavedMessage, SavedState};
use crate::message::{Message, Outgoing, SharedMessage};
use crate::metrics::{
    charge_helper_threads, process_cpu_seconds, resident_mib, thread_cpu_seconds,
};
use crate::module::{
    module_seed, AnyModule, Module, ModuleError, ModuleState, RemoteModule, ResourceProbe,
    SetupContext, StepInfo, Usage,
};
use crate::pacing::{Pacer, PacingReport};
use crate::recorder::{RecordError, Recorder, TimingRow, CORE};
use crate::topic::{validate_topic, Pattern};

/// Publishing on this topic ends the episode after the current step.
pub const END_TOPIC: &str = "caviar.episode.end";

/// A module's one-line status for people (a JSON string, e.g. what share of its work a
/// cache served): the command line shows each module's latest beside its progress. It is
/// recorded like any message and means nothing to the engine.
pub const STATUS_TOPIC: &str = "caviar.status";

#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    #[error("module '{module}' failed {}: {}{}", place(.phase, .step, .time), .error.message, trace(.error))]
    Module {
        module: String,
        phase: &'static str,
        step: Option<u64>,
        time: Option<f64>,
        /// Boxed: keeps `Result<_, EngineError>` small.
        error: Box<ModuleError>,
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

/// What a module is doing when the [`StartHook`] is told it started.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    Setup,
    Step,
    Teardown,
}

impl Phase {
    pub fn as_str(self) -> &'static str {
        match self {
            Phase::Setup => "setup",
            Phase::Step => "step",
            Phase::Teardown => "teardown",
        }
    }
}

/// Told, before a stage's modules start their step, which ones (in start order), and
/// with an empty list when the stage is over; likewise before each module's setup and
/// teardown (stage `""`): what a run record and a watchdog need to name the module a
/// dead or stuck run was in.
pub type StartHook = Box<dyn FnMut(Phase, StepInfo, &str, &[&str]) + Send>;

/// How a module takes part in an episode.
pub struct ModuleSpec {
    pub name: String,
    pub stage: String,
    pub every: u64,
    pub offset: u64,
    /// `None`: the module's own default subscriptions.
    pub subscribe: Option<Vec<String>>,
    pub params: serde_json::Value,
    pub module: AnyModule,
}

struct Slot {
    name: String,
    stage: usize,
    every: u64,
    offset: u64,
    subs: Vec<Pattern>,
    seed: u64,
    params: serde_json::Value,
    module: AnyModule,
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
    /// Set when the episode ended before its planned steps ran out (or had none).
    end: Option<EndReason>,
    /// The module that published [`END_TOPIC`], when that ended the episode.
    ended_by: Option<String>,
    started: Option<Instant>,
    wall_s: f64,
    record_s: f64,
    tap: Option<Tap>,
    probe: Option<Box<dyn ResourceProbe>>,
    on_start: Option<StartHook>,
    pacer: Option<Pacer>,
    /// The step the last checkpoint resumes at, and the steps this run was resumed at.
    checkpoint_step: Option<u64>,
    resumed_at: Vec<u64>,
    checkpoint_s: f64,
}

/// Why an episode ended (`end_reason` in run.json).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum EndReason {
    /// The configured number of steps ran.
    Steps,
    /// A module published [`END_TOPIC`].
    Module,
    /// A module, the recorder or a publication failed.
    Error,
    /// The host asked to stop (Ctrl-C).
    Interrupted,
    /// The host closed the episode before its end (`Simulation.close()`).
    Closed,
}

/// An in-process module's step, ready to run.
struct LocalStep<'a> {
    slot: usize,
    name: &'a str,
    module: &'a mut Box<dyn Module>,
    inbox: Vec<SharedMessage>,
}

/// A remote module's step, ready to start.
struct RemoteStep<'a> {
    slot: usize,
    name: &'a str,
    module: &'a mut Box<dyn RemoteModule>,
    inbox: Vec<SharedMessage>,
}

/// What running one module's step gave.
struct Ran {
    slot: usize,
    result: Result<Vec<Outgoing>, ModuleError>,
    wall_s: f64,
    cpu_s: f64,
    /// What the module's own process reported (remote modules): memory and GPU.
    reported: Option<Usage>,
    msgs_in: u32,
}

fn run_local(s: &mut LocalStep, at: StepInfo) -> Ran {
    let (t0, c0) = (Instant::now(), thread_cpu_seconds());
    let mut out = Vec::new();
    let result = s.module.step(at, &s.inbox, &mut out).map(|()| out);
    Ran {
        slot: s.slot,
        result,
        wall_s: t0.elapsed().as_secs_f64(),
        cpu_s: thread_cpu_seconds() - c0,
        reported: None,
        msgs_in: s.inbox.len() as u32,
    }
}

/// Starts a remote module's step; `finish_remote` waits for it.
fn start_remote(s: &mut RemoteStep, at: StepInfo) -> Result<(), ModuleError> {
    s.module.start_step(at, &s.inbox)
}

fn finish_remote(s: RemoteStep, started: Result<(), ModuleError>) -> Ran {
    let mut out = Vec::new();
    let result = started.and_then(|()| s.module.finish_step(&mut out));
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
        msgs_in: s.inbox.len() as u32,
    }
}

/// What the process looked like after a stage: charged to each in-process module of it.
#[derive(Clone, Copy)]
struct StageSample {
    rss_mib: f64,
    gpu: Option<(f64, f64)>,
}

/// A step in progress: what its stages published and how it is going.
struct StepState {
    at: StepInfo,
    published: Vec<SharedMessage>,
    /// Module work of the step: each stage's slowest member.
    module_wall: f64,
    failure: Option<EngineError>,
    /// The first module that published [`END_TOPIC`].
    end_by: Option<String>,
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
            end: None,
            ended_by: None,
            started: None,
            wall_s: 0.0,
            record_s: 0.0,
            tap: None,
            probe: None,
            on_start: None,
            pacer: None,
            checkpoint_step: None,
            resumed_at: Vec::new(),
            checkpoint_s: 0.0,
        })
    }

    /// Paces the steps on the wall clock (`episode.pace`, see [`crate::pacing`]).
    pub fn set_pacer(&mut self, pacer: Pacer) {
        self.pacer = Some(pacer);
    }

    /// How the steps kept to the wall clock; `None` when the run is not paced.
    pub fn pacing(&self) -> Option<PacingReport> {
        self.pacer.as_ref().map(Pacer::report)
    }

    /// Samples GPU use after each stage for the in-process modules.
    /// The step the last checkpoint taken resumes at.
    pub fn checkpoint_step(&self) -> Option<u64> {
        self.checkpoint_step
    }

    /// The steps this run was resumed at (earlier resumes first).
    pub fn resumed_at(&self) -> &[u64] {
        &self.resumed_at
    }

    pub fn set_probe(&mut self, probe: Box<dyn ResourceProbe>) {
        self.probe = Some(probe);
    }

    pub fn set_start_hook(&mut self, hook: StartHook) {
        self.on_start = Some(hook);
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
        self.end_reason().is_some()
    }

    /// Why the episode ended; `None` while it goes on.
    pub fn end_reason(&self) -> Option<EndReason> {
        self.end.or_else(|| {
            self.opts
                .steps
                .is_some_and(|n| self.next_step >= n)
                .then_some(EndReason::Steps)
        })
    }

    /// The module that ended the episode by publishing [`END_TOPIC`].
    pub fn ended_by(&self) -> Option<&str> {
        self.ended_by.as_deref()
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
        let at = StepInfo { step: 0, time: 0.0 };
        let mut hook = self.on_start.as_mut();
        for slot in &mut self.slots {
            if let Some(h) = hook.as_mut() {
                h(Phase::Setup, at, "", &[slot.name.as_str()]);
            }
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
                    error: Box::new(error),
                })?;
            slot.set_up = true;
        }
        if let Some(h) = hook {
            h(Phase::Setup, at, "", &[]);
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
        let result = self.setup().and_then(|()| {
            self.pace();
            if self.pacer.is_some() && crate::interrupt::requested() {
                // Ctrl-C while waiting for the step's slot: the step does not run.
                return Err(EngineError::Interrupted {
                    step: self.next_step,
                });
            }
            self.run_step()
        });
        if result.is_err() {
            let reason = if crate::interrupt::requested() {
                EndReason::Interrupted
            } else {
                EndReason::Error
            };
            self.end.get_or_insert(reason);
        }
        result.map(Some)
    }

    /// Waits for the next step's slot on the wall clock, or (`behind = "drop"`) skips
    /// the steps whose slot has passed, always leaving the episode's last step to run.
    fn pace(&mut self) {
        let Some(pacer) = self.pacer.as_mut() else {
            return;
        };
        let left = self
            .opts
            .steps
            .map_or(u64::MAX, |n| n.saturating_sub(self.next_step + 1));
        self.next_step += pacer.before_step(self.next_step, left, &crate::interrupt::requested);
    }

    /// The stages of the next step in order, each: run → account → deliver; then the
    /// step's record.
    fn run_step(&mut self) -> Result<StepReport, EngineError> {
        let step = self.next_step;
        let t_step = Instant::now();
        let mut state = StepState {
            at: StepInfo {
                step,
                time: step as f64 * self.opts.ts,
            },
            published: Vec::new(),
            module_wall: 0.0,
            failure: None,
            end_by: None,
        };
        for stage in 0..self.opts.stages.len() {
            let stage_start = state.published.len();
            let (t_stage, cpu_stage) = (Instant::now(), process_cpu_seconds());
            let mut ran = self.run_stage(stage, state.at);
            let stage_wall = t_stage.elapsed().as_secs_f64();
            let sample = self.account(&mut ran, stage_wall, cpu_stage, &mut state);
            self.deliver(ran, sample, &mut state);
            if let Some(tap) = &mut self.tap {
                tap(&state.published[stage_start..]);
            }
            if state.failure.is_some() {
                break;
            }
        }
        let wall_s = t_step.elapsed().as_secs_f64();
        self.next_step += 1;
        let record_s = self.record_step(&state, wall_s)?;
        let wall_s = wall_s + record_s;
        self.wall_s += wall_s;
        if let Some(f) = state.failure {
            // A module step cut short by Ctrl-C (KeyboardInterrupt in a plugin, a NATS
            // wait given up) is an interruption, not the module's failure.
            if crate::interrupt::requested() {
                self.end = Some(EndReason::Interrupted);
                return Err(EngineError::Interrupted { step });
            }
            return Err(f);
        }
        if let Some(module) = state.end_by {
            self.end = Some(EndReason::Module);
            self.ended_by = Some(module);
        }
        Ok(StepReport {
            step,
            time: state.at.time,
            messages: state.published,
            wall_s,
            ended: self.is_done(),
        })
    }

    /// Charges the stage's CPU time and samples the process for its modules' timings.
    fn account(
        &mut self,
        ran: &mut [Ran],
        stage_wall: f64,
        cpu_before: f64,
        state: &mut StepState,
    ) -> StageSample {
        let local = ran.iter_mut().filter(|r| r.reported.is_none());
        charge_helper_threads(
            local.map(|r| (&mut r.cpu_s, r.wall_s)),
            process_cpu_seconds() - cpu_before,
        );
        // Modules of one process share its memory: the process's size after the stage
        // is what each module of the stage is charged with (NATS workers report their own).
        let sampled = self.recorder.is_some() && !ran.is_empty();
        let sample = StageSample {
            rss_mib: if sampled { resident_mib() } else { f64::NAN },
            gpu: if sampled {
                self.probe.as_mut().and_then(|p| p.sample())
            } else {
                None
            },
        };
        // The stage's share of module work is its slowest member (they ran side by side).
        state.module_wall += ran
            .iter()
            .map(|r| r.wall_s)
            .fold(0.0, f64::max)
            .min(stage_wall);
        sample
    }

    /// Records each module's timing and routes what it published, in module order.
    fn deliver(&mut self, mut ran: Vec<Ran>, sample: StageSample, state: &mut StepState) {
        ran.sort_by_key(|r| r.slot);
        let at = state.at;
        for r in ran {
            let name = self.slots[r.slot].name.clone();
            let outgoing = match r.result {
                Ok(out) => out,
                Err(error) => {
                    state.failure.get_or_insert(EngineError::Module {
                        module: name.clone(),
                        phase: "step",
                        step: Some(at.step),
                        time: Some(at.time),
                        error: Box::new(error),
                    });
                    Vec::new()
                }
            };
            if let Some(rec) = &mut self.recorder {
                let (rss_mib, gpu_util_pct, gpu_mem_mib) = match r.reported {
                    Some(u) => (u.rss_mib, u.gpu_util_pct, u.gpu_mem_mib),
                    None => (
                        sample.rss_mib,
                        sample.gpu.map(|g| g.0),
                        sample.gpu.map(|g| g.1),
                    ),
                };
                rec.record_timing(&TimingRow {
                    step: at.step,
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
                self.publish(&name, o, state);
            }
        }
    }

    /// Checks one outgoing message, hands it to its subscribers and the recorder.
    fn publish(&mut self, name: &str, o: Outgoing, state: &mut StepState) {
        let at = state.at;
        if let Err(reason) = check_publish(&o.topic) {
            state.failure.get_or_insert(EngineError::Publish {
                module: name.to_string(),
                step: at.step,
                topic: o.topic,
                reason,
            });
            return;
        }
        if o.topic == END_TOPIC && state.end_by.is_none() {
            state.end_by = Some(name.to_string());
        }
        let msg = Arc::new(Message {
            step: at.step,
            time: at.time,
            topic: o.topic,
            source: name.to_string(),
            payload: o.payload,
        });
        for &j in self.subscribers(&msg.topic).iter() {
            self.slots[j].inbox.push(msg.clone());
        }
        if let Some(rec) = &mut self.recorder {
            rec.record_message(&msg);
        }
        state.published.push(msg);
    }

    /// The core's own timing row, then the step's messages to disk (all of them, or
    /// what there is after a failure). Returns the seconds that took.
    fn record_step(&mut self, state: &StepState, wall_s: f64) -> Result<f64, EngineError> {
        let t_record = Instant::now();
        if let Some(rec) = &mut self.recorder {
            rec.record_timing(&TimingRow {
                step: state.at.step,
                time: state.at.time,
                module: CORE.into(),
                wall_s: (wall_s - state.module_wall).max(0.0),
                cpu_s: 0.0,
                rss_mib: resident_mib(),
                msgs_in: 0,
                msgs_out: 0,
                gpu_util_pct: None,
                gpu_mem_mib: None,
            });
            if state.failure.is_some() {
                rec.flush()?;
            } else {
                rec.end_step()?;
            }
        }
        let record_s = t_record.elapsed().as_secs_f64();
        self.record_s += record_s;
        Ok(record_s)
    }

    fn run_stage(&mut self, stage: usize, at: StepInfo) -> Vec<Ran> {
        let (mut remote, mut parallel, mut serial) = (Vec::new(), Vec::new(), Vec::new());
        for (i, slot) in self.slots.iter_mut().enumerate() {
            if slot.stage != stage || !slot.runs_at(at.step) {
                continue;
            }
            let inbox = std::mem::take(&mut slot.inbox);
            let name = slot.name.as_str();
            match &mut slot.module {
                AnyModule::Remote(module) => remote.push(RemoteStep {
                    slot: i,
                    name,
                    module,
                    inbox,
                }),
                AnyModule::Local(module) => {
                    let concurrent = module.concurrent();
                    let s = LocalStep {
                        slot: i,
                        name,
                        module,
                        inbox,
                    };
                    if concurrent {
                        &mut parallel
                    } else {
                        &mut serial
                    }
                    .push(s);
                }
            }
        }
        let stage_name = self.opts.stages[stage].as_str();
        let mut hook = self.on_start.as_mut();
        let mut running: Vec<&str> = remote.iter().map(|s| s.name).collect();
        // Remote modules first: they work while this process runs the local ones.
        if let Some(h) = hook.as_mut().filter(|_| !running.is_empty()) {
            h(Phase::Step, at, stage_name, &running);
        }
        let started: Vec<_> = remote.iter_mut().map(|s| start_remote(s, at)).collect();
        let mut ran = if parallel.len() <= 1 {
            // Not worth a thread hop.
            serial.append(&mut parallel);
            let mut ran = Vec::with_capacity(serial.len());
            for s in serial.iter_mut() {
                if let Some(h) = hook.as_mut() {
                    running.push(s.name);
                    h(Phase::Step, at, stage_name, &running);
                    running.pop();
                }
                ran.push(run_local(s, at));
            }
            ran
        } else {
            if let Some(h) = hook.as_mut() {
                running.extend(parallel.iter().chain(serial.iter()).map(|s| s.name));
                h(Phase::Step, at, stage_name, &running);
            }
            let (mut a, b) = rayon::join(
                || {
                    parallel
                        .par_iter_mut()
                        .map(|s| run_local(s, at))
                        .collect::<Vec<_>>()
                },
                || {
                    serial
                        .iter_mut()
                        .map(|s| run_local(s, at))
                        .collect::<Vec<_>>()
                },
            );
            a.extend(b);
            a
        };
        ran.extend(
            remote
                .into_iter()
                .zip(started)
                .map(|(s, r)| finish_remote(s, r)),
        );
        if let Some(h) = hook {
            h(Phase::Step, at, stage_name, &[]);
        }
        ran
    }

    /// Runs steps until the episode ends. `after_step` sees each step; returning
    /// `false` from it interrupts the run.
    pub fn run(
        &mut self,
        mut after_step: impl FnMut(&Engine, &StepReport) -> bool,
    ) -> Result<(), EngineError> {
        while let Some(report) = self.step()? {
            let go_on = after_step(self, &report) && !crate::interrupt::requested();
            if !go_on && !report.ended {
                return Err(self.interrupt_after(report.step));
            }
        }
        Ok(())
    }

    /// Ends the episode as interrupted after `step` (the host's stop between steps).
    pub fn interrupt_after(&mut self, step: u64) -> EngineError {
        self.end = Some(EndReason::Interrupted);
        EngineError::Interrupted { step }
    }

    /// Time spent writing a checkpoint (part of the run's wall time).
    pub fn add_checkpoint_s(&mut self, seconds: f64) {
        self.checkpoint_s += seconds;
        self.wall_s += seconds;
    }

    /// Seconds spent writing checkpoints.
    pub fn checkpoint_s(&self) -> f64 {
        self.checkpoint_s
    }

    /// A checkpoint of the run between two steps (see [`crate::checkpoint`]): flushes
    /// the recording so that every step before it is on disk, then asks every module
    /// for its state. A module whose `state` fails fails the run, named; the first that
    /// cannot be resumed ends the checkpoint there, naming it (and `checkpoint_step`
    /// stays as it was: there is nothing to resume from).
    pub fn checkpoint(&mut self) -> Result<Checkpoint, EngineError> {
        if let Some(rec) = self.recorder.as_mut() {
            rec.flush()?;
        }
        let mut cp = Checkpoint::new(
            self.next_step,
            self.wall_s,
            self.record_s,
            &self.opts.config_dir,
        );
        let at = StepInfo {
            step: self.next_step,
            time: self.next_step as f64 * self.opts.ts,
        };
        for slot in &mut self.slots {
            let state = if slot.set_up {
                slot.module.state().map_err(|error| EngineError::Module {
                    module: slot.name.clone(),
                    phase: "state",
                    step: Some(at.step),
                    time: Some(at.time),
                    error: Box::new(error),
                })?
            } else {
                ModuleState::Stateless
            };
            if let ModuleState::Unsupported(why) = state {
                // The run cannot be resumed: the checkpoint only says which module and
                // why (no other state is asked for, no inbox written: it costs nothing).
                cp.modules = vec![ModuleCheckpoint {
                    name: slot.name.clone(),
                    state: SavedState::Unsupported { why },
                    inbox: Vec::new(),
                }];
                return Ok(cp);
            }
            cp.modules.push(ModuleCheckpoint {
                name: slot.name.clone(),
                state: state.into(),
                inbox: slot.inbox.iter().map(|m| SavedMessage::of(m)).collect(),
            });
        }
        self.checkpoint_step = Some(self.next_step);
        Ok(cp)
    }

    /// Goes on from `cp` (a fresh engine on the same configuration): sets every module
    /// up, restores its state and inbox, and makes `cp.next_step` the next step.
    /// `resumed_before`: the steps the run was resumed at earlier.
    pub fn resume_from(
        &mut self,
        cp: &Checkpoint,
        resumed_before: &[u64],
    ) -> Result<(), EngineError> {
        let module_error = |module: &str, message: String| EngineError::Module {
            module: module.to_string(),
            phase: "restore",
            step: Some(cp.next_step),
            time: Some(cp.next_step as f64 * self.opts.ts),
            error: Box::new(ModuleError::new(message)),
        };
        // Refuse before anything is set up: every module must be resumable.
        for slot in &self.slots {
            let Some(m) = cp.modules.iter().find(|m| m.name == slot.name) else {
                return Err(module_error(
                    &slot.name,
                    "the checkpoint has no such module (was the configuration changed?)".into(),
                ));
            };
            if let SavedState::Unsupported { why } = &m.state {
                return Err(module_error(&slot.name, format!("cannot resume: {why}")));
            }
        }
        self.setup()?;
        let ts = self.opts.ts;
        for slot in &mut self.slots {
            let m = cp
                .modules
                .iter()
                .find(|m| m.name == slot.name)
                .expect("checked above");
            let fail = |message: String| EngineError::Module {
                module: slot.name.clone(),
                phase: "restore",
                step: Some(cp.next_step),
                time: Some(cp.next_step as f64 * ts),
                error: Box::new(ModuleError::new(message)),
            };
            if let SavedState::Saved { hex } = &m.state {
                let bytes = crate::checkpoint::unhex(hex).map_err(&fail)?;
                slot.module
                    .restore(&bytes)
                    .map_err(|error| EngineError::Module {
                        module: slot.name.clone(),
                        phase: "restore",
                        step: Some(cp.next_step),
                        time: Some(cp.next_step as f64 * ts),
                        error: Box::new(error),
                    })?;
            }
            slot.inbox = m
                .inbox
                .iter()
                .map(|s| s.to_message().map(Arc::new))
                .collect::<Result<_, _>>()
                .map_err(&fail)?;
            slot.module
                .resume_at(cp.next_step)
                .map_err(|error| EngineError::Module {
                    module: slot.name.clone(),
                    phase: "restore",
                    step: Some(cp.next_step),
                    time: Some(cp.next_step as f64 * ts),
                    error: Box::new(error),
                })?;
        }
        self.next_step = cp.next_step;
        self.wall_s = cp.wall_s;
        self.record_s = cp.record_s;
        self.checkpoint_step = Some(cp.next_step);
        self.resumed_at = resumed_before.to_vec();
        self.resumed_at.push(cp.next_step);
        Ok(())
    }

    /// Tears the modules down and finishes the recording. Call once, also after a
    /// failed step: whatever was recorded is then compacted and readable.
    pub fn close(&mut self) -> Result<(), EngineError> {
        if self.end_reason().is_none() {
            self.end = Some(EndReason::Closed);
        }
        let mut first = None;
        let at = StepInfo {
            step: self.next_step,
            time: self.next_step as f64 * self.opts.ts,
        };
        let mut hook = self.on_start.as_mut();
        for slot in self.slots.iter_mut().filter(|s| s.set_up) {
            slot.set_up = false;
            if let Some(h) = hook.as_mut() {
                h(Phase::Teardown, at, "", &[slot.name.as_str()]);
            }
            if let Err(error) = slot.module.teardown() {
                first.get_or_insert(EngineError::Module {
                    module: slot.name.clone(),
                    phase: "teardown",
                    step: None,
                    time: None,
                    error: Box::new(error),
                });
            }
        }
        if let Some(h) = hook {
            h(Phase::Teardown, at, "", &[]);
        }
        if let Some(rec) = self.recorder.take() {
            rec.finish()?;
        }
        first.map_or(Ok(()), Err)
    }
}

fn check_publish(topic: &str) -> Result<(), String> {
    validate_topic(topic).map_err(|e| e.to_string())?;
    if topic.starts_with("caviar.") && topic != END_TOPIC && topic != STATUS_TOPIC {
        return Err(format!(
            "topics under 'caviar.' are reserved for the core (modules may publish '{END_TOPIC}' \
             and '{STATUS_TOPIC}')"
        ));
    }
    Ok(())
}
