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
//!
//! Here: the tables' names and schemas (`schema`), the recorder that writes them
//! (`writer`, filling the builders of `columns`), where their files lie (`layout`) and
//! the readers (`reader`); the one error type of them all (`error`).

mod columns;
mod error;
mod layout;
mod reader;
mod schema;
mod writer;

pub use error::RecordError;
pub use layout::{compacted_file, table_files};
pub use reader::{read_messages, read_table, read_timings};
pub use schema::{messages_schema, timings_schema, TimingRow, CORE, MESSAGES, TIMINGS};
pub use writer::{Recorder, CHUNK_BYTES, CHUNK_PARTS};

#[cfg(test)]
mod tests;
