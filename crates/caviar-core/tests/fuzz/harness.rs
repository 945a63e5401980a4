//! The harness: proptest's runner, counted, bounded, watched for hangs.

use std::fmt::Debug;
use std::fs;
use std::io::Write;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestCaseError, TestRng, TestRunner};

/// One case running longer than this is a hang: the process says which and aborts.
const HANG: Duration = Duration::from_secs(20);

/// The case in progress, for the hang watch.
#[derive(Default)]
struct Current {
    since: Option<Instant>,
    input: String,
}

/// Runs `check` on inputs from `strategy`: `cases` of them from a fixed seed, or, with
/// `CAVIAR_FUZZ_SECONDS`, fresh seeds for that long. A failing case (an `Err` or a
/// panic) is shrunk by proptest and reported with the target's name.
pub(crate) fn fuzz<S>(
    target: &str,
    cases: u32,
    strategy: S,
    check: impl Fn(S::Value) -> Result<(), TestCaseError>,
) where
    S: Strategy,
    S::Value: Debug,
{
    let seconds: Option<f64> = std::env::var("CAVIAR_FUZZ_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok());
    let started = Instant::now();
    let count = AtomicU64::new(0);
    let current = Arc::new(Mutex::new(Current::default()));
    let done = Arc::new(AtomicBool::new(false));
    let watch = {
        let (current, done, target) = (current.clone(), done.clone(), target.to_string());
        std::thread::spawn(move || {
            while !done.load(Ordering::Relaxed) {
                std::thread::sleep(Duration::from_millis(200));
                let c = current.lock().unwrap_or_else(|p| p.into_inner());
                if c.since.is_some_and(|t| t.elapsed() > HANG) {
                    eprintln!(
                        "fuzz {target}: a case ran for more than {} s (a hang) on input:\n{}",
                        HANG.as_secs(),
                        c.input
                    );
                    std::process::abort();
                }
            }
        })
    };
    let mut round = 0u64;
    let result = loop {
        let config = Config {
            cases: if seconds.is_some() { 2000 } else { cases },
            failure_persistence: None,
            max_shrink_iters: 4096,
            ..Config::default()
        };
        let rng = match seconds {
            None => TestRng::deterministic_rng(RngAlgorithm::ChaCha),
            Some(_) => {
                let nanos = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_nanos() as u64);
                let mut seed = [0u8; 32];
                seed[..8].copy_from_slice(&nanos.to_le_bytes());
                seed[8..16].copy_from_slice(&round.to_le_bytes());
                TestRng::from_seed(RngAlgorithm::ChaCha, &seed)
            }
        };
        let mut runner = TestRunner::new_with_rng(config, rng);
        let outcome = runner.run(&strategy, |value| {
            count.fetch_add(1, Ordering::Relaxed);
            {
                let mut c = current.lock().unwrap_or_else(|p| p.into_inner());
                c.input = format!("{value:.2000?}");
                c.since = Some(Instant::now());
            }
            let r = check(value);
            current.lock().unwrap_or_else(|p| p.into_inner()).since = None;
            r
        });
        round += 1;
        match seconds {
            Some(s) if outcome.is_ok() && started.elapsed().as_secs_f64() < s => continue,
            _ => break outcome,
        }
    };
    done.store(true, Ordering::Relaxed);
    let _ = watch.join();
    let cases = count.load(Ordering::Relaxed);
    let elapsed = started.elapsed().as_secs_f64();
    eprintln!(
        "fuzz {target}: {cases} cases in {elapsed:.1} s, {}",
        if result.is_ok() {
            "no failure"
        } else {
            "FAILED"
        }
    );
    if let Ok(path) = std::env::var("CAVIAR_FUZZ_REPORT") {
        let line = serde_json::json!({
            "target": target, "cases": cases, "seconds": elapsed,
            "failures": u32::from(result.is_err()),
        });
        if let Ok(mut f) = fs::OpenOptions::new().create(true).append(true).open(path) {
            let _ = writeln!(f, "{line}");
        }
    }
    if let Err(e) = result {
        panic!("fuzz {target}: {e}");
    }
}
