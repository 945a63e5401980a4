//! Ctrl-C as a flag every layer can poll: the engine between and after module steps,
//! the NATS transport while it waits for a step's replies.
//!
//! `caviar-core run` installs its own SIGINT handler for the run ([`Guard`]): a Ctrl-C
//! sets the flag instead of raising `KeyboardInterrupt` in whatever Python code
//! happens to run (which would be blamed on a module). A host that keeps Python's
//! handler (the `Simulation` API) calls [`request`] when a plugin raised
//! `KeyboardInterrupt`. Either way the run ends as `interrupted` (exit 130).

use std::sync::atomic::{AtomicU32, Ordering};

static COUNT: AtomicU32 = AtomicU32::new(0);

/// Ctrl-C presses since [`reset`].
pub fn count() -> u32 {
    COUNT.load(Ordering::Relaxed)
}

/// True once Ctrl-C was pressed (or [`request`] called) since [`reset`].
pub fn requested() -> bool {
    count() > 0
}

/// Asks the run to stop, as a Ctrl-C would.
pub fn request() {
    COUNT.fetch_add(1, Ordering::Relaxed);
}

/// Forgets earlier requests (at the start of a run).
pub fn reset() {
    COUNT.store(0, Ordering::Relaxed);
}

extern "C" fn on_sigint(_: libc::c_int) {
    // Async-signal-safe: one atomic add.
    COUNT.fetch_add(1, Ordering::Relaxed);
}

/// While alive, SIGINT sets the flag; dropping it restores the previous handler.
pub struct Guard {
    previous: libc::sigaction,
}

impl Guard {
    pub fn install() -> Guard {
        reset();
        // SAFETY: plain sigaction calls with zeroed, then filled, structs.
        unsafe {
            let mut action: libc::sigaction = std::mem::zeroed();
            action.sa_sigaction = on_sigint as *const () as libc::sighandler_t;
            action.sa_flags = libc::SA_RESTART;
            libc::sigemptyset(&mut action.sa_mask);
            let mut previous: libc::sigaction = std::mem::zeroed();
            libc::sigaction(libc::SIGINT, &action, &mut previous);
            Guard { previous }
        }
    }
}

impl Drop for Guard {
    fn drop(&mut self) {
        // SAFETY: restores the handler saved by `install`.
        unsafe {
            libc::sigaction(libc::SIGINT, &self.previous, std::ptr::null_mut());
        }
    }
}
