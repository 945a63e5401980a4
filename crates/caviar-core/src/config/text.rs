//! Helpers on the configuration's TOML text: `--set` overrides, the line a key is
//! written on, and numbers written for people in messages.

/// The last `--set KEY=VALUE` whose key is `path` or a table holding it: where the value
/// at `path` came from.
pub(super) fn override_of<'a>(overrides: &'a [String], path: &[&str]) -> Option<&'a str> {
    overrides
        .iter()
        .rev()
        .find(|ov| {
            let key = ov.split_once('=').map_or(ov.as_str(), |(k, _)| k);
            let set: Vec<&str> = key.trim().split('.').collect();
            path.len() >= set.len() && path[..set.len()] == set[..]
        })
        .map(String::as_str)
}

/// Applies `key.path=value` overrides. The value is read as a TOML value
/// (`3`, `2.5`, `true`, `"text"`, `[1, 2]`); anything else is taken as a string.
pub(super) fn apply_overrides(text: &str, overrides: &[String]) -> Result<String, String> {
    let mut doc: toml_edit::DocumentMut = text
        .parse()
        .map_err(|e: toml_edit::TomlError| e.to_string())?;
    for ov in overrides {
        let (key, raw) = ov
            .split_once('=')
            .ok_or_else(|| format!("--set '{ov}': expected KEY=VALUE, e.g. episode.steps=10"))?;
        let path: Vec<&str> = key.trim().split('.').collect();
        if path.iter().any(|p| p.is_empty()) {
            return Err(format!("--set '{ov}': '{key}' is not a dotted key path"));
        }
        let value: toml_edit::Value = raw
            .trim()
            .parse()
            .unwrap_or_else(|_| toml_edit::Value::from(raw.trim()));
        let mut table = doc.as_table_mut() as &mut dyn toml_edit::TableLike;
        for part in &path[..path.len() - 1] {
            let entry = table.entry(part).or_insert(toml_edit::table());
            table = entry
                .as_table_like_mut()
                .ok_or_else(|| format!("--set '{ov}': '{part}' is a value, not a table"))?;
        }
        table.insert(path[path.len() - 1], toml_edit::Item::Value(value));
    }
    Ok(doc.to_string())
}

pub(super) fn is_datetime_at(text: &str, path: &[&str]) -> bool {
    let Ok(doc) = toml_edit::ImDocument::parse(text) else {
        return false;
    };
    let mut item: &toml_edit::Item = doc.as_item();
    for part in path {
        match item.get(part) {
            Some(i) => item = i,
            None => return false,
        }
    }
    item.as_datetime().is_some()
}

/// A number for messages: plain when readable, else in scientific notation.
pub(super) fn num(x: f64) -> String {
    if x == 0.0 || (1e-4..1e9).contains(&x.abs()) {
        format!("{x}")
    } else if x.is_finite() {
        let s = format!("{x:.3e}");
        let (mantissa, exp) = s.split_once('e').expect("scientific notation");
        let mantissa = mantissa.trim_end_matches('0').trim_end_matches('.');
        format!("{mantissa}e{exp}")
    } else {
        format!("{x}").to_lowercase()
    }
}

/// 1-based line of byte offset `pos`.
pub(super) fn line_at(text: &str, pos: usize) -> usize {
    text[..pos.min(text.len())]
        .bytes()
        .filter(|&b| b == b'\n')
        .count()
        + 1
}

/// 1-based line where the key path is written (its value, or the deepest part found).
pub fn line_of_key(text: &str, path: &[&str]) -> Option<usize> {
    let doc = toml_edit::ImDocument::parse(text).ok()?;
    let mut table: &dyn toml_edit::TableLike = doc.as_table();
    let mut line = None;
    let mut i = 0;
    while i < path.len() {
        let Some((k, item)) = table.get_key_value(path[i]) else {
            break;
        };
        if let Some(span) = item.span().or_else(|| k.span()) {
            line = Some(line_at(text, span.start));
        }
        // `sites.1.name`: the second `[[…sites]]` table (or item of an inline array).
        let index = path.get(i + 1).and_then(|p| p.parse::<usize>().ok());
        if let (Some(n), Some(tables)) = (index, item.as_array_of_tables()) {
            let Some(t) = tables.get(n) else { break };
            if let Some(span) = t.span() {
                line = Some(line_at(text, span.start));
            }
            i += 2;
            table = t;
            continue;
        }
        if let (Some(n), Some(array)) = (index, item.as_array()) {
            if let Some(span) = array.get(n).and_then(|v| v.span()) {
                line = Some(line_at(text, span.start));
            }
            break;
        }
        i += 1;
        if i == path.len() {
            break;
        }
        match item.as_table_like() {
            Some(t) => table = t,
            None => break,
        }
    }
    line
}
