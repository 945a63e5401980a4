//! The episode recorder: every message and every module's per-step timing, as Parquet.
//!
//! While a run goes, the recorder writes small Parquet files (`messages/part-NNNNNN.parquet`,
//! `timings/part-NNNNNN.parquet`), each complete and readable on its own, after every
//! step (or every `output.flush_interval` seconds). A killed process thus loses at most
//! what was not yet flushed. Every [`CHUNK_PARTS`] parts (or [`CHUNK_BYTES`] of them) are
//! rewritten as one `chunk-AAAAAA-BBBBBB.parquet` (parts A to B, from the batches still in
//! memory) and the parts removed, so that a run of 100,000 fast steps leaves hundreds
//! of files, not 100,000, and ends in a second, not minutes. A chunk is renamed into
//! place before its parts go: a reader that sees both takes the chunk and skips the
//! parts it covers. At the end of a run everything is compacted into
//! `messages.parquet` and `timings.parquet`. Readers accept every form.

use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use arrow_array::builder::{
    BinaryBuilder, Float64Builder, StringBuilder, UInt32Builder, UInt64Builder,
};
use arrow_array::{
    Array, ArrayRef, BinaryArray, Float64Array, RecordBatch, StringArray, UInt32Array, UInt64Array,
};
use arrow_schema::{DataType, Field, Schema, SchemaRef};
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::properties::WriterProperties;

use crate::message::{Message, Payload, PayloadKind};
use crate::topic::Pattern;

pub const MESSAGES: &str = "messages";
pub const TIMINGS: &str = "timings";

/// Parts merged into one chunk file.
pub const CHUNK_PARTS: usize = 256;
/// ... or fewer, once the parts since the last chunk hold this many bytes.
pub const CHUNK_BYTES: usize = 64 << 20;

#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Parquet {
        path: PathBuf,
        source: parquet::errors::ParquetError,
    },
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> RecordError + '_ {
    move |source| RecordError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn pq_err(path: &Path) -> impl FnOnce(parquet::errors::ParquetError) -> RecordError + '_ {
    move |source| RecordError::Parquet {
        path: path.to_path_buf(),
        source,
    }
}

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

#[derive(Default)]
struct MessageColumns {
    step: UInt64Builder,
    time: Float64Builder,
    seq: UInt32Builder,
    source: StringBuilder,
    topic: StringBuilder,
    kind: StringBuilder,
    text: StringBuilder,
    meta: StringBuilder,
    data: BinaryBuilder,
    rows: usize,
}

impl MessageColumns {
    fn push(&mut self, seq: u32, m: &Message) {
        self.step.append_value(m.step);
        self.time.append_value(m.time);
        self.seq.append_value(seq);
        self.source.append_value(&m.source);
        self.topic.append_value(&m.topic);
        self.kind.append_value(m.payload.kind().as_str());
        match &m.payload {
            Payload::Json(text) | Payload::Artifact(text) => {
                self.text.append_value(text);
                self.meta.append_null();
                self.data.append_null();
            }
            Payload::Binary { meta, data } => {
                self.text.append_null();
                self.meta.append_value(meta);
                self.data.append_value(data);
            }
        }
        self.rows += 1;
    }

    fn finish(&mut self) -> RecordBatch {
        self.rows = 0;
        let cols: Vec<ArrayRef> = vec![
            Arc::new(self.step.finish()),
            Arc::new(self.time.finish()),
            Arc::new(self.seq.finish()),
            Arc::new(self.source.finish()),
            Arc::new(self.topic.finish()),
            Arc::new(self.kind.finish()),
            Arc::new(self.text.finish()),
            Arc::new(self.meta.finish()),
            Arc::new(self.data.finish()),
        ];
        RecordBatch::try_new(messages_schema(), cols).expect("columns match the schema")
    }
}

