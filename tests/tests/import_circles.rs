//! No import circles inside a crate: in every crate of the workspace (each library, binary,
//! integration test, bench and example root), no source file imports from another file that
//! imports, directly or through others, from it. A file "imports from" another when it names an
//! item there by a `crate::`, `super::` or `self::` path, in a `use` or inline; a file naming its
//! own child modules (declared by its `mod` items) is not an import, so a `mod.rs` and the files
//! below it may use each other's items one way: children up.
//!
//! The check reads the sources as text (comments and string contents left out), builds each
//! crate's file graph from its `mod` declarations and those paths, and names every strongly
//! connected group of files with the imports that close it.

#![allow(clippy::unwrap_used)]

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// One token of Rust source: an identifier or keyword, a string literal's contents, or one
/// punctuation character (`::` is one token), with its 1-based line.
#[derive(Debug, Clone, PartialEq)]
enum Tok {
    Ident(String),
    Str(String),
    PathSep,
    Punct(char),
}

/// `src` as tokens, comments dropped, char literals and lifetimes skipped.
fn lex(src: &str) -> Vec<(Tok, usize)> {
    let c: Vec<char> = src.chars().collect();
    let (mut i, mut line, mut out) = (0, 1, Vec::new());
    while i < c.len() {
        let ch = c[i];
        let next = c.get(i + 1).copied();
        if ch == '\n' {
            line += 1;
            i += 1;
        } else if ch.is_whitespace() {
            i += 1;
        } else if ch == '/' && next == Some('/') {
            while i < c.len() && c[i] != '\n' {
                i += 1;
            }
        } else if ch == '/' && next == Some('*') {
            i = skip_block_comment(&c, i, &mut line);
        } else if let Some((end, text)) = string_literal(&c, i) {
            line += c[i..end].iter().filter(|&&x| x == '\n').count();
            out.push((Tok::Str(text), line));
            i = end;
        } else if ch == '\'' {
            i = skip_char_or_lifetime(&c, i);
        } else if ch.is_alphanumeric() || ch == '_' {
            let start = i;
            while i < c.len() && (c[i].is_alphanumeric() || c[i] == '_') {
                i += 1;
            }
            out.push((Tok::Ident(c[start..i].iter().collect()), line));
        } else if ch == ':' && next == Some(':') {
            out.push((Tok::PathSep, line));
            i += 2;
        } else {
            out.push((Tok::Punct(ch), line));
            i += 1;
        }
    }
    out
}

/// The index after the (nested) block comment opening at `i`, counting its newlines.
fn skip_block_comment(c: &[char], mut i: usize, line: &mut usize) -> usize {
    let mut depth = 0;
    while i < c.len() {
        if c[i] == '/' && c.get(i + 1) == Some(&'*') {
            depth += 1;
            i += 2;
        } else if c[i] == '*' && c.get(i + 1) == Some(&'/') {
            depth -= 1;
            i += 2;
            if depth == 0 {
                return i;
            }
        } else {
            *line += usize::from(c[i] == '\n');
            i += 1;
        }
    }
    i
}

/// A string literal at `i` (`"…"`, `b"…"`, `r#"…"#`, `br"…"`, `c"…"`): the index after it and its
/// contents (escapes left as written); `None` when none starts there.
fn string_literal(c: &[char], i: usize) -> Option<(usize, String)> {
    let mut j = i;
    if matches!(c[j], 'b' | 'c') && matches!(c.get(j + 1), Some('"' | 'r')) {
        j += 1;
    }
    if c[j] == 'r' && matches!(c.get(j + 1), Some('"' | '#')) {
        let mut hashes = 0;
        j += 1;
        while c.get(j) == Some(&'#') {
            hashes += 1;
            j += 1;
        }
        if c.get(j) != Some(&'"') {
            return None; // a raw identifier such as r#type
        }
        let start = j + 1;
        let mut k = start;
        while k < c.len() {
            if c[k] == '"' && (1..=hashes).all(|h| c.get(k + h) == Some(&'#')) {
                return Some((k + 1 + hashes, c[start..k].iter().collect()));
            }
            k += 1;
        }
        return Some((k, c[start..].iter().collect()));
    }
    if c[j] != '"' || (j > i && !matches!(c[i], 'b' | 'c')) {
        return None;
    }
    let start = j + 1;
    let mut k = start;
    while k < c.len() && c[k] != '"' {
        k += if c[k] == '\\' { 2 } else { 1 };
    }
    Some((k + 1, c[start..k.min(c.len())].iter().collect()))
}

