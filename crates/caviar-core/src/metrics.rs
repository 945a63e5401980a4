//! Process metrics: CPU time of a thread and of the whole process, resident memory,
//! and the charging of helper threads' CPU time to the modules that caused it.
//!
//! A leaf: it uses nothing of the crate. The engine measures in-process modules with
//! it, the NATS worker measures the module it hosts.

/// CPU time of the calling thread, in seconds.
pub fn thread_cpu_seconds() -> f64 {
    cpu_clock(libc::CLOCK_THREAD_CPUTIME_ID)
}

/// CPU time of all threads of this process, in seconds.
pub fn process_cpu_seconds() -> f64 {
    cpu_clock(libc::CLOCK_PROCESS_CPUTIME_ID)
}

fn cpu_clock(clock: libc::clockid_t) -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes into the timespec we own.
    unsafe { libc::clock_gettime(clock, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// Resident set size of this process in MiB (Linux; NaN elsewhere).
pub fn resident_mib() -> f64 {
    use std::os::unix::fs::FileExt;
    use std::sync::OnceLock;
    // Opened once and read with pread: one system call per reading (open + read + close
    // cost about 6 µs, three times per step).
    static STATM: OnceLock<Option<(std::fs::File, f64)>> = OnceLock::new();
    let Some((file, page_mib)) = STATM.get_or_init(|| {
        // SAFETY: sysconf has no preconditions.
        let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) } as f64;
        std::fs::File::open("/proc/self/statm")
            .ok()
            .map(|f| (f, page / (1024.0 * 1024.0)))
    }) else {
        return f64::NAN;
    };
    let mut buf = [0u8; 128];
    let Ok(n) = file.read_at(&mut buf, 0) else {
        return f64::NAN;
    };
    let pages = std::str::from_utf8(&buf[..n]).ok().and_then(|t| {
        t.split_whitespace()
            .nth(1)
            .and_then(|v| v.parse::<f64>().ok())
    });
    pages.map_or(f64::NAN, |p| p * page_mib)
}

/// Work that a module hands to threads of its own (Dr.Jit's pool, a plugin's thread
/// pool) does not show on the thread that ran its step. The process's CPU time over the
/// stage beyond what the in-process modules' own threads used is therefore shared among
/// them, in proportion to their own CPU time (their wall time where that is all zero):
/// a module alone in its stage is charged the process's CPU time of its step.
///
/// `local`: each in-process module's CPU seconds (raised in place) and wall seconds.
/// Remote modules report their own process's time and are not passed here.
pub fn charge_helper_threads<'a>(
    local: impl IntoIterator<Item = (&'a mut f64, f64)>,
    process_cpu_s: f64,
) {
    let mut local: Vec<(&mut f64, f64)> = local.into_iter().collect();
    let own: f64 = local.iter().map(|(cpu, _)| **cpu).sum();
    let extra = process_cpu_s - own;
    if local.is_empty() || extra <= 0.0 {
        return;
    }
    let by_cpu = own > 0.0;
    let total = if by_cpu {
        own
    } else {
        local.iter().map(|(_, wall)| wall).sum()
    };
    let count = local.len() as f64;
    for (cpu, wall) in local.iter_mut() {
        let weight = if by_cpu { **cpu } else { *wall };
        **cpu += if total > 0.0 {
            extra * weight / total
        } else {
            extra / count
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn helper_threads_are_charged_in_proportion_to_own_cpu_then_wall() {
        let (mut a, mut b) = (1.0, 3.0);
        charge_helper_threads([(&mut a, 0.5), (&mut b, 0.5)], 8.0);
        assert_eq!((a, b), (2.0, 6.0));
        let (mut a, mut b) = (0.0, 0.0);
        charge_helper_threads([(&mut a, 1.0), (&mut b, 3.0)], 4.0);
        assert_eq!((a, b), (1.0, 3.0));
        let mut a = 5.0;
        charge_helper_threads([(&mut a, 1.0)], 2.0);
        assert_eq!(a, 5.0, "never less than the module's own time");
    }

    #[test]
    fn clocks_and_memory_read_something() {
        assert!(process_cpu_seconds() >= thread_cpu_seconds() - 1e-6);
        assert!(resident_mib() > 0.0);
    }
}
