//! The column builders a recorder fills between flushes: one per table, each
//! finished into a record batch of that table's schema.

use std::sync::Arc;

use arrow_array::builder::{
    BinaryBuilder, Float64Builder, StringBuilder, UInt32Builder, UInt64Builder,
};
use arrow_array::{ArrayRef, RecordBatch};

use super::schema::{messages_schema, timings_schema, TimingRow};
use crate::message::{Message, Payload};

/// Declares a table's column builders, in the order of the table's schema, with the
/// row count since the last `finish`, and `finish`, which empties them into a record
/// batch of that schema. Each table fills its builders in a `push` of its own.
macro_rules! columns {
    ($(#[$doc:meta])* $name:ident, $schema:ident { $($column:ident: $builder:ty),+ $(,)? }) => {
        $(#[$doc])*
        #[derive(Default)]
        pub(super) struct $name {
            $($column: $builder,)+
            pub(super) rows: usize,
        }

        impl $name {
            pub(super) fn finish(&mut self) -> RecordBatch {
                self.rows = 0;
                let cols: Vec<ArrayRef> = vec![$(Arc::new(self.$column.finish())),+];
                RecordBatch::try_new($schema(), cols).expect("columns match the schema")
            }
        }
    };
}

columns!(
    /// The `messages` table's columns.
    MessageColumns,
    messages_schema {
        step: UInt64Builder,
        time: Float64Builder,
        seq: UInt32Builder,
        source: StringBuilder,
        topic: StringBuilder,
        kind: StringBuilder,
        text: StringBuilder,
        meta: StringBuilder,
        data: BinaryBuilder,
    }
);

columns!(
    /// The `timings` table's columns.
    TimingColumns,
    timings_schema {
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
    }
);

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
}
