//! Reading a run's recorded tables back, finished or not, from Parquet files this
//! recorder or other tools wrote; a corrupt file is an error naming it, not a panic.

use std::fs::File;
use std::path::Path;

use arrow_array::{
    Array, ArrayRef, BinaryArray, Float64Array, RecordBatch, StringArray, UInt32Array, UInt64Array,
};
use arrow_schema::DataType;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;

use super::error::{io_err, pq_err, RecordError};
use super::layout::table_files;
use super::schema::{TimingRow, MESSAGES, TIMINGS};
use crate::message::{Message, Payload, PayloadKind};

fn read_file(path: &Path, out: &mut Vec<RecordBatch>) -> Result<(), RecordError> {
    // The Parquet reader panics on some corrupt files (an index out of bounds deep in a
    // page decoder, found by tests/fuzz.rs): that is a corrupt file too, said as such.
    let read = quiet_unwind(|| -> Result<Vec<RecordBatch>, RecordError> {
        let file = File::open(path).map_err(io_err(path))?;
        let reader = ParquetRecordBatchReaderBuilder::try_new(file)
            .map_err(pq_err(path))?
            .build()
            .map_err(pq_err(path))?;
        reader
            .map(|batch| {
                batch.map_err(|e| RecordError::Format {
                    path: path.to_path_buf(),
                    message: e.to_string(),
                })
            })
            .collect()
    });
    match read {
        Ok(batches) => out.extend(batches?),
        Err(why) => {
            return Err(RecordError::Format {
                path: path.to_path_buf(),
                message: format!("corrupt Parquet file (the reader gave up: {why})"),
            })
        }
    }
    Ok(())
}

thread_local! {
    static QUIET_PANICS: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `f`, turning a panic into `Err(its message)` without printing it (the panic
/// hook stays the default one for every other panic, and on other threads).
fn quiet_unwind<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let default = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET_PANICS.with(std::cell::Cell::get) {
                default(info);
            }
        }));
    });
    QUIET_PANICS.with(|q| q.set(true));
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    QUIET_PANICS.with(|q| q.set(false));
    result.map_err(|payload| {
        payload
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "a panic".into())
    })
}

/// Reads a recorded table (`messages` or `timings`) of a run, finished or not.
pub fn read_table(run_dir: &Path, table: &str) -> Result<Vec<RecordBatch>, RecordError> {
    let mut out = Vec::new();
    for file in table_files(run_dir, table)? {
        read_file(&file, &mut out)?;
    }
    Ok(out)
}

/// A column as the expected Arrow type. Parquet written by other tools (polars writes
/// `Utf8View`, pandas `LargeUtf8`) is cast rather than rejected.
fn column(
    batch: &RecordBatch,
    name: &str,
    path: &Path,
    to: &DataType,
) -> Result<ArrayRef, RecordError> {
    let format = |message: String| RecordError::Format {
        path: path.to_path_buf(),
        message,
    };
    let col = batch
        .column_by_name(name)
        .ok_or_else(|| format(format!("recorded table lacks column '{name}'")))?;
    if col.data_type() == to {
        return Ok(col.clone());
    }
    arrow_cast::cast(col, to).map_err(|e| format(format!("column '{name}': {e}")))
}

macro_rules! typed {
    ($batch:expr, $name:expr, $path:expr, $array:ty, $dtype:expr) => {{
        let col = column($batch, $name, $path, &$dtype)?;
        col.as_any()
            .downcast_ref::<$array>()
            .expect("cast to the matching type")
            .clone()
    }};
}

/// All recorded messages of a run, in recording order.
pub fn read_messages(run_dir: &Path) -> Result<Vec<Message>, RecordError> {
    let mut out = Vec::new();
    for b in read_table(run_dir, MESSAGES)? {
        let p = run_dir;
        let step = typed!(&b, "step", p, UInt64Array, DataType::UInt64);
        let time = typed!(&b, "time", p, Float64Array, DataType::Float64);
        let source = typed!(&b, "source", p, StringArray, DataType::Utf8);
        let topic = typed!(&b, "topic", p, StringArray, DataType::Utf8);
        let kind = typed!(&b, "kind", p, StringArray, DataType::Utf8);
        let text = typed!(&b, "text", p, StringArray, DataType::Utf8);
        let meta = typed!(&b, "meta", p, StringArray, DataType::Utf8);
        let data = typed!(&b, "data", p, BinaryArray, DataType::Binary);
        for i in 0..b.num_rows() {
            let payload = match PayloadKind::parse(kind.value(i)) {
                Some(PayloadKind::Json) => Payload::Json(text.value(i).to_string()),
                Some(PayloadKind::Artifact) => Payload::Artifact(text.value(i).to_string()),
                Some(PayloadKind::Binary) => Payload::Binary {
                    meta: meta.value(i).to_string(),
                    data: data.value(i).to_vec(),
                },
                None => {
                    return Err(RecordError::Format {
                        path: run_dir.to_path_buf(),
                        message: format!("unknown payload kind '{}'", kind.value(i)),
                    })
                }
            };
            out.push(Message {
                step: step.value(i),
                time: time.value(i),
                topic: topic.value(i).to_string(),
                source: source.value(i).to_string(),
                payload,
            });
        }
    }
    Ok(out)
}

/// All timing rows of a run.
pub fn read_timings(run_dir: &Path) -> Result<Vec<TimingRow>, RecordError> {
    let mut out = Vec::new();
    for b in read_table(run_dir, TIMINGS)? {
        let p = run_dir;
        let step = typed!(&b, "step", p, UInt64Array, DataType::UInt64);
        let time = typed!(&b, "time", p, Float64Array, DataType::Float64);
        let module = typed!(&b, "module", p, StringArray, DataType::Utf8);
        let wall = typed!(&b, "wall_s", p, Float64Array, DataType::Float64);
        let cpu = typed!(&b, "cpu_s", p, Float64Array, DataType::Float64);
        let rss = typed!(&b, "rss_mib", p, Float64Array, DataType::Float64);
        let msgs_in = typed!(&b, "msgs_in", p, UInt32Array, DataType::UInt32);
        let msgs_out = typed!(&b, "msgs_out", p, UInt32Array, DataType::UInt32);
        // Runs recorded before GPU accounting lack the columns.
        let gpu = |name| {
            b.column_by_name(name)
                .and_then(|c| arrow_cast::cast(c, &DataType::Float64).ok())
                .map(|c| {
                    c.as_any()
                        .downcast_ref::<Float64Array>()
                        .expect("float64")
                        .clone()
                })
        };
        let (gpu_util, gpu_mem) = (gpu("gpu_util_pct"), gpu("gpu_mem_mib"));
        let at = |a: &Option<Float64Array>, i: usize| {
            a.as_ref().and_then(|a| (!a.is_null(i)).then(|| a.value(i)))
        };
        for i in 0..b.num_rows() {
            out.push(TimingRow {
                step: step.value(i),
                time: time.value(i),
                module: module.value(i).to_string(),
                wall_s: wall.value(i),
                cpu_s: cpu.value(i),
                rss_mib: rss.value(i),
                msgs_in: msgs_in.value(i),
                msgs_out: msgs_out.value(i),
                gpu_util_pct: at(&gpu_util, i),
                gpu_mem_mib: at(&gpu_mem, i),
            });
        }
    }
    Ok(out)
}