#[derive(Default)]
struct TimingColumns {
    step: UInt64Builder,
    time: Float64Builder,
    module: StringBuilder,
    wall: Float64Builder,
    cpu: Float64Builder,
    rss: Float64Builder,
    msgs_in: UInt32Builder,
    msgs_out: UInt32Builder,
    gpu_util: Float64Builder,
    gpu_mem: Float64Builder,
    rows: usize,
}

impl TimingColumns {
    fn push(&mut self, r: &TimingRow) {
        self.step.append_value(r.step);
        self.time.append_value(r.time);
        self.module.append_value(&r.module);
        self.wall.append_value(r.wall_s);
        self.cpu.append_value(r.cpu_s);
        self.rss.append_value(r.rss_mib);
        self.msgs_in.append_value(r.msgs_in);
        self.msgs_out.append_value(r.msgs_out);
        self.gpu_util.append_option(r.gpu_util_pct);
        self.gpu_mem.append_option(r.gpu_mem_mib);
        self.rows += 1;
    }

    fn finish(&mut self) -> RecordBatch {
        self.rows = 0;
        let cols: Vec<ArrayRef> = vec![
            Arc::new(self.step.finish()),
            Arc::new(self.time.finish()),
            Arc::new(self.module.finish()),
            Arc::new(self.wall.finish()),
            Arc::new(self.cpu.finish()),
            Arc::new(self.rss.finish()),
            Arc::new(self.msgs_in.finish()),
            Arc::new(self.msgs_out.finish()),
            Arc::new(self.gpu_util.finish()),
            Arc::new(self.gpu_mem.finish()),
        ];
        RecordBatch::try_new(timings_schema(), cols).expect("columns match the schema")
    }
}

pub struct Recorder {
    run_dir: PathBuf,
    exclude: Vec<Pattern>,
    flush_interval: Duration,
    last_flush: Instant,
    messages: MessageColumns,
    timings: TimingColumns,
    next_part: usize,
    /// The parts written since the last chunk: (part, messages, timings), and their bytes.
    unchunked: Vec<(usize, RecordBatch, RecordBatch)>,
    unchunked_bytes: usize,
    /// Sequence number of the next message within the current step.
    seq: u32,
    seq_step: u64,
}

fn writer_props() -> WriterProperties {
    WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .build()
}

fn write_parquet(
    path: &Path,
    schema: SchemaRef,
    batches: &[RecordBatch],
) -> Result<(), RecordError> {
    // Write beside, then rename: a reader never sees a half-written file.
    let tmp = path.with_extension("parquet.tmp");
    let file = File::create(&tmp).map_err(io_err(&tmp))?;
    let mut w = ArrowWriter::try_new(file, schema, Some(writer_props())).map_err(pq_err(&tmp))?;
    for b in batches {
        w.write(b).map_err(pq_err(&tmp))?;
    }
    w.close().map_err(pq_err(&tmp))?;
    fs::rename(&tmp, path).map_err(io_err(path))
}

impl Recorder {
    /// Starts recording into `run_dir` (which must exist).
    pub fn create(
        run_dir: &Path,
        exclude: Vec<Pattern>,
        flush_interval: Duration,
    ) -> Result<Self, RecordError> {
        for table in [MESSAGES, TIMINGS] {
            let d = run_dir.join(table);
            fs::create_dir_all(&d).map_err(io_err(&d))?;
        }
        Ok(Recorder {
            run_dir: run_dir.to_path_buf(),
            exclude,
            flush_interval,
            last_flush: Instant::now(),
            messages: MessageColumns::default(),
            timings: TimingColumns::default(),
            next_part: 0,
            unchunked: Vec::new(),
            unchunked_bytes: 0,
            seq: 0,
            seq_step: 0,
        })
    }

