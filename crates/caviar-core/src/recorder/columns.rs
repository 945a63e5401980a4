//! The column builders a recorder fills between flushes: one per table, each
//! finished into a record batch of that table's schema.

use std::sync::Arc;

use arrow_array::builder::{
    BinaryBuilder, Float64Builder, StringBuilder, UInt32Builder, UInt64Builder,
};
use arrow_array::{ArrayRef, RecordBatch};

use super::schema::{messages_schema, timings_schema, TimingRow};
use crate::message::{Message, Payload};

#[derive(Default)]
pub(super) struct MessageColumns {
    step: UInt64Builder,
    time: Float64Builder,
    seq: UInt32Builder,
    source: StringBuilder,
    topic: StringBuilder,
    kind: StringBuilder,
    text: StringBuilder,
    meta: StringBuilder,
    data: BinaryBuilder,
    pub(super) rows: usize,
}

impl MessageColumns {
    pub(super) fn push(&mut self, seq: u32, m: &Message) {
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

    pub(super) fn finish(&mut self) -> RecordBatch {
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
pub(super) struct TimingColumns {
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
    pub(super) rows: usize,
}

impl TimingColumns {
    pub(super) fn push(&mut self, r: &TimingRow) {
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

    pub(super) fn finish(&mut self) -> RecordBatch {
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
