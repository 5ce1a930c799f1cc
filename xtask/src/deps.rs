//! `cargo xtask deps`: file-level import cycles inside each crate.
//!
//! An edge A → B means file A names an item through a path that resolves to
//! file B (`use crate::x::y`, `crate::x::y::Z` in code, `super::…`,
//! `self::…`). `mod x;` declarations and a module naming its own submodules
//! are structure, not edges; test files (`tests.rs`, `*/tests/*`) and
//! `#[cfg(test)] mod … { … }` blocks are skipped. A cycle is a strongly
//! connected component of two or more files. `cargo xtask test` fails when
//! one appears (ARCHITECTURE.md, "Dependency rules").

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

/// The crates' source folders checked by default.
pub const CRATE_SOURCES: [&str; 4] = ["shared/src", "backend/src", "frontend/src", "python/src"];

type ModPath = Vec<String>;

/// Every cycle (a sorted list of files, relative to `repo`) in the crates
/// under `sources`.
pub fn cycles(repo: &Path, sources: &[&str]) -> Vec<Vec<PathBuf>> {
    let mut out = Vec::new();
    for src in sources {
        let dir = repo.join(src);
        if !dir.is_dir() {
            continue;
        }
        let files = module_files(&dir);
        let mut graph: BTreeMap<PathBuf, BTreeSet<PathBuf>> = BTreeMap::new();
        for (module, file) in &files {
            if is_test_file(file) {
                continue;
            }
            graph.entry(file.clone()).or_default();
            let text = strip(&fs::read_to_string(file).unwrap_or_default());
            for path in paths_in(&text) {
                let Some(target) = resolve(&path, module, &files) else {
                    continue;
                };
                if target == *module || target.is_empty() || target.starts_with(module) {
                    // itself, the crate root, or its own submodules (structure)
                    continue;
                }
                let target_file = &files[&target];
                if !is_test_file(target_file) {
                    graph
                        .entry(file.clone())
                        .or_default()
                        .insert(target_file.clone());
                }
            }
        }
        for component in strongly_connected(&graph) {
            out.push(
                component
                    .into_iter()
                    .map(|f| f.strip_prefix(repo).unwrap_or(&f).to_path_buf())
                    .collect(),
            );
        }
    }
    out
}

fn is_test_file(f: &Path) -> bool {
    f.file_name().is_some_and(|n| n == "tests.rs")
        || f.components().any(|c| c.as_os_str() == "tests")
}

/// Module path → file, from `lib.rs`/`main.rs` and every `.rs` below.
fn module_files(src: &Path) -> BTreeMap<ModPath, PathBuf> {
    let mut files = BTreeMap::new();
    for root in ["lib.rs", "main.rs"] {
        if src.join(root).exists() {
            files.insert(Vec::new(), src.join(root));
            break;
        }
    }
    let mut stack = vec![src.to_path_buf()];
    while let Some(dir) = stack.pop() {
        let Ok(entries) = fs::read_dir(&dir) else {
            continue;
        };
        for entry in entries.flatten() {
            let p = entry.path();
            if p.is_dir() {
                stack.push(p);
                continue;
            }
            if p.extension().is_none_or(|e| e != "rs") {
                continue;
            }
            let rel = p.strip_prefix(src).unwrap().with_extension("");
            let mut parts: ModPath = rel
                .components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect();
            if parts == ["lib"] || parts == ["main"] {
                continue;
            }
            if parts.last().is_some_and(|l| l == "mod") {
                parts.pop();
            }
            files.entry(parts).or_insert(p);
        }
    }
    files
}

/// The source without comments, string contents and `#[cfg(test)] mod` blocks.
fn strip(text: &str) -> String {
    let b = text.as_bytes();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'/' && b.get(i + 1) == Some(&b'/') {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
        } else if b[i] == b'/' && b.get(i + 1) == Some(&b'*') {
            i += 2;
            while i + 1 < b.len() && !(b[i] == b'*' && b[i + 1] == b'/') {
                i += 1;
            }
            i += 2;
        } else if b[i] == b'"' {
            out.push_str("\"\"");
            i += 1;
            while i < b.len() && b[i] != b'"' {
                i += if b[i] == b'\\' { 2 } else { 1 };
            }
            i += 1;
        } else {
            let c = text[i..].chars().next().unwrap();
            out.push(c);
            i += c.len_utf8();
        }
    }
    drop_test_modules(&out)
}

