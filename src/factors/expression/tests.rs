use std::sync::Arc;

use serde_json::{json, Value};

use super::*;
use crate::factors::testing::{assert_jacobians_match, Rng};
use crate::factors::{BetweenSe2, BetweenSe3, Factor};
use crate::geometry::Point3;
use crate::variables::Variable;

fn definition(value: Value) -> FactorTypeDefinition {
    serde_json::from_value(value).expect("a well-formed definition")
}

fn compile(value: Value) -> Result<Arc<ExpressionType>, DefinitionError> {
    ExpressionType::compile(definition(value))
}

/// `between_se2` written as an expression: `[t(E), wrap(θ(E))]`, `E = z⁻¹ (a⁻¹ b)`.
pub fn between_se2_definition() -> Value {
    json!({
        "name": "my_between_se2",
        "variables": [{"name": "a", "kind": "se2"}, {"name": "b", "kind": "se2"}],
        "parameters": [{"name": "z", "kind": "se2"}],
        "residual": [
            {"translation": [{"between": ["z", {"between": ["a", "b"]}]}]},
            {"wrap": [{"angle": [{"between": ["z", {"between": ["a", "b"]}]}]}]}
        ]
    })
}

fn evaluate(f: &dyn Factor, vars: &[Box<dyn Variable>]) -> (Vec<f64>, Vec<f64>) {
    let refs: Vec<&dyn Variable> = vars.iter().map(|v| v.as_ref()).collect();
    let cols: usize = vars.iter().map(|v| v.tangent_dim()).sum();
    let mut e = vec![0.0; f.residual_dim()];
    let mut j = vec![0.0; f.residual_dim() * cols];
    f.evaluate(&refs, &mut e, Some(&mut j)).unwrap();
    (e, j)
}

fn assert_close(a: &[f64], b: &[f64], tolerance: f64) {
    for (x, y) in a.iter().zip(b) {
        assert!(
            (x - y).abs() <= tolerance * (1.0 + y.abs()),
            "{a:?}\nvs\n{b:?}"
        );
    }
}

#[test]
fn between_se2_expression_equals_the_built_in_factor() {
    let ty = compile(between_se2_definition()).unwrap();
    assert_eq!((ty.residual_dim(), ty.measurement_len()), (3, 3));
    let mut rng = Rng::new(11);
    for _ in 0..200 {
        let z = rng.se2();
        let built_in = BetweenSe2::new(0, 1, z);
        let user = ty.build(&[0, 1], &[z.x, z.y, z.theta]).unwrap();
        let vars: Vec<Box<dyn Variable>> = vec![Box::new(rng.se2()), Box::new(rng.se2())];
        let (e0, j0) = evaluate(&built_in, &vars);
        let (e1, j1) = evaluate(&user, &vars);
        assert_close(&e1, &e0, 1e-12);
        assert_close(&j1, &j0, 1e-12);
        assert_jacobians_match(&user, &vars);
    }
}

#[test]
fn between_se3_expression_equals_the_built_in_factor() {
    let e = json!({"between": ["z", {"between": ["a", "b"]}]});
    let ty = compile(json!({
        "name": "my_between_se3",
        "variables": [{"name": "a", "kind": "se3"}, {"name": "b", "kind": "se3"}],
        "parameters": [{"name": "z", "kind": "se3"}],
        "residual": [{"translation": [e.clone()]}, {"log": [{"rotation": [e]}]}]
    }))
    .unwrap();
    let mut rng = Rng::new(5);
    for _ in 0..200 {
        let z = rng.se3();
        let q = z.rotation.quaternion();
        let wire = [
            z.translation.x,
            z.translation.y,
            z.translation.z,
            q.i,
            q.j,
            q.k,
            q.w,
        ];
        let built_in = BetweenSe3::new(0, 1, z);
        let user = ty.build(&[0, 1], &wire).unwrap();
        let vars: Vec<Box<dyn Variable>> = vec![Box::new(rng.se3()), Box::new(rng.se3())];
        let (e0, j0) = evaluate(&built_in, &vars);
        let (e1, j1) = evaluate(&user, &vars);
        assert_close(&e1, &e0, 1e-9);
        assert_close(&j1, &j0, 1e-7);
    }
}

