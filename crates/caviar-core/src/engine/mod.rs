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
//!
//! Here: the engine's types (`types`) and errors (`error`); running a step's stages
//! (`stepping`), charging their time (`accounting`) and delivering what they published
//! (`delivery`); checkpoints and resuming from one (`resume`).

mod accounting;
mod delivery;
mod error;
mod resume;
mod stepping;
mod types;

use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

use crate::module::{module_seed, ResourceProbe, SetupContext, StepInfo};
use crate::pacing::{Pacer, PacingReport};
use crate::recorder::Recorder;
use crate::topic::Pattern;
use types::Slot;

pub use error::EngineError;
pub use types::{
    EndReason, Engine, EngineOptions, ModuleSpec, Phase, StartHook, StepReport, Tap, END_TOPIC,
    STATUS_TOPIC,
};

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
