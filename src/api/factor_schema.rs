//! The JSON Schema of a batch's factor specs, generated from the catalogue's [`FactorWire`]
//! declarations: `proto/v1/factors.schema.json` is this function's output, and
//! `tests/api/factor_schema.rs` fails when the committed file differs (`FACTORD_BLESS=1 cargo test
//! --test api factor_schema::` rewrites it). So the schema cannot drift from the code: a factor's
//! `type`, its number of keys, its measurement length and its residual dimension (the sizes of
//! `information` and `sigmas`) are written once, in the factor's file.

use serde_json::{json, Map, Value};

use super::catalogue::{self, FactorWire, SESSION_KINDS};

/// Where the generated schema is committed, relative to the crate root.
pub const PATH: &str = "proto/v1/factors.schema.json";

/// The schema of one factor spec (an item of a batch's `factors`): the common shape, and per
/// type (dispatched on `type`) the exact lengths of `keys`, `measurement`, `information` and
/// `sigmas`. `$defs` holds one complete schema per type, named by the type.
pub fn factor_schema() -> Value {
    let factors = catalogue::factors();
    let names: Vec<&str> = factors.iter().map(|f| f.name).collect();
    let mut defs = Map::new();
    for f in factors {
        defs.insert(f.name.to_string(), factor_type(f));
    }
    let dispatch: Vec<Value> = factors
        .iter()
        .map(|f| {
            json!({
                "if": {"properties": {"type": {"const": f.name}}, "required": ["type"]},
                "then": {"$ref": format!("#/$defs/{}", f.name)}
            })
        })
        .collect();
    json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "https://factord.invalid/proto/v1/factors.schema.json",
        "title": "Factor",
        "description": "A new factor (measurement): an item of a batch's `factors`. GENERATED from the factors' WIRE declarations (src/factors/*.rs) by src/api/factor_schema.rs; do not edit: `FACTORD_BLESS=1 cargo test --test api factor_schema::` rewrites it. Give exactly one of `information` and `sigmas` (400 missing_noise otherwise); the information matrix must be symmetric positive definite (400 bad_information). Each type's exact lengths are in `$defs/<type>`.",
        "type": "object",
        "required": ["type", "keys", "measurement"],
        "additionalProperties": false,
        "properties": {
            "type": {
                "description": "Must be a factor type of the session's kind (400 unknown_factor_type).",
                "enum": names
            },
            "keys": keys(None),
            "measurement": measurement(None),
            "information": information(None),
            "sigmas": sigmas(None),
            "robust": robust(),
            "outlier": outlier()
        },
        "oneOf": [{"required": ["information"]}, {"required": ["sigmas"]}],
        "allOf": dispatch,
        "$defs": defs
    })
}

/// The whole schema of one factor type.
fn factor_type(f: &FactorWire) -> Value {
    let accepted: Vec<&str> = SESSION_KINDS
        .iter()
        .filter(|k| k.factor_types.contains(&f.name))
        .map(|k| k.name)
        .collect();
    let keys_doc: Vec<String> = f
        .key_names
        .iter()
        .zip(f.variable_kinds)
        .map(|(name, kind)| format!("{name} ({kind})"))
        .collect();
    let description = format!(
        "`{}`: keys [{}]; measurement [{}]; residual dimension {}. {} Accepted by session kinds: {}.",
        f.name,
        keys_doc.join(", "),
        f.measurement.join(", "),
        f.residual_dim,
        f.description,
        if accepted.is_empty() { "none".to_string() } else { accepted.join(", ") }
    );
    json!({
        "description": description,
        "type": "object",
        "required": ["type", "keys", "measurement"],
        "additionalProperties": false,
        "properties": {
            "type": {"const": f.name},
            "keys": keys(Some(f)),
            "measurement": measurement(Some(f)),
            "information": information(Some(f)),
            "sigmas": sigmas(Some(f)),
            "robust": robust(),
            "outlier": outlier()
        },
        "oneOf": [{"required": ["information"]}, {"required": ["sigmas"]}]
    })
}

/// `[min, max]` items, when the type is known.
fn exactly(schema: &mut Value, n: Option<usize>) {
    if let Some(n) = n {
        schema["minItems"] = json!(n);
        schema["maxItems"] = json!(n);
    }
}

fn keys(f: Option<&FactorWire>) -> Value {
    let mut s = json!({
        "description": match f {
            Some(f) => format!("[{}]: variables of kinds {:?}, in this order.", f.key_names.join(", "), f.variable_kinds),
            None => "The connected variables, in the order the type defines; each must exist (in the session or this batch; 422 unknown_variable) and have the kind the type expects (422 wrong_kind); no key twice (400 repeated_variable).".to_string(),
        },
        "type": "array",
        "items": {"$ref": "common.schema.json#/$defs/key"},
        "uniqueItems": true
    });
    exactly(&mut s, f.map(|f| f.variable_kinds.len()));
    s
}

fn measurement(f: Option<&FactorWire>) -> Value {
    let mut s = json!({
        "description": match f {
            Some(f) => format!("[{}] ({} numbers; 400 wrong_dimension otherwise).", f.measurement.join(", "), f.measurement_len),
            None => "The measured value, in the encoding of the type (se2 [x, y, theta], se3 [x, y, z, qx, qy, qz, qw], …; see `$defs/<type>`).".to_string(),
        },
        "type": "array",
        "items": {"type": "number"}
    });
    exactly(&mut s, f.map(|f| f.measurement_len));
    s
}

