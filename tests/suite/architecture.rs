//! The layering rules of docs/architecture.md, read from the source: no import cycle among
//! the root crate's top-level modules; nothing outside `daemon/` imports `daemon::*` but the
//! cli (its protocol, and the in-process daemon of `rigctl demo`); nothing below the cli
//! imports `cli::*`. Cargo keeps the core crate pure; this keeps the root crate layered.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The `crate::<module>` paths each source file names, outside its unit tests.
struct Source {
    /// Path under `src/`, with `/` separators.
    rel: String,
    /// The first segment after `crate::` of every path it uses.
    uses: BTreeSet<String>,
    /// `daemon::<x>` segments it uses.
    daemon_uses: BTreeSet<String>,
}

fn src_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The code of a file without comments and without its `#[cfg(test)]` module.
fn code(text: &str) -> String {
    let text = match text.find("#[cfg(test)]\nmod tests") {
        Some(i) => &text[..i],
        None => text,
    };
    text.lines()
        .map(|l| match l.find("//") {
            Some(i) => &l[..i],
            None => l,
        })
        .collect::<Vec<_>>()
        .join("\n")
}

fn ident(s: &str) -> String {
    s.trim_start()
        .chars()
        .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
        .collect()
}

/// The items of a `{…}` group that `s` starts inside of, split at its own commas.
fn group_items(s: &str) -> Vec<&str> {
    let (mut depth, mut start, mut items) = (0usize, 0, Vec::new());
    for (i, c) in s.char_indices() {
        match c {
            '{' => depth += 1,
            '}' if depth == 0 => {
                items.push(&s[start..i]);
                return items;
            }
            '}' => depth -= 1,
            ',' if depth == 0 => {
                items.push(&s[start..i]);
                start = i + 1;
            }
            _ => {}
        }
    }
    items.push(&s[start..]);
    items
}

/// `a::b…` (or `a::{b, c}`) as (a, b) pairs.
fn split_path(item: &str, out: &mut Vec<(String, String)>) {
    let item = item.trim_start();
    let first = ident(item);
    match item[first.len()..].strip_prefix("::") {
        Some(rest) if rest.starts_with('{') => {
            for sub in group_items(&rest[1..]) {
                out.push((first.clone(), ident(sub)));
            }
        }
        Some(rest) => out.push((first, ident(rest))),
        None => out.push((first, String::new())),
    }
}

/// Every `crate::a::b` as (a, b), grouped uses (`crate::{a::b, c}`) included.
fn crate_paths(code: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    for (i, _) in code.match_indices("crate::") {
        let rest = &code[i + "crate::".len()..];
        match rest.strip_prefix('{') {
            Some(group) => {
                for item in group_items(group) {
                    split_path(item, &mut out);
                }
            }
            None => split_path(rest, &mut out),
        }
    }
    out.retain(|(a, _)| !a.is_empty());
    out
}

fn top_level(rel: &str) -> String {
    let first = rel.split('/').next().unwrap();
    first.strip_suffix(".rs").unwrap_or(first).to_string()
}

fn sources() -> Vec<Source> {
    let root = src_dir();
    let mut files = Vec::new();
    rust_files(&root, &mut files);
    files
        .iter()
        .map(|p| {
            let rel = p
                .strip_prefix(&root)
                .unwrap()
                .to_string_lossy()
                .replace('\\', "/");
            let code = code(&std::fs::read_to_string(p).unwrap());
            let paths = crate_paths(&code);
            Source {
                uses: paths.iter().map(|(a, _)| a.clone()).collect(),
                daemon_uses: paths
                    .iter()
                    .filter(|(a, _)| a == "daemon")
                    .map(|(_, b)| b.clone())
                    .collect(),
                rel,
            }
        })
        .collect()
}

/// Top-level module -> the modules it uses -> the files that do.
type Graph = BTreeMap<String, BTreeMap<String, BTreeSet<String>>>;

fn graph(sources: &[Source]) -> Graph {
    let modules: BTreeSet<String> = sources
        .iter()
        .filter(|s| s.rel != "lib.rs" && !s.rel.starts_with("bin/"))
        .map(|s| top_level(&s.rel))
        .collect();
    let mut g = Graph::new();
    for s in sources {
        let from = top_level(&s.rel);
        if !modules.contains(&from) {
            continue;
        }
        g.entry(from.clone()).or_default();
        for to in s
            .uses
            .iter()
            .filter(|m| modules.contains(*m) && **m != from)
        {
            g.get_mut(&from)
                .unwrap()
                .entry(to.clone())
                .or_default()
                .insert(s.rel.clone());
        }
    }
    g
}

/// A path from `to` back to `from`, if the graph has one.
fn path_back(g: &Graph, from: &str, to: &str) -> Option<Vec<String>> {
    let mut seen = BTreeSet::new();
    let mut stack = vec![vec![to.to_string()]];
    while let Some(path) = stack.pop() {
        let last = path.last().unwrap();
        if last == from {
            return Some(path);
        }
        if !seen.insert(last.clone()) {
            continue;
        }
        for next in g.get(last).into_iter().flat_map(|m| m.keys()) {
            let mut p = path.clone();
            p.push(next.clone());
            stack.push(p);
        }
    }
    None
}

#[test]
fn the_top_level_modules_form_no_cycle() {
    let g = graph(&sources());
    assert!(g.len() >= 15, "found only {:?}", g.keys());
    let mut cycles = Vec::new();
    for (from, tos) in &g {
        for (to, files) in tos {
            if let Some(back) = path_back(&g, from, to) {
                cycles.push(format!(
                    "{from} -> {} (the first edge from {files:?})",
                    back.join(" -> ")
                ));
            }
        }
    }
    assert!(cycles.is_empty(), "import cycles:\n{}", cycles.join("\n"));
}

#[test]
fn only_the_cli_reaches_into_the_daemon_and_only_by_its_protocol() {
    let mut wrong = Vec::new();
    for s in sources() {
        let outside = !s.rel.starts_with("daemon/") && !s.rel.starts_with("bin/");
        if !outside {
            continue;
        }
        for x in &s.daemon_uses {
            // rigctl's in-process daemon (`demo`) starts the server like rigd does.
            let allowed = s.rel.starts_with("cli/")
                && (x == "protocol" || (s.rel == "cli/demo.rs" && x == "server"));
            if !allowed {
                wrong.push(format!("{} uses daemon::{x}", s.rel));
            }
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

#[test]
fn nothing_below_the_cli_imports_it() {
    let wrong: Vec<String> = sources()
        .into_iter()
        .filter(|s| !s.rel.starts_with("cli/") && !s.rel.starts_with("bin/"))
        .filter(|s| s.uses.contains("cli"))
        .map(|s| s.rel)
        .collect();
    assert!(wrong.is_empty(), "these import cli::*: {wrong:?}");
}

#[test]
fn the_reader_finds_grouped_and_nested_paths() {
    let c = code(
        "use crate::{a::b, c::{d, e::f}};\nuse crate::g::{h::{i, j}, k};\n\
         fn f() { crate::l::m(); } // crate::x\n",
    );
    let pairs: Vec<String> = crate_paths(&c)
        .iter()
        .map(|(a, b)| format!("{a}::{b}"))
        .collect();
    assert_eq!(pairs, ["a::b", "c::d", "c::e", "g::h", "g::k", "l::m"]);
}
