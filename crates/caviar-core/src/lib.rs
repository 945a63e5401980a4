//! CAVIAR co-simulation core.
//!
//! The core owns virtual time, stages and barriers ([`engine`]), routes messages on
//! NATS-style topics ([`topic`]), records every message ([`recorder`]) and reads the
//! experiment from one TOML file ([`config`]). It knows nothing of radio, UAVs or AI:
//! that is the plugins' work, behind the small [`module::Module`] contract.

pub mod cli;
pub mod config;
pub mod engine;
pub mod message;
pub mod module;
pub mod nats;
pub mod recorder;
pub mod replay;
pub mod run;
pub mod topic;

#[cfg(feature = "python")]
mod python;

pub use config::{ConfigError, LoadedConfig};
pub use engine::{Engine, EngineError, EngineOptions, ModuleSpec, StepReport, END_TOPIC};
pub use message::{Message, Outgoing, Payload, SharedMessage};
pub use module::{Module, ModuleError, ResourceProbe, SetupContext, StepInfo, Usage};
