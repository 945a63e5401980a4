//! Wall-clock pacing: a twin that runs beside its physical twin.
//!
//! With `episode.pace = p`, step k starts no earlier than t0 + k·Ts/p on the wall clock
//! (t0: when the first step could start, after every module's setup): `pace = 1` is real
//! time, 2 twice as fast. A step that starts after its slot is *late* (its predecessor
//! overran); what happens then is `episode.behind`:
//!
//! - `catch-up` (the default): the late steps run back to back, without waiting, until
//!   the run is on schedule again; no step is lost, every virtual instant is computed.
//! - `drop`: the steps whose whole slot has already passed are skipped (not run: no
//!   module steps, no messages for them; virtual time moves on), and the step of the
//!   current slot runs. Every skipped step is counted. It suits modules that read the
//!   step's time `t` or live inputs (telemetry): a module that advances a fixed amount
//!   per call (a flight's distance per step, SUMO's substeps) falls behind virtual time
//!   by the dropped steps.
//!
//! The lateness of every step (0 when on time) gives the report run.json and `inspect`
//! show: late steps, dropped steps, the worst and the 99th-percentile lateness.

use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

/// What to do when the run falls behind the wall clock (`episode.behind`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Behind {
    CatchUp,
    Drop,
}

impl Behind {
    pub const NAMES: [&'static str; 2] = ["catch-up", "drop"];

    pub fn parse(name: &str) -> Option<Self> {
        match name {
            "catch-up" => Some(Behind::CatchUp),
            "drop" => Some(Behind::Drop),
            _ => None,
        }
    }
}

/// A step starting up to this much after its slot is on time (the scheduler's jitter).
pub const ON_TIME: Duration = Duration::from_millis(1);

/// Longest single sleep: a Ctrl-C is noticed within it.
const SLEEP_CHUNK: Duration = Duration::from_millis(20);

/// The pacing of a run, as run.json reports it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PacingReport {
    pub pace: f64,
    pub behind: Behind,
    /// Steps run, each paced.
    pub steps: u64,
    /// Of them, those that started more than 1 ms after their slot.
    pub late_steps: u64,
    /// Steps skipped because their slot had passed (`behind = "drop"`).
    pub dropped_steps: u64,
    /// The largest lateness of a step, milliseconds.
    pub worst_late_ms: f64,
    /// The 99th percentile of the steps' lateness (on-time steps count as 0), ms.
    pub p99_late_ms: f64,
}

/// Paces the steps of one run; see the module documentation.
#[derive(Debug)]
pub struct Pacer {
    pace: f64,
    slot: Duration,
    behind: Behind,
    t0: Option<Instant>,
    lateness_s: Vec<f64>,
    late: u64,
    dropped: u64,
}

impl Pacer {
    /// `pace` > 0 (validated by the configuration), `ts` the step's virtual seconds.
    pub fn new(pace: f64, ts: f64, behind: Behind) -> Self {
        Pacer {
            pace,
            slot: Duration::from_secs_f64(ts / pace),
            behind,
            t0: None,
            lateness_s: Vec::new(),
            late: 0,
            dropped: 0,
        }
    }

    /// Before step `k` (after setup): waits for its slot, or, late under `drop`, returns
    /// how many steps to skip, at most `max_skip` (the episode's end: the step that runs is
    /// then `k + skipped`). `interrupted` is polled while waiting: true stops the wait.
    pub fn before_step(&mut self, k: u64, max_skip: u64, interrupted: &dyn Fn() -> bool) -> u64 {
        let now = Instant::now();
        let slot = self.slot;
        let t0 = *self
            .t0
            .get_or_insert_with(|| now.checked_sub(slot.mul_f64(k as f64)).unwrap_or(now));
        let due = |step: u64| t0 + slot.mul_f64(step as f64);
        if now < due(k) {
            sleep_until(due(k), interrupted);
            self.lateness_s.push(0.0);
            return 0;
        }
        let mut skip = 0;
        if self.behind == Behind::Drop && !slot.is_zero() {
            // Whole slots passed since step k's: those steps are dropped.
            skip = ((now - due(k)).as_secs_f64() / slot.as_secs_f64()).floor() as u64;
            skip = skip.min(max_skip);
            self.dropped += skip;
        }
        let late = now.saturating_duration_since(due(k + skip));
        if late > ON_TIME {
            self.late += 1;
        }
        self.lateness_s.push(late.as_secs_f64());
        skip
    }

