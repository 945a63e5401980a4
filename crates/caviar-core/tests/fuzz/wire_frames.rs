//! The wire frame codec: frames round-trip exactly, and corrupt ones are rejected
//! with a reason.

use std::sync::Arc;

use proptest::prelude::*;
use proptest::test_runner::TestCaseError;

use caviar_core::module::Usage;
use caviar_core::transport::nats::wire;
use caviar_core::{Message, Outgoing, Payload, SharedMessage, StepInfo};

use crate::harness::fuzz;
use crate::mutation::mutated;

fn payload() -> impl Strategy<Value = Payload> {
    prop_oneof![
        "[ -~]{0,40}".prop_map(Payload::Json),
        "\\PC{0,20}".prop_map(Payload::Artifact),
        ("[ -~]{0,20}", prop::collection::vec(any::<u8>(), 0..64))
            .prop_map(|(meta, data)| Payload::Binary { meta, data }),
    ]
}

fn topic() -> impl Strategy<Value = String> {
    prop::collection::vec("[a-zA-Z0-9_-]{1,6}", 1..4).prop_map(|t| t.join("."))
}

fn message() -> impl Strategy<Value = Message> {
    (
        any::<u64>(),
        any::<f64>().prop_filter("finite", |t| t.is_finite()),
        topic(),
        "[a-z]{0,8}",
        payload(),
    )
        .prop_map(|(step, time, topic, source, payload)| Message {
            step,
            time,
            topic,
            source,
            payload,
        })
}

#[test]
fn wire_frames_round_trip_exactly() {
    let cases = (
        any::<u64>(),
        any::<f64>().prop_filter("finite", |t| t.is_finite()),
        prop::collection::vec(message(), 0..5),
    );
    fuzz("wire round trip", 2000, cases, |(step, time, inbox)| {
        let shared: Vec<SharedMessage> = inbox.iter().cloned().map(Arc::new).collect();
        let frame = wire::encode_request(StepInfo { step, time }, 1, 3, &shared);
        let (req, back) = wire::decode_request(&frame).map_err(TestCaseError::fail)?;
        prop_assert_eq!(
            (req.step, req.time.to_bits(), req.shard, req.shards),
            (step, time.to_bits(), 1, 3)
        );
        prop_assert_eq!(back.len(), inbox.len());
        for (a, b) in back.iter().zip(&inbox) {
            // Bit for bit: a run over NATS records the same times as one in process.
            prop_assert_eq!(
                (a.step, a.time.to_bits(), &a.topic, &a.source, &a.payload),
                (b.step, b.time.to_bits(), &b.topic, &b.source, &b.payload)
            );
        }
        let out: Vec<Outgoing> = inbox
            .iter()
            .map(|m| Outgoing::new(m.topic.clone(), m.payload.clone()))
            .collect();
        let usage = Usage {
            wall_s: time.abs(),
            cpu_s: 0.5,
            rss_mib: 12.0,
            gpu_util_pct: None,
            gpu_mem_mib: None,
        };
        let mut decoded = Vec::new();
        let got = wire::decode_reply(&wire::encode_reply(&out, usage), &mut decoded)
            .map_err(|e| TestCaseError::fail(e.message))?;
        prop_assert_eq!(got.wall_s.to_bits(), time.abs().to_bits());
        prop_assert_eq!(decoded, out);
        Ok(())
    });
}

#[test]
fn corrupt_frames_are_rejected_with_a_reason() {
    // Seeds: valid requests and replies of every payload kind, failures, and junk.
    let inbox: Vec<SharedMessage> = vec![
        Message {
            step: 3,
            time: 0.3,
            topic: "a.b".into(),
            source: "m".into(),
            payload: Payload::Json("{\"x\": 1}".into()),
        },
        Message {
            step: 3,
            time: 0.3,
            topic: "img.rgb".into(),
            source: "cam".into(),
            payload: Payload::Binary {
                meta: "{\"shape\": [2, 2]}".into(),
                data: vec![0, 1, 2, 255],
            },
        },
        Message {
            step: 2,
            time: 0.2,
            topic: "a.file".into(),
            source: "m".into(),
            payload: Payload::Artifact("out/x.png".into()),
        },
    ]
    .into_iter()
    .map(Arc::new)
    .collect();
    let out: Vec<Outgoing> = inbox
        .iter()
        .map(|m| Outgoing::new(m.topic.clone(), m.payload.clone()))
        .collect();
    let usage = Usage {
        wall_s: 0.1,
        cpu_s: 0.1,
        rss_mib: 10.0,
        gpu_util_pct: Some(3.0),
        gpu_mem_mib: None,
    };
    let failure = wire::WireError {
        message: "boom".into(),
        trace: Some("Traceback".into()),
        key: Some("params.x".into()),
    };
    let seeds = vec![
        wire::encode_request(StepInfo { step: 3, time: 0.3 }, 0, 1, &inbox),
        wire::encode_request(
            StepInfo { step: 0, time: 0.0 },
            0,
            1,
            &[] as &[SharedMessage],
        ),
        wire::encode_reply(&out, usage),
        wire::encode_failure(&failure),
        b"\x02\x00\x00\x00{}".to_vec(),
        Vec::new(),
    ];
    let strategy = prop_oneof![
        4 => mutated(seeds, 6),
        1 => prop::collection::vec(any::<u8>(), 0..64),
    ];
    fuzz("wire frames", 20_000, strategy, |bytes| {
        match wire::decode_request(&bytes) {
            Ok((req, inbox)) => prop_assert_eq!(req.messages.len(), 0, "{:?}", inbox),
            Err(e) => prop_assert!(!e.is_empty()),
        }
        let mut out = Vec::new();
        if let Err(e) = wire::decode_reply(&bytes, &mut out) {
            prop_assert!(!e.message.is_empty());
        }
        Ok(())
    });
}