/// The index after the char literal (`'x'`, `'\n'`) or lifetime quote at `i`.
fn skip_char_or_lifetime(c: &[char], i: usize) -> usize {
    if c.get(i + 1) == Some(&'\\') {
        let mut k = i + 2;
        while k < c.len() && c[k] != '\'' {
            k += 1;
        }
        return k + 1;
    }
    if c.get(i + 2) == Some(&'\'') {
        return i + 3;
    }
    i + 1 // a lifetime: its name lexes as an identifier, harmless
}

/// One module of a crate: its name, parent, children by name and the file that holds it (an
/// inline `mod x { … }` is held by its parent's file).
#[derive(Debug)]
struct Module {
    parent: Option<usize>,
    children: BTreeMap<String, usize>,
    file: usize,
}

/// A path a file names: the module it is named in, its segments and the line.
#[derive(Debug)]
struct NamedPath {
    module: usize,
    segments: Vec<String>,
    line: usize,
}

/// A crate's module tree and the paths each file names.
#[derive(Debug, Default)]
struct CrateTree {
    modules: Vec<Module>,
    /// Every file of the crate, index = the `file` of its modules.
    files: Vec<PathBuf>,
    /// The module each file holds at its top.
    file_module: Vec<usize>,
    paths: Vec<NamedPath>,
}

impl CrateTree {
    /// The tree of the crate whose root file is `root` (`lib.rs`, `main.rs`, a test or bench
    /// file); module files are found as rustc finds them (`x.rs`, `x/mod.rs`, `#[path]`).
    fn read(root: &Path) -> CrateTree {
        let mut t = CrateTree::default();
        t.add_file(root.to_path_buf(), None, true);
        t
    }

    /// Reads `file` as the module declared under `parent` (`None`: the crate root); `mod_rs`:
    /// whether its children live beside it (root, `mod.rs`, a `#[path]` file) rather than in a
    /// folder named after it.
    fn add_file(&mut self, file: PathBuf, parent: Option<(usize, String)>, mod_rs: bool) -> usize {
        let src = std::fs::read_to_string(&file)
            .unwrap_or_else(|e| panic!("cannot read {}: {e}", file.display()));
        let file_ix = self.files.len();
        self.files.push(file.clone());
        let module = self.new_module(parent, file_ix);
        self.file_module.push(module);
        let dir = file.parent().unwrap().to_path_buf();
        let child_dir = if mod_rs {
            dir.clone()
        } else {
            dir.join(file.file_stem().unwrap())
        };
        self.read_items(&lex(&src), module, &dir, child_dir);
        module
    }

    fn new_module(&mut self, parent: Option<(usize, String)>, file: usize) -> usize {
        let ix = self.modules.len();
        let parent_ix = parent.as_ref().map(|(p, _)| *p);
        self.modules.push(Module {
            parent: parent_ix,
            children: BTreeMap::new(),
            file,
        });
        if let Some((p, name)) = parent {
            self.modules[p].children.insert(name, ix);
        }
        ix
    }

    /// Walks one file's tokens: `mod` declarations (files read in turn, inline modules entered),
    /// `use` trees and inline `crate::`/`super::`/`self::` paths, each recorded with the module it
    /// is written in.
    fn read_items(&mut self, toks: &[(Tok, usize)], top: usize, dir: &Path, child_dir: PathBuf) {
        // One entry per open brace: the inline module it opens (with its children's folder).
        let mut braces: Vec<Option<(usize, PathBuf)>> = Vec::new();
        let current = |braces: &[Option<(usize, PathBuf)>]| {
            braces
                .iter()
                .rev()
                .flatten()
                .next()
                .map_or((top, child_dir.clone()), |(m, d)| (*m, d.clone()))
        };
        let mut path_attr: Option<String> = None;
        let mut i = 0;
        while i < toks.len() {
            let (module, mod_dir) = current(&braces);
            match &toks[i].0 {
                Tok::Punct('#') => {
                    if let Some(p) = path_attribute(&toks[i..]) {
                        path_attr = Some(p);
                    }
                }
                Tok::Punct('{') => braces.push(None),
                Tok::Punct('}') => {
                    braces.pop();
                }
                Tok::Ident(k) if k == "mod" => {
                    if let Some((Tok::Ident(name), _)) = toks.get(i + 1) {
                        let name = name.clone();
                        match toks.get(i + 2).map(|t| &t.0) {
                            Some(Tok::Punct(';')) => {
                                let (file, mod_rs) = match path_attr.take() {
                                    Some(p) => (dir.join(p), true),
                                    None => (module_file(&mod_dir, &name), false),
                                };
                                let mod_rs = mod_rs || file.ends_with("mod.rs");
                                self.add_file(file, Some((module, name)), mod_rs);
                                i += 3;
                                continue;
                            }
                            Some(Tok::Punct('{')) => {
                                let file = self.modules[module].file;
                                let inner = self.new_module(Some((module, name.clone())), file);
                                braces.push(Some((inner, mod_dir.join(&name))));
                                path_attr = None;
                                i += 3;
                                continue;
                            }
                            _ => {}
                        }
                    }
                }
                Tok::Ident(k) if k == "use" => {
                    let (paths, end) = use_tree(toks, i + 1);
                    for (segments, line) in paths {
                        self.name_path(module, segments, line);
                    }
                    i = end;
                    continue;
                }
                Tok::Ident(k)
                    if matches!(k.as_str(), "crate" | "super" | "self")
                        && toks.get(i + 1).map(|t| &t.0) == Some(&Tok::PathSep)
                        && !preceded_by_in(toks, i) =>
                {
                    let (segments, end) = plain_path(toks, i);
                    self.name_path(module, segments, toks[i].1);
                    i = end;
                    continue;
                }
                _ => {}
            }
            i += 1;
        }
    }