#[test]
fn every_operation_differentiates_like_central_differences() {
    let mut rng = Rng::new(17);
    let residuals = [
        json!([{"log": [{"compose": ["p", {"exp_se2": [[{"at": ["v", 0]}, 0.3, {"atan": ["s"]}]]}]}]}]),
        json!({"act": [{"inverse": ["p"]}, {"translation": ["q"]}]}),
        json!([{"atan2": [{"sin": ["s"]}, {"add": [2, {"cos": ["s"]}]}]}, {"tan": [{"mul": [0.2, "s"]}]}]),
        json!([{"sqrt": [{"add": [1, {"squared_norm": ["v"]}]}]}, {"exp": [{"mul": [0.1, "s"]}]}]),
        json!([{"log": [{"add": [2, {"sin": ["s"]}]}]}, {"pow": [{"add": [3, {"cos": ["s"]}]}, 1.5]}]),
        json!([{"asin": [{"mul": [0.5, {"sin": ["s"]}]}]}, {"acos": [{"mul": [0.5, {"cos": ["s"]}]}]}]),
        json!({"div": [{"cross": ["v", {"translation": ["r"]}]}, {"add": [5, {"norm": ["v"]}]}]}),
        json!({"log": [{"compose": [{"rotation": ["r"]}, {"exp_so3": [{"mul": [0.1, "v"]}]}]}]}),
        json!({"translation": [{"compose": [{"inverse": ["r"]}, {"se3": [{"exp_so3": ["v"]}, "v"]}]}]}),
        json!([{"dot": ["v", {"act": ["r", "v"]}]}, {"neg": [{"abs": [{"add": [10, "s"]}]}]}]),
        json!({"sub": ["v", {"act": [{"rotation": ["r"]}, "v"]}]}),
    ];
    for (k, residual) in residuals.into_iter().enumerate() {
        let ty = compile(json!({
            "name": format!("ops_{k}"),
            "variables": [
                {"name": "p", "kind": "se2"}, {"name": "q", "kind": "se2"},
                {"name": "r", "kind": "se3"}, {"name": "v", "kind": "point3"},
                {"name": "c", "kind": "snavely_camera"}
            ],
            "parameters": [{"name": "s_unused", "kind": "scalar"}],
            "residual": residual.to_string().replace("\"s\"", "{\"at\": [{\"translation\": [\"q\"]}, 0]}")
                .parse::<Value>().unwrap()
        }))
        .unwrap_or_else(|e| panic!("residual {k}: {e}"));
        for _ in 0..50 {
            let vars: Vec<Box<dyn Variable>> = vec![
                Box::new(rng.se2()),
                Box::new(rng.se2()),
                Box::new(rng.se3()),
                Box::new(Point3(rng.vector3(2.0))),
                Box::new(crate::geometry::SnavelyCamera {
                    rotation: rng.se3().rotation,
                    translation: rng.vector3(1.0),
                    focal: 500.0,
                    k1: 0.0,
                    k2: 0.0,
                }),
            ];
            let f = ty.build(&[0, 1, 2, 3, 4], &[0.0]).unwrap();
            assert_jacobians_match(&f, &vars);
        }
    }
}

#[test]
fn camera_projection_differentiates_like_central_differences() {
    // A pinhole projection of a point through a bundle-adjustment camera (no distortion).
    let ty = compile(
        json!({
            "name": "pinhole",
            "variables": [{"name": "c", "kind": "snavely_camera"}, {"name": "x", "kind": "point3"}],
            "parameters": [{"name": "uv", "kind": "vector", "len": 2}],
            "residual": {"sub": [
                {"mul": [{"at": [{"intrinsics": ["c"]}, 0]},
                         {"div": [[{"at": ["p", 0]}, {"at": ["p", 1]}], {"at": ["p", 2]}]}]},
                "uv"]}
        })
        .to_string()
        .replace(
            "\"p\"",
            "{\"add\": [{\"act\": [{\"rotation\": [\"c\"]}, \"x\"]}, {\"translation\": [\"c\"]}]}",
        )
        .parse()
        .unwrap(),
    );
    let ty = ty.unwrap();
    let mut rng = Rng::new(3);
    for _ in 0..100 {
        let pose = rng.se3();
        let camera = crate::geometry::SnavelyCamera {
            rotation: pose.rotation,
            translation: nalgebra::Vector3::new(0.0, 0.0, 10.0),
            focal: 400.0 + rng.uniform(),
            k1: 0.0,
            k2: 0.0,
        };
        let vars: Vec<Box<dyn Variable>> =
            vec![Box::new(camera), Box::new(Point3(rng.vector3(1.0)))];
        assert_jacobians_match(&ty.build(&[0, 1], &[1.0, 2.0]).unwrap(), &vars);
    }
}

