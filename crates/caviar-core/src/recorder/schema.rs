//! The recorded tables: their names, their Arrow schemas, and [`TimingRow`], one row
//! of `timings`.

use std::sync::Arc;

use arrow_schema::{DataType, Field, Schema, SchemaRef};

pub const MESSAGES: &str = "messages";
pub const TIMINGS: &str = "timings";

pub fn messages_schema() -> SchemaRef {
    Arc::new(Schema::new(vec![
        Field::new("step", DataType::UInt64, false),
        Field::new("time", DataType::Float64, false),
        Field::new("seq", DataType::UInt32, false),
        Field::new("source", DataType::Utf8, false),
        Field::new("topic", DataType::Utf8, false),
        Field::new("kind", DataType::Utf8, false),
        // JSON text, or the artifact's path relative to the run directory.
        Field::new("text", DataType::Utf8, true),
        // For binary payloads: JSON description (dtype, shape, content type).
        Field::new("meta", DataType::Utf8, true),
        Field::new("data", DataType::Binary, true),
    ]))
}

pub fn timings_schema() -> SchemaRef {
    Arc::new(Schema::new(vec![
        Field::new("step", DataType::UInt64, false),
        Field::new("time", DataType::Float64, false),
        Field::new("module", DataType::Utf8, false),
        Field::new("wall_s", DataType::Float64, false),
        Field::new("cpu_s", DataType::Float64, false),
        Field::new("rss_mib", DataType::Float64, false),
        Field::new("msgs_in", DataType::UInt32, false),
        Field::new("msgs_out", DataType::UInt32, false),
        // Null where no NVIDIA GPU (or no nvidia-ml-py) was seen.
        Field::new("gpu_util_pct", DataType::Float64, true),
        Field::new("gpu_mem_mib", DataType::Float64, true),
    ]))
}

/// The recorded tables, by name, with their schemas, in the order they are written.
pub(super) fn tables() -> [(&'static str, SchemaRef); 2] {
    [(MESSAGES, messages_schema()), (TIMINGS, timings_schema())]
}

/// One module's cost in one step. The core's own share of a step is recorded under
/// the module name [`CORE`].
#[derive(Debug, Clone, PartialEq)]
pub struct TimingRow {
    pub step: u64,
    pub time: f64,
    pub module: String,
    pub wall_s: f64,
    pub cpu_s: f64,
    /// Resident memory of the module's process after its stage, MiB.
    pub rss_mib: f64,
    pub msgs_in: u32,
    pub msgs_out: u32,
    /// GPU utilisation (%, of the devices the process uses) and the process's GPU
    /// memory (MiB) after the module's stage, where an NVIDIA GPU is present.
    pub gpu_util_pct: Option<f64>,
    pub gpu_mem_mib: Option<f64>,
}

/// Module name under which the core's own per-step overhead is recorded.
pub const CORE: &str = "caviar.core";
