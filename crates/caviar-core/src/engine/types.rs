//! The engine's types: its options and modules, what a step reports, why an episode
//! ended, the hooks a host installs, and the [`Engine`] itself (its methods are in the
//! modules beside this one).

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::message::SharedMessage;
use crate::module::{AnyModule, ResourceProbe, StepInfo};
use crate::pacing::Pacer;
use crate::recorder::Recorder;
use crate::topic::Pattern;

/// Publishing on this topic ends the episode after the current step.
pub const END_TOPIC: &str = "caviar.episode.end";

/// A module's one-line status for people (a JSON string, e.g. what share of its work a
/// cache served): the command line shows each module's latest beside its progress. It is
/// recorded like any message and means nothing to the engine.
pub const STATUS_TOPIC: &str = "caviar.status";

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

impl ModuleSpec {
    /// `module`, named `name`, in `stage`: every step from step 0, on its own default
    /// subscriptions, without parameters (null). Change a field for anything else.
    pub fn new(
        name: impl Into<String>,
        stage: impl Into<String>,
        module: impl Into<AnyModule>,
    ) -> Self {
        ModuleSpec {
            name: name.into(),
            stage: stage.into(),
            every: 1,
            offset: 0,
            subscribe: None,
            params: serde_json::Value::Null,
            module: module.into(),
        }
    }
}

pub(super) struct Slot {
    pub(super) name: String,
    pub(super) stage: usize,
    pub(super) every: u64,
    pub(super) offset: u64,
    pub(super) subs: Vec<Pattern>,
    pub(super) seed: u64,
    pub(super) params: serde_json::Value,
    pub(super) module: AnyModule,
    pub(super) inbox: Vec<SharedMessage>,
    pub(super) set_up: bool,
}

impl Slot {
    pub(super) fn runs_at(&self, step: u64) -> bool {
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
    pub(super) opts: EngineOptions,
    pub(super) slots: Vec<Slot>,
    /// Subscribers of each topic seen so far (topics repeat every step).
    pub(super) routes: HashMap<String, Arc<[usize]>>,
    pub(super) recorder: Option<Recorder>,
    pub(super) next_step: u64,
    /// Set when the episode ended before its planned steps ran out (or had none).
    pub(super) end: Option<EndReason>,
    /// The module that published [`END_TOPIC`], when that ended the episode.
    pub(super) ended_by: Option<String>,
    pub(super) started: Option<Instant>,
    pub(super) wall_s: f64,
    pub(super) record_s: f64,
    pub(super) tap: Option<Tap>,
    pub(super) probe: Option<Box<dyn ResourceProbe>>,
    pub(super) on_start: Option<StartHook>,
    pub(super) pacer: Option<Pacer>,
    /// The step the last checkpoint resumes at, and the steps this run was resumed at.
    pub(super) checkpoint_step: Option<u64>,
    pub(super) resumed_at: Vec<u64>,
    pub(super) checkpoint_s: f64,
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
