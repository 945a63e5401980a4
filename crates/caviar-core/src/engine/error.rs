//! The engine's errors: a module's failure (named, with where and its trace), a bad
//! publication, the recorder's, an interruption.

use crate::module::ModuleError;
use crate::recorder::RecordError;

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
