//! Fuzzing of the parsers that take input from outside (issue #28): the wire frame
//! codec, the topic matcher, the TOML loader with `--set` overrides and the
//! run-directory reader. proptest generates their inputs, and mutates a corpus seeded
//! from the tests and the blueprints (flipped, inserted, deleted, duplicated and
//! truncated bytes). The property everywhere: no panic, no hang, and every rejection a
//! clean error that says what was wrong (and, for files, which file).
//!
//! Bounded by default: a fixed number of cases per target from a fixed seed, the same
//! cases on every run (a few seconds each in a debug build). Longer on demand:
//!
//! ```text
//! CAVIAR_FUZZ_SECONDS=300 cargo test --release --test fuzz -- --nocapture
//! ```
//!
//! runs each target for that long, on fresh seeds. `CAVIAR_FUZZ_REPORT=FILE` appends a
//! JSON line per target (cases, seconds, failures); `scripts/fuzz.sh` collects them in
//! `docs/results/reliability.json`.
//!
//! One test target (`--test fuzz`) whose modules are in `tests/fuzz/`: the harness and
//! the byte mutations the targets share, then one module per parser.

#[path = "fuzz/config_loader.rs"]
mod config_loader;
#[path = "fuzz/harness.rs"]
mod harness;
#[path = "fuzz/mutation.rs"]
mod mutation;
#[path = "fuzz/run_dir.rs"]
mod run_dir;
#[path = "fuzz/topic_matcher.rs"]
mod topic_matcher;
#[path = "fuzz/wire_frames.rs"]
mod wire_frames;