    /// Goes on recording a run resumed at step `next_step`: what is recorded (parts,
    /// chunks, or the compacted tables of a run that failed) is cut to the steps before
    /// it and rewritten as one chunk per table; new parts follow it.
    pub fn resume(
        run_dir: &Path,
        exclude: Vec<Pattern>,
        flush_interval: Duration,
        next_step: u64,
    ) -> Result<Self, RecordError> {
        let mut last_part = 0;
        let mut kept = Vec::new();
        for table in [MESSAGES, TIMINGS] {
            let batches = match table_files(run_dir, table) {
                Ok(_) => read_table(run_dir, table)?,
                Err(_) => Vec::new(),
            };
            let dir = run_dir.join(table);
            if dir.is_dir() {
                for f in part_files(&dir)? {
                    last_part = last_part.max(parts_of(&f).map_or(0, |(_, b)| b));
                }
            }
            kept.push(before_step(batches, next_step));
        }
        let name = format!("chunk-000000-{last_part:06}.parquet");
        for ((table, schema), batches) in
            [(MESSAGES, messages_schema()), (TIMINGS, timings_schema())]
                .into_iter()
                .zip(kept)
        {
            let dir = run_dir.join(table);
            fs::create_dir_all(&dir).map_err(io_err(&dir))?;
            // The chunk supersedes every file of the folder; the compacted table goes
            // after it (a reader prefers it while it is there).
            write_parquet(&dir.join(&name), schema, &batches)?;
            for f in fs::read_dir(&dir).map_err(io_err(&dir))?.flatten() {
                if f.file_name().to_str() != Some(name.as_str()) {
                    fs::remove_file(f.path()).map_err(io_err(&f.path()))?;
                }
            }
            let single = run_dir.join(format!("{table}.parquet"));
            if single.exists() {
                fs::remove_file(&single).map_err(io_err(&single))?;
            }
        }
        let mut r = Recorder::create(run_dir, exclude, flush_interval)?;
        r.next_part = last_part + 1;
        Ok(r)
    }

    pub fn is_recorded(&self, topic: &str) -> bool {
        !self.exclude.iter().any(|p| p.matches(topic))
    }

    pub fn record_message(&mut self, m: &Message) {
        if m.step != self.seq_step {
            self.seq_step = m.step;
            self.seq = 0;
        }
        if self.is_recorded(&m.topic) {
            self.messages.push(self.seq, m);
        }
        self.seq += 1;
    }

    pub fn record_timing(&mut self, row: &TimingRow) {
        self.timings.push(row);
    }

    /// Called after each step: flushes when the flush interval has passed.
    pub fn end_step(&mut self) -> Result<(), RecordError> {
        if self.last_flush.elapsed() >= self.flush_interval {
            self.flush()?;
        }
        Ok(())
    }

    /// Writes what is buffered as one part file per table.
    pub fn flush(&mut self) -> Result<(), RecordError> {
        self.last_flush = Instant::now();
        if self.messages.rows == 0 && self.timings.rows == 0 {
            return Ok(());
        }
        let part = self.next_part;
        let name = format!("part-{part:06}.parquet");
        self.next_part += 1;
        let messages = self.messages.finish();
        write_parquet(
            &self.run_dir.join(MESSAGES).join(&name),
            messages_schema(),
            std::slice::from_ref(&messages),
        )?;
        let timings = self.timings.finish();
        write_parquet(
            &self.run_dir.join(TIMINGS).join(&name),
            timings_schema(),
            std::slice::from_ref(&timings),
        )?;
        self.unchunked_bytes += messages.get_array_memory_size() + timings.get_array_memory_size();
        self.unchunked.push((part, messages, timings));
        if self.unchunked.len() >= CHUNK_PARTS || self.unchunked_bytes >= CHUNK_BYTES {
            self.write_chunk()?;
        }
        Ok(())
    }

