//! Marginal covariance of one pose (the last, by default) on a 2D g2o graph at its optimum:
//!
//! 1. in-process: linearise + factorise H (`Marginals::new`), then one covariance query from
//!    the held factor;
//! 2. over HTTP against the real server: the first request at an estimate (factorises) and a
//!    repeated one (reuses), client-measured;
//! 3. GTSAM 4.3's `Marginals` (constructor: linearise + eliminate) and `marginalCovariance`
//!    from Python, on the same estimate, in the same run.
//!
//! `cargo bench --bench marginals -- <file.g2o> [--rounds N] [--key K]`

#[path = "../../tests/common/mod.rs"]
mod common;

#[path = "../args.rs"]
mod args;
#[path = "../stats.rs"]
mod stats;

use std::process::Command;
use std::time::Instant;

use common::server::{client, g2o_batches, get, post, TestServer};
use factord::solver::marginals::Marginals;
use factord::solver::{self, SolverOptions};
use serde_json::{json, Value};

fn main() {
    let args = args::Args::from_env();
    let file = args.first("usage: marginals <file.g2o> [--rounds N] [--key K]");
    let rounds: usize = args.parsed("--rounds", 20);
    let text = std::fs::read_to_string(&file).unwrap();

    let mut graph = factord::io::load(file.as_ref(), None).unwrap();
    let summary = solver::optimize(&mut graph.problem, &SolverOptions::default(), &mut |_| {
        std::ops::ControlFlow::Continue(())
    })
    .unwrap();
    let values = &graph.problem.values;
    let key: u64 = args.parsed("--key", values.key(values.len() - 1));
    let (mut factorize, mut query) = (Vec::new(), Vec::new());
    let mut held = None;
    for _ in 0..rounds {
        let start = Instant::now();
        let m = Marginals::new(&graph.problem).unwrap();
        factorize.push(start.elapsed().as_secs_f64());
        held = Some(m);
    }
    let held = held.unwrap();
    for _ in 0..rounds {
        let start = Instant::now();
        let cov = held.covariance(&[key]).unwrap();
        query.push(start.elapsed().as_secs_f64());
        assert!(cov.joint[0] > 0.0);
    }

    // GTSAM on the same estimate.
    let dir = common::temp_dir("bench-marginals");
    let estimate = dir.join("estimate.g2o");
    factord::io::g2o::write(&graph, &estimate).unwrap();
    let gtsam = match common::python_venv("gtsam", &[vec!["gtsam".into()]]) {
        Ok(python) => {
            let out = Command::new(python)
                .arg(concat!(
                    env!("CARGO_MANIFEST_DIR"),
                    "/benches/marginals/gtsam_marginals.py"
                ))
                .arg(&file)
                .arg(&estimate)
                .args(["--keys", &key.to_string(), "--factor", "gtsam", "--repeat"])
                .arg(rounds.min(10).to_string())
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
            let v: Value = serde_json::from_slice(&out.stdout).unwrap();
            let mut build: Vec<f64> = serde_json::from_value(v["build_seconds"].clone()).unwrap();
            json!({"marginals_constructor_seconds": stats::median(&mut build),
                   "marginal_covariance_seconds": v["query_seconds"][key.to_string()]})
        }
        Err(reason) => json!({"skipped": reason}),
    };

    // Over HTTP: the session's first request at an estimate factorises, later ones reuse.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap();
    let http = runtime.block_on(async {
        let s = TestServer::start(&["--log", "warn", "--no-zenoh"]);
        let c = client();
        let create =
            json!({"session": "m", "kind": "pose_graph_2d", "auto_optimize": {"policy": "manual"}});
        assert_eq!(post(&c, &s.url("/v1/sessions"), &create).await.0, 201);
        let (mut variables, mut factors) = (Vec::new(), Vec::new());
        for b in g2o_batches(&text) {
            variables.extend(b["variables"].as_array().unwrap().iter().cloned());
            factors.extend(b["factors"].as_array().unwrap().iter().cloned());
        }
        let batch = json!({"variables": variables, "factors": factors});
        assert_eq!(
            post(&c, &s.url("/v1/sessions/m/batches"), &batch).await.0,
            200
        );
        assert_eq!(
            post(
                &c,
                &s.url("/v1/sessions/m/optimize?wait=true"),
                &json!(null)
            )
            .await
            .0,
            200
        );
        let url = s.url(&format!("/v1/sessions/m/marginals?keys={key}"));
        let (mut first, mut again, mut server_first) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..rounds {
            // Re-setting a guess to its own value changes the estimate's version, not its values.
            let (_, est) = get(
                &c,
                &s.url(&format!("/v1/sessions/m/estimate?from={key}&to={key}")),
            )
            .await;
            let guess = json!({"guesses": [{"key": key, "value": est["variables"][0]["value"]}]});
            assert_eq!(
                post(&c, &s.url("/v1/sessions/m/batches"), &guess).await.0,
                200
            );
            let start = Instant::now();
            let (status, v) = get(&c, &url).await;
            first.push(start.elapsed().as_secs_f64());
            assert_eq!(
                (status, &v["reused_factorization"]),
                (200, &json!(false)),
                "{v}"
            );
            server_first.push(v["seconds"].as_f64().unwrap());
            let start = Instant::now();
            let (_, v) = get(&c, &url).await;
            again.push(start.elapsed().as_secs_f64());
            assert_eq!(v["reused_factorization"], true);
        }
        s.assert_no_panic();
        json!({"first_request_seconds": stats::median(&mut first),
               "first_request_server_seconds": stats::median(&mut server_first),
               "repeated_request_seconds": stats::median(&mut again)})
    });
    let report = json!({
        "dataset": file, "key": key, "rounds": rounds,
        "variables": values.len(), "factors": graph.problem.factors().len(),
        "final_chi2": summary.final_chi2,
        "factord": {"linearize_and_factorize_seconds": stats::median(&mut factorize),
                    "covariance_query_seconds": stats::median(&mut query)},
        "factord_http": http,
        "gtsam": gtsam,
    });
    println!("{}", serde_json::to_string_pretty(&report).unwrap());
}
