//! The layering rules the crate boundary does not cover, checked on the sources.
//!
//! `cellgate-core` cannot import tokio or zenoh: its Cargo.toml has neither, so the compiler
//! keeps that rule. What is left is the order of the modules inside each crate: a module may
//! import its own submodules and the modules of lower layers, never one of its own layer or
//! above, so no two modules import each other and the layers of `docs/architecture.md` stay
//! true. And in the gateway only the bus side (`bus`, `client`, `gateway`, the binary) speaks
//! zenoh: links, jobs and transports can run without a bus.
//!
//! Test code (`tests.rs`, `#[cfg(test)]` modules) is not checked: a test may reach anywhere.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The core's modules, lowest layer first.
const CORE_LAYERS: &[&[&str]] = &[
    &["pb", "keys", "near"],
    &["codes"],
    &["engine"],
    &["fanuc", "fuji"],
    &["program"],
    &["bounds", "history"],
    &["config"],
    &["plc", "sim"],
    &["mtconnect"],
    &["opcua"],
];

/// The gateway's modules, lowest layer first.
const GATEWAY_LAYERS: &[&[&str]] = &[
    &["telemetry", "storage"],
    &["transport", "door"],
    &["link", "library"],
    &["jobs", "plc", "sim"],
    &["history"],
    &["bus"],
    &["cell", "client"],
    &["console"],
    &["mtconnect", "opcua", "historian"],
    &["gateway", "soak"],
];

/// Gateway modules that may use zenoh.
const ZENOH_MODULES: &[&str] = &[
    "bus",
    "client",
    "console",
    "mtconnect",
    "opcua",
    "historian",
    "gateway",
    "soak",
];

fn sources(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}

/// The top module a source file belongs to (`bus` for `src/bus/route_job.rs`), or `None` for
/// the crate root and test files.
fn top_module(root: &Path, file: &Path) -> Option<String> {
    let rel = file.strip_prefix(root).unwrap();
    let name = rel.file_name()?.to_str()?;
    if rel.components().count() == 1 && (name == "lib.rs" || name == "main.rs") {
        return None;
    }
    // The binary's own modules (`src/main/`) sit on top of the library, as `main.rs` does.
    if rel.starts_with("main") {
        return None;
    }
    if name == "tests.rs" || name == "testkit.rs" {
        return None;
    }
    let first = rel.components().next()?.as_os_str().to_str()?;
    Some(first.trim_end_matches(".rs").to_string())
}

