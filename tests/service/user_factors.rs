//! User-defined factor types over HTTP (issue 18, item 4): `between_se2` written as an
//! expression reproduces the built-in factor on intel (the same optimum), survives a kill -9 and
//! a restart with the journal on, and every bad definition or use is refused with the field or
//! expression node at fault while nothing is created or changed.

use crate::common;

use common::server::{client, create, get, post, TestServer};
use common::user_between_se2;
use serde_json::{json, Value};

/// The whole g2o graph as one batch, every vertex with its value, edges of type `edge_type`.
fn whole_graph(text: &str, edge_type: &str) -> Value {
    let mut variables = vec![];
    let mut factors = vec![];
    for line in text.lines() {
        let t: Vec<&str> = line.split_whitespace().collect();
        let nums =
            |from: usize| -> Vec<f64> { t[from..].iter().map(|v| v.parse().unwrap()).collect() };
        match t.first() {
            Some(&"VERTEX_SE2") => variables.push(
                json!({"key": t[1].parse::<u64>().unwrap(), "kind": "se2", "value": nums(2)}),
            ),
            Some(&"EDGE_SE2") => {
                let n = nums(3);
                factors.push(json!({"type": edge_type, "keys": [t[1].parse::<u64>().unwrap(), t[2].parse::<u64>().unwrap()],
                    "measurement": &n[..3], "information": &n[3..]}));
            }
            _ => {}
        }
    }
    json!({"variables": variables, "factors": factors})
}

/// Both sessions start from the file's values and stop at a tight tolerance, so both reach
/// the optimum (the chordal start is for built-in relative poses only).
fn session(name: &str, factor_types: Value) -> Value {
    json!({"session": name, "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"},
        "options": {"method": "gauss_newton", "initialization": "none", "function_tolerance": 1e-12},
        "factor_types": factor_types})
}

