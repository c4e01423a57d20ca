//! The documentation check: the README and every page under `docs/` (and the other
//! Markdown files of the repository) stay true to the repository.
//!
//! - Every relative link resolves: the file exists, and a `#anchor` names a heading of the
//!   target page under GitHub's slug rules (the renderer users read the docs with).
//! - Every `texavatars …` command the README shows (in code spans and code blocks, and the
//!   `cargo run --release -- …` form) parses with the real command line (clap's
//!   `try_parse_from`; nothing runs).
//! - The README stays at most 10 KB.

use std::collections::HashSet;
use std::fs;
use std::path::{Path, PathBuf};

use clap::Parser;
use texavatars::cli::Cli;

/// The README's size limit in bytes.
const README_MAX_BYTES: usize = 10 * 1024;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Every Markdown file of the repository outside build output and git's folder.
fn markdown_files() -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        let Ok(entries) = fs::read_dir(dir) else {
            return;
        };
        let mut entries: Vec<_> = entries.filter_map(Result::ok).map(|e| e.path()).collect();
        entries.sort();
        for path in entries {
            let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
            if path.is_dir() {
                if !matches!(name, "target" | ".git" | "node_modules" | "out") {
                    walk(&path, out);
                }
            } else if name.ends_with(".md") {
                out.push(path);
            }
        }
    }
    let mut out = Vec::new();
    walk(&root(), &mut out);
    out
}

/// The page's lines outside fenced and indented code blocks, with their line numbers.
fn prose_lines(text: &str) -> Vec<(usize, &str)> {
    let mut out = Vec::new();
    let mut fenced = false;
    let mut prev_blank = true;
    let mut in_indented = false;
    for (i, line) in text.lines().enumerate() {
        let trimmed = line.trim_start();
        if trimmed.starts_with("```") {
            fenced = !fenced;
            prev_blank = false;
            continue;
        }
        if fenced {
            continue;
        }
        let blank = line.trim().is_empty();
        // An indented code block starts after a blank line with four spaces of indent and
        // runs until a non-blank line with less indent (list continuations are not code:
        // they follow a non-blank line).
        if line.starts_with("    ") && (prev_blank || in_indented) && !blank {
            in_indented = true;
            prev_blank = false;
            continue;
        }
        if !blank {
            in_indented = false;
        }
        prev_blank = blank;
        out.push((i + 1, line));
    }
    out
}

/// `line` with its inline code spans removed (links inside them are not links).
fn without_code_spans(line: &str) -> String {
    let mut out = String::new();
    let mut in_code = false;
    for c in line.chars() {
        if c == '`' {
            in_code = !in_code;
        } else if !in_code {
            out.push(c);
        }
    }
    out
}

/// The targets of the inline links and images `[text](target)` on a line.
fn link_targets(line: &str) -> Vec<String> {
    let line = without_code_spans(line);
    let bytes = line.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while let Some(pos) = line[i..].find("](") {
        let start = i + pos + 2;
        let mut depth = 0usize;
        let mut end = None;
        for (j, &b) in bytes.iter().enumerate().skip(start) {
            match b {
                b'(' => depth += 1,
                b')' if depth == 0 => {
                    end = Some(j);
                    break;
                }
                b')' => depth -= 1,
                _ => {}
            }
        }
        let Some(end) = end else { break };
        let target = line[start..end].split_whitespace().next().unwrap_or("");
        out.push(target.to_string());
        i = end + 1;
    }
    out
}

/// GitHub's anchor for a heading: the rendered text lowercased, everything but letters,
/// digits, `_`, `-` and spaces dropped, spaces turned into `-`.
fn slug(heading: &str) -> String {
    // Rendered text: links show their text, code spans their contents.
    let mut text = String::new();
    let mut rest = heading;
    while let Some(open) = rest.find('[') {
        let Some(close) = rest[open..].find("](") else {
            break;
        };
        let Some(paren) = rest[open + close..].find(')') else {
            break;
        };
        text.push_str(&rest[..open]);
        text.push_str(&rest[open + 1..open + close]);
        rest = &rest[open + close + paren + 1..];
    }
    text.push_str(rest);
    text.to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || matches!(c, '_' | '-' | ' '))
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a page's headings, with GitHub's `-1`, `-2` suffixes for repeats.
fn anchors(text: &str) -> HashSet<String> {
    let mut seen = HashSet::new();
    for (_, line) in prose_lines(text) {
        let t = line.trim_start();
        if !t.starts_with('#') {
            continue;
        }
        let level = t.chars().take_while(|&c| c == '#').count();
        if level > 6 || !t[level..].starts_with(' ') {
            continue;
        }
        let base = slug(t[level..].trim());
        let mut candidate = base.clone();
        let mut n = 0;
        while seen.contains(&candidate) {
            n += 1;
            candidate = format!("{base}-{n}");
        }
        seen.insert(candidate);
    }
    seen
}