/// Every refusal names the node or field at fault.
#[test]
fn bad_definitions_are_refused_with_the_path_of_the_bad_node() {
    let base = between_se2_definition();
    let with_residual = |residual: Value| {
        let mut d = base.clone();
        d["residual"] = residual;
        d
    };
    let mut deep = json!("a");
    for _ in 0..100 {
        deep = json!({"inverse": [deep]});
    }
    let deep_path = format!("residual{}", ".inverse[0]".repeat(MAX_DEPTH + 1));
    let wide: Vec<Value> = (0..5000).map(|_| json!(1.0)).collect();
    let cases: Vec<(Value, &str, &str)> = vec![
        (
            with_residual(json!({"compose": ["a", {"frobnicate": ["b"]}]})),
            "residual.compose[1].frobnicate",
            "unknown operation",
        ),
        (
            with_residual(json!({"add": ["a", "b"]})),
            "residual.add",
            "`add` takes",
        ),
        (
            with_residual(json!([{"translation": ["a"]}, {"compose": ["a", "b"]}])),
            "residual[1]",
            "not a se2",
        ),
        (
            with_residual(json!({"sin": ["nobody"]})),
            "residual.sin[0]",
            "unknown name",
        ),
        (
            with_residual(json!({"sin": ["a", "b"]})),
            "residual.sin",
            "takes 1 argument",
        ),
        (
            with_residual(json!({"sin": "a"})),
            "residual.sin",
            "are an array",
        ),
        (
            with_residual(json!({"sin": [1], "cos": [1]})),
            "residual",
            "exactly one key",
        ),
        (with_residual(json!(true)), "residual", "expected a number"),
        (with_residual(json!([])), "residual", "empty vector"),
        (
            with_residual(json!({"at": [{"translation": ["a"]}, 2]})),
            "residual.at[1]",
            "outside a vector of 2",
        ),
        (
            with_residual(json!({"at": [{"translation": ["a"]}, -1]})),
            "residual.at[1]",
            "integer literal",
        ),
        (
            with_residual(json!({"between": ["a", "b"]})),
            "residual",
            "not a se2",
        ),
        (
            with_residual(json!([{"log": [0]}, {"angle": ["a"]}])),
            "residual[0].log",
            "not a finite number",
        ),
        (
            with_residual(json!([{"div": [1, {"sub": [2, 2]}]}])),
            "residual[0].div",
            "not a finite number",
        ),
        (
            with_residual(
                json!({"sqrt": [{"neg": [{"add": [1, {"squared_norm": [{"translation": ["a"]}]}]}]}]}),
            ),
            "residual.sqrt",
            "not finite at any",
        ),
        (with_residual(deep), &deep_path, "deeper than 48"),
        (
            with_residual(Value::Array(wide)),
            "residual[4095]",
            "more than 4096 nodes",
        ),
        (
            with_residual(json!([{"abs": [{"angle": [{"between": ["a", "b"]}]}]}])),
            "",
            "",
        ),
        (
            json!({"name": "Bad Name", "variables": [], "residual": 1}),
            "name",
            "[a-z0-9_]",
        ),
        (
            json!({"name": "x", "variables": [], "residual": 1}),
            "variables",
            "1 to 8",
        ),
        (
            json!({"name": "x", "variables": [{"name": "a", "kind": "se4"}], "residual": 1}),
            "variables[0].kind",
            "unknown kind",
        ),
        (
            json!({"name": "x", "variables": [{"name": "a", "kind": "se2"}, {"name": "a", "kind": "se2"}], "residual": 1}),
            "variables[1].name",
            "declared twice",
        ),
        (
            json!({"name": "x", "variables": [{"name": "a", "kind": "se2"}], "parameters": [{"name": "v", "kind": "vector"}], "residual": 1}),
            "parameters[0].len",
            "len of 1 to",
        ),
        (
            json!({"name": "x", "variables": [{"name": "a", "kind": "se2"}], "residual": "a"}),
            "residual",
            "not a se2",
        ),
        (
            json!({"name": "x", "variables": [{"name": "a", "kind": "se2"}], "residual": [1, 2], "residual_dim": 3}),
            "residual_dim",
            "has 2 entries",
        ),
    ];
    for (definition_json, path, message) in cases {
        let result = compile(definition_json.clone());
        if path.is_empty() {
            // |angle| has a kink only where the angle is 0: accepted.
            assert!(result.is_ok(), "{definition_json}: {result:?}");
            continue;
        }
        let e = result.expect_err(&definition_json.to_string());
        assert_eq!(e.path, path, "{definition_json}: {e}");
        assert!(e.message.contains(message), "{definition_json}: {e}");
    }
}