/// The code of a file outside its test modules, without comments.
fn production_code(text: &str) -> String {
    let code = match text.find("#[cfg(test)]") {
        Some(i) => &text[..i],
        None => text,
    };
    code.lines()
        .map(|l| match l.find("//") {
            Some(i) => &l[..i],
            None => l,
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// Every `crate::<module>` a file's code names.
fn crate_imports(code: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = code;
    while let Some(i) = rest.find("crate::") {
        let before = rest[..i].chars().next_back();
        rest = &rest[i + "crate::".len()..];
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == ':') {
            continue; // `cellgate_core::…` and the like
        }
        let name: String = rest
            .chars()
            .take_while(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || *c == '_')
            .collect();
        if !name.is_empty() {
            out.push(name);
        }
    }
    out
}

fn layer_of(layers: &'static [&'static [&'static str]]) -> BTreeMap<&'static str, usize> {
    let mut map = BTreeMap::new();
    for (i, layer) in layers.iter().enumerate() {
        for m in *layer {
            map.insert(*m, i);
        }
    }
    map
}

fn violations(root: &Path, layers: &'static [&'static [&'static str]]) -> Vec<String> {
    let layer = layer_of(layers);
    let mut found = Vec::new();
    for file in sources(root) {
        let Some(module) = top_module(root, &file) else {
            continue;
        };
        let Some(&own) = layer.get(module.as_str()) else {
            found.push(format!(
                "{}: module `{module}` is in no layer of this test",
                file.display()
            ));
            continue;
        };
        let code = production_code(&std::fs::read_to_string(&file).unwrap());
        for import in crate_imports(&code) {
            if import == module {
                continue;
            }
            match layer.get(import.as_str()) {
                Some(&l) if l < own => {}
                Some(_) => found.push(format!(
                    "{}: `{module}` imports `crate::{import}`, which is not below it",
                    file.display()
                )),
                None => {} // a crate-root item (`crate::pb` re-exports and the like)
            }
        }
    }
    found
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn core_modules_import_only_lower_layers() {
    let found = violations(&root().join("crates/cellgate-core/src"), CORE_LAYERS);
    assert!(found.is_empty(), "{}", found.join("\n"));
}

#[test]
fn gateway_modules_import_only_lower_layers() {
    let found = violations(&root().join("src"), GATEWAY_LAYERS);
    assert!(found.is_empty(), "{}", found.join("\n"));
}

#[test]
fn only_the_bus_side_of_the_gateway_speaks_zenoh() {
    let src = root().join("src");
    let mut found = Vec::new();
    for file in sources(&src) {
        let Some(module) = top_module(&src, &file) else {
            continue;
        };
        let code = production_code(&std::fs::read_to_string(&file).unwrap());
        if !ZENOH_MODULES.contains(&module.as_str()) && code.contains("zenoh::") {
            found.push(file.display().to_string());
        }
    }
    assert!(
        found.is_empty(),
        "zenoh used outside {ZENOH_MODULES:?}: {found:?}"
    );
}

#[test]
fn the_checker_sees_a_backward_import() {
    // The checker itself: a lower module naming a higher one is caught.
    assert_eq!(
        crate_imports("use crate::bus::keys; x::crate::no; cellgate_core::pb"),
        ["bus"]
    );
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("link")).unwrap();
    std::fs::write(dir.path().join("link/mod.rs"), "use crate::bus::X;\n").unwrap();
    std::fs::write(
        dir.path().join("bus.rs"),
        "use crate::link::Y;\n#[cfg(test)]\nmod t { use crate::gateway::Z; }\n",
    )
    .unwrap();
    let found = violations(dir.path(), GATEWAY_LAYERS);
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(
        found[0].contains("`link` imports `crate::bus`"),
        "{found:?}"
    );
}

/// The modules of `bus/` (`bus` for its `mod.rs`), each with the modules of `bus/` its code
/// names: `super::X`, `crate::bus::X` and, in `mod.rs`, `self::X` or `X::` for a child `X`. An
/// item of `mod.rs` named from a child (`super::BusError`) is an import of `bus` itself.
fn bus_imports(dir: &Path) -> BTreeMap<String, std::collections::BTreeSet<String>> {
    let mut children = std::collections::BTreeSet::new();
    for file in sources(dir) {
        let rel = file.strip_prefix(dir).unwrap();
        if rel.components().count() == 1 {
            let name = rel.file_stem().unwrap().to_str().unwrap();
            if name != "mod" && name != "tests" {
                children.insert(name.to_string());
            }
        }
    }
    let mut graph = BTreeMap::new();
    for file in sources(dir) {
        let rel = file.strip_prefix(dir).unwrap();
        if rel.components().count() != 1 {
            continue; // `acl/tests.rs` and the like: test code
        }
        let stem = rel.file_stem().unwrap().to_str().unwrap();
        if stem == "tests" {
            continue;
        }
        let module = if stem == "mod" { "bus" } else { stem };
        let code = production_code(&std::fs::read_to_string(&file).unwrap());
        let mut names = std::collections::BTreeSet::new();
        for prefix in ["super::", "crate::bus::", "self::", ""] {
            if prefix == "self::" || prefix.is_empty() {
                if module != "bus" {
                    continue;
                }
            } else if prefix == "super::" && module == "bus" {
                continue;
            }
            for target in paths_after(&code, prefix) {
                if children.contains(&target) {
                    names.insert(target);
                } else if !prefix.is_empty() && module != "bus" {
                    names.insert("bus".to_string());
                }
            }
        }
        names.remove(module);
        graph.insert(module.to_string(), names);
    }
    graph
}

/// The first segment of every path after `prefix` in `code` (each name of a `{a, b::c}`
/// group); with an empty prefix, every `name::` that starts a path.
fn paths_after(code: &str, prefix: &str) -> Vec<String> {
    let ident = |c: char| c.is_alphanumeric() || c == '_';
    let mut out = Vec::new();
    let pattern = if prefix.is_empty() { "::" } else { prefix };
    let mut from = 0;
    while let Some(i) = code[from..].find(pattern) {
        let at = from + i;
        from = at + pattern.len();
        if prefix.is_empty() {
            // `name::` with nothing path-like before `name`.
            let head: String = code[..at]
                .chars()
                .rev()
                .take_while(|c| ident(*c))
                .collect::<Vec<_>>()
                .into_iter()
                .rev()
                .collect();
            let before = code[..at - head.len()].chars().next_back();
            if !head.is_empty() && !before.is_some_and(|c| ident(c) || c == ':') {
                out.push(head);
            }
            continue;
        }
        let before = code[..at].chars().next_back();
        if before.is_some_and(|c| ident(c) || c == ':') {
            continue; // `cellgate_core::…`, `a::super::…`
        }
        let rest = &code[from..];
        if let Some(group) = rest.strip_prefix('{') {
            // One level of `{…}`: each member's first segment.
            let end = group.find('}').unwrap_or(group.len());
            for member in group[..end].split(',') {
                let name: String = member.trim().chars().take_while(|c| ident(*c)).collect();
                if !name.is_empty() && name != "self" {
                    out.push(name);
                }
            }
        } else {
            let name: String = rest.chars().take_while(|c| ident(*c)).collect();
            if !name.is_empty() {
                out.push(name);
            }
        }
    }
    out
}

/// A cycle of `graph`, if it has one, as the modules along it.
fn cycle(graph: &BTreeMap<String, std::collections::BTreeSet<String>>) -> Option<Vec<String>> {
    // Depth first: 0 unseen, 1 on the current path, 2 done.
    fn visit(
        node: &str,
        graph: &BTreeMap<String, std::collections::BTreeSet<String>>,
        state: &mut BTreeMap<String, u8>,
        path: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        state.insert(node.to_string(), 1);
        path.push(node.to_string());
        for next in graph.get(node).into_iter().flatten() {
            match state.get(next).copied().unwrap_or(0) {
                1 => {
                    let start = path.iter().position(|n| n == next).unwrap_or(0);
                    let mut found = path[start..].to_vec();
                    found.push(next.clone());
                    return Some(found);
                }
                0 => {
                    if let Some(found) = visit(next, graph, state, path) {
                        return Some(found);
                    }
                }
                _ => {}
            }
        }
        path.pop();
        state.insert(node.to_string(), 2);
        None
    }
    let mut state = BTreeMap::new();
    for node in graph.keys() {
        if state.get(node).copied().unwrap_or(0) == 0 {
            let mut path = Vec::new();
            if let Some(found) = visit(node, graph, &mut state, &mut path) {
                return Some(found);
            }
        }
    }
    None
}

#[test]
fn bus_modules_import_one_another_without_a_cycle() {
    let graph = bus_imports(&root().join("src/bus"));
    assert!(graph.len() > 20, "{graph:?}");
    if let Some(found) = cycle(&graph) {
        panic!("bus/ imports in a circle: {}", found.join(" -> "));
    }
}

#[test]
fn the_checker_sees_a_bus_cycle() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, text: &str| std::fs::write(dir.path().join(name), text).unwrap();
    write(
        "mod.rs",
        "mod a;\nmod b;\nmod c;\npub use a::X;\nuse self::c::Z;\n",
    );
    write("a.rs", "use super::b::Y;\n");
    write(
        "b.rs",
        "use super::{Thing, c};\n#[cfg(test)]\nmod t { use super::a; }\n",
    );
    write("c.rs", "use cellgate_core::keys::super_thing;\n");
    write("tests.rs", "use super::a::X;\n");
    let graph = bus_imports(dir.path());
    let edges = |m: &str| graph[m].iter().cloned().collect::<Vec<_>>();
    assert_eq!(edges("bus"), ["a", "c"]);
    assert_eq!(edges("a"), ["b"]);
    assert_eq!(edges("b"), ["bus", "c"]);
    assert!(edges("c").is_empty());
    assert_eq!(
        cycle(&graph).unwrap(),
        ["a", "b", "bus", "a"].map(String::from)
    );
    // Without `Thing` from `mod.rs` the circle is gone.
    write("b.rs", "use super::c;\n");
    assert_eq!(cycle(&bus_imports(dir.path())), None);
}

/// The top modules of a crate's `src/`, from its files and folders (`main` aside: the
/// binary's own modules).
fn top_modules(src: &Path) -> Vec<String> {
    let mut out: Vec<String> = std::fs::read_dir(src)
        .unwrap()
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let module = name.strip_suffix(".rs").unwrap_or(&name).to_string();
            let is_module = name.ends_with(".rs")
                || e.path().join("mod.rs").exists()
                || src.join(format!("{name}.rs")).exists();
            (is_module && !["lib", "main", "tests", "testkit"].contains(&module.as_str()))
                .then_some(module)
        })
        .collect();
    out.sort();
    out.dedup();
    out
}

/// The maps say where everything is: each crate's `lib.rs` names every top module of it,
/// every one is in a layer of this test, and docs/architecture.md names every room of the
/// gateway (`src/NAME`) and every module of the core.
#[test]
fn the_maps_name_every_module() {
    let arch = std::fs::read_to_string(root().join("docs/architecture.md")).unwrap();
    let mut missing = Vec::new();
    for (src, layers, in_arch) in [
        (root().join("src"), GATEWAY_LAYERS, "`src/"),
        (root().join("crates/cellgate-core/src"), CORE_LAYERS, "| `"),
    ] {
        let lib = std::fs::read_to_string(src.join("lib.rs")).unwrap();
        for m in top_modules(&src) {
            if !lib.contains(&format!("[`{m}`]")) && !lib.contains(&format!("`{m}`")) {
                missing.push(format!("{}: lib.rs does not name {m}", src.display()));
            }
            if !layers.iter().any(|l| l.contains(&m.as_str())) && m != "testkit" {
                missing.push(format!(
                    "{}: {m} is in no layer of this test",
                    src.display()
                ));
            }
            if !arch.contains(&format!("{in_arch}{m}")) {
                missing.push(format!("docs/architecture.md does not name {in_arch}{m}"));
            }
        }
    }
    assert!(missing.is_empty(), "{missing:#?}");
}
