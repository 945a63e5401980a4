//! Checkpoints of a run between two steps (see [`crate::checkpoint`]) and resuming a
//! fresh engine from one.

use std::sync::Arc;

use super::error::EngineError;
use super::types::Engine;
use crate::checkpoint::{Checkpoint, ModuleCheckpoint, SavedMessage, SavedState};
use crate::module::{ModuleError, ModuleState, StepInfo};

impl Engine {
    /// The step the last checkpoint taken resumes at.
    pub fn checkpoint_step(&self) -> Option<u64> {
        self.checkpoint_step
    }

    /// The steps this run was resumed at (earlier resumes first).
    pub fn resumed_at(&self) -> &[u64] {
        &self.resumed_at
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
        // Whatever goes wrong is the module's, in its restore phase at the resumed step.
        let (step, time) = (cp.next_step, cp.next_step as f64 * self.opts.ts);
        let failed = move |module: &str, error: ModuleError| EngineError::Module {
            module: module.to_string(),
            phase: "restore",
            step: Some(step),
            time: Some(time),
            error: Box::new(error),
        };
        let failed_with = |module: &str, message: String| failed(module, ModuleError::new(message));
        // Refuse before anything is set up: every module must be resumable.
        for slot in &self.slots {
            let Some(m) = cp.modules.iter().find(|m| m.name == slot.name) else {
                return Err(failed_with(
                    &slot.name,
                    "the checkpoint has no such module (was the configuration changed?)".into(),
                ));
            };
            if let SavedState::Unsupported { why } = &m.state {
                return Err(failed_with(&slot.name, format!("cannot resume: {why}")));
            }
        }
        self.setup()?;
        for slot in &mut self.slots {
            let m = cp
                .modules
                .iter()
                .find(|m| m.name == slot.name)
                .expect("checked above");
            if let SavedState::Saved { hex } = &m.state {
                let bytes =
                    crate::checkpoint::unhex(hex).map_err(|e| failed_with(&slot.name, e))?;
                slot.module
                    .restore(&bytes)
                    .map_err(|e| failed(&slot.name, e))?;
            }
            slot.inbox = m
                .inbox
                .iter()
                .map(|s| s.to_message().map(Arc::new))
                .collect::<Result<_, _>>()
                .map_err(|e| failed_with(&slot.name, e))?;
            slot.module
                .resume_at(cp.next_step)
                .map_err(|e| failed(&slot.name, e))?;
        }
        self.next_step = cp.next_step;
        self.wall_s = cp.wall_s;
        self.record_s = cp.record_s;
        self.checkpoint_step = Some(cp.next_step);
        self.resumed_at = resumed_before.to_vec();
        self.resumed_at.push(cp.next_step);
        Ok(())
    }
}