async fn solve(c: &reqwest::Client, s: &TestServer, name: &str) -> (f64, Vec<Value>) {
    let (status, v) = post(
        c,
        &s.url(&format!("/v1/sessions/{name}/optimize?wait=true")),
        &json!(null),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let chi2 = v["stats"]["chi2"].as_f64().unwrap();
    let (status, estimate) = get(c, &s.url(&format!("/v1/sessions/{name}/estimate"))).await;
    assert_eq!(status, 200, "{estimate}");
    (chi2, estimate["variables"].as_array().unwrap().clone())
}

fn max_difference(a: &[Value], b: &[Value]) -> f64 {
    assert_eq!(a.len(), b.len());
    let mut worst: f64 = 0.0;
    for (p, q) in a.iter().zip(b) {
        assert_eq!(p["key"], q["key"]);
        for k in 0..3 {
            worst = worst
                .max((p["value"][k].as_f64().unwrap() - q["value"][k].as_f64().unwrap()).abs());
        }
    }
    worst
}

#[tokio::test(flavor = "multi_thread")]
async fn a_user_defined_between_se2_reaches_the_built_in_optimum_on_intel_and_survives_a_restart() {
    let Some(path) = common::data_file("2d/sesync/intel.g2o") else {
        return;
    };
    let text = std::fs::read_to_string(path).unwrap();
    let dir = common::temp_dir("user-factors");
    let s = TestServer::start_at(&dir, &[], &[]);
    let c = client();
    create(&c, &s, &session("built_in", json!([]))).await;
    let info = create(&c, &s, &session("user", json!([user_between_se2()]))).await;
    assert_eq!(info["factor_types"], json!(["user_between_se2"]), "{info}");
    for (name, edge_type) in [("built_in", "between_se2"), ("user", "user_between_se2")] {
        let (status, v) = post(
            &c,
            &s.url(&format!("/v1/sessions/{name}/batches")),
            &whole_graph(&text, edge_type),
        )
        .await;
        assert_eq!(status, 200, "{name}: {v}");
    }
    let (chi2_built_in, built_in) = solve(&c, &s, "built_in").await;
    let (chi2_user, user) = solve(&c, &s, "user").await;
    let relative = (chi2_user - chi2_built_in).abs() / chi2_built_in;
    let worst = max_difference(&built_in, &user);
    println!("intel: chi2 built-in {chi2_built_in} user-defined {chi2_user} (relative {relative:e}); largest coordinate difference {worst:e}");
    assert!(relative <= 1e-9, "{chi2_user} vs {chi2_built_in}");
    assert!(worst <= 1e-9, "{worst}");

    // kill -9, restart on the same files: the type is compiled again from the creation record
    // before the journal is replayed, and takes new factors.
    drop(s.kill());
    let s = TestServer::start_at(&dir, &[], &[]);
    let (info, _) = common::server::recovered(&c, &s, "user", std::time::Instant::now()).await;
    assert_eq!(info["factor_types"], json!(["user_between_se2"]), "{info}");
    let (chi2_recovered, recovered) = solve(&c, &s, "user").await;
    assert!(
        (chi2_recovered - chi2_user).abs() <= 1e-9 * chi2_user,
        "{chi2_recovered} vs {chi2_user}"
    );
    assert!(max_difference(&user, &recovered) <= 1e-9);
    let (status, v) = post(&c, &s.url("/v1/sessions/user/batches"), &json!({
        "variables": [{"key": 100000, "kind": "se2", "value": [0.0, 0.0, 0.0]}],
        "factors": [{"type": "user_between_se2", "keys": [0, 100000], "measurement": [0.0, 0.0, 0.0], "sigmas": [1.0, 1.0, 1.0]}]
    })).await;
    assert_eq!(status, 200, "{v}");
    s.assert_no_panic();
}

#[tokio::test(flavor = "multi_thread")]
async fn bad_definitions_and_uses_are_refused_naming_the_field_and_nothing_changes() {
    let s = TestServer::start(&[]);
    let c = client();
    let with_residual = |residual: Value| {
        let mut d = user_between_se2();
        d["residual"] = residual;
        json!([d])
    };
    // Nested vectors: 65 levels are too deep for an expression, not for JSON.
    let mut deep = json!("a");
    for _ in 0..65 {
        deep = json!([deep]);
    }
    let mut landmark = user_between_se2();
    landmark["variables"][1]["kind"] = json!("point3");
    let mut built_in_name = user_between_se2();
    built_in_name["name"] = json!("between_se2");
    let cases: Vec<(&str, Value, &str)> = vec![
        (
            "pose_graph_2d",
            with_residual(json!({"compose": ["a", {"frobnicate": ["b"]}]})),
            "factor_types[0].residual.compose[1].frobnicate",
        ),
        (
            "pose_graph_2d",
            with_residual(json!({"add": ["a", "b"]})),
            "factor_types[0].residual.add",
        ),
        (
            "pose_graph_2d",
            with_residual(json!([{"log": [0]}, 1, 2])),
            "factor_types[0].residual[0].log",
        ),
        (
            "pose_graph_2d",
            with_residual(
                json!({"acos": [{"add": [2, {"squared_norm": [{"translation": ["a"]}]}]}]}),
            ),
            "factor_types[0].residual.acos",
        ),
        (
            "pose_graph_2d",
            with_residual(deep),
            "factor_types[0].residual[0][0]",
        ),
        (
            "pose_graph_2d",
            json!([landmark]),
            "factor_types[0].variables[1].kind",
        ),
        (
            "pose_graph_2d",
            json!([built_in_name]),
            "factor_types[0].name",
        ),
        (
            "pose_graph_2d",
            json!([user_between_se2(), user_between_se2()]),
            "factor_types[1].name",
        ),
        (
            "sliding_window",
            json!([user_between_se2()]),
            "factor_types",
        ),
    ];
    for (kind, factor_types, field) in cases {
        let (status, v) = post(
            &c,
            &s.url("/v1/sessions"),
            &json!({"session": "bad", "kind": kind, "factor_types": factor_types}),
        )
        .await;
        assert_eq!(status, 400, "{factor_types}: {v}");
        assert_eq!(v["error"]["code"], "invalid_factor_type", "{v}");
        assert!(
            v["error"]["field"].as_str().unwrap().starts_with(field),
            "{field} vs {v}"
        );
        assert_eq!(
            get(&c, &s.url("/v1/sessions/bad")).await.0,
            404,
            "nothing was created"
        );
    }

    // Uses of a good type that are wrong are refused whole; the session keeps what it had.
    create(
        &c,
        &s,
        &json!({"session": "ok", "kind": "pose_graph_3d", "factor_types": [{
            "name": "pose_prior",
            "variables": [{"name": "x", "kind": "se3"}],
            "parameters": [{"name": "z", "kind": "se3"}, {"name": "scale", "kind": "scalar"}],
            "residual": {"mul": ["scale", [{"translation": [{"between": ["z", "x"]}]}, {"log": [{"rotation": [{"between": ["z", "x"]}]}]}]]}
        }]}),
    )
    .await;
    let x = json!({"key": 1, "kind": "se3", "value": [0, 0, 0, 0, 0, 0, 1]});
    // Turned 0.1 rad about x: a residual of 0.1 scaled by 1e300 overflows once squared.
    let x_turned = json!({"key": 1, "kind": "se3", "value": [0, 0, 0, 0.0499792, 0, 0, 0.9987503]});
    let prior = |measurement: Value| json!({"type": "pose_prior", "keys": [1], "measurement": measurement, "sigmas": [0.1, 0.1, 0.1, 0.1, 0.1, 0.1]});
    let bad_batches = [
        (
            json!({"variables": [x], "factors": [prior(json!([0, 0, 0, 0, 0, 0, 1]))]}),
            400,
            "factors[0].measurement",
        ),
        (
            json!({"variables": [x], "factors": [prior(json!([0, 0, 0, 0, 0, 0, 2, 1]))]}),
            400,
            "factors[0].measurement",
        ),
        (
            json!({"variables": [x_turned], "factors": [prior(json!([0, 0, 0, 0, 0, 0, 1, 1e300]))]}),
            422,
            "factors[0]",
        ),
        (
            json!({"variables": [x], "factors": [{"type": "pose_prior", "keys": [1], "measurement": [0, 0, 0, 0, 0, 0, 1, 1], "sigmas": [1, 1]}]}),
            400,
            "factors[0].sigmas",
        ),
        (
            json!({"variables": [x], "factors": [{"type": "pose_prior", "keys": [1, 2], "measurement": [0, 0, 0, 0, 0, 0, 1, 1], "sigmas": [1, 1, 1]}]}),
            400,
            "factors[0].keys",
        ),
        (
            json!({"variables": [x], "factors": [{"type": "pose_priors", "keys": [1], "measurement": [0, 0, 0, 0, 0, 0, 1, 1], "sigmas": [1, 1, 1]}]}),
            400,
            "factors[0].type",
        ),
    ];
    for (batch, expected, field) in bad_batches {
        let (status, v) = post(&c, &s.url("/v1/sessions/ok/batches"), &batch).await;
        assert_eq!(status, expected, "{batch}: {v}");
        assert_eq!(v["error"]["field"], field, "{v}");
        let (_, stats) = get(&c, &s.url("/v1/sessions/ok")).await;
        assert_eq!(
            (
                stats["num_variables"].as_u64(),
                stats["num_factors"].as_u64()
            ),
            (Some(0), Some(0)),
            "{stats}"
        );
    }
    let (status, v) = post(
        &c,
        &s.url("/v1/sessions/ok/batches"),
        &json!({"variables": [x],
        "factors": [prior(json!([0, 0, 0, 0.0499792, 0, 0, 0.9987503, 1]))]}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let (status, v) = post(
        &c,
        &s.url("/v1/sessions/ok/optimize?wait=true"),
        &json!(null),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    let (_, estimate) = get(&c, &s.url("/v1/sessions/ok/estimate")).await;
    let q = &estimate["variables"][0]["value"];
    assert!(
        (q[3].as_f64().unwrap() - 0.0499792).abs() < 1e-6,
        "the prior pulled the pose: {estimate}"
    );
    s.assert_no_panic();
}

/// The documented examples compile on the server (the wire test only checks their shape).
#[tokio::test(flavor = "multi_thread")]
async fn the_documented_examples_compile() {
    let s = TestServer::start(&["--no-journal"]);
    let c = client();
    let example = |name: &str| -> Value {
        let path = format!("{}/proto/v1/examples/{name}", env!("CARGO_MANIFEST_DIR"));
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
    };
    let info = create(&c, &s, &example("create-session-factor-types.example.json")).await;
    assert_eq!(info["factor_types"], json!(["wheel_odometry_with_slip"]));
    let info = create(
        &c,
        &s,
        &json!({"session": "baro", "kind": "pose_graph_3d",
        "factor_types": [example("factor-type.example.json")]}),
    )
    .await;
    assert_eq!(info["factor_types"], json!(["barometric_altitude"]));
}

/// The JSON block after `<!-- example: {marker} -->` in the factor types guide.
fn guide_example(marker: &str) -> Value {
    let path = format!("{}/docs/guide/factor-types.md", env!("CARGO_MANIFEST_DIR"));
    let guide = std::fs::read_to_string(path).unwrap();
    let after = guide
        .split(&format!("<!-- example: {marker} -->"))
        .nth(1)
        .unwrap_or_else(|| panic!("the guide has no example {marker}"));
    let block = after
        .split("```json")
        .nth(1)
        .and_then(|b| b.split("```").next())
        .unwrap_or_else(|| panic!("no JSON block after {marker}"));
    serde_json::from_str(block).unwrap_or_else(|e| panic!("{marker}: {e}\n{block}"))
}

/// The guide's session with a declared type and its batch, posted exactly as documented: the
/// measurement is the parameters in declared order (beacon x, y, then the range), so pose 1
/// lands where both ranges and the odometry agree (issue 56: the layout had to be guessed).
#[tokio::test(flavor = "multi_thread")]
async fn the_guides_batch_with_a_declared_type_solves_as_it_says() {
    let s = TestServer::start(&["--no-journal"]);
    let c = client();
    let session = guide_example("user-factor-session");
    let name = session["session"].as_str().unwrap().to_string();
    let info = create(&c, &s, &session).await;
    assert_eq!(info["factor_types"], json!(["beacon_range"]));
    let (status, ack) = post(
        &c,
        &s.url(&format!("/v1/sessions/{name}/batches?wait=true")),
        &guide_example("user-factor-batch"),
    )
    .await;
    assert_eq!(status, 200, "{ack}");
    let (status, stats) = get(&c, &s.url(&format!("/v1/sessions/{name}"))).await;
    assert_eq!(status, 200, "{stats}");
    let chi2 = stats["chi2"].as_f64().unwrap();
    assert!(chi2 < 1e-9, "the documented measurements agree: χ² {chi2}");
    let (status, estimate) = get(&c, &s.url(&format!("/v1/sessions/{name}/estimate"))).await;
    assert_eq!(status, 200, "{estimate}");
    let pose = estimate["variables"]
        .as_array()
        .unwrap()
        .iter()
        .find(|v| v["key"] == 1)
        .expect("pose 1")["value"]
        .clone();
    let pose: Vec<f64> = serde_json::from_value(pose).unwrap();
    for (got, want) in pose.iter().zip([1.0, 0.0, 0.0]) {
        assert!(
            (got - want).abs() < 1e-6,
            "pose 1 at {pose:?}, the guide says (1, 0)"
        );
    }
    s.assert_no_panic();
}

/// A type declared in a running session (`POST …/factor_types`) is journalled in order with the
/// batches, listed in snapshots, and back after kill -9; a bad declaration changes nothing.
#[tokio::test(flavor = "multi_thread")]
async fn types_declared_in_a_running_session_survive_snapshots_and_kill_9() {
    let dir = common::temp_dir("user-factors-late");
    let config = dir.join("factord.json");
    std::fs::write(
        &config,
        json!({"journal": {"snapshot_every": 4}}).to_string(),
    )
    .unwrap();
    let config = config.display().to_string();
    let s = TestServer::start_at(&dir, &["--config", &config], &[]);
    let c = client();
    create(
        &c,
        &s,
        &json!({"session": "late", "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}}),
    )
    .await;
    let url = s.url("/v1/sessions/late/batches");
    let (status, v) = post(
        &c,
        &url,
        &json!({"variables": [{"key": 0, "kind": "se2", "value": [0, 0, 0], "fixed": true}]}),
    )
    .await;
    assert_eq!(status, 200, "{v}");
    // Not declared yet: refused, naming the type.
    let odometry = |k: u64| {
        json!({"variables": [{"key": k, "kind": "se2", "value": [k as f64, 0.1 * k as f64, 0.0]}],
        "factors": [{"type": "user_between_se2", "keys": [k - 1, k], "measurement": [1.0, 0.0, 0.05], "sigmas": [0.1, 0.1, 0.01]}]})
    };
    let (status, v) = post(&c, &url, &odometry(1)).await;
    assert_eq!(
        (status, v["error"]["field"].as_str()),
        (400, Some("factors[0].type")),
        "{v}"
    );

    let declare = s.url("/v1/sessions/late/factor_types");
    let (status, info) = post(&c, &declare, &json!({"factor_types": [user_between_se2()]})).await;
    assert_eq!(status, 200, "{info}");
    assert_eq!(info["factor_types"], json!(["user_between_se2"]));
    let mut typo = user_between_se2();
    typo["name"] = json!("second");
    typo["residual"] = json!({"compose": ["a", {"inverse": ["c"]}]});
    for (body, field) in [
        (
            json!({"factor_types": [user_between_se2()]}),
            "factor_types[0].name",
        ),
        (
            json!({"factor_types": [typo]}),
            "factor_types[0].residual.compose[1].inverse[0]",
        ),
        (json!({"factor_type": []}), "factor_type"),
    ] {
        let (status, v) = post(&c, &declare, &body).await;
        assert_eq!(status, 400, "{body}: {v}");
        assert_eq!(v["error"]["field"], field, "{v}");
        let (_, stats) = get(&c, &s.url("/v1/sessions/late")).await;
        assert_eq!(
            stats["factor_types"],
            json!(["user_between_se2"]),
            "{stats}"
        );
        assert_eq!(stats["sequence"], 1, "{stats}");
    }
    for k in 1..=9 {
        let (status, v) = post(&c, &url, &odometry(k)).await;
        assert_eq!(status, 200, "{v}");
    }
    // The snapshot (every 4 entries) lists the type.
    let snapshot = dir.join("sessions/late/snapshot.json");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    while !std::fs::read_to_string(&snapshot)
        .is_ok_and(|t| t.contains("user_between_se2\",\"variables"))
    {
        assert!(
            std::time::Instant::now() < deadline,
            "no snapshot with the type"
        );
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    let (chi2, before) = solve(&c, &s, "late").await;

    drop(s.kill());
    let s = TestServer::start_at(&dir, &["--config", &config], &[]);
    let (stats, _) = common::server::recovered(&c, &s, "late", std::time::Instant::now()).await;
    assert_eq!(
        stats["factor_types"],
        json!(["user_between_se2"]),
        "{stats}"
    );
    assert_eq!(stats["num_factors"], 9, "{stats}");
    let (chi2_after, after) = solve(&c, &s, "late").await;
    assert!(
        (chi2_after - chi2).abs() <= 1e-9 * chi2.max(1e-12),
        "{chi2_after} vs {chi2}"
    );
    assert!(max_difference(&before, &after) <= 1e-9);
    let (status, v) = post(&c, &s.url("/v1/sessions/late/batches"), &odometry(10)).await;
    assert_eq!(status, 200, "{v}");
    s.assert_no_panic();
}

/// Bundle adjustment with BAL's reprojection written as an expression: the Schur complement
/// eliminates the points as for the built-in factor, and LM reaches the same cost.
#[test]
fn a_user_defined_reprojection_solves_bal_through_the_schur_complement() {
    use factord::factors::expression::{ExpressionType, FactorTypeDefinition};
    use factord::factors::{Factor, ReprojectionSnavely};
    use factord::solver::{optimize, SolverOptions};
    let Some(path) = common::data_file("bal/problem-49-7776-pre.txt") else {
        return;
    };
    let example = format!(
        "{}/proto/v1/examples/factor-type-reprojection.example.json",
        env!("CARGO_MANIFEST_DIR")
    );
    let definition: FactorTypeDefinition =
        serde_json::from_str(&std::fs::read_to_string(example).unwrap()).unwrap();
    let ty = ExpressionType::compile(definition).unwrap();
    let solve = |user: bool| {
        let mut b = factord::io::bal::load(&path).unwrap();
        if user {
            let mut problem =
                factord::problem::Problem::with_gauge(b.problem.gauge).eliminating(&["point3"]);
            for idx in 0..b.problem.values.len() {
                problem
                    .add_variable(
                        b.problem.values.key(idx),
                        b.problem.values.variable(idx).clone_box(),
                    )
                    .unwrap();
            }
            for f in b.problem.factors() {
                let r = f
                    .factor
                    .as_any()
                    .downcast_ref::<ReprojectionSnavely>()
                    .unwrap();
                let user = ty.build(r.keys(), &[r.observed.x, r.observed.y]).unwrap();
                problem
                    .add_factor_sqrt(
                        Box::new(user),
                        f.sqrt_information.clone(),
                        f.robust,
                        f.label.clone(),
                    )
                    .unwrap();
            }
            b.problem = problem;
        }
        let summary = optimize(
            &mut b.problem,
            &SolverOptions::bundle_adjustment(),
            &mut |_| std::ops::ControlFlow::Continue(()),
        )
        .unwrap();
        let schur = summary
            .used
            .schur
            .as_ref()
            .expect("points eliminated")
            .eliminated_variables;
        (summary.final_chi2 / 2.0, summary.iterations, schur)
    };
    let (built_in, user) = (solve(false), solve(true));
    println!("problem-49-7776: cost built-in {built_in:?}, user-defined {user:?}");
    assert_eq!(user.2, built_in.2);
    assert!(
        (user.0 - built_in.0).abs() <= 1e-6 * built_in.0,
        "{user:?} vs {built_in:?}"
    );
}

/// Types in the server's configuration reach every new graph session whose kinds fit, as if
/// declared first; a bad one stops the server at start, naming it.
#[tokio::test(flavor = "multi_thread")]
async fn server_wide_types_from_the_configuration() {
    let dir = common::temp_dir("user-factors-config");
    let beacon = json!({"name": "beacon_range", "variables": [{"name": "x", "kind": "se2"}],
        "parameters": [{"name": "beacon", "kind": "point2"}, {"name": "range", "kind": "scalar"}],
        "residual": {"sub": [{"norm": [{"sub": ["beacon", {"translation": ["x"]}]}]}, "range"]}});
    let altitude: Value = serde_json::from_str(
        &std::fs::read_to_string(format!(
            "{}/proto/v1/examples/factor-type.example.json",
            env!("CARGO_MANIFEST_DIR")
        ))
        .unwrap(),
    )
    .unwrap();
    let config = dir.join("factord.json");
    std::fs::write(
        &config,
        json!({"factor_types": [beacon, altitude]}).to_string(),
    )
    .unwrap();
    let config = config.display().to_string();
    let s = TestServer::start_at(&dir, &["--config", &config], &[]);
    let c = client();
    let info = create(
        &c,
        &s,
        &json!({"session": "plane", "kind": "pose_graph_2d"}),
    )
    .await;
    assert_eq!(
        info["factor_types"],
        json!(["beacon_range"]),
        "only the types whose kinds fit"
    );
    let info = create(
        &c,
        &s,
        &json!({"session": "space", "kind": "pose_graph_3d"}),
    )
    .await;
    assert_eq!(
        info["factor_types"],
        json!(["barometric_altitude"]),
        "the se3 type only: {info}"
    );
    let (status, v) = post(
        &c,
        &s.url("/v1/sessions"),
        &json!({"session": "clash", "kind": "pose_graph_2d", "factor_types": [user_between_se2(), {
        "name": "beacon_range", "variables": [{"name": "x", "kind": "se2"}], "residual": 1}]}),
    )
    .await;
    assert_eq!(
        (status, v["error"]["field"].as_str()),
        (400, Some("factor_types[1].name")),
        "{v}"
    );
    let (status, v) = post(&c, &s.url("/v1/sessions/plane/batches"), &json!({
        "variables": [{"key": 1, "kind": "se2", "value": [0.5, 0.5, 0.0]}],
        "factors": [{"type": "beacon_range", "keys": [1], "measurement": [0.0, 0.0, 5.0], "sigmas": [0.1]}]})).await;
    assert_eq!(status, 200, "{v}");
    drop(s);

    // A type that does not compile: the server does not start, and says which and where.
    std::fs::write(
        dir.join("bad.json"),
        json!({"factor_types": [{"name": "typo", "variables": [{"name": "x", "kind": "se2"}],
        "residual": {"nrom": ["x"]}}]})
        .to_string(),
    )
    .unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_factord"))
        .args(["serve", "--no-zenoh", "--listen", "127.0.0.1:0", "--config"])
        .arg(dir.join("bad.json"))
        .arg("--state-dir")
        .arg(dir.join("bad-state"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(stderr.contains("factor_types[0].residual.nrom"), "{stderr}");
}
