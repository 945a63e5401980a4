//! What a step costs: each stage's CPU time charged to its modules, the process
//! sampled for their memory and GPU use, and the core's own row in the timings.

use std::time::Instant;

use super::error::EngineError;
use super::stepping::{Ran, StepState};
use super::types::Engine;
use crate::metrics::{charge_helper_threads, process_cpu_seconds, resident_mib};
use crate::recorder::{TimingRow, CORE};

/// What the process looked like after a stage: charged to each in-process module of it.
#[derive(Clone, Copy)]
pub(super) struct StageSample {
    pub(super) rss_mib: f64,
    pub(super) gpu: Option<(f64, f64)>,
}

impl Engine {
    /// Charges the stage's CPU time and samples the process for its modules' timings.
    pub(super) fn account(
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

    /// The core's own timing row, then the step's messages to disk (all of them, or
    /// what there is after a failure). Returns the seconds that took.
    pub(super) fn record_step(
        &mut self,
        state: &StepState,
        wall_s: f64,
    ) -> Result<f64, EngineError> {
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
}
