//! Whether the process that wrote a run.json still runs: its pid alive, not a zombie,
//! and started when run.json says (a pid is reused, the pair is not), from /proc.

/// Whether the process `pid` that started at `start` (when known) still runs: a live
/// process under that pid that started at another time is a later one (the pid reused).
/// A zombie (ended, not yet reaped by its parent) is not alive.
pub(super) fn same_process_alive(pid: u32, start: Option<u64>) -> bool {
    process_alive(pid)
        && proc_stat_field(pid, 3).as_deref() != Some("Z")
        && match (start, process_start(pid)) {
            (Some(then), Some(now)) => then == now,
            _ => true,
        }
}

/// When process `pid` started, in clock ticks after boot (field 22 of /proc/PID/stat;
/// `None` where there is no /proc).
pub(super) fn process_start(pid: u32) -> Option<u64> {
    proc_stat_field(pid, 22)?.parse().ok()
}

/// Field `n` (1-based, as proc(5) numbers them, from 3 on) of /proc/PID/stat.
fn proc_stat_field(pid: u32, n: usize) -> Option<String> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Field 2, the command, is in parentheses and may hold spaces: fields 3.. follow the last ')'.
    let rest = &stat[stat.rfind(')')? + 1..];
    rest.split_whitespace().nth(n - 3).map(String::from)
}

/// Whether process `pid` exists (signal 0: permission denied still means it does).
fn process_alive(pid: u32) -> bool {
    // SAFETY: kill with signal 0 only checks.
    let r = unsafe { libc::kill(pid as libc::pid_t, 0) };
    r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}
