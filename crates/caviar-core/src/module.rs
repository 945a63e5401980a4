//! The contract between the core and a module: Gymnasium-small.
//!
//! The core calls `setup` once, then `step` at each of the module's steps with the
//! messages it received since its previous step, then `teardown` once. Where a
//! module runs (this process, a Python plugin, another machine) is not its concern:
//! in-process modules implement [`Module`], modules that run elsewhere (a transport's)
//! implement [`RemoteModule`], whose step is started and finished apart, and the
//! engine holds either as an [`AnyModule`].

use std::path::PathBuf;

use crate::message::{Outgoing, SharedMessage};

/// A module's failure. `trace` carries a traceback or backtrace when there is one.
#[derive(Debug, Clone, Default)]
pub struct ModuleError {
    pub message: String,
    pub trace: Option<String>,
    /// The failure is bad input that the module could only find out when it loaded it
    /// (a file its parameters name that its tool rejects), not a crash: the run ends
    /// with exit code 2 and the message, without a traceback.
    pub bad_input: bool,
}

impl ModuleError {
    pub fn new(message: impl Into<String>) -> Self {
        ModuleError {
            message: message.into(),
            ..Default::default()
        }
    }

    /// A failure caused by bad input (see [`ModuleError::bad_input`]).
    pub fn bad_input(message: impl Into<String>) -> Self {
        ModuleError {
            message: message.into(),
            bad_input: true,
            ..Default::default()
        }
    }
}

impl std::fmt::Display for ModuleError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl<E: std::error::Error> From<E> for ModuleError {
    fn from(e: E) -> Self {
        ModuleError::new(e.to_string())
    }
}

/// What a module learns once, before its first step.
#[derive(Debug, Clone)]
pub struct SetupContext {
    pub name: String,
    /// The module's own seed, derived from the episode seed and the module name:
    /// adding or renaming another module does not change it.
    pub seed: u64,
    /// Sampling interval Ts in seconds.
    pub ts: f64,
    /// Steps in the episode, if known in advance.
    pub steps: Option<u64>,
    pub every: u64,
    pub offset: u64,
    pub run_dir: PathBuf,
    /// Directory of the configuration file, for the plugin's relative paths.
    pub config_dir: PathBuf,
    /// The plugin's `[modules.NAME.params]` table.
    pub params: serde_json::Value,
}

/// A module's state in a checkpoint (`output.checkpoint_every`, `caviar-core run --resume`).
#[derive(Debug, Clone, PartialEq)]
pub enum ModuleState {
    /// The module keeps nothing across steps that changes what it publishes: a resumed
    /// run sets it up again and goes on.
    Stateless,
    /// Its state, as bytes only the module reads back (`restore`).
    Saved(Vec<u8>),
    /// It has no state hooks and does not declare itself stateless: a run with it
    /// cannot be resumed (the reason says so).
    Unsupported(String),
}

/// Where a step happens.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepInfo {
    pub step: u64,
    /// Virtual time t = step * Ts.
    pub time: f64,
}

/// What a step cost where it ran, as a module elsewhere reports it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Usage {
    pub wall_s: f64,
    pub cpu_s: f64,
    /// Resident memory of the process that ran the step, MiB.
    pub rss_mib: f64,
    /// GPU utilisation (%) and the process's GPU memory (MiB), where it has a GPU.
    pub gpu_util_pct: Option<f64>,
    pub gpu_mem_mib: Option<f64>,
}

/// Samples GPU use of this process (the Python host provides one built on
/// nvidia-ml-py); `None` from `sample` where there is nothing to measure.
pub trait ResourceProbe: Send {
    /// (utilisation %, this process's GPU memory MiB)
    fn sample(&mut self) -> Option<(f64, f64)>;
}

/// The methods [`Module`] and [`RemoteModule`] share, with their defaults, written once
/// and expanded into both traits: each keeps all of them as its own, so an
/// implementation of either overrides them in its own `impl`. A module's state is
/// unsupported by default, for the reasons the trait gives (`no_state`: why it has no
/// state to save, `no_restore`: why none can be put back).
macro_rules! shared_module_methods {
    (no_state: $no_state:literal, no_restore: $no_restore:literal $(,)?) => {
        /// Subscription patterns used when the config gives none.
        fn default_subscriptions(&self) -> Vec<String> {
            Vec::new()
        }

        /// Topics (or patterns) the module may publish; `None`: not declared (it may
        /// publish anything). Only `caviar-core validate` reads it, to warn about
        /// subscriptions nobody feeds and publications nobody reads.
        fn publishes(&self) -> Option<Vec<String>> {
            None
        }

        /// Default subscriptions the module works without (optional inputs): `validate`
        /// does not warn when no module publishes them.
        fn optional_subscriptions(&self) -> Vec<String> {
            Vec::new()
        }

        /// Inputs its parameters name, as (pattern, key of the module's table that names
        /// it): a configuration in which no module publishes one is refused before
        /// anything runs.
        fn required_inputs(&self) -> Vec<(String, String)> {
            Vec::new()
        }

        fn setup(&mut self, _ctx: &SetupContext) -> Result<(), ModuleError> {
            Ok(())
        }

        fn teardown(&mut self) -> Result<(), ModuleError> {
            Ok(())
        }

        /// The module's state between two steps, for a checkpoint. Default: unsupported.
        fn state(&mut self) -> Result<ModuleState, ModuleError> {
            Ok(ModuleState::Unsupported($no_state.into()))
        }

        /// Puts back a state from `state`, after `setup`, before the next step.
        fn restore(&mut self, _state: &[u8]) -> Result<(), ModuleError> {
            Err(ModuleError::new($no_restore))
        }

        /// A resumed run goes on at `next_step` (after `restore`, for every module).
        fn resume_at(&mut self, _next_step: u64) -> Result<(), ModuleError> {
            Ok(())
        }
    };
}

