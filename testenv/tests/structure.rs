//! The workspace's structure, checked on every `cargo test`: within each crate no two source
//! files import each other through a chain (an import circle makes a set of files one unit
//! that can only be read, tested and changed together), and no function of a crate's `src/`
//! is longer than [`MAX_FUNCTION_LINES`] lines, except the SIMD kernels (functions compiled
//! with `#[target_feature]`, whose length is their unrolled lanes) and tests.
//!
//! Read as text: a file's imports are the `crate::`, `super::` and `self::` paths its code
//! names before its tests (in `use` items and inline); a path is the file of the longest
//! module it names. A file's
//! own ancestors and descendants in the module tree are not counted: a module and its
//! submodules are one unit by construction.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Longest function allowed, lines from its `fn` line to its closing brace.
const MAX_FUNCTION_LINES: usize = 120;

/// The workspace root (this crate's parent folder).
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_default()
}

/// The crates: every folder of the root with a `Cargo.toml` and a `src/` (the fuzz targets
/// are a crate outside the workspace and checked with it too).
fn crates() -> Vec<PathBuf> {
    let mut out: Vec<PathBuf> = std::fs::read_dir(root())
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("Cargo.toml").is_file() && p.join("src").is_dir())
        .collect();
    out.sort();
    out
}

/// The `.rs` files under `dir`, recursively.
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                todo.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// The module path of `file` under `src` (`[]` for `lib.rs` and `main.rs`).
fn module_of(src: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src).unwrap_or(file);
    let mut parts: Vec<String> = rel
        .iter()
        .map(|c| c.to_string_lossy().into_owned())
        .collect();
    let last = parts.pop().unwrap_or_default();
    let stem = last.trim_end_matches(".rs");
    let at_root = parts.is_empty() && (stem == "lib" || stem == "main");
    if stem != "mod" && !at_root {
        parts.push(stem.to_string());
    }
    parts
}

/// `text` with comments, string and character literals blanked (replaced by spaces, newlines
/// kept), so that braces and paths are read from code alone.
fn code_only(text: &str) -> String {
    let b: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    let blank = |c: char| if c == '\n' { '\n' } else { ' ' };
    while i < b.len() {
        let c = b[i];
        let next = b.get(i + 1).copied().unwrap_or('\0');
        if c == '/' && next == '/' {
            while i < b.len() && b[i] != '\n' {
                out.push(' ');
                i += 1;
            }
        } else if c == '/' && next == '*' {
            let mut depth = 0;
            while i < b.len() {
                if b[i] == '/' && b.get(i + 1) == Some(&'*') {
                    depth += 1;
                    out.push_str("  ");
                    i += 2;
                } else if b[i] == '*' && b.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    out.push_str("  ");
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    out.push(blank(b[i]));
                    i += 1;
                }
            }
        } else if c == 'r' && (next == '"' || next == '#') && !prev_is_ident(&b, i) {
            // A raw string r"…", r#"…"#: ends at a quote followed by as many hashes.
            let mut j = i + 1;
            let mut hashes = 0;
            while b.get(j) == Some(&'#') {
                hashes += 1;
                j += 1;
            }
            if b.get(j) != Some(&'"') {
                out.push(c);
                i += 1;
                continue;
            }
            j += 1;
            while j < b.len() {
                if b[j] == '"' && (0..hashes).all(|k| b.get(j + 1 + k) == Some(&'#')) {
                    j += 1 + hashes;
                    break;
                }
                j += 1;
            }
            for &x in &b[i..j.min(b.len())] {
                out.push(blank(x));
            }
            i = j;
        } else if c == '"' {
            let mut j = i + 1;
            while j < b.len() && b[j] != '"' {
                j += if b[j] == '\\' { 2 } else { 1 };
            }
            for &x in &b[i..(j + 1).min(b.len())] {
                out.push(blank(x));
            }
            i = j + 1;
        } else if c == '\'' {
            // A character literal ('x', '\n', '\u{…}'), not a lifetime ('a).
            let end = if next == '\\' {
                (i + 2..b.len().min(i + 12)).find(|&k| b[k] == '\'')
            } else if b.get(i + 2) == Some(&'\'') {
                Some(i + 2)
            } else {
                None
            };
            match end {
                Some(e) => {
                    for _ in i..=e {
                        out.push(' ');
                    }
                    i = e + 1;
                }
                None => {
                    out.push(c);
                    i += 1;
                }
            }
        } else {
            out.push(c);
            i += 1;
        }
    }
    out
}

