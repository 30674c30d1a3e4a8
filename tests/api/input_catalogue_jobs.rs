//! The J rows of docs/INPUT_CATALOGUE.md (batch jobs, `POST /v1/jobs`, HTTP only), row by row,
//! against the real server: status, `error.code`, `error.field`, the message and, for 503, the
//! `Retry-After` header. Rows that only need one request are a table (`cases()`); J12
//! (too_many_jobs) and J13 (shutting_down) need a server of their own.
//!
//! Every graph is a tiny text written here (g2o, TORO, BAL); the long jobs of J12/J13 use
//! `common::synthetic_manhattan`.

use crate::common;

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use common::server::{client, get, TestServer};
use common::synthetic_manhattan;
use serde_json::{json, Value};

// ---------------------------------------------------------------------------------------------
// Small graph texts.

/// Lines joined by newlines.
fn text(lines: &[&str]) -> String {
    let mut s = lines.join("\n");
    s.push('\n');
    s
}

/// `VERTEX_SE2 id x y θ`.
fn v2(id: &str, x: &str) -> String {
    format!("VERTEX_SE2 {id} {x} 0 0")
}

/// `EDGE_SE2 i j dx 0 0` with the information `info` (upper triangle, 6 numbers).
fn e2_info(i: u64, j: u64, dx: &str, info: &str) -> String {
    format!("EDGE_SE2 {i} {j} {dx} 0 0 {info}")
}

/// `EDGE_SE2 i j 1 0 0` with unit information.
fn e2(i: u64, j: u64) -> String {
    e2_info(i, j, "1", "1 0 0 1 0 1")
}

/// `VERTEX_SE3:QUAT id 0 0 0 qx qy qz qw`.
fn v3_quat(id: u64, q: &str) -> String {
    format!("VERTEX_SE3:QUAT {id} 0 0 0 {q}")
}

/// `EDGE_SE3:QUAT i j` (1 m along x, no turn) with unit information (21 numbers).
fn e3(i: u64, j: u64) -> String {
    let mut info = Vec::new();
    for r in 0..6 {
        for c in r..6 {
            info.push(if r == c { "1" } else { "0" });
        }
    }
    format!("EDGE_SE3:QUAT {i} {j} 1 0 0 0 0 0 1 {}", info.join(" "))
}

/// A good 2D g2o graph: two poses one metre apart.
fn g2o_pair() -> String {
    text(&[&v2("0", "0"), &v2("1", "1"), &e2(0, 1)])
}

/// `VERTEX2 id x 0 0` (TORO).
fn tv(id: u64, x: &str) -> String {
    format!("VERTEX2 {id} {x} 0 0")
}

/// `EDGE2 i j 1 0 0` with the information in TORO order `xx xy yy tt xt yt`.
fn te_info(i: u64, j: u64, info: &str) -> String {
    format!("EDGE2 {i} {j} 1 0 0 {info}")
}

/// A good TORO graph: two poses one metre apart.
fn toro_pair() -> String {
    text(&[&tv(0, "0"), &tv(1, "1"), &te_info(0, 1, "1 0 1 1 0 0")])
}

/// A BAL camera at the origin looking down −z (f = 500, no distortion).
const CAMERA: &str = "0 0 0 0 0 0 500 0 0";
/// A point 5 m in front of it, on the optical axis (it projects to (0, 0)).
const POINT: &str = "0 0 -5";

/// A BAL text: the header, then the observations, cameras and points (one per line).
fn bal(header: &str, observations: &[&str], cameras: &[&str], points: &[&str]) -> String {
    let mut lines = vec![header];
    lines.extend_from_slice(observations);
    lines.extend_from_slice(cameras);
    lines.extend_from_slice(points);
    text(&lines)
}

/// A good BAL problem: one camera, one point, one observation exactly where it projects.
fn bal_one() -> String {
    bal("1 1 1", &["0 0 0 0"], &[CAMERA], &[POINT])
}

// ---------------------------------------------------------------------------------------------
// The table.