/// A module that runs in this process: the engine calls `step` and waits for it.
pub trait Module: Send {
    shared_module_methods! {
        no_state: "it has no state()/restore() hooks and does not declare itself stateless",
        no_restore: "it has no restore() hook",
    }

    /// One step: read `inbox`, push what to publish onto `out`.
    fn step(
        &mut self,
        at: StepInfo,
        inbox: &[SharedMessage],
        out: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError>;

    /// Whether `step` may run on a worker thread beside the other modules of its
    /// stage. Python plugins say no: they share one interpreter lock anyway and
    /// running them on the calling thread keeps tracebacks and signals simple.
    fn concurrent(&self) -> bool {
        true
    }
}

/// A module that runs elsewhere (a NATS worker). A step is split in two: the engine
/// calls `start_step` on every remote module of a stage before it waits for any of
/// them with `finish_step`, so remote modules run side by side without a thread each.
///
/// The split belongs to remote modules only: a local module has no `start_step`.
///
/// ```compile_fail
/// use caviar_core::{Module, StepInfo};
/// fn start(m: &mut dyn Module) {
///     let _ = m.start_step(StepInfo { step: 0, time: 0.0 }, &[]);
/// }
/// ```
pub trait RemoteModule: Send {
    shared_module_methods! {
        no_state: "its transport does not carry module states",
        no_restore: "its transport does not carry module states",
    }

    /// Hands the step off and returns without waiting.
    fn start_step(&mut self, at: StepInfo, inbox: &[SharedMessage]) -> Result<(), ModuleError>;

    /// Waits for the step started by `start_step`; returns what it cost where it ran.
    fn finish_step(&mut self, out: &mut Vec<Outgoing>) -> Result<Usage, ModuleError>;
}

/// A module as the engine holds it: run here, or elsewhere.
pub enum AnyModule {
    Local(Box<dyn Module>),
    Remote(Box<dyn RemoteModule>),
}

impl AnyModule {
    pub fn local(module: impl Module + 'static) -> Self {
        AnyModule::Local(Box::new(module))
    }

    pub fn remote(module: impl RemoteModule + 'static) -> Self {
        AnyModule::Remote(Box::new(module))
    }

    pub fn default_subscriptions(&self) -> Vec<String> {
        match self {
            AnyModule::Local(m) => m.default_subscriptions(),
            AnyModule::Remote(m) => m.default_subscriptions(),
        }
    }

    pub fn publishes(&self) -> Option<Vec<String>> {
        match self {
            AnyModule::Local(m) => m.publishes(),
            AnyModule::Remote(m) => m.publishes(),
        }
    }

    pub fn optional_subscriptions(&self) -> Vec<String> {
        match self {
            AnyModule::Local(m) => m.optional_subscriptions(),
            AnyModule::Remote(m) => m.optional_subscriptions(),
        }
    }

    pub fn required_inputs(&self) -> Vec<(String, String)> {
        match self {
            AnyModule::Local(m) => m.required_inputs(),
            AnyModule::Remote(m) => m.required_inputs(),
        }
    }

    pub fn setup(&mut self, ctx: &SetupContext) -> Result<(), ModuleError> {
        match self {
            AnyModule::Local(m) => m.setup(ctx),
            AnyModule::Remote(m) => m.setup(ctx),
        }
    }

    pub fn teardown(&mut self) -> Result<(), ModuleError> {
        match self {
            AnyModule::Local(m) => m.teardown(),
            AnyModule::Remote(m) => m.teardown(),
        }
    }

    pub fn state(&mut self) -> Result<ModuleState, ModuleError> {
        match self {
            AnyModule::Local(m) => m.state(),
            AnyModule::Remote(m) => m.state(),
        }
    }

    pub fn restore(&mut self, state: &[u8]) -> Result<(), ModuleError> {
        match self {
            AnyModule::Local(m) => m.restore(state),
            AnyModule::Remote(m) => m.restore(state),
        }
    }

    pub fn resume_at(&mut self, next_step: u64) -> Result<(), ModuleError> {
        match self {
            AnyModule::Local(m) => m.resume_at(next_step),
            AnyModule::Remote(m) => m.resume_at(next_step),
        }
    }
}

impl From<Box<dyn Module>> for AnyModule {
    fn from(m: Box<dyn Module>) -> Self {
        AnyModule::Local(m)
    }
}

impl From<Box<dyn RemoteModule>> for AnyModule {
    fn from(m: Box<dyn RemoteModule>) -> Self {
        AnyModule::Remote(m)
    }
}

/// Seed of one module: SplitMix64 of the episode seed mixed with an FNV-1a hash of
/// the module name. Stable across platforms and releases.
pub fn module_seed(episode_seed: u64, name: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in name.bytes() {
        h ^= b as u64;
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    let mut z = episode_seed ^ h;
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    (z ^ (z >> 31)) >> 1 // keep it within i64 for Python and Parquet consumers
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn module_seeds_differ_by_name_and_episode_seed_and_are_stable() {
        let a = module_seed(1, "uav");
        assert_eq!(a, module_seed(1, "uav"));
        assert_ne!(a, module_seed(2, "uav"));
        assert_ne!(a, module_seed(1, "uav2"));
        assert!(a <= i64::MAX as u64);
    }
}
