//! The dependency lists match what the code uses (issue #14: tokio was declared and never
//! imported): every entry of every crate's `[dependencies]` (and target-specific ones) is named
//! as a path (`name::…`, `use name…`) somewhere in that crate's `src/`, every `[dev-dependencies]`
//! entry in its `src/`, `tests/`, `benches/` or `examples/`, and every
//! `[workspace.dependencies]` entry is declared by some crate.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the workspace root")
        .to_path_buf()
}

/// The dependency names of each section of a `Cargo.toml` (table header → names), read line
/// by line: `name.workspace = true`, `name = "1"`, `name = { … }`.
fn sections(manifest: &str) -> Vec<(String, Vec<String>)> {
    let mut out: Vec<(String, Vec<String>)> = Vec::new();
    for line in manifest.lines().map(str::trim) {
        if let Some(h) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            out.push((h.to_string(), Vec::new()));
            continue;
        }
        let Some((_, names)) = out.last_mut() else {
            continue;
        };
        if line.starts_with('#') || !line.contains('=') {
            continue;
        }
        let key = line.split('=').next().unwrap_or_default().trim();
        let name = key.split('.').next().unwrap_or_default().trim();
        if !name.is_empty() {
            names.push(name.to_string());
        }
    }
    out
}

fn rust_sources(dir: &Path, out: &mut String) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            rust_sources(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push_str(&std::fs::read_to_string(&p).expect("a readable source"));
            out.push('\n');
        }
    }
}

/// `name` is used as a path in `text`: `name::` or `use name` (identifier boundaries).
fn used(text: &str, name: &str) -> bool {
    let ident = name.replace('-', "_");
    let boundary = |i: usize| {
        i == 0 || !text.as_bytes()[i - 1].is_ascii_alphanumeric() && text.as_bytes()[i - 1] != b'_'
    };
    text.match_indices(&format!("{ident}::"))
        .any(|(i, _)| boundary(i))
        || text
            .match_indices(&format!("use {ident}"))
            .any(|(i, _)| boundary(i))
}

#[test]
fn every_declared_dependency_is_used() {
    let root = root();
    let workspace = std::fs::read_to_string(root.join("Cargo.toml")).expect("Cargo.toml");
    let members: Vec<String> = workspace
        .lines()
        .find(|l| l.trim_start().starts_with("members"))
        .expect("workspace members")
        .split('"')
        .skip(1)
        .step_by(2)
        .map(str::to_string)
        .collect();
    assert!(members.len() >= 4, "{members:?}");
    let mut unused = Vec::new();
    let mut declared = BTreeSet::new();
    for m in &members {
        let manifest =
            std::fs::read_to_string(root.join(m).join("Cargo.toml")).expect("a member manifest");
        let (mut src, mut all) = (String::new(), String::new());
        rust_sources(&root.join(m).join("src"), &mut src);
        for d in ["src", "tests", "benches", "examples"] {
            rust_sources(&root.join(m).join(d), &mut all);
        }
        for (section, names) in sections(&manifest) {
            let text = if section == "dependencies"
                || section.starts_with("target.") && section.ends_with(".dependencies")
            {
                &src
            } else if section == "dev-dependencies" {
                &all
            } else {
                continue;
            };
            for n in names {
                declared.insert(n.clone());
                if !used(text, &n) {
                    unused.push(format!("{m}: [{section}] {n}"));
                }
            }
        }
    }
    assert!(
        unused.is_empty(),
        "declared but never used: {unused:#?} (drop them, or use them)"
    );
    let ws = sections(&workspace);
    let ws_deps = &ws
        .iter()
        .find(|(h, _)| h == "workspace.dependencies")
        .expect("[workspace.dependencies]")
        .1;
    let orphans: Vec<&String> = ws_deps.iter().filter(|d| !declared.contains(*d)).collect();
    assert!(
        orphans.is_empty(),
        "[workspace.dependencies] no crate declares: {orphans:?}"
    );
}

/// The checker itself: a declaration with no use is found, one used through `use` or a path is
/// not, and a longer identifier that merely ends with the name does not count.
#[test]
fn the_checker_tells_used_from_unused() {
    let text = "use serde::Deserialize;\nlet x = my_rand::thing();\nnalgebra::Vector3::zeros();";
    assert!(used(text, "serde"));
    assert!(used(text, "nalgebra"));
    assert!(!used(text, "rand"), "my_rand:: is not rand::");
    assert!(!used(text, "tokio"));
    let s = sections(
        "[package]\nname = \"x\"\n[dependencies]\nfoo.workspace = true\nbar-baz = { version = \"1\" }\n# c = 1\n",
    );
    assert_eq!(
        s[1],
        ("dependencies".into(), vec!["foo".into(), "bar-baz".into()])
    );
}
