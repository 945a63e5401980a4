//! Engine benchmarks: router throughput, barrier latency, recorder cost.
//!
//! cargo bench -p caviar-core --bench router
//!
//! Barrier latency is the time of one step of an engine whose modules do nothing:
//! the cost of running a stage and waiting for all of its modules.

use std::time::Duration;

use caviar_core::recorder::Recorder;
use caviar_core::{
    Engine, EngineOptions, Module, ModuleError, ModuleSpec, Outgoing, Payload, SharedMessage,
    StepInfo,
};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};

struct Noop;

impl Module for Noop {
    fn step(
        &mut self,
        _: StepInfo,
        _: &[SharedMessage],
        _: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        Ok(())
    }
}

/// Like Noop but runs on the calling thread, as Python plugins do.
struct SerialNoop;

impl Module for SerialNoop {
    fn step(
        &mut self,
        _: StepInfo,
        _: &[SharedMessage],
        _: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        Ok(())
    }
    fn concurrent(&self) -> bool {
        false
    }
}

struct Publisher {
    per_step: usize,
}

impl Module for Publisher {
    fn step(
        &mut self,
        at: StepInfo,
        _: &[SharedMessage],
        out: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        for i in 0..self.per_step {
            let topic = if i % 2 == 0 {
                "3D.mobility.positions"
            } else {
                "communications.throughput"
            };
            out.push(Outgoing::new(
                topic,
                Payload::Json(format!(
                    r#"{{"UE_type":"UAV","UE_Id":"uav{i}","step":{}}}"#,
                    at.step
                )),
            ));
        }
        Ok(())
    }
}

struct Sink;

impl Module for Sink {
    fn default_subscriptions(&self) -> Vec<String> {
        vec!["3D.mobility.*".into(), "communications.>".into()]
    }
    fn step(
        &mut self,
        _: StepInfo,
        inbox: &[SharedMessage],
        _: &mut Vec<Outgoing>,
    ) -> Result<(), ModuleError> {
        std::hint::black_box(inbox.len());
        Ok(())
    }
}

fn engine(
    stages: &[&str],
    modules: Vec<(String, &str, Box<dyn Module>)>,
    recorder: Option<Recorder>,
) -> Engine {
    let opts = EngineOptions {
        ts: 0.1,
        steps: None,
        seed: 0,
        stages: stages.iter().map(|s| s.to_string()).collect(),
        run_dir: std::env::temp_dir(),
        config_dir: std::env::temp_dir(),
    };
    let specs = modules
        .into_iter()
        .map(|(name, stage, module)| ModuleSpec::new(name, stage, module))
        .collect();
    Engine::new(opts, specs, recorder).unwrap()
}

fn barrier(c: &mut Criterion) {
    let mut g = c.benchmark_group("barrier");
    for n in [1usize, 10, 100] {
        let mods = (0..n)
            .map(|i| (format!("m{i}"), "s", Box::new(Noop) as Box<dyn Module>))
            .collect();
        let mut e = engine(&["s"], mods, None);
        g.bench_with_input(BenchmarkId::new("concurrent_modules", n), &n, |b, _| {
            b.iter(|| e.step().unwrap())
        });
        let mods = (0..n)
            .map(|i| {
                (
                    format!("m{i}"),
                    "s",
                    Box::new(SerialNoop) as Box<dyn Module>,
                )
            })
            .collect();
        let mut e = engine(&["s"], mods, None);
        g.bench_with_input(BenchmarkId::new("serial_modules", n), &n, |b, _| {
            b.iter(|| e.step().unwrap())
        });
    }
    g.finish();
}

fn router(c: &mut Criterion) {
    let mut g = c.benchmark_group("router");
    for subscribers in [1usize, 10] {
        let per_step = 1000;
        let mut mods: Vec<(String, &str, Box<dyn Module>)> =
            vec![("pub".into(), "a", Box::new(Publisher { per_step }))];
        mods.extend(
            (0..subscribers).map(|i| (format!("sink{i}"), "b", Box::new(Sink) as Box<dyn Module>)),
        );
        let mut e = engine(&["a", "b"], mods, None);
        g.throughput(Throughput::Elements(per_step as u64));
        g.bench_with_input(
            BenchmarkId::new("messages_to_subscribers", subscribers),
            &subscribers,
            |b, _| b.iter(|| e.step().unwrap()),
        );
    }
    g.finish();
}

fn recorder(c: &mut Criterion) {
    // A quickstart-like step: 3 modules, 3 small messages; recording flushed every step
    // (the default) or batched (output.flush_interval).
    let mut g = c.benchmark_group("recorded_step");
    g.measurement_time(Duration::from_secs(5));
    for (label, interval) in [
        ("flush_every_step", Duration::ZERO),
        ("flush_every_second", Duration::from_secs(1)),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let rec = Recorder::create(dir.path(), vec![], interval).unwrap();
        let mods: Vec<(String, &str, Box<dyn Module>)> = vec![
            ("pub".into(), "a", Box::new(Publisher { per_step: 3 })),
            ("sink".into(), "b", Box::new(Sink)),
        ];
        let mut e = engine(&["a", "b"], mods, Some(rec));
        g.bench_function(label, |b| b.iter(|| e.step().unwrap()));
        drop(e);
    }
    g.finish();
}

criterion_group!(benches, barrier, router, recorder);
criterion_main!(benches);
