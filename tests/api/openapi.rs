//! `proto/v1/openapi.json` is generated: the document the server serves at `/v1/openapi.json`,
//! built from the handlers' annotations and the wire types by the same `OpenApiRouter` that builds
//! the router (`factord::transport::http::routes`), so the router has no route the document
//! lacks. These tests keep the committed file equal to it, check on a real server that every
//! documented operation is served (and no other method on its path), and that the generated
//! schemas and the hand-written `proto/v1/*.schema.json` agree on property names and required
//! fields, also for each alternative of the tagged unions (every event `type`, every command `op`).

use crate::common;

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use common::server::{client, TestServer};
use factord::transport::http::openapi;
use serde_json::Value;

const BLESS: &str = "FACTORD_BLESS=1 cargo test --release --test api openapi::";

fn proto(file: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("proto/v1")
        .join(file)
}

pub(crate) fn generated() -> Value {
    serde_json::from_str(&openapi::document()).expect("the document is JSON")
}

#[test]
fn the_committed_document_is_the_generated_one() {
    let path = proto("openapi.json");
    let document = openapi::document();
    if std::env::var_os("FACTORD_BLESS").is_some() {
        std::fs::write(&path, &document).expect("write proto/v1/openapi.json");
        return;
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    if committed != document {
        let first = committed
            .lines()
            .zip(document.lines())
            .position(|(a, b)| a != b)
            .unwrap_or(committed.lines().count().min(document.lines().count()));
        panic!(
            "{} differs from the generated OpenAPI document (first at line {}: committed {:?}, \
             generated {:?}); regenerate it with `{BLESS}` and commit it",
            path.display(),
            first + 1,
            committed.lines().nth(first),
            document.lines().nth(first),
        );
    }
}

const METHODS: [&str; 5] = ["get", "put", "post", "delete", "patch"];

/// (path, method) of every documented operation.
fn operations(api: &Value) -> BTreeSet<(String, String)> {
    let paths = api["paths"].as_object().expect("paths");
    paths
        .iter()
        .flat_map(|(path, item)| {
            METHODS
                .iter()
                .filter(|m| item.get(**m).is_some())
                .map(move |m| (path.clone(), m.to_string()))
        })
        .collect()
}

/// Every documented operation is routed (not `no_route`, not 405), and every other method on a
/// documented path is 405: the router serves no operation the document leaves out there.
#[tokio::test(flavor = "multi_thread")]
async fn every_documented_operation_is_served_and_no_other_method() {
    let api = generated();
    let documented = operations(&api);
    assert!(documented.len() >= 20, "{documented:?}");
    let server = TestServer::start(&[]);
    let client = client();
    let paths: BTreeSet<&String> = documented.iter().map(|(p, _)| p).collect();
    let mut wrong = Vec::new();
    for path in paths {
        let url = server.url(&path.replace("{session}", "openapi-probe"));
        for method in METHODS {
            let request = client
                .request(method.to_uppercase().parse().expect("method"), &url)
                .header("content-type", "application/json")
                .body("{}");
            let response = request.send().await.expect("request");
            let status = response.status().as_u16();
            let body: Value = response.json().await.unwrap_or(Value::Null);
            let code = body["error"]["code"].as_str().unwrap_or("").to_string();
            let is_documented = documented.contains(&(path.clone(), method.to_string()));
            let routed = status != 405 && code != "no_route";
            if is_documented != routed {
                wrong.push(format!(
                    "{} {path}: documented {is_documented}, answered {status} {code}",
                    method.to_uppercase()
                ));
            }
        }
    }
    server.assert_no_panic();
    assert!(
        wrong.is_empty(),
        "router and document disagree:\n{}",
        wrong.join("\n")
    );
}

/// The served document is the generated one, open without a token like the docs page.
#[tokio::test(flavor = "multi_thread")]
async fn the_document_and_docs_page_are_served_without_a_token() {
    let server =
        TestServer::start_with_env(&[], &[("FACTORD_TOKENS", "openapi-test-token-0123456789")]);
    let client = client();
    let served: Value = client
        .get(server.url("/v1/openapi.json"))
        .send()
        .await
        .expect("request")
        .json()
        .await
        .expect("json");
    assert_eq!(served, generated());
    let page = client
        .get(server.url("/v1/docs"))
        .send()
        .await
        .expect("docs");
    assert_eq!(page.status(), 200);
    assert!(page.text().await.expect("text").contains("/assets/docs.js"));
    let script = client
        .get(server.url("/assets/docs.js"))
        .send()
        .await
        .expect("js");
    assert_eq!(script.status(), 200);
    let sessions = client
        .get(server.url("/v1/sessions"))
        .send()
        .await
        .expect("list");
    assert_eq!(
        sessions.status(),
        401,
        "the API itself still needs the token"
    );
}

/// The hand-written schema files next to the document, by the component they describe:
/// (component, file, JSON pointer in the file).
const SCHEMA_FILES: &[(&str, &str, &str)] = &[
    ("Health", "health.schema.json", ""),
    ("CreateSession", "create-session.schema.json", ""),
    ("Ros2Binding", "ros2-binding.schema.json", ""),
    ("SessionInfo", "session-info.schema.json", ""),
    ("SessionList", "session-list.schema.json", ""),
    ("SessionStats", "session-stats.schema.json", ""),
    (
        "SolverOptions",
        "solver-options.schema.json",
        "/$defs/complete",
    ),
    ("Batch", "batch.schema.json", ""),
    ("BatchAck", "batch-ack.schema.json", ""),
    ("ProducerStatus", "producer-status.schema.json", ""),
    ("EstimateQuery", "estimate-query.schema.json", ""),
    ("Estimate", "estimate.schema.json", ""),
    ("Graph", "graph.schema.json", ""),
    ("Marginals", "marginals.schema.json", ""),
    ("SessionHistory", "history.schema.json", ""),
    (
        "TimelinePoint",
        "history.schema.json",
        "/$defs/timeline_point",
    ),
    ("LoggedEvent", "history.schema.json", "/$defs/logged_event"),
    ("LoginRequest", "login.schema.json", ""),
    ("LoginReply", "login.schema.json", "/$defs/reply"),
    ("Summary", "summary.schema.json", ""),
    ("JobResult", "job-result.schema.json", ""),
    ("Error", "error.schema.json", ""),
    ("FusionBatch", "fusion.schema.json", ""),
    ("Deleted", "reply.schema.json", "/$defs/deleted"),
    ("Optimizing", "reply.schema.json", "/$defs/optimizing"),
    (
        "AutoOptimizeSet",
        "reply.schema.json",
        "/$defs/auto_optimize_set",
    ),
    ("Cancelled", "reply.schema.json", "/$defs/cancelled"),
    ("ProducerList", "reply.schema.json", "/$defs/producer_list"),
    ("FusionAck", "fusion.schema.json", "/$defs/ack"),
    ("StateReport", "fusion.schema.json", "/$defs/state"),
    ("ErrorBody", "common.schema.json", "/$defs/error_body"),
    (
        "IterationReport",
        "summary.schema.json",
        "/$defs/iteration_report",
    ),
    ("UsedOptions", "summary.schema.json", "/$defs/used_options"),
    ("Termination", "summary.schema.json", "/$defs/termination"),
    ("Timings", "summary.schema.json", "/$defs/timings"),
];

/// Properties a hand-written schema has beyond what the server sends: `factord solve
/// --summary-json` adds these to the summary (summary.schema.json says so).
const CLI_ONLY: &[(&str, &str)] = &[
    ("Summary", "input"),
    ("Summary", "load_seconds"),
    ("Summary", "solve_seconds_runs"),
    ("Summary", "final_chi2_g2o"),
];

/// Property names and required names of an object schema, following `$ref`s inside `root`
/// and merging `allOf` parts.
pub(crate) fn shape(schema: &Value, root: &Value) -> (BTreeSet<String>, BTreeSet<String>) {
    let schema = match schema.get("$ref").and_then(Value::as_str) {
        Some(r) if r.starts_with('#') => {
            let pointer = r.trim_start_matches('#');
            return shape(root.pointer(pointer).unwrap_or(&Value::Null), root);
        }
        _ => schema,
    };
    let names = |v: Option<&Value>| -> BTreeSet<String> {
        match v {
            Some(Value::Object(o)) => o.keys().cloned().collect(),
            Some(Value::Array(a)) => a
                .iter()
                .filter_map(|s| s.as_str().map(String::from))
                .collect(),
            _ => BTreeSet::new(),
        }
    };
    let mut properties = names(schema.get("properties"));
    let mut required = names(schema.get("required"));
    for part in schema
        .get("allOf")
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
    {
        let (p, r) = shape(part, root);
        properties.extend(p);
        required.extend(r);
    }
    (properties, required)
}

#[test]
fn generated_schemas_agree_with_the_hand_written_ones() {
    let api = generated();
    let mut mismatches = Vec::new();
    let mut files: BTreeMap<&str, Value> = BTreeMap::new();
    for (component, file, pointer) in SCHEMA_FILES {
        let Some(ours) = api.pointer(&format!("/components/schemas/{component}")) else {
            mismatches.push(format!("{component}: not in the generated document"));
            continue;
        };
        let text = files.entry(file).or_insert_with(|| {
            let text = std::fs::read_to_string(proto(file)).expect("schema file");
            serde_json::from_str(&text).expect("schema JSON")
        });
        let theirs = text.pointer(pointer).unwrap_or(&Value::Null).clone();
        let (our_props, our_required) = shape(ours, &api);
        let (mut their_props, their_required) = shape(&theirs, text);
        for (_, extra) in CLI_ONLY.iter().filter(|(c, _)| c == component) {
            their_props.remove(*extra);
        }
        if our_props != their_props {
            mismatches.push(format!(
                "{component} vs {file}{pointer}: properties only generated {:?}, only hand-written {:?}",
                our_props.difference(&their_props).collect::<Vec<_>>(),
                their_props.difference(&our_props).collect::<Vec<_>>()
            ));
        }
        if our_required != their_required {
            mismatches.push(format!(
                "{component} vs {file}{pointer}: required only generated {:?}, only hand-written {:?}",
                our_required.difference(&their_required).collect::<Vec<_>>(),
                their_required.difference(&our_required).collect::<Vec<_>>()
            ));
        }
    }
    assert!(
        mismatches.is_empty(),
        "schemas drifted:\n{}",
        mismatches.join("\n")
    );
}

/// The tagged unions, (component, tag property, file): each generated alternative, named by its
/// tag's value, against the file's `$defs/<tag>` (the file's `oneOf` lists exactly those).
const TAGGED: &[(&str, &str, &str)] = &[
    ("SessionEvent", "type", "event.schema.json"),
    ("Command", "op", "command.schema.json"),
];

/// The value of an alternative's tag property (`"enum": ["ack"]`), in it or its `allOf` parts.
fn tag_of(schema: &Value, tag: &str) -> Option<String> {
    if let Some(value) = schema.pointer(&format!("/properties/{tag}/enum/0")) {
        return value.as_str().map(String::from);
    }
    if let Some(value) = schema.pointer(&format!("/properties/{tag}/const")) {
        return value.as_str().map(String::from);
    }
    schema
        .get("allOf")
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
        .find_map(|part| tag_of(part, tag))
}

/// Property and required names of a hand-written schema in `file`: its own `properties` and
/// `required`, those of its `$ref` (in this file or another one: `batch-ack.schema.json#/$defs/ack`)
/// and of its `allOf` parts.
fn hand_shape(schema: &Value, file: &str) -> (BTreeSet<String>, BTreeSet<String>) {
    let (mut properties, mut required) = shape(
        &serde_json::json!({
            "properties": schema.get("properties").cloned().unwrap_or(Value::Null),
            "required": schema.get("required").cloned().unwrap_or(Value::Null),
        }),
        &Value::Null,
    );
    let mut parts: Vec<(Value, String)> = schema
        .get("allOf")
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
        .map(|part| (part.clone(), file.to_string()))
        .collect();
    if let Some(reference) = schema.get("$ref").and_then(Value::as_str) {
        let (target, pointer) = reference.split_once('#').unwrap_or((reference, ""));
        let target = if target.is_empty() { file } else { target };
        let text = std::fs::read_to_string(proto(target)).expect("schema file");
        let document: Value = serde_json::from_str(&text).expect("schema JSON");
        let part = document.pointer(pointer).cloned().unwrap_or(Value::Null);
        parts.push((part, target.to_string()));
    }
    for (part, in_file) in parts {
        let (p, r) = hand_shape(&part, &in_file);
        properties.extend(p);
        required.extend(r);
    }
    (properties, required)
}

#[test]
fn tagged_variants_agree_with_the_hand_written_definitions() {
    let api = generated();
    let mut mismatches = Vec::new();
    for (component, tag, file) in TAGGED {
        let alternatives = api
            .pointer(&format!("/components/schemas/{component}/oneOf"))
            .and_then(Value::as_array)
            .unwrap_or_else(|| panic!("{component} is a oneOf in the generated document"));
        let text = std::fs::read_to_string(proto(file)).expect("schema file");
        let document: Value = serde_json::from_str(&text).expect("schema JSON");
        let listed: BTreeSet<String> = document["oneOf"]
            .as_array()
            .expect("the file's oneOf")
            .iter()
            .filter_map(|alt| alt["$ref"].as_str())
            .filter_map(|r| r.strip_prefix("#/$defs/").map(String::from))
            .collect();
        let mut generated_tags = BTreeSet::new();
        for alternative in alternatives {
            let Some(name) = tag_of(alternative, tag) else {
                mismatches.push(format!("{component}: an alternative without a `{tag}`"));
                continue;
            };
            generated_tags.insert(name.clone());
            let Some(theirs) = document.pointer(&format!("/$defs/{name}")) else {
                mismatches.push(format!("{component} `{name}`: no {file}#/$defs/{name}"));
                continue;
            };
            let (our_props, our_required) = shape(alternative, &api);
            let (their_props, their_required) = hand_shape(theirs, file);
            if our_props != their_props {
                mismatches.push(format!(
                    "{component} `{name}` vs {file}#/$defs/{name}: properties only generated {:?}, only hand-written {:?}",
                    our_props.difference(&their_props).collect::<Vec<_>>(),
                    their_props.difference(&our_props).collect::<Vec<_>>()
                ));
            }
            if our_required != their_required {
                mismatches.push(format!(
                    "{component} `{name}` vs {file}#/$defs/{name}: required only generated {:?}, only hand-written {:?}",
                    our_required.difference(&their_required).collect::<Vec<_>>(),
                    their_required.difference(&our_required).collect::<Vec<_>>()
                ));
            }
        }
        if generated_tags != listed {
            mismatches.push(format!(
                "{component}: `{tag}`s only generated {:?}, only in {file}'s oneOf {:?}",
                generated_tags.difference(&listed).collect::<Vec<_>>(),
                listed.difference(&generated_tags).collect::<Vec<_>>()
            ));
        }
    }
    assert!(
        mismatches.is_empty(),
        "tagged unions drifted:\n{}",
        mismatches.join("\n")
    );
}
