//! Transports: how modules that run outside this process take part in an episode.
//!
//! The interface is [`interface`] ([`Transport`], [`Connection`], [`Prepared`],
//! [`WorkerLauncher`]); this file is the registry: the transports this core has, by
//! `transport.kind`, and the checks of `[transport]` that do not depend on one.
//! Each transport is a folder of its own and a leaf of the crate: nothing outside
//! `transport/` names one. Adding a transport (shared memory, ZeroMQ, …) is a new
//! folder here that implements [`Transport`] and one line in `all()` below
//! (docs/architecture.md, "A transport").

pub mod interface;
pub mod nats;

pub use interface::{Connection, Prepared, Transport, WorkerLauncher};

use crate::config::{ConfigError, LoadedConfig, IN_PROCESS};

/// The bindings the transports' Python workers need, added to `caviar._core`.
#[cfg(feature = "python")]
pub fn register_python(m: &pyo3::Bound<'_, pyo3::types::PyModule>) -> pyo3::PyResult<()> {
    nats::python::register(m)
}

/// Every transport this core has, in-process excepted.
fn all() -> Vec<Box<dyn Transport>> {
    vec![Box::new(nats::Nats)]
}

/// The transport `kind` names; `None` for [`IN_PROCESS`] or an unknown name.
pub fn by_kind(kind: &str) -> Option<Box<dyn Transport>> {
    all().into_iter().find(|t| t.kind() == kind)
}

/// True for a built-in plugin of some transport (not loaded by the plugin host).
pub fn is_transport_builtin(plugin: &str) -> bool {
    all().iter().any(|t| t.builtin_plugins().contains(&plugin))
}

/// What module `name`, a transport's built-in that `validate` does not build, publishes.
pub fn builtin_publishes(cfg: &LoadedConfig, name: &str) -> Option<Vec<String>> {
    let plugin = &cfg.config.modules.get(name)?.plugin;
    all()
        .into_iter()
        .find(|t| t.builtin_plugins().contains(&plugin.as_str()))?
        .builtin_publishes(cfg, name)
}

/// Checks `[transport]`: a known `kind`, no section of an unknown transport, the chosen
/// transport's own section, and built-in plugins used only with their transport.
/// Returns the chosen transport (`None`: in-process).
pub fn check(cfg: &LoadedConfig) -> Result<Option<Box<dyn Transport>>, ConfigError> {
    let kind = cfg.transport_kind();
    let transports = all();
    let known: Vec<&str> = std::iter::once(IN_PROCESS)
        .chain(transports.iter().map(|t| t.kind()))
        .collect();
    if !known.contains(&kind) {
        return Err(cfg.error_at(
            "transport.kind",
            format!("unknown transport '{kind}', expected one of {known:?}"),
        ));
    }
    for key in cfg.config.transport.keys() {
        if key != "kind" && !transports.iter().any(|t| t.kind() == key) {
            return Err(cfg.error_at(
                &format!("transport.{key}"),
                format!(
                    "unknown key, expected `kind` or the section of a transport ({:?})",
                    &known[1..]
                ),
            ));
        }
    }
    for (name, m) in &cfg.config.modules {
        if let Some(owner) = transports
            .iter()
            .find(|t| t.builtin_plugins().contains(&m.plugin.as_str()))
        {
            if owner.kind() != kind {
                return Err(cfg.error_at(
                    &format!("modules.{name}.plugin"),
                    format!(
                        "'{}' needs the {} transport (transport.kind = \"{}\")",
                        m.plugin,
                        owner.kind(),
                        owner.kind()
                    ),
                ));
            }
        }
    }
    // A section is checked whether or not its transport runs: a typo in it is one either
    // way (and `transport.nats.step_timeout` applies in process too).
    for t in &transports {
        if t.kind() == kind || cfg.config.transport.contains_key(t.kind()) {
            t.check(cfg)?;
        }
    }
    Ok(transports.into_iter().find(|t| t.kind() == kind))
}

