//! The crate's layering, checked from its sources: no two Rust modules import each
//! other, directly or round a longer loop (docs/architecture.md), and nothing outside
//! `transport/` names a transport.
//!
//! A module is a file under `src/` (`a/b.rs` or `a/b/mod.rs` is `a::b`); it imports
//! another when it names it through `crate::`, `super::` or its own child modules
//! (`use`, paths in code alike). A parent declaring its children (`mod x;`) is not an
//! import. Unit tests (`#[cfg(test)] mod tests`) are left out: they may use anything.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Every module of the crate (not the root) with the text of its file, tests cut.
fn modules(src: &Path) -> BTreeMap<String, String> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(&p, out);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    let mut files = Vec::new();
    walk(src, &mut files);
    let mut out = BTreeMap::new();
    for f in files {
        let rel = f.strip_prefix(src).unwrap().with_extension("");
        let mut parts: Vec<String> = rel
            .components()
            .map(|c| c.as_os_str().to_string_lossy().into_owned())
            .collect();
        if parts.last().is_some_and(|p| p == "mod") {
            parts.pop();
        }
        let name = parts.join("::");
        if name == "lib" || name == "main" {
            continue;
        }
        let text = std::fs::read_to_string(&f).unwrap();
        let text = match text.find("#[cfg(test)]\nmod tests") {
            Some(i) => text[..i].to_string(),
            None => text,
        };
        out.insert(name, text);
    }
    out
}

/// The modules `name` imports: the longest known module each `crate::…`,
/// `super::…` or `child::…` path starts with, other than itself and its own
/// descendants' declarations.
fn imports(name: &str, text: &str, known: &BTreeSet<String>) -> BTreeSet<String> {
    let parent: Vec<&str> = name.split("::").collect();
    let parent = &parent[..parent.len() - 1];
    let mut out = BTreeSet::new();
    let code: String = text
        .lines()
        .map(|l| l.split("//").next().unwrap_or(""))
        .collect::<Vec<_>>()
        .join("\n");
    let is_ident = |c: char| c.is_ascii_alphanumeric() || c == '_';
    let bytes: Vec<char> = code.chars().collect();
    let mut i = 0;
    while i < bytes.len() {
        // A path: identifiers joined by `::`, starting where no identifier continues.
        if !is_ident(bytes[i]) || (i > 0 && (is_ident(bytes[i - 1]) || bytes[i - 1] == ':')) {
            i += 1;
            continue;
        }
        let mut segs = Vec::new();
        let mut j = i;
        loop {
            let start = j;
            while j < bytes.len() && is_ident(bytes[j]) {
                j += 1;
            }
            segs.push(bytes[start..j].iter().collect::<String>());
            if j + 2 < bytes.len()
                && bytes[j] == ':'
                && bytes[j + 1] == ':'
                && is_ident(bytes[j + 2])
            {
                j += 2;
            } else {
                break;
            }
        }
        // `child::{A, B}` (a use list after one segment) names the child too.
        let braced =
            j + 2 < bytes.len() && bytes[j] == ':' && bytes[j + 1] == ':' && bytes[j + 2] == '{';
        i = j.max(i + 1);
        if segs.len() < 2 && !braced {
            continue;
        }
        let base: Vec<String> = match segs[0].as_str() {
            "crate" => Vec::new(),
            "super" => parent.iter().map(|s| s.to_string()).collect(),
            // A child of this module, named from inside it (`nats::Nats`).
            _ => name.split("::").map(String::from).collect(),
        };
        let rest = if segs[0] == "crate" || segs[0] == "super" {
            &segs[1..]
        } else {
            &segs[..]
        };
        // `super::Item` names the parent module itself.
        let mut best =
            (segs[0] == "super" && known.contains(&base.join("::"))).then(|| base.join("::"));
        let mut path = base.clone();
        for s in rest {
            path.push(s.clone());
            let candidate = path.join("::");
            if known.contains(&candidate) {
                best = Some(candidate);
            }
        }
        if let Some(m) = best {
            if m != name {
                out.insert(m);
            }
        }
    }
    out
}

fn graph() -> BTreeMap<String, BTreeSet<String>> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mods = modules(&src);
    let known: BTreeSet<String> = mods.keys().cloned().collect();
    mods.iter()
        .map(|(n, t)| (n.clone(), imports(n, t, &known)))
        .collect()
}

/// A cycle through `start`, if any (depth-first).
fn cycle(g: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        g: &BTreeMap<String, BTreeSet<String>>,
        n: &str,
        stack: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(i) = stack.iter().position(|s| s == n) {
            let mut c = stack[i..].to_vec();
            c.push(n.to_string());
            return Some(c);
        }
        if done.contains(n) {
            return None;
        }
        stack.push(n.to_string());
        for m in g.get(n).into_iter().flatten() {
            if let Some(c) = visit(g, m, stack, done) {
                return Some(c);
            }
        }
        stack.pop();
        done.insert(n.to_string());
        None
    }
    let mut done = BTreeSet::new();
    for n in g.keys() {
        if let Some(c) = visit(g, n, &mut Vec::new(), &mut done) {
            return Some(c);
        }
    }
    None
}

#[test]
fn no_two_modules_import_each_other() {
    let g = graph();
    assert!(g.len() > 20, "{} modules found", g.len());
    // The checker sees imports: the run reaches the transports' registry.
    assert!(g["run"].contains("transport"), "{:?}", g["run"]);
    assert!(g["transport::nats"].contains("transport::interface"));
    if let Some(c) = cycle(&g) {
        panic!("modules import each other: {}", c.join(" -> "));
    }
}

#[test]
fn the_checker_finds_a_cycle() {
    let mut g = graph();
    g.get_mut("topic").unwrap().insert("run".into());
    let c = cycle(&g).expect("topic -> run -> … -> topic");
    assert_eq!(c.first(), c.last(), "{c:?}");
}

#[test]
fn a_parent_named_by_super_and_a_use_list_of_a_child_count_as_imports() {
    let known: BTreeSet<String> = ["a", "a::b", "a::c"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    let of = |name: &str, text: &str| imports(name, text, &known).into_iter().collect::<Vec<_>>();
    assert_eq!(of("a::b", "use super::Thing;"), ["a"]);
    assert_eq!(of("a::b", "use super::c::Thing;"), ["a::c"]);
    assert_eq!(of("a", "pub use b::{One, Two};"), ["a::b"]);
}

#[test]
fn only_the_transport_registry_names_a_transport() {
    let g = graph();
    for (module, uses) in &g {
        if module.starts_with("transport") {
            continue;
        }
        let named: Vec<&String> = uses
            .iter()
            .filter(|u| u.starts_with("transport::") && *u != "transport::interface")
            .collect();
        assert!(named.is_empty(), "{module} names {named:?}");
    }
}