fn prev_is_ident(b: &[char], i: usize) -> bool {
    i > 0 && (b[i - 1].is_alphanumeric() || b[i - 1] == '_')
}

/// The module paths `code` names from `module`: `crate::a::b`, `super::c`, `self::d`, with
/// `use` groups (`crate::{a, b::c}`) expanded.
fn named_paths(code: &str, module: &[String]) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    for (start, head) in [("crate::", 0), ("super::", 1), ("self::", 2)] {
        let mut from = 0;
        while let Some(at) = code[from..].find(start).map(|k| k + from) {
            from = at + start.len();
            if at > 0 && {
                let p = code[..at].chars().next_back().unwrap_or(' ');
                p.is_alphanumeric() || p == '_' || p == ':'
            } {
                continue;
            }
            // The base module the path starts from.
            let mut base: Vec<String> = match head {
                0 => Vec::new(),
                1 => {
                    let mut m = module.to_vec();
                    m.pop();
                    m
                }
                _ => module.to_vec(),
            };
            let mut rest = &code[from..];
            // Chains of `super::super::`.
            while let Some(r) = rest.strip_prefix("super::") {
                base.pop();
                rest = r;
            }
            out.extend(expand(base, rest));
        }
    }
    out
}

/// The paths of `rest` (what follows a path's head) from `base`, `use` groups (`{a, b::c}`,
/// nested too) expanded.
fn expand(base: Vec<String>, rest: &str) -> Vec<Vec<String>> {
    if let Some(group) = rest.strip_prefix('{') {
        let chars: Vec<char> = rest.chars().collect();
        let close = matching(&chars, 0);
        let inner: String = group.chars().take(close.saturating_sub(1)).collect();
        return split_top(&inner)
            .into_iter()
            .flat_map(|item| expand(base.clone(), item.trim()))
            .collect();
    }
    let names = idents(rest);
    let consumed: usize = names.iter().map(|n| n.len() + 2).sum::<usize>();
    let mut path = base;
    path.extend(names);
    match rest
        .get(consumed.saturating_sub(2)..)
        .and_then(|r| r.strip_prefix("::{"))
    {
        Some(_) if consumed > 0 => expand(path, &rest[consumed..]),
        _ => vec![path],
    }
}

/// The identifiers of a path's start `a::b::c…` (stops at anything else).
fn idents(s: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = s;
    loop {
        let end = rest
            .find(|c: char| !(c.is_alphanumeric() || c == '_'))
            .unwrap_or(rest.len());
        if end == 0 {
            break;
        }
        out.push(rest[..end].to_string());
        match rest[end..].strip_prefix("::") {
            Some(r) if !r.starts_with('{') => rest = r,
            _ => break,
        }
    }
    out
}

/// The char index of the brace closing the one at char index `open`.
fn matching(chars: &[char], open: usize) -> usize {
    let mut depth = 0;
    for (k, &c) in chars.iter().enumerate().skip(open) {
        match c {
            '{' => depth += 1,
            '}' => {
                depth -= 1;
                if depth == 0 {
                    return k;
                }
            }
            _ => {}
        }
    }
    chars.len()
}

/// `s` split at its top-level commas.
fn split_top(s: &str) -> Vec<&str> {
    let mut out = Vec::new();
    let (mut depth, mut last) = (0, 0);
    for (k, c) in s.char_indices() {
        match c {
            '{' => depth += 1,
            '}' => depth -= 1,
            ',' if depth == 0 => {
                out.push(&s[last..k]);
                last = k + 1;
            }
            _ => {}
        }
    }
    out.push(&s[last..]);
    out
}