    fn name_path(&mut self, module: usize, segments: Vec<String>, line: usize) {
        if matches!(
            segments.first().map(String::as_str),
            Some("crate" | "super" | "self")
        ) {
            self.paths.push(NamedPath {
                module,
                segments,
                line,
            });
        }
    }

    /// The module a path named in `from` reaches: `crate`, `super` and `self` followed, then
    /// every segment that names a child module; the last item segment ends it.
    fn resolve(&self, from: usize, segments: &[String]) -> usize {
        let mut m = from;
        for s in segments {
            m = match s.as_str() {
                "crate" => 0,
                "super" => self.modules[m].parent.unwrap_or(0),
                "self" => m,
                name => match self.modules[m].children.get(name) {
                    Some(&c) => c,
                    None => break,
                },
            };
        }
        m
    }

    /// Whether module `m` is `ancestor` or below it.
    fn within(&self, mut m: usize, ancestor: usize) -> bool {
        loop {
            if m == ancestor {
                return true;
            }
            match self.modules[m].parent {
                Some(p) => m = p,
                None => return false,
            }
        }
    }

    /// The file graph: for each file, the files it imports from, each with the first path and
    /// line that does. A path into the file's own module or below is no edge.
    fn imports(&self) -> Vec<BTreeMap<usize, (String, usize)>> {
        let mut edges = vec![BTreeMap::new(); self.files.len()];
        for p in &self.paths {
            let from_file = self.modules[p.module].file;
            let target = self.resolve(p.module, &p.segments);
            if self.within(target, self.file_module[from_file]) {
                continue;
            }
            edges[from_file]
                .entry(self.modules[target].file)
                .or_insert_with(|| (p.segments.join("::"), p.line));
        }
        edges
    }
}

/// `dir/name.rs`, else `dir/name/mod.rs`.
fn module_file(dir: &Path, name: &str) -> PathBuf {
    let flat = dir.join(format!("{name}.rs"));
    if flat.exists() {
        flat
    } else {
        dir.join(name).join("mod.rs")
    }
}

/// The file of a `#[path = "…"]` attribute starting at `toks[0]` (`#`).
fn path_attribute(toks: &[(Tok, usize)]) -> Option<String> {
    match toks.get(1..5)?.iter().map(|t| &t.0).collect::<Vec<_>>()[..] {
        [Tok::Punct('['), Tok::Ident(p), Tok::Punct('='), Tok::Str(s)] if p == "path" => {
            Some(s.clone())
        }
        _ => None,
    }
}

/// Whether the path at `i` is a visibility's (`pub(in crate::x)`), not an import.
fn preceded_by_in(toks: &[(Tok, usize)], i: usize) -> bool {
    i > 1 && toks[i - 1].0 == Tok::Ident("in".into()) && toks[i - 2].0 == Tok::Punct('(')
}

/// The identifiers of the path starting at `toks[i]`, up to its first non-identifier segment
/// (`::<`, `::{`, `::*`); returns them and the index after them.
fn plain_path(toks: &[(Tok, usize)], mut i: usize) -> (Vec<String>, usize) {
    let mut segments = Vec::new();
    while let Some((Tok::Ident(s), _)) = toks.get(i) {
        segments.push(s.clone());
        i += 1;
        if toks.get(i).map(|t| &t.0) != Some(&Tok::PathSep) {
            break;
        }
        i += 1;
    }
    (segments, i)
}

