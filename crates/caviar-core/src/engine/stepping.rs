//! Running a step: its stages in order, each run (remote modules started first, the
//! in-process ones on this thread or the thread pool), then accounted and delivered.

use std::time::Instant;

use rayon::prelude::*;

use super::error::EngineError;
use super::types::{EndReason, Engine, Phase, StepReport};
use crate::message::{Outgoing, SharedMessage};
use crate::metrics::{process_cpu_seconds, thread_cpu_seconds};
use crate::module::{AnyModule, Module, ModuleError, RemoteModule, StepInfo, Usage};

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
pub(super) struct Ran {
    pub(super) slot: usize,
    pub(super) result: Result<Vec<Outgoing>, ModuleError>,
    pub(super) wall_s: f64,
    pub(super) cpu_s: f64,
    /// What the module's own process reported (remote modules): memory and GPU.
    pub(super) reported: Option<Usage>,
    pub(super) msgs_in: u32,
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

/// A step in progress: what its stages published and how it is going.
pub(super) struct StepState {
    pub(super) at: StepInfo,
    pub(super) published: Vec<SharedMessage>,
    /// Module work of the step: each stage's slowest member.
    pub(super) module_wall: f64,
    pub(super) failure: Option<EngineError>,
    /// The first module that published [`END_TOPIC`].
    pub(super) end_by: Option<String>,
}

impl Engine {
    /// The stages of the next step in order, each: run → account → deliver; then the
    /// step's record.
    pub(super) fn run_step(&mut self) -> Result<StepReport, EngineError> {
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
        if state.failure.is_none() {
            // (`steps_done` counts finished steps: a step a module failed in is not one,
            // whatever the fault, as when the process died in it. What its earlier stages
            // published is recorded all the same.)
            self.next_step += 1;
        }
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
}
