//! Graphs without vertices (issue 18, item 3): SE-Sync's `CSAIL.g2o` and GTSAM's `w20000.txt`
//! are read, get a start from a spanning tree of their edges, and converge; w20000's six numbers
//! are read as GTSAM reads them (a covariance); a graph whose edges do not connect is refused
//! naming a vertex, from a file, and as a batch job over HTTP.
//!
//! GTSAM in the same terms: `benches/edges_only/gtsam_no_vertices.py` (see its README).

use crate::common;

use std::path::Path;

use common::server::{client, TestServer};
use factord::geometry::Se2;
use factord::io;
use factord::problem::evaluate_chi2;
use factord::solver::{optimize, SolverOptions, Summary};
use serde_json::Value;

fn solve(graph: &mut io::PoseGraph) -> Summary {
    optimize(&mut graph.problem, &SolverOptions::default(), &mut |_| {
        std::ops::ControlFlow::Continue(())
    })
    .expect("solve succeeds")
}

/// `text` without its vertex lines.
fn edges_only(text: &str) -> String {
    text.lines()
        .filter(|l| !l.starts_with("VERTEX"))
        .map(|l| format!("{l}\n"))
        .collect()
}

#[test]
fn w20000_and_csail_converge_from_no_vertices() {
    // (file, poses, the optimum's chi2 bound): w20000's is GTSAM LM's result at its default
    // 100-iteration cap from the chained start (MANIFEST.md); CSAIL's is GTSAM's optimum
    // (40.5509, Gauss-Newton and LM agree) plus the gap between GTSAM's Pose2 error (Logmap)
    // and ours (t2v), measured 0.02 on these poses.
    for (file, poses, bound) in [
        // w20000 names 20061 poses (ids 0-20060), not the 20000 of its name.
        ("2d/gtsam/w20000.txt", 20061, 1155.28),
        ("2d/sesync/CSAIL.g2o", 1045, 40.6),
    ] {
        let Some(path) = common::data_file(file) else {
            continue;
        };
        let mut graph = io::load(&path, None).expect("an edges-only file loads");
        assert_eq!(graph.problem.values.len(), poses, "{file}");
        assert_eq!(graph.vertex_order.len(), poses, "{file}");
        let s = solve(&mut graph);
        assert!(s.termination.converged(), "{file}: {:?}", s.termination);
        assert!(
            s.final_chi2 <= bound,
            "{file}: chi2 {} > {bound}",
            s.final_chi2
        );
        eprintln!(
            "{file}: chi2 {} in {} iterations",
            s.final_chi2, s.iterations
        );
    }
}

#[test]
fn an_edges_only_graph_is_placed_along_its_spanning_tree() {
    let text = common::synthetic_manhattan(300, 5);
    let with_vertices = io::parse_text(&text, Path::new("with"), None).unwrap();
    let mut without = io::parse_text(&edges_only(&text), Path::new("without"), None).unwrap();
    assert_eq!(
        without.problem.values.len(),
        with_vertices.problem.values.len()
    );
    // Pose 1 is pose 0 composed with the measurement of the edge between them.
    let edge = without
        .problem
        .factors()
        .iter()
        .find(|f| f.factor.keys() == [0, 1])
        .expect("an odometry edge 0-1");
    let predicted = edge
        .factor
        .predict(&[Some(without.problem.values.get(0).unwrap()), None], 1)
        .unwrap();
    let placed = without.problem.values.get(1).unwrap();
    let as_se2 = |v: &dyn factord::problem::Variable| {
        let p = v.as_any().downcast_ref::<Se2>().expect("an se2 pose");
        [p.x, p.y, p.theta]
    };
    assert_eq!(as_se2(predicted.as_ref()), as_se2(placed));
    // Both starts reach the same optimum.
    let mut with_vertices = with_vertices;
    let (x, y) = (solve(&mut with_vertices), solve(&mut without));
    let rel = (x.final_chi2 - y.final_chi2).abs() / x.final_chi2.max(1.0);
    assert!(rel < 1e-6, "{} vs {}", x.final_chi2, y.final_chi2);
}

#[test]
fn gtsam_covariance_layout_is_read_as_a_covariance() {
    // Six numbers `a 0 0 b 0 c`: GTSAM's covariance xx xy xθ yy yθ θθ (as TORO information
    // they would have yy = 0). Covariance diag(4, 9, 25): an error (1, 1, 1) costs
    // 1/4 + 1/9 + 1/25.
    let text = "VERTEX2 0 0 0 0\nVERTEX2 1 1 1 1\nEDGE2 0 1 0 0 0 4 0 0 9 0 25\n";
    let graph = io::parse_text(text, Path::new("cov"), None).unwrap();
    let chi2 = evaluate_chi2(graph.problem.factors(), &graph.problem.values).unwrap();
    let expected = 1.0 / 4.0 + 1.0 / 9.0 + 1.0 / 25.0;
    // The SE(2) error of (1, 1, 1) from the origin is (1, 1, 1) (t2v of the relative pose).
    assert!((chi2 - expected).abs() < 1e-12, "{chi2} vs {expected}");
    // TORO information as before: xx xy yy tt xt yt.
    let text = "VERTEX2 0 0 0 0\nVERTEX2 1 1 1 1\nEDGE2 0 1 0 0 0 2 0 3 5 0 0\n";
    let graph = io::parse_text(text, Path::new("toro"), None).unwrap();
    let chi2 = evaluate_chi2(graph.problem.factors(), &graph.problem.values).unwrap();
    assert!((chi2 - 10.0).abs() < 1e-12, "{chi2}");
}