/// The full paths of the `use` tree starting at `toks[i]` (groups expanded, `self` in a group
/// meaning the group's prefix), each with its line; and the index after the closing `;`.
fn use_tree(toks: &[(Tok, usize)], i: usize) -> (Vec<(Vec<String>, usize)>, usize) {
    let mut out = Vec::new();
    let end = use_subtree(toks, i, &[], &mut out);
    let mut j = end;
    while j < toks.len() && toks[j].0 != Tok::Punct(';') {
        j += 1;
    }
    (out, j + 1)
}

fn use_subtree(
    toks: &[(Tok, usize)],
    mut i: usize,
    prefix: &[String],
    out: &mut Vec<(Vec<String>, usize)>,
) -> usize {
    let mut path = prefix.to_vec();
    let line = toks.get(i).map_or(0, |t| t.1);
    loop {
        match toks.get(i).map(|t| &t.0) {
            Some(Tok::Ident(s)) if s == "as" => {
                i += 2; // the alias
                break;
            }
            Some(Tok::Ident(s)) => {
                if !(s == "self" && !path.is_empty() && path.len() == prefix.len()) {
                    path.push(s.clone());
                }
                i += 1;
            }
            Some(Tok::PathSep) => i += 1,
            Some(Tok::Punct('{')) => {
                i += 1;
                while toks.get(i).is_some_and(|t| t.0 != Tok::Punct('}')) {
                    i = use_subtree(toks, i, &path, out);
                    if toks.get(i).map(|t| &t.0) == Some(&Tok::Punct(',')) {
                        i += 1;
                    }
                }
                return i + 1;
            }
            _ => break, // `*`, `,`, `}` or `;`
        }
    }
    out.push((path, line));
    i
}

/// The groups of two or more files that import from each other (Tarjan's strongly connected
/// components), each as file indices.
fn circles(edges: &[BTreeMap<usize, (String, usize)>]) -> Vec<Vec<usize>> {
    struct State<'a> {
        edges: &'a [BTreeMap<usize, (String, usize)>],
        index: Vec<Option<usize>>,
        low: Vec<usize>,
        stack: Vec<usize>,
        on_stack: Vec<bool>,
        next: usize,
        groups: Vec<Vec<usize>>,
    }
    fn visit(s: &mut State, v: usize) {
        s.index[v] = Some(s.next);
        s.low[v] = s.next;
        s.next += 1;
        s.stack.push(v);
        s.on_stack[v] = true;
        for &w in s.edges[v].keys() {
            match s.index[w] {
                None => {
                    visit(s, w);
                    s.low[v] = s.low[v].min(s.low[w]);
                }
                Some(iw) if s.on_stack[w] => s.low[v] = s.low[v].min(iw),
                Some(_) => {}
            }
        }
        if Some(s.low[v]) == s.index[v] {
            let mut group = Vec::new();
            while let Some(w) = s.stack.pop() {
                s.on_stack[w] = false;
                group.push(w);
                if w == v {
                    break;
                }
            }
            if group.len() > 1 {
                group.sort_unstable();
                s.groups.push(group);
            }
        }
    }
    let n = edges.len();
    let mut s = State {
        edges,
        index: vec![None; n],
        low: vec![0; n],
        stack: Vec::new(),
        on_stack: vec![false; n],
        next: 0,
        groups: Vec::new(),
    };
    for v in 0..n {
        if s.index[v].is_none() {
            visit(&mut s, v);
        }
    }
    s.groups
}

/// Every circle in the crate rooted at `root`, each described by its files' imports of each
/// other (`a.rs:12 → b.rs (crate::b::item)`), paths relative to `base`.
fn describe_circles(root: &Path, base: &Path) -> Vec<String> {
    let tree = CrateTree::read(root);
    let edges = tree.imports();
    let name = |f: usize| {
        let p = &tree.files[f];
        p.strip_prefix(base).unwrap_or(p).display().to_string()
    };
    circles(&edges)
        .into_iter()
        .map(|group| {
            let members: BTreeSet<usize> = group.iter().copied().collect();
            let arrows: Vec<String> = group
                .iter()
                .flat_map(|&a| {
                    edges[a]
                        .iter()
                        .filter(|(b, _)| members.contains(b))
                        .map(move |(&b, (path, line))| (a, b, path, line))
                })
                .map(|(a, b, path, line)| format!("{}:{line} → {} ({path})", name(a), name(b)))
                .collect();
            format!("circle in {}:\n    {}", name(0), arrows.join("\n    "))
        })
        .collect()
}

