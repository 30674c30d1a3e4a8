//! The Python client's `TypedDict`s (`clients/python/factord_client/wire.py`) against the Rust
//! request and reply types: each class's keys, and which of them are required (declared in a
//! `total=True` class or base), are those of the schema the server's own types generate
//! (`proto/v1/openapi.json`'s components). A field added to a reply, or renamed, fails here until
//! the client says so too; `tests/api/openapi.rs` does the same for the JSON Schema files.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use super::openapi::{generated, shape};

/// (Python class, generated component); `RobustKernel` is a tagged union in Rust, typed loosely
/// in Python.
const CLASSES: &[(&str, &str)] = &[
    ("GuessSpec", "GuessSpec"),
    ("Batch", "Batch"),
    ("FusionBatch", "FusionBatch"),
    ("BatchAck", "Accepted"),
    ("VariableValue", "VariableValue"),
    ("Estimate", "Estimate"),
    ("Export", "Export"),
    ("ErrorBody", "ErrorBody"),
    ("Health", "Health"),
    ("SessionInfo", "SessionInfo"),
    ("SessionList", "SessionList"),
    ("SessionStats", "SessionStats"),
    ("ProducerStatus", "ProducerStatus"),
    ("ProducerList", "ProducerList"),
    ("Marginals", "Marginals"),
    ("Graph", "Graph"),
    ("DrawnVariable", "DrawnVariable"),
    ("JobResult", "JobResult"),
    ("OptimizeAnswer", "Optimizing"),
];

/// One `TypedDict` as written: its bases, whether it is `total`, its own keys.
struct Class {
    bases: Vec<String>,
    total: bool,
    keys: Vec<String>,
}

/// The `TypedDict` classes of a Python module written as `wire.py` is (one key per line, four
/// spaces in, docstrings between `"""`).
fn typed_dicts(text: &str) -> BTreeMap<String, Class> {
    let mut classes = BTreeMap::new();
    let mut current: Option<String> = None;
    let mut in_docstring = false;
    for line in text.lines() {
        if line.matches("\"\"\"").count() % 2 == 1 {
            in_docstring = !in_docstring;
            continue;
        }
        if in_docstring {
            continue;
        }
        if let Some(header) = line.strip_prefix("class ") {
            let (name, rest) = header.split_once('(').expect("class Name(Bases):");
            let bases = rest.trim_end_matches("):");
            let parts: Vec<String> = bases.split(',').map(|b| b.trim().to_string()).collect();
            classes.insert(
                name.to_string(),
                Class {
                    total: !parts.iter().any(|p| p == "total=False"),
                    bases: parts.into_iter().filter(|p| !p.contains('=')).collect(),
                    keys: Vec::new(),
                },
            );
            current = Some(name.to_string());
            continue;
        }
        if !line.starts_with(' ') && !line.trim().is_empty() {
            current = None;
            continue;
        }
        let (Some(name), Some(field)) = (&current, line.strip_prefix("    ")) else {
            continue;
        };
        if let Some((key, _)) = field.split_once(':') {
            if key
                .chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
            {
                let class = classes.get_mut(name).expect("current class");
                class.keys.push(key.to_string());
            }
        }
    }
    classes
}

/// All keys of `name` with its bases', and the required ones.
fn keys_of(classes: &BTreeMap<String, Class>, name: &str) -> (BTreeSet<String>, BTreeSet<String>) {
    let class = &classes[name];
    let mut all: BTreeSet<String> = class.keys.iter().cloned().collect();
    let mut required = if class.total {
        all.clone()
    } else {
        BTreeSet::new()
    };
    for base in class.bases.iter().filter(|b| classes.contains_key(*b)) {
        let (a, r) = keys_of(classes, base);
        all.extend(a);
        required.extend(r);
    }
    (all, required)
}

#[test]
fn the_python_typed_dicts_have_the_keys_of_the_rust_types() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("clients/python/factord_client/wire.py");
    let classes = typed_dicts(&std::fs::read_to_string(&path).expect("wire.py"));
    let api = generated();
    let mut mismatches = Vec::new();
    for (class, component) in CLASSES {
        if !classes.contains_key(*class) {
            mismatches.push(format!("{class}: not in wire.py"));
            continue;
        }
        let Some(schema) = api.pointer(&format!("/components/schemas/{component}")) else {
            mismatches.push(format!("{component}: not in the generated document"));
            continue;
        };
        let (rust_keys, rust_required) = shape(schema, &api);
        let (python_keys, python_required) = keys_of(&classes, class);
        if rust_keys != python_keys {
            mismatches.push(format!(
                "{class} vs {component}: keys only in Rust {:?}, only in Python {:?}",
                rust_keys.difference(&python_keys).collect::<Vec<_>>(),
                python_keys.difference(&rust_keys).collect::<Vec<_>>()
            ));
        }
        if rust_required != python_required {
            mismatches.push(format!(
                "{class} vs {component}: required only in Rust {:?}, only in Python {:?}",
                rust_required
                    .difference(&python_required)
                    .collect::<Vec<_>>(),
                python_required
                    .difference(&rust_required)
                    .collect::<Vec<_>>()
            ));
        }
    }
    assert!(
        mismatches.is_empty(),
        "wire.py drifted from the Rust types:\n{}",
        mismatches.join("\n")
    );
}

/// The parser reads what it must: a drift it cannot see would make the test above vacuous.
#[test]
fn the_parser_reads_bases_totality_and_keys() {
    let text = "class _AKeys(TypedDict):\n    a: int\n\n\nclass A(_AKeys, total=False):\n    \
                \"\"\"Doc.\n    not_a_key: no\n    \"\"\"\n\n    b: str\n";
    let classes = typed_dicts(text);
    let (all, required) = keys_of(&classes, "A");
    assert_eq!(all, BTreeSet::from(["a".to_string(), "b".to_string()]));
    assert_eq!(required, BTreeSet::from(["a".to_string()]));
}