/// The problems with one page's relative links.
fn link_problems(page: &Path) -> Vec<String> {
    let text = fs::read_to_string(page).unwrap_or_else(|e| panic!("{}: {e}", page.display()));
    let rel = page
        .strip_prefix(root())
        .unwrap_or(page)
        .display()
        .to_string();
    let dir = page.parent().unwrap_or(Path::new("."));
    let mut problems = Vec::new();
    for (n, line) in prose_lines(&text) {
        for target in link_targets(line) {
            if target.is_empty()
                || target.contains("://")
                || target.starts_with("mailto:")
                || target.starts_with('<')
            {
                continue;
            }
            let (path, anchor) = match target.split_once('#') {
                Some((p, a)) => (p, Some(a)),
                None => (target.as_str(), None),
            };
            let file = if path.is_empty() {
                page.to_path_buf()
            } else {
                dir.join(path)
            };
            if !file.exists() {
                problems.push(format!("{rel}:{n}: link target {target} does not exist"));
                continue;
            }
            let Some(anchor) = anchor else { continue };
            if file.extension().and_then(|e| e.to_str()) != Some("md") {
                continue;
            }
            let target_text = fs::read_to_string(&file).unwrap_or_default();
            if !anchors(&target_text).contains(anchor) {
                problems.push(format!(
                    "{rel}:{n}: link {target}: no heading with anchor #{anchor} in {}",
                    file.strip_prefix(root()).unwrap_or(&file).display()
                ));
            }
        }
    }
    problems
}

/// Every command line the README shows: code spans and code-block lines that start with
/// `texavatars ` or `cargo run --release -- `, as argument vectors for the binary.
fn readme_commands(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut push = |n: usize, cmd: &str| {
        let cmd = cmd.trim();
        let args = if let Some(rest) = cmd.strip_prefix("cargo run --release -- ") {
            rest
        } else if let Some(rest) = cmd.strip_prefix("texavatars ") {
            rest
        } else {
            return;
        };
        out.push((n, args.trim().to_string()));
    };
    for (i, line) in text.lines().enumerate() {
        let n = i + 1;
        if line.starts_with("    ") {
            push(n, line);
        }
        let mut parts = line.split('`');
        parts.next();
        while let Some(span) = parts.next() {
            push(n, span);
            parts.next();
        }
    }
    out
}

#[test]
fn links_resolve() {
    let pages = markdown_files();
    assert!(
        pages.iter().any(|p| p.ends_with("README.md")) && pages.len() > 5,
        "the documentation was not found under {}",
        root().display()
    );
    let problems: Vec<String> = pages.iter().flat_map(|p| link_problems(p)).collect();
    assert!(
        problems.is_empty(),
        "{} broken link(s):\n{}",
        problems.len(),
        problems.join("\n")
    );
}

#[test]
fn readme_commands_parse() {
    let text = fs::read_to_string(root().join("README.md")).expect("README.md");
    let commands = readme_commands(&text);
    assert!(
        commands.len() >= 10,
        "found only {} commands in README.md",
        commands.len()
    );
    let mut problems = Vec::new();
    for (n, args) in &commands {
        let argv = std::iter::once("texavatars").chain(args.split_whitespace());
        if let Err(e) = Cli::try_parse_from(argv) {
            let first = e.to_string().lines().next().unwrap_or("").to_string();
            problems.push(format!("README.md:{n}: `texavatars {args}`: {first}"));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn readme_is_at_most_10_kb() {
    let len = fs::metadata(root().join("README.md"))
        .expect("README.md")
        .len() as usize;
    assert!(
        len <= README_MAX_BYTES,
        "README.md is {len} bytes, above {README_MAX_BYTES}: move detail into docs/"
    );
}

#[test]
fn the_check_finds_what_it_is_for() {
    // A broken link, a missing anchor and an unknown flag are caught; code is not a link.
    assert_eq!(
        link_targets("see [a](docs/x.md#y) and ![p](i.png) but `[c](d)`"),
        vec!["docs/x.md#y", "i.png"]
    );
    assert_eq!(
        slug("CPU training against PyTorch (`cargo bench --bench cpu_vs_torch`)"),
        "cpu-training-against-pytorch-cargo-bench---bench-cpu_vs_torch"
    );
    assert_eq!(slug("`demo`: the main job"), "demo-the-main-job");
    let a = anchors("# T\n## Build\n## Build\n```\n# not a heading\n```\n");
    assert!(a.contains("build") && a.contains("build-1") && !a.contains("not-a-heading"));
    let cmds =
        readme_commands("run `texavatars demo --out x`:\n\n    cargo run --release -- demo\n");
    assert_eq!(cmds.len(), 2);
    assert!(Cli::try_parse_from(["texavatars", "demo", "--no-such-flag"]).is_err());
    assert!(Cli::try_parse_from(["texavatars", "demo", "--out", "x"]).is_ok());
}