/// Whether `a` is an ancestor of `b` in the module tree, or `b` itself.
fn ancestor_or_self(a: &[String], b: &[String]) -> bool {
    b.starts_with(a)
}

/// The import circles of one crate: each a list of files, in order.
fn circles(krate: &Path) -> Vec<Vec<String>> {
    let src = krate.join("src");
    let files = rust_files(&src);
    let modules: BTreeMap<Vec<String>, usize> = files
        .iter()
        .enumerate()
        .map(|(i, f)| (module_of(&src, f), i))
        .collect();
    let mut edges: Vec<BTreeSet<usize>> = vec![BTreeSet::new(); files.len()];
    for (i, f) in files.iter().enumerate() {
        let Ok(text) = std::fs::read_to_string(f) else {
            continue;
        };
        let code = code_only(&text);
        // A file's tests may reach anywhere in the crate: they are not its imports.
        let code = code.split("#[cfg(test)]").next().unwrap_or_default();
        let module = module_of(&src, f);
        for path in named_paths(code, &module) {
            // The file of the longest module the path names.
            let target = (0..=path.len())
                .rev()
                .find_map(|n| modules.get(&path[..n]).map(|&t| (t, n)));
            let Some((t, n)) = target else { continue };
            let target_module = &path[..n];
            if t != i
                && !ancestor_or_self(target_module, &module)
                && !ancestor_or_self(&module, target_module)
            {
                edges[i].insert(t);
            }
        }
    }
    strongly_connected(&edges)
        .into_iter()
        .filter(|c| c.len() > 1)
        .map(|c| {
            c.iter()
                .map(|&k| {
                    files[k]
                        .strip_prefix(root())
                        .unwrap_or(&files[k])
                        .display()
                        .to_string()
                })
                .collect()
        })
        .collect()
}

/// Tarjan's strongly connected components of the graph `edges`.
fn strongly_connected(edges: &[BTreeSet<usize>]) -> Vec<Vec<usize>> {
    struct T<'a> {
        edges: &'a [BTreeSet<usize>],
        index: Vec<Option<usize>>,
        low: Vec<usize>,
        on: Vec<bool>,
        stack: Vec<usize>,
        next: usize,
        out: Vec<Vec<usize>>,
    }
    fn visit(t: &mut T, v: usize) {
        t.index[v] = Some(t.next);
        t.low[v] = t.next;
        t.next += 1;
        t.stack.push(v);
        t.on[v] = true;
        for &w in t.edges[v].iter() {
            match t.index[w] {
                None => {
                    visit(t, w);
                    t.low[v] = t.low[v].min(t.low[w]);
                }
                Some(iw) if t.on[w] => t.low[v] = t.low[v].min(iw),
                _ => {}
            }
        }
        if Some(t.low[v]) == t.index[v] {
            let mut c = Vec::new();
            while let Some(w) = t.stack.pop() {
                t.on[w] = false;
                c.push(w);
                if w == v {
                    break;
                }
            }
            t.out.push(c);
        }
    }
    let n = edges.len();
    let mut t = T {
        edges,
        index: vec![None; n],
        low: vec![0; n],
        on: vec![false; n],
        stack: Vec::new(),
        next: 0,
        out: Vec::new(),
    };
    for v in 0..n {
        if t.index[v].is_none() {
            visit(&mut t, v);
        }
    }
    t.out
}

