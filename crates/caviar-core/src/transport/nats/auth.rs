//! Authentication of the run's control traffic (docs/nats-protocol.md, "Who is trusted").
//!
//! Every frame the core sends (hello answers, setup, step, teardown, stop) and every
//! frame a worker sends back carries a trailer: an 8-byte little-endian sequence number
//! and an HMAC-SHA256 tag over the run id, the subject it was published on, the
//! sequence number and the body. The key is made fresh for each run (32 random bytes)
//! and handed to the workers through the environment ([`KEY_ENV`] or [`KEY_FILE_ENV`]).
//! A frame moved to another subject, another run, or with any byte changed fails
//! verification; a captured frame sent again repeats a sequence number and is refused;
//! step frames must also carry the step the worker expects next ([`StepGuard`]).
//!
//! One implementation for both sides: the Python worker reaches it through
//! `caviar._core.RunKey` and `caviar._core.Guard`.

use std::collections::BTreeSet;

use ring::hmac;
use ring::rand::{SecureRandom, SystemRandom};

/// Environment variable holding the run key (64 hex digits).
pub const KEY_ENV: &str = "CAVIAR_RUN_KEY";
/// Environment variable naming a file that holds the run key (64 hex digits).
pub const KEY_FILE_ENV: &str = "CAVIAR_RUN_KEY_FILE";
/// Bytes added to a frame: sequence number (8) and tag (32).
pub const TRAILER: usize = 8 + 32;
/// Domain separation: a tag of this protocol cannot be another protocol's.
const DOMAIN: &[u8] = b"caviar-nats-v2\0";
/// How far behind the newest sequence number a frame may arrive (frames of one step
/// are published by concurrent tasks and may overtake each other).
const WINDOW: u64 = 4096;

/// The per-run key of the HMAC.
#[derive(Clone)]
pub struct RunKey {
    key: hmac::Key,
    hex: String,
}

impl std::fmt::Debug for RunKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("RunKey(…)")
    }
}

/// 32 random bytes from the operating system, as hex.
pub fn random_hex(bytes: usize) -> Result<String, String> {
    let mut b = vec![0u8; bytes];
    SystemRandom::new()
        .fill(&mut b)
        .map_err(|_| "the operating system's random generator failed".to_string())?;
    Ok(b.iter().map(|x| format!("{x:02x}")).collect())
}

impl RunKey {
    /// A fresh random key.
    pub fn generate() -> Result<Self, String> {
        Self::from_hex(&random_hex(32)?)
    }

    /// The key from 64 hex digits (surrounding whitespace ignored).
    pub fn from_hex(text: &str) -> Result<Self, String> {
        let t = text.trim();
        if t.len() != 64 || !t.bytes().all(|c| c.is_ascii_hexdigit()) {
            return Err("a run key is 64 hex digits (32 bytes)".into());
        }
        let bytes: Vec<u8> = (0..32)
            .map(|i| u8::from_str_radix(&t[2 * i..2 * i + 2], 16).expect("hex"))
            .collect();
        Ok(RunKey {
            key: hmac::Key::new(hmac::HMAC_SHA256, &bytes),
            hex: t.to_ascii_lowercase(),
        })
    }

    /// The key of a worker: `CAVIAR_RUN_KEY`, else the file named by `CAVIAR_RUN_KEY_FILE`.
    pub fn from_env() -> Result<Self, String> {
        if let Ok(hex) = std::env::var(KEY_ENV) {
            return Self::from_hex(&hex).map_err(|e| format!("{KEY_ENV}: {e}"));
        }
        if let Ok(path) = std::env::var(KEY_FILE_ENV) {
            let text = std::fs::read_to_string(&path)
                .map_err(|e| format!("{KEY_FILE_ENV}={path}: {e}"))?;
            return Self::from_key_file_text(&text).map_err(|e| format!("{path}: {e}"));
        }
        Err(format!(
            "no run key: the core hands it to the workers it starts in {KEY_ENV}; \
             for a worker you start yourself set {KEY_FILE_ENV} to the run's key file \
             (the core prints its path)"
        ))
    }

    /// The run key in a key file: 64 hex digits, alone or as `CAVIAR_RUN_KEY=…` among
    /// other `NAME=value` lines (the `run.key` the core writes for hand-started workers).
    pub fn from_key_file_text(text: &str) -> Result<Self, String> {
        let line = text
            .lines()
            .map(str::trim)
            .find_map(|l| l.strip_prefix(&format!("{KEY_ENV}=")))
            .unwrap_or(text.trim());
        Self::from_hex(line)
    }

    pub fn hex(&self) -> &str {
        &self.hex
    }

    fn tag(&self, run: &str, subject: &str, seq: u64, body: &[u8]) -> hmac::Tag {
        let mut c = hmac::Context::with_key(&self.key);
        c.update(DOMAIN);
        for part in [run.as_bytes(), subject.as_bytes()] {
            c.update(&(part.len() as u64).to_le_bytes());
            c.update(part);
        }
        c.update(&seq.to_le_bytes());
        c.update(body);
        c.sign()
    }

