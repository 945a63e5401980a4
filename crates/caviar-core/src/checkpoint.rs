//! Checkpoints, and resuming a run from one (`caviar-core run --resume RUN_DIR`).
//!
//! Every `output.checkpoint_every` steps (100 by default; 0: never), or sooner once
//! `output.checkpoint_interval_s` of wall time passed since the last one (60 s by default;
//! 0: by steps only), the run writes `RUN_DIR/checkpoint.json`, atomically (a temporary file renamed over it), after the
//! step's messages are on disk: the first step still to run, the engine's clocks, and
//! per module its state ([`ModuleState`]: the plugin's `state()` with its random
//! stream, pickled, or "stateless") and its inbox (the messages delivered for its next
//! step). The seeds need no saving: each module's is derived from the episode seed and
//! its name.
//!
//! A resumed run reads the configuration the run saved (`RUN_DIR/config.toml`, with its
//! `--set` overrides applied), sets every module up again, restores the states and
//! inboxes, drops from the recording the steps after the checkpoint (the crashed run
//! may have recorded some), and goes on: it records exactly the messages an
//! uninterrupted run with the same seed records (tested, CPU, in process and over NATS,
//! whose workers answer `state` and `resume` requests). A module that has no state hooks
//! and does not declare itself stateless makes `--resume` refuse, naming it.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::message::{Message, Payload, PayloadKind};
use crate::module::ModuleState;

pub const FILE: &str = "checkpoint.json";
const VERSION: u32 = 1;

/// `output.checkpoint_every` when not given.
pub const DEFAULT_EVERY: u64 = 100;
/// `output.checkpoint_interval_s` when not given: a checkpoint at least once a minute of
/// wall time, so that any run killed after its first minute resumes.
pub const DEFAULT_INTERVAL_S: f64 = 60.0;

/// What a checkpoint holds.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Checkpoint {
    pub version: u32,
    /// The first step a resumed run runs: steps before it are recorded.
    pub next_step: u64,
    pub wall_s: f64,
    pub record_s: f64,
    /// Where the configuration's relative paths point (absolute).
    pub config_dir: PathBuf,
    pub modules: Vec<ModuleCheckpoint>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModuleCheckpoint {
    pub name: String,
    pub state: SavedState,
    pub inbox: Vec<SavedMessage>,
}

/// [`ModuleState`] as JSON (bytes as hex).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum SavedState {
    Stateless,
    Saved { hex: String },
    Unsupported { why: String },
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SavedMessage {
    pub step: u64,
    pub time: f64,
    pub topic: String,
    pub source: String,
    pub kind: String,
    /// JSON text or artifact path; for binary payloads, the meta text.
    pub text: String,
    /// Binary payloads: the bytes, hex.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hex: Option<String>,
}

impl From<ModuleState> for SavedState {
    fn from(s: ModuleState) -> Self {
        match s {
            ModuleState::Stateless => SavedState::Stateless,
            ModuleState::Saved(b) => SavedState::Saved { hex: hex(&b) },
            ModuleState::Unsupported(why) => SavedState::Unsupported { why },
        }
    }
}

impl SavedMessage {
    pub fn of(m: &Message) -> Self {
        let (text, data) = match &m.payload {
            Payload::Json(t) | Payload::Artifact(t) => (t.clone(), None),
            Payload::Binary { meta, data } => (meta.clone(), Some(hex(data))),
        };
        SavedMessage {
            step: m.step,
            time: m.time,
            topic: m.topic.clone(),
            source: m.source.clone(),
            kind: m.payload.kind().as_str().into(),
            text,
            hex: data,
        }
    }