fn drop_test_modules(text: &str) -> String {
    let mut out = String::new();
    let mut rest = text;
    while let Some(at) = rest.find("#[cfg(test)]") {
        let after = rest[at + "#[cfg(test)]".len()..].trim_start();
        let is_mod = after.starts_with("mod ") && {
            let head: String = after
                .chars()
                .take_while(|&c| c != ';' && c != '{')
                .collect();
            after[head.len()..].starts_with('{')
        };
        if !is_mod {
            out.push_str(&rest[..at + 1]);
            rest = &rest[at + 1..];
            continue;
        }
        out.push_str(&rest[..at]);
        let open = rest[at..].find('{').map(|k| at + k).unwrap_or(rest.len());
        let mut depth = 0usize;
        let mut end = rest.len();
        for (k, c) in rest[open..].char_indices() {
            match c {
                '{' => depth += 1,
                '}' => {
                    depth -= 1;
                    if depth == 0 {
                        end = open + k + 1;
                        break;
                    }
                }
                _ => {}
            }
        }
        rest = &rest[end..];
    }
    out.push_str(rest);
    out
}

/// Paths starting with `crate`, `super` or `self`, with `use` groups expanded.
fn paths_in(text: &str) -> Vec<ModPath> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(at) = find_word(rest, "use") {
        let after = &rest[at + 3..];
        let end = after.find(';').unwrap_or(after.len());
        let spec = after[..end].trim();
        if ["crate", "super", "self"].iter().any(|r| {
            spec.starts_with(r)
                && !spec[r.len()..].starts_with(|c: char| c.is_alphanumeric() || c == '_')
        }) {
            expand(&spec.replace('\n', " "), &mut out);
        }
        rest = &after[end.min(after.len())..];
    }
    // paths in code: crate::a::b, super::a, self::a
    let bytes = text.as_bytes();
    for root in ["crate", "super", "self"] {
        let mut from = 0;
        while let Some(k) = text[from..].find(root) {
            let start = from + k;
            from = start + root.len();
            let before_ok = start == 0
                || !(bytes[start - 1].is_ascii_alphanumeric()
                    || bytes[start - 1] == b'_'
                    || bytes[start - 1] == b':');
            if !before_ok || !text[from..].starts_with("::") {
                continue;
            }
            let mut segs = vec![root.to_string()];
            let mut p = from;
            while text[p..].starts_with("::") {
                let word: String = text[p + 2..]
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect();
                if word.is_empty() {
                    break;
                }
                p += 2 + word.len();
                segs.push(word);
            }
            if segs.len() > 1 {
                out.push(segs);
            }
        }
    }
    out
}

fn find_word(text: &str, word: &str) -> Option<usize> {
    let b = text.as_bytes();
    let mut from = 0;
    while let Some(k) = text[from..].find(word) {
        let at = from + k;
        let before = at == 0 || !(b[at - 1].is_ascii_alphanumeric() || b[at - 1] == b'_');
        let after = b
            .get(at + word.len())
            .is_some_and(|c| c.is_ascii_whitespace());
        if before && after {
            return Some(at);
        }
        from = at + word.len();
    }
    None
}

fn expand(spec: &str, out: &mut Vec<ModPath>) {
    let spec = spec.trim();
    let Some(open) = spec.find('{') else {
        out.push(
            spec.split("::")
                .map(|s| {
                    s.trim()
                        .split(" as ")
                        .next()
                        .unwrap_or("")
                        .trim()
                        .to_string()
                })
                .filter(|s| !s.is_empty())
                .collect(),
        );
        return;
    };
    let head = spec[..open].trim_end_matches(':').trim();
    let close = spec.rfind('}').unwrap_or(spec.len());
    let body = &spec[open + 1..close];
    let (mut depth, mut cur, mut parts) = (0i32, String::new(), Vec::new());
    for c in body.chars() {
        match c {
            ',' if depth == 0 => {
                parts.push(std::mem::take(&mut cur));
                continue;
            }
            '{' => depth += 1,
            '}' => depth -= 1,
            _ => {}
        }
        cur.push(c);
    }
    parts.push(cur);
    for p in parts {
        let p = p.trim();
        if p.is_empty() {
            continue;
        }
        if p == "self" {
            out.push(
                head.split("::")
                    .filter(|s| !s.is_empty())
                    .map(String::from)
                    .collect(),
            );
        } else {
            expand(&format!("{head}::{p}"), out);
        }
    }
}