    /// Appends the sequence number and the tag to `body`.
    pub fn seal(&self, run: &str, subject: &str, seq: u64, mut body: Vec<u8>) -> Vec<u8> {
        let tag = self.tag(run, subject, seq, &body);
        body.reserve(TRAILER);
        body.extend_from_slice(&seq.to_le_bytes());
        body.extend_from_slice(tag.as_ref());
        body
    }

    /// Checks the tag of a frame received on `subject`; returns its sequence number and body.
    pub fn open<'a>(
        &self,
        run: &str,
        subject: &str,
        frame: &'a [u8],
    ) -> Result<(u64, &'a [u8]), String> {
        if frame.len() < TRAILER {
            return Err(format!(
                "unauthenticated message on {subject} ({} bytes, no tag)",
                frame.len()
            ));
        }
        let (body, trailer) = frame.split_at(frame.len() - TRAILER);
        let seq = u64::from_le_bytes(trailer[..8].try_into().expect("8 bytes"));
        let expected = self.tag(run, subject, seq, body);
        let ok = constant_time_eq(expected.as_ref(), &trailer[8..]);
        if !ok {
            return Err(format!(
                "message on {subject} fails authentication (forged, altered, or meant for another subject or run)"
            ));
        }
        Ok((seq, body))
    }
}

/// Constant-time equality of two tags.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// Sequence numbers seen from one sender: each is accepted once, and none older than
/// [`WINDOW`] behind the newest.
#[derive(Debug, Default)]
pub struct SeqWindow {
    seen: BTreeSet<u64>,
    newest: u64,
}

impl SeqWindow {
    pub fn accept(&mut self, seq: u64) -> Result<(), String> {
        if seq == 0 {
            return Err("sequence number 0 is never sent".into());
        }
        if seq + WINDOW <= self.newest || self.seen.contains(&seq) {
            return Err(format!(
                "sequence number {seq} was already used (a replayed message)"
            ));
        }
        self.seen.insert(seq);
        if seq > self.newest {
            self.newest = seq;
            let floor = self.newest.saturating_sub(WINDOW);
            self.seen = self.seen.split_off(&floor);
        }
        Ok(())
    }
}

/// The steps a worker accepts: on its module's schedule (`offset`, then every
/// `every`-th), never one it already ran, and — when it is the module's only worker —
/// exactly the next one (each shard of a step once).
#[derive(Debug, Clone)]
pub struct StepGuard {
    every: u64,
    offset: u64,
    steps: Option<u64>,
    shards: u64,
    exclusive: bool,
    current: Option<u64>,
    shards_seen: BTreeSet<u64>,
}

impl StepGuard {
    pub fn new(every: u64, offset: u64, steps: Option<u64>, shards: u64, exclusive: bool) -> Self {
        StepGuard {
            every: every.max(1),
            offset,
            steps,
            shards: shards.max(1),
            exclusive,
            current: None,
            shards_seen: BTreeSet::new(),
        }
    }

    /// The steps before `next_step` count as run (a resumed run): the next one expected
    /// is the first on the schedule from `next_step`, and no earlier step is accepted.
    pub fn resume_at(&mut self, next_step: u64) {
        let first = if next_step <= self.offset {
            self.offset
        } else {
            self.offset + (next_step - self.offset).div_ceil(self.every) * self.every
        };
        if first >= self.offset + self.every {
            self.current = Some(first - self.every);
            self.shards_seen = (0..self.shards).collect();
        }
    }

    /// Accepts `step` (shard `shard`) or says why not; an accepted step is remembered.
    pub fn accept(&mut self, step: u64, shard: u64) -> Result<(), String> {
        let on_grid = step >= self.offset && (step - self.offset).is_multiple_of(self.every);
        if !on_grid {
            return Err(format!(
                "step {step} is not on this module's schedule (offset {}, every {})",
                self.offset, self.every
            ));
        }
        if self.steps.is_some_and(|n| step >= n) {
            return Err(format!(
                "step {step} is past the end of the episode ({} steps)",
                self.steps.unwrap_or(0)
            ));
        }
        if shard >= self.shards {
            return Err(format!(
                "shard {shard} of a module with {} shards",
                self.shards
            ));
        }
        let next = self.current.map_or(self.offset, |c| c + self.every);
        match self.current {
            Some(c) if step == c => {
                if !self.shards_seen.insert(shard) {
                    return Err(format!("step {step} shard {shard} was already run"));
                }
            }
            Some(c) if step < c => {
                return Err(format!("step {step} comes after step {c} (out of order)"));
            }
            _ => {
                if self.exclusive && step != next {
                    return Err(format!("step {step} is not the next step ({next})"));
                }
                self.current = Some(step);
                self.shards_seen.clear();
                self.shards_seen.insert(shard);
            }
        }
        Ok(())
    }
}

/// A worker's side: the run key, the core's sequence numbers seen, the worker's own
/// counter, the step schedule, and what was refused.
#[derive(Debug)]
pub struct Guard {
    pub key: RunKey,
    pub run: String,
    core_seqs: SeqWindow,
    own_seq: u64,
    steps: Option<StepGuard>,
    pub rejected: u64,
}