    /// Rewrites the parts since the last chunk as one chunk file per table, then
    /// removes them (a crash in between leaves parts that readers skip).
    fn write_chunk(&mut self) -> Result<(), RecordError> {
        let (Some(first), Some(last)) = (self.unchunked.first(), self.unchunked.last()) else {
            return Ok(());
        };
        let name = format!("chunk-{:06}-{:06}.parquet", first.0, last.0);
        let parts: Vec<usize> = self.unchunked.iter().map(|u| u.0).collect();
        let (messages, timings): (Vec<RecordBatch>, Vec<RecordBatch>) =
            self.unchunked.drain(..).map(|(_, m, t)| (m, t)).unzip();
        self.unchunked_bytes = 0;
        for (table, schema, batches) in [
            (MESSAGES, messages_schema(), messages),
            (TIMINGS, timings_schema(), timings),
        ] {
            let dir = self.run_dir.join(table);
            write_parquet(&dir.join(&name), schema, &batches)?;
            for part in &parts {
                let file = dir.join(format!("part-{part:06}.parquet"));
                fs::remove_file(&file).map_err(io_err(&file))?;
            }
        }
        Ok(())
    }

    /// Flushes and compacts the parts into one file per table.
    pub fn finish(mut self) -> Result<(), RecordError> {
        self.flush()?;
        for (table, schema) in [(MESSAGES, messages_schema()), (TIMINGS, timings_schema())] {
            compact(&self.run_dir, table, schema)?;
        }
        Ok(())
    }
}

/// The rows of `batches` (in recording order: steps never decrease) before `step`.
fn before_step(batches: Vec<RecordBatch>, step: u64) -> Vec<RecordBatch> {
    let mut out = Vec::with_capacity(batches.len());
    for b in batches {
        let steps = b
            .column_by_name("step")
            .and_then(|c| c.as_any().downcast_ref::<UInt64Array>().cloned());
        let Some(steps) = steps else { continue };
        let keep = steps.values().iter().take_while(|&&s| s < step).count();
        if keep > 0 {
            out.push(b.slice(0, keep));
        }
        if keep < b.num_rows() {
            break;
        }
    }
    out
}

/// The parts a file of a table's folder holds: `part-N` holds N, `chunk-A-B` A to B.
fn parts_of(path: &Path) -> Option<(usize, usize)> {
    let stem = path.file_name()?.to_str()?.strip_suffix(".parquet")?;
    if let Some(n) = stem.strip_prefix("part-") {
        let n = n.parse().ok()?;
        return Some((n, n));
    }
    let (a, b) = stem.strip_prefix("chunk-")?.split_once('-')?;
    Some((a.parse().ok()?, b.parse().ok()?)).filter(|(a, b)| a <= b)
}

/// A table's files in recording order: chunks and the parts no chunk covers.
fn part_files(dir: &Path) -> Result<Vec<PathBuf>, RecordError> {
    let mut files: Vec<((usize, usize), PathBuf)> = fs::read_dir(dir)
        .map_err(io_err(dir))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter_map(|p| parts_of(&p).map(|range| (range, p)))
        .collect();
    // Chunks (wider ranges) first at the same start; a part inside a chunk is skipped.
    files.sort_by_key(|((a, b), _)| (*a, std::cmp::Reverse(*b)));
    let mut out = Vec::with_capacity(files.len());
    let mut covered_to: Option<usize> = None;
    for ((a, b), path) in files {
        if covered_to.is_some_and(|end| a <= end) {
            continue;
        }
        covered_to = Some(b);
        out.push(path);
    }
    Ok(out)
}

fn compact(run_dir: &Path, table: &str, schema: SchemaRef) -> Result<(), RecordError> {
    let parts_dir = run_dir.join(table);
    let batches = read_table(run_dir, table)?;
    write_parquet(&run_dir.join(format!("{table}.parquet")), schema, &batches)?;
    fs::remove_dir_all(&parts_dir).map_err(io_err(&parts_dir))
}

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