fn information(f: Option<&FactorWire>) -> Value {
    let description = "Information matrix Omega (inverse covariance) in the factor's residual order: d*d numbers row-major, or the d(d+1)/2 numbers of its upper triangle row by row (g2o's order). `null` is the same as leaving the field out.";
    let Some(f) = f else {
        return json!({"description": description, "type": ["array", "null"], "items": {"type": "number"}});
    };
    let d = f.residual_dim;
    let array = |n: usize| json!({"type": "array", "items": {"type": "number"}, "minItems": n, "maxItems": n});
    json!({
        "description": format!("d = {d}: {} numbers (full, row-major) or {} (upper triangle row by row).", d * d, d * (d + 1) / 2),
        "anyOf": [array(d * d), array(d * (d + 1) / 2), {"type": "null"}]
    })
}

fn sigmas(f: Option<&FactorWire>) -> Value {
    let mut array = json!({"type": "array", "items": {"type": "number", "exclusiveMinimum": 0}});
    let Some(f) = f else {
        array["description"] = json!("Standard deviations of a diagonal noise, one per residual component (> 0), in the residual's units (rotation components in radians). `null` is the same as leaving the field out.");
        array["type"] = json!(["array", "null"]);
        return array;
    };
    exactly(&mut array, Some(f.residual_dim));
    json!({"description": format!("{} numbers.", f.residual_dim), "anyOf": [array, {"type": "null"}]})
}

fn outlier() -> Value {
    json!({
        "description": "`auto`: the factor may be wrong (a loop closure from place recognition); it enters the estimate once the session finds it consistent (GET /v1/sessions/{s}/outliers). `trusted`: never held out, whatever the session's `outliers` policy. `null` is the same as leaving the field out.",
        "anyOf": [{"enum": ["auto", "trusted"]}, {"type": "null"}]
    })
}

fn robust() -> Value {
    json!({
        "description": "Optional robust kernel for this factor. `null` is the same as leaving the field out.",
        "anyOf": [{"$ref": "common.schema.json#/$defs/robust_kernel"}, {"type": "null"}]
    })
}

/// The generated schema as committed, laid out as the other files in `proto/` (and
/// `proto/validate.py`'s `compact`): containers that fit in 120 columns on one line, others one
/// item per line indented by two; a final newline.
pub fn factor_schema_text() -> String {
    let mut text = compact(&factor_schema(), 0);
    text.push('\n');
    text
}

/// One line, with Python's `json.dumps` separators (`", "`, `": "`).
fn flat(value: &Value) -> String {
    match value {
        Value::Object(m) => {
            let items: Vec<String> = m
                .iter()
                .map(|(k, v)| format!("{}: {}", Value::from(k.as_str()), flat(v)))
                .collect();
            format!("{{{}}}", items.join(", "))
        }
        Value::Array(a) => format!("[{}]", a.iter().map(flat).collect::<Vec<_>>().join(", ")),
        scalar => scalar.to_string(),
    }
}

fn compact(value: &Value, indent: usize) -> String {
    let flat = flat(value);
    let empty = match value {
        Value::Object(m) => m.is_empty(),
        Value::Array(a) => a.is_empty(),
        _ => true,
    };
    if empty || flat.len() + indent <= 120 {
        return flat;
    }
    let pad = " ".repeat(indent + 2);
    let (open, items, close): (_, Vec<String>, _) = match value {
        Value::Object(m) => (
            '{',
            m.iter()
                .map(|(k, v)| {
                    format!(
                        "{pad}{}: {}",
                        Value::from(k.as_str()),
                        compact(v, indent + 2)
                    )
                })
                .collect(),
            '}',
        ),
        Value::Array(a) => (
            '[',
            a.iter()
                .map(|v| format!("{pad}{}", compact(v, indent + 2)))
                .collect(),
            ']',
        ),
        _ => unreachable!("scalars are returned flat above"),
    };
    format!(
        "{open}\n{}\n{}{close}",
        items.join(",\n"),
        " ".repeat(indent)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_factor_has_its_definition_and_dispatch() {
        let schema = factor_schema();
        for f in catalogue::factors() {
            let def = &schema["$defs"][f.name];
            assert_eq!(def["properties"]["type"]["const"], f.name);
            assert_eq!(
                def["properties"]["keys"]["maxItems"],
                f.variable_kinds.len()
            );
            assert_eq!(
                def["properties"]["measurement"]["minItems"],
                f.measurement_len
            );
            let d = f.residual_dim;
            assert_eq!(
                def["properties"]["information"]["anyOf"][0]["maxItems"],
                d * d
            );
            assert_eq!(
                def["properties"]["information"]["anyOf"][1]["maxItems"],
                d * (d + 1) / 2
            );
            assert_eq!(def["properties"]["sigmas"]["anyOf"][0]["minItems"], d);
        }
        assert_eq!(
            schema["allOf"].as_array().map(Vec::len),
            Some(catalogue::factors().len())
        );
    }
}