    pub fn report(&self) -> PacingReport {
        let mut sorted = self.lateness_s.clone();
        sorted.sort_by(f64::total_cmp);
        let p99 = if sorted.is_empty() {
            0.0
        } else {
            // Nearest rank: the smallest value with at least 99 % of the steps at or below it.
            let rank = ((0.99 * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
            sorted[rank - 1]
        };
        PacingReport {
            pace: self.pace,
            behind: self.behind,
            steps: self.lateness_s.len() as u64,
            late_steps: self.late,
            dropped_steps: self.dropped,
            worst_late_ms: sorted.last().copied().unwrap_or(0.0) * 1e3,
            p99_late_ms: p99 * 1e3,
        }
    }
}

fn sleep_until(deadline: Instant, interrupted: &dyn Fn() -> bool) {
    loop {
        let now = Instant::now();
        if now >= deadline || interrupted() {
            return;
        }
        std::thread::sleep((deadline - now).min(SLEEP_CHUNK));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn on_time_steps_wait_for_their_slot() {
        let mut p = Pacer::new(1.0, 0.02, Behind::CatchUp);
        let start = Instant::now();
        for k in 0..5 {
            assert_eq!(p.before_step(k, u64::MAX, &|| false), 0);
        }
        // Step 4 starts 4 slots (80 ms) after step 0.
        let took = start.elapsed().as_secs_f64();
        assert!((0.079..0.5).contains(&took), "{took}");
        let r = p.report();
        assert_eq!((r.steps, r.late_steps, r.dropped_steps), (5, 0, 0));
    }

    #[test]
    fn catch_up_runs_late_steps_back_to_back_and_counts_them() {
        let mut p = Pacer::new(2.0, 0.04, Behind::CatchUp); // 20 ms slots
        assert_eq!(p.before_step(0, u64::MAX, &|| false), 0);
        std::thread::sleep(Duration::from_millis(70)); // step 0 overran 3.5 slots
        for k in 1..4 {
            assert_eq!(p.before_step(k, u64::MAX, &|| false), 0);
        }
        let r = p.report();
        assert_eq!(r.late_steps, 3, "{r:?}");
        assert!(r.worst_late_ms >= 50.0 && r.worst_late_ms < 150.0, "{r:?}");
        assert_eq!(r.dropped_steps, 0);
    }

    #[test]
    fn drop_skips_the_steps_whose_slot_passed() {
        let mut p = Pacer::new(1.0, 0.04, Behind::Drop);
        assert_eq!(p.before_step(0, u64::MAX, &|| false), 0);
        // Step 1's slot began at 40 ms: at 140 ms (±20 ms of jitter) 2.5 slots have passed.
        std::thread::sleep(Duration::from_millis(140));
        let skip = p.before_step(1, u64::MAX, &|| false);
        assert_eq!(
            skip, 2,
            "steps 1 and 2 dropped, step 3 runs late within its slot"
        );
        let r = p.report();
        assert_eq!(r.dropped_steps, 2);
        assert!(r.worst_late_ms < 40.0, "{r:?}");
    }

    #[test]
    fn drop_never_skips_past_the_episodes_end_and_measures_the_step_that_runs() {
        let mut p = Pacer::new(1.0, 0.04, Behind::Drop);
        p.before_step(0, u64::MAX, &|| false);
        std::thread::sleep(Duration::from_millis(140)); // 2.5 slots passed
        assert_eq!(
            p.before_step(1, 1, &|| false),
            1,
            "only one step was left to skip"
        );
        let r = p.report();
        assert_eq!(r.dropped_steps, 1);
        // Step 2 runs, late from its own slot (80 ms): about 60 ms.
        assert!(r.worst_late_ms > 40.0 && r.late_steps == 1, "{r:?}");
    }

    #[test]
    fn an_interrupt_ends_the_wait() {
        let mut p = Pacer::new(1.0, 10.0, Behind::CatchUp);
        p.before_step(0, u64::MAX, &|| false);
        let start = Instant::now();
        p.before_step(1, u64::MAX, &|| true);
        assert!(start.elapsed() < Duration::from_secs(1));
    }

    #[test]
    fn the_99th_percentile_is_the_nearest_rank() {
        let mut p = Pacer::new(1.0, 1.0, Behind::CatchUp);
        p.lateness_s = (1..=200).map(|i| i as f64 / 1000.0).collect();
        let r = p.report();
        assert!((r.p99_late_ms - 198.0).abs() < 1e-9, "{r:?}");
        assert!((r.worst_late_ms - 200.0).abs() < 1e-9);
    }
}
