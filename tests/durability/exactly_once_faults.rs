//! Exactly-once ingest under faults (issue 17's acceptance test), against the real binary:
//! two retrying producers stream one session, `zen` over zenoh puts and `web` over HTTP
//! through a proxy, while the server is killed with -9 ten times at random points and
//! restarted on the same state directory, the proxy loses ~10% of the HTTP acknowledgements
//! (the batch is applied, the answer never arrives) and the zenoh producer ignores ~10% of the
//! acknowledgements it receives. At the end every batch is applied exactly once: the factor
//! and variable counts are those sent, no acknowledgement says a batch was applied twice, and
//! the optimum equals the batch solver's on the same graph.
//!
//! The producers stream two disjoint graphs (the same kind of graph, different seeds, keys of
//! `web` shifted by [`OFFSET`]) into ONE session: both producers' tables, the session-wide
//! sequence and the snapshots are shared as in a real fleet, yet no batch of one producer needs
//! a variable of the other, so the interleaving of the two streams cannot matter.
//!
//! `FACTORD_FAULTS_SEED=<n>` replays a run (the seed is printed).

use crate::common;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::ack_proxy::AckDroppingProxy;
use common::producer::{run_http, run_zenoh, Counters, Producer, ZenohFaults};
use common::server::{
    client, create, free_port, g2o_batches, get, post, recovered, zenoh_session, TestServer,
};
use factord::factors::testing::Rng;
use serde_json::{json, Value};

/// Poses per producer.
const POSES: usize = 1500;
/// `web`'s keys are shifted by this.
const OFFSET: u64 = 100_000;
const KILLS: usize = 10;
const SESSION: &str = "faults";
/// Batches per second of each producer (a robot's rate; a producer behind catches up at once).
const RATE: f64 = 100.0;

/// The batches with every key shifted by `offset`.
fn shifted(batches: Vec<Value>, offset: u64) -> Vec<Value> {
    let shift = |v: &mut Value| *v = json!(v.as_u64().expect("a key") + offset);
    batches
        .into_iter()
        .map(|mut b| {
            for var in b["variables"].as_array_mut().unwrap() {
                shift(&mut var["key"]);
            }
            for f in b["factors"].as_array_mut().unwrap() {
                for k in f["keys"].as_array_mut().unwrap() {
                    shift(k);
                }
            }
            b
        })
        .collect()
}

/// The g2o text with every vertex id shifted by `offset`.
fn shifted_g2o(text: &str, offset: u64) -> String {
    let mut out = String::new();
    for line in text.lines() {
        let mut t: Vec<String> = line.split_whitespace().map(String::from).collect();
        let ids = match t.first().map(String::as_str) {
            Some("VERTEX_SE2") => 1..2,
            Some("EDGE_SE2") => 1..3,
            _ => 0..0,
        };
        for i in ids {
            t[i] = (t[i].parse::<u64>().unwrap() + offset).to_string();
        }
        out += &t.join(" ");
        out.push('\n');
    }
    out
}

fn factors(batches: &[Value]) -> usize {
    batches
        .iter()
        .map(|b| b["factors"].as_array().unwrap().len())
        .sum()
}

fn http_addr(s: &TestServer) -> SocketAddr {
    s.http
        .trim_start_matches("http://")
        .parse()
        .expect("a socket address")
}

