//! CAVIAR co-simulation core.
//!
//! The core owns virtual time, stages and barriers ([`engine`]), routes messages on
//! NATS-style topics ([`topic`]), records every message ([`recorder`]) and reads the
//! experiment from one TOML file ([`config`]). It knows nothing of radio, UAVs or AI:
//! that is the plugins' work, behind the small [`module::Module`] contract (and
//! [`module::RemoteModule`] for modules that run elsewhere).
//!
//! # Dependency order
//!
//! Each module uses only modules listed before it (none imports a module that
//! imports it back: `tests/layering.rs` checks that from the sources; the order is
//! kept by hand); transports are
//! leaves behind [`transport::interface`], and only the registry in [`transport`]
//! names one:
//!
//! 1. [`topic`], [`message`], [`metrics`], [`interrupt`] (the Ctrl-C flag), [`pacing`]
//!    (wall-clock pacing of a live twin): leaves
//! 2. [`module`] (message)
//! 3. [`recorder`] (message, topic): the run directory's tables, written and read
//! 4. [`config`] (topic): the experiment file; `[transport]` kept as written
//! 5. [`replay`] (config, message, module, recorder, topic); [`checkpoint`] (message,
//!    module): checkpoint.json, module states and inboxes
//! 6. [`engine`] (checkpoint, message, metrics, module, recorder, topic)
//! 7. [`assembly`] (config, engine, module, replay, topic): the core's built-in
//!    plugins, `build_modules`, `PrepareError`, wiring warnings
//! 8. [`status`] (config, engine, module): run.json, progress.json and the
//!    in-process watchdog of setup, steps and teardown ([`status::Monitor`])
//! 9. [`inspect`] (checkpoint, engine, message, recorder, status): `caviar-core inspect`'s report
//!    and the per-module totals
//! 10. [`transport::interface`] (assembly, config, engine); the transports
//!     ([`transport::nats`]: assembly, config, engine, message, metrics, module,
//!     topic, interface) and the registry [`transport`] (config, interface, nats)
//! 11. [`run`] (assembly, checkpoint, config, engine, module, recorder, status, topic,
//!     transport): [`run::RunSession`], one run from start to run.json
//! 12. [`cli`] (assembly, config, engine, inspect, run, status)
//! 13. `py_messages`, `python` (feature `python`: the `caviar._core` extension;
//!     everything above, the transports through their registry)

pub mod assembly;
pub mod checkpoint;
pub mod cli;
pub mod concurrency;
pub mod config;
pub mod engine;
pub mod inspect;
pub mod interrupt;
pub mod message;
pub mod metrics;
pub mod module;
pub mod pacing;
pub mod recorder;
pub mod replay;
pub mod run;
pub mod status;
pub mod topic;
pub mod transport;

#[cfg(feature = "python")]
mod py_messages;
#[cfg(feature = "python")]
mod python;

pub use config::{ConfigError, LoadedConfig};
pub use engine::{
    EndReason, Engine, EngineError, EngineOptions, ModuleSpec, Phase, StepReport, END_TOPIC,
};
pub use message::{Message, Outgoing, Payload, SharedMessage};
pub use module::{
    AnyModule, Module, ModuleError, ModuleState, RemoteModule, ResourceProbe, SetupContext,
    StepInfo, Usage,
};
pub use status::{RunState, RunStatus};
