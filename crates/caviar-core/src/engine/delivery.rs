//! Delivery at a stage's end: each module's timing recorded and what it published
//! checked, routed to the subscribers' inboxes and recorded, in module order.

use std::sync::Arc;

use super::accounting::StageSample;
use super::error::EngineError;
use super::stepping::{Ran, StepState};
use super::types::{Engine, END_TOPIC, STATUS_TOPIC};
use crate::message::{Message, Outgoing};
use crate::recorder::TimingRow;
use crate::topic::validate_topic;

impl Engine {
    fn subscribers(&mut self, topic: &str) -> Arc<[usize]> {
        if let Some(r) = self.routes.get(topic) {
            return r.clone();
        }
        let r: Arc<[usize]> = self
            .slots
            .iter()
            .enumerate()
            .filter(|(_, s)| s.subs.iter().any(|p| p.matches(topic)))
            .map(|(i, _)| i)
            .collect();
        self.routes.insert(topic.to_string(), r.clone());
        r
    }

    /// Records each module's timing and routes what it published, in module order.
    pub(super) fn deliver(
        &mut self,
        mut ran: Vec<Ran>,
        sample: StageSample,
        state: &mut StepState,
    ) {
        ran.sort_by_key(|r| r.slot);
        let at = state.at;
        for r in ran {
            let name = self.slots[r.slot].name.clone();
            let outgoing = match r.result {
                Ok(out) => out,
                Err(error) => {
                    state.failure.get_or_insert(EngineError::Module {
                        module: name.clone(),
                        phase: "step",
                        step: Some(at.step),
                        time: Some(at.time),
                        error: Box::new(error),
                    });
                    Vec::new()
                }
            };
            if let Some(rec) = &mut self.recorder {
                let (rss_mib, gpu_util_pct, gpu_mem_mib) = match r.reported {
                    Some(u) => (u.rss_mib, u.gpu_util_pct, u.gpu_mem_mib),
                    None => (
                        sample.rss_mib,
                        sample.gpu.map(|g| g.0),
                        sample.gpu.map(|g| g.1),
                    ),
                };
                rec.record_timing(&TimingRow {
                    step: at.step,
                    time: at.time,
                    module: name.clone(),
                    wall_s: r.wall_s,
                    cpu_s: r.cpu_s,
                    rss_mib,
                    msgs_in: r.msgs_in,
                    msgs_out: outgoing.len() as u32,
                    gpu_util_pct,
                    gpu_mem_mib,
                });
            }
            for o in outgoing {
                self.publish(&name, o, state);
            }
        }
    }

    /// Checks one outgoing message, hands it to its subscribers and the recorder.
    fn publish(&mut self, name: &str, o: Outgoing, state: &mut StepState) {
        let at = state.at;
        if let Err(reason) = check_publish(&o.topic) {
            state.failure.get_or_insert(EngineError::Publish {
                module: name.to_string(),
                step: at.step,
                topic: o.topic,
                reason,
            });
            return;
        }
        if o.topic == END_TOPIC && state.end_by.is_none() {
            state.end_by = Some(name.to_string());
        }
        let msg = Arc::new(Message {
            step: at.step,
            time: at.time,
            topic: o.topic,
            source: name.to_string(),
            payload: o.payload,
        });
        for &j in self.subscribers(&msg.topic).iter() {
            self.slots[j].inbox.push(msg.clone());
        }
        if let Some(rec) = &mut self.recorder {
            rec.record_message(&msg);
        }
        state.published.push(msg);
    }
}

fn check_publish(topic: &str) -> Result<(), String> {
    validate_topic(topic).map_err(|e| e.to_string())?;
    if topic.starts_with("caviar.") && topic != END_TOPIC && topic != STATUS_TOPIC {
        return Err(format!(
            "topics under 'caviar.' are reserved for the core (modules may publish '{END_TOPIC}' \
             and '{STATUS_TOPIC}')"
        ));
    }
    Ok(())
}
