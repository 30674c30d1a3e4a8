//! Layers point one way (docs/ARCHITECTURE.md): a module may use what is below it
//! or beside it, never what is above. An upward import fails this test with its file and line,
//! and so does a top-level module missing from [`LAYERS`] (every module has a place).
//!
//! Only `crate::<module>` paths in code are read (not comments); `super::` stays inside a module.

use std::collections::BTreeMap;
use std::path::Path;

/// The layers, lowest first. Modules on one rank may use each other.
const LAYERS: &[(&str, u8)] = &[
    ("wire_number", 0),
    ("geometry", 0),
    ("variables", 1),
    ("factors", 2),
    ("problem", 3),
    ("solver", 4),
    ("io", 5),
    ("fusion", 5),
    ("api", 6),
    ("journal", 7),
    // The pool and metrics: sessions and the service both use them (docs/ARCHITECTURE.md).
    ("runtime", 7),
    ("session", 8),
    ("service", 9),
    ("transport", 11),
    // The composition root: starts the service and the transports (with the binary's cli).
    ("server", 12),
];

fn rank(module: &str) -> Option<u8> {
    LAYERS.iter().find(|(m, _)| *m == module).map(|&(_, r)| r)
}

/// Every `crate::<module>` in the code of `text` (comments skipped), with its line number.
fn crate_paths(text: &str) -> Vec<(usize, String)> {
    let mut found = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let code = line.split("//").next().unwrap_or("");
        let mut rest = code;
        while let Some(at) = rest.find("crate::") {
            rest = &rest[at + "crate::".len()..];
            let name: String = rest
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            found.push((n + 1, name));
        }
    }
    found
}

fn rust_files(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
    for entry in std::fs::read_dir(dir).expect("readable source tree") {
        let path = entry.expect("a directory entry").path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

#[test]
fn lower_layers_never_import_higher_ones() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut upward: BTreeMap<(String, String), Vec<String>> = BTreeMap::new();
    for file in &files {
        let relative = file.strip_prefix(&src).unwrap();
        let top = relative.components().next().unwrap().as_os_str();
        let top = top.to_str().unwrap().trim_end_matches(".rs").to_string();
        if ["lib", "main", "cli"].contains(&top.as_str()) {
            continue; // the crate root and the binary's cli: the top, which may use anything
        }
        let Some(from) = rank(&top) else {
            panic!("src/{top} is not in LAYERS: give the new module its place");
        };
        let text = std::fs::read_to_string(file).unwrap();
        for (line, target) in crate_paths(&text) {
            if rank(&target).is_some_and(|to| to > from) {
                let place = format!("{}:{line}", relative.display());
                upward.entry((top.clone(), target)).or_default().push(place);
            }
        }
    }
    let problems: Vec<String> = upward
        .iter()
        .map(|((from, to), places)| format!("upward import {from} → {to} at {}", places.join(", ")))
        .collect();
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn the_path_reader_skips_comments_and_reads_each_path() {
    let text = "use crate::solver::x; // crate::service\n//! crate::session\nlet a = crate::io::load(crate::geometry::SE2);";
    let found: Vec<_> = crate_paths(text).into_iter().map(|(_, m)| m).collect();
    assert_eq!(found, ["solver", "io", "geometry"]);
}
