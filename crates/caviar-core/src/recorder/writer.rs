//! The [`Recorder`]: buffers a run's messages and timings and writes them as part
//! files after each step (or each flush interval), merges parts into chunks, and
//! compacts everything into one file per table at the end.

use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use arrow_array::{Array, RecordBatch, UInt64Array};
use arrow_schema::SchemaRef;
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::properties::WriterProperties;

use super::columns::{MessageColumns, TimingColumns};
use super::error::{io_err, pq_err, RecordError};
use super::layout::{compacted_file, part_files, parts_of, table_files};
use super::reader::read_table;
use super::schema::{messages_schema, tables, timings_schema, TimingRow, MESSAGES, TIMINGS};
use crate::message::Message;
use crate::topic::Pattern;

/// Parts merged into one chunk file.
pub const CHUNK_PARTS: usize = 256;
/// ... or fewer, once the parts since the last chunk hold this many bytes.
pub const CHUNK_BYTES: usize = 64 << 20;

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

pub(super) fn write_parquet(
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
        for ((table, schema), batches) in tables().into_iter().zip(kept) {
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
            let single = run_dir.join(compacted_file(table));
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
        let write_part = |table: &str, schema, batch: &RecordBatch| {
            let file = self.run_dir.join(table).join(&name);
            write_parquet(&file, schema, std::slice::from_ref(batch))
        };
        let messages = self.messages.finish();
        write_part(MESSAGES, messages_schema(), &messages)?;
        let timings = self.timings.finish();
        write_part(TIMINGS, timings_schema(), &timings)?;
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
        for ((table, schema), batches) in tables().into_iter().zip([messages, timings]) {
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
        for (table, schema) in tables() {
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

fn compact(run_dir: &Path, table: &str, schema: SchemaRef) -> Result<(), RecordError> {
    let parts_dir = run_dir.join(table);
    let batches = read_table(run_dir, table)?;
    write_parquet(&run_dir.join(compacted_file(table)), schema, &batches)?;
    fs::remove_dir_all(&parts_dir).map_err(io_err(&parts_dir))
}
