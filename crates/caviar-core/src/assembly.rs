//! Module assembly: from the `[modules.*]` tables to the engine's [`ModuleSpec`]s.
//!
//! Shared by the run (in-process modules) and the transports (modules in workers):
//! the names of the built-in plugins, the order, stage, period and subscriptions of
//! every module, and the checks of how modules connect (what `validate` warns about).

use crate::config::{ConfigError, LoadedConfig, ModuleConfig, TransportKind};
use crate::engine::{ModuleSpec, END_TOPIC};
use crate::module::AnyModule;
use crate::replay::{self, Replay};
use crate::topic::{validate_topic, Pattern};

/// `caviar.replay`: republishes topics of a recorded run ([`crate::replay`]).
pub const REPLAY_PLUGIN: &str = replay::PLUGIN;

/// `caviar.nats-bridge`: brings plain NATS messages into the episode (NATS transport).
pub const BRIDGE_PLUGIN: &str = "caviar.nats-bridge";

/// True for a plugin the core provides itself (no worker, no Python).
pub fn is_builtin(plugin: &str) -> bool {
    plugin == REPLAY_PLUGIN || plugin == BRIDGE_PLUGIN
}

#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    #[error("{0}")]
    Config(#[from] ConfigError),
    #[error("{0}")]
    Io(String),
}

/// Built-in plugins that need what the configuration does not give them.
fn check_builtins(cfg: &LoadedConfig) -> Result<(), ConfigError> {
    let nats = cfg.config.transport.kind == TransportKind::Nats;
    for (name, m) in &cfg.config.modules {
        if m.plugin == BRIDGE_PLUGIN && !nats {
            return Err(cfg.error_at(
                &format!("modules.{name}.plugin"),
                "the NATS bridge needs the NATS transport (transport.kind = \"nats\")",
            ));
        }
    }
    Ok(())
}

/// The modules of the configuration in its order, with their stage, period and
/// subscriptions: built-in replays here, every other module by `make` (`None`
/// leaves it out).
pub fn build_modules(
    cfg: &LoadedConfig,
    mut make: impl FnMut(&str, &ModuleConfig) -> Result<Option<AnyModule>, ConfigError>,
) -> Result<Vec<ModuleSpec>, ConfigError> {
    check_builtins(cfg)?;
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
struct Wiring {
    name: String,
    subscribe: Vec<String>,
    /// The subscriptions are the plugin's defaults (the table has no `subscribe`).
    default_subs: bool,
    /// `None`: not declared (the module may publish anything).
    publishes: Option<Vec<String>>,
}

fn wiring(cfg: &LoadedConfig, specs: &[ModuleSpec]) -> Vec<Wiring> {
    let mut out = Vec::new();
    for (name, m) in &cfg.config.modules {
        let spec = specs.iter().find(|s| s.name == *name);
        let (defaults, publishes) = match spec {
            Some(s) => (s.module.default_subscriptions(), s.module.publishes()),
            // Not built without a live connection: the bridge publishes its subjects.
            None if m.plugin == BRIDGE_PLUGIN => (
                Vec::new(),
                serde_json::from_value(cfg.params_json(name)["subjects"].clone()).ok(),
            ),
            None => (Vec::new(), None),
        };
        out.push(Wiring {
            name: name.clone(),
            default_subs: m.subscribe.is_none(),
            subscribe: m.subscribe.clone().unwrap_or(defaults),
            publishes,
        });
    }
    out
}

fn patterns(texts: &[String]) -> Vec<Pattern> {
    texts.iter().filter_map(|t| Pattern::new(t).ok()).collect()
}

/// Warnings about how the modules connect, for `validate` (not errors: a module may
/// well publish only for the recording):
///
/// * a subscription that no module declares publishing (only when every module
///   declared what it publishes: one that did not may publish anything);
/// * a declared publication that no module subscribes to.
pub fn wiring_warnings(cfg: &LoadedConfig, specs: &[ModuleSpec]) -> Vec<String> {
    let modules = wiring(cfg, specs);
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
            if sub.as_str() == END_TOPIC || published.iter().any(|p| p.overlaps(&sub)) {
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
    for m in &modules {
        for topic in patterns(m.publishes.as_deref().unwrap_or_default()) {
            let reserved = topic.as_str().starts_with("caviar.");
            if reserved || subscribed.iter().any(|s| s.overlaps(&topic)) {
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
    }

    impl Module for Fake {
        fn default_subscriptions(&self) -> Vec<String> {
            self.subscribe.clone()
        }
        fn publishes(&self) -> Option<Vec<String>> {
            self.publishes.clone()
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
        let cfg =
            crate::config::parse(text, "config.toml", std::path::Path::new("."), &[]).unwrap();
        let strings = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let specs = build_modules(&cfg, |name, _| {
            let (_, subs, pubs) = fakes.iter().find(|f| f.0 == name).unwrap();
            Ok(Some(AnyModule::local(Fake {
                subscribe: strings(subs),
                publishes: pubs.map(strings),
            })))
        })
        .unwrap();
        wiring_warnings(&cfg, &specs)
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

    #[test]
    fn the_bridge_needs_the_nats_transport() {
        let text = format!("{HEAD}[modules.a]\nstage = \"s\"\nplugin = \"{BRIDGE_PLUGIN}\"\n");
        let cfg = crate::config::parse(&text, "c.toml", std::path::Path::new("."), &[]).unwrap();
        let err = build_modules(&cfg, |_, _| Ok(None)).err().unwrap();
        assert_eq!(err.key.as_deref(), Some("modules.a.plugin"));
        assert!(err.message.contains("needs the NATS transport"), "{err}");
    }
}