impl Guard {
    pub fn new(key: RunKey, run: &str) -> Self {
        Guard {
            key,
            run: run.into(),
            core_seqs: SeqWindow::default(),
            own_seq: 0,
            steps: None,
            rejected: 0,
        }
    }

    /// Seals a message of this worker for `subject`.
    pub fn seal(&mut self, subject: &str, body: Vec<u8>) -> Vec<u8> {
        self.own_seq += 1;
        self.key.seal(&self.run, subject, self.own_seq, body)
    }

    /// Verifies a frame of the core received on `subject`; counts a refusal.
    pub fn open<'a>(&mut self, subject: &str, frame: &'a [u8]) -> Result<&'a [u8], String> {
        let r = self
            .key
            .open(&self.run, subject, frame)
            .and_then(|(seq, body)| self.core_seqs.accept(seq).map(|_| body));
        if r.is_err() {
            self.rejected += 1;
        }
        r
    }

    /// The module's schedule, from its setup.
    pub fn schedule(
        &mut self,
        every: u64,
        offset: u64,
        steps: Option<u64>,
        shards: u64,
        exclusive: bool,
    ) {
        self.steps = Some(StepGuard::new(every, offset, steps, shards, exclusive));
    }

    /// A resumed run goes on at `next_step`: the steps before it count as run.
    pub fn resume_at(&mut self, next_step: u64) {
        if let Some(g) = self.steps.as_mut() {
            g.resume_at(next_step);
        }
    }

    /// Accepts a step (already authenticated) or counts a refusal.
    pub fn accept_step(&mut self, step: u64, shard: u64) -> Result<(), String> {
        let r = match self.steps.as_mut() {
            Some(g) => g.accept(step, shard),
            None => Err(format!("step {step} before setup")),
        };
        if r.is_err() {
            self.rejected += 1;
        }
        r
    }

    /// Counts a refusal decided elsewhere (a teardown without a reply subject).
    pub fn refuse(&mut self) {
        self.rejected += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sealed_frame_opens_only_on_its_run_and_subject_unaltered() {
        let k = RunKey::generate().unwrap();
        let f = k.seal("r", "caviar.r.m.step", 7, b"hello".to_vec());
        assert_eq!(
            k.open("r", "caviar.r.m.step", &f).unwrap(),
            (7, &b"hello"[..])
        );
        assert!(k.open("r", "caviar.r.other.step", &f).is_err());
        assert!(k.open("r2", "caviar.r.m.step", &f).is_err());
        let mut g = f.clone();
        g[0] ^= 1;
        assert!(k.open("r", "caviar.r.m.step", &g).is_err());
        let mut g = f.clone();
        g[5] ^= 1; // the sequence number
        assert!(k.open("r", "caviar.r.m.step", &g).is_err());
        assert!(k.open("r", "caviar.r.m.step", b"{}").is_err());
        let other = RunKey::generate().unwrap();
        assert!(other.open("r", "caviar.r.m.step", &f).is_err());
        assert!(RunKey::from_hex(k.hex())
            .unwrap()
            .open("r", "caviar.r.m.step", &f)
            .is_ok());
    }

    #[test]
    fn sequence_numbers_are_accepted_once_in_any_order_within_the_window() {
        let mut w = SeqWindow::default();
        for s in [2, 1, 3, 10] {
            w.accept(s).unwrap();
        }
        assert!(w.accept(3).is_err());
        assert!(w.accept(0).is_err());
        w.accept(10 + WINDOW).unwrap();
        assert!(w.accept(9).is_err(), "older than the window");
    }

    #[test]
    fn steps_follow_the_schedule() {
        let mut g = StepGuard::new(2, 1, Some(9), 1, true);
        assert!(g.accept(0, 0).is_err());
        g.accept(1, 0).unwrap();
        assert!(g.accept(1, 0).is_err(), "replayed");
        assert!(g.accept(5, 0).is_err(), "skipped step 3");
        g.accept(3, 0).unwrap();
        assert!(g.accept(1_000_000 + 1, 0).is_err());
        let mut g = StepGuard::new(1, 0, None, 3, false);
        g.accept(0, 2).unwrap();
        g.accept(0, 0).unwrap();
        assert!(g.accept(0, 0).is_err());
        g.accept(4, 1).unwrap(); // other workers took steps 1-3
        assert!(g.accept(2, 0).is_err());
        assert!(g.accept(5, 3).is_err(), "no shard 3");
    }

    #[test]
    fn a_resumed_schedule_expects_the_first_step_on_it_from_the_checkpoint() {
        // every 2 from 1: steps 1, 3, 5, 7; resumed at step 4, the next is 5.
        let mut g = StepGuard::new(2, 1, Some(9), 1, true);
        g.resume_at(4);
        assert!(g.accept(3, 0).is_err(), "before the checkpoint");
        assert!(g.accept(7, 0).is_err(), "skips step 5");
        g.accept(5, 0).unwrap();
        // Resumed at the very start: as a fresh schedule.
        let mut g = StepGuard::new(1, 0, None, 1, true);
        g.resume_at(0);
        g.accept(0, 0).unwrap();
    }
}
