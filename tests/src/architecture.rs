//! The workspace's structure, checked: dependencies between crates point one way
//! (`proto ← engine ← precompute ← server`), no crate has a cycle among its modules, and
//! every crate of the workspace has its own build settings in the root `Cargo.toml`.
//! See `docs/architecture.md`.
//!
//! In: the crates' `Cargo.toml` files and `src/` trees beside this crate. Out: test
//! failures naming the dependency that points the wrong way or the modules of a cycle.

#[cfg(test)]
mod tests {
    use std::collections::{BTreeMap, BTreeSet};
    use std::path::{Path, PathBuf};

    /// The crates in dependency order: each may depend only on those before it.
    const ORDER: [(&str, &str); 4] = [
        ("proto", "translux-proto"),
        ("engine", "translux-engine"),
        ("precompute", "translux-precompute"),
        ("server", "translux-server"),
    ];

    fn root() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
    }

    /// The package names under `[dependencies]` of a Cargo.toml (dev-dependencies and build
    /// dependencies excluded: tests may reach across).
    fn dependencies(toml: &str) -> BTreeSet<String> {
        let mut out = BTreeSet::new();
        let mut in_deps = false;
        for line in toml.lines() {
            let line = line.trim();
            if line.starts_with('[') {
                in_deps = line == "[dependencies]";
                continue;
            }
            if in_deps && let Some((name, _)) = line.split_once('=') {
                let name = name.trim().trim_end_matches(".workspace").trim();
                if !name.is_empty() && !name.starts_with('#') {
                    out.insert(name.to_string());
                }
            }
        }
        out
    }

    #[test]
    fn crate_dependencies_point_one_way() {
        for (k, (dir, _)) in ORDER.iter().enumerate() {
            let toml = std::fs::read_to_string(root().join(dir).join("Cargo.toml")).unwrap();
            let deps = dependencies(&toml);
            for (later, name) in &ORDER[k + 1..] {
                assert!(
                    !deps.contains(*name),
                    "{dir} depends on {name}, but {later} comes after it: dependencies \
                     point proto ← engine ← precompute ← server"
                );
            }
            // Nothing HTTP or GPU below the server.
            if *dir != "server" {
                for banned in ["axum", "hyper", "wgpu", "tokio"] {
                    assert!(!deps.contains(banned), "{dir} depends on {banned}");
                }
            }
        }
        let parse = dependencies(
            "[dependencies]\na.workspace = true\nb = \"1\"\n[dev-dependencies]\nc = \"1\"\n",
        );
        assert_eq!(parse, BTreeSet::from(["a".to_string(), "b".to_string()]));
    }

    /// The root `Cargo.toml`'s dev profile is the dependencies' (opt-level 3, no debug
    /// info) and names each of our crates with its own settings: a crate added to the
    /// workspace without its table would build like a dependency.
    #[test]
    fn every_workspace_crate_has_its_own_dev_profile() {
        let root_toml = std::fs::read_to_string(root().join("Cargo.toml")).unwrap();
        let members = root_toml
            .lines()
            .find_map(|l| l.trim().strip_prefix("members = ["))
            .expect("the workspace's members line");
        for dir in members.trim_end_matches(']').split(',') {
            let dir = dir.trim().trim_matches('"');
            let toml = std::fs::read_to_string(root().join(dir).join("Cargo.toml")).unwrap();
            let name = toml
                .lines()
                .find_map(|l| l.trim().strip_prefix("name = "))
                .map(|n| n.trim_matches('"'))
                .unwrap_or_else(|| panic!("{dir}/Cargo.toml names no package"));
            assert!(
                root_toml.contains(&format!("[profile.dev.package.{name}]")),
                "{name} ({dir}) has no [profile.dev.package.{name}] in Cargo.toml: it would \
                 build like a dependency (opt-level 3, no line tables)"
            );
        }
    }

    /// Top-level module of each `.rs` file under `src` → the top-level modules its non-test
    /// code names as `crate::x` (or `crate::{x, …}`).
    fn module_graph(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
        fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
            for e in std::fs::read_dir(dir).unwrap().flatten() {
                let p = e.path();
                if p.is_dir() {
                    walk(&p, out);
                } else if p.extension().is_some_and(|x| x == "rs") {
                    out.push(p);
                }
            }
        }
        let mut files = Vec::new();
        walk(src, &mut files);
        let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        for f in files {
            let rel = f.strip_prefix(src).unwrap();
            let first = rel
                .components()
                .next()
                .unwrap()
                .as_os_str()
                .to_string_lossy();
            let module = first.trim_end_matches(".rs").to_string();
            if module == "lib" || module == "main" {
                continue;
            }
            // A module's unit tests in their own file (`voxel/tests.rs`) are test code, like
            // an inline `mod tests`.
            if f.file_name().is_some_and(|n| n == "tests.rs") {
                continue;
            }
            let text = std::fs::read_to_string(&f).unwrap();
            let code = text.split("#[cfg(test)]\nmod tests").next().unwrap_or("");
            let deps = graph.entry(module.clone()).or_default();
            for line in code.lines() {
                let line = line.split("//").next().unwrap_or("");
                let mut rest = line;
                while let Some(i) = rest.find("crate::") {
                    rest = &rest[i + "crate::".len()..];
                    let names: Vec<&str> = if let Some(group) = rest.strip_prefix('{') {
                        group
                            .split('}')
                            .next()
                            .unwrap_or("")
                            .split(',')
                            .map(|n| n.trim().split("::").next().unwrap_or("").trim())
                            .collect()
                    } else {
                        vec![
                            rest.split(|c: char| !(c.is_alphanumeric() || c == '_'))
                                .next()
                                .unwrap_or(""),
                        ]
                    };
                    for n in names {
                        if !n.is_empty() && n != module {
                            deps.insert(n.to_string());
                        }
                    }
                }
            }
        }
        let modules: BTreeSet<String> = graph.keys().cloned().collect();
        for deps in graph.values_mut() {
            deps.retain(|d| modules.contains(d));
        }
        graph
    }

    /// The strongly connected components with more than one module (Tarjan).
    fn cycles(graph: &BTreeMap<String, BTreeSet<String>>) -> Vec<Vec<String>> {
        struct Walk<'a> {
            graph: &'a BTreeMap<String, BTreeSet<String>>,
            index: BTreeMap<&'a str, usize>,
            low: BTreeMap<&'a str, usize>,
            stack: Vec<&'a str>,
            on: BTreeSet<&'a str>,
            out: Vec<Vec<String>>,
        }
        impl<'a> Walk<'a> {
            fn visit(&mut self, v: &'a str) {
                let i = self.index.len();
                self.index.insert(v, i);
                self.low.insert(v, i);
                self.stack.push(v);
                self.on.insert(v);
                let graph = self.graph;
                for w in &graph[v] {
                    let w = w.as_str();
                    if !self.index.contains_key(w) {
                        self.visit(w);
                        let lw = self.low[w];
                        let lv = self.low.get_mut(v).unwrap();
                        *lv = (*lv).min(lw);
                    } else if self.on.contains(w) {
                        let iw = self.index[w];
                        let lv = self.low.get_mut(v).unwrap();
                        *lv = (*lv).min(iw);
                    }
                }
                if self.low[v] == self.index[v] {
                    let mut comp = Vec::new();
                    while let Some(w) = self.stack.pop() {
                        self.on.remove(w);
                        comp.push(w.to_string());
                        if w == v {
                            break;
                        }
                    }
                    if comp.len() > 1 {
                        comp.sort();
                        self.out.push(comp);
                    }
                }
            }
        }
        let mut walk = Walk {
            graph,
            index: BTreeMap::new(),
            low: BTreeMap::new(),
            stack: Vec::new(),
            on: BTreeSet::new(),
            out: Vec::new(),
        };
        for v in graph.keys() {
            if !walk.index.contains_key(v.as_str()) {
                walk.visit(v);
            }
        }
        walk.out
    }

    #[test]
    fn no_crate_has_a_module_cycle() {
        // The checker finds a planted cycle.
        let planted: BTreeMap<String, BTreeSet<String>> = [
            ("a", vec!["b"]),
            ("b", vec!["c"]),
            ("c", vec!["a"]),
            ("d", vec!["a"]),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v.into_iter().map(String::from).collect()))
        .collect();
        assert_eq!(cycles(&planted), vec![vec!["a", "b", "c"]]);

        for (dir, _) in ORDER {
            let graph = module_graph(&root().join(dir).join("src"));
            assert!(graph.len() > 3, "{dir}: {} modules found", graph.len());
            let found = cycles(&graph);
            assert!(
                found.is_empty(),
                "{dir} has module cycles (each list imports itself through crate::): {found:?}"
            );
        }
    }
}