    pub fn to_message(&self) -> Result<Message, String> {
        let payload = match PayloadKind::parse(&self.kind) {
            Some(PayloadKind::Json) => Payload::Json(self.text.clone()),
            Some(PayloadKind::Artifact) => Payload::Artifact(self.text.clone()),
            Some(PayloadKind::Binary) => Payload::Binary {
                meta: self.text.clone(),
                data: unhex(self.hex.as_deref().unwrap_or_default())?,
            },
            None => return Err(format!("unknown payload kind '{}'", self.kind)),
        };
        Ok(Message {
            step: self.step,
            time: self.time,
            topic: self.topic.clone(),
            source: self.source.clone(),
            payload,
        })
    }
}

impl Checkpoint {
    pub fn new(next_step: u64, wall_s: f64, record_s: f64, config_dir: &Path) -> Self {
        Checkpoint {
            version: VERSION,
            next_step,
            wall_s,
            record_s,
            config_dir: config_dir
                .canonicalize()
                .unwrap_or_else(|_| config_dir.to_path_buf()),
            modules: Vec::new(),
        }
    }

    /// Writes `RUN_DIR/checkpoint.json` atomically.
    pub fn write(&self, run_dir: &Path) -> Result<(), String> {
        let path = run_dir.join(FILE);
        let tmp = run_dir.join(".checkpoint.json.tmp");
        let text = serde_json::to_vec(self).expect("json");
        std::fs::write(&tmp, text)
            .and_then(|()| std::fs::rename(&tmp, &path))
            .map_err(|e| format!("{}: {e}", path.display()))
    }

    /// Reads `RUN_DIR/checkpoint.json`.
    pub fn read(run_dir: &Path) -> Result<Self, String> {
        let path = run_dir.join(FILE);
        let text = std::fs::read(&path).map_err(|e| {
            format!(
                "{}: no checkpoint to resume from ({e}); checkpoints are written every \
                 output.checkpoint_every steps or output.checkpoint_interval_s seconds",
                path.display()
            )
        })?;
        let cp: Checkpoint =
            serde_json::from_slice(&text).map_err(|e| format!("{}: {e}", path.display()))?;
        if cp.version != VERSION {
            return Err(format!(
                "{}: checkpoint version {} (this caviar reads {VERSION})",
                path.display(),
                cp.version
            ));
        }
        Ok(cp)
    }
}

pub fn hex(bytes: &[u8]) -> String {
    const DIGITS: &[u8; 16] = b"0123456789abcdef";
    let mut s = String::with_capacity(bytes.len() * 2);
    for b in bytes {
        s.push(DIGITS[(b >> 4) as usize] as char);
        s.push(DIGITS[(b & 15) as usize] as char);
    }
    s
}

pub fn unhex(text: &str) -> Result<Vec<u8>, String> {
    let digit = |c: u8| match c {
        b'0'..=b'9' => Ok(c - b'0'),
        b'a'..=b'f' => Ok(c - b'a' + 10),
        _ => Err(format!("'{}' is not a hex digit", c as char)),
    };
    let b = text.as_bytes();
    if !b.len().is_multiple_of(2) {
        return Err("hex text of odd length".into());
    }
    b.chunks(2)
        .map(|p| Ok(digit(p[0])? << 4 | digit(p[1])?))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hex_round_trips_and_rejects_junk() {
        let bytes: Vec<u8> = (0..=255).collect();
        assert_eq!(unhex(&hex(&bytes)).unwrap(), bytes);
        assert!(unhex("abc").is_err() && unhex("zz").is_err());
    }

    #[test]
    fn messages_of_every_kind_round_trip() {
        for payload in [
            Payload::Json("{\"a\":1}".into()),
            Payload::Artifact("artifacts/x.png".into()),
            Payload::Binary {
                meta: "{}".into(),
                data: vec![0, 1, 254, 255],
            },
        ] {
            let m = Message {
                step: 4,
                time: 0.1 + 0.2,
                topic: "a.b".into(),
                source: "m".into(),
                payload,
            };
            let text = serde_json::to_string(&SavedMessage::of(&m)).unwrap();
            let back: SavedMessage = serde_json::from_str(&text).unwrap();
            assert_eq!(back.to_message().unwrap(), m);
        }
    }
}