/// The Parquet files that hold a recorded table (`messages` or `timings`), in order:
/// `TABLE.parquet` once the run was compacted, else `TABLE/part-NNNNNN.parquet` (a
/// run in progress or one that was killed). The one place that knows the layout: the
/// readers of the Rust side and of the Python side (`caviar._core.table_files`) use it.
pub fn table_files(run_dir: &Path, table: &str) -> Result<Vec<PathBuf>, RecordError> {
    let single = run_dir.join(format!("{table}.parquet"));
    if single.exists() {
        return Ok(vec![single]);
    }
    let parts_dir = run_dir.join(table);
    if !parts_dir.is_dir() {
        return Err(RecordError::Format {
            path: run_dir.to_path_buf(),
            message: format!("not a run directory: neither {table}.parquet nor {table}/ is there"),
        });
    }
    part_files(&parts_dir)
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

#[cfg(test)]
mod tests {
    use super::*;

    fn msg(step: u64, topic: &str, payload: Payload) -> Message {
        Message {
            step,
            time: step as f64 * 0.5,
            topic: topic.into(),
            source: "m".into(),
            payload,
        }
    }

    #[test]
    fn parts_are_readable_before_finish_and_compacted_after() {
        let dir = tempfile::tempdir().unwrap();
        let mut r = Recorder::create(
            dir.path(),
            vec![Pattern::new("debug.>").unwrap()],
            Duration::ZERO,
        )
        .unwrap();
        let a = msg(0, "a.b", Payload::Json("{\"x\":1}".into()));
        let b = msg(
            0,
            "bin",
            Payload::Binary {
                meta: "{\"dtype\":\"|u1\"}".into(),
                data: vec![0, 255, 7],
            },
        );
        r.record_message(&a);
        r.record_message(&msg(0, "debug.noise", Payload::Json("1".into())));
        r.record_message(&b);
        r.end_step().unwrap();
        let c = msg(1, "file", Payload::Artifact("images/0001.png".into()));
        r.record_message(&c);
        r.end_step().unwrap();
        // As after a crash: parts only.
        assert_eq!(
            read_messages(dir.path()).unwrap(),
            vec![a.clone(), b.clone(), c.clone()]
        );
        r.finish().unwrap();
        assert!(dir.path().join("messages.parquet").exists());
        assert!(!dir.path().join("messages").exists());
        assert_eq!(read_messages(dir.path()).unwrap(), vec![a, b, c]);
    }

    fn names(dir: &Path) -> Vec<String> {
        let mut n: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        n.sort();
        n
    }

    #[test]
    fn parts_become_chunks_and_a_crash_between_loses_or_repeats_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let mut r = Recorder::create(dir.path(), vec![], Duration::ZERO).unwrap();
        let steps = 2 * CHUNK_PARTS as u64 + 3;
        let all: Vec<Message> = (0..steps)
            .map(|k| msg(k, "a.b", Payload::Json(format!("{{\"k\":{k}}}"))))
            .collect();
        for m in &all {
            r.record_message(m);
            r.end_step().unwrap();
        }
        let last = CHUNK_PARTS * 2 - 1;
        assert_eq!(
            names(&dir.path().join(MESSAGES)),
            vec![
                format!("chunk-000000-{:06}.parquet", CHUNK_PARTS - 1),
                format!("chunk-{:06}-{last:06}.parquet", CHUNK_PARTS),
                format!("part-{:06}.parquet", last + 1),
                format!("part-{:06}.parquet", last + 2),
                format!("part-{:06}.parquet", last + 3),
            ]
        );
        assert_eq!(read_messages(dir.path()).unwrap(), all);
        // As if the process died after renaming a chunk into place, before removing its
        // parts: the parts are there again, and read once.
        for k in [3usize, 4, CHUNK_PARTS + 1] {
            let part = dir
                .path()
                .join(MESSAGES)
                .join(format!("part-{k:06}.parquet"));
            write_parquet(
                &part,
                messages_schema(),
                &[RecordBatch::new_empty(messages_schema())],
            )
            .unwrap();
        }
        assert_eq!(read_messages(dir.path()).unwrap(), all);
        r.finish().unwrap();
        assert_eq!(read_messages(dir.path()).unwrap(), all);
        assert!(!dir.path().join(MESSAGES).exists());
    }

    #[test]
    fn a_missing_run_directory_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let e = read_messages(&dir.path().join("nope"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("not a run directory"), "{e}");
    }
}
