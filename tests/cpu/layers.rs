//! The house's layering: every import of `src/` points down.
//!
//! - The layers are the numbered list under "# Layers" in `src/lib.rs`'s docs, lowest first;
//!   a module named there may use modules of lower layers only, not its own layer's or a
//!   higher one's.
//! - No two folders import each other (`models::texavatars` and `models::gaussianavatars`,
//!   `drive` and `synth`, …); a folder and one inside it (`splat` and `splat::cpu`) are one
//!   concept and may.
//!
//! An import is any `crate::a::b…` path in code (a `use` line or a path written out);
//! comments and doc comments are not code. Paths through `super::super` and grouped
//! `crate::{…}` imports would hide an import from this check and are rejected.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

fn src() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("src")
}

/// Every `.rs` file under `dir`.
fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<PathBuf> = fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .filter_map(Result::ok)
        .map(|e| e.path())
        .collect();
    entries.sort();
    for path in entries {
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The layers of `lib.rs`'s docs, lowest first: the module names in backticks on each
/// numbered line of the "# Layers" section.
fn layers(lib: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let mut inside = false;
    for line in lib.lines() {
        let Some(doc) = line.strip_prefix("//!") else {
            continue;
        };
        let doc = doc.trim();
        if doc.starts_with('#') {
            inside = doc == "# Layers";
            continue;
        }
        if !inside {
            continue;
        }
        let Some((number, rest)) = doc.split_once(". ") else {
            continue;
        };
        if number.parse::<usize>().is_err() {
            continue;
        }
        let names: Vec<String> = rest
            .split('`')
            .skip(1)
            .step_by(2)
            .map(|s| s.trim_matches(['[', ']']).to_string())
            .filter(|s| s.chars().all(|c| c.is_ascii_lowercase() || c == '_'))
            .collect();
        out.push(names);
    }
    out
}

/// The module path of a file under `src/` (`models/texavatars/net.rs` → `models::texavatars::
/// net`; a `mod.rs` is its folder's module).
fn module_of(file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src()).expect("under src");
    let mut parts: Vec<String> = rel
        .iter()
        .map(|p| p.to_string_lossy().trim_end_matches(".rs").to_string())
        .collect();
    if parts.last().is_some_and(|p| p == "mod") {
        parts.pop();
    }
    parts
}

/// The `crate::…` paths in the code lines of `text`, with their line numbers, each as its
/// segments up to the first that is not a lower-case module name (a type, a brace, …).
fn crate_paths(text: &str) -> Vec<(usize, Vec<String>)> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let code = line.trim_start();
        if code.starts_with("//") {
            continue;
        }
        let code = code.split(" //").next().unwrap_or(code);
        let mut rest = code;
        while let Some(at) = rest.find("crate::") {
            let before = rest[..at].chars().last();
            rest = &rest[at + "crate::".len()..];
            if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
                continue;
            }
            let segments: Vec<String> = rest
                .split("::")
                .map_while(|s| {
                    let name: String = s
                        .chars()
                        .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                        .collect();
                    let whole = name.len() == s.len();
                    let module = !name.is_empty() && name.chars().all(|c| !c.is_uppercase());
                    (module).then_some((name, whole))
                })
                .scan(true, |go, (name, whole)| {
                    let keep = *go;
                    *go = keep && whole;
                    keep.then_some(name)
                })
                .collect();
            if !segments.is_empty() {
                out.push((i + 1, segments));
            }
        }
    }
    out
}

/// The folders (module paths that are directories) under `src/`.
fn folders() -> BTreeSet<Vec<String>> {
    fn walk(dir: &Path, prefix: &[String], out: &mut BTreeSet<Vec<String>>) {
        for e in fs::read_dir(dir).into_iter().flatten().flatten() {
            let path = e.path();
            if path.is_dir() {
                let mut p = prefix.to_vec();
                p.push(e.file_name().to_string_lossy().to_string());
                out.insert(p.clone());
                walk(&path, &p, out);
            }
        }
    }
    let mut out = BTreeSet::new();
    walk(&src(), &[], &mut out);
    out
}

