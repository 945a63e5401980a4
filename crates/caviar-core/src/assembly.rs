//! Module assembly: from the `[modules.*]` tables to the engine's [`ModuleSpec`]s.
//!
//! Shared by the run (in-process modules) and the transports (modules in workers):
//! the names of the built-in plugins, the order, stage, period and subscriptions of
//! every module, and the checks of how modules connect (what `validate` warns about).

use crate::config::{ConfigError, LoadedConfig, ModuleConfig};
use crate::engine::{ModuleSpec, END_TOPIC};
use crate::module::AnyModule;
use crate::replay::{self, Replay};
use crate::topic::{validate_topic, Pattern};

/// `caviar.replay`: republishes topics of a recorded run ([`crate::replay`]).
pub const REPLAY_PLUGIN: &str = replay::PLUGIN;

/// True for a plugin the core provides itself, whatever the transport (no worker, no
/// Python). Transports may add their own (`crate::transport::Transport::builtin_plugins`).
pub fn is_builtin(plugin: &str) -> bool {
    plugin == REPLAY_PLUGIN
}

#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    #[error("{0}")]
    Config(#[from] ConfigError),
    #[error("{0}")]
    Io(String),
}

/// The modules of the configuration in its order, with their stage, period and
/// subscriptions: built-in replays here, every other module by `make` (`None`
/// leaves it out).
pub fn build_modules(
    cfg: &LoadedConfig,
    mut make: impl FnMut(&str, &ModuleConfig) -> Result<Option<AnyModule>, ConfigError>,
) -> Result<Vec<ModuleSpec>, ConfigError> {
    let mut specs = Vec::new();
    for (name, m) in &cfg.config.modules {
        let module = if m.plugin == REPLAY_PLUGIN {
            Some(AnyModule::local(Replay::from_config(cfg, name)?))
        } else {
            make(name, m)?
        };
        let Some(module) = module else { continue };
        specs.push(ModuleSpec {
            name: name.clone(),
            stage: m.stage.clone(),
            every: m.every,
            offset: m.offset,
            subscribe: m.subscribe.clone(),
            params: cfg.params_json(name),
            module,
        });
    }
    Ok(specs)
}

/// How one module connects: what it subscribes to and what it says it publishes.
pub(crate) struct Wiring {
    pub(crate) name: String,
    pub(crate) subscribe: Vec<String>,
    /// The subscriptions are the plugin's defaults (the table has no `subscribe`).
    default_subs: bool,
    /// Default subscriptions the plugin works without.
    optional: Vec<String>,
    /// `None`: not declared (the module may publish anything).
    pub(crate) publishes: Option<Vec<String>>,
}

/// What a module that was not built (it needs a live connection) declares publishing.
pub type Unbuilt<'a> = &'a dyn Fn(&str) -> Option<Vec<String>>;

pub(crate) fn wiring(cfg: &LoadedConfig, specs: &[ModuleSpec], unbuilt: Unbuilt) -> Vec<Wiring> {
    let mut out = Vec::new();
    for (name, m) in &cfg.config.modules {
        let spec = specs.iter().find(|s| s.name == *name);
        let (defaults, publishes, optional) = match spec {
            Some(s) => (
                s.module.default_subscriptions(),
                s.module.publishes(),
                s.module.optional_subscriptions(),
            ),
            None => (Vec::new(), unbuilt(name), Vec::new()),
        };
        out.push(Wiring {
            name: name.clone(),
            default_subs: m.subscribe.is_none(),
            optional,
            subscribe: m.subscribe.clone().unwrap_or(defaults),
            publishes,
        });
    }
    out
}

pub(crate) fn patterns(texts: &[String]) -> Vec<Pattern> {
    texts.iter().filter_map(|t| Pattern::new(t).ok()).collect()
}

