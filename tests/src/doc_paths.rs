//! Every repository path that README.md and docs/*.md name exists.
//!
//! In: README.md and the top-level docs/*.md. Checked: relative markdown links
//! (`[text](docs/api.md)`, `(../engine/src/relight.rs#L3)`), resolved against the file
//! that holds them, and inline code spans that look like repository paths (`` `engine/src/relight.rs` ``:
//! no spaces, a `/`, and a first component that is a top-level entry of the repository),
//! resolved against the repository root. Skipped: URLs, anchors within the page, fenced
//! code blocks, globs and placeholders (`*`, `{…}`, `?`, `<…>`), build output (`target/`),
//! and paths outside the repository (`../shared/…`, which may be absent). Out: a failure
//! that lists every missing path with its file and line.

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;
    use std::path::{Component, Path, PathBuf};

    fn root() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("..")
            .canonicalize()
            .expect("repository root")
    }

    /// README.md and docs/*.md (not the folders below docs/).
    fn markdown_files(root: &Path) -> Vec<PathBuf> {
        let mut files = vec![root.join("README.md")];
        let mut docs: Vec<PathBuf> = std::fs::read_dir(root.join("docs"))
            .expect("docs/")
            .map(|e| e.expect("docs/ entry").path())
            .filter(|p| p.extension().is_some_and(|e| e == "md"))
            .collect();
        docs.sort();
        files.extend(docs);
        files
    }

    /// Top-level names of the repository that a backticked path may start with.
    fn top_level(root: &Path) -> BTreeSet<String> {
        std::fs::read_dir(root)
            .expect("repository root")
            .map(|e| {
                e.expect("root entry")
                    .file_name()
                    .to_string_lossy()
                    .into_owned()
            })
            .filter(|n| !matches!(n.as_str(), ".git" | "target" | "bundles" | "demo-bundles"))
            .collect()
    }

    /// `a/./b/../c` → `a/c`, without touching the file system; `None` when the path climbs
    /// above the repository root (it is outside the repository).
    fn normalise(path: &Path) -> Option<PathBuf> {
        let mut out = PathBuf::new();
        for c in path.components() {
            match c {
                Component::CurDir => {}
                Component::ParentDir => {
                    if !out.pop() {
                        return None;
                    }
                }
                Component::Normal(n) => out.push(n),
                _ => return None,
            }
        }
        Some(out)
    }

    /// A target with its anchor, `:line` suffix and trailing punctuation removed; `None` for
    /// what is not a file path to check (URLs, page anchors, globs, placeholders).
    fn clean(target: &str) -> Option<&str> {
        let t = target.trim().trim_start_matches('<').trim_end_matches('>');
        if t.is_empty()
            || t.starts_with('#')
            || t.starts_with('/')
            || t.contains("://")
            || t.starts_with("mailto:")
        {
            return None;
        }
        let t = t.split('#').next()?;
        let t = t.split('?').next()?;
        if t.contains(['*', '{', '}', '<', '>', '$', '…']) {
            return None;
        }
        // `engine/src/solver.rs:120`
        let t = match t.rsplit_once(':') {
            Some((p, line)) if line.chars().all(|c| c.is_ascii_digit() || c == '-') => p,
            _ => t,
        };
        let t = t.trim_end_matches([',', '.', ';', ')']);
        (!t.is_empty()).then_some(t)
    }

    /// The targets of the markdown links of one line: `](target)` and reference
    /// definitions `[name]: target`.
    fn links(line: &str) -> Vec<String> {
        let mut out = Vec::new();
        let mut rest = line;
        while let Some(i) = rest.find("](") {
            let after = &rest[i + 2..];
            let end = after.find([')', ' ']).unwrap_or(after.len());
            out.push(after[..end].to_string());
            rest = &after[end..];
        }
        let t = line.trim_start();
        if t.starts_with('[')
            && let Some(j) = t.find("]: ")
        {
            out.push(
                t[j + 3..]
                    .split_whitespace()
                    .next()
                    .unwrap_or("")
                    .to_string(),
            );
        }
        out
    }

    /// The inline code spans of one line.
    fn code_spans(line: &str) -> Vec<&str> {
        line.split('`').skip(1).step_by(2).collect()
    }

    /// Every missing path of one markdown text, as `FILE:LINE: PATH (why)`.
    fn missing(root: &Path, file: &Path, text: &str, top: &BTreeSet<String>) -> Vec<String> {
        let dir = file.parent().expect("a file in a folder");
        let rel_dir = dir.strip_prefix(root).unwrap_or(Path::new(""));
        let name = file
            .strip_prefix(root)
            .unwrap_or(file)
            .display()
            .to_string();
        let mut out = Vec::new();
        let mut fenced = false;
        for (n, line) in text.lines().enumerate() {
            if line.trim_start().starts_with("```") {
                fenced = !fenced;
                continue;
            }
            if fenced {
                continue;
            }
            for target in links(line) {
                let Some(t) = clean(&target) else { continue };
                let Some(rel) = normalise(&rel_dir.join(t)) else {
                    continue; // outside the repository, e.g. ../shared/docs/PRODUCT.md
                };
                if rel.starts_with("target") {
                    continue;
                }
                if !root.join(&rel).exists() {
                    out.push(format!(
                        "{name}:{}: link ({target}) → {}",
                        n + 1,
                        rel.display()
                    ));
                }
            }
            for span in code_spans(line) {
                if span.contains(char::is_whitespace) || !span.contains('/') {
                    continue;
                }
                let Some(t) = clean(span) else { continue };
                let first = t.split('/').next().unwrap_or("");
                if !top.contains(first) {
                    continue;
                }
                let Some(rel) = normalise(Path::new(t)) else {
                    continue;
                };
                if !root.join(&rel).exists() {
                    out.push(format!("{name}:{}: `{span}`", n + 1));
                }
            }
        }
        out
    }

    #[test]
    fn every_path_named_in_the_readme_and_docs_exists() {
        let root = root();
        let top = top_level(&root);
        let mut dead = Vec::new();
        for file in markdown_files(&root) {
            let text = std::fs::read_to_string(&file).expect("a markdown file");
            dead.extend(missing(&root, &file, &text, &top));
        }
        assert!(
            dead.is_empty(),
            "{} path(s) named in README.md and docs/*.md do not exist:\n{}",
            dead.len(),
            dead.join("\n")
        );
    }

    #[test]
    fn a_dead_link_and_a_dead_backticked_path_are_found() {
        let root = root();
        let top = top_level(&root);
        let file = root.join("docs/example.md");
        let text = "See [the API](api.md), [gone](gone.md), [outside](../../x.md), \
                    [web](https://example.com/a.md) and [here](#top).\n\
                    `engine/src/lib.rs`, `engine/src/nowhere.rs:12`, `image/png`, \
                    `bench/results/table1-{date}.md`, `../shared/docs/PRODUCT.md`.\n\
                    ```sh\ncat engine/src/nowhere_either.rs\n```\n";
        let found = missing(&root, &file, text, &top);
        assert_eq!(
            found,
            [
                "docs/example.md:1: link (gone.md) → docs/gone.md",
                "docs/example.md:2: `engine/src/nowhere.rs:12`",
            ],
        );
    }
}