#[tokio::test(flavor = "multi_thread")]
async fn every_batch_is_applied_exactly_once_through_kills_and_lost_acks() {
    let started = Instant::now();
    let seed = std::env::var("FACTORD_FAULTS_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_nanos() as u64
        });
    println!("seed {seed} (FACTORD_FAULTS_SEED={seed} replays it)");
    let mut rng = Rng::new(seed);

    let zen_text = common::synthetic_manhattan(POSES, 21);
    let web_text = common::synthetic_manhattan(POSES, 22);
    let zen_batches = g2o_batches(&zen_text);
    let web_batches = shifted(g2o_batches(&web_text), OFFSET);
    let total_factors = factors(&zen_batches) + factors(&web_batches);
    let total_batches = (zen_batches.len() + web_batches.len()) as u64;

    // The uninterrupted optimum: the batch solver on both graphs at once.
    let dir = common::temp_dir("exactly-once-faults");
    let reference = {
        let path = dir.join("both.g2o");
        std::fs::write(&path, zen_text.clone() + &shifted_g2o(&web_text, OFFSET)).unwrap();
        let mut g = factord::io::load(&path, None).unwrap();
        factord::solver::optimize(&mut g.problem, &Default::default(), &mut |_| {
            std::ops::ControlFlow::Continue(())
        })
        .unwrap()
        .final_chi2
    };

    let state = dir.join("state");
    std::fs::create_dir_all(&state).unwrap();
    let config = dir.join("factord.json");
    std::fs::write(
        &config,
        json!({"journal": {"snapshot_every": 200}}).to_string(),
    )
    .unwrap();
    let config = config.display().to_string();
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let extra = [
        "--config",
        config.as_str(),
        "--zenoh-connect",
        endpoint.as_str(),
    ];
    // The producers' zenoh peer listens; the server connects to it, again after every restart.
    let z = zenoh_session("peer", "listen", &endpoint).await;
    let proxy = AckDroppingProxy::start(rng.next_u64(), 0.1).await;
    let c = client();

    let mut server = TestServer::start_at(&state, &extra, &[]);
    create(
        &c,
        &server,
        &json!({"session": SESSION, "kind": "pose_graph_2d"}),
    )
    .await;
    proxy.set_upstream(Some(http_addr(&server)));

    let paced = |name: &str, batches| {
        let mut p = Producer::new(SESSION, name, batches);
        p.rate = RATE;
        Arc::new(p)
    };
    let (zen, web) = (paced("zen", zen_batches), paced("web", web_batches));
    let zen_task = tokio::spawn(run_zenoh(
        Arc::clone(&zen),
        z.clone(),
        "factord",
        ZenohFaults {
            ignore_acks: 0.1,
            seed: rng.next_u64(),
        },
    ));
    let web_task = tokio::spawn(run_http(Arc::clone(&web), proxy.url("")));
    let mut tasks = [Some(zen_task), Some(web_task)];
    // The slower producer's progress (a finished one's is complete): kills come while it streams.
    let progress = || {
        Counters::get(&zen.counters.accepted_through)
            .min(Counters::get(&web.counters.accepted_through))
    };

    // Kill points: after random amounts of acknowledged progress, plus a random delay (some
    // land while the restarted server is still recovering, before anything moved).
    let mut thresholds: Vec<u64> = (0..KILLS)
        .map(|_| (POSES as f64 * (0.03 + 0.9 * rng.uniform())) as u64)
        .collect();
    thresholds.sort_unstable();
    let mut kills = Vec::new();
    for threshold in thresholds {
        let deadline = Instant::now() + Duration::from_secs(30);
        while progress() < threshold {
            assert!(
                Instant::now() < deadline,
                "no progress to {threshold} (at {}): zen {}; web {}",
                progress(),
                zen.counters.summary(),
                web.counters.summary()
            );
            // A producer that finished had all its batches acknowledged: the kills go on at the
            // other's progress (with two kill points close to the end, the faster one can
            // finish while the server recovers from the first). One that failed ends the test.
            for (name, task) in ["zen", "web"].into_iter().zip(&mut tasks) {
                if task.as_ref().is_some_and(|t| t.is_finished()) {
                    let outcome = task.take().expect("checked").await;
                    if !matches!(outcome, Ok(Ok(()))) {
                        panic!(
                            "producer {name} stopped before the kills were over: {outcome:?}\n\
                             server log:\n{}",
                            server.stderr()
                        );
                    }
                }
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
        tokio::time::sleep(Duration::from_millis(rng.next_u64() % 150)).await;
        proxy.set_upstream(None);
        let at = progress();
        let log = server.kill();
        assert!(!log.contains("panicked"), "{log}");
        kills.push(at);
        server = TestServer::start_at(&state, &extra, &[]);
        proxy.set_upstream(Some(http_addr(&server)));
    }

    let finish = |task: Option<tokio::task::JoinHandle<Result<(), String>>>| async move {
        let Some(task) = task else {
            return Ok(()); // finished during the kills
        };
        match tokio::time::timeout(Duration::from_secs(40), task).await {
            Ok(Ok(outcome)) => outcome,
            Ok(Err(e)) => Err(format!("producer task failed: {e}")),
            Err(_) => Err("producer did not finish in 40 s".into()),
        }
    };
    let [zen_task, web_task] = tasks;
    let (zen_done, web_done) = (finish(zen_task).await, finish(web_task).await);
    let report = || {
        format!(
            "seed {seed}; kills at progress {kills:?}\nzen: {}\nweb: {}\nproxy: dropped {} relayed {} refused {}",
            zen.counters.summary(),
            web.counters.summary(),
            proxy.dropped(),
            proxy.relayed(),
            proxy.refused()
        )
    };
    if let Err(e) = zen_done.and(web_done) {
        panic!("{e}\n{}\nserver log:\n{}", report(), server.stderr());
    }

    // Every batch applied exactly once.
    let (stats, _) = recovered(&c, &server, SESSION, Instant::now()).await;
    assert_eq!(stats["num_factors"], total_factors, "{stats}\n{}", report());
    assert_eq!(stats["num_variables"], 2 * POSES, "{stats}\n{}", report());
    for p in [&zen, &web] {
        let (status, v) = get(
            &c,
            &server.url(&format!("/v1/sessions/{SESSION}/producers/{}", p.name)),
        )
        .await;
        assert_eq!(status, 200, "{v}");
        assert_eq!(v["accepted_through"], POSES, "{v}");
    }
    let mut ids: Vec<u64> = [&zen, &web]
        .iter()
        .flat_map(|p| p.audit.lock().unwrap().factor_ids())
        .collect();
    let seen = ids.len();
    ids.sort_unstable();
    ids.dedup();
    assert_eq!(ids.len(), seen, "a factor id acknowledged for two batches");
    assert!(seen <= total_factors);

    let (status, solved) = post(
        &c,
        &server.url(&format!("/v1/sessions/{SESSION}/optimize?wait=true")),
        &json!({}),
    )
    .await;
    assert_eq!(status, 200, "{solved}");
    let chi2 = solved["stats"]["chi2"].as_f64().unwrap();
    let relative = (chi2 - reference).abs() / reference;
    server.assert_no_panic();
    println!(
        "{KILLS} kills at progress {kills:?} (of {POSES} per producer); {total_batches} batches ({total_factors} factors)\n\
         zen (zenoh): {}\nweb (HTTP): {}\n\
         HTTP acks dropped by the proxy {} (relayed {}, connections refused while down {}); \
         zenoh acks ignored by the producer {}\n\
         acknowledgements audited: zen {} web {} batches\n\
         chi2 {chi2} vs uninterrupted {reference} (relative {relative:.2e}); total {:.1} s",
        zen.counters.summary(),
        web.counters.summary(),
        proxy.dropped(),
        proxy.relayed(),
        proxy.refused(),
        Counters::get(&zen.counters.acks_ignored),
        zen.audit.lock().unwrap().batches_acknowledged(),
        web.audit.lock().unwrap().batches_acknowledged(),
        started.elapsed().as_secs_f64()
    );
    // A recovery replays the journal without acknowledging its batches again: no
    // acknowledgement ever goes back.
    for p in [&zen, &web] {
        let audit = p.audit.lock().unwrap();
        assert!(
            audit.replayed.is_empty(),
            "{}: {} acknowledgements re-published with an older accepted_through, e.g. {}",
            p.name,
            audit.replayed.len(),
            audit.replayed[0]
        );
    }
    assert!(relative <= 1e-6, "chi2 {chi2} vs {reference}\n{}", report());
    // The faults happened: the test cannot pass by not testing.
    assert_eq!(kills.len(), KILLS);
    assert!(proxy.dropped() > 0 && Counters::get(&zen.counters.acks_ignored) > 0);
    assert!(
        Counters::get(&web.counters.duplicates) > 0,
        "no repeat was answered as a duplicate\n{}",
        report()
    );
    z.close().await.unwrap();
}