/// Refuses a configuration with an input that modules' parameters name and no module
/// publishes ([`unfed_inputs`]): always an error, the first with the others appended.
pub fn refuse_unfed(
    cfg: &LoadedConfig,
    specs: &[ModuleSpec],
    unbuilt: Unbuilt,
) -> Result<(), ConfigError> {
    let mut errors = unfed_inputs(cfg, specs, unbuilt).into_iter();
    let Some(mut first) = errors.next() else {
        return Ok(());
    };
    for more in errors {
        first.message.push_str(&format!("\n  and {more}"));
    }
    Err(first)
}

/// Errors: an input that a module's parameters name (its [`AnyModule::required_inputs`])
/// and that no module declares publishing, each naming the key that asked for it (only when
/// every module declared what it publishes: one that did not may publish anything).
pub fn unfed_inputs(
    cfg: &LoadedConfig,
    specs: &[ModuleSpec],
    unbuilt: Unbuilt,
) -> Vec<ConfigError> {
    let modules = wiring(cfg, specs, unbuilt);
    if !modules.iter().all(|m| m.publishes.is_some()) {
        return Vec::new();
    }
    let published: Vec<(String, Pattern)> = modules
        .iter()
        .flat_map(|m| {
            patterns(m.publishes.as_deref().unwrap_or_default())
                .into_iter()
                .map(|p| (m.name.clone(), p))
        })
        .collect();
    let mut errors = Vec::new();
    for spec in specs {
        for (input, key) in spec.module.required_inputs() {
            let Ok(wanted) = Pattern::new(&input) else {
                continue;
            };
            if published
                .iter()
                .any(|(name, p)| *name != spec.name && p.overlaps(&wanted))
            {
                continue;
            }
            let key = format!("modules.{}.{key}", spec.name);
            errors.push(cfg.error_at(&key, format!("'{input}' — no other module publishes it")));
        }
    }
    errors
}

