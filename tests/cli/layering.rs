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
    &["pb", "keys"],
    &["codes"],
    &["engine"],
    &["fanuc", "fuji"],
    &["program"],
    &["bounds", "history"],
    &["config"],
    &["plc", "sim"],
    &["mtconnect"],
];

/// The gateway's modules, lowest layer first.
const GATEWAY_LAYERS: &[&[&str]] = &[
    &["telemetry"],
    &["transport"],
    &["link"],
    &["jobs", "plc", "sim"],
    &["history"],
    &["bus"],
    &["cell", "client"],
    &["console", "mtconnect"],
    &["gateway"],
];

/// Gateway modules that may use zenoh.
const ZENOH_MODULES: &[&str] = &["bus", "client", "console", "mtconnect", "gateway"];

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
