//! What a compiled factor type holds, estimated from the sizes of its parts (not an allocator
//! count): sessions are charged it and bounded by it, and the server's total of distinct
//! compiled types is bounded by it too (`limits.max_factor_type_bytes_*`).

use std::mem::size_of;

use serde_json::Value;

use super::{Declared, FactorTypeDefinition};

/// An allocation's bookkeeping and a map node's links, beside the bytes it holds.
const NODE: usize = 16;

/// A compiled type of `struct_size` bytes holding `definition`, a tape of `tape_bytes` and
/// `other_bytes` of small vectors.
pub(super) fn type_bytes(
    struct_size: usize,
    definition: &FactorTypeDefinition,
    tape_bytes: usize,
    other_bytes: usize,
) -> usize {
    struct_size + tape_bytes + other_bytes + definition_bytes(definition)
}

fn declared_bytes(declared: &[Declared]) -> usize {
    declared
        .iter()
        .map(|d| size_of::<Declared>() + d.name.capacity() + d.kind.capacity())
        .sum()
}

fn definition_bytes(d: &FactorTypeDefinition) -> usize {
    d.name.capacity()
        + declared_bytes(&d.variables)
        + declared_bytes(&d.parameters)
        + d.description.as_ref().map_or(0, String::capacity)
        + json_bytes(&d.residual)
}

/// A JSON tree's heap: strings, arrays of values, objects' entries (keys, values, nodes).
fn json_bytes(value: &Value) -> usize {
    match value {
        Value::Null | Value::Bool(_) | Value::Number(_) => 0,
        Value::String(s) => s.capacity() + NODE,
        Value::Array(items) => {
            items.capacity() * size_of::<Value>()
                + NODE
                + items.iter().map(json_bytes).sum::<usize>()
        }
        Value::Object(map) => map
            .iter()
            .map(|(k, v)| {
                size_of::<String>() + k.capacity() + size_of::<Value>() + 2 * NODE + json_bytes(v)
            })
            .sum(),
    }
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::super::ExpressionType;

    fn definition(terms: usize) -> super::FactorTypeDefinition {
        let sum: Vec<_> = (0..terms)
            .map(|k| json!({"mul": [1.0 + k as f64, {"at": [{"translation": ["a"]}, 0]}]}))
            .collect();
        serde_json::from_value(json!({
            "name": "t",
            "variables": [{"name": "a", "kind": "se2"}],
            "residual": sum,
        }))
        .unwrap()
    }

    #[test]
    fn a_larger_expression_is_counted_larger_and_at_least_its_tape() {
        let small = ExpressionType::compile(definition(2)).unwrap();
        let large = ExpressionType::compile(definition(60)).unwrap();
        let (ops, _) = large.operations();
        assert!(large.memory_bytes() > small.memory_bytes());
        // Each operation is at least its tape entry and its flag; an entry is 16 bytes.
        assert_eq!(std::mem::size_of::<super::super::tape::Op>(), 16);
        assert!(large.memory_bytes() > ops * (std::mem::size_of::<super::super::tape::Op>() + 1));
        // And the definition it keeps: its JSON is at least as large as its text.
        let text = serde_json::to_string(&large.definition).unwrap().len();
        assert!(
            large.memory_bytes() > text,
            "{} <= {text}",
            large.memory_bytes()
        );
    }
}