#[test]
fn a_disconnected_edges_only_graph_is_refused_naming_a_vertex() {
    let text = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 5 6 1 0 0 1 0 0 1 0 1\n";
    let error = io::parse_text(text, Path::new("two parts"), None)
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("vertex 5") && error.contains("vertex 0"),
        "{error}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn batch_jobs_take_edges_only_graphs() {
    let s = TestServer::start(&[]);
    let c = client();
    let text = edges_only(&common::synthetic_manhattan(200, 2));
    let answer = c.post(s.url("/v1/jobs")).body(text).send().await.unwrap();
    assert_eq!(answer.status(), 200);
    let v: Value = answer.json().await.unwrap();
    assert_eq!(
        v["estimate"]["variables"].as_array().unwrap().len(),
        200,
        "{v}"
    );

    // GTSAM's landmark text, detected or named: poses and landmarks come back.
    let landmarks = "ODOMETRY 0 1 1 0 0.5 0.01 0 0 0.01 0 0.0001\n\
                     LANDMARK 0 3 2 0 0.1 0 0.1\n\
                     LANDMARK 1 3 0.5 -1.2 0.1 0 0.1\n";
    for query in ["", "?format=gtsam"] {
        let answer = c
            .post(s.url(&format!("/v1/jobs{query}")))
            .body(landmarks)
            .send()
            .await
            .unwrap();
        assert_eq!(answer.status(), 200, "{query}");
        let v: Value = answer.json().await.unwrap();
        let kinds: Vec<&str> = v["estimate"]["variables"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x["kind"].as_str().unwrap())
            .collect();
        assert_eq!(kinds, ["se2", "se2", "point2"], "{v}");
    }

    let split = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 5 6 1 0 0 1 0 0 1 0 1\n";
    let answer = c.post(s.url("/v1/jobs")).body(split).send().await.unwrap();
    assert_eq!(answer.status(), 400);
    let v: Value = answer.json().await.unwrap();
    assert_eq!(v["error"]["code"], "invalid_graph", "{v}");
    assert!(
        v["error"]["message"].as_str().unwrap().contains("vertex 5"),
        "{v}"
    );
    s.assert_no_panic();
}

/// Victoria Park (issue 18, item 1) in GTSAM's text format: 6969 poses from chained odometry,
/// 151 landmarks from their first sightings (bearing-range factors), solved with the defaults.
/// GTSAM's LM from the same start stops at 210660.29 (MANIFEST.md; 210240.35 with tolerances
/// 1e-6 / 1e-9 in `benches/edges_only`), its Gauss-Newton diverges; GTSAM scores our optimum at
/// 68385.6 and its Gauss-Newton started there stays (68384.95).
#[test]
fn victoria_park_reaches_a_lower_optimum_than_gtsam_lm() {
    let Some(path) = common::data_file("2d/gtsam/victoria_park.txt") else {
        return;
    };
    let mut graph = io::load(&path, None).expect("victoria_park loads");
    let values = &graph.problem.values;
    let landmarks = (0..values.len())
        .filter(|&v| values.variable(v).kind() == "point2")
        .count();
    assert_eq!((values.len() - landmarks, landmarks), (6969, 151));
    assert!(values.get(io::gtsam_text::landmark_key(5)).is_some());
    let s = solve(&mut graph);
    assert_relative(
        s.initial_chi2,
        1.13688015e8,
        1e-6,
        "start (GTSAM's: 113688014.85)",
    );
    assert!(s.termination.converged(), "{:?}", s.termination);
    assert!(s.final_chi2 <= 210660.29, "chi2 {}", s.final_chi2);
    assert_relative(s.final_chi2, 68384.31, 1e-5, "optimum");
    assert_eq!(
        s.used.gauge_fixed,
        vec![0],
        "the first pose, not a landmark"
    );
}

#[test]
fn gtsam_text_odometry_and_landmarks_are_read_as_gtsam_reads_them() {
    // Pose 1 one metre ahead, turned 90°; landmark 3 seen from pose 0 at (2, 0) and from pose 1
    // at (0, -1) (the same place); v1 = v3 = 0.1 gives σ_bearing = 0.1, σ_range = √0.1.
    let text = "ODOMETRY 0 1 1 0 1.5707963267948966 0.01 0 0 0.01 0 0.0001\n\
                LANDMARK 0 3 2 0 0.1 0 0.1\n\
                LANDMARK 1 3 0 -1 0.1 0 0.1\n";
    let graph = io::parse_text(text, Path::new("gtsam"), None).unwrap();
    let l = graph
        .problem
        .values
        .get(io::gtsam_text::landmark_key(3))
        .expect("landmark 3")
        .as_any()
        .downcast_ref::<factord::geometry::Point2>()
        .unwrap()
        .0;
    assert!(
        (l.x - 2.0).abs() < 1e-12 && l.y.abs() < 1e-12,
        "first sighting: {l}"
    );
    let chi2 = evaluate_chi2(graph.problem.factors(), &graph.problem.values).unwrap();
    assert!(chi2 < 1e-20, "consistent: {chi2}");
    let sighting = &graph.problem.factors()[1];
    let info = sighting.sqrt_information.information();
    assert!(
        (info[(0, 0)] - 100.0).abs() < 1e-9 && (info[(1, 1)] - 10.0).abs() < 1e-9,
        "{info}"
    );
    let bad = "LANDMARK 0 3 0 0 0.1 0 0.1\n";
    let e = io::parse_text(bad, Path::new("bad"), None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("bad:1") && e.contains("no bearing"), "{e}");
}

fn assert_relative(actual: f64, expected: f64, tolerance: f64, what: &str) {
    let rel = (actual - expected).abs() / expected.abs();
    assert!(
        rel <= tolerance,
        "{what}: {actual} vs {expected} (relative {rel:.2e})"
    );
}