/// The crate roots of a package folder: `src/lib.rs`, `src/main.rs`, `src/bin/*.rs` and the
/// top-level files of `tests/`, `benches/` and `examples/`.
fn crate_roots(package: &Path) -> Vec<PathBuf> {
    let mut roots: Vec<PathBuf> = ["src/lib.rs", "src/main.rs"]
        .iter()
        .map(|r| package.join(r))
        .filter(|p| p.exists())
        .collect();
    for folder in ["src/bin", "tests", "benches", "examples"] {
        let Ok(entries) = std::fs::read_dir(package.join(folder)) else {
            continue;
        };
        let mut files: Vec<PathBuf> = entries
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|x| x == "rs"))
            .collect();
        files.sort();
        roots.extend(files);
    }
    roots
}

/// The workspace's package folders: the root `Cargo.toml`'s `members`.
fn workspace_packages(workspace: &Path) -> Vec<PathBuf> {
    let manifest = std::fs::read_to_string(workspace.join("Cargo.toml")).unwrap();
    let members = manifest
        .lines()
        .find(|l| l.trim_start().starts_with("members"))
        .expect("the workspace lists its members on one line");
    let toks = lex(members);
    let found: Vec<PathBuf> = toks
        .iter()
        .filter_map(|(t, _)| match t {
            Tok::Str(s) => Some(workspace.join(s)),
            _ => None,
        })
        .collect();
    assert!(!found.is_empty(), "no members in {members}");
    found
}

#[test]
fn no_file_imports_from_a_file_that_imports_from_it() {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let workspace = workspace.canonicalize().unwrap();
    let mut found = Vec::new();
    let mut roots = 0;
    for package in workspace_packages(&workspace) {
        for root in crate_roots(&package) {
            roots += 1;
            found.extend(describe_circles(&root, &workspace));
        }
    }
    assert!(
        roots >= 8,
        "only {roots} crate roots found under {}",
        workspace.display()
    );
    assert!(
        found.is_empty(),
        "{} import circle(s); move the item both sides use into a module of its own that \
         imports from neither:\n{}",
        found.len(),
        found.join("\n")
    );
}

/// A scratch crate: `files` (path under `src/`, contents) written to a fresh folder.
fn scratch_crate(name: &str, files: &[(&str, &str)]) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("slag-circles-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    for (path, text) in files {
        let p = dir.join("src").join(path);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, text).unwrap();
    }
    dir
}

#[test]
fn two_siblings_using_each_other_are_a_circle_and_a_parent_using_its_child_is_not() {
    let dir = scratch_crate(
        "siblings",
        &[
            ("lib.rs", "mod a;\npub mod b;\npub use crate::b::Thing;\n"),
            // `a` names `b` through a group and `super`; `b` names `a` inline in an expression.
            (
                "a/mod.rs",
                "pub mod inner;\nuse super::{b::{self, Thing}};\npub fn helper() {}\n",
            ),
            (
                "a/inner.rs",
                "/// `crate::b::Thing` in a comment is no import,\npub fn f() { let _ = \"crate::b::x\"; }\n",
            ),
            (
                "b.rs",
                "pub struct Thing;\nfn g() {\n    crate::a::helper();\n    crate::a::inner::f();\n}\n",
            ),
        ],
    );
    let found = describe_circles(&dir.join("src/lib.rs"), &dir);
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(
        found[0].contains("src/a/mod.rs:2 → src/b.rs (super::b)"),
        "{found:?}"
    );
    assert!(
        found[0].contains("src/b.rs:3 → src/a/mod.rs (crate::a::helper)"),
        "{found:?}"
    );
    assert!(
        !found[0].contains("inner.rs:"),
        "a comment or a string is no import: {found:?}"
    );
    let dir = scratch_crate(
        "parent",
        &[
            ("lib.rs", "mod p;\n"),
            ("p/mod.rs", "mod c;\npub use self::c::f;\npub struct T;\n"),
            ("p/c.rs", "use super::T;\npub fn f(_: T) {}\n"),
        ],
    );
    assert_eq!(
        describe_circles(&dir.join("src/lib.rs"), &dir),
        Vec::<String>::new()
    );
    let _ = std::fs::remove_dir_all(&dir);
}