/// Functions of `text` (code only) longer than the limit: `(line, name, lines)`, leaving out
/// SIMD kernels and whatever follows a `#[cfg(test)]`.
fn long_functions(text: &str) -> Vec<(usize, String, usize)> {
    let code = code_only(text);
    let lines: Vec<&str> = code.lines().collect();
    let chars: Vec<char> = code.chars().collect();
    // Char index of each line's start.
    let mut starts = Vec::with_capacity(lines.len());
    let mut at = 0;
    for l in &lines {
        starts.push(at);
        at += l.chars().count() + 1;
    }
    let mut out = Vec::new();
    for (n, line) in lines.iter().enumerate() {
        let t = line.trim_start();
        if t.starts_with("#[cfg(test)]") {
            break;
        }
        let Some(k) = fn_keyword(t) else { continue };
        let name: String = t[k + 3..]
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect();
        let kernel = lines[n.saturating_sub(4)..n]
            .iter()
            .any(|l| l.contains("#[target_feature"));
        // The body's opening brace: the first `{` or `;` after the signature.
        let from = starts[n];
        let Some(open) = (from..chars.len()).find(|&c| chars[c] == '{' || chars[c] == ';') else {
            continue;
        };
        if chars[open] == ';' || kernel {
            continue;
        }
        let close = matching(&chars, open);
        let end_line = starts.partition_point(|&s| s <= close);
        let length = end_line - n;
        if length > MAX_FUNCTION_LINES {
            out.push((n + 1, name, length));
        }
    }
    out
}

/// Where `fn ` starts in a trimmed line that declares a function, if it does.
fn fn_keyword(t: &str) -> Option<usize> {
    let mut rest = t;
    let mut skipped = 0;
    for prefix in [
        "pub(crate) ",
        "pub(super) ",
        "pub ",
        "const ",
        "async ",
        "unsafe ",
        "extern \"C\" ",
    ] {
        if let Some(r) = rest.strip_prefix(prefix) {
            skipped += prefix.len();
            rest = r;
        }
    }
    rest.starts_with("fn ").then_some(skipped)
}

#[test]
fn no_import_circle_between_the_files_of_a_crate() {
    let found: Vec<String> = crates()
        .iter()
        .flat_map(|c| circles(c))
        .map(|c| c.join(" → "))
        .collect();
    assert!(
        found.is_empty(),
        "files that import each other through a chain:\n{}",
        found.join("\n")
    );
}

#[test]
fn no_function_longer_than_the_limit_outside_simd_kernels() {
    let mut found = Vec::new();
    for krate in crates() {
        for f in rust_files(&krate.join("src")) {
            let Ok(text) = std::fs::read_to_string(&f) else {
                continue;
            };
            for (line, name, length) in long_functions(&text) {
                let shown = f.strip_prefix(root()).unwrap_or(&f).display().to_string();
                found.push(format!("{shown}:{line} {name}: {length} lines"));
            }
        }
    }
    assert!(
        found.is_empty(),
        "functions over {MAX_FUNCTION_LINES} lines (split them by concept):\n{}",
        found.join("\n")
    );
}

#[test]
fn the_reader_sees_circles_and_long_functions() {
    // Two files that name each other make one circle; a sibling named one way does not.
    let module = vec!["a".to_string()];
    let paths = named_paths(
        &code_only("use super::b::{X, c::Y};\nfn f() { crate::d::g(); let s = \"crate::e\"; }"),
        &module,
    );
    assert_eq!(
        paths,
        vec![
            vec!["d".to_string(), "g".to_string()],
            vec!["b".to_string(), "X".to_string()],
            vec!["b".to_string(), "c".to_string(), "Y".to_string()],
        ]
    );
    let edges = vec![
        BTreeSet::from([1]),
        BTreeSet::from([0]),
        BTreeSet::from([0]),
    ];
    let mut c = strongly_connected(&edges);
    c.iter_mut().for_each(|c| c.sort_unstable());
    assert!(c.contains(&vec![0, 1]) && c.contains(&vec![2]), "{c:?}");
    // A function of 122 lines is found; a kernel of the same length and a short one are not.
    let body = "    let x = 1;\n".repeat(120);
    let text = format!(
        "fn long() {{\n{body}}}\n#[target_feature(enable = \"avx2\")]\nunsafe fn kernel() {{\n{body}}}\nfn short() {{ '{{'; }}\n"
    );
    assert_eq!(long_functions(&text), vec![(1, "long".to_string(), 122)]);
}
