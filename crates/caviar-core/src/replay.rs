//! `caviar.replay`: republishes chosen topics of a recorded run.
//!
//! This is how the paper's simulation categories are made without the expensive
//! parts in the loop: AI/Comm-in-loop replays the mobility of an earlier run;
//! pre-computed channels are replayed from a recorded run like from a database.
//!
//! ```toml
//! [modules.mobility]
//! stage = "mobility"
//! plugin = "caviar.replay"
//! [modules.mobility.params]
//! run = "runs/quickstart-001"      # relative to the config file
//! topics = ["3D.mobility.>"]       # default: every topic
//! sources = ["uav"]                # optional: only these recorded modules
//! ```
//!
//! A message recorded at virtual time t_r is published in the first step whose time
//! is t_r or later, so a run recorded at another Ts replays in time order too.

use std::collections::VecDeque;
use std::path::PathBuf;

use crate::config::{ConfigError, LoadedConfig};
use crate::message::{Message, Outgoing, SharedMessage};
use crate::module::{Module, ModuleError, StepInfo};
use crate::recorder::read_messages;
use crate::topic::Pattern;

pub const PLUGIN: &str = "caviar.replay";

pub struct Replay {
    queue: VecDeque<Message>,
}

impl Replay {
    pub fn from_config(cfg: &LoadedConfig, name: &str) -> Result<Self, ConfigError> {
        let key = |k: &str| format!("modules.{name}.params.{k}");
        let params = &cfg.config.modules[name].params;
        for k in params.keys() {
            if !["run", "topics", "sources"].contains(&k.as_str()) {
                return Err(cfg.error_at(
                    &key(k),
                    "unknown parameter of caviar.replay, expected one of run, topics, sources",
                ));
            }
        }
        let run = params.get("run").and_then(|v| v.as_str()).ok_or_else(|| {
            cfg.error_at(
                &format!("modules.{name}.params"),
                "caviar.replay needs `run`, the path of a recorded run directory",
            )
        })?;
        let strings = |k: &str, default: Vec<String>| -> Result<Vec<String>, ConfigError> {
            match params.get(k) {
                None => Ok(default),
                Some(v) => v
                    .as_array()
                    .and_then(|a| {
                        a.iter()
                            .map(|x| x.as_str().map(String::from))
                            .collect::<Option<Vec<_>>>()
                    })
                    .ok_or_else(|| cfg.error_at(&key(k), "expected a list of strings")),
            }
        };
        let topics = strings("topics", vec![">".into()])?
            .iter()
            .map(|p| Pattern::new(p).map_err(|e| cfg.error_at(&key("topics"), e.to_string())))
            .collect::<Result<Vec<_>, _>>()?;
        let sources = strings("sources", Vec::new())?;
        let run_dir: PathBuf = cfg.resolve(run.as_ref());
        let messages = read_messages(&run_dir)
            .map_err(|e| cfg.error_at(&key("run"), format!("cannot read the recorded run: {e}")))?;
        let queue: VecDeque<Message> = messages
            .into_iter()
            .filter(|m| topics.iter().any(|p| p.matches(&m.topic)))
            .filter(|m| sources.is_empty() || sources.contains(&m.source))
            .collect();
        if queue.is_empty() {
            return Err(cfg.error_at(
                &key("topics"),
                format!(
                    "no recorded message in {} matches these topics and sources",
                    run_dir.display()
                ),
            ));
        }
        Ok(Replay { queue })
    }
}

impl Module for Replay {
    fn step(
        &mut self,
        at: StepInfo,
        _inbox: &[SharedMessage],
        out: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        let horizon = at.time + 1e-9 * at.time.abs().max(1.0);
        while self.queue.front().is_some_and(|m| m.time <= horizon) {
            let m = self.queue.pop_front().expect("front exists");
            out.push(Outgoing {
                topic: m.topic,
                payload: m.payload,
            });
        }
        Ok(())
    }
}
