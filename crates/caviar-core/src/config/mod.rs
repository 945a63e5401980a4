//! The experiment description: one TOML file.
//!
//! ```toml
//! [episode]
//! ts = 0.1                 # sampling interval Ts, seconds of virtual time
//! duration = 60.0          # or `steps = 600`; neither: until a module ends the episode
//! seed = 7
//! stages = ["mobility", "communications", "ai"]
//! step_timeout = 600.0     # s one module step may take, any transport (default 600)
//! setup_timeout = 600.0    # s one module's setup or teardown may take, in process (default 600)
//!
//! [output]
//! checkpoint_every = 100   # steps between checkpoints for `run --resume` (default 100; 0: none)
//! checkpoint_interval_s = 60.0  # or sooner, after this much wall time (default 60; 0: by steps only)
//! pace = 1.0               # wall-clock pacing (1: real time); absent: as fast as possible
//! behind = "catch-up"      # or "drop": what a paced run does when it falls behind
//!
//! [modules.uav]
//! stage = "mobility"
//! plugin = "caviar_plugins.mobility:WaypointFlight"   # or an entry-point name
//! every = 1                # run every k-th step (default 1), starting at `offset`
//! subscribe = ["mission.>"]
//! [modules.uav.params]     # the plugin's own parameters
//! speed = 5.0
//! ```
//!
//! Every error names the file, the line and the key. Relative paths in the file are
//! relative to the file's directory.
//!
//! Here: the file's types and [`LoadedConfig`] (`model`), the checks types alone
//! cannot make (`checks`) and the helpers on its TOML text (`text`).

mod checks;
mod model;
mod text;

use std::path::Path;

use checks::validate;
use text::{apply_overrides, is_datetime_at, line_at, override_of};

pub use model::{
    Config, ConfigError, Episode, LoadedConfig, ModuleConfig, Output, DEFAULT_SETUP_TIMEOUT,
    DEFAULT_STEP_TIMEOUT, IN_PROCESS, MAX_STEPS,
};
pub use text::line_of_key;

/// Reads, overrides and validates a configuration file.
pub fn load(path: &Path, overrides: &[String]) -> Result<LoadedConfig, ConfigError> {
    let file = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| ConfigError {
        file: file.clone(),
        line: None,
        key: None,
        message: format!("cannot read the configuration file: {e}"),
    })?;
    let base_dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
    parse(&text, &file, &base_dir, overrides)
}

/// Like [`load`], from text; `file` is only used in messages.
pub fn parse(
    source: &str,
    file: &str,
    base_dir: &Path,
    overrides: &[String],
) -> Result<LoadedConfig, ConfigError> {
    let error = |line, key: Option<String>, message: String| ConfigError {
        file: file.to_string(),
        line,
        key,
        message,
    };
    let text = if overrides.is_empty() {
        source.to_string()
    } else {
        apply_overrides(source, overrides).map_err(|e| error(None, None, e))?
    };
    let de = toml::Deserializer::new(&text);
    let config: Config = serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let mut line = inner.span().map(|s| line_at(&text, s.start));
        let mut key = (path != "." && !path.is_empty()).then_some(path);
        let mut message = inner.message().to_string();
        if message.is_empty() {
            // The TOML parser says nothing of some characters (a control character in
            // a comment): say what is at the place it points to.
            let at = inner.span().map_or(text.len(), |s| s.start);
            message = match text.get(at..).and_then(|rest| rest.chars().next()) {
                Some(c) if c.is_control() => format!(
                    "a control character (U+{:04X}) is not allowed here in TOML",
                    c as u32
                ),
                Some(c) => format!("invalid TOML at '{c}'"),
                None => "the file ends where TOML expects more".into(),
            };
        }
        // "missing field `ts`" at `episode`: name the missing key, at its table's line.
        if let Some(field) = message
            .strip_prefix("missing field `")
            .and_then(|m| m.strip_suffix('`'))
        {
            let full = match &key {
                Some(k) => format!("{k}.{field}"),
                None => field.to_string(),
            };
            let table: Vec<&str> = full.split('.').collect();
            line = line_of_key(&text, &table[..table.len() - 1]).filter(|_| table.len() > 1);
            key = Some(full);
            message = "this required key is missing".into();
        }
        // serde sees a TOML date/time as a map: say what it is.
        if message.starts_with("invalid type: map") {
            let path: Vec<&str> = key.as_deref().unwrap_or("").split('.').collect();
            if is_datetime_at(&text, &path) {
                message = message.replace("invalid type: map", "invalid type: TOML date/time");
            }
        }
        if !overrides.is_empty() {
            // Lines were counted in the overridden text: name the file's own line, and
            // the override that set the key.
            let path: Vec<&str> = key.as_deref().map_or(vec![], |k| k.split('.').collect());
            match override_of(overrides, &path).filter(|_| !path.is_empty()) {
                Some(ov) => message.push_str(&format!(" (from --set {ov})")),
                None => message.push_str(" (after --set overrides)"),
            }
            line = (!path.is_empty())
                .then(|| line_of_key(source, &path))
                .flatten();
        }
        error(line, key, message)
    })?;
    let loaded = LoadedConfig {
        config,
        file: file.to_string(),
        base_dir: base_dir.to_path_buf(),
        text,
        source: source.to_string(),
        overrides: overrides.to_vec(),
    };
    validate(&loaded)?;
    Ok(loaded)
}

#[cfg(test)]
mod tests;