/// The longest module prefix of `path` (relative to `here`) that is a file.
fn resolve(path: &[String], here: &ModPath, files: &BTreeMap<ModPath, PathBuf>) -> Option<ModPath> {
    let (mut base, mut rest): (ModPath, &[String]) = match path.first()?.as_str() {
        "crate" => (Vec::new(), &path[1..]),
        "super" | "self" => (here.clone(), path),
        _ => return None,
    };
    while let Some(first) = rest.first() {
        match first.as_str() {
            "super" => {
                base.pop();
            }
            "self" => {}
            _ => break,
        }
        rest = &rest[1..];
    }
    let mut best = files.contains_key(&base).then(|| base.clone());
    let mut cur = base;
    for s in rest {
        cur.push(s.clone());
        if files.contains_key(&cur) {
            best = Some(cur.clone());
        } else {
            break;
        }
    }
    best
}

/// Tarjan's strongly connected components of two or more nodes.
fn strongly_connected(graph: &BTreeMap<PathBuf, BTreeSet<PathBuf>>) -> Vec<Vec<PathBuf>> {
    struct State<'a> {
        graph: &'a BTreeMap<PathBuf, BTreeSet<PathBuf>>,
        index: BTreeMap<&'a PathBuf, usize>,
        low: BTreeMap<&'a PathBuf, usize>,
        stack: Vec<&'a PathBuf>,
        on_stack: BTreeSet<&'a PathBuf>,
        next: usize,
        out: Vec<Vec<PathBuf>>,
    }
    fn visit<'a>(s: &mut State<'a>, v: &'a PathBuf) {
        s.index.insert(v, s.next);
        s.low.insert(v, s.next);
        s.next += 1;
        s.stack.push(v);
        s.on_stack.insert(v);
        if let Some(edges) = s.graph.get(v) {
            for w in edges {
                let Some((w, _)) = s.graph.get_key_value(w) else {
                    continue;
                };
                if !s.index.contains_key(w) {
                    visit(s, w);
                    let lw = s.low[w];
                    let lv = s.low.get_mut(v).unwrap();
                    *lv = (*lv).min(lw);
                } else if s.on_stack.contains(w) {
                    let iw = s.index[w];
                    let lv = s.low.get_mut(v).unwrap();
                    *lv = (*lv).min(iw);
                }
            }
        }
        if s.low[v] == s.index[v] {
            let mut comp = Vec::new();
            while let Some(w) = s.stack.pop() {
                s.on_stack.remove(w);
                comp.push(w.clone());
                if w == v {
                    break;
                }
            }
            if comp.len() > 1 {
                comp.sort();
                s.out.push(comp);
            }
        }
    }
    let mut s = State {
        graph,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on_stack: BTreeSet::new(),
        next: 0,
        out: Vec::new(),
    };
    for v in graph.keys() {
        if !s.index.contains_key(v) {
            visit(&mut s, v);
        }
    }
    s.out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A crate of `files` in a folder of its own (`tag`: one per test, so
    /// tests running in parallel never share it).
    fn crate_with(tag: &str, files: &[(&str, &str)]) -> (PathBuf, Vec<Vec<PathBuf>>) {
        let dir = std::env::temp_dir().join(format!("xtask-deps-{}-{tag}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        for (path, text) in files {
            let p = dir.join("c/src").join(path);
            fs::create_dir_all(p.parent().unwrap()).unwrap();
            fs::write(p, text).unwrap();
        }
        let found = cycles(&dir, &["c/src"]);
        (dir, found)
    }

    #[test]
    fn a_use_cycle_between_two_files_is_found_and_structure_is_not_a_cycle() {
        let (dir, found) = crate_with("cycle", &[
            ("lib.rs", "pub mod a;\npub mod b;\npub use a::A;"),
            ("a.rs", "use crate::b::{B, self};\npub struct A;"),
            ("b/mod.rs", "pub mod inner;\n// use crate::a::A; (a comment)\npub fn f() -> super::a::A { loop {} }\npub struct B;"),
            ("b/inner.rs", "use super::B;"),
        ]);
        let _ = fs::remove_dir_all(&dir);
        assert_eq!(
            found,
            vec![vec![
                PathBuf::from("c/src/a.rs"),
                PathBuf::from("c/src/b/mod.rs")
            ]]
        );
    }

    #[test]
    fn comments_strings_and_test_modules_make_no_edge() {
        let (dir, found) = crate_with("no-edge", &[
            ("lib.rs", "pub mod a;\npub mod b;\npub mod c;"),
            ("a.rs", "use crate::b::B;\n"),
            (
                "b.rs",
                "pub struct B;\nconst S: &str = \"crate::a::X\";\n/* use crate::a; */\n#[cfg(test)]\nmod tests { use crate::a; }",
            ),
            ("c.rs", "#[cfg(test)]\nuse crate::a;\n"),
        ]);
        let _ = fs::remove_dir_all(&dir);
        assert!(found.is_empty(), "{found:?}");
    }
}