/// Seconds one module step may take, whatever the transport: `episode.step_timeout`, or
/// its older name in a transport's section (`transport.nats.step_timeout`), or 600.
pub fn step_timeout(cfg: &LoadedConfig) -> f64 {
    cfg.config
        .episode
        .step_timeout
        .or_else(|| {
            all()
                .iter()
                .filter(|t| cfg.config.transport.contains_key(t.kind()))
                .find_map(|t| t.step_timeout(cfg))
        })
        .unwrap_or(crate::config::DEFAULT_STEP_TIMEOUT)
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEAD: &str = "[episode]\nts = 1.0\nstages = [\"s\"]\n[modules.a]\nstage = \"s\"\n";

    fn checked(text: &str) -> Result<Option<&'static str>, ConfigError> {
        let cfg = crate::config::parse(text, "c.toml", std::path::Path::new("."), &[])?;
        check(&cfg).map(|t| t.map(|t| t.kind()))
    }

    #[test]
    fn the_kind_picks_a_transport_or_none() {
        let text = format!("{HEAD}plugin = \"x:Y\"\n");
        assert_eq!(checked(&text).unwrap(), None);
        let nats = format!("{text}[transport]\nkind = \"nats\"\n");
        assert_eq!(checked(&nats).unwrap(), Some("nats"));
    }

    #[test]
    fn unknown_kinds_and_sections_name_their_key_and_line() {
        let text = format!("{HEAD}plugin = \"x:Y\"\n[transport]\nkind = \"zmq\"\n");
        let err = checked(&text).unwrap_err();
        assert_eq!(
            (err.key.as_deref(), err.line),
            (Some("transport.kind"), Some(8))
        );
        assert!(
            err.message.contains("'zmq'") && err.message.contains("\"nats\""),
            "{err}"
        );
        let text = format!("{HEAD}plugin = \"x:Y\"\n[transport.zmq]\nport = 1\n");
        let err = checked(&text).unwrap_err();
        assert_eq!(err.key.as_deref(), Some("transport.zmq"), "{err}");
    }

    #[test]
    fn a_transport_built_in_needs_its_transport() {
        let text = format!("{HEAD}plugin = \"{}\"\n", nats::BRIDGE_PLUGIN);
        let err = checked(&text).unwrap_err();
        assert_eq!(err.key.as_deref(), Some("modules.a.plugin"));
        assert!(err.message.contains("needs the nats transport"), "{err}");
        assert!(is_transport_builtin(nats::BRIDGE_PLUGIN) && !is_transport_builtin("x:Y"));
    }

    #[test]
    fn a_section_is_checked_whether_or_not_its_transport_runs() {
        for (section, key) in [
            ("step_timout = 5", "transport.nats.step_timout"),
            ("step_timeout = 0", "transport.nats.step_timeout"),
            ("mirror = [\"a..b\"]", "transport.nats.mirror"),
        ] {
            let text = format!("{HEAD}plugin = \"x:Y\"\n[transport.nats]\n{section}\n");
            let err = checked(&text).unwrap_err();
            assert_eq!(
                (err.key.as_deref(), err.line),
                (Some(key), Some(8)),
                "{err}"
            );
        }
        // The older name of episode.step_timeout applies in process too.
        let text = format!("{HEAD}plugin = \"x:Y\"\n[transport.nats]\nstep_timeout = 5\n");
        assert_eq!(checked(&text).unwrap(), None);
        let cfg = crate::config::parse(&text, "c.toml", std::path::Path::new("."), &[]).unwrap();
        assert_eq!(step_timeout(&cfg), 5.0);
        let plain = format!("{HEAD}plugin = \"x:Y\"\n");
        let cfg = crate::config::parse(&plain, "c.toml", std::path::Path::new("."), &[]).unwrap();
        assert_eq!(step_timeout(&cfg), crate::config::DEFAULT_STEP_TIMEOUT);
    }

    #[test]
    fn the_transport_reads_its_own_section() {
        let text =
            format!("{HEAD}plugin = \"x:Y\"\n[transport]\nkind = \"nats\"\n[transport.nats]\nheartbeat_timeout = -1\n");
        let err = checked(&text).unwrap_err();
        assert_eq!(
            (err.key.as_deref(), err.line),
            (Some("transport.nats.heartbeat_timeout"), Some(10))
        );
        let text = format!("{HEAD}plugin = \"x:Y\"\n[transport]\nkind = \"nats\"\n[transport.nats]\nspawn = \"yes\"\n");
        let err = checked(&text).unwrap_err();
        assert_eq!(err.key.as_deref(), Some("transport.nats.spawn"), "{err}");
        assert!(err.message.contains("invalid type"), "{err}");
    }
}