/// The folder a module path lies in: its longest prefix that is a folder (`None` at the top).
fn folder_of(path: &[String], folders: &BTreeSet<Vec<String>>) -> Option<Vec<String>> {
    (1..=path.len())
        .rev()
        .map(|n| path[..n].to_vec())
        .find(|p| folders.contains(p))
}

#[test]
fn every_import_points_down() {
    let lib = fs::read_to_string(src().join("lib.rs")).expect("src/lib.rs");
    let layers = layers(&lib);
    assert!(
        layers.len() >= 5,
        "no layer list in src/lib.rs's docs: {layers:?}"
    );
    let level: BTreeMap<&str, usize> = layers
        .iter()
        .enumerate()
        .flat_map(|(i, names)| names.iter().map(move |n| (n.as_str(), i)))
        .collect();
    let mut files = Vec::new();
    rust_files(&src(), &mut files);
    let mut problems = Vec::new();
    for file in &files {
        let module = module_of(file);
        let Some(top) = module.first().filter(|m| *m != "lib" && *m != "main") else {
            continue;
        };
        let Some(&from) = level.get(top.as_str()) else {
            problems.push(format!("{}: module `{top}` is in no layer", file.display()));
            continue;
        };
        let text = fs::read_to_string(file).expect("readable source");
        for hidden in ["super::super", "crate::{"] {
            if text.contains(hidden) {
                problems.push(format!("{}: a `{hidden}` path", file.display()));
            }
        }
        for (line, path) in crate_paths(&text) {
            let target = path[0].as_str();
            if target == top {
                continue;
            }
            match level.get(target) {
                Some(&to) if to < from => {}
                Some(&to) => problems.push(format!(
                    "{}:{line}: `{top}` (layer {}) imports `{target}` (layer {})",
                    file.display(),
                    from + 1,
                    to + 1
                )),
                None => problems.push(format!(
                    "{}:{line}: `crate::{target}` is in no layer",
                    file.display()
                )),
            }
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn no_two_folders_import_each_other() {
    let folders = folders();
    let mut files = Vec::new();
    rust_files(&src(), &mut files);
    let mut edges: BTreeMap<(Vec<String>, Vec<String>), String> = BTreeMap::new();
    for file in &files {
        let Some(from) = folder_of(&module_of(file), &folders) else {
            continue;
        };
        let text = fs::read_to_string(file).expect("readable source");
        for (line, path) in crate_paths(&text) {
            if let Some(to) = folder_of(&path, &folders).filter(|to| *to != from) {
                edges
                    .entry((from.clone(), to))
                    .or_insert_with(|| format!("{}:{line}", file.display()));
            }
        }
    }
    let mut problems = Vec::new();
    for ((a, b), at) in &edges {
        let nested = a.starts_with(b) || b.starts_with(a);
        if a < b
            && !nested
            && let Some(back) = edges.get(&(b.clone(), a.clone()))
        {
            problems.push(format!(
                "`{}` and `{}` import each other ({at}, {back})",
                a.join("::"),
                b.join("::")
            ));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

/// The parsers on known text, so that a check that passes is not one that reads nothing.
#[test]
fn the_checks_read_what_they_are_for() {
    let lib = "//! # Layers\n//!\n//! 1. [`error`], [`io`]: x\n//! 2. [`camera`] and `fusion`\n//! # Next\n//! 3. [`no`]\n";
    assert_eq!(
        layers(lib),
        vec![vec!["error", "io"], vec!["camera", "fusion"]]
    );
    let code = "use crate::splat::{Gaussians, ply};\n// crate::train::x\nlet a = crate::eval::run::load_avatar(p);\nuse crate::{a, b};\nfoo_crate::x::y";
    assert_eq!(
        crate_paths(code),
        vec![
            (1, vec!["splat".to_string()]),
            (3, vec!["eval".into(), "run".into(), "load_avatar".into()]),
        ]
    );
}
