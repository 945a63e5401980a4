//! CPU accounting of in-process modules that keep threads of their own busy. Its own
//! test binary: the engine reads the process's CPU clock, which other tests running
//! beside it in one process would move.

use caviar_core::recorder::{read_timings, Recorder};
use caviar_core::{
    AnyModule, Engine, EngineOptions, Module, ModuleError, ModuleSpec, Outgoing, SharedMessage,
    StepInfo,
};

/// Burns `own` of CPU on the thread that runs its step and `helper` on a thread it starts.
struct Burner {
    own: f64,
    helper: f64,
}

fn thread_cpu() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes into the timespec we own.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

fn burn(seconds: f64) {
    let start = thread_cpu();
    while thread_cpu() - start < seconds {
        std::hint::spin_loop();
    }
}

impl Module for Burner {
    fn step(
        &mut self,
        _: StepInfo,
        _: &[SharedMessage],
        _: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        let helper = self.helper;
        let thread = std::thread::spawn(move || burn(helper));
        burn(self.own);
        thread.join().unwrap();
        Ok(())
    }
}

#[test]
fn cpu_time_includes_the_threads_a_module_keeps_busy() {
    let dir = tempfile::tempdir().unwrap();
    let module = |name: &str, stage: &str, own: f64, helper: f64| ModuleSpec {
        subscribe: Some(vec![]),
        ..ModuleSpec::new(name, stage, AnyModule::local(Burner { own, helper }))
    };
    let opts = EngineOptions {
        ts: 0.5,
        steps: Some(1),
        seed: 1,
        stages: vec!["a".into(), "b".into(), "c".into()],
        run_dir: dir.path().to_path_buf(),
        config_dir: dir.path().to_path_buf(),
    };
    let recorder = Recorder::create(dir.path(), vec![], std::time::Duration::ZERO).unwrap();
    let modules = vec![
        module("pool-user", "a", 0.0, 0.08),
        module("idle", "b", 0.0, 0.0),
        module("mixed", "c", 0.03, 0.06),
        module("plain", "c", 0.03, 0.0),
    ];
    let mut e = Engine::new(opts, modules, Some(recorder)).unwrap();
    e.run(|_, _| true).unwrap();
    e.close().unwrap();
    let t = read_timings(dir.path()).unwrap();
    let cpu = |m: &str| t.iter().find(|r| r.module == m).unwrap().cpu_s;
    // Alone in its stage, a module is charged its helper thread's 80 ms.
    assert!(
        (0.08..0.095).contains(&cpu("pool-user")),
        "{}",
        cpu("pool-user")
    );
    assert!(cpu("idle") < 0.01, "{}", cpu("idle"));
    // Two side by side: the 60 ms no thread of theirs accounts for is shared by their
    // own CPU time (30 ms each), and the stage's 120 ms are all charged.
    let (mixed, plain) = (cpu("mixed"), cpu("plain"));
    assert!(
        (0.12..0.135).contains(&(mixed + plain)),
        "{mixed} + {plain}"
    );
    assert!((mixed - plain).abs() < 0.02, "{mixed} vs {plain}");
}