#[test]
fn an_expression_too_costly_to_evaluate_is_refused() {
    // 300 distinct SE(3) compositions over eight poses (48 derivative lanes): few nodes, many
    // operations.
    let terms: Vec<Value> = (0..300)
        .map(|k| {
            let v = json!([k as f64 * 0.01, 0, 0]);
            json!({"translation": [{"compose": [format!("r{}", k % 8), {"se3": [{"exp_so3": [v]}, v]}]}]})
        })
        .collect();
    let variables: Vec<Value> = (0..8)
        .map(|k| json!({"name": format!("r{k}"), "kind": "se3"}))
        .collect();
    let e =
        compile(json!({"name": "costly", "variables": variables, "residual": {"norm": [terms]}}))
            .unwrap_err();
    assert_eq!(e.path, "residual", "{e}");
    assert!(e.message.contains("over the bound"), "{e}");
}

#[test]
fn an_invalid_se3_parameter_is_refused_when_the_factor_is_built() {
    let ty = compile(json!({
        "name": "pose_prior",
        "variables": [{"name": "x", "kind": "se3"}],
        "parameters": [{"name": "z", "kind": "se3"}],
        "residual": {"log": [{"rotation": [{"between": ["z", "x"]}]}]}
    }))
    .unwrap();
    let e = ty
        .build(&[0], &[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0])
        .unwrap_err();
    assert!(e.contains("parameter `z`") && e.contains("norm"), "{e}");
}

/// BAL's reprojection (`reprojection_snavely`) written as an expression: the documented example.
fn snavely_definition() -> Value {
    serde_json::from_str(include_str!(
        "../../../proto/v1/examples/factor-type-reprojection.example.json"
    ))
    .expect("the example is JSON")
}

#[test]
fn snavely_reprojection_expression_equals_the_built_in_factor() {
    let ty = compile(snavely_definition()).unwrap();
    let mut rng = Rng::new(23);
    for _ in 0..200 {
        let pose = rng.se3();
        let camera = crate::geometry::SnavelyCamera {
            rotation: pose.rotation,
            translation: nalgebra::Vector3::new(0.1 * rng.normal(), 0.1 * rng.normal(), -10.0),
            focal: 500.0 + 10.0 * rng.normal(),
            k1: 0.05 * rng.normal(),
            k2: 0.01 * rng.normal(),
        };
        let z = [rng.normal(), rng.normal()];
        let built_in =
            crate::factors::ReprojectionSnavely::new(0, 1, nalgebra::Vector2::new(z[0], z[1]));
        let user = ty.build(&[0, 1], &z).unwrap();
        let vars: Vec<Box<dyn Variable>> =
            vec![Box::new(camera), Box::new(Point3(rng.vector3(1.0)))];
        let (e0, j0) = evaluate(&built_in, &vars);
        let (e1, j1) = evaluate(&user, &vars);
        assert_close(&e1, &e0, 1e-10);
        assert_close(&j1, &j0, 1e-9);
    }
}