/// Warnings about how the modules connect, for `validate` and the start of `run` (not
/// errors, unless `episode.strict_wiring`: a module may well publish only for the
/// recording). `unbuilt`: what modules missing from `specs` publish.
///
/// * a subscription that no module declares publishing (only when every module
///   declared what it publishes: one that did not may publish anything);
/// * a declared publication that no module subscribes to, unless `output.analysis`
///   declares it recorded for analysis;
/// * an `output.analysis` pattern that matches no declared publication (only when every
///   module declared what it publishes).
pub fn wiring_warnings(cfg: &LoadedConfig, specs: &[ModuleSpec], unbuilt: Unbuilt) -> Vec<String> {
    let modules = wiring(cfg, specs, unbuilt);
    let mut warnings = Vec::new();
    let all_declared = modules.iter().all(|m| m.publishes.is_some());
    let published: Vec<Pattern> = modules
        .iter()
        .flat_map(|m| patterns(m.publishes.as_deref().unwrap_or_default()))
        .collect();
    let subscribed: Vec<Pattern> = modules
        .iter()
        .flat_map(|m| patterns(&m.subscribe))
        .collect();
    for m in &modules {
        if !all_declared {
            break;
        }
        for sub in patterns(&m.subscribe) {
            let optional = m.default_subs && m.optional.iter().any(|o| o == sub.as_str());
            if optional || sub.as_str() == END_TOPIC || published.iter().any(|p| p.overlaps(&sub)) {
                continue;
            }
            let default = if m.default_subs {
                " (the plugin's default)"
            } else {
                ""
            };
            let key = format!("modules.{}.subscribe", m.name);
            warnings.push(
                cfg.error_at(&key, format!("'{sub}'{default} — no module publishes it"))
                    .to_string(),
            );
        }
    }
    let exclude = patterns(&cfg.config.output.exclude);
    let analysis = patterns(&cfg.config.output.analysis);
    for m in &modules {
        for topic in patterns(m.publishes.as_deref().unwrap_or_default()) {
            let reserved = topic.as_str().starts_with("caviar.");
            let read = subscribed.iter().any(|s| s.overlaps(&topic));
            if reserved || read || analysis.iter().any(|a| a.overlaps(&topic)) {
                continue;
            }
            let excluded = validate_topic(topic.as_str()).is_ok()
                && exclude.iter().any(|e| e.matches(topic.as_str()));
            let fate = if excluded {
                "and output.exclude keeps it out of the recording"
            } else {
                "(recorded only)"
            };
            let key = format!("modules.{}", m.name);
            warnings.push(
                cfg.error_at(
                    &key,
                    format!("publishes '{topic}' — no module subscribes to it {fate}"),
                )
                .to_string(),
            );
        }
    }
    for a in analysis.iter().filter(|_| all_declared) {
        if !published.iter().any(|p| p.overlaps(a)) {
            warnings.push(
                cfg.error_at("output.analysis", format!("'{a}' — no module publishes it"))
                    .to_string(),
            );
        }
    }
    warnings
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::message::{Outgoing, SharedMessage};
    use crate::module::{Module, ModuleError, StepInfo};

    struct Fake {
        subscribe: Vec<String>,
        publishes: Option<Vec<String>>,
        optional: Vec<String>,
    }

    impl Module for Fake {
        fn default_subscriptions(&self) -> Vec<String> {
            self.subscribe.clone()
        }
        fn publishes(&self) -> Option<Vec<String>> {
            self.publishes.clone()
        }
        fn optional_subscriptions(&self) -> Vec<String> {
            self.optional.clone()
        }
        /// (a default subscription named "req.*" is an input its parameters name)
        fn required_inputs(&self) -> Vec<(String, String)> {
            self.subscribe
                .iter()
                .filter(|s| s.starts_with("req."))
                .map(|s| (s.clone(), "params.wants".to_string()))
                .collect()
        }
        fn step(
            &mut self,
            _: StepInfo,
            _: &[SharedMessage],
            _: &mut Vec<Outgoing>,
        ) -> Result<(), ModuleError> {
            Ok(())
        }
    }

    /// A module's name, default subscriptions and what it declares publishing.
    type FakeSpec<'a> = (&'a str, &'a [&'a str], Option<&'a [&'a str]>);

    /// Warnings of a config whose modules are `fakes`.
    fn warnings(text: &str, fakes: &[FakeSpec]) -> Vec<String> {
        let (cfg, specs) = fake_modules(text, fakes);
        wiring_warnings(&cfg, &specs, &|_| None)
    }

    fn fake_modules(text: &str, fakes: &[FakeSpec]) -> (LoadedConfig, Vec<ModuleSpec>) {
        let cfg =
            crate::config::parse(text, "config.toml", std::path::Path::new("."), &[]).unwrap();
        let strings = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let specs = build_modules(&cfg, |name, _| {
            let (_, subs, pubs) = fakes.iter().find(|f| f.0 == name).unwrap();
            Ok(Some(AnyModule::local(Fake {
                subscribe: strings(subs),
                publishes: pubs.map(strings),
                // (a default subscription named "opt.*" is an optional input)
                optional: strings(subs)
                    .into_iter()
                    .filter(|s| s.starts_with("opt."))
                    .collect(),
            })))
        })
        .unwrap();
        (cfg, specs)
    }

    #[test]
    fn an_input_the_parameters_name_that_no_other_module_publishes_is_an_error_naming_its_key() {
        let text = format!(
            "{HEAD}[modules.a]\nstage = \"s\"\nplugin = \"x\"\n\
             [modules.b]\nstage = \"s\"\nplugin = \"x\"\n"
        );
        let fed: &[FakeSpec] = &[
            ("a", &[], Some(&["req.one"])),
            ("b", &["req.*"], Some(&["req.two"])),
        ];
        let (cfg, specs) = fake_modules(&text, fed);
        assert!(refuse_unfed(&cfg, &specs, &|_| None).is_ok());
        // Its own publication does not feed it; the error names the module's key and line.
        let unfed: &[FakeSpec] = &[("a", &[], Some(&["x.one"])), fed[1]];
        let (cfg, specs) = fake_modules(&text, unfed);
        let e = refuse_unfed(&cfg, &specs, &|_| None).unwrap_err();
        assert_eq!(e.key.as_deref(), Some("modules.b.params.wants"));
        assert!(
            e.message.contains("'req.*' — no other module publishes it"),
            "{e}"
        );
        // A module that does not declare what it publishes may publish it: no error.
        let open: &[FakeSpec] = &[("a", &[], None), fed[1]];
        let (cfg, specs) = fake_modules(&text, open);
        assert!(refuse_unfed(&cfg, &specs, &|_| None).is_ok());
    }

    const HEAD: &str = "[episode]\nts = 1.0\nsteps = 1\nstages = [\"s\"]\n";

    #[test]
    fn subscriptions_nobody_publishes_and_publications_nobody_reads_are_warned_about() {
        let text = format!(
            "{HEAD}[modules.a]\nstage = \"s\"\nplugin = \"x\"\n\
             [modules.b]\nstage = \"s\"\nplugin = \"x\"\nsubscribe = [\"foo.bar\", \"a.*\"]\n"
        );
        let w = warnings(
            &text,
            &[
                ("a", &[], Some(&["a.one", "baz"])),
                ("b", &["ignored"], Some(&["caviar.episode.end"])),
            ],
        );
        assert_eq!(
            w,
            [
                "config.toml:11: modules.b.subscribe: 'foo.bar' — no module publishes it",
                "config.toml:5: modules.a: publishes 'baz' — no module subscribes to it (recorded only)",
            ]
        );
    }

    #[test]
    fn an_optional_input_nobody_publishes_is_not_warned_about_unless_the_user_asked_for_it() {
        let text = format!("{HEAD}[modules.a]\nstage = \"s\"\nplugin = \"x\"\n");
        let w = warnings(&text, &[("a", &["opt.hover", "needed"], Some(&[]))]);
        assert_eq!(
            w,
            ["config.toml:5: modules.a.subscribe: 'needed' (the plugin's default) — no module publishes it"]
        );
        let text = format!("{text}subscribe = [\"opt.hover\"]\n");
        let w = warnings(&text, &[("a", &["opt.hover", "needed"], Some(&[]))]);
        assert_eq!(
            w,
            ["config.toml:8: modules.a.subscribe: 'opt.hover' — no module publishes it"]
        );
    }

    #[test]
    fn topics_recorded_for_analysis_are_not_warned_about_and_a_stale_pattern_is() {
        let text = format!(
            "{HEAD}[output]\nanalysis = [\"report.*\", \"gone.>\"]\n\
             [modules.a]\nstage = \"s\"\nplugin = \"x\"\n"
        );
        let w = warnings(&text, &[("a", &[], Some(&["report.x", "other"]))]);
        assert_eq!(
            w,
            [
                "config.toml:7: modules.a: publishes 'other' — no module subscribes to it (recorded only)",
                "config.toml:6: output.analysis: 'gone.>' — no module publishes it",
            ]
        );
    }

    #[test]
    fn a_module_that_declares_nothing_may_publish_anything() {
        let text = format!(
            "{HEAD}[output]\nexclude = [\"debug.>\"]\n[modules.a]\nstage = \"s\"\nplugin = \"x\"\n\
             [modules.b]\nstage = \"s\"\nplugin = \"x\"\n"
        );
        // b declares nothing: its subscription may be fed by it, no warning for that.
        let w = warnings(
            &text,
            &[("a", &[], Some(&["debug.x"])), ("b", &["nobody.*"], None)],
        );
        assert_eq!(
            w,
            [
                "config.toml:7: modules.a: publishes 'debug.x' — no module subscribes to it \
              and output.exclude keeps it out of the recording"
            ]
        );
        let w = warnings(&text, &[("a", &["x.>"], None), ("b", &["nobody.*"], None)]);
        assert!(w.is_empty(), "{w:?}");
    }
}