/// One request and what it must get.
struct Case {
    row: &'static str,
    /// Query string, without `?`.
    query: &'static str,
    body: Vec<u8>,
    accept: Option<&'static str>,
    status: u16,
    /// `error.code` (None: the job must succeed).
    code: Option<&'static str>,
    /// `error.field`.
    field: Option<&'static str>,
    /// A part of `error.message`, or of the answer's text when the job succeeds.
    message: &'static str,
    /// A further check of a successful JSON answer, with what it checks.
    check: Option<(&'static str, fn(&Value) -> bool)>,
}

/// A refusal: status, code, field, a part of the message.
fn refused(
    row: &'static str,
    query: &'static str,
    body: impl Into<Vec<u8>>,
    status: u16,
    code: &'static str,
    field: Option<&'static str>,
    message: &'static str,
) -> Case {
    Case {
        row,
        query,
        body: body.into(),
        accept: None,
        status,
        code: Some(code),
        field,
        message,
        check: None,
    }
}

/// A 400 `invalid_parameter` on `field` (J2–J10).
fn bad_param(
    row: &'static str,
    query: &'static str,
    field: &'static str,
    message: &'static str,
) -> Case {
    refused(
        row,
        query,
        g2o_pair(),
        400,
        "invalid_parameter",
        Some(field),
        message,
    )
}

/// A 400 `invalid_graph` on `body` (J15–J31): a parse or graph-building error.
fn bad_graph(
    row: &'static str,
    query: &'static str,
    body: impl Into<Vec<u8>>,
    message: &'static str,
) -> Case {
    refused(
        row,
        query,
        body,
        400,
        "invalid_graph",
        Some("body"),
        message,
    )
}

/// The control of a row: this request is accepted and solved (200), and the answer's text
/// contains `contains`.
fn solved(
    row: &'static str,
    query: &'static str,
    body: impl Into<Vec<u8>>,
    contains: &'static str,
) -> Case {
    Case {
        row,
        query,
        body: body.into(),
        accept: None,
        status: 200,
        code: None,
        field: None,
        message: contains,
        check: None,
    }
}

fn with_accept(mut case: Case, accept: &'static str) -> Case {
    case.accept = Some(accept);
    case
}

fn with_check(mut case: Case, what: &'static str, check: fn(&Value) -> bool) -> Case {
    case.check = Some((what, check));
    case
}

/// The SE(3) value `[x, y, z, qx, qy, qz, qw]` of the first variable of a JSON answer.
fn first_value(v: &Value) -> Vec<f64> {
    v["estimate"]["variables"][0]["value"]
        .as_array()
        .map(|a| a.iter().filter_map(Value::as_f64).collect())
        .unwrap_or_default()
}

fn cases() -> Vec<Case> {
    let pair = g2o_pair;
    let j1 = |query, field| {
        refused(
            "J1",
            query,
            g2o_pair(),
            400,
            "invalid_query",
            Some(field),
            "invalid query parameter",
        )
    };
    vec![
        // J1: only the known parameters, with the right types.
        j1("iterations=3", "iterations"),
        j1("max_iterations=ten", "max_iterations"),
        j1("max_iterations=2.5", "max_iterations"),
        j1("max_iterations=-1", "max_iterations"),
        j1("function_tolerance=small", "function_tolerance"),
        solved(
            "J1",
            "format=g2o&method=gn&max_iterations=5&init=none&robust=huber&function_tolerance=0&gradient_tolerance=0&parameter_tolerance=0&linear_solver=auto&output=json",
            pair(),
            "\"termination\"",
        ),
        // J2–J10: values of the parameters.
        bad_param("J2", "format=csv", "format", "unknown format `csv`"),
        solved("J2", "format=toro", toro_pair(), "\"termination\""),
        bad_param("J3", "method=newton", "method", "unknown method `newton`"),
        solved("J3", "method=Levenberg_Marquardt", pair(), "levenberg_marquardt"),
        solved("J3", "method=DL", pair(), "dogleg"),
        bad_param("J4", "init=random", "init", "unknown initialisation `random`"),
        solved("J4", "init=chordal", pair(), "\"termination\""),
        bad_param("J5", "linear_solver=qr", "linear_solver", "unknown linear solver `qr`"),
        solved("J5", "linear_solver=sparse_normal_cholesky", pair(), "\"termination\""),
        bad_param("J6", "max_iterations=0", "max_iterations", "between 1 and 100000"),
        bad_param("J6", "max_iterations=100001", "max_iterations", "between 1 and 100000"),
        solved("J6", "max_iterations=100000", pair(), "\"termination\""),
        bad_param("J7", "function_tolerance=-1", "function_tolerance", "finite number >= 0"),
        bad_param("J7", "gradient_tolerance=inf", "gradient_tolerance", "finite number >= 0"),
        bad_param("J7", "parameter_tolerance=NaN", "parameter_tolerance", "finite number >= 0"),
        bad_param("J8", "robust=welsch", "robust", "welsch"),
        bad_param("J8", "robust=huber:0", "robust", ""),
        bad_param("J8", "robust=cauchy:-2", "robust", ""),
        bad_param("J8", "robust=tukey:inf", "robust", ""),
        bad_param("J8", "robust=gm:x", "robust", ""),
        solved("J8", "robust=gm", pair(), "\"termination\""),
        solved("J8", "robust=Cauchy:0.5", pair(), "\"termination\""),
        bad_param("J9", "output=csv", "output", "unknown output `csv`"),
        solved("J9", "output=tum", pair(), "0 0 0 0 0 0 0 1\n1 "),
        bad_param("J10", "output=bal", "output", "bal output for bal input"),
        bad_param("J10", "format=bal&output=g2o", "output", "for pose graphs"),
        bad_param("J10", "format=bal&output=tum", "output", "for pose graphs"),
        with_accept(
            bad_param("J10", "format=bal", "output", "for pose graphs"),
            "text/plain",
        ),
        with_accept(solved("J10", "", pair(), "VERTEX_SE2 1 "), "text/plain"),
        solved("J10", "format=bal&output=bal", bal_one(), "1 1 1\n"),
        // J11: the body is UTF-8.
        refused(
            "J11",
            "",
            b"VERTEX_SE2 0 0 0 \xff\n".to_vec(),
            400,
            "unreadable_body",
            Some("body"),
            "not UTF-8",
        ),
        // J14: a solve that fails. chi2 = (1e200)² overflows: a non-finite initial cost.
        refused(
            "J14",
            "",
            text(&[&v2("0", "0"), &v2("1", "1e200"), &e2_info(0, 1, "0", "1 0 0 1 0 1")]),
            422,
            "solve_failed",
            None,
            "non-finite",
        ),
        // J14: Gauss-Newton on bundle adjustment, whose gauge is free and whose distortion
        // parameters have exactly zero Jacobian columns for a point on the optical axis.
        refused(
            "J14",
            "format=bal&method=gn",
            bal("1 1 1", &["0 0 1 1"], &[CAMERA], &[POINT]),
            422,
            "solve_failed",
            None,
            "indeterminate system",
        ),
        // J15: known records; comments and blank lines skipped (but counted in line numbers).
        bad_graph("J15", "", "VERTEX_XYZ 0 0 0 0\n", "request body:1: unsupported record `VERTEX_XYZ`"),
        bad_graph(
            "J15",
            "",
            text(&["# a comment", "", &v2("0", "0"), "EQUIV 0 0"]),
            "request body:4: unsupported record `EQUIV`",
        ),
        bad_graph(
            "J15",
            "",
            text(&[&tv(0, "0"), "FIX 0"]),
            "request body:2: unknown record `FIX` in a TORO file",
        ),
        bad_graph(
            "J15",
            "format=toro",
            text(&[&v2("0", "0")]),
            "request body:1: unknown record `VERTEX_SE2` in a TORO file",
        ),
        bad_graph(
            "J15",
            "",
            text(&["VERTEX 0 0 0 0", &e2(0, 0)]),
            "request body:2: unknown record `EDGE_SE2` in a TORO file",
        ),
        solved(
            "J15",
            "",
            text(&["# comment", "", &v2("0", "0"), "   ", &v2("1", "1"), &e2(0, 1), "FIX 0"]),
            "\"termination\"",
        ),
        solved(
            "J15",
            "",
            text(&["# TORO", &tv(0, "0"), &tv(1, "1"), &te_info(0, 1, "1 0 1 1 0 0"), "EQUIV 0 1"]),
            "\"termination\"",
        ),
        solved(
            "J15",
            "",
            text(&["VERTEX 0 0 0 0", "VERTEX 1 1 0 0", "EDGE 0 1 1 0 0 1 0 1 1 0 0"]),
            "\"termination\"",
        ),
        // J16: field counts.
        bad_graph("J16", "", "VERTEX_SE2 0 0 0\n", "request body:1: VERTEX_SE2 expects 4 fields, found 3"),
        bad_graph(
            "J16",
            "",
            "VERTEX_SE3:QUAT 0 0 0 0 0 0 1\n",
            "request body:1: VERTEX_SE3:QUAT expects 8 fields, found 7",
        ),
        bad_graph(
            "J16",
            "",
            text(&[&v2("0", "0"), &v2("1", "1"), "EDGE_SE2 0 1 1 0 0 1 0 0 1 0"]),
            "request body:3: EDGE_SE2 expects 11 fields, found 10",
        ),
        bad_graph(
            "J16",
            "",
            text(&[&v3_quat(0, "0 0 0 1"), &format!("{} 1", e3(0, 1))]),
            "request body:2: EDGE_SE3:QUAT expects 30 fields, found 31",
        ),
        bad_graph("J16", "", "VERTEX2 0 0 0\n", "request body:1: VERTEX2 expects 4 fields, found 3"),
        bad_graph(
            "J16",
            "",
            text(&[&tv(0, "0"), &tv(1, "1"), "EDGE2 0 1 1 0 0 1 0 1 1 0"]),
            "request body:3: EDGE2 expects 11 fields, found 10",
        ),
        // J17: numbers, and finite.
        bad_graph("J17", "", "VERTEX_SE2 0 x 0 0\n", "request body:1: field 2 (`x`) is not a number"),
        bad_graph("J17", "", "VERTEX_SE2 0 1e400 0 0\n", "request body:1: field 2 (`1e400`) is not finite"),
        bad_graph(
            "J17",
            "",
            text(&[&tv(0, "0"), &tv(1, "1"), &te_info(0, 1, "1 0 1 nan 0 0")]),
            "request body:3: field 9 (`nan`) is not finite",
        ),
        // J18: ids are 64-bit integers, read exactly (GTSAM's symbol keys, a robot's pose
        // ('b' << 56) | i); an id written as a float is an integer up to 2^53; FIX ids parse.
        bad_graph("J18", "", "VERTEX_SE2 -1 0 0 0\n", "request body:1: field 1 (`-1`) is not a valid id"),
        bad_graph("J18", "", "VERTEX_SE2 1.5 0 0 0\n", "request body:1: field 1 (`1.5`) is not a valid id"),
        bad_graph(
            "J18",
            "",
            "VERTEX_SE2 18446744073709551616 0 0 0\n",
            "request body:1: field 1 (`18446744073709551616`) is not a valid id",
        ),
        bad_graph(
            "J18",
            "",
            "VERTEX_SE2 1e17 0 0 0\n",
            "request body:1: field 1 (`1e17`) is not a valid id",
        ),
        solved("J18", "", "VERTEX_SE2 7061644215716937728 0 0 0\n", "\"key\":7061644215716937728"),
        bad_graph(
            "J18",
            "",
            text(&[&v2("0", "0"), &v2("1", "1"), "EDGE_SE2 0 1.5 1 0 0 1 0 0 1 0 1"]),
            "request body:3: field 2 (`1.5`) is not a valid id",
        ),
        bad_graph("J18", "", text(&[&v2("0", "0"), "FIX a"]), "request body:2: FIX field 1 (`a`) is not an id"),
        bad_graph("J18", "", text(&[&v2("0", "0"), "FIX 0 -3"]), "request body:2: field 2 (`-3`) is not a valid id"),
        solved("J18", "", "VERTEX_SE2 9007199254740992 0 0 0\n", "\"key\":9007199254740992"),
        // J19: quaternion norm in [0.5, 2], then normalised.
        bad_graph("J19", "", v3_quat(0, "0 0 0 0.1"), "request body:1: quaternion norm 0.1 is far from 1"),
        bad_graph(
            "J19",
            "",
            text(&[&v3_quat(0, "0 0 0 1"), &v3_quat(1, "0 0 0 1"), &e3(0, 1).replace(" 0 0 0 1 1 ", " 0 0 0 3 1 ")]),
            "request body:3: quaternion norm 3 is far from 1",
        ),
        with_check(
            solved("J19", "", v3_quat(0, "0 0 0.9 1.2"), "\"se3\""),
            "the quaternion (0, 0, 0.9, 1.2) comes back normalised to (0, 0, 0.6, 0.8)",
            |v| {
                let x = first_value(v);
                x.len() == 7 && (x[5] - 0.6).abs() < 1e-12 && (x[6] - 0.8).abs() < 1e-12
            },
        ),
        // J20: no mixing of 2D and 3D.
        bad_graph(
            "J20",
            "",
            text(&[&v2("0", "0"), &v3_quat(1, "0 0 0 1")]),
            "request body:2: mixes 2D and 3D records",
        ),
        bad_graph(
            "J20",
            "",
            text(&[&v3_quat(0, "0 0 0 1"), &v2("1", "0")]),
            "request body:2: mixes 2D and 3D records",
        ),
        // J21: at least one vertex or edge. These errors name no line: `request body: <reason>`.
        bad_graph("J21", "", "", "request body: no vertices or edges"),
        bad_graph("J21", "", "# nothing\n\n", "request body: no vertices or edges"),
        bad_graph("J21", "", "FIX 0\n", "request body: no vertices or edges"),
        bad_graph("J21", "format=toro", "# nothing\nEQUIV 0 1\n", "request body: no vertices or edges"),
        // J21a: edges only, but not connected.
        bad_graph(
            "J21a",
            "",
            "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 5 6 1 0 0 1 0 0 1 0 1\n",
            "request body: the file has no vertices and its edges do not connect vertex 5",
        ),
        bad_graph(
            "J21a",
            "format=toro",
            "EDGE2 0 1 1 0 0 1 0 1 1 0 0\nEDGE2 5 6 1 0 0 1 0 1 1 0 0\n",
            "do not connect vertex 5 (and 1 more) to vertex 0",
        ),
        // J22: unique vertex ids.
        bad_graph(
            "J22",
            "",
            text(&[&v2("0", "0"), &v2("0", "1")]),
            "request body:2: variable 0 already exists",
        ),
        bad_graph(
            "J22",
            "",
            text(&[&tv(4, "0"), &tv(4, "1")]),
            "request body:2: variable 4 already exists",
        ),
        // J23: edge endpoints and FIX ids exist.
        bad_graph(
            "J23",
            "",
            text(&[&v2("0", "0"), &e2(0, 7)]),
            "request body:2: EDGE_SE2 0 7 (request body:2): refers to unknown variable 7",
        ),
        bad_graph(
            "J23",
            "",
            text(&[&tv(0, "0"), &te_info(9, 0, "1 0 1 1 0 0")]),
            "refers to unknown variable 9",
        ),
        bad_graph("J23", "", text(&[&v2("0", "0"), "FIX 9"]), "request body:2: unknown variable 9"),
        // J24: information positive definite (g2o: upper triangle; TORO: xx xy yy tt xt yt).
        // "Symmetric" cannot fail from a file: both formats give only one triangle.
        bad_graph(
            "J24",
            "",
            text(&[&v2("0", "0"), &v2("1", "1"), &e2_info(0, 1, "1", "1 0 0 -1 0 1")]),
            "request body:3: EDGE_SE2 0 1 (request body:3): information matrix is invalid",
        ),
        bad_graph(
            "J24",
            "",
            text(&[&tv(0, "0"), &tv(1, "1"), &te_info(0, 1, "1 2 1 1 0 0")]),
            "request body:3: EDGE2 0 1 (request body:3): information matrix is invalid",
        ),
        // PD in TORO's order, not in g2o's (xx xy xt yy yt tt): TORO's order is the one read.
        solved(
            "J24",
            "",
            text(&[&tv(0, "0"), &tv(1, "1"), &te_info(0, 1, "1 0 1 1 0 0.5")]),
            "\"termination\"",
        ),
        // J25: distinct endpoints, finite residual at the initial values.
        bad_graph(
            "J25",
            "",
            text(&[&v2("0", "0"), &e2(0, 0)]),
            "request body:2: EDGE_SE2 0 0 (request body:2): touches variable 0 twice",
        ),
        bad_graph(
            "J25",
            "",
            text(&[&v2("0", "1e308"), &v2("1", "-1e308"), &e2(0, 1)]),
            "request body:3: EDGE_SE2 0 1 (request body:3): measurement is not finite",
        ),
        // J26: the BAL header.
        bad_graph("J26", "format=bal", "x 0 0\n", "request body:1: the number of cameras (`x`) is not a number"),
        bad_graph(
            "J26",
            "format=bal",
            "-1 0 0\n",
            "request body:1: the number of cameras `-1` is not an index below 1099511627776",
        ),
        bad_graph(
            "J26",
            "format=bal",
            "1 1099511627776 0\n",
            "request body:1: the number of points `1099511627776` is not an index below 1099511627776",
        ),
        bad_graph(
            "J26",
            "format=bal",
            "1 1 0.5\n",
            "request body:1: the number of observations `0.5` is not an index below",
        ),
        bad_graph(
            "J26",
            "format=bal",
            "1 1\n",
            "request body:1: file ends where the number of observations was expected",
        ),
        // J27: enough numbers for the counts.
        bad_graph(
            "J27",
            "format=bal",
            bal("1 1 1", &["0 0 0 0"], &[CAMERA], &[]),
            "request body:3: the header announces 1 cameras, 1 points and 1 observations (19 numbers), the file has 16",
        ),
        // J28: observation indices in range.
        bad_graph(
            "J28",
            "format=bal",
            bal("1 1 1", &["1 0 0 0"], &[CAMERA], &[POINT]),
            "request body:2: observation 0's camera `1` is not an index below 1",
        ),
        bad_graph(
            "J28",
            "format=bal",
            bal("1 1 1", &["0 3 0 0"], &[CAMERA], &[POINT]),
            "request body:2: observation 0's point `3` is not an index below 1",
        ),
        // J29: numbers, and finite.
        bad_graph(
            "J29",
            "format=bal",
            bal("1 1 1", &["0 0 abc 0"], &[CAMERA], &[POINT]),
            "request body:2: observation 0's x (`abc`) is not a number",
        ),
        bad_graph(
            "J29",
            "format=bal",
            bal("1 1 1", &["0 0 0 0"], &["nan 0 0 0 0 0 500 0 0"], &[POINT]),
            "request body:3: camera 0's parameter 0 (`nan`) is not finite",
        ),
        bad_graph(
            "J29",
            "format=bal",
            bal("1 1 1", &["0 0 0 0"], &[CAMERA], &["0 0 -1e999"]),
            "request body:4: point 0's coordinate 2 (`-1e999`) is not finite",
        ),
        // J30: nothing after the last point.
        bad_graph(
            "J30",
            "format=bal",
            bal("1 1 1", &["0 0 0 0"], &[CAMERA], &[POINT, "7"]),
            "request body:5: unexpected `7` after the last point: the counts in the header do not match the data",
        ),
        // J31: a point at the camera's centre (depth 0) has no finite reprojection.
        bad_graph(
            "J31",
            "format=bal",
            bal("1 1 1", &["0 0 0 0"], &[CAMERA], &["0 0 0"]),
            "request body:1: observation 0: measurement is not finite",
        ),
        solved("J31", "format=bal", bal_one(), "\"termination\""),
    ]
}

/// What the server answered.
struct Answer {
    status: u16,
    retry_after: Option<String>,
    content_type: String,
    text: String,
    json: Value,
}

async fn post_job(
    c: &reqwest::Client,
    url: &str,
    body: impl Into<reqwest::Body>,
    accept: Option<&str>,
) -> Answer {
    let mut req = c.post(url).body(body);
    if let Some(a) = accept {
        req = req.header("accept", a);
    }
    let resp = req
        .send()
        .await
        .unwrap_or_else(|e| panic!("{url}: request failed: {e:?}"));
    let header = |name: &str| {
        resp.headers()
            .get(name)
            .map(|v| v.to_str().unwrap_or("?").to_string())
    };
    let (retry_after, content_type) = (header("retry-after"), header("content-type"));
    let status = resp.status().as_u16();
    let text = resp.text().await.expect("body");
    Answer {
        status,
        retry_after,
        content_type: content_type.unwrap_or_default(),
        json: serde_json::from_str(&text).unwrap_or(Value::Null),
        text,
    }
}

/// Checks an error answer: status, code, field, message (a part of it), and the `status` and
/// `retry_after` inside the body against the header.
fn assert_error(
    what: &str,
    a: &Answer,
    status: u16,
    code: &str,
    field: Option<&str>,
    message: &str,
    retry_after: Option<u64>,
) {
    let e = &a.json["error"];
    assert_eq!(a.status, status, "{what}: status; answer {}", a.text);
    assert_eq!(e["code"], code, "{what}: code; answer {}", a.text);
    assert_eq!(
        e["field"].as_str(),
        field,
        "{what}: field; answer {}",
        a.text
    );
    assert_eq!(
        e["status"], status,
        "{what}: error.status; answer {}",
        a.text
    );
    let m = e["message"].as_str().unwrap_or_default();
    assert!(
        m.contains(message),
        "{what}: message {m:?} lacks {message:?}"
    );
    assert_eq!(
        a.retry_after,
        retry_after.map(|s| s.to_string()),
        "{what}: Retry-After header; answer {}",
        a.text
    );
    assert_eq!(
        e["retry_after"].as_u64(),
        retry_after,
        "{what}: error.retry_after; answer {}",
        a.text
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn every_job_row_answers_as_the_catalogue_says() {
    let s = TestServer::start(&["--no-zenoh"]);
    let c = client();
    let mut checked: Vec<&str> = Vec::new();
    for case in cases() {
        let url = if case.query.is_empty() {
            s.url("/v1/jobs")
        } else {
            s.url(&format!("/v1/jobs?{}", case.query))
        };
        let what = format!(
            "{} ?{} {:?}",
            case.row,
            case.query,
            String::from_utf8_lossy(&case.body[..case.body.len().min(120)])
        );
        let a = post_job(&c, &url, case.body.clone(), case.accept).await;
        match case.code {
            Some(code) => {
                assert_error(&what, &a, case.status, code, case.field, case.message, None);
            }
            None => {
                assert_eq!(a.status, case.status, "{what}: {}", a.text);
                assert!(
                    a.text.contains(case.message),
                    "{what}: the answer lacks {:?}: {}",
                    case.message,
                    a.text
                );
                let text_output = case.query.contains("output=tum")
                    || case.query.contains("output=bal")
                    || case.accept == Some("text/plain");
                if text_output {
                    assert!(
                        a.content_type.starts_with("text/plain"),
                        "{what}: content type {}",
                        a.content_type
                    );
                } else {
                    assert!(
                        a.json["summary"]["termination"]["reason"].is_string()
                            && a.json["estimate"]["variables"].is_array(),
                        "{what}: not a job result: {}",
                        a.text
                    );
                }
                if let Some((check, ok)) = case.check {
                    assert!(ok(&a.json), "{what}: {check}: {}", a.text);
                }
            }
        }
        if checked.last() != Some(&case.row) {
            checked.push(case.row);
        }
    }
    // Every simple row has at least one case (J12 and J13 have tests of their own).
    for n in (1..=31).filter(|n| ![12, 13].contains(n)) {
        let row = format!("J{n}");
        assert!(checked.contains(&row.as_str()), "{row} has no case");
    }
    s.assert_no_panic();
    println!("rows checked over HTTP: {checked:?}");
}

// ---------------------------------------------------------------------------------------------
// J12 and J13: a server of their own.

/// Query parameters that make a job on `synthetic_manhattan(1500, _)` run for minutes:
/// Gauss-Newton with every tolerance off runs all its iterations.
const ENDLESS: &str = "/v1/jobs?max_iterations=100000&function_tolerance=0&gradient_tolerance=0&parameter_tolerance=0&init=none";

/// A server with `limits` from a config file (and zenoh off).
fn server_with_limits(limits: Value) -> TestServer {
    let config = common::temp_dir("config").join("factord.json");
    std::fs::write(&config, json!({ "limits": limits }).to_string()).unwrap();
    TestServer::start(&["--no-zenoh", "--config", config.to_str().unwrap()])
}

/// Polls `/v1/health` until `ready` holds for it (at most 30 s).
async fn wait_for_health(
    c: &reqwest::Client,
    s: &TestServer,
    what: &str,
    ready: fn(&Value) -> bool,
) {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let (status, h) = get(c, &s.url("/v1/health")).await;
        if status == 200 && ready(&h) {
            return;
        }
        assert!(Instant::now() < deadline, "waiting for {what}: {h}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// A long job, in the background.
fn spawn_long_job(
    c: &reqwest::Client,
    s: &TestServer,
    seed: u64,
) -> tokio::task::JoinHandle<Answer> {
    let (c, url) = (c.clone(), s.url(ENDLESS));
    tokio::spawn(async move { post_job(&c, &url, synthetic_manhattan(1500, seed), None).await })
}

#[tokio::test(flavor = "multi_thread")]
async fn j12_a_job_beyond_max_jobs_gets_503_too_many_jobs() {
    let s = server_with_limits(json!({"workers": 1, "max_jobs": 1}));
    let c = client();
    // Control: with nothing else in flight a small job runs.
    let small = synthetic_manhattan(10, 1);
    let a = post_job(&c, &s.url("/v1/jobs"), small.clone(), None).await;
    assert_eq!(a.status, 200, "J12 control: {}", a.text);
    wait_for_health(&c, &s, "an idle worker", |h| h["busy_workers"] == 0).await;

    let long = spawn_long_job(&c, &s, 4);
    // The worker is busy with the long job, which holds the only job slot.
    wait_for_health(&c, &s, "the long job running", |h| h["busy_workers"] == 1).await;
    let a = post_job(&c, &s.url("/v1/jobs"), small, None).await;
    assert_error(
        "J12",
        &a,
        503,
        "too_many_jobs",
        None,
        "1 batch jobs are already running or queued",
        Some(1),
    );
    assert!(!long.is_finished(), "J12: the long job ended early");
    long.abort();
    s.assert_no_panic();
    println!("rows checked over HTTP: [\"J12\"]");
}

/// A job request over a raw connection whose body is held back: the server has read its
/// headers and is reading its body (it answered `Expect: 100-continue`) when `finish` sends it.
struct HeldJob {
    stream: std::net::TcpStream,
    body: String,
}

impl HeldJob {
    fn open(addr: &str, body: String) -> Self {
        let mut stream = std::net::TcpStream::connect(addr).expect("connect");
        stream
            .set_read_timeout(Some(Duration::from_secs(30)))
            .unwrap();
        write!(
            stream,
            "POST /v1/jobs HTTP/1.1\r\nHost: {addr}\r\nContent-Length: {}\r\nExpect: 100-continue\r\nConnection: close\r\n\r\n",
            body.len()
        )
        .unwrap();
        // The interim answer: the handler is reading the body.
        let mut head = Vec::new();
        let mut byte = [0u8];
        while !head.ends_with(b"\r\n\r\n") {
            let n = stream.read(&mut byte).expect("reading 100 Continue");
            assert_eq!(n, 1, "connection closed before 100 Continue: {head:?}");
            head.push(byte[0]);
        }
        let head = String::from_utf8_lossy(&head);
        assert!(
            head.starts_with("HTTP/1.1 100"),
            "expected 100 Continue: {head}"
        );
        Self { stream, body }
    }

    /// Sends the body and reads the answer (the connection closes after it).
    fn finish(mut self) -> Answer {
        self.stream.write_all(self.body.as_bytes()).unwrap();
        let mut raw = Vec::new();
        self.stream
            .read_to_end(&mut raw)
            .expect("reading the answer");
        let raw = String::from_utf8_lossy(&raw).into_owned();
        let (head, body) = raw
            .split_once("\r\n\r\n")
            .unwrap_or_else(|| panic!("no complete answer: {raw:?}"));
        let mut lines = head.lines();
        let status = lines
            .next()
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("no status line: {raw:?}"));
        let header = |name: &str| {
            head.lines().find_map(|l| {
                let (k, v) = l.split_once(':')?;
                k.eq_ignore_ascii_case(name).then(|| v.trim().to_string())
            })
        };
        assert!(
            header("transfer-encoding").is_none(),
            "expected a sized answer: {raw:?}"
        );
        Answer {
            status,
            retry_after: header("retry-after"),
            content_type: header("content-type").unwrap_or_default(),
            json: serde_json::from_str(body).unwrap_or(Value::Null),
            text: body.to_string(),
        }
    }
}

/// J13. With one worker and two long jobs, one job runs and the other waits in the queue. At
/// SIGTERM the pool stops: queued work is dropped (its caller gets 503 shutting_down, "the job
/// was dropped at shutdown") and the running solve stops after its current iteration and answers
/// 200 with its best estimate (termination `interrupted`); a job stopped before its first step
/// has no estimate to give and answers 503 shutting_down, "the job was stopped at shutdown"
/// (the jobs share the worker in time slices, so on a loaded machine the second job may have
/// started and not finished a step). Which of these each job meets is not ours to choose, so
/// each must be one of those answers, and at least one must be a 503. A third job whose body arrives after the service has stopped is refused at
/// submission with 503 shutting_down, "the service is shutting down". (A job sent on a new
/// connection after SIGTERM cannot be tested: the listener closes, so it is refused by TCP.)
#[tokio::test(flavor = "multi_thread")]
async fn j13_jobs_at_shutdown_get_503_shutting_down() {
    let s = server_with_limits(json!({"workers": 1, "max_jobs": 3}));
    let c = client();
    let first = spawn_long_job(&c, &s, 4);
    let second = spawn_long_job(&c, &s, 5);
    // Both jobs are on the pool: one runs, the other is queued.
    wait_for_health(&c, &s, "one job running and one queued", |h| {
        h["busy_workers"] == 1 && h["queued"] == 1
    })
    .await;
    let addr = s.http.trim_start_matches("http://").to_string();
    let held = tokio::task::spawn_blocking(move || HeldJob::open(&addr, g2o_pair()))
        .await
        .unwrap();

    let kill = std::process::Command::new("kill")
        .args(["-TERM", &s.pid().to_string()])
        .status()
        .expect("kill runs");
    assert!(kill.success(), "SIGTERM not delivered");
    // Whichever job answers first proves the pool is stopping (both answer only at shutdown).
    let deadline = Instant::now() + Duration::from_secs(30);
    while !first.is_finished() && !second.is_finished() {
        assert!(
            Instant::now() < deadline,
            "J13: no job answered after SIGTERM"
        );
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    let late = tokio::task::spawn_blocking(move || held.finish())
        .await
        .unwrap();
    assert_error(
        "J13 (a job submitted while shutting down)",
        &late,
        503,
        "shutting_down",
        None,
        "the service is shutting down",
        Some(5),
    );

    let answers = [first.await.unwrap(), second.await.unwrap()];
    let mut dropped = 0;
    for (i, a) in answers.iter().enumerate() {
        let what = format!("J13 (long job {i})");
        if a.status == 200 {
            assert_eq!(
                a.json["summary"]["termination"]["reason"], "interrupted",
                "{what}: a job answered 200 must have been interrupted: {}",
                a.text
            );
        } else {
            let message = match a.text.contains("stopped") {
                true => "the job was stopped at shutdown",
                false => "the job was dropped at shutdown",
            };
            assert_error(&what, a, 503, "shutting_down", None, message, Some(5));
            dropped += 1;
        }
    }
    assert!(
        dropped >= 1,
        "J13: neither job was dropped or stopped before a step: {} / {}",
        answers[0].text,
        answers[1].text
    );
    let (exit, log) = s.terminate(Duration::from_secs(30));
    assert!(
        exit.is_some_and(|e| e.success()),
        "the server did not exit cleanly ({exit:?}):\n{log}"
    );
    assert!(!log.contains("panicked"), "server panicked:\n{log}");
    println!("rows checked over HTTP: [\"J13\"] ({dropped} of 2 long jobs answered 503, the late one refused)");
}

#[tokio::test(flavor = "multi_thread")]
async fn j32_a_job_beyond_max_job_memory_bytes_gets_413_job_too_large() {
    // 2000 poses need a few MiB; 1 MiB refuses them, while two poses fit.
    let s = server_with_limits(json!({"max_job_memory_bytes": 1 << 20}));
    let c = client();
    let a = post_job(&c, &s.url("/v1/jobs"), g2o_pair(), None).await;
    assert_eq!(a.status, 200, "J32 control: {}", a.text);
    let start = Instant::now();
    let a = post_job(&c, &s.url("/v1/jobs"), synthetic_manhattan(2000, 1), None).await;
    assert_error(
        "J32",
        &a,
        413,
        "job_too_large",
        Some("body"),
        "more than limits.max_job_memory_bytes (1 MiB)",
        None,
    );
    // Refused from the symbolic factorisation, before any numeric work.
    assert_eq!(
        a.json["error"]["message"]
            .as_str()
            .map(|m| m.contains("MiB of memory")),
        Some(true)
    );
    assert!(start.elapsed() < Duration::from_secs(5));
    s.assert_no_panic();
    println!("rows checked over HTTP: [\"J32\"]");
}
